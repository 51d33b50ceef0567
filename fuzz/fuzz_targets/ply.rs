#![no_main]
//! PLY files (`outputs::parse_ply`).

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    mrfmap_fuzz::run("ply", data);
});
