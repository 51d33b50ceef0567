#![no_main]
//! 16-bit depth PNGs (`source::decode_depth_png`).

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    mrfmap_fuzz::run("depth_png", data);
});
