//! End-to-end tests of the client against the synthetic database and the
//! fake server (no network).

mod common;

use common::*;
use glam::DVec3;
use planet_client::importance::{block_distance, importance, selected_lod, wants_split};
use planet_client::quality::{QualityConfig, QualityMode};
use planet_client::refinement::{Footprint, Kind};
use planet_client::tree::Samples;
use planet_client::visibility::{segment_hits_ball, View};
use planet_client::{Camera, Client, ClientConfig, FrameOutput, Policy, TransportError};
use planet_core::cube::FaceCoord;
use planet_core::format::Tree;
use planet_core::lod::is_first_lod;
use planet_core::BlockId;
use planet_testkit::converge;
use planet_testkit::testdb::{FakeServer, TestDb, TestDbConfig};
use proptest::prelude::*;

fn client(threads: usize) -> Client {
    fixed_qf_client(1e4, threads)
}

fn step(c: &mut Client, s: &mut FakeServer, cam: &Camera) -> FrameOutput {
    converge::step(c, s, db(), cam)
}

/// Run until nothing is sent, in flight, decoding or pending for 3 frames.
fn converge(c: &mut Client, s: &mut FakeServer, cam: &Camera, max: usize) -> FrameOutput {
    converge::converge(c, s, db(), cam, max)
}

fn ground_camera() -> Camera {
    let eye = surface(DVec3::new(1.0, 0.1, 0.2), 150_000.0);
    let target = surface(DVec3::new(1.0, 0.3, 0.25), 0.0);
    Camera::look_at(eye, target, eye.normalize())
}

/// Independent check: some point of the block (dense grid at its min and max
/// elevation) is in front of the eye and not hidden by a slightly smaller
/// min sphere.
fn maybe_visible(block: BlockId, cam: &Camera, r_min: f64) -> bool {
    let r = db().refs[&(Tree::Elevation, block)];
    let (s0, t0, s1, t1) = block.extent();
    let f = cam.forward.normalize();
    let n = 16;
    let mut dirs: Vec<[f64; 3]> = (0..=n)
        .flat_map(|j| {
            (0..=n).map(move |i| {
                FaceCoord {
                    face: block.face,
                    s: s0 + (s1 - s0) * i as f64 / n as f64,
                    t: t0 + (t1 - t0) * j as f64 / n as f64,
                }
                .direction()
            })
        })
        .collect();
    // The block's slab right above or below the eye (a grid of a coarse
    // block misses it, and it is in view looking up from under `h_max`).
    let under = FaceCoord::from_direction(cam.eye.to_array());
    if under.face == block.face && (s0..=s1).contains(&under.s) && (t0..=t1).contains(&under.t) {
        dirs.push(under.direction());
    }
    for d in dirs {
        for h in [r.min_elevation as f64, r.max_elevation as f64] {
            let p = DVec3::from_array(db().header.datum.position(d, h));
            let front = f.dot(p - cam.eye) > 0.0;
            if front && !segment_hits_ball(cam.eye, p, r_min * 0.995) {
                return true;
            }
        }
    }
    false
}

fn check_exact(c: &Client, out: &FrameOutput) {
    let et = c.tree().elevation();
    let w = et.width;
    for d in &out.draw {
        let n = et.get(&d.block).expect("drawn node");
        let Some(Samples::Elevation(g)) = &n.samples else {
            panic!("no samples")
        };
        let truth = &db().elevation[&d.block];
        for j in 0..=w {
            for i in 0..=w {
                if n.lod == 0 || is_first_lod(i, j) {
                    assert_eq!(g[j * (w + 1) + i], truth[j * (w + 1) + i], "{:?}", d.block);
                }
            }
        }
    }
    if let Some(ct) = c.tree().colour() {
        for n in ct.nodes() {
            if let Some(Samples::Colour { lod1, full }) = &n.samples {
                let truth = &db().colour[&n.id];
                assert_eq!(*lod1, planet_core::lod::colour_filter(truth, ct.width));
                if let Some(f) = full {
                    assert_eq!(f, truth);
                }
            }
        }
    }
}

fn static_camera_converges(threads: usize) {
    let mut c = client(threads);
    let mut s = FakeServer::new(2);
    let cam = ground_camera();
    let out = converge(&mut c, &mut s, &cam, 400);
    check_exact(&c, &out);
    let et = c.tree().elevation();
    let deepest = out.draw.iter().map(|d| d.block.level).max().unwrap_or(0);
    assert!(deepest >= 3, "deepest drawn level {deepest}");
    for d in &out.draw {
        let n = et.get(&d.block).expect("node");
        let b = n.bounds.as_ref().expect("bounds");
        let imp = importance(
            block_distance(cam.eye, b.centre, b.radius),
            b.radius,
            et.width as f64,
            c.quality_factor(),
        );
        // The LOD it needs is loaded...
        assert!(n.lod <= selected_lod(imp), "{:?} needs LOD 0", d.block);
        // ...and it does not need to split.
        if wants_split(imp) {
            assert!(
                c.tree().can_split(Tree::Elevation, &d.block).is_err(),
                "{:?}",
                d.block
            );
        }
        // Crack-fixing info: lodDiff consistent with the erratum formula.
        for nb in d.neighbours.iter().flatten() {
            let diff =
                (nb.lod as i32 - d.lod as i32) + (d.block.level as i32 - nb.block.level as i32);
            assert_eq!(nb.lod_diff, diff);
        }
        assert!(d.colour.is_some());
    }
    assert!(
        out.stats.totals.relevant_ratio() > 0.5,
        "{:?}",
        out.stats.totals
    );
    assert!(out.stats.max_screen_error.is_finite());
}

#[test]
fn static_camera_converges_inline() {
    static_camera_converges(0);
}

#[test]
fn static_camera_converges_threaded() {
    static_camera_converges(2);
}

#[test]
fn nothing_hidden_is_requested() {
    let cams = [
        ground_camera(),
        {
            // Low, looking along the horizon.
            let eye = surface(DVec3::new(0.2, -1.0, 0.3), 3000.0);
            let east = DVec3::Z.cross(eye).normalize();
            Camera::look_at(eye, eye + east, eye.normalize())
        },
        {
            // High above a pole, looking down.
            let eye = DVec3::new(0.0, 0.0, 1.2e7);
            Camera::look_at(eye, DVec3::ZERO, DVec3::X)
        },
        {
            // Looking away from the planet.
            let eye = surface(DVec3::new(-1.0, 0.2, -0.4), 20_000.0);
            Camera::look_at(eye, eye * 2.0, DVec3::Z)
        },
    ];
    for (ci, cam) in cams.into_iter().enumerate() {
        let mut c = client(0);
        let mut s = FakeServer::new(1);
        let (r_min, _) = c.radii();
        for _ in 0..120 {
            step(&mut c, &mut s, &cam);
        }
        let mut forced = 0;
        for o in &s.log {
            if o.forced {
                forced += 1;
                continue;
            }
            assert!(
                maybe_visible(o.block, &cam, r_min),
                "{:?} requested but hidden (camera {ci})",
                o.block
            );
        }
        assert!(forced <= s.log.len());
    }
}

#[test]
fn irrelevant_requests_are_cancelled_and_late_responses_dropped() {
    let mut c = client(0);
    let mut s = FakeServer::new(1_000_000); // never answers by itself
    let cam = ground_camera();
    let mut sent = vec![];
    // Load the roots' LOD 0 by hand so deeper requests follow.
    let mut quick = FakeServer::new(0);
    for _ in 0..40 {
        let out = step(&mut c, &mut quick, &cam);
        if out.stats.nodes > 30 {
            break;
        }
    }
    for _ in 0..20 {
        let out = c.frame(&cam, 1.0 / 60.0);
        s.submit(&out);
        sent.extend(out.send.iter().copied());
        if sent.len() >= 4 {
            break;
        }
    }
    assert!(!sent.is_empty());
    // Turn to the other side of the planet: the in-flight requests are no
    // longer triggered and get cancelled within the grace period.
    let away = Camera::look_at(-cam.eye.normalize() * 1e9, -cam.eye * 6.0, DVec3::Z);
    let mut cancelled = vec![];
    for _ in 0..200 {
        let out = c.frame(&away, 1.0 / 60.0);
        cancelled.extend(out.cancel.iter().copied());
        c.tree().validate().expect("valid");
        if c.tree().node_count() == 12 && c.queue().in_flight() == 0 {
            break;
        }
    }
    assert!(
        sent.iter().all(|o| cancelled.contains(&o.id)),
        "all cancelled"
    );
    assert_eq!(c.tree().node_count(), 12, "merged back to the roots");
    // Late responses (cancelled ids; blocks merged away) are dropped safely.
    let before = c.totals();
    let mut late_bytes = 0;
    for o in &sent {
        let bytes = db().read(&o.record).expect("record");
        late_bytes += bytes.len() as u64;
        c.deliver(o.id, Ok(bytes));
    }
    let out = c.frame(&away, 1.0 / 60.0);
    c.tree().validate().expect("valid");
    assert_eq!(out.stats.totals.refines_applied, before.refines_applied);
    assert_eq!(
        out.stats.totals.bytes_dropped - before.bytes_dropped,
        late_bytes
    );
}

#[test]
fn duplicate_response_is_dropped() {
    // A response whose id is still known but whose block has LOD 0 already or
    // is gone: `deliver` drops it without decoding.
    let mut c = client(0);
    let mut s = FakeServer::new(0);
    let cam = ground_camera();
    let out = step(&mut c, &mut s, &cam);
    assert!(!out.send.is_empty());
    // Frame 2 sends more; answer one with the bytes, then again (duplicate).
    let first = out.send[0];
    let bytes = db().read(&first.record).expect("record");
    let before = c.totals();
    c.deliver(first.id, Ok(bytes.clone()));
    let out = c.frame(&cam, 1.0 / 60.0);
    assert_eq!(
        out.stats.totals.bytes_dropped,
        before.bytes_dropped + bytes.len() as u64
    );
    c.tree().validate().expect("valid");
}

#[test]
fn corrupt_and_wrong_records_are_rejected_and_re_requested() {
    let mut c = client(0);
    let mut s = FakeServer::new(1);
    let cam = ground_camera();
    for r in &db().header.elevation.root_records {
        s.corrupt_once.insert(r.offset);
    }
    // First frame: swap the answers of two requests (wrong block).
    let out = c.frame(&cam, 1.0 / 60.0);
    s.submit(&out);
    assert!(out.send.len() >= 2);
    let (a, b) = (out.send[0], out.send[1]);
    c.deliver(a.id, Ok(db().read(&b.record).expect("b")));
    c.deliver(b.id, Err(TransportError::request("reset")));
    let out = c.frame(&cam, 1.0 / 60.0);
    s.submit(&out);
    assert_eq!(out.stats.records_rejected, 1);
    assert!(c.last_error().is_some());
    let out = converge(&mut c, &mut s, &cam, 400);
    check_exact(&c, &out);
    assert!(out.stats.totals.records_rejected >= 2);
    for (f, r) in db().header.elevation.root_records.iter().enumerate() {
        if s.corrupt_once.contains(&r.offset) {
            continue; // never requested
        }
        let n = s.log.iter().filter(|o| o.record.offset == r.offset).count();
        assert!(n >= 2, "corrupted root {f} requested again");
        let root = c
            .tree()
            .elevation()
            .get(&BlockId::root(planet_core::Face::ALL[f]))
            .expect("root");
        assert!(root.split || root.lod == 0, "root {f} loaded after retry");
    }
    assert!(
        s.corrupt_once.len() < 6,
        "some corrupt record was requested"
    );
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, .. ProptestConfig::default() })]

    /// Any sequence of camera moves keeps the tree valid, and flying away
    /// returns it to the six roots of each tree (no leaks).
    #[test]
    fn camera_moves_keep_tree_valid(
        moves in camera_moves(),
        latency in 0u64..3,
    ) {
        let mut c = client(0);
        let mut s = FakeServer::new(latency);
        for m in &moves {
            let (eye, f) = move_eye_forward(m);
            let cam = Camera::look_at(eye, eye + f, eye.normalize());
            for _ in 0..m.3 * 4 {
                step(&mut c, &mut s, &cam);
                if let Err(e) = c.tree().validate() {
                    prop_assert!(false, "{e}");
                }
            }
        }
        let far = Camera::look_at(DVec3::new(1e9, 0.0, 0.0), DVec3::ZERO, DVec3::Z);
        converge(&mut c, &mut s, &far, 400);
        prop_assert_eq!(c.tree().node_count(), 12);
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 16, .. ProptestConfig::default() })]

    /// Random cameras: no request (other than forced neighbours) is for a
    /// block entirely behind the camera or behind the horizon.
    #[test]
    fn random_cameras_request_nothing_hidden(
        (x, y, z) in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
        alt_log in 2.5f64..7.5,
        (fx, fy, fz) in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
    ) {
        let dir = DVec3::new(x, y, z);
        let dir = if dir.length() < 1e-3 { DVec3::X } else { dir };
        let eye = surface(dir, 10f64.powf(alt_log));
        let f = DVec3::new(fx, fy, fz);
        let f = if f.length() < 1e-3 { -eye } else { f };
        if let Some(b) = hidden_request(eye, f) {
            prop_assert!(false, "{:?} requested but hidden", b);
        }
    }
}

/// The first request (other than forced neighbours) of a client looking
/// from `eye` along `f` for 40 frames that is for a block entirely behind
/// the camera or behind the horizon.
fn hidden_request(eye: DVec3, f: DVec3) -> Option<BlockId> {
    let cam = Camera::look_at(eye, eye + f, eye.normalize());
    let mut c = client(0);
    let mut s = FakeServer::new(1);
    let (r_min, _) = c.radii();
    for _ in 0..40 {
        step(&mut c, &mut s, &cam);
    }
    s.log
        .iter()
        .filter(|o| !o.forced)
        .map(|o| o.block)
        .find(|b| !maybe_visible(*b, &cam, r_min))
}

/// A case the property test above found: 316 m above the datum, looking
/// straight up, the coarse blocks under the eye (their bounding points
/// pushed out up to 2 km over a coarse grid) were requested.
#[test]
fn looking_up_from_low_requests_nothing_below() {
    for dir in [DVec3::NEG_X, DVec3::new(0.3, 0.5, 0.8), DVec3::Z] {
        let eye = surface(dir, 316.3);
        for tilt in [0.0, 0.2, 0.5] {
            let f = eye.normalize() + eye.normalize().any_orthonormal_vector() * tilt;
            assert_eq!(hidden_request(eye, f), None, "eye {eye}, tilt {tilt}");
        }
    }
}

/// Blocks 4 samples wide, levels 0..=5, with colour: a level difference
/// of 1 only (thesis §4.3.3), so splits force coarser neighbours.
fn width4_db() -> TestDb {
    TestDb::build(TestDbConfig {
        elevation_width: 4,
        elevation_max_level: 5,
        colour: Some((8, 3)),
        ..TestDbConfig::default()
    })
}

/// Block width 4 allows a level difference of 1 only (thesis §4.3.3): splits
/// must force coarser neighbours, and the limit holds every frame.
#[test]
fn level_difference_limit_one_is_kept() {
    let db4 = width4_db();
    let cfg = ClientConfig {
        decode_threads: 0,
        quality: QualityConfig {
            mode: QualityMode::Fixed,
            initial: 1e4,
            ..QualityConfig::default()
        },
        ..ClientConfig::for_policy(Policy::Thesis, 1.0)
    };
    let mut c = Client::new(db4.header.clone(), cfg).expect("client");
    assert_eq!(c.tree().max_level_difference(), 1);
    let mut s = FakeServer::new(1);
    let eye = DVec3::new(1.0, 0.02, 0.01).normalize() * (6_371_000.0 + 5_000.0);
    let cam = Camera::look_at(
        eye,
        DVec3::new(1.0, 0.2, 0.02).normalize() * 6_371_000.0,
        eye.normalize(),
    );
    let mut forced = 0;
    for _ in 0..300 {
        let out = c.frame(&cam, 1.0 / 60.0);
        forced += out.send.iter().filter(|o| o.forced).count();
        s.submit(&out);
        for (id, bytes) in s.tick(&db4) {
            c.deliver(id, Ok(bytes));
        }
        c.tree().validate().expect("valid");
    }
    let deepest = c
        .tree()
        .elevation()
        .nodes()
        .map(|n| n.id.level)
        .max()
        .unwrap_or(0);
    assert!(deepest >= 4, "deepest {deepest}");
    assert!(forced > 0, "no neighbour was forced");
}

/// A descending camera with a slow link: requests filtered by the view
/// predicted for their arrival (view_prediction.rs) waste fewer bytes on
/// blocks that left the view than requests for the current view, and the
/// client converges as well once the camera stops.
#[test]
fn predicted_view_requests_waste_less_while_descending() {
    let run = |predict: bool| {
        let cfg = ClientConfig {
            decode_threads: 0,
            quality: QualityConfig {
                mode: QualityMode::Fixed,
                initial: 1e5,
                ..QualityConfig::default()
            },
            predict_view: predict,
            ..ClientConfig::for_policy(Policy::Thesis, 1.0)
        };
        let mut c = Client::new(db().header.clone(), cfg).expect("client");
        let mut s = FakeServer::new(12);
        let r = db().header.datum.equatorial_radius();
        let dir = FaceCoord {
            face: planet_core::Face::new(2).expect("face"),
            s: 0.37,
            t: 0.61,
        }
        .direction();
        let d = DVec3::from_array(dir);
        let side = d.cross(DVec3::Z).normalize();
        // Descend from 2 radii to 0.02 radii above the surface, looking down
        // and slightly sideways, in 240 frames; then hover.
        let cam_at = |k: usize| {
            let a = (k.min(240) as f64) / 240.0;
            let h = r * 2.0 * (0.01f64).powf(a);
            let eye = d * (r + h);
            Camera::look_at(eye, d * r + side * (0.3 * h), d.cross(side))
        };
        for k in 0..240 {
            let cam = cam_at(k);
            step(&mut c, &mut s, &cam);
            c.tree().validate().expect("valid");
        }
        let moving = c.totals();
        // Converged: nothing sent, in flight, decoding or pending.
        let last = converge(&mut c, &mut s, &cam_at(240), 2000);
        (moving, last.stats.max_screen_error)
    };
    let (with, sse_with) = run(true);
    let (without, sse_without) = run(false);
    let waste = |t: &planet_client::stats::Totals| t.bytes_received - t.bytes_relevant;
    println!(
        "descent, latency 12 frames: with prediction {} of {} bytes irrelevant ({:.2} % relevant), without {} of {} ({:.2} %)",
        waste(&with),
        with.bytes_received,
        100.0 * with.relevant_ratio(),
        waste(&without),
        without.bytes_received,
        100.0 * without.relevant_ratio()
    );
    assert!(
        waste(&without) > 0,
        "the scenario must waste bytes without prediction"
    );
    assert!(waste(&with) < waste(&without));
    // Once the camera stops the prediction is the camera itself, and the
    // client converges as well as without it (the trees may differ: split
    // hysteresis keeps what the descent refined).
    println!("converged max SSE: with {sse_with:.3} px, without {sse_without:.3} px");
    assert!(
        sse_with <= sse_without * 1.01 + 1e-9,
        "{sse_with} {sse_without}"
    );
}

/// A moving camera that turns its back on the blocks it asked: a request
/// whose block is neither in view nor in the view predicted for its answer
/// is cancelled in the frame that sees it leave, not after the queue's ten
/// untriggered frames (client.rs, `retain_relevant`), and none stays in
/// flight for a block out of both views.
#[test]
fn requests_for_blocks_left_behind_are_cancelled_at_once() {
    let mut c = sse_client(1.0, 0);
    // Answers take 30 frames: the requests of the first view are still in
    // flight when the camera turns.
    let mut s = FakeServer::new(30);
    let d = DVec3::new(1.0, 0.25, 0.2).normalize();
    let north = DVec3::Z.reject_from(d).normalize();
    // 300 km up, moving north at 2 km a frame, looking north and down;
    // then up, away from the planet.
    let eye_at = |k: usize| surface(d, 300_000.0) + north * (2_000.0 * k as f64);
    let look = |k: usize, up: bool| {
        let eye = eye_at(k);
        if up {
            Camera::look_at(eye, eye * 2.0, north)
        } else {
            Camera::look_at(
                eye,
                eye + north * 400_000.0 - eye.normalize() * 300_000.0,
                eye.normalize(),
            )
        }
    };
    let mut k = 0;
    // Until a latency is measured (a prediction exists) and requests are
    // in flight.
    while k < 200 && (k < 40 || c.queue().in_flight() == 0) {
        step(&mut c, &mut s, &look(k, false));
        k += 1;
    }
    let asked: Vec<(Tree, BlockId, bool)> = c
        .queue()
        .in_flight_requests()
        .map(|r| (r.tree, r.block, r.forced))
        .collect();
    let unforced = asked.iter().filter(|a| !a.2).count();
    assert!(unforced > 0, "nothing in flight after {k} frames");
    // Turn to look up: every block asked has left the view, and the
    // prediction turns further away.
    let out = step(&mut c, &mut s, &look(k, true));
    assert!(
        out.cancel.len() >= unforced,
        "{} cancelled of {unforced} in flight",
        out.cancel.len()
    );
    for (t, b, forced) in &asked {
        assert!(
            *forced || !c.queue().is_in_flight(*t, b),
            "{t:?} {b:?} left the view and is still in flight"
        );
    }
}

/// Hand a frame's requests to the fake server, deliver what is due; whether
/// the client is idle (nothing sent, in flight, pending, decoding or due).
fn exchange(c: &mut Client, s: &mut FakeServer, out: &FrameOutput) -> bool {
    s.submit(out);
    for (id, bytes) in s.tick(db()) {
        c.deliver(id, Ok(bytes));
    }
    out.send.is_empty()
        && c.queue().in_flight() == 0
        && c.pending_ops().is_empty()
        && c.decoding() == 0
        && s.pending() == 0
}

/// The default policy refines exactly where the screen-space error is above
/// the tolerance (client/src/refinement.rs): every request it sends (not
/// forced by a neighbour's split, §4.3.3) is for a block whose first LOD is
/// off by more than the tolerance, and once converged every drawn block is
/// within it or is the finest there is, at several tolerances and
/// altitudes.
#[test]
fn sse_refines_exactly_above_the_tolerance() {
    for (tol, alt) in [(0.1, 150_000.0), (1.0, 3_000.0), (4.0, 500.0)] {
        let mut c = sse_client(tol, 0);
        let mut s = FakeServer::new(2);
        let eye = surface(DVec3::new(1.0, 0.1, 0.2), alt);
        let cam = Camera::look_at(
            eye,
            surface(DVec3::new(1.0, 0.13, 0.21), 0.0),
            eye.normalize(),
        );
        let (r_min, r_max) = c.radii();
        let view = View::new(&cam, r_min, r_max);
        let mut sent = 0;
        let mut quiet = 0;
        let mut last = None;
        let mut first_colour = None;
        for _ in 0..4000 {
            let r = c.refiner(&view);
            let out = c.frame(&cam, 1.0 / 60.0);
            // The colour drawn from the header's roots alone.
            first_colour.get_or_insert_with(|| c.colour_screen_error(&cam, &out.draw));
            for o in out.send.iter().filter(|o| !o.forced) {
                let t = c.tree();
                // A child of a block whose split this frame chose is asked
                // before the split is executed (ClientConfig::eager_children):
                // its record and bounds are those the split will give it.
                let (error, b) = match t.tree(o.tree).and_then(|x| x.get(&o.block)) {
                    Some(n) => {
                        let b = t.elevation().get(&o.block).and_then(|e| e.bounds.clone());
                        (n.record.error, (*b.expect("bounds")).clone())
                    }
                    None => {
                        let p = o.block.parent().expect("a root always exists");
                        if c.pending_ops().iter().any(|op| op.block == p) {
                            let kids = t.split_children(&p).expect("the parent can split");
                            let (_, r, b) = kids[o.block.child_index()].clone();
                            (r.error, b)
                        } else {
                            // Asked ahead of its parent's record
                            // (ClientConfig::lookahead): the reference came
                            // with its grandparent's.
                            assert!(
                                o.tree == Tree::Elevation
                                    && t.elevation().get(&p).is_none_or(|n| n.lod == 1),
                                "{:?} asked without its parent's split pending",
                                o.block
                            );
                            (o.record.error, t.bounds_of(o.block, &o.record))
                        }
                    }
                };
                let (kind, w) = match o.tree {
                    Tree::Elevation => (Kind::Elevation, t.elevation().width),
                    Tree::Colour => (Kind::Colour, t.colour().expect("colour").width),
                };
                let fp = Footprint::of(&b);
                let m = r.measure(kind, &fp, w as f64, error as f64, 0.0);
                // An elevation block may also be refined for its colour:
                // colour splits only under split elevation (§4.4.1), so a
                // colour leaf whose LOD 0 texels are coarser than the
                // tolerance pulls its elevation block's LOD 0.
                let for_colour = o.tree == Tree::Elevation
                    && t.colour()
                        .and_then(|ct| ct.get(&o.block))
                        .is_some_and(|cn| {
                            let ch = cn.child_refs.as_ref().map_or(0.0, |c| {
                                c.iter().map(|r| r.error as f64).fold(0.0, f64::max)
                            });
                            let w = t.colour().map_or(0, |ct| ct.width) as f64;
                            cn.lod == 0
                                && r.measure(Kind::Colour, &fp, w, cn.record.error as f64, ch)
                                    .b
                                    > tol
                        });
                assert!(
                    m.a > tol || for_colour,
                    "{:?} {:?} requested at {} px ≤ {tol} px",
                    o.tree,
                    o.block,
                    m.a
                );
                sent += 1;
            }
            let idle = exchange(&mut c, &mut s, &out);
            quiet = if idle { quiet + 1 } else { 0 };
            last = Some(out);
            if quiet >= 3 {
                break;
            }
        }
        assert!(quiet >= 3, "no convergence at {tol} px, {alt} m");
        eprintln!("{tol} px, {alt} m: {sent} requests");
        assert!(
            sent >= 5,
            "only {sent} requests at {tol} px, {alt} m: the view tests too little"
        );
        let out = last.expect("frames");
        let et = c.tree().elevation();
        for d in &out.draw {
            let n = et.get(&d.block).expect("drawn");
            let finest = d.lod == 0 && n.child_refs.as_ref().is_some_and(|c| c.is_empty());
            assert!(
                d.screen_error <= tol || finest,
                "{:?} at LOD {}: {} px > {tol} px",
                d.block,
                d.lod,
                d.screen_error
            );
        }
        // The colour half of the rendered error (what `planet-bench
        // flight` reports with the stops): coarser than the tolerance from
        // the roots, within it once converged.
        let first = first_colour.expect("frames");
        let now = c.colour_screen_error(&cam, &out.draw);
        assert!(
            first > tol,
            "roots' texels {first} px ≤ {tol} px at {alt} m"
        );
        assert!(
            now <= tol,
            "converged texels {now} px > {tol} px at {alt} m"
        );
        c.tree().validate().expect("valid");
    }
}

/// A memory budget (`ClientConfig::memory_budget`) coarsens the tolerance
/// until the least needed blocks merge: the same view converges within half
/// the bytes it takes without a budget, and still draws every area.
#[test]
fn memory_budget_bounds_the_resident_tree() {
    let eye = surface(DVec3::new(1.0, 0.1, 0.2), 2_000_000.0);
    let cam = Camera::look_at(eye, DVec3::ZERO, DVec3::Z);
    let run = |budget: Option<u64>| {
        let cfg = ClientConfig {
            decode_threads: 0,
            memory_budget: budget,
            // The synthetic database is smooth: a fine tolerance makes a
            // tree of a few hundred nodes.
            ..ClientConfig::for_policy(Policy::Ours, 0.01)
        };
        let mut c = Client::new(db().header.clone(), cfg).expect("client");
        let mut s = FakeServer::new(1);
        let mut out = None;
        for _ in 0..3000 {
            out = Some(step(&mut c, &mut s, &cam));
        }
        c.tree().validate().expect("valid");
        (
            c.resident_bytes(),
            out.expect("frames").draw.len(),
            c.tolerance(),
        )
    };
    let (free, drawn_free, _) = run(None);
    let budget = free / 2;
    let (bounded, drawn, tol) = run(Some(budget));
    eprintln!(
        "resident {free} B without a budget, {bounded} B with {budget} B (tolerance {tol:.3} px)"
    );
    assert!(bounded <= budget, "{bounded} > {budget}");
    assert!(tol > 0.01, "the tolerance was coarsened");
    assert!(drawn > 0 && drawn < drawn_free);
}

#[test]
fn a_record_that_keeps_failing_is_retried_with_exponential_backoff() {
    // Root 0 fails every time (a server `storage` error, say): it is
    // re-requested after 0.1, 0.2, 0.4, 0.8 s..., not every frame.
    let mut c = client(0);
    let cam = ground_camera();
    let failing = db().header.elevation.root_records[0].offset;
    let mut requests = 0;
    for _ in 0..120 {
        let out = c.frame(&cam, 1.0 / 60.0);
        for o in &out.send {
            if o.record.offset == failing {
                requests += 1;
                c.deliver(o.id, Err(TransportError::request("storage")));
            } else {
                c.deliver(o.id, Ok(db().read(&o.record).expect("record")));
            }
        }
    }
    // In 2 s: the first request, then retries at about 0.1, 0.3, 0.7 and
    // 1.5 s (frames are 1/60 s apart).
    assert!(
        (4..=6).contains(&requests),
        "{requests} requests in 120 frames"
    );
}

/// What a descent from orbit to the ground ended with ([`descend`]).
struct Descent {
    /// Frames until idle.
    frames: u32,
    /// Requests counted by the caller's test.
    counted: usize,
    /// Largest drawn screen-space error at the end.
    max_sse: f64,
    /// Bytes dropped on arrival.
    dropped: u64,
    /// The final elevation tree's blocks, sorted.
    nodes: Vec<BlockId>,
    /// The client's totals at the end.
    totals: planet_client::stats::Totals,
}

/// A descent from 2 km over the ground to convergence with `cfg` behind
/// a fake server of `latency` frames; `count` counts the requests of each
/// frame (given the client before the answers). Checks that no block is
/// asked twice and that the tree stays valid.
fn descend(
    cfg: ClientConfig,
    latency: u64,
    mut count: impl FnMut(&Client, &planet_client::Outgoing) -> bool,
) -> Descent {
    let eye = surface(DVec3::new(1.0, 0.1, 0.2), 2_000.0);
    let cam = Camera::look_at(
        eye,
        surface(DVec3::new(1.0, 0.13, 0.21), 0.0),
        eye.normalize(),
    );
    let mut c = Client::new(db().header.clone(), cfg).expect("client");
    let mut s = FakeServer::new(latency);
    let (mut counted, mut quiet) = (0, 0);
    for frame in 0..4000u32 {
        let out = c.frame(&cam, 1.0 / 60.0);
        counted += out.send.iter().filter(|o| count(&c, o)).count();
        let idle = exchange(&mut c, &mut s, &out);
        quiet = if idle { quiet + 1 } else { 0 };
        if quiet >= 3 {
            let blocks: std::collections::HashSet<_> =
                s.log.iter().map(|o| (o.tree, o.block)).collect();
            assert_eq!(blocks.len(), s.log.len(), "a block asked twice ({cfg:?})");
            c.tree().validate().expect("valid");
            let mut nodes: Vec<_> = c.tree().elevation().nodes().map(|n| n.id).collect();
            nodes.sort();
            return Descent {
                frames: frame,
                counted,
                max_sse: out.draw.iter().map(|d| d.screen_error).fold(0.0, f64::max),
                dropped: c.totals().bytes_dropped,
                nodes,
                totals: c.totals(),
            };
        }
    }
    panic!("no convergence ({cfg:?}, latency {latency})");
}

/// `ours` asks a splitting block's children in the frame that chooses the
/// split (`ClientConfig::eager_children`): a descent from orbit to the
/// ground converges in fewer frames than with the children asked a frame
/// later, sends no request twice, and loses no byte, also when the answers
/// come before the next frame executes the split (a link faster than a
/// frame: they wait for it).
#[test]
fn children_are_asked_in_the_frame_that_splits() {
    let run = |eager: bool, latency: u64| {
        let cfg = ClientConfig {
            decode_threads: 0,
            eager_children: eager,
            lookahead: false,
            ..ClientConfig::for_policy(Policy::Ours, 1.0)
        };
        // Asked while its block does not exist yet.
        descend(cfg, latency, |c, o| {
            c.tree().elevation().get(&o.block).is_none()
        })
    };
    for latency in [0, 1, 4] {
        let late = run(false, latency);
        let eager = run(true, latency);
        eprintln!(
            "latency {latency}: {} → {} frames, {} children asked early",
            late.frames, eager.frames, eager.counted
        );
        assert_eq!(late.counted, 0);
        assert!(
            eager.counted > 0,
            "no child asked in its parent's split frame"
        );
        assert!(
            eager.frames < late.frames,
            "{} frames, not fewer than {}",
            eager.frames,
            late.frames
        );
        assert_eq!((late.dropped, eager.dropped), (0, 0), "bytes dropped");
        assert!(
            late.max_sse <= 1.0 && eager.max_sse <= 1.0,
            "{} {}",
            late.max_sse,
            eager.max_sse
        );
    }
}

/// `ours` learns its grandchildren's references with a record
/// (`ClientConfig::lookahead`, `LodRefsRequest` answered by the fake server
/// as planet-server does) and asks a child's children with the child: a
/// descent from orbit converges in fewer frames than one level per round
/// trip, at latencies of 2 to 8 frames, sends no request twice, drops no
/// record, and ends at the same tree.
#[test]
fn two_levels_per_round_trip_with_the_child_tables() {
    let run = |lookahead: bool, latency: u64| {
        let cfg = ClientConfig {
            decode_threads: 0,
            lookahead,
            ..ClientConfig::for_policy(Policy::Ours, 1.0)
        };
        let mut tables = 0;
        // Asked while even its parent does not exist yet.
        let d = descend(cfg, latency, |c, o| {
            tables += usize::from(o.refs.is_some());
            o.block
                .parent()
                .is_some_and(|p| c.tree().elevation().get(&p).is_none())
        });
        (d, tables)
    };
    for latency in [2, 4, 8] {
        let (one, t_one) = run(false, latency);
        let (two, t_two) = run(true, latency);
        eprintln!(
            "latency {latency}: {} → {} frames, {} blocks asked ahead of their parent, \
             {t_two} requests with tables",
            one.frames, two.frames, two.counted
        );
        assert_eq!((one.counted, t_one), (0, 0));
        assert!(two.counted > 0 && t_two > 0, "nothing asked ahead");
        assert!(
            two.frames < one.frames,
            "{} frames, not fewer than {}",
            two.frames,
            one.frames
        );
        assert_eq!((one.dropped, two.dropped), (0, 0), "bytes dropped");
        assert!(
            one.max_sse <= 1.0 && two.max_sse <= 1.0,
            "{} {}",
            one.max_sse,
            two.max_sse
        );
        assert_eq!(one.nodes, two.nodes, "another tree");
        // The tables travel with the records; those through which a drawn
        // record was asked count as used (97 bytes each), no more than came.
        let t = two.totals;
        eprintln!(
            "  tables: {} bytes, {} used; relevant {:.4}, cancelled {}",
            t.bytes_tables,
            t.bytes_tables_used,
            t.relevant_ratio(),
            t.cancelled
        );
        assert_eq!(one.totals.bytes_tables, 0);
        assert!(t.bytes_tables_used > 0 && t.bytes_tables_used <= t.bytes_tables);
        assert_eq!(t.bytes_tables_used % 97, 0);
        // Nothing asked ahead is given up on a straight descent.
        assert_eq!(t.cancelled, 0, "{t:?}");
    }
}

/// `ours` waits at frame start for the records delivered before it to be
/// decoded by the workers (`ClientConfig::decode_wait_s`): each frame
/// applies every record that came before it, never a frame later. (The
/// wait is 2 ms by default; a second here, so that a loaded test machine
/// cannot make the workers miss it. Without the wait the second frame
/// already fails.)
#[test]
fn records_delivered_before_a_frame_are_applied_in_it() {
    let cfg = ClientConfig {
        decode_threads: 2,
        decode_wait_s: 1.0,
        lookahead: false,
        ..ClientConfig::for_policy(Policy::Ours, 1.0)
    };
    let mut c = Client::new(db().header.clone(), cfg).expect("client");
    let mut s = FakeServer::new(0);
    let eye = surface(DVec3::new(1.0, 0.1, 0.2), 3_000.0);
    let cam = Camera::look_at(
        eye,
        surface(DVec3::new(1.0, 0.13, 0.21), 0.0),
        eye.normalize(),
    );
    let mut delivered = 0;
    for _ in 0..200 {
        let out = c.frame(&cam, 1.0 / 60.0);
        assert_eq!(
            out.stats.refines_applied + out.stats.records_rejected,
            delivered,
            "frame {}: records delivered before it not all applied",
            out.stats.frame
        );
        s.submit(&out);
        let due = s.tick(db());
        delivered = due.len();
        for (id, bytes) in due {
            c.deliver(id, Ok(bytes));
        }
    }
    assert!(c.totals().refines_applied > 5);
}

/// A forced record (a coarse neighbour's LOD 0, loaded so that a visible
/// block may split, thesis §4.3.3) is drawn in the frame it is applied:
/// the splits it unblocks are executed in that frame, not the next, so its
/// bytes count as relevant rather than drawn later. (Before, this view
/// drew 292 bytes of forced records a frame late.) Forced records of
/// neighbours that are not visible are never drawn, and stay counted apart.
#[test]
fn forced_neighbours_are_drawn_on_arrival() {
    let db4 = width4_db();
    let cfg = ClientConfig {
        decode_threads: 0,
        ..ClientConfig::for_policy(Policy::Ours, 1.0)
    };
    let mut c = Client::new(db4.header.clone(), cfg).expect("client");
    let mut s = FakeServer::new(1);
    let eye = DVec3::new(1.0, 0.02, 0.01).normalize() * (6_371_000.0 + 2_000.0);
    let cam = Camera::look_at(
        eye,
        DVec3::new(1.0, -0.2, 0.05).normalize() * 6_371_000.0,
        eye.normalize(),
    );
    let mut forced_bytes = 0u64;
    for _ in 0..300 {
        let out = converge::step(&mut c, &mut s, &db4, &cam);
        forced_bytes += out
            .send
            .iter()
            .filter(|o| o.forced)
            .map(|o| u64::from(o.record.size))
            .sum::<u64>();
        c.tree().validate().expect("valid");
    }
    let t = c.totals();
    assert_eq!(t.bytes_drawn_later, 0, "{t:?}");
    assert!(
        forced_bytes > t.bytes_forced,
        "no forced record drawn on arrival: {forced_bytes} forced, {t:?}"
    );
}
