//! The superblock and header of a database file a server may be handed. Each
//! input is tried as is and with its CRC repaired, so the field checks and the
//! root decoding behind the checksum are reached.
#![no_main]
use libfuzzer_sys::fuzz_target;
use planet_core::format::{Header, Superblock, SUPERBLOCK_LEN};

fuzz_target!(|data: &[u8]| {
    let _ = Superblock::decode(data);
    let _ = Header::decode(data, None);
    let _ = Header::decode(data, Some(1 << 20));
    if data.len() >= 8 {
        let mut fixed = data.to_vec();
        let n = fixed.len();
        let crc = crc32fast::hash(&fixed[..n - 4]);
        fixed[n - 4..].copy_from_slice(&crc.to_le_bytes());
        let _ = Header::decode(&fixed, Some(1 << 20));
        if n >= SUPERBLOCK_LEN {
            let crc = crc32fast::hash(&fixed[..60]);
            fixed[60..64].copy_from_slice(&crc.to_le_bytes());
            let _ = Superblock::decode(&fixed);
        }
    }
});
