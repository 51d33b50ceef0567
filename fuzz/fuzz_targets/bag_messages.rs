#![no_main]
//! ROS message decoders of bags (`source::bag::msgs`): a tag byte picks the message type and
//! the serialisation, the rest is the message (`msgs::check_tagged`).

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    mrfmap_fuzz::run("bag_messages", data);
});
