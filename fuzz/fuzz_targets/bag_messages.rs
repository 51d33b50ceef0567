#![no_main]
//! ROS message decoders of bags (`source::bag::msgs`): the first byte picks the message type
//! and the serialisation, the rest is the message.
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    use mrfmap::source::bag::msgs;
    let Some((&kind, cdr)) = data.split_first() else { return };
    // Bit 4 picks ROS 1's serialisation instead of CDR.
    let enc = if kind & 16 != 0 { mrfmap::source::bag::Encoding::Ros1 } else { mrfmap::source::bag::Encoding::Cdr };
    match kind % 7 {
        0 => drop(msgs::depth_image(cdr, enc)),
        1 => drop(msgs::compressed_depth(cdr, enc)),
        2 => drop(msgs::camera_info(cdr, enc)),
        3 => drop(msgs::tf_message(cdr, enc)),
        4 => drop(msgs::laser_scan(cdr, enc)),
        5 => drop(msgs::point_cloud(cdr, enc)),
        _ => drop(msgs::pose(cdr, enc, kind & 8 != 0)),
    }
});
