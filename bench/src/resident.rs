//! `planet-bench resident`: CPU time of `Client::frame` (selection and
//! scheduling: apply finished work, traverse both trees, importance, LOD
//! selection, triggers, request queue, split/merge selection) with at least
//! 10 000 resident blocks. The tree is grown over a synthetic database
//! (`planet_testkit::testdb`, no network, inline decoding), then frames are
//! timed with the thread's CPU clock for a static camera, a camera turning
//! on the spot (the eye stays: importance is reused, only visibility
//! changes) and a moving camera (the eye drifts 0.01° of latitude, about
//! 1.1 km, per frame: everything is recomputed and the tree changes).

use crate::thread_cpu;
use anyhow::{bail, Result};
use clap::Args;
use planet_client::quality::{QualityConfig, QualityMode};
use planet_client::request_queue::QueueConfig;
use planet_client::trajectory::{camera_from_keyframe, Keyframe};
use planet_client::{Camera, Client, ClientConfig, FrameOutput, Policy};
use planet_testkit::testdb::{FakeServer, TestDb, TestDbConfig};
use std::time::Instant;

#[derive(Args, Debug, Clone)]
pub struct ResidentArgs {
    /// Resident nodes (both trees) to reach before timing.
    #[arg(long, default_value_t = 10_000)]
    pub min_blocks: usize,
    /// Elevation block width of the synthetic database.
    #[arg(long, default_value_t = 16)]
    pub width: usize,
    /// Deepest level of the synthetic database.
    #[arg(long, default_value_t = 6)]
    pub levels: u8,
    /// Client policy (the selection and scheduling timed).
    #[arg(long, default_value = "ours")]
    pub policy: Policy,
    /// Pixel tolerance: the workload's size. The synthetic database is
    /// smooth (a few sines), so reaching 10 000 resident blocks over it
    /// takes a tolerance far below a pixel; the work per frame depends on
    /// the number of blocks, not on why they are resident.
    #[arg(long, default_value_t = 1e-5)]
    pub max_sse: f64,
    /// Quality factor of the thesis policy (high: many blocks).
    #[arg(long, default_value_t = 1e7)]
    pub qf: f64,
    /// Frames timed per camera.
    #[arg(long, default_value_t = 300)]
    pub frames: usize,
    /// Time only the cameras whose name contains this (e.g. `moving`, for
    /// profiling one case).
    #[arg(long)]
    pub only: Option<String>,
}

/// One timed frame, apart from the frames that grow the tree, so that a
/// profiler can collect these alone:
/// `valgrind --tool=callgrind --toggle-collect='*timed_frame*'`.
#[inline(never)]
fn timed_frame(client: &mut Client, camera: &Camera) -> FrameOutput {
    client.frame(camera, 1.0 / 30.0)
}

fn stats(v: &mut [f64]) -> (f64, f64, f64, f64) {
    v.sort_by(f64::total_cmp);
    let n = v.len().max(1);
    let mean = v.iter().sum::<f64>() / n as f64;
    let med = v[n / 2];
    let p99 = v[((n as f64 * 0.99) as usize).min(n - 1)];
    (mean, med, p99, v[n - 1])
}

pub fn run(a: ResidentArgs) -> Result<()> {
    let t0 = Instant::now();
    let db = TestDb::build(TestDbConfig {
        radius: 6_371_000.0,
        elevation_width: a.width,
        elevation_max_level: a.levels,
        colour: Some((a.width * 2, a.levels.saturating_sub(1))),
    });
    eprintln!(
        "synthetic database: {} elevation + {} colour blocks, {:.1} MB, built in {:.1} s",
        db.elevation.len(),
        db.colour.len(),
        db.file.len() as f64 / 1e6,
        t0.elapsed().as_secs_f64()
    );
    let base = ClientConfig::for_policy(a.policy, a.max_sse);
    let cfg = ClientConfig {
        queue: QueueConfig {
            max_in_flight: 64,
            ..base.queue
        },
        tree_ops_per_frame: 256,
        decode_threads: 0,
        quality: QualityConfig {
            mode: QualityMode::Fixed,
            initial: a.qf,
            ..QualityConfig::default()
        },
        ..base
    };
    let mut client = Client::new(db.header.clone(), cfg)?;
    let mut server = FakeServer::new(1);
    let cam_at = |heading: f64, lat: f64| {
        camera_from_keyframe(
            &Keyframe {
                t: 0.0,
                lat_deg: lat,
                lon_deg: 10.0,
                alt_m: 9_000_000.0,
                heading_deg: heading,
                pitch_deg: -90.0,
            },
            &planet_core::Datum::Sphere {
                radius: 6_371_000.0,
            },
            60f64.to_radians(),
            16.0 / 9.0,
            1080.0,
        )
    };
    let cam = |heading: f64| cam_at(heading, 30.0);
    // Grow the tree until it is stable.
    let camera = cam(0.0);
    let mut quiet = 0;
    let mut n = 0;
    while quiet < 5 {
        for (id, bytes) in server.tick(&db) {
            client.deliver(id, Ok(bytes));
        }
        let out = client.frame(&camera, 1.0 / 30.0);
        server.submit(&out);
        let busy = !out.send.is_empty()
            || server.pending() > 0
            || !client.pending_ops().is_empty()
            || out.stats.refines_applied > 0;
        quiet = if busy { 0 } else { quiet + 1 };
        n += 1;
        if n > 20_000 {
            bail!("the tree did not stabilise");
        }
    }
    let nodes = client.tree().node_count();
    let elev = client.tree().elevation().len();
    let out = client.frame(&camera, 1.0 / 30.0);
    eprintln!(
        "stable after {n} frames: {nodes} resident nodes ({elev} elevation), {} drawn blocks, {} triangles",
        out.draw.len(),
        out.stats.triangles
    );
    if nodes < a.min_blocks {
        bail!(
            "only {nodes} resident nodes (< {}): lower --max-sse (or raise --qf with --policy thesis) or raise --levels",
            a.min_blocks
        );
    }
    let mut report = Vec::new();
    for (name, turn, drift) in [
        ("static camera", 0.0, 0.0),
        ("turning camera (0.5°/frame)", 0.5, 0.0),
        ("moving camera (0.01° lat/frame)", 0.0, 0.01),
    ] {
        if a.only.as_ref().is_some_and(|o| !name.contains(o.as_str())) {
            continue;
        }
        let mut v = Vec::with_capacity(a.frames);
        let mut wall = Vec::with_capacity(a.frames);
        let rebuilds = client.selector().rebuilds();
        let mut ops = 0;
        for k in 0..a.frames {
            for (id, bytes) in server.tick(&db) {
                client.deliver(id, Ok(bytes));
            }
            let camera = cam_at(turn * k as f64, 30.0 + drift * k as f64);
            let w0 = Instant::now();
            let c0 = thread_cpu();
            let out = timed_frame(&mut client, &camera);
            v.push(thread_cpu().saturating_sub(c0).as_secs_f64() * 1e3);
            wall.push(w0.elapsed().as_secs_f64() * 1e3);
            ops += out.stats.splits + out.stats.merges + out.stats.refines_applied;
            server.submit(&out);
            client.recycle(out.draw);
        }
        eprintln!(
            "{name}: {ops} splits + merges + refines, {} selection cache rebuilds",
            client.selector().rebuilds() - rebuilds
        );
        let (mean, med, p99, max) = stats(&mut v);
        let (wmean, _, _, _) = stats(&mut wall);
        let line = format!(
            "| {name} | {} | {} | {mean:.3} | {med:.3} | {p99:.3} | {max:.3} | {wmean:.3} |",
            client.tree().node_count(),
            client.tree().elevation().len(),
        );
        report.push(line);
    }
    println!("| camera | resident nodes | elevation nodes | CPU mean (ms) | median | p99 | max | wall mean (ms) |");
    println!("|---|---|---|---|---|---|---|---|");
    for l in report {
        println!("{l}");
    }
    Ok(())
}
