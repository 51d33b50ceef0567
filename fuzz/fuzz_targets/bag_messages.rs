#![no_main]
//! ROS 2 message decoders of bags (`source::bag::msgs`): the first byte picks the message type,
//! the rest is the CDR message.
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    use mrfmap::source::bag::msgs;
    let Some((&kind, cdr)) = data.split_first() else { return };
    match kind % 7 {
        0 => drop(msgs::depth_image(cdr)),
        1 => drop(msgs::compressed_depth(cdr)),
        2 => drop(msgs::camera_info(cdr)),
        3 => drop(msgs::tf_message(cdr)),
        4 => drop(msgs::laser_scan(cdr)),
        5 => drop(msgs::point_cloud(cdr)),
        _ => drop(msgs::pose(cdr, kind & 8 != 0)),
    }
});
