//! What each fuzz target feeds its parser, in one place: the libFuzzer binaries in
//! `fuzz_targets/` call [`run`] with their name, and the library's test
//! `fuzz_regressions` includes this file to replay the inputs the fuzzers found
//! (`crates/mrfmap/tests/fuzz_regressions/TARGET-what-N`) through the same code.

/// Every target [`run`] knows.
pub const TARGETS: [&str; 9] =
    ["depth_png", "camera_toml", "noise_toml", "scene_toml", "map_file", "ply", "octomap", "carmen", "bag_messages"];

/// Feeds `data` to the parser of `target` (and what reads its result further); errors are
/// the parser's answer, a panic is a finding. False for an unknown target.
pub fn run(target: &str, data: &[u8]) -> bool {
    let text = std::str::from_utf8(data).ok();
    match target {
        "depth_png" => drop(mrfmap::source::decode_depth_png(std::io::Cursor::new(data), 1000.0, None)),
        "camera_toml" => drop(text.map(|t| mrfmap::frames::Camera::from_toml(t, "camera.toml".as_ref()))),
        "noise_toml" => {
            if let Some(Ok(model)) = text.map(|t| mrfmap::frames::NoiseModel::from_toml(t, "noise.toml".as_ref())) {
                for z in [0.1, 1.0, 5.0] {
                    let _ = model.bias_std(0, 0, z);
                }
            }
        }
        "scene_toml" => drop(text.map(|t| mrfmap::source::Scene::from_toml(t, "scene.toml".as_ref()))),
        "tile_index" => drop(text.map(|t| mrfmap::map::TileIndex::from_toml(t, "tiles.toml".as_ref()))),
        "map_file" => {
            let _ = mrfmap::map::Map::from_bytes(data);
            // The same bytes with a checksum that matches, so the fuzzer gets past it.
            if data.len() > 4 {
                let body = &data[..data.len() - 4];
                let mut fixed = body.to_vec();
                fixed.extend_from_slice(&crc32(body).to_le_bytes());
                let _ = mrfmap::map::Map::from_bytes(&fixed);
            }
        }
        "ply" => drop(mrfmap::outputs::parse_ply(data)),
        "octomap" => drop(mrfmap::outputs::decode_octomap(data)),
        "carmen" => {
            use mrfmap::source::{CarmenOptions, Misses, parse_carmen};
            if let Ok(readings) = parse_carmen(data, CarmenOptions::default()) {
                for (i, r) in readings.iter().enumerate() {
                    let _ = r.to_scan(i, 0.025, 1, Misses::Free, None);
                }
            }
        }
        #[cfg(feature = "bags")]
        "bag_messages" => drop(mrfmap::source::bag::msgs::check_tagged(data)),
        #[cfg(not(feature = "bags"))]
        "bag_messages" => {}
        _ => return false,
    }
    true
}

/// The CRC-32 (IEEE) that map files end with.
fn crc32(data: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in data {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}
