#![no_main]
//! Tiled maps' index files (`map::TileIndex::from_toml`).

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    mrfmap_fuzz::run("tile_index", data);
});
