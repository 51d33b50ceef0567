#![no_main]
//! `camera.toml` (`frames::Camera::from_toml`).
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = mrfmap::frames::Camera::from_toml(text, "camera.toml".as_ref());
    }
});
