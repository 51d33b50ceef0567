#![no_main]
//! OctoMap `.bt` / `.ot` files (`outputs::decode_octomap`).

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    mrfmap_fuzz::run("octomap", data);
});
