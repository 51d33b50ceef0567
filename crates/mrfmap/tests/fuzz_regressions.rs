//! Inputs the fuzzers (`fuzz/`) found, fed again to the parser they broke: each must now be
//! refused (or read) without a panic, in well under a second. Files are named
//! `TARGET-what-N` after the fuzz target.

use std::time::Instant;

#[cfg(feature = "bags")]
fn bag_messages(data: &[u8]) {
    use mrfmap::source::bag::{Encoding, msgs};
    let Some((&kind, cdr)) = data.split_first() else { return };
    let enc = if kind & 16 != 0 { Encoding::Ros1 } else { Encoding::Cdr };
    match kind % 7 {
        0 => drop(msgs::depth_image(cdr, enc)),
        1 => drop(msgs::compressed_depth(cdr, enc)),
        2 => drop(msgs::camera_info(cdr, enc)),
        3 => drop(msgs::tf_message(cdr, enc)),
        4 => drop(msgs::laser_scan(cdr, enc)),
        5 => drop(msgs::point_cloud(cdr, enc)),
        _ => drop(msgs::pose(cdr, enc, kind & 8 != 0)),
    }
}

#[test]
fn found_inputs_no_longer_break_their_parsers() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_regressions");
    let mut checked = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        let data = std::fs::read(&path).unwrap();
        let t = Instant::now();
        match name.split('-').next().unwrap() {
            #[cfg(feature = "bags")]
            "bag_messages" => bag_messages(&data),
            "ply" => drop(mrfmap::outputs::parse_ply(&data)),
            "map_file" => drop(mrfmap::map::Map::from_bytes(&data)),
            _ => continue,
        }
        assert!(t.elapsed().as_secs_f64() < 1.0, "{name} took {:?}", t.elapsed());
        checked += 1;
    }
    assert!(checked > 0 || cfg!(not(feature = "bags")));
}
