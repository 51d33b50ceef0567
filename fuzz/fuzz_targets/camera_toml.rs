#![no_main]
//! `camera.toml` (`frames::Camera::from_toml`).

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    mrfmap_fuzz::run("camera_toml", data);
});
