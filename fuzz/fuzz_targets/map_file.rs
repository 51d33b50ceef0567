#![no_main]
//! Map files (`map::Map::from_bytes`). Each input is tried as given and with its last four
//! bytes replaced by the CRC-32 of the rest, so the fuzzer reaches the decoder behind the
//! checksum instead of failing it every time.

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    mrfmap_fuzz::run("map_file", data);
});
