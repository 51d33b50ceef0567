#![no_main]
//! CARMEN laser logs (`source::parse_carmen`), and every reading turned into a scan.
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    use mrfmap::source::{CarmenOptions, Misses, parse_carmen};
    if let Ok(readings) = parse_carmen(data, CarmenOptions::default()) {
        for (i, r) in readings.iter().enumerate() {
            let _ = r.to_scan(i, 0.025, 1, Misses::Free, None);
        }
    }
});
