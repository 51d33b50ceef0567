//! Inputs the fuzzers (`fuzz/`) found, fed again to the parser they broke through the fuzz
//! targets' own code (`fuzz/src/lib.rs`, a module here): each must now be refused (or read)
//! without a panic, in well under a second. Files are named `TARGET-what-N` after the fuzz
//! target.

use std::time::Instant;

#[path = "../../../fuzz/src/lib.rs"]
mod targets;

#[test]
fn found_inputs_no_longer_break_their_parsers() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_regressions");
    let mut checked = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        let data = std::fs::read(&path).unwrap();
        let target = name.split('-').next().unwrap();
        let t = Instant::now();
        assert!(targets::run(target, &data), "{name}: no fuzz target {target} (targets: {:?})", targets::TARGETS);
        assert!(t.elapsed().as_secs_f64() < 1.0, "{name} took {:?}", t.elapsed());
        checked += 1;
    }
    assert!(checked >= 3, "{checked} inputs in {}", dir.display());
}
