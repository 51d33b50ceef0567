//! Inputs the fuzzers (`fuzz/`) found, fed again to the parser they broke: each must now be
//! refused (or read) without a panic, in well under a second. Files are named
//! `TARGET-what-N` after the fuzz target.

use std::time::Instant;

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
            "bag_messages" => drop(mrfmap::source::bag::msgs::check_tagged(&data)),
            "ply" => drop(mrfmap::outputs::parse_ply(&data)),
            "map_file" => drop(mrfmap::map::Map::from_bytes(&data)),
            _ => continue,
        }
        assert!(t.elapsed().as_secs_f64() < 1.0, "{name} took {:?}", t.elapsed());
        checked += 1;
    }
    assert!(checked > 0 || cfg!(not(feature = "bags")));
}
