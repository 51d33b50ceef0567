#![no_main]
//! Scene files (`source::Scene::from_toml`).
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = mrfmap::source::Scene::from_toml(text, "scene.toml".as_ref());
    }
});
