//! Cost of crack fixing at a fixed triangle budget (thesis §4.6, Table 4.2:
//! a few per cent at about 2 M triangles per frame).
//!
//! `cargo bench -p planet-render --bench crack_fixing` renders the same scene,
//! about 2 M triangles of W = 64 blocks over the whole planet with LOD 0 and
//! LOD 1 mixed (so about half the edges need stitching), alternately with
//! and without edge strips, and prints a table: the renderer's CPU time per
//! frame (encoding, on the CPU), the whole frame time (submit to completion:
//! on lavapipe that is the rasterisation on the CPU too; on a GPU it is GPU
//! time plus driver overhead) and triangles per second. Frames alternate
//! between the two settings so that drift in machine load hits both equally.
//! `PLANET_BENCH_FRAMES` sets the frames per setting (default 12).

use planet_core::{BlockId, Datum, Edge, Face};
use planet_render::mesh::sample_position;
use planet_render::{BlockMesh, Camera, DrawBlock, HeadlessRenderer, RenderSettings};
use std::collections::HashMap;
use std::sync::Arc;

const W: usize = 64;
const LEVEL: u8 = 3;
const SIZE: u32 = 1024;

fn relief(d: [f64; 3]) -> f64 {
    2500.0 * (40.0 * d[0]).sin() * (37.0 * d[1] + 1.0).sin() + 800.0 * (90.0 * d[2]).cos()
}

fn lod_of(id: BlockId) -> u8 {
    ((id.key().wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40) % 2) as u8
}

fn scene(datum: &Datum) -> Vec<DrawBlock> {
    let unit = Datum::Sphere { radius: 1.0 };
    let mut leaves = HashMap::new();
    let n = 1u32 << LEVEL;
    for f in Face::ALL {
        for y in 0..n {
            for x in 0..n {
                let id = BlockId::new(f, LEVEL, x, y).expect("block in range");
                leaves.insert(id, lod_of(id));
            }
        }
    }
    let mut blocks = Vec::new();
    for (&id, &lod) in &leaves {
        let grid: Vec<i16> = (0..(W + 1) * (W + 1))
            .map(|k| {
                relief(sample_position(&unit, id, W, k % (W + 1), k / (W + 1), 0.0)).round() as i16
            })
            .collect();
        let mut diff = [0u8; 4];
        for e in Edge::ALL {
            let (nb, _) = id.neighbour(e);
            // Same level everywhere: the difference is the LOD difference.
            diff[e as usize] = (leaves[&nb] as i32 - lod as i32).max(0) as u8;
        }
        blocks.push(DrawBlock {
            id,
            lod,
            neighbour_lod_diff: diff,
            mesh: Arc::new(BlockMesh::build(datum, id, W, &grid, 1.0, 0.0)),
            colour: None,
        });
    }
    blocks
}

struct Sample {
    cpu: Vec<f64>,
    frame: Vec<f64>,
    triangles: u64,
}

fn main() {
    let frames: usize = std::env::var("PLANET_BENCH_FRAMES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(12);
    let datum = Datum::WGS84;
    let settings = RenderSettings::for_planet(&datum, -3500.0, 3500.0);
    let mut hr = match HeadlessRenderer::with_settings(SIZE, SIZE, settings) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("NOTE: no wgpu adapter ({e}); nothing to measure");
            return;
        }
    };
    let adapter = hr.adapter_name.clone();
    let blocks = scene(&datum);
    let a = datum.equatorial_radius();
    let camera = Camera {
        fov_y: 50f64.to_radians(),
        ..Camera::look_at(
            glam::DVec3::new(2.2, 1.3, 1.6) * a,
            glam::DVec3::ZERO,
            glam::DVec3::Z,
        )
    };
    let mut results = [
        Sample {
            cpu: vec![],
            frame: vec![],
            triangles: 0,
        },
        Sample {
            cpu: vec![],
            frame: vec![],
            triangles: 0,
        },
    ];
    // Two warm-up frames per setting (uploads happen there), then alternate.
    for round in 0..frames + 2 {
        for (k, fixing) in [true, false].into_iter().enumerate() {
            hr.renderer.settings.crack_fixing = fixing;
            let t = match hr.time_frame(&camera, &blocks) {
                Ok(t) => t,
                Err(e) => {
                    eprintln!("error: {e}");
                    std::process::exit(1);
                }
            };
            if round >= 2 {
                let s = &mut results[k];
                s.cpu.push(t.encode_s);
                s.frame.push(t.frame_s);
                s.triangles = hr.renderer.stats.triangles;
            }
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    println!("adapter: {adapter}; {} blocks of W = {W}, {SIZE}x{SIZE}, {frames} frames per setting (medians)", blocks.len());
    println!("| crack fixing | triangles/frame | renderer CPU/frame | frame time | triangles/s |");
    println!("|---|---|---|---|---|");
    let mut tps = [0.0; 2];
    for (k, name) in ["on", "off"].iter().enumerate() {
        let s = &mut results[k];
        let cpu = median(&mut s.cpu);
        let frame = median(&mut s.frame);
        tps[k] = s.triangles as f64 / frame;
        println!(
            "| {name} | {} | {:.3} ms | {:.3} ms | {:.1} M |",
            s.triangles,
            cpu * 1e3,
            frame * 1e3,
            tps[k] / 1e6
        );
    }
    println!(
        "crack fixing costs {:+.1} % of triangle throughput (thesis: about 4 % at 2 M triangles)",
        (tps[1] / tps[0] - 1.0) * 100.0
    );
}
