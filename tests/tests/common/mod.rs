//! Helpers shared by the end-to-end suites: the small database and its
//! truth, cameras, the converge loop and the exactness check.
#![allow(dead_code)] // not every suite uses every helper

use planet_client::refinement::KEEP_LOD0;
use planet_client::trajectory::{camera_from_keyframe, Keyframe};
use planet_client::tree::Samples;
use planet_client::{Camera, ClientConfig, DrawBlock, FrameOutput};
use planet_core::{BlockId, Datum};
use planet_preprocess::db::Sampler;
use planet_session::streaming::StreamingClient;
use planet_testkit::harness::{build_procedural_db, LocalServer};
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// A small procedural database (3 levels, 64-sample blocks), built once.
pub fn small_db() -> &'static PathBuf {
    static DB: OnceLock<PathBuf> = OnceLock::new();
    DB.get_or_init(|| {
        let dir = tempfile::tempdir().expect("tempdir").keep();
        let p = dir.join("small.planetdb");
        build_procedural_db(&p, 3, 7).expect("procedural build");
        p
    })
}

/// Full elevation grids of every block, decoded from the file directly.
pub fn truth() -> &'static HashMap<BlockId, Vec<i16>> {
    static T: OnceLock<HashMap<BlockId, Vec<i16>>> = OnceLock::new();
    T.get_or_init(|| {
        let s = Sampler::open(small_db()).expect("open db");
        let mut m = HashMap::new();
        s.for_each_elevation_block(|b, g| {
            m.insert(b, g.to_vec());
        })
        .expect("decode db");
        m
    })
}

pub fn cam(lat: f64, lon: f64, alt: f64, heading: f64, pitch: f64) -> Camera {
    camera_from_keyframe(
        &Keyframe {
            t: 0.0,
            lat_deg: lat,
            lon_deg: lon,
            alt_m: alt,
            heading_deg: heading,
            pitch_deg: pitch,
        },
        &Datum::WGS84,
        60f64.to_radians(),
        16.0 / 9.0,
        720.0,
    )
}

pub fn client_cfg() -> ClientConfig {
    ClientConfig {
        decode_threads: 1,
        ..ClientConfig::default()
    }
}

pub fn connect(
    rt: &tokio::runtime::Runtime,
    server: &LocalServer,
    addr: std::net::SocketAddr,
) -> StreamingClient {
    let cfg = server.session_config(addr).expect("session config");
    StreamingClient::connect(rt.handle(), cfg, client_cfg(), Duration::from_secs(10))
        .expect("connect")
}

pub fn idle(sc: &StreamingClient, out: &FrameOutput) -> bool {
    let c = &sc.client;
    out.send.is_empty()
        && out.cancel.is_empty()
        && c.queue().in_flight() == 0
        && c.pending_ops().is_empty()
        && c.decoding() == 0
        && out.stats.refines_applied == 0
        && out.stats.splits == 0
        && out.stats.merges == 0
}

/// Runs frames (every ~10 ms, real time) until 10 idle frames in a row; the
/// last frame's output. Panics after `limit`.
pub fn converge(
    sc: &mut StreamingClient,
    camera: &Camera,
    limit: Duration,
    mut each: impl FnMut(&StreamingClient, &FrameOutput),
) -> FrameOutput {
    let start = Instant::now();
    let mut last = Instant::now();
    let mut quiet = 0;
    loop {
        std::thread::sleep(Duration::from_millis(10));
        let dt = last.elapsed().as_secs_f64();
        last = Instant::now();
        let out = sc.frame(camera, dt);
        each(sc, &out);
        if idle(sc, &out) {
            quiet += 1;
            if quiet >= 10 {
                return out;
            }
        } else {
            quiet = 0;
        }
        assert!(
            start.elapsed() < limit,
            "no convergence in {limit:?}: in flight {}, connected {}, counters {:?}, last error {:?}",
            sc.client.queue().in_flight(),
            sc.is_connected(),
            sc.counters(),
            sc.client.last_error()
        );
    }
}

/// Every drawn block is converged (its screen-space error within the
/// client's default tolerance, or nothing finer exists), at no finer a LOD
/// than it needs, and its samples are exactly the database's (all samples
/// at LOD 0, the even ones at LOD 1).
/// The samples a drawn block shows (every sample at LOD 0, the even ones
/// at LOD 1) are the database's, exactly.
pub fn assert_drawn_samples_exact(
    d: &DrawBlock,
    grid: &[i16],
    truth: &HashMap<BlockId, Vec<i16>>,
    side: usize,
) {
    let t = truth.get(&d.block).expect("block in database");
    let step = if d.lod == 0 { 1 } else { 2 };
    for j in (0..side).step_by(step) {
        for i in (0..side).step_by(step) {
            assert_eq!(
                grid[j * side + i],
                t[j * side + i],
                "{:?} sample ({i},{j}) at LOD {}",
                d.block,
                d.lod
            );
        }
    }
}

pub fn assert_exact(sc: &StreamingClient, out: &FrameOutput) {
    let truth = truth();
    let et = sc.client.tree().elevation();
    let w = et.width;
    let side = w + 1;
    let tol = sc.client.tolerance();
    assert!(!out.draw.is_empty());
    let mut lod0 = 0;
    let mut full_records = 0;
    for d in &out.draw {
        let node = et.get(&d.block).expect("drawn node");
        let finest = d.lod == 0 && node.child_refs.as_ref().is_some_and(|c| c.is_empty());
        assert!(
            d.screen_error <= tol || finest,
            "{:?} drawn at LOD {} with {} px > {tol} px and not the finest",
            d.block,
            d.lod,
            d.screen_error
        );
        // The default policy reports the first LOD's error as importance:
        // LOD 0 is drawn only where LOD 1 would be off by more than half
        // the tolerance (the hysteresis of client/src/refinement.rs).
        if d.lod == 0 {
            assert!(
                d.importance > tol * KEEP_LOD0,
                "{:?} drawn at LOD 0 though LOD 1 is off by {} px only",
                d.block,
                d.importance
            );
        }
        let Some(Samples::Elevation(grid)) = &node.samples else {
            panic!("leaf without samples")
        };
        assert_drawn_samples_exact(d, grid, truth, side);
        lod0 += usize::from(d.lod == 0);
        // A block below a root drawn at LOD 1 shows its parent's LOD 0
        // record (a split block's full grid is its children's LOD 1): since
        // colour refines by texel size beyond the geometry, the view may be
        // all such blocks.
        full_records += usize::from(d.lod == 0 || d.block.level > 0);
    }
    assert!(
        full_records > 0,
        "no record checked at full resolution: the view tests too little"
    );
    let levels: std::collections::BTreeSet<u8> = out.draw.iter().map(|d| d.block.level).collect();
    eprintln!(
        "exact: {} drawn blocks ({lod0} at LOD 0, levels {levels:?}), {} bytes, counters {:?}",
        out.draw.len(),
        sc.bytes_received(),
        sc.counters()
    );
    sc.client.tree().validate().expect("tree invariants");
}

/// A view that needs the finest level of the small database within the
/// default 1 px tolerance near the camera and coarser ones away from it:
/// 60 km above the ground looking 25° down.
pub fn static_camera() -> Camera {
    cam(46.85, -121.76, 60_000.0, 30.0, -25.0)
}
