#![no_main]
//! `noise.toml` (`frames::NoiseModel::from_toml`), and the model's use at a few depths.

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    mrfmap_fuzz::run("noise_toml", data);
});
