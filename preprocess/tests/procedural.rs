//! Procedural planet: build, verify, corruption detection, exact samples.

use planet_core::format::{parse_record, ChildRef, DbFile};
use planet_core::{lod, BlockId, Edge, Face};
use planet_preprocess::db::{verify, Sampler};
use planet_preprocess::plan::Plan;
use planet_preprocess::{
    build_procedural, default_procedural_options, Procedural, ProceduralOptions,
};
use rand::{Rng, SeedableRng};
use std::collections::HashMap;
use std::fs::OpenOptions;
use std::os::unix::fs::FileExt;
use std::path::Path;

/// A small planet with exact codecs (tests compare samples with the
/// generator's).
fn small(levels: u8, colour: bool) -> ProceduralOptions {
    ProceduralOptions {
        levels,
        colour,
        seed: 7,
        codecs: planet_preprocess::CodecOptions {
            colour: planet_preprocess::ColourQuality::Lossless,
            ..Default::default()
        },
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

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// A uniform planet's samples are those the generator made before detail
/// regions existed: FNV-1a over every leaf's elevation and colour grid of
/// seed 1 at 2 levels, faces and blocks in order (the file's bytes also
/// depend on the codec and the description, which changed since).
#[test]
fn uniform_planet_is_unchanged() {
    let mut o = default_procedural_options();
    o.levels = 2;
    let g = Procedural::new(&o);
    let mut bytes = Vec::new();
    for f in Face::ALL {
        for y in 0..4 {
            for x in 0..4 {
                let b = BlockId::new(f, 2, x, y).unwrap();
                for v in g.elevation_grid(b) {
                    bytes.extend_from_slice(&v.to_le_bytes());
                }
                for c in g.colour_grid(b) {
                    bytes.extend_from_slice(&c);
                }
            }
        }
    }
    assert_eq!(bytes.len(), 96 * (65 * 65 * 2 + 128 * 128 * 3));
    assert_eq!(fnv1a(&bytes), EXPECTED_UNIFORM_SAMPLES);
}

/// The hash of [`uniform_planet_is_unchanged`], computed with the generator
/// of commit aa03e92 (whose file the test pinned before, byte for byte).
const EXPECTED_UNIFORM_SAMPLES: u64 = 0x82cc_c218_8c7c_bb98;

/// The samples along the edge `e` of a full `(W+1)²` grid, in edge order.
fn edge_of(grid: &[i16], w: usize, e: Edge) -> Vec<i16> {
    (0..=w)
        .map(|k| {
            let (i, j) = match e {
                Edge::Left => (0, k),
                Edge::Right => (w, k),
                Edge::Bottom => (k, 0),
                Edge::Top => (k, w),
            };
            grid[j * (w + 1) + i]
        })
        .collect()
}

/// A planet with a detail region: the database holds the generator's
/// grids, verifies, and every pair of same-level neighbours (across faces
/// too) shares bit-identical edge samples, in particular where a leaf meets
/// a split block of its level whose samples come from deeper leaves.
#[test]
fn detail_region_edges_are_bit_identical() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.db");
    let mut opts = small(4, true);
    // On the edge between faces 0 and 2 (45° N, 0° E), 300 km, to level 8:
    // deep enough for a rough octave (wavelength ~1.6 km), wide enough for
    // base lattice points (every ~78 km) inside it.
    opts.detail = vec!["45,0,300,8".parse().unwrap()];
    let stats = build_procedural(&opts, &path).unwrap();
    let gen = Procedural::new(&opts);
    let Plan::Explicit { split, .. } = gen.plan() else {
        panic!("explicit plan expected");
    };
    assert_eq!(stats.max_level, 8);
    assert_eq!(stats.colour_max_level, 8);
    assert_eq!(stats.colour_records, gen.plan().block_counts().1);
    assert!(stats.colour_records > 6 * 341);
    assert_eq!(stats.elevation_records, 6 + 4 * split.len() as u64);
    let rep = verify(&path).unwrap();
    assert_eq!(rep.max_level, 8);
    let s = Sampler::open(&path).unwrap();
    let mut grids: HashMap<BlockId, Vec<i16>> = HashMap::new();
    s.for_each_elevation_block(|b, grid| {
        grids.insert(b, grid.to_vec());
    })
    .unwrap();
    assert_eq!(grids.len() as u64, stats.elevation_records);
    // The database holds exactly the generator's grids (from level 4 down:
    // the shallower ones regenerate whole faces).
    for (b, g) in grids.iter().filter(|(b, _)| b.level >= 4) {
        assert_eq!(g, &gen.elevation_grid(*b), "{b:?}");
    }
    let w = 64;
    let (mut pairs, mut leaf_split, mut cross_face) = (0, 0, 0);
    for (b, g) in &grids {
        for e in Edge::ALL {
            let (n, back) = b.neighbour(e);
            let Some(ng) = grids.get(&n) else { continue };
            assert_eq!(edge_of(g, w, e), edge_of(ng, w, back), "{b:?} {e:?} {n:?}");
            pairs += 1;
            if split.contains(b) != split.contains(&n) && b.level >= 4 {
                leaf_split += 1;
            }
            if n.face != b.face && b.level >= 5 {
                cross_face += 1;
            }
        }
    }
    assert!(pairs > 1000, "{pairs} pairs");
    assert!(leaf_split >= 8, "{leaf_split} leaf/split boundaries");
    assert!(cross_face >= 4, "{cross_face} deep cross-face pairs");
    // A point in the region descends to a level-8 leaf, one outside to 4.
    assert_eq!(s.sample(45.0, 0.1).unwrap().leaf.level, 8);
    assert_eq!(s.sample(-30.0, 100.0).unwrap().leaf.level, 4);
}

/// Every colour block of a database with its reference (error) and full
/// grid, walking the colour tree from the header.
fn colour_blocks(path: &Path) -> HashMap<BlockId, (ChildRef, Vec<lod::Rgb>)> {
    let db = DbFile::open(path).unwrap();
    let ct = db.header.colour.clone().unwrap();
    let w = ct.block_width as usize;
    let mut out = HashMap::new();
    for (fi, face) in Face::ALL.iter().enumerate() {
        let mut stack = vec![(
            BlockId::root(*face),
            ct.root_records[fi],
            ct.root_first_lods[fi].clone(),
        )];
        while let Some((b, r, lod1)) = stack.pop() {
            let bytes = db.read_record(&r).unwrap();
            let rec = parse_record(&bytes, None).unwrap();
            let full = rec.decode_colour(&ct.codec, &lod1, w).unwrap();
            for (k, c) in rec.header.children.iter().enumerate() {
                stack.push((b.child(k), *c, lod::split_colour(&full, w, k)));
            }
            out.insert(b, (r, full));
        }
    }
    out
}

/// Inside a detail region the colour tree is as deep as the elevation tree
/// (colour blocks at the region's level, bound to elevation blocks of the
/// same id, §4.4.1), with the generator's colours and honest errors;
/// outside it, the colour tree stops at the base level with the colours a
/// base-level leaf had before, also where the elevation goes deeper.
#[test]
fn detail_region_colour_follows_the_elevation() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.db");
    let mut opts = small(3, true);
    opts.detail = vec!["45,0,150,7".parse().unwrap()];
    let stats = build_procedural(&opts, &path).unwrap();
    assert_eq!((stats.max_level, stats.colour_max_level), (7, 7));
    let gen = Procedural::new(&opts);
    let plan = gen.plan();
    let Plan::Explicit { split, .. } = &plan else {
        panic!("explicit plan expected");
    };
    let rep = verify(&path).unwrap();
    assert_eq!(rep.colour_records, stats.colour_records);
    let s = Sampler::open(&path).unwrap();
    let mut elevation = std::collections::HashSet::new();
    s.for_each_elevation_block(|b, _| {
        elevation.insert(b);
    })
    .unwrap();
    let colour = colour_blocks(&path);
    assert_eq!(colour.len() as u64, stats.colour_records);
    let cap = opts.detail[0].cap(&opts.datum);
    let (mut deep_leaves, mut deep_detail, mut outside_leaves, mut rim) = (0, 0, 0, 0);
    for (b, (r, full)) in &colour {
        // Binding: a colour block only where the elevation block exists,
        // and split only where the elevation block is.
        assert!(elevation.contains(b), "colour {b:?} without elevation");
        let colour_split = colour.contains_key(&b.child(0));
        assert!(!colour_split || split.contains(b), "{b:?}");
        assert_eq!(colour_split, plan.colour_split(*b), "{b:?}");
        // The generator's colours (levels >= 3: shallower ones would
        // regenerate whole faces).
        if b.level >= 3 {
            assert_eq!(full, &gen.colour_grid(*b), "{b:?}");
        }
        let lod1 = lod::colour_filter(full, 128);
        let own = planet_preprocess::build::colour_lod_error(full, &lod1, 128);
        if colour_split {
            // Own LOD 1 error plus the worst child's: never below either.
            let worst = (0..4)
                .map(|k| colour[&b.child(k)].0.error)
                .fold(0f32, f32::max);
            assert_eq!(r.error, own as f32 + worst, "{b:?}");
            continue;
        }
        // A leaf's error is exactly its LOD 1 deviation.
        assert_eq!(r.error, own as f32, "{b:?}");
        if plan_meets(b, &cap) {
            assert_eq!(b.level, 7, "colour leaf {b:?} in the region");
            assert!(!split.contains(b));
            deep_leaves += 1;
            deep_detail += (r.error >= 2.0) as usize;
        } else if b.level == 3 {
            outside_leaves += 1;
        } else {
            // Below the base level outside the region: a child of a block
            // meeting it, as deep as the elevation there.
            assert!(plan_meets(&b.ancestor(b.level - 1), &cap), "{b:?}");
            assert!(!split.contains(b), "{b:?}");
            rim += 1;
        }
    }
    assert!(deep_leaves >= 16, "{deep_leaves} deep colour leaves");
    // Deep leaves hold colour their first LOD lacks (texel-level slope).
    assert!(
        deep_detail * 2 >= deep_leaves,
        "{deep_detail}/{deep_leaves}"
    );
    assert!(outside_leaves > 300 && rim >= 8, "{outside_leaves} {rim}");
    // Points: deep colour in the region, base colour far away.
    let deepest = |lat: f64, lon: f64| {
        let p = planet_core::cube::direction_from_lat_lon(lat.to_radians(), lon.to_radians());
        let fc = planet_core::cube::FaceCoord::from_direction(p);
        (0..=7u8)
            .filter(|&l| {
                let n = 1u32 << l;
                let cell = |v: f64| ((v * n as f64) as u32).min(n - 1);
                colour.contains_key(&BlockId::new(fc.face, l, cell(fc.s), cell(fc.t)).unwrap())
            })
            .max()
            .unwrap()
    };
    assert_eq!(deepest(45.0, 0.1), 7);
    assert_eq!(deepest(-30.0, 100.0), 3);
}

fn plan_meets(b: &BlockId, cap: &planet_preprocess::plan::Cap) -> bool {
    planet_preprocess::plan::block_meets_cap(*b, cap)
}

/// Every codec choice: verify against the generator holds the elevation
/// bound on every leaf sample (exact for 0 m and legacy) and the colour
/// PSNR target (lossless codecs exact), and the legacy codecs are what the
/// header says.
#[test]
fn codecs_meet_their_bounds_against_the_source() {
    use planet_preprocess::{CodecOptions, ColourQuality, ElevationChoice};
    let dir = tempfile::tempdir().unwrap();
    for (elevation, colour) in [
        (ElevationChoice::Legacy, ColourQuality::LosslessLegacy),
        (ElevationChoice::MaxError(0.0), ColourQuality::Lossless),
        (ElevationChoice::MaxError(3.0), ColourQuality::Psnr(36.0)),
        (ElevationChoice::MaxErrorId1(3.0), ColourQuality::Psnr(36.0)),
        (ElevationChoice::MaxErrorId2(3.0), ColourQuality::Psnr(36.0)),
        (ElevationChoice::MaxError(0.0), ColourQuality::Psnr(45.0)),
    ] {
        let path = dir.path().join("c.db");
        let mut o = small(2, true);
        o.codecs = CodecOptions { elevation, colour };
        build_procedural(&o, &path).unwrap();
        let src = Procedural::new(&o);
        let rep = planet_preprocess::db::verify_against(&path, Some(&src)).unwrap();
        let bound = match elevation {
            ElevationChoice::Legacy => 0.0,
            ElevationChoice::MaxError(m)
            | ElevationChoice::MaxErrorId1(m)
            | ElevationChoice::MaxErrorId2(m) => m,
        };
        // The in-loop build's exact first pass is gone.
        let files: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(files.len(), 1, "{elevation:?}: {files:?}");
        assert_eq!(rep.elevation_bound_m, Some(bound));
        assert!(rep.elevation_max_error_m.unwrap() <= bound);
        let psnr = rep.colour_psnr.unwrap();
        match colour {
            ColourQuality::Psnr(t) => assert!(psnr >= t as f64, "{psnr} < {t}"),
            _ => assert_eq!(psnr, f64::INFINITY),
        }
        let db = DbFile::open(&path).unwrap();
        let id = match elevation {
            ElevationChoice::Legacy => 0,
            ElevationChoice::MaxErrorId1(_) => 1,
            ElevationChoice::MaxErrorId2(_) => 2,
            ElevationChoice::MaxError(_) => 3,
        };
        assert_eq!(db.header.elevation.codec.id(), id, "{elevation:?}");
    }
}

/// The geometric error of every elevation reference includes the codec's
/// max error: with `--max-error 3` each reference's error is the exact
/// build's plus 3 m (added at the leaves, carried up), and the bounds widen
/// by 3 m.
#[test]
fn child_errors_include_the_codec_error() {
    use planet_preprocess::{CodecOptions, ElevationChoice};
    let dir = tempfile::tempdir().unwrap();
    // Per build: every reference (block, error, min, max), sorted by block.
    let refs = |m: f64| -> Vec<(BlockId, f32, f32, f32)> {
        let path = dir.path().join(format!("e{m}.db"));
        let mut o = small(2, false);
        o.codecs = CodecOptions {
            elevation: ElevationChoice::MaxError(m),
            ..Default::default()
        };
        build_procedural(&o, &path).unwrap();
        let db = DbFile::open(&path).unwrap();
        let mut all = Vec::new();
        let mut stack: Vec<(BlockId, ChildRef)> = Face::ALL
            .iter()
            .zip(db.header.elevation.root_records)
            .map(|(f, r)| (BlockId::root(*f), r))
            .collect();
        while let Some((b, r)) = stack.pop() {
            all.push((b, r.error, r.min_elevation, r.max_elevation));
            let bytes = db.read_record(&r).unwrap();
            let rec = parse_record(&bytes, None).unwrap();
            for (k, c) in rec.header.children.iter().enumerate() {
                stack.push((b.child(k), *c));
            }
        }
        all.sort_by_key(|r| r.0);
        all
    };
    let (exact, bounded) = (refs(0.0), refs(3.0));
    assert_eq!(exact.len(), 6 * 21);
    assert_eq!(exact.len(), bounded.len());
    for (a, b) in exact.iter().zip(&bounded) {
        assert_eq!(a.0, b.0);
        assert!(
            (b.1 - (a.1 + 3.0)).abs() < 1e-3,
            "{:?}: {} vs {} + 3",
            a.0,
            b.1,
            a.1
        );
        assert!((b.2 - (a.2 - 3.0)).abs() < 1e-3 && (b.3 - (a.3 + 3.0)).abs() < 1e-3);
    }
}
