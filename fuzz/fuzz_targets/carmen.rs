#![no_main]
//! CARMEN laser logs (`source::parse_carmen`), and every reading turned into a scan.

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    mrfmap_fuzz::run("carmen", data);
});
