#![no_main]
//! Scene files (`source::Scene::from_toml`).

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    mrfmap_fuzz::run("scene_toml", data);
});
