//! Encode and decode throughput of the record codecs (criterion):
//! `cargo bench -p planet-core --bench codec`. Throughput is in samples
//! (new elevation samples or LOD 0 texels of a record) per second, one core.
//!
//! Before criterion's wall-clock groups it prints a table (and a JSON line)
//! of samples per *CPU*-second of the bench thread (from
//! `/proc/thread-self/schedstat`), which stays meaningful on a shared,
//! loaded machine where wall-clock rates are not.
//!
//! Inputs are made here: 32 elevation blocks of W = 64 (the builder's
//! width) of fractal terrain (value-noise fBm, 3 km relief, about SRTM-like
//! roughness at 90 m spacing: residuals of tens of metres), and 32 colour
//! blocks of W = 128 of smooth gradients, edges and noise; the figures in
//! docs/BENCHMARKS.md "Bytes per sample" come from this bench. These
//! blocks are rougher than any data the project builds (0.95 bytes a new
//! sample exact, against 0.45 on the real data's records).
//!
//! With `CODEC_BENCH_DB=PATH` it also decodes the elevation records of a
//! database (up to 4096, in a depth-first walk from the roots, each from
//! its parent's decoded samples): a row of the table and a criterion
//! group `elevation-db`.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use planet_core::codec::colour::HaarParams;
use planet_core::codec::{ColourCodec, ElevationCodec};
use planet_core::lod::{self, Rgb};
use std::hint::black_box;

const EW: usize = 64;

/// The elevation codecs measured: legacy, ids 1 and 2 exact and at 1 m,
/// id 3 at 1 m (exact, its payloads are id 2's).
const ELEVATION_CODECS: [(&str, ElevationCodec); 6] = [
    ("elevation legacy", ElevationCodec::Legacy),
    (
        "elevation id 1 exact",
        ElevationCodec::Quantised { max_error: 0 },
    ),
    (
        "elevation id 1 1 m",
        ElevationCodec::Quantised { max_error: 1 },
    ),
    (
        "elevation id 2 exact",
        ElevationCodec::Laplace { max_error: 0 },
    ),
    (
        "elevation id 2 1 m",
        ElevationCodec::Laplace { max_error: 1 },
    ),
    (
        "elevation id 3 1 m",
        ElevationCodec::InLoop { max_error: 1 },
    ),
];

/// A database's elevation records to decode: each payload with its
/// `raw_len` and the grid holding its parent's decoded LOD 1.
struct DbRecords {
    codec: ElevationCodec,
    width: usize,
    records: Vec<(Vec<u8>, usize, Vec<i16>)>,
    samples: u64,
}

/// The records of `CODEC_BENCH_DB`, if set (a bad path panics: a bench
/// asked for it).
fn db_records() -> Option<DbRecords> {
    let path = std::env::var_os("CODEC_BENCH_DB")?;
    let db = planet_core::format::DbFile::open(path.as_ref()).expect("CODEC_BENCH_DB opens");
    let mut records = Vec::new();
    db.walk_elevation(|v| {
        records.push((
            v.record.payload.to_vec(),
            v.record.header.raw_len as usize,
            v.lod1.to_vec(),
        ));
        records.len() < 4096
    })
    .expect("CODEC_BENCH_DB's records decode");
    let h = &db.header.elevation;
    let width = h.block_width as usize;
    Some(DbRecords {
        codec: h.codec,
        width,
        samples: (records.len() * lod::elevation_new_samples(width)) as u64,
        records,
    })
}

impl DbRecords {
    fn decode_all(&self, grid: &mut Vec<i16>) {
        for (p, raw, lod1) in &self.records {
            grid.clone_from(lod1);
            self.codec
                .decode(p, *raw, self.width, grid)
                .expect("own database's record");
            black_box(&grid);
        }
    }
}

const CW: usize = 128;
const BLOCKS: usize = 32;

fn hash(x: i64, y: i64, seed: u64) -> f64 {
    let mut h = (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ seed.wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 29;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

fn value_noise(x: f64, y: f64, seed: u64) -> f64 {
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
    let (xi, yi) = (x0 as i64, y0 as i64);
    let a = hash(xi, yi, seed);
    let b = hash(xi + 1, yi, seed);
    let c = hash(xi, yi + 1, seed);
    let d = hash(xi + 1, yi + 1, seed);
    a + (b - a) * sx + (c - a) * sy + (a - b - c + d) * sx * sy
}

fn fbm(x: f64, y: f64, seed: u64) -> f64 {
    let (mut s, mut f, mut a) = (0.0, 1.0, 1.0);
    for o in 0..8 {
        s += a * value_noise(x * f, y * f, seed + o);
        f *= 2.0;
        a *= 0.5;
    }
    s
}

fn elevation_blocks() -> Vec<Vec<i16>> {
    let side = EW + 1;
    (0..BLOCKS)
        .map(|b| {
            (0..side * side)
                .map(|p| {
                    let (i, j) = ((p % side) as f64, (p / side) as f64);
                    let x = (b % 8) as f64 * 4.0 + i / 16.0;
                    let y = (b / 8) as f64 * 4.0 + j / 16.0;
                    (1500.0 * fbm(x, y, 7) - 500.0) as i16
                })
                .collect()
        })
        .collect()
}

fn colour_blocks() -> Vec<Vec<Rgb>> {
    (0..BLOCKS)
        .map(|b| {
            (0..CW * CW)
                .map(|p| {
                    let (i, j) = ((p % CW) as f64, (p / CW) as f64);
                    let x = (b % 8) as f64 * 8.0 + i / 16.0;
                    let y = (b / 8) as f64 * 8.0 + j / 16.0;
                    let t = fbm(x, y, 11);
                    let n = hash(p as i64, b as i64, 3) * 6.0;
                    [
                        (60.0 + 90.0 * t + n).clamp(0.0, 255.0) as u8,
                        (80.0 + 70.0 * t + n).clamp(0.0, 255.0) as u8,
                        (40.0 + 50.0 * t + n).clamp(0.0, 255.0) as u8,
                    ]
                })
                .collect()
        })
        .collect()
}

/// CPU time of this thread in ns (Linux; `None` elsewhere).
fn cpu_ns() -> Option<u64> {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// Samples per CPU-second of `f` (which handles `n` samples), run for about
/// one CPU-second.
fn per_cpu_second(n: u64, mut f: impl FnMut()) -> Option<f64> {
    f();
    let start = cpu_ns()?;
    let mut runs = 0u64;
    while cpu_ns()? - start < 1_000_000_000 {
        f();
        runs += 1;
    }
    Some((runs * n) as f64 / ((cpu_ns()? - start) as f64 * 1e-9))
}

/// The CPU-time table: encode and decode rates of every codec.
fn cpu_table() {
    let eblocks = elevation_blocks();
    let side = EW + 1;
    let en = (BLOCKS * lod::elevation_new_samples(EW)) as u64;
    let mut rows = Vec::new();
    for (name, codec) in ELEVATION_CODECS {
        let payloads: Vec<_> = eblocks.iter().map(|b| codec.encode(b, EW)).collect();
        let bytes: usize = payloads.iter().map(|p| p.bytes.len()).sum();
        let enc = per_cpu_second(en, || {
            for b in &eblocks {
                black_box(codec.encode(black_box(b), EW));
            }
        });
        let mut grid = vec![0i16; side * side];
        let dec = per_cpu_second(en, || {
            for (p, b) in payloads.iter().zip(&eblocks) {
                lod::elevation_place_first_lod(&lod::elevation_first_lod(b, EW), EW, &mut grid);
                codec
                    .decode(&p.bytes, p.raw_len as usize, EW, &mut grid)
                    .expect("own payload");
                black_box(&grid);
            }
        });
        rows.push((name.to_string(), bytes as f64 / en as f64, enc, dec));
    }
    if let Some(db) = db_records() {
        let bytes: usize = db.records.iter().map(|r| r.0.len()).sum();
        let mut grid = Vec::new();
        let dec = per_cpu_second(db.samples, || db.decode_all(&mut grid));
        let name = format!(
            "elevation {} k {}, {} records of CODEC_BENCH_DB",
            db.codec.name(),
            db.codec.max_error(),
            db.records.len()
        );
        rows.push((name, bytes as f64 / db.samples as f64, None, dec));
    }
    let cblocks = colour_blocks();
    let lod1s: Vec<Vec<Rgb>> = cblocks.iter().map(|b| lod::colour_filter(b, CW)).collect();
    let cn = (BLOCKS * CW * CW) as u64;
    for (name, codec) in [
        ("colour legacy", ColourCodec::Legacy),
        ("colour lossless", ColourCodec::Lossless),
        (
            "colour 42 dB",
            ColourCodec::Haar(HaarParams::for_psnr(42.0)),
        ),
    ] {
        let payloads: Vec<_> = cblocks
            .iter()
            .zip(&lod1s)
            .map(|(b, l)| codec.encode(b, l, CW, 0).0)
            .collect();
        let bytes: usize = payloads.iter().map(|p| p.bytes.len()).sum();
        let enc = per_cpu_second(cn, || {
            for (b, l) in cblocks.iter().zip(&lod1s) {
                black_box(codec.encode(black_box(b), l, CW, 0));
            }
        });
        let dec = per_cpu_second(cn, || {
            for (p, l) in payloads.iter().zip(&lod1s) {
                black_box(
                    codec
                        .decode(&p.bytes, p.raw_len as usize, l, CW)
                        .expect("own payload"),
                );
            }
        });
        rows.push((name.to_string(), bytes as f64 / cn as f64, enc, dec));
    }
    let m = |v: Option<f64>| v.map_or("n/a".to_string(), |v| format!("{:.1}", v / 1e6));
    println!("| codec | bytes per sample | encode M samples/CPU-s | decode M samples/CPU-s |");
    println!("|---|---|---|---|");
    for (name, b, e, d) in &rows {
        println!("| {name} | {b:.4} | {} | {} |", m(*e), m(*d));
    }
    let json: Vec<String> = rows
        .iter()
        .map(|(name, b, e, d)| {
            format!(
                "{{\"codec\":\"{name}\",\"bytes_per_sample\":{b:.5},\"encode_per_cpu_s\":{},\"decode_per_cpu_s\":{}}}",
                e.map_or("null".into(), |v| format!("{v:.0}")),
                d.map_or("null".into(), |v| format!("{v:.0}"))
            )
        })
        .collect();
    println!("[{}]", json.join(","));
}

fn elevation(c: &mut Criterion) {
    cpu_table();
    let blocks = elevation_blocks();
    let side = EW + 1;
    let n = (BLOCKS * lod::elevation_new_samples(EW)) as u64;
    let mut g = c.benchmark_group("elevation");
    g.throughput(Throughput::Elements(n));
    for (name, codec) in ELEVATION_CODECS {
        let payloads: Vec<_> = blocks.iter().map(|b| codec.encode(b, EW)).collect();
        let bytes: usize = payloads.iter().map(|p| p.bytes.len()).sum();
        println!(
            "{name}: {:.4} bytes per new sample",
            bytes as f64 / n as f64
        );
        g.bench_function(BenchmarkId::new("encode", name), |bench| {
            bench.iter(|| {
                for b in &blocks {
                    black_box(codec.encode(black_box(b), EW));
                }
            })
        });
        let firsts: Vec<Vec<i16>> = blocks
            .iter()
            .map(|b| {
                let mut g = vec![0i16; side * side];
                lod::elevation_place_first_lod(&lod::elevation_first_lod(b, EW), EW, &mut g);
                g
            })
            .collect();
        g.bench_function(BenchmarkId::new("decode", name), |bench| {
            let mut grid = vec![0i16; side * side];
            bench.iter(|| {
                for (p, f) in payloads.iter().zip(&firsts) {
                    grid.copy_from_slice(f);
                    codec
                        .decode(&p.bytes, p.raw_len as usize, EW, &mut grid)
                        .expect("own payload");
                    black_box(&grid);
                }
            })
        });
    }
    g.finish();
    if let Some(db) = db_records() {
        let mut g = c.benchmark_group("elevation-db");
        g.throughput(Throughput::Elements(db.samples));
        let mut grid = Vec::new();
        g.bench_function(BenchmarkId::new("decode", db.codec.name()), |bench| {
            bench.iter(|| db.decode_all(&mut grid))
        });
        g.finish();
    }
}

fn colour(c: &mut Criterion) {
    let blocks = colour_blocks();
    let lod1s: Vec<Vec<Rgb>> = blocks.iter().map(|b| lod::colour_filter(b, CW)).collect();
    let n = (BLOCKS * CW * CW) as u64;
    let mut g = c.benchmark_group("colour");
    g.throughput(Throughput::Elements(n));
    for (name, codec) in [
        ("legacy", ColourCodec::Legacy),
        ("lossless", ColourCodec::Lossless),
        ("psnr42", ColourCodec::Haar(HaarParams::for_psnr(42.0))),
    ] {
        let payloads: Vec<_> = blocks
            .iter()
            .zip(&lod1s)
            .map(|(b, l)| codec.encode(b, l, CW, 0).0)
            .collect();
        let bytes: usize = payloads.iter().map(|p| p.bytes.len()).sum();
        println!(
            "colour {name}: {:.4} bytes per texel",
            bytes as f64 / n as f64
        );
        g.bench_function(BenchmarkId::new("encode", name), |bench| {
            bench.iter(|| {
                for (b, l) in blocks.iter().zip(&lod1s) {
                    black_box(codec.encode(black_box(b), l, CW, 0));
                }
            })
        });
        g.bench_function(BenchmarkId::new("decode", name), |bench| {
            bench.iter(|| {
                for (p, l) in payloads.iter().zip(&lod1s) {
                    black_box(
                        codec
                            .decode(&p.bytes, p.raw_len as usize, l, CW)
                            .expect("own payload"),
                    );
                }
            })
        });
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10).measurement_time(std::time::Duration::from_secs(2));
    targets = elevation, colour
}
criterion_main!(benches);
