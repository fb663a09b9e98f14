//! Replays the fuzz corpora and regressions without cargo-fuzz: every file in
//! `fuzz/regressions/TARGET/` and `fuzz/corpus/TARGET/` goes through the same
//! logic as the target `fuzz/fuzz_targets/TARGET.rs` (kept in sync by hand;
//! the CRC repair uses a local CRC-32 identical to `crc32fast`). A crash found
//! by `fuzz/run.sh` is copied into `fuzz/regressions/TARGET/` and replayed
//! here forever.

use std::path::{Path, PathBuf};

use planet_core::codec::{colour::HaarParams, ColourCodec, ElevationCodec};
use planet_core::format::{Header, Superblock, SUPERBLOCK_LEN};
use planet_core::{codec, format};
use planet_protocol::{decode_request_stream, FrameDecoder, LodRequest, ResponseDecoder};

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz")
}

/// Every input of a target: regressions first, then the corpus.
fn inputs(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    for kind in ["regressions", "corpus"] {
        let dir = fuzz_dir().join(kind).join(target);
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        let mut paths: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file())
            .filter(|p| {
                !p.file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with('.'))
            })
            .collect();
        paths.sort();
        for p in paths {
            let bytes = std::fs::read(&p).unwrap();
            out.push((p, bytes));
        }
    }
    out
}

fn replay(target: &str, run: fn(&[u8])) -> usize {
    let all = inputs(target);
    for (path, bytes) in &all {
        let r = std::panic::catch_unwind(|| run(bytes));
        assert!(r.is_ok(), "{target}: {} panics", path.display());
    }
    eprintln!("{target}: replayed {} inputs", all.len());
    all.len()
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// `fuzz_targets/protocol_frames.rs`.
fn protocol_frames(data: &[u8]) {
    let cut = data.first().map_or(0, |b| *b as usize % (data.len() + 1));
    let mut dec = FrameDecoder::new();
    dec.push(&data[..cut]);
    while let Ok(Some(_)) = dec.next_frame() {}
    dec.push(&data[cut..]);
    while let Ok(Some(_)) = dec.next_frame() {}
    let _ = dec.finish();
    let _ = decode_request_stream(data);
    let req = LodRequest {
        id: 7,
        offset: 64,
        size: 100,
    };
    let mut resp = ResponseDecoder::new(req);
    let _ = resp.push(data);
    let _ = resp.finish();
}

fn db_record_exercise(data: &[u8]) {
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

/// `fuzz_targets/db_record.rs`.
fn db_record(data: &[u8]) {
    db_record_exercise(data);
    if data.len() >= format::MIN_RECORD_LEN {
        let mut fixed = data.to_vec();
        let n = fixed.len();
        fixed[4..8].copy_from_slice(&(n as u32).to_le_bytes());
        let crc = crc32(&fixed[..n - 4]);
        fixed[n - 4..].copy_from_slice(&crc.to_le_bytes());
        db_record_exercise(&fixed);
    }
    let _ = codec::decompress(data, 4096);
}

/// `fuzz_targets/db_header.rs`.
fn db_header(data: &[u8]) {
    let _ = Superblock::decode(data);
    let _ = Header::decode(data, None);
    let _ = Header::decode(data, Some(1 << 20));
    if data.len() >= 8 {
        let mut fixed = data.to_vec();
        let n = fixed.len();
        let crc = crc32(&fixed[..n - 4]);
        fixed[n - 4..].copy_from_slice(&crc.to_le_bytes());
        let _ = Header::decode(&fixed, Some(1 << 20));
        if n >= SUPERBLOCK_LEN {
            let crc = crc32(&fixed[..60]);
            fixed[60..64].copy_from_slice(&crc.to_le_bytes());
            let _ = Superblock::decode(&fixed);
        }
    }
}

/// `fuzz_targets/control_session.rs` (stateful: the control-stream state
/// machine driven by a sequence of operations).
fn control_session(data: &[u8]) {
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

/// `fuzz_targets/server_config.rs`.
fn server_config(data: &[u8]) {
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

#[test]
fn replay_protocol_frames() {
    assert!(replay("protocol_frames", protocol_frames) > 0);
}

#[test]
fn replay_db_record() {
    assert!(replay("db_record", db_record) > 0);
}

#[test]
fn replay_db_header() {
    assert!(replay("db_header", db_header) > 0);
}

#[test]
fn replay_control_session() {
    // The seeds reach every state: welcomed then requests, cancel and
    // goodbye; refused; garbage.
    assert!(replay("control_session", control_session) >= 3);
}

#[test]
fn replay_server_config() {
    assert!(replay("server_config", server_config) > 0);
}

#[test]
fn the_local_crc_matches_the_format() {
    // The CRC used for repairs above must be the format's CRC-32 (IEEE).
    assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
}
