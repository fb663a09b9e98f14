//! End-to-end: real server, real QUIC, through the linksim relay.

use planet_client::refinement::KEEP_LOD0;
use planet_client::trajectory::{camera_from_keyframe, Keyframe};
use planet_client::tree::Samples;
use planet_client::{Camera, ClientConfig, DrawBlock, FrameOutput, Outgoing};
use planet_core::{BlockId, Datum};
use planet_linksim::{Link, LinkConfig};
use planet_preprocess::db::Sampler;
use planet_session::streaming::StreamingClient;
use planet_testkit::harness::{block_behind_horizon, build_procedural_db, runtime, LocalServer};
use proptest::prelude::*;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// A small procedural database (3 levels, 64-sample blocks), built once.
fn small_db() -> &'static PathBuf {
    static DB: OnceLock<PathBuf> = OnceLock::new();
    DB.get_or_init(|| {
        let dir = tempfile::tempdir().expect("tempdir").keep();
        let p = dir.join("small.planetdb");
        build_procedural_db(&p, 3, 7).expect("procedural build");
        p
    })
}

/// Full elevation grids of every block, decoded from the file directly.
fn truth() -> &'static HashMap<BlockId, Vec<i16>> {
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

fn cam(lat: f64, lon: f64, alt: f64, heading: f64, pitch: f64) -> Camera {
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

fn client_cfg() -> ClientConfig {
    ClientConfig {
        decode_threads: 1,
        ..ClientConfig::default()
    }
}

fn connect(
    rt: &tokio::runtime::Runtime,
    server: &LocalServer,
    addr: std::net::SocketAddr,
) -> StreamingClient {
    let cfg = server.session_config(addr).expect("session config");
    StreamingClient::connect(rt.handle(), cfg, client_cfg(), Duration::from_secs(10))
        .expect("connect")
}

fn idle(sc: &StreamingClient, out: &FrameOutput) -> bool {
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
fn converge(
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
fn assert_exact(sc: &StreamingClient, out: &FrameOutput) {
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
        let t = truth.get(&d.block).expect("block in database");
        for j in 0..side {
            for i in 0..side {
                if d.lod == 0 || (i % 2 == 0 && j % 2 == 0) {
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
fn static_camera() -> Camera {
    cam(46.85, -121.76, 60_000.0, 30.0, -25.0)
}

#[test]
fn static_camera_converges_to_exact_samples() {
    let rt = runtime(2).expect("runtime");
    let server = LocalServer::start(rt.handle(), small_db()).expect("server");
    let link = rt
        .block_on(Link::start_symmetric(
            server.addr(),
            "50mbit,5ms".parse::<LinkConfig>().expect("link"),
        ))
        .expect("link");
    let mut sc = connect(&rt, &server, link.local_addr());
    let camera = static_camera();
    let out = converge(&mut sc, &camera, Duration::from_secs(30), |_, _| {});
    assert_exact(&sc, &out);
    assert!(sc.bytes_received() > 0);
    sc.close();
}

#[test]
fn no_request_behind_the_horizon() {
    let rt = runtime(2).expect("runtime");
    let server = LocalServer::start(rt.handle(), small_db()).expect("server");
    let link = rt
        .block_on(Link::start_symmetric(
            server.addr(),
            "50mbit,5ms".parse::<LinkConfig>().expect("link"),
        ))
        .expect("link");
    let mut sc = connect(&rt, &server, link.local_addr());
    let h = sc.header().clone();
    let datum = h.datum;
    let r_occ = datum.polar_radius() + (h.min_elevation as f64).min(0.0);
    // Low cameras looking at the horizon in every direction, and one higher.
    let mut checked = 0usize;
    let mut drawn_checked = 0usize;
    let (h_min, h_max) = (h.min_elevation as f64, h.max_elevation as f64);
    let mut check = |camera: &Camera, sends: &[Outgoing], drawn: &[DrawBlock]| {
        // Nothing behind the horizon is drawn either (with the database's
        // whole elevation range, a block found hidden is certainly hidden).
        for d in drawn {
            let hidden = block_behind_horizon(&datum, camera.eye, d.block, h_min, h_max, r_occ, 17);
            assert!(
                !hidden,
                "{:?} drawn behind the horizon from {:?}",
                d.block, camera.eye
            );
            drawn_checked += 1;
        }
        for s in sends {
            let hidden = block_behind_horizon(
                &datum,
                camera.eye,
                s.block,
                s.record.min_elevation as f64,
                s.record.max_elevation as f64,
                r_occ,
                17,
            );
            assert!(
                !hidden,
                "request for {:?} ({:?}, forced {}) behind the horizon from {:?}",
                s.block, s.tree, s.forced, camera.eye
            );
            checked += 1;
        }
    };
    let start = Instant::now();
    let mut last = Instant::now();
    let mut t = 0.0;
    while start.elapsed() < Duration::from_secs(8) {
        std::thread::sleep(Duration::from_millis(10));
        let dt = last.elapsed().as_secs_f64();
        last = Instant::now();
        t += dt;
        let camera = if t < 6.0 {
            cam(46.85, -121.76, 3000.0, t * 60.0, 5.0)
        } else {
            cam(0.0, 179.9, 150_000.0, t * 90.0, -10.0)
        };
        let out = sc.frame(&camera, dt);
        check(&camera, &out.send, &out.draw);
    }
    assert!(checked > 20, "too few requests checked ({checked})");
    assert!(
        drawn_checked > 100,
        "too few drawn blocks checked ({drawn_checked})"
    );
    eprintln!("horizon: {checked} requests and {drawn_checked} drawn blocks checked");
    sc.close();
}

#[test]
fn server_restart_is_survived() {
    let rt = runtime(2).expect("runtime");
    let mut server = LocalServer::start(rt.handle(), small_db()).expect("server");
    let link = rt
        .block_on(Link::start_symmetric(
            server.addr(),
            "20mbit,10ms".parse::<LinkConfig>().expect("link"),
        ))
        .expect("link");
    let mut sc = connect(&rt, &server, link.local_addr());
    let camera = static_camera();
    // Stream a little, then stop the server mid-stream.
    for _ in 0..15 {
        std::thread::sleep(Duration::from_millis(10));
        sc.frame(&camera, 0.01);
    }
    server.stop();
    let down = Instant::now();
    while down.elapsed() < Duration::from_millis(700) {
        std::thread::sleep(Duration::from_millis(10));
        let out = sc.frame(&camera, 0.01);
        sc.client
            .tree()
            .validate()
            .expect("tree while disconnected");
        assert!(!out.draw.is_empty(), "the tree is kept while disconnected");
    }
    server.restart().expect("restart on the same port");
    // The session reconnects by itself (with backoff), whether or not the
    // view still needs data.
    let up = Instant::now();
    while sc.counters().connects < 2 && up.elapsed() < Duration::from_secs(30) {
        std::thread::sleep(Duration::from_millis(10));
        sc.frame(&camera, 0.01);
    }
    let out = converge(&mut sc, &camera, Duration::from_secs(40), |_, _| {});
    assert!(
        sc.counters().connects >= 2,
        "reconnected: {:?}",
        sc.counters()
    );
    assert_exact(&sc, &out);
    sc.close();
}

#[test]
fn lossy_reordering_link_converges() {
    let rt = runtime(2).expect("runtime");
    let server = LocalServer::start(rt.handle(), small_db()).expect("server");
    let cfg: LinkConfig = "20mbit,10ms,5%loss,5%reorder".parse().expect("link");
    let link = rt
        .block_on(Link::start(
            server.addr(),
            cfg.clone().with_seed(3),
            cfg.with_seed(4),
        ))
        .expect("link");
    let mut sc = connect(&rt, &server, link.local_addr());
    let out = converge(
        &mut sc,
        &static_camera(),
        Duration::from_secs(40),
        |_, _| {},
    );
    assert_exact(&sc, &out);
    assert!(
        link.stats().packets_dropped_loss > 0,
        "the link lost packets"
    );
    sc.close();
}

#[test]
fn blackhole_then_recovery_converges() {
    let rt = runtime(2).expect("runtime");
    let server = LocalServer::start(rt.handle(), small_db()).expect("server");
    let link = rt
        .block_on(Link::start_symmetric(
            server.addr(),
            "10mbit,20ms".parse::<LinkConfig>().expect("link"),
        ))
        .expect("link");
    let mut sc = connect(&rt, &server, link.local_addr());
    let camera = static_camera();
    for _ in 0..10 {
        std::thread::sleep(Duration::from_millis(10));
        sc.frame(&camera, 0.01);
    }
    link.set_blackhole(true);
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_secs(2) {
        std::thread::sleep(Duration::from_millis(10));
        sc.frame(&camera, 0.01);
        sc.client
            .tree()
            .validate()
            .expect("tree during the blackhole");
    }
    link.set_blackhole(false);
    let out = converge(&mut sc, &camera, Duration::from_secs(40), |_, _| {});
    assert_exact(&sc, &out);
    assert!(link.stats().packets_dropped_blackhole > 0);
    sc.close();
}

#[derive(Debug, Clone)]
struct Move {
    lat: f64,
    lon: f64,
    alt: f64,
    heading: f64,
    pitch: f64,
    frames: usize,
}

fn moves() -> impl Strategy<Value = Vec<Move>> {
    prop::collection::vec(
        (
            -89.0f64..89.0,
            -180.0f64..180.0,
            3.0f64..7.3,
            0.0f64..360.0,
            -90.0f64..10.0,
            1usize..12,
        )
            .prop_map(|(lat, lon, la, heading, pitch, frames)| Move {
                lat,
                lon,
                alt: 10f64.powf(la),
                heading,
                pitch,
                frames,
            }),
        1..8,
    )
}

#[test]
fn random_camera_moves_keep_the_tree_valid() {
    let rt = runtime(2).expect("runtime");
    let server = LocalServer::start(rt.handle(), small_db()).expect("server");
    let mut runner = proptest::test_runner::TestRunner::new(ProptestConfig {
        cases: 4,
        failure_persistence: None,
        ..ProptestConfig::default()
    });
    runner
        .run(&moves(), |ms| {
            let mut sc = connect(&rt, &server, server.addr());
            for m in &ms {
                let camera = cam(m.lat, m.lon, m.alt, m.heading, m.pitch);
                for _ in 0..m.frames {
                    std::thread::sleep(Duration::from_millis(5));
                    let out = sc.frame(&camera, 0.005);
                    prop_assert!(
                        sc.client.tree().validate().is_ok(),
                        "{:?}",
                        sc.client.tree().validate()
                    );
                    for d in &out.draw {
                        prop_assert!(sc
                            .client
                            .tree()
                            .elevation()
                            .get(&d.block)
                            .is_some_and(|n| n.is_leaf()));
                    }
                }
            }
            sc.close();
            Ok(())
        })
        .expect("property");
}
