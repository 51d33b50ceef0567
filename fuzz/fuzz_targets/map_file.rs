#![no_main]
//! Map files (`map::Map::from_bytes`). Each input is tried as given and with its last four
//! bytes replaced by the CRC-32 of the rest, so the fuzzer reaches the decoder behind the
//! checksum instead of failing it every time.

fn crc32(data: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in data {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let _ = mrfmap::map::Map::from_bytes(data);
    if data.len() > 4 {
        let body = &data[..data.len() - 4];
        let mut fixed = body.to_vec();
        fixed.extend_from_slice(&crc32(body).to_le_bytes());
        let _ = mrfmap::map::Map::from_bytes(&fixed);
    }
});
