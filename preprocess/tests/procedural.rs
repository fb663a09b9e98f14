//! Procedural planet: build, verify, corruption detection, exact samples.

use planet_core::format::DbFile;
use planet_preprocess::db::{verify, Sampler};
use planet_preprocess::{
    build_procedural, default_procedural_options, Procedural, ProceduralOptions,
};
use rand::{Rng, SeedableRng};
use std::fs::OpenOptions;
use std::os::unix::fs::FileExt;
use std::path::Path;

fn small(levels: u8, colour: bool) -> ProceduralOptions {
    ProceduralOptions {
        levels,
        colour,
        seed: 7,
        ..default_procedural_options()
    }
}

fn flip_fails(path: &Path, at: u64) {
    let f = OpenOptions::new()
        .read(true)
        .write(true)
        .open(path)
        .unwrap();
    let mut b = [0u8; 1];
    f.read_exact_at(&mut b, at).unwrap();
    f.write_all_at(&[b[0] ^ 0x20], at).unwrap();
    let r = verify(path);
    f.write_all_at(&b, at).unwrap();
    assert!(r.is_err(), "flip at {at} not detected");
}

#[test]
fn verify_passes_and_every_flip_is_detected() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.db");
    let stats = build_procedural(&small(1, true), &path).unwrap();
    assert_eq!(stats.elevation_records, 30);
    assert_eq!(stats.colour_records, 30);
    let rep = verify(&path).unwrap();
    assert_eq!(rep.elevation_records, 30);
    assert_eq!(rep.colour_records, 30);
    assert_eq!(rep.max_level, 1);
    let len = std::fs::metadata(&path).unwrap().len();
    assert_eq!(len, stats.file_bytes);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    for _ in 0..300 {
        flip_fails(&path, rng.random_range(0..len));
    }
    for at in [0, 1, 63, 64, len - 1, len - 2] {
        flip_fails(&path, at);
    }
    // Every byte of one record (a root's colour record, the smallest kind
    // that has children is still ~10 kB; use an elevation leaf instead).
    let db = DbFile::open(&path).unwrap();
    let r = db.header.elevation.root_records[2];
    drop(db);
    for at in r.offset..r.offset + r.size as u64 {
        flip_fails(&path, at);
    }
    // And the header region.
    let db = DbFile::open(&path).unwrap();
    let h = db.superblock.header_offset;
    drop(db);
    for at in (h..len).step_by(7) {
        flip_fails(&path, at);
    }
    assert!(verify(&path).is_ok(), "restored file verifies again");
    // Truncation and a missing file are errors too.
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() - 1]).unwrap();
    assert!(verify(&path).is_err());
    assert!(verify(&dir.path().join("missing.db")).is_err());
}

#[test]
fn every_sample_is_the_generators_reprojected_grid() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.db");
    let opts = small(2, true);
    build_procedural(&opts, &path).unwrap();
    let gen = Procedural::new(&opts);
    let s = Sampler::open(&path).unwrap();
    let mut n = 0;
    s.for_each_elevation_block(|b, grid| {
        assert_eq!(grid, gen.elevation_grid(b).as_slice(), "elevation {b:?}");
        n += 1;
    })
    .unwrap();
    assert_eq!(n, 6 * 21);
    let mut n = 0;
    s.for_each_colour_block(|b, grid| {
        assert_eq!(grid, gen.colour_grid(b).as_slice(), "colour {b:?}");
        n += 1;
    })
    .unwrap();
    assert_eq!(n, 6 * 21);
    // Point sampling descends to a level-2 leaf.
    let r = s.sample(45.0, 10.0).unwrap();
    assert_eq!(r.leaf.level, 2);
    let h = s.header();
    assert!(r.metres >= h.min_elevation as f64 && r.metres <= h.max_elevation as f64);
}

#[test]
fn deterministic_and_sphere_datum() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.db");
    let b = dir.path().join("b.db");
    let mut o = small(1, false);
    o.datum = planet_core::Datum::Sphere {
        radius: 1_737_400.0,
    };
    // One thread: the record order is fixed, so the bytes are identical
    // (with several threads, records of sibling subtrees interleave).
    o.threads = Some(1);
    build_procedural(&o, &a).unwrap();
    build_procedural(&o, &b).unwrap();
    assert!(std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap());
    let db = DbFile::open(&a).unwrap();
    assert!(db.header.colour.is_none());
    assert_eq!(db.header.datum, o.datum);
    // Child references carry consistent bounds and errors.
    for r in db.header.elevation.root_records {
        assert!(r.min_elevation <= r.max_elevation && r.error >= 0.0);
    }
}
