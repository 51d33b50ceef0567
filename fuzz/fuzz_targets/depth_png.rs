#![no_main]
//! 16-bit depth PNGs (`source::decode_depth_png`).
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = mrfmap::source::decode_depth_png(std::io::Cursor::new(data), 1000.0, None);
});
