//! Replays the fuzz corpora and regressions without cargo-fuzz: every file in
//! `fuzz/regressions/TARGET/` and `fuzz/corpus/TARGET/` goes through the
//! function `planet_testkit::fuzzing::TARGET` that the target
//! `fuzz/fuzz_targets/TARGET.rs` calls (one body for both). A crash found by
//! `fuzz/run.sh` is copied into `fuzz/regressions/TARGET/` and replayed here
//! forever.

use std::path::{Path, PathBuf};

use planet_testkit::fuzzing::{
    control_session, db_header, db_open_request, db_open_request_seed, db_record, protocol_frames,
    repair_crc, server_config,
};

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
            let bytes = std::fs::read(&p).expect("read a fuzz input");
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
fn replay_db_open_request() {
    // A fresh seed (a valid file, a request for each of its records and
    // four bad ones) by pread and from the map, as is and repaired: all 26
    // record requests accepted, the others refused.
    // PLANET_WRITE_FUZZ_SEEDS=DIR writes them there (the corpus's seeds).
    for flags in [0u8, 1, 2, 3] {
        let seed = db_open_request_seed(flags);
        assert_eq!(db_open_request(&seed), 26, "flags {flags}");
        if let Some(dir) = std::env::var_os("PLANET_WRITE_FUZZ_SEEDS") {
            std::fs::write(Path::new(&dir).join(format!("seed-{flags}")), &seed).expect("write");
        }
    }
    // A truncated file refuses to open (nothing accepted).
    let seed = db_open_request_seed(0);
    assert_eq!(db_open_request(&seed[..seed.len() - 1]), 0);
    let n = replay("db_open_request", |d| {
        db_open_request(d);
    });
    assert!(n >= 4);
}

#[test]
fn replay_server_config() {
    assert!(replay("server_config", server_config) > 0);
}

#[test]
fn the_repair_crc_matches_the_format() {
    // The CRC used for repairs must be the format's CRC-32 (IEEE).
    assert_eq!(repair_crc(b"123456789"), 0xCBF4_3926);
}
