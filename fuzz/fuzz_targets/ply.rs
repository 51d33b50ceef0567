#![no_main]
//! PLY files (`outputs::parse_ply`).
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = mrfmap::outputs::parse_ply(data);
});
