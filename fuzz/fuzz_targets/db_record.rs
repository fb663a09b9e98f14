//! A record as a client receives it from the network, or as a server reads it
//! from a hostile file: parse, check and decode every payload kind. Each input
//! is tried as is and with its length field and CRC repaired, so the fuzzer
//! reaches the field checks and codecs behind the checksum.
#![no_main]
use libfuzzer_sys::fuzz_target;
use planet_core::codec::{colour::HaarParams, ColourCodec, ElevationCodec};
use planet_core::{codec, format};

fn exercise(data: &[u8]) {
    let _ = format::peek_record_len(data);
    if let Ok(rec) = format::parse_record(data, Some(1 << 40)) {
        let w = 64;
        for c in [
            ElevationCodec::Legacy,
            ElevationCodec::Quantised { max_error: 0 },
            ElevationCodec::Quantised { max_error: 3 },
            ElevationCodec::Laplace { max_error: 0 },
            ElevationCodec::Laplace { max_error: 3 },
        ] {
            let mut grid = vec![0i16; (w + 1) * (w + 1)];
            let _ = rec.decode_elevation(&c, w, &mut grid);
        }
        let lod1 = vec![[0u8; 3]; 64 * 64];
        for c in [
            ColourCodec::Legacy,
            ColourCodec::Lossless,
            ColourCodec::Haar(HaarParams::for_psnr(42.0)),
        ] {
            let _ = rec.decode_colour(&c, &lod1, 128);
        }
    }
    // The sample codecs' raw stage directly, behind no entropy layer.
    let mut grid = vec![0i16; 17 * 17];
    let _ = codec::elevation::decode(data, 16, 2, &mut grid);
    let _ = codec::elevation2::decode(data, 16, 2, &mut grid);
    let _ = codec::elevation2::decode(data, 16, 0, &mut grid);
    let _ = codec::colour::decode(data, &[[7u8; 3]; 64], 16, &HaarParams::for_psnr(42.0));
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
