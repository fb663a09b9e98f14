//! The cached per-frame selection ([`Selector`], thesis §3.6 / Alg. 3.1)
//! against the reference traversal ([`select`]): the same draw list, loads
//! and operations, bit for bit, on every frame while the tree grows, is
//! refined, splits and merges (so the cache is patched and rebuilt), and
//! while the camera moves, turns and stands still (so per-node hints and
//! witnesses are reused and go stale). After every frame the cache, patched
//! and spliced from the tree's change log, is also compared with one rebuilt
//! from scratch ([`Selector::consistency_error`]).

mod common;

use common::*;
use glam::DVec3;
use planet_client::refinement::Refiner;
use planet_client::request_queue::OpKind;
use planet_client::selection::{select, Selector};
use planet_client::stats::FrameStats;
use planet_client::visibility::View;
use planet_client::{Camera, Client, Policy};
use planet_core::format::Tree;
use planet_testkit::testdb::FakeServer;
use proptest::prelude::*;

fn client(qf: f64) -> Client {
    fixed_qf_client(qf, 0)
}

/// One frame: compare both selections on the current tree, then step.
fn checked_step(
    c: &mut Client,
    s: &mut FakeServer,
    sel: &mut Selector,
    cam: &Camera,
) -> FrameStats {
    let (r_min, r_max) = c.radii();
    let view = View::new(cam, r_min, r_max);
    let r = c.refiner(&view);
    let want = select(c.tree(), &view, &r);
    let got = sel.select(c.tree(), &view, &r);
    assert_eq!(got, want, "selector differs from select");
    // Colour loads only what a drawn block is textured with.
    for l in want.loads.iter().filter(|l| l.tree == Tree::Colour) {
        assert!(
            want.draw
                .iter()
                .any(|d| d.colour.is_some_and(|b| b.block == l.block)),
            "colour load {:?} textures no drawn block",
            l.block
        );
    }
    if let Some(e) = sel.consistency_error(c.tree()) {
        panic!("spliced cache differs from a rebuilt one: {e}");
    }
    let out = c.frame(cam, 1.0 / 60.0);
    s.submit(&out);
    for (id, bytes) in s.tick(db()) {
        c.deliver(id, Ok(bytes));
    }
    out.stats
}

#[test]
fn selector_matches_select() {
    selector_matches_select_with(client(1e5));
}

/// The same with the default policy (screen-space error, 1 px).
#[test]
fn selector_matches_select_sse() {
    selector_matches_select_with(sse_client(1.0, 0));
}

fn selector_matches_select_with(mut c: Client) {
    let mut s = FakeServer::new(1);
    let mut sel = Selector::new();
    let base = DVec3::new(1.0, 0.2, 0.3);
    let down = |eye: DVec3| Camera::look_at(eye, DVec3::ZERO, DVec3::Z);
    // Descend, turn on the spot, fly along, stand still, climb away.
    let mut cams: Vec<Camera> = (0..120)
        .map(|k| down(surface(base, 2e7 * 0.93f64.powi(k))))
        .collect();
    let eye = surface(base, 2e7 * 0.93f64.powi(120));
    cams.extend((0..90).map(|k| {
        let a = k as f64 * 0.05;
        let f = DVec3::new(-a.cos(), a.sin(), -0.3);
        Camera::look_at(eye, eye + f, eye.normalize())
    }));
    for k in 0..90 {
        let dir = base + DVec3::new(0.0, k as f64 * 0.01, 0.0);
        let eye = surface(dir, 60_000.0);
        let target = surface(dir + DVec3::new(0.0, 0.05, 0.0), 0.0);
        let cam = Camera::look_at(eye, target, eye.normalize());
        cams.extend(std::iter::repeat_n(cam, if k % 30 == 0 { 5 } else { 1 }));
    }
    cams.extend((0..120).map(|k| down(surface(base, 60_000.0 * 1.08f64.powi(k)))));
    for cam in &cams {
        checked_step(&mut c, &mut s, &mut sel, cam);
    }
    let frames = cams.len() as u64;
    c.tree().validate().expect("valid");
    // The cache was built once, then patched (refines) and spliced
    // (splits, merges).
    assert_eq!(sel.rebuilds(), 1);
    assert!(sel.splices() > 5, "{} splices", sel.splices());
    assert!(sel.splices() < frames, "{} splices", sel.splices());
    assert!(c.totals().refines_applied > 20);
}

/// A low, fast flight along a great circle over four cube faces (+X, +Y,
/// −X, −Y) looking ahead: blocks split in front and merge behind, several per
/// frame, on every face crossed, so the cache is spliced (never rebuilt)
/// frame after frame while the eye moves.
#[test]
fn selector_splices_while_moving_across_faces() {
    let mut c = client(2e3);
    let mut s = FakeServer::new(1);
    let mut sel = Selector::new();
    let (mut splits, mut merges, mut busy, mut mixed) = (0, 0, 0, 0);
    let mut faces_split = std::collections::BTreeSet::new();
    let mut faces_merged = std::collections::BTreeSet::new();
    let at = |t: f64| DVec3::new(t.cos(), t.sin(), 0.35);
    // Settle over the start, then fly.
    let eye = surface(at(-0.4), 80_000.0);
    let cam = Camera::look_at(eye, surface(at(-0.35), 0.0), eye.normalize());
    for _ in 0..30 {
        checked_step(&mut c, &mut s, &mut sel, &cam);
    }
    let splices = sel.splices();
    for k in 0..230 {
        let t = -0.4 + k as f64 * 0.02;
        let eye = surface(at(t), 80_000.0);
        let cam = Camera::look_at(eye, surface(at(t + 0.05), 0.0), eye.normalize());
        // Executed at the start of this step's frame, seen by the next
        // step's selection.
        for op in c.pending_ops() {
            match op.kind {
                OpKind::Split => faces_split.insert(op.block.face),
                OpKind::Merge => faces_merged.insert(op.block.face),
            };
        }
        let st = checked_step(&mut c, &mut s, &mut sel, &cam);
        splits += st.splits;
        merges += st.merges;
        busy += usize::from(st.splits + st.merges >= 2);
        mixed += usize::from(st.splits > 0 && st.merges > 0);
    }
    let splices = sel.splices() - splices;
    eprintln!(
        "{splits} splits, {merges} merges, {busy} frames with several, {mixed} with both, {splices} splices"
    );
    c.tree().validate().expect("valid");
    assert_eq!(sel.rebuilds(), 1);
    assert!(faces_split.len() >= 3, "splits on faces {faces_split:?}");
    assert!(faces_merged.len() >= 3, "merges on faces {faces_merged:?}");
    assert!(
        splits >= 50 && merges >= 50,
        "{splits} splits, {merges} merges"
    );
    assert!(
        busy >= 30 && mixed >= 10,
        "{busy} busy frames, {mixed} mixed"
    );
    assert!(splices >= 50, "{splices} splices");
}

/// Another tree value (even a clone of the same tree) is never served from
/// the cache of the first.
#[test]
fn selector_notices_another_tree() {
    let mut c = client(1e5);
    let mut s = FakeServer::new(0);
    let mut sel = Selector::new();
    let eye = surface(DVec3::new(1.0, 0.1, 0.2), 300_000.0);
    let cam = Camera::look_at(eye, DVec3::ZERO, DVec3::Z);
    for _ in 0..40 {
        checked_step(&mut c, &mut s, &mut sel, &cam);
    }
    let (r_min, r_max) = c.radii();
    let view = View::new(&cam, r_min, r_max);
    let fresh = client(1e5);
    let r0 = sel.rebuilds();
    let thesis = |view: &View, qf: f64| Refiner::new(Policy::Thesis, view, qf, 1.0);
    let r = thesis(&view, 1e5);
    assert_eq!(
        sel.select(fresh.tree(), &view, &r),
        select(fresh.tree(), &view, &r)
    );
    let copy = c.tree().clone();
    assert_eq!(sel.select(&copy, &view, &r), select(&copy, &view, &r));
    assert_eq!(sel.rebuilds(), r0 + 2);
    // Same tree and eye, other quality factors and viewports: the kept
    // importances and errors are not reused.
    for (qf, h) in [(1e3, 1080.0), (1e7, 1080.0), (1e7, 720.0), (1e5, 720.0)] {
        let mut cam = cam;
        cam.viewport_height_px = h;
        let view = View::new(&cam, r_min, r_max);
        let r = thesis(&view, qf);
        assert_eq!(sel.select(&copy, &view, &r), select(&copy, &view, &r));
    }
    // Other policies and tolerances on the same tree and eye.
    for p in Policy::ALL {
        for tol in [0.5, 1.0, 4.0] {
            let r = Refiner::new(p, &view, 1e5, tol);
            assert_eq!(sel.select(&copy, &view, &r), select(&copy, &view, &r));
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 10, .. ProptestConfig::default() })]

    /// Random camera moves (position, direction, altitude, quality factor).
    #[test]
    fn selector_matches_select_on_random_moves(
        moves in camera_moves(),
        qf_log in 2.0f64..7.0,
        latency in 0u64..3,
        sse in proptest::option::of(0.3f64..8.0),
    ) {
        // The thesis's policy at a random QF, or the default one at a
        // random tolerance.
        let mut c = match sse {
            None => client(10f64.powf(qf_log)),
            Some(t) => sse_client(t, 0),
        };
        let mut s = FakeServer::new(latency);
        let mut sel = Selector::new();
        for m in &moves {
            let (eye, f) = move_eye_forward(m);
            for k in 0..m.3 * 4 {
                // Turn a little every frame around the same eye.
                let f = f + DVec3::new(0.0, 0.0, k as f64 * 0.01);
                let cam = Camera::look_at(eye, eye + f, eye.normalize());
                checked_step(&mut c, &mut s, &mut sel, &cam);
            }
        }
    }
}
