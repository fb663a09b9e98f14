//! Measures elevation predictor / entropy-coder variants on a database's
//! decoded grids (for choosing the codec): `cargo run --release -p
//! planet-core --example codec_lab -- DB [k]`; `DB decode [STRIDE]`
//! measures the decode rate of a database's own records (every STRIDE-th
//! in the traversal, for databases too large to hold), `DB payload k` the payload size
//! (and a digest of the payloads, which a change of implementation that
//! keeps the format keeps) of each quantised codec on an exact database's
//! grids; `synthetic AMP` the id 2 decode rate of noise of amplitude AMP
//! (0: flat, every residual zero: the decoder's cost without branch misses).
use planet_core::codec::{ElevationCodec, Payload};
use planet_core::format::{parse_record, DbFile};
use planet_core::lod;
use planet_core::BlockId;
use std::collections::HashMap;

fn grids(path: &str) -> Vec<Vec<i16>> {
    let db = DbFile::open(path.as_ref()).unwrap();
    let mut out = Vec::new();
    db.walk_elevation(|v| {
        out.push(v.full.to_vec());
        true
    })
    .unwrap();
    out
}

/// Id 2 against id 3 at max error `k` on an exact database: top-down, id
/// 3's LOD 1 from the parent's id 3 decode; payload bytes, and the largest
/// error of id 3's decoded samples against the source.
fn in_loop(path: &str, k: u16) {
    let db = DbFile::open(path.as_ref()).unwrap();
    let w = db.header.elevation.block_width as usize;
    let (fixed, inloop) = (
        ElevationCodec::Laplace { max_error: k },
        ElevationCodec::InLoop { max_error: k },
    );
    let (mut b2, mut b3, mut n, mut worst) = (0usize, 0usize, 0usize, 0i32);
    // Each split block's id 3 decode, with the children still to visit.
    let mut decoded: HashMap<BlockId, (Vec<i16>, usize)> = HashMap::new();
    db.walk_elevation(|v| {
        b2 += fixed.encode(v.full, w).bytes.len();
        // The decoder's LOD 1: the parent's id 3 decode (the root's exact).
        let mut dec = v.lod1.to_vec();
        if let Some(parent) = v.block.parent() {
            let (pgrid, left) = decoded.get_mut(&parent).expect("parent first");
            lod::split_elevation(pgrid, w, v.block.child_index(), &mut dec);
            *left -= 1;
            if *left == 0 {
                decoded.remove(&parent);
            }
        }
        // The encoder's grid: that LOD 1, the source elsewhere.
        let mut enc = v.full.to_vec();
        lod::elevation_place_first_lod(&lod::elevation_first_lod(&dec, w), w, &mut enc);
        let p = inloop.encode(&enc, w);
        b3 += p.bytes.len();
        inloop
            .decode(&p.bytes, p.raw_len as usize, w, &mut dec)
            .unwrap();
        for (a, b) in dec.iter().zip(v.full) {
            worst = worst.max((*a as i32 - *b as i32).abs());
        }
        n += 1;
        let kids = v.record.header.children.len();
        if kids > 0 {
            decoded.insert(v.block, (dec, kids));
        }
        true
    })
    .unwrap();
    println!(
        "{n} records, k {k}: id 2 {b2} bytes, id 3 {b3} bytes ({:.4}×), id 3 max error {worst}",
        b3 as f64 / b2 as f64
    );
}

fn zz(v: i32) -> u32 {
    ((v << 1) ^ (v >> 31)) as u32
}

/// Residuals (and a context per residual) for a predictor variant.
fn residuals(idx: &[i32], side: usize, variant: u8) -> (Vec<i32>, Vec<u8>) {
    let at = |i: usize, j: usize| idx[j * side + i];
    let mut r = Vec::new();
    let mut ctx = Vec::new();
    let cubic = |a: i32, b: i32, c: i32, d: i32| (-a + 9 * b + 9 * c - d + 8).div_euclid(16);
    let mid = |i: usize, j: usize| -> (i32, i32) {
        // returns (prediction, activity)
        if j.is_multiple_of(2) {
            let (b, c) = (at(i - 1, j), at(i + 1, j));
            let act = (b - c).abs();
            if variant >= 1 && i >= 3 && i + 3 < side {
                (cubic(at(i - 3, j), b, c, at(i + 3, j)), act)
            } else {
                ((b + c) >> 1, act)
            }
        } else {
            let (b, c) = (at(i, j - 1), at(i, j + 1));
            let act = (b - c).abs();
            if variant >= 1 && j >= 3 && j + 3 < side {
                (cubic(at(i, j - 3), b, c, at(i, j + 3)), act)
            } else {
                ((b + c) >> 1, act)
            }
        }
    };
    let bucket = |a: i32| -> u8 { (32 - (a as u32).leading_zeros()).min(15) as u8 };
    for j in 0..side {
        let range: Vec<usize> = if j.is_multiple_of(2) {
            (1..side).step_by(2).collect()
        } else {
            (0..side).step_by(2).collect()
        };
        for i in range {
            let (p, a) = mid(i, j);
            r.push(at(i, j) - p);
            ctx.push(bucket(a));
        }
    }
    for j in (1..side).step_by(2) {
        for i in (1..side).step_by(2) {
            let (l, rr, u, d) = (at(i - 1, j), at(i + 1, j), at(i, j - 1), at(i, j + 1));
            let p = if variant >= 2 {
                // median-ish: mean of the two middle of four
                let mut v = [l, rr, u, d];
                v.sort();
                (v[1] + v[2]) >> 1
            } else {
                (l + rr + u + d) >> 2
            };
            let a = (l - rr).abs().max((u - d).abs());
            r.push(at(i, j) - p);
            ctx.push(bucket(a));
        }
    }
    (r, ctx)
}

/// Context from causal residual magnitudes: midpoints use the previous
/// residual in coding order plus the LOD 1 activity; centres the four
/// midpoints' residuals around them.
fn residual_contexts(idx: &[i32], side: usize, r: &[i32], act: &[u8]) -> Vec<u8> {
    let mut res = vec![0i32; side * side];
    let mut order = Vec::new();
    for j in 0..side {
        let first = if j.is_multiple_of(2) { 1 } else { 0 };
        for i in (first..side).step_by(2) {
            order.push((i, j));
        }
    }
    let n1 = order.len();
    for j in (1..side).step_by(2) {
        for i in (1..side).step_by(2) {
            order.push((i, j));
        }
    }
    let _ = idx;
    let bucket = |a: u32| -> u8 { (32 - a.leading_zeros()).min(15) as u8 };
    let mut out = Vec::with_capacity(order.len());
    let mut prev = 0u32;
    for (k, &(i, j)) in order.iter().enumerate() {
        if k < n1 {
            let c = bucket(prev * 2 + (1u32 << act[k]) / 2);
            out.push(c.min(11));
            prev = r[k].unsigned_abs();
        } else {
            let at = |i: usize, j: usize| res[j * side + i].unsigned_abs();
            let s = at(i - 1, j) + at(i + 1, j) + at(i, j - 1) + at(i, j + 1);
            out.push(bucket(s).min(11));
        }
        res[j * side + i] = r[k];
    }
    out
}

fn entropy(syms: &[u32]) -> f64 {
    let mut h: HashMap<u32, usize> = HashMap::new();
    for s in syms {
        *h.entry(*s).or_default() += 1;
    }
    let n = syms.len() as f64;
    h.values()
        .map(|&c| -(c as f64) * (c as f64 / n).log2())
        .sum::<f64>()
        / 8.0
}

/// CPU time of this thread in ns (Linux).
fn cpu_ns() -> u64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .unwrap()
        .split_whitespace()
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

/// Decode rate of the database's own elevation records, samples per
/// CPU-second (records read once, decoded repeatedly from memory).
fn decode_rate(path: &str, stride: usize) {
    let db = DbFile::open(path.as_ref()).unwrap();
    let h = db.header.clone();
    let w = h.elevation.block_width as usize;
    let side = w + 1;
    let (mut jobs, mut seen) = (Vec::new(), 0usize);
    db.walk_elevation(|v| {
        seen += 1;
        if seen % stride == 0 {
            jobs.push((v.bytes.to_vec(), v.lod1.to_vec()));
        }
        true
    })
    .unwrap();
    let n = jobs.len() * lod::elevation_new_samples(w);
    let start = cpu_ns();
    let mut runs = 0;
    let mut grid = vec![0i16; side * side];
    while cpu_ns() - start < 2_000_000_000 {
        for (bytes, first) in &jobs {
            let rec = parse_record(bytes, None).unwrap();
            grid.copy_from_slice(first);
            rec.decode_elevation(&h.elevation.codec, w, &mut grid)
                .unwrap();
        }
        runs += 1;
    }
    let secs = (cpu_ns() - start) as f64 * 1e-9;
    println!(
        "{path}: {} decode {:.1} M samples per CPU-second ({} records)",
        h.elevation.codec.name(),
        (runs * n) as f64 / secs / 1e6,
        jobs.len()
    );
}

/// Payload bytes per new sample of every quantised codec on an exact
/// database's grids at max error `k` (each grid's LOD 1 is its source).
fn payload_sizes(path: &str, k: u16) {
    let gs = grids(path);
    let side = (gs[0].len() as f64).sqrt() as usize;
    let n = (gs.len() * lod::elevation_new_samples(side - 1)) as f64;
    for codec in [
        ElevationCodec::Quantised { max_error: k },
        ElevationCodec::Laplace { max_error: k },
    ] {
        let w = side - 1;
        let start = cpu_ns();
        let payloads: Vec<_> = gs.iter().map(|g| codec.encode(g, w)).collect();
        let enc = n / ((cpu_ns() - start) as f64 * 1e-9);
        let bytes: usize = payloads.iter().map(|p| p.bytes.len()).sum();
        // A digest of every payload in order: an implementation change that
        // keeps the format must keep it.
        let digest = {
            use std::hash::{Hash, Hasher};
            let mut h = std::collections::hash_map::DefaultHasher::new();
            for p in &payloads {
                p.bytes.hash(&mut h);
            }
            h.finish()
        };
        let dec = decode_payloads(codec, &payloads, &gs, w);
        println!(
            "{} k {k}: {:.4} B per new sample ({} grids, digest {digest:016x}), encode {:.1} M, decode {:.1} M samples per CPU-second",
            codec.name(),
            bytes as f64 / n,
            gs.len(),
            enc / 1e6,
            dec / 1e6
        );
    }
}

/// New samples per CPU-second decoding `payloads` of `grids` (full, each
/// decoded from its own LOD 1: the quantisation is pointwise) for 2 s.
fn decode_payloads(
    codec: ElevationCodec,
    payloads: &[Payload],
    grids: &[Vec<i16>],
    w: usize,
) -> f64 {
    let side = w + 1;
    let firsts: Vec<Vec<i16>> = grids
        .iter()
        .map(|g| {
            let mut f = vec![0i16; side * side];
            lod::elevation_place_first_lod(&lod::elevation_first_lod(g, w), w, &mut f);
            f
        })
        .collect();
    let n = (grids.len() * lod::elevation_new_samples(w)) as f64;
    let mut grid = vec![0i16; side * side];
    let (start, mut runs) = (cpu_ns(), 0);
    while cpu_ns() - start < 2_000_000_000 {
        for (p, f) in payloads.iter().zip(&firsts) {
            grid.copy_from_slice(f);
            codec
                .decode(&p.bytes, p.raw_len as usize, w, &mut grid)
                .unwrap();
        }
        runs += 1;
    }
    runs as f64 * n / ((cpu_ns() - start) as f64 * 1e-9)
}

/// Decode rate of synthetic grids: `flat` (every residual 0) or `noise`
/// (uniform noise of amplitude `amp`), to bound the decoder's cost.
fn synthetic(amp: i32) {
    let w = 64;
    let side = w + 1;
    let mut x = 1u32;
    let gs: Vec<Vec<i16>> = (0..500)
        .map(|_| {
            (0..side * side)
                .map(|_| {
                    x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    (if amp == 0 {
                        100
                    } else {
                        100 + (x >> 16) as i32 % amp
                    }) as i16
                })
                .collect()
        })
        .collect();
    let codec = ElevationCodec::Laplace { max_error: 0 };
    let payloads: Vec<_> = gs.iter().map(|g| codec.encode(g, w)).collect();
    let n = (gs.len() * lod::elevation_new_samples(w)) as f64;
    let bytes: usize = payloads.iter().map(|p| p.bytes.len()).sum();
    let dec = decode_payloads(codec, &payloads, &gs, w);
    println!(
        "amp {amp}: {:.3} B/sample, decode {:.1} M samples per CPU-second",
        bytes as f64 / n,
        dec / 1e6
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.get(1).map(String::as_str) == Some("synthetic") {
        return synthetic(args.get(2).map_or(0, |s| s.parse().unwrap()));
    }
    if args.get(2).map(String::as_str) == Some("decode") {
        let stride = args.get(3).map_or(1, |s| s.parse().unwrap());
        return decode_rate(&args[1], stride);
    }
    if args.get(2).map(String::as_str) == Some("inloop") {
        return in_loop(&args[1], args.get(3).map_or(1, |s| s.parse().unwrap()));
    }
    if args.get(2).map(String::as_str) == Some("payload") {
        let k = args.get(3).map_or(0, |s| s.parse().unwrap());
        return payload_sizes(&args[1], k);
    }
    let gs = grids(&args[1]);
    let k: i32 = args.get(2).map_or(0, |s| s.parse().unwrap());
    let s = 2 * k + 1;
    let side = (gs[0].len() as f64).sqrt() as usize;
    let n: usize = gs.len() * lod::elevation_new_samples(side - 1);
    println!("{} grids, {} new samples, k {}", gs.len(), n, k);
    for variant in 1..2u8 {
        let (mut z9, mut z19, mut h0, mut hc, mut hr) = (0usize, 0usize, 0f64, 0f64, 0f64);
        for g in &gs {
            let idx: Vec<i32> = g.iter().map(|&v| (v as i32 + k).div_euclid(s)).collect();
            let (r, ctx) = residuals(&idx, side, variant);
            let syms: Vec<u32> = r.iter().map(|&v| zz(v)).collect();
            let mut bytes = Vec::new();
            let mut tail = Vec::new();
            for &v in &syms {
                if v < 255 {
                    bytes.push(v as u8)
                } else {
                    bytes.push(255);
                    tail.extend_from_slice(&v.to_le_bytes());
                }
            }
            bytes.extend_from_slice(&tail);
            z9 += zstd::bulk::compress(&bytes, 9).unwrap().len();
            z19 += zstd::bulk::compress(&bytes, 19).unwrap().len();
            h0 += entropy(&syms);
            let ctx2 = residual_contexts(&idx, side, &r, &ctx);
            for c in 0..16u8 {
                let sub: Vec<u32> = syms
                    .iter()
                    .zip(&ctx2)
                    .filter(|(_, &x)| x == c)
                    .map(|(s, _)| *s)
                    .collect();
                hr += entropy(&sub);
            }
            for c in 0..16u8 {
                let sub: Vec<u32> = syms
                    .iter()
                    .zip(&ctx)
                    .filter(|(_, &x)| x == c)
                    .map(|(s, _)| *s)
                    .collect();
                hc += entropy(&sub);
            }
        }
        println!(
            "variant {variant}: zstd9 {:.4} B/sample, zstd19 {:.4}, order0 {:.4}, ctx {:.4}, residual ctx {:.4}",
            z9 as f64 / n as f64,
            z19 as f64 / n as f64,
            h0 / n as f64,
            hc / n as f64,
            hr / n as f64
        );
    }
}
