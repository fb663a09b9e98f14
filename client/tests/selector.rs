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
use planet_client::selection::{draws_lod0, select, Selector};
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
    // With a prefetch for a view ahead (a third of the height closer,
    // along the view direction), then without, as the client runs them.
    let ahead = {
        let mut a = *cam;
        let height = (cam.eye.length() - r_min).max(0.0);
        a.eye += cam.forward.normalize_or_zero() * (height / 3.0);
        c.refiner(&View::new(&a, r_min, r_max))
    };
    let want = select(c.tree(), &view, &r, Some(&ahead));
    let got = sel.select(c.tree(), &view, &r, Some(&ahead));
    assert_eq!(got, want, "selector differs from select (prefetch)");
    let want = select(c.tree(), &view, &r, None);
    let got = sel.select(c.tree(), &view, &r, None);
    assert_eq!(got, want, "selector differs from select");
    // Which records the draw list draws at LOD 0 (the relevance account),
    // from the flat tree as from a scan of the list; about 500 nodes a
    // frame, so that the scans stay cheap.
    for kind in [Tree::Elevation, Tree::Colour] {
        let Some(t) = c.tree().tree(kind) else {
            continue;
        };
        let step = (t.len() / 500).max(1);
        for n in t.nodes().step_by(step) {
            assert_eq!(
                sel.draws_lod0(kind, &n.id),
                draws_lod0(&want.draw, kind, &n.id),
                "{kind:?} {:?} drawn at LOD 0",
                n.id
            );
        }
    }
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

/// A split block found surely kept (its first LOD's error above the merge
/// threshold as far as the eye may be from it, thesis §3.6's coherence) is
/// not measured again until the eye has travelled that slack, and a new
/// tolerance or viewport forgets every such finding. Here the tolerance
/// grows, the viewport shrinks and the eye climbs in small steps, each
/// making blocks merge that were kept just before: the selection must be
/// the reference's every time, with those merges (asserted, so that the
/// test is not vacuous).
const TOL: f64 = 0.001;

#[test]
fn kept_splits_merge_when_the_tolerance_viewport_or_eye_change() {
    let mut c = sse_client(TOL, 0);
    let mut s = FakeServer::new(0);
    let mut sel = Selector::new();
    let base = DVec3::new(1.0, 0.2, 0.3);
    // `shift` moves the eye back along the ground.
    let at = |alt: f64, shift: f64| {
        let dir = base - DVec3::new(0.0, shift, 0.0);
        let eye = surface(dir, alt);
        let target = surface(dir + DVec3::new(0.0, 0.05, 0.0), 0.0);
        Camera::look_at(eye, target, eye.normalize())
    };
    let cam = at(30_000.0, 0.0);
    for _ in 0..300 {
        checked_step(&mut c, &mut s, &mut sel, &cam);
    }
    let tree = c.tree().clone();
    let (r_min, r_max) = c.radii();
    let mut merges = |cam: &Camera, tol: f64| {
        let view = View::new(cam, r_min, r_max);
        let r = Refiner::new(Policy::Ours, &view, 1e5, tol);
        let want = select(&tree, &view, &r, None);
        assert_eq!(sel.select(&tree, &view, &r, None), want, "at {tol} px");
        want.ops.iter().filter(|o| o.kind == OpKind::Merge).count()
    };
    let settled = merges(&cam, TOL);
    let looser = merges(&cam, TOL * 128.0);
    assert!(
        looser > settled,
        "{looser} merges at 128 times the tolerance, {settled} at it"
    );
    merges(&cam, TOL);
    let mut small = cam;
    small.viewport_height_px /= 128.0;
    let smaller = merges(&small, TOL);
    assert!(
        smaller > settled,
        "{smaller} merges on 1/128 of the viewport"
    );
    // Flying back at the same height (the near distance stays), then
    // climbing by 4 % of the height a frame, at tolerances where blocks
    // kept at the start merge on the way.
    let (tol, start) = (TOL * 8.0, merges(&cam, TOL * 8.0));
    let flown: Vec<usize> = (1..=120)
        .map(|k| merges(&at(30_000.0, k as f64 * 0.01), tol))
        .collect();
    let (tol, start2) = (TOL * 16.0, merges(&cam, TOL * 16.0));
    let climbed: Vec<usize> = (1..=120)
        .map(|k| merges(&at(30_000.0 * 1.04f64.powi(k), 1.2), tol))
        .collect();
    for (leg, start, m) in [("flying back", start, flown), ("climbing", start2, climbed)] {
        assert!(
            m.iter().filter(|m| **m > start).count() >= 3,
            "merges while {leg}: {m:?}"
        );
    }
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
        sel.select(fresh.tree(), &view, &r, None),
        select(fresh.tree(), &view, &r, None)
    );
    let copy = c.tree().clone();
    assert_eq!(
        sel.select(&copy, &view, &r, None),
        select(&copy, &view, &r, None)
    );
    assert_eq!(sel.rebuilds(), r0 + 2);
    // Same tree and eye, other quality factors and viewports: the kept
    // importances and errors are not reused.
    for (qf, h) in [(1e3, 1080.0), (1e7, 1080.0), (1e7, 720.0), (1e5, 720.0)] {
        let mut cam = cam;
        cam.viewport_height_px = h;
        let view = View::new(&cam, r_min, r_max);
        let r = thesis(&view, qf);
        assert_eq!(
            sel.select(&copy, &view, &r, None),
            select(&copy, &view, &r, None)
        );
    }
    // Other policies and tolerances on the same tree and eye.
    for p in Policy::ALL {
        for tol in [0.5, 1.0, 4.0] {
            let r = Refiner::new(p, &view, 1e5, tol);
            assert_eq!(
                sel.select(&copy, &view, &r, None),
                select(&copy, &view, &r, None)
            );
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

/// The case the colour binding is for: an elevation block that passes the
/// cull test while each of its children fails it (the conservative tests
/// of a large block near the frustum's edge or the horizon), under a
/// colour leaf with its id that the refiner would load or split. Its
/// texture would go on no drawn block, so neither selection requests it.
/// A descent grows the tree over a database whose colour is coarser per
/// level than its elevation (32 texels a block against 8 samples), so
/// some colour leaves lie over split elevation blocks; seeded cameras about
/// each such block (an eye within a few block radii, any direction, a
/// field of view of 1–90°) must meet the case (asserted: the test is not
/// vacuous; 238 of 16 000 probes meet it) and never request the leaf, and
/// the request filter's leaf test answers no there. The
/// selection before e01dd2f, whose colour gate was the elevation block's
/// visibility, fails here ("over culled children requested").
#[test]
fn colour_leaf_over_culled_children_is_not_requested() {
    use planet_client::refinement::{Footprint, Kind};
    use planet_client::ClientConfig;
    use planet_core::{BlockId, Face};
    use planet_testkit::testdb::{TestDb, TestDbConfig};
    let db = TestDb::build(TestDbConfig {
        elevation_max_level: 5,
        colour: Some((32, 5)),
        ..TestDbConfig::default()
    });
    // Decoded on the frame's thread: the same tree on every run.
    let cfg = ClientConfig {
        decode_threads: 0,
        ..ClientConfig::for_policy(Policy::Ours, 1.0)
    };
    let mut c = Client::new(db.header.clone(), cfg).expect("client");
    let mut s = FakeServer::new(1);
    let mut sel = Selector::new();
    let base = DVec3::new(1.0, 0.2, 0.3);
    let radius = db.header.datum.equatorial_radius();
    let surface = |dir: DVec3, alt: f64| dir.normalize() * (radius + alt);
    // Each altitude held a second frame: a still camera predicts nothing,
    // so the tree does not depend on the view prediction's filters.
    for k in 0..300 {
        let eye = surface(base, 2e7 * 0.93f64.powi(k / 2));
        let out = c.frame(&Camera::look_at(eye, DVec3::ZERO, DVec3::Z), 1.0 / 60.0);
        s.submit(&out);
        for (id, bytes) in s.tick(&db) {
            c.deliver(id, Ok(bytes));
        }
    }
    // The colour leaves over a split elevation block (whose id they share)
    // that could still refine.
    let (et, ct) = (c.tree().elevation(), c.tree().colour().expect("colour"));
    let mut leaves: Vec<BlockId> = Vec::new();
    let mut stack: Vec<BlockId> = Face::ALL.map(BlockId::root).into();
    while let Some(id) = stack.pop() {
        let Some(n) = ct.get(&id) else { continue };
        if n.split {
            stack.extend(id.children());
        } else if et.get(&id).is_some_and(|e| e.split) && (n.lod == 1 || n.can_split_data().is_ok())
        {
            leaves.push(id);
        }
    }
    assert!(!leaves.is_empty(), "no colour leaf over a split block");
    // Seeded probes about each: an eye within a few block radii of the
    // block, looking anywhere, with a field of view of 1–90°.
    let mut x = 0x9e37_79b9u64;
    let mut rand = move || {
        x = x
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    let (mut cases, mut probes) = (0, 0);
    for &id in &leaves {
        let Some(b) = et.get(&id).and_then(|e| e.bounds.clone()) else {
            continue;
        };
        for _ in 0..2_000 {
            probes += 1;
            let mut unit =
                || DVec3::new(rand() - 0.5, rand() - 0.5, rand() - 0.5).normalize_or(DVec3::X);
            let (offset, look) = (unit(), unit());
            let eye = b.centre + offset * b.sphere_radius * (0.2 + 3.0 * rand());
            let eye = eye.normalize() * eye.length().max(radius + 100.0);
            let mut cam = Camera::look_at(eye, eye + look, eye.normalize());
            cam.fov_y = (1.0 + 89.0 * rand()).to_radians();
            let (r_min, r_max) = c.radii();
            let view = View::new(&cam, r_min, r_max);
            // The case: the block visible down from its root, each child
            // culled.
            let visible = |id: &BlockId| {
                et.get(id)
                    .and_then(|n| n.bounds.as_ref())
                    .is_some_and(|b| view.is_visible(b))
            };
            // The request filter's test of the leaves under a colour block
            // (`LinkedTree::leaves_in_view`) agrees: yes with a visible leaf
            // child, no with every child culled.
            let leaf_child_visible = id
                .children()
                .iter()
                .any(|c| et.get(c).is_some_and(|n| !n.split) && visible(c));
            if leaf_child_visible {
                assert!(
                    et.leaves_in_view(&id, &view),
                    "{id:?}: a leaf child is visible"
                );
            }
            if !(0..=id.level).all(|l| visible(&id.ancestor(l)))
                || id.children().iter().any(visible)
            {
                continue;
            }
            assert!(
                !et.leaves_in_view(&id, &view),
                "{id:?}: every child is culled"
            );
            let r = c.refiner(&view);
            let cn = ct.get(&id).expect("colour leaf");
            let m = r.measure(
                Kind::Colour,
                &Footprint::of(&b),
                ct.width as f64,
                cn.record.error as f64,
                cn.child_error(),
            );
            let d = r.leaf(&m, cn.lod);
            if !(d.load || (d.split && cn.can_split_data().is_ok())) {
                continue;
            }
            let got = select(c.tree(), &view, &r, None);
            assert_eq!(
                sel.select(c.tree(), &view, &r, None),
                got,
                "selector differs from select"
            );
            if got
                .draw
                .iter()
                .any(|d| d.colour.is_some_and(|b| b.block == id))
            {
                continue;
            }
            cases += 1;
            let requested = got
                .loads
                .iter()
                .map(|l| (l.tree, l.block))
                .chain(got.ops.iter().map(|o| (o.tree, o.block)))
                .any(|(t, b)| t == Tree::Colour && b == id);
            assert!(
                !requested,
                "colour leaf {id:?} over culled children requested"
            );
        }
    }
    println!("{cases} of {probes} probes met the case");
    assert!(cases > 0, "no probe of {probes} met the case");
}

/// The prefetch for the view ahead ([`planet_client::ClientConfig::prefetch`]),
/// at a tolerance that the smooth synthetic planet needs (0.0002 px): over
/// a tree converged for a camera 10 000 km up, the view from 3 000 km asks
/// for loads or splits that the present view does not, all below every
/// present priority (in `[−1, 0)`), and draws the same blocks; over a tree
/// converged 1 500 km up, a present view from 200 000 km merges fewer blocks
/// when the view ahead is the low one, and only blocks it merges alone
/// too.
#[test]
fn prefetch_asks_for_the_view_ahead_and_keeps_its_splits() {
    let base = DVec3::new(1.0, 0.2, 0.3);
    let down = |alt: f64| {
        let eye = surface(base, alt);
        Camera::look_at(eye, DVec3::ZERO, DVec3::Z)
    };
    let converged = |alt: f64| {
        let mut c = sse_client(2e-4, 0);
        let mut s = FakeServer::new(0);
        let cam = down(alt);
        let mut quiet = 0;
        for _ in 0..2000 {
            let out = c.frame(&cam, 1.0 / 60.0);
            s.submit(&out);
            let busy = !out.send.is_empty() || !c.pending_ops().is_empty() || s.pending() > 0;
            for (id, bytes) in s.tick(db()) {
                c.deliver(id, Ok(bytes));
            }
            quiet = if busy { 0 } else { quiet + 1 };
            if quiet > 5 {
                return c;
            }
        }
        panic!("no convergence at {alt} m");
    };
    let selections = |c: &Client, now: f64, ahead: f64| {
        let (r_min, r_max) = c.radii();
        let view = View::new(&down(now), r_min, r_max);
        let r = c.refiner(&view);
        let ra = c.refiner(&View::new(&down(ahead), r_min, r_max));
        let mut sel = Selector::new();
        let with = select(c.tree(), &view, &r, Some(&ra));
        assert_eq!(sel.select(c.tree(), &view, &r, Some(&ra)), with);
        (select(c.tree(), &view, &r, None), with)
    };
    let c = converged(1e7);
    let (without, with) = selections(&c, 1e7, 3e6);
    let splits = |s: &planet_client::selection::Selection| {
        s.ops
            .iter()
            .filter(|o| o.kind == OpKind::Split)
            .map(|o| o.importance)
            .collect::<Vec<_>>()
    };
    assert!(without.loads.is_empty() && splits(&without).is_empty());
    let asked: Vec<f64> = with
        .loads
        .iter()
        .map(|l| l.importance)
        .chain(splits(&with))
        .collect();
    assert!(!asked.is_empty(), "nothing prefetched");
    assert!(asked.iter().all(|p| (-1.0..0.0).contains(p)), "{asked:?}");
    assert_eq!(with.draw, without.draw);

    let c = converged(1.5e6);
    let (without, with) = selections(&c, 2e8, 1.5e6);
    let merges = |s: &planet_client::selection::Selection| {
        s.ops
            .iter()
            .filter(|o| o.kind == OpKind::Merge)
            .map(|o| (o.tree, o.block))
            .collect::<std::collections::HashSet<_>>()
    };
    let (all, kept) = (merges(&without), merges(&with));
    assert!(
        kept.len() < all.len(),
        "{} of {} merges",
        kept.len(),
        all.len()
    );
    assert!(kept.is_subset(&all));
}
