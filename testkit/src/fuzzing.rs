//! The fuzz targets' bodies, one plain function each (feature `fuzzing`):
//! `fuzz/fuzz_targets/TARGET.rs` calls `TARGET(data)` under libFuzzer, and
//! `server/tests/fuzz_regressions.rs` replays every file of
//! `fuzz/regressions/TARGET/` and `fuzz/corpus/TARGET/` through the same
//! function without cargo-fuzz. Each returns normally on any input; a panic
//! is a bug.

use std::path::Path;

use planet_core::codec::{colour::HaarParams, ColourCodec, ElevationCodec};
use planet_core::format::{Header, Superblock, SUPERBLOCK_LEN};
use planet_core::{codec, format};
use planet_preprocess::crs::{Crs, GeoKeys};
use planet_protocol::{
    decode_any_request_stream, decode_prioritized_request_stream, decode_request_stream,
    ErrorFloors, FrameDecoder, LodRequest, RequestKind, ResponseDecoder,
};

/// The CRC-32 (IEEE) of the database format, used to repair inputs so the
/// checks behind the checksum are reached.
pub fn repair_crc(bytes: &[u8]) -> u32 {
    crc32fast::hash(bytes)
}

/// `protocol_frames`: protocol frames from an untrusted peer: the frame
/// decoder fed in arbitrary fragments (split at a data-dependent point), the
/// request-stream decoders (`LodRequest` only, and either kind) and the
/// response decoders (plain, and with the trailer of a `LodRefsRequest`).
pub fn protocol_frames(data: &[u8]) {
    let cut = data.first().map_or(0, |b| *b as usize % (data.len() + 1));
    let mut dec = FrameDecoder::new();
    dec.push(&data[..cut]);
    while let Ok(Some(_)) = dec.next_frame() {}
    dec.push(&data[cut..]);
    while let Ok(Some(_)) = dec.next_frame() {}
    let _ = dec.finish();
    let _ = decode_request_stream(data);
    let _ = decode_any_request_stream(data);
    let _ = decode_prioritized_request_stream(data);
    let req = LodRequest {
        id: 7,
        offset: 64,
        size: 100,
    };
    let above = ErrorFloors::new([0.0, 1.5, f32::INFINITY, 0.0])
        .map_or(RequestKind::RecordAndRefs, RequestKind::RecordAndRefsAbove);
    for mut resp in [
        ResponseDecoder::new(req),
        ResponseDecoder::with_refs(req),
        ResponseDecoder::for_kind(req, above),
    ] {
        let _ = resp.push(&data[..cut]);
        let _ = resp.push(&data[cut..]);
        let _ = resp.finish();
    }
}

/// Parse, check and decode `data` as a record of every payload kind.
fn db_record_exercise(data: &[u8]) {
    let _ = format::peek_record_len(data);
    // The child references alone, as a server reads them for a
    // `LodRefsRequest`, and the data as such a response's trailer.
    let _ = format::record_child_refs(data, None);
    let _ = format::record_child_refs(data, Some(1 << 40));
    for n in 0..=4 {
        let _ = format::parse_child_tables(data, n, None);
        let _ = format::parse_child_tables(data, n, Some(1 << 40));
    }
    if let Ok(rec) = format::parse_record(data, Some(1 << 40)) {
        let w = 64;
        for c in [
            ElevationCodec::Legacy,
            ElevationCodec::Quantised { max_error: 0 },
            ElevationCodec::Quantised { max_error: 3 },
            ElevationCodec::Laplace { max_error: 0 },
            ElevationCodec::Laplace { max_error: 3 },
            ElevationCodec::InLoop { max_error: 3 },
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
    let _ = codec::elevation2::decode_in_loop(data, 16, 2, &mut grid);
    let _ = codec::colour::decode(data, &[[7u8; 3]; 64], 16, &HaarParams::for_psnr(42.0));
}

/// `db_record`: a record as a client receives it from the network, or as a
/// server reads it from a hostile file: parse, check and decode every
/// payload kind, as is and with its length field and CRC repaired (so the
/// field checks and codecs behind the checksum are reached); also the child
/// references alone (`record_child_refs`, what a server reads for a
/// `LodRefsRequest`) and the bytes as such a response's child tables
/// (`parse_child_tables` for 0 to 4 children).
pub fn db_record(data: &[u8]) {
    db_record_exercise(data);
    if data.len() >= format::MIN_RECORD_LEN {
        let mut fixed = data.to_vec();
        let n = fixed.len();
        fixed[4..8].copy_from_slice(&(n as u32).to_le_bytes());
        let crc = repair_crc(&fixed[..n - 4]);
        fixed[n - 4..].copy_from_slice(&crc.to_le_bytes());
        db_record_exercise(&fixed);
    }
    let _ = codec::decompress(data, 4096);
}

/// `db_header`: the superblock and header of a database file a server may
/// be handed, as is and with its CRC repaired.
pub fn db_header(data: &[u8]) {
    let _ = Superblock::decode(data);
    let _ = Header::decode(data, None);
    let _ = Header::decode(data, Some(1 << 20));
    if data.len() >= 8 {
        let mut fixed = data.to_vec();
        let n = fixed.len();
        let crc = repair_crc(&fixed[..n - 4]);
        fixed[n - 4..].copy_from_slice(&crc.to_le_bytes());
        let _ = Header::decode(&fixed, Some(1 << 20));
        if n >= SUPERBLOCK_LEN {
            let crc = repair_crc(&fixed[..60]);
            fixed[60..64].copy_from_slice(&crc.to_le_bytes());
            let _ = Superblock::decode(&fixed);
        }
    }
}

/// `control_session` (stateful): the server's control-stream state machine
/// (`ServerSession`, sans IO) driven by a sequence of operations taken from
/// the input: chunks of bytes in arbitrary fragments, the end of the stream,
/// request checks, with an authorizer that accepts or refuses. After every
/// step it checks that a closed session stays silent, a fatal event closes
/// it and carries a decodable `Error` frame, the Welcome comes at most once
/// and only from an accepting authorizer, requests pass only once
/// established, and cancels, peer errors and goodbyes come only after the
/// Welcome.
pub fn control_session(data: &[u8]) {
    use planet_protocol::{
        ErrorCode, ErrorMsg, Hello, Limits, Message, ServerEvent, ServerSession, Welcome,
    };
    // The first byte picks the authorizer's answer; then operations: a chunk
    // of `op / 4` bytes fed to the session (op % 4 == 0 or 1), the end of the
    // control stream (2), or a request check (3).
    let Some((&mode, mut rest)) = data.split_first() else {
        return;
    };
    let accept = mode & 1 == 0;
    let auth = move |h: &Hello| -> Result<Welcome, ErrorMsg> {
        if accept {
            Ok(Welcome {
                version: 0,
                database: h.database.clone(),
                file_size: 1 << 20,
                header: vec![],
                limits: Limits::default(),
            })
        } else {
            Err(ErrorMsg::new(ErrorCode::Unauthorized, "no"))
        }
    };
    let mut s = ServerSession::new();
    let mut welcomed = 0u32;
    while let Some((&op, r)) = rest.split_first() {
        rest = r;
        let was_closed = s.is_closed();
        let events = match op % 4 {
            0 | 1 => {
                let n = (op as usize / 4).min(rest.len());
                let (chunk, r) = rest.split_at(n);
                rest = r;
                s.receive(chunk, &auth)
            }
            2 => s.finish().into_iter().collect(),
            _ => {
                let req = LodRequest {
                    id: 1,
                    offset: 64,
                    size: 8,
                };
                match s.check_request(&req) {
                    Ok(()) => assert!(s.is_established()),
                    Err(e) => {
                        assert!(!s.is_established());
                        assert_eq!(e.code, ErrorCode::HelloRequired);
                    }
                }
                vec![]
            }
        };
        // A closed session says nothing more.
        assert!(!was_closed || events.is_empty());
        for ev in &events {
            match ev {
                ServerEvent::Welcomed { reply, .. } => {
                    welcomed += 1;
                    assert!(accept, "welcomed by a refusing authorizer");
                    assert!(!reply.is_empty());
                }
                ServerEvent::Fatal { error, reply } => {
                    let mut d = FrameDecoder::new();
                    d.push(reply);
                    match d.next_frame() {
                        Ok(Some(Message::Error(e))) => assert_eq!(e.code, error.code),
                        other => panic!("fatal reply is not an Error frame: {other:?}"),
                    }
                }
                // Only an established session cancels, hears errors or
                // goodbyes.
                ServerEvent::Cancel { .. }
                | ServerEvent::PeerError(_)
                | ServerEvent::Goodbye { .. } => {
                    assert_eq!(welcomed, 1)
                }
            }
        }
        if matches!(events.last(), Some(ServerEvent::Fatal { .. })) {
            assert!(s.is_closed(), "a fatal event leaves the session open");
        }
        assert!(welcomed <= 1, "welcomed twice");
        assert!(!s.is_established() || welcomed == 1);
    }
}

/// `server_config`: the server's TOML configuration: parsing and validation
/// (`ServerConfig::from_toml_str`) return `Ok` or a `ConfigError`, never
/// panic, whatever the text; a config that parsed is valid, and its Debug
/// output never shows a token. Relative paths resolve under a directory
/// that does not exist, so only absolute paths can name real files.
pub fn server_config(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let base = Path::new("/nonexistent/planet-fuzz");
    match planet_server::ServerConfig::from_toml_str(text, base) {
        Ok(cfg) => {
            cfg.validate()
                .expect("from_toml_str returned an invalid config");
            let _ = cfg.max_tenant_in_flight();
            let dbg = format!("{cfg:?}");
            // Tokens are kept as hashes: find each tenant's secret among
            // the quoted strings of the input, and check Debug never shows it.
            let quoted: Vec<&str> = text.split('"').skip(1).step_by(2).collect();
            for t in &cfg.tenants {
                assert!(dbg.contains("<redacted>"));
                for secret in quoted.iter().filter(|q| t.token.matches(q)) {
                    let unique = secret.len() >= 24
                        && !cfg.tenants.iter().any(|o| o.name.contains(secret))
                        && !cfg.databases.iter().any(|d| {
                            d.name.contains(secret) || d.path.to_string_lossy().contains(secret)
                        });
                    assert!(!unique || !dbg.contains(secret), "token in Debug output");
                }
            }
        }
        Err(e) => {
            let _ = e.to_string();
        }
    }
}

/// `db_open_request`: a database file a server is handed, opened and
/// validated as `planet-server` opens it (by `pread` or from a map),
/// together with requests a client sends for it, checked as the server
/// checks them ([`MappedDb::check_request`]).
///
/// Input: a flags byte (bit 0: map the file; bit 1: repair the
/// superblock's file length and the superblock's and header's checksums, so
/// the checks behind them are reached), a request count `k` (mod 32), `k`
/// requests of 12 bytes (offset u64 LE, size u32 LE), then the file. An
/// accepted request must lie in the record area and read back as a whole
/// record of its size; a refusal must be one of the three request errors;
/// nothing may fail to read from a file that did not change. Writes the
/// file to the temporary directory under a name of the process. Returns the
/// number of accepted requests (the replay test checks that the seeds reach
/// acceptance).
pub fn db_open_request(data: &[u8]) -> usize {
    use planet_protocol::ErrorCode;
    use planet_server::config::StorageMode;
    use planet_server::db::{MappedDb, RequestCheck};

    let [flags, k, rest @ ..] = data else {
        return 0;
    };
    let k = usize::from(*k % 32);
    if rest.len() < 12 * k {
        return 0;
    }
    let (reqs, file) = rest.split_at(12 * k);
    let mut file = file.to_vec();
    if flags & 2 != 0 {
        repair_db_file(&mut file);
    }
    let path = std::env::temp_dir().join(format!("planet-fuzz-db-{}.planetdb", std::process::id()));
    if std::fs::write(&path, &file).is_err() {
        return 0;
    }
    let mode = if flags & 1 != 0 {
        StorageMode::Mmap
    } else {
        StorageMode::Pread
    };
    let mut accepted = 0;
    if let Ok(db) = MappedDb::open_with("fuzz", &path, mode) {
        let db = std::sync::Arc::new(db);
        assert!(db.records_end() >= SUPERBLOCK_LEN as u64 && db.records_end() <= db.len());
        for r in reqs.chunks_exact(12) {
            let (o, z) = r.split_at(8);
            let offset = u64::from_le_bytes(o.try_into().expect("8 bytes"));
            let size = u32::from_le_bytes(z.try_into().expect("4 bytes"));
            match db.check_request(offset, size) {
                Ok(()) => {
                    let end = offset + u64::from(size);
                    assert!(offset >= SUPERBLOCK_LEN as u64 && end <= db.records_end());
                    let bytes = db
                        .read(offset, size as usize)
                        .expect("an accepted record reads back");
                    assert_eq!(format::peek_record_len(&bytes).ok(), Some(size));
                    accepted += 1;
                }
                Err(RequestCheck::Refused(e)) => assert!(
                    matches!(
                        e.code,
                        ErrorCode::OutOfRange | ErrorCode::NotARecord | ErrorCode::WrongSize
                    ),
                    "{e:?}"
                ),
                Err(RequestCheck::Storage(e)) => panic!("storage error on an unchanged file: {e}"),
            }
        }
    }
    let _ = std::fs::remove_file(&path);
    accepted
}

/// Sets a database file's stored length to its length and repairs the
/// header's and the superblock's checksums (docs/FORMAT.md).
fn repair_db_file(file: &mut [u8]) {
    if file.len() < SUPERBLOCK_LEN {
        return;
    }
    let len = file.len() as u64;
    file[32..40].copy_from_slice(&len.to_le_bytes());
    let field = |a: usize, b: usize| {
        file[a..b]
            .iter()
            .rev()
            .fold(0u64, |v, x| v << 8 | u64::from(*x))
    };
    let (ho, hl) = (field(16, 24), field(24, 28));
    if hl >= 4 && ho.checked_add(hl).is_some_and(|e| e <= len) {
        let (ho, hl) = (ho as usize, hl as usize);
        let crc = repair_crc(&file[ho..ho + hl - 4]);
        file[ho + hl - 4..ho + hl].copy_from_slice(&crc.to_le_bytes());
    }
    let crc = repair_crc(&file[..60]);
    file[60..64].copy_from_slice(&crc.to_le_bytes());
}

/// A seed input of [`db_open_request`]: a small valid database (per face a
/// root with four children, payloads of tens of bytes) and requests for
/// each of its records, for a record with a wrong size, inside a record,
/// and outside the record area.
pub fn db_open_request_seed(flags: u8) -> Vec<u8> {
    let path =
        std::env::temp_dir().join(format!("planet-fuzz-seed-{}.planetdb", std::process::id()));
    let recs = crate::testdb::write_two_level_db(&path, 4, "fuzz seed", |f, k| match k {
        Some(k) => (0..20 + k).map(|i| (i * 7 + f) as u8).collect(),
        None => vec![f as u8; 30],
    })
    .expect("write the seed database");
    let file = std::fs::read(&path).expect("read the seed database");
    let _ = std::fs::remove_file(&path);
    let (o0, s0) = recs[0];
    let mut reqs: Vec<(u64, u32)> = recs.iter().copied().take(26).collect();
    reqs.extend([
        (o0, s0 + 1),
        (o0 + 4, s0),
        (0, 64),
        (file.len() as u64 - 8, 8),
    ]);
    let mut out = vec![flags, reqs.len() as u8];
    for (o, z) in reqs {
        out.extend_from_slice(&o.to_le_bytes());
        out.extend_from_slice(&z.to_le_bytes());
    }
    out.extend_from_slice(&file);
    out
}

/// `raster_readers`: the raster readers of planet-build (GeoTIFF with its
/// GeoKeys and CRS) on untrusted bytes: no panic, and allocation bounded by
/// the tiff decoder's limits and the 1 MiB chunk cache whatever the header
/// claims (`planet_preprocess::geotiff::probe`). Writes `data` to a file of
/// the temporary directory named after the process.
pub fn raster_readers(data: &[u8]) {
    let path = std::env::temp_dir().join(format!("planet-fuzz-raster-{}.tif", std::process::id()));
    if std::fs::write(&path, data).is_ok() {
        let _ = planet_preprocess::geotiff::probe(&path);
    }
    // The GeoKey directory alone: u16 keys then f64 parameters.
    let (keys, rest) = data.split_at(data.len() / 2);
    let dir: Vec<u16> = keys
        .chunks_exact(2)
        .map(|b| u16::from_le_bytes([b[0], b[1]]))
        .collect();
    let doubles: Vec<f64> = rest
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
        .collect();
    let _ = Crs::from_geokeys(&GeoKeys::parse(&dir, &doubles));
}
