//! A record as a client receives it from the network, or as a server reads it
//! from a hostile file: parse, check and decode every payload kind. Each input
//! is tried as is and with its length field and CRC repaired, so the fuzzer
//! reaches the field checks and codecs behind the checksum.
#![no_main]
use libfuzzer_sys::fuzz_target;
use planet_core::{codec, format};

fn exercise(data: &[u8]) {
    let _ = format::peek_record_len(data);
    if let Ok(rec) = format::parse_record(data, Some(1 << 40)) {
        if let Ok(raw) = rec.raw_payload() {
            let w = 64;
            let mut grid = vec![0i16; (w + 1) * (w + 1)];
            let _ = codec::decode_elevation(&raw, w, &mut grid);
            let lod1 = vec![[0u8; 3]; 64 * 64];
            let _ = codec::decode_colour(&raw, &lod1, 128);
        }
    }
}

fuzz_target!(|data: &[u8]| {
    exercise(data);
    if data.len() >= format::MIN_RECORD_LEN {
        let mut fixed = data.to_vec();
        let n = fixed.len();
        fixed[4..8].copy_from_slice(&(n as u32).to_le_bytes());
        let crc = crc32fast::hash(&fixed[..n - 4]);
        fixed[n - 4..].copy_from_slice(&crc.to_le_bytes());
        exercise(&fixed);
    }
    let _ = codec::decompress(data, 4096);
});
