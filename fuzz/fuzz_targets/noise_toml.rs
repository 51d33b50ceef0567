#![no_main]
//! `noise.toml` (`frames::NoiseModel::from_toml`), and the model's use at a few depths.
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data)
        && let Ok(model) = mrfmap::frames::NoiseModel::from_toml(text, "noise.toml".as_ref())
    {
        for z in [0.1, 1.0, 5.0] {
            let _ = model.bias_std(0, 0, z);
        }
    }
});
