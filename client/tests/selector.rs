//! The cached per-frame selection ([`Selector`], thesis §3.6 / Alg. 3.1)
//! against the reference traversal ([`select`]): the same draw list, loads
//! and operations, bit for bit, on every frame while the tree grows, is
//! refined, splits and merges (so the cache is patched and rebuilt), and
//! while the camera moves, turns and stands still (so per-node hints and
//! witnesses are reused and go stale).

use glam::DVec3;
use planet_client::quality::{QualityConfig, QualityMode};
use planet_client::selection::{select, Selector};
use planet_client::testdb::{FakeServer, TestDb, TestDbConfig};
use planet_client::visibility::View;
use planet_client::{Camera, Client, ClientConfig};
use proptest::prelude::*;
use std::sync::OnceLock;

fn db() -> &'static TestDb {
    static DB: OnceLock<TestDb> = OnceLock::new();
    DB.get_or_init(|| TestDb::build(TestDbConfig::default()))
}

fn client(qf: f64) -> Client {
    let cfg = ClientConfig {
        decode_threads: 0,
        quality: QualityConfig {
            mode: QualityMode::Fixed,
            initial: qf,
            ..QualityConfig::default()
        },
        ..ClientConfig::default()
    };
    Client::new(db().header.clone(), cfg).expect("client")
}

fn surface(dir: DVec3, alt: f64) -> DVec3 {
    dir.normalize() * (db().header.datum.equatorial_radius() + alt)
}

/// One frame: compare both selections on the current tree, then step.
fn checked_step(c: &mut Client, s: &mut FakeServer, sel: &mut Selector, cam: &Camera) {
    let (r_min, r_max) = c.radii();
    let view = View::new(cam, r_min, r_max);
    let qf = c.quality_factor();
    let want = select(c.tree(), &view, qf);
    let got = sel.select(c.tree(), &view, qf);
    assert_eq!(got, want, "selector differs from select");
    let out = c.frame(cam, 1.0 / 60.0);
    s.submit(&out);
    for (id, bytes) in s.tick(db()) {
        c.deliver(id, Ok(bytes));
    }
}

#[test]
fn selector_matches_select() {
    let mut c = client(1e5);
    let mut s = FakeServer::new(1);
    let mut sel = Selector::new();
    let mut frames = 0u64;
    let base = DVec3::new(1.0, 0.2, 0.3);
    // Descend, turn on the spot, fly along, stand still, climb away.
    for k in 0..120 {
        let alt = 2e7 * 0.93f64.powi(k);
        let eye = surface(base, alt);
        checked_step(
            &mut c,
            &mut s,
            &mut sel,
            &Camera::look_at(eye, DVec3::ZERO, DVec3::Z),
        );
        frames += 1;
    }
    let eye = surface(base, 2e7 * 0.93f64.powi(120));
    for k in 0..90 {
        let a = k as f64 * 0.05;
        let f = DVec3::new(-a.cos(), a.sin(), -0.3);
        checked_step(
            &mut c,
            &mut s,
            &mut sel,
            &Camera::look_at(eye, eye + f, eye.normalize()),
        );
        frames += 1;
    }
    for k in 0..90 {
        let dir = base + DVec3::new(0.0, k as f64 * 0.01, 0.0);
        let eye = surface(dir, 60_000.0);
        let target = surface(dir + DVec3::new(0.0, 0.05, 0.0), 0.0);
        let cam = Camera::look_at(eye, target, eye.normalize());
        for _ in 0..(if k % 30 == 0 { 5 } else { 1 }) {
            checked_step(&mut c, &mut s, &mut sel, &cam);
            frames += 1;
        }
    }
    for k in 0..120 {
        let eye = surface(base, 60_000.0 * 1.08f64.powi(k));
        checked_step(
            &mut c,
            &mut s,
            &mut sel,
            &Camera::look_at(eye, DVec3::ZERO, DVec3::Z),
        );
        frames += 1;
    }
    c.tree().validate().expect("valid");
    // The cache was both patched (refines) and rebuilt (splits, merges).
    assert!(sel.rebuilds() > 5, "{} rebuilds", sel.rebuilds());
    assert!(sel.rebuilds() < frames, "{} rebuilds", sel.rebuilds());
    assert!(c.totals().refines_applied > 20);
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
    assert_eq!(
        sel.select(fresh.tree(), &view, 1e5),
        select(fresh.tree(), &view, 1e5)
    );
    let copy = c.tree().clone();
    assert_eq!(sel.select(&copy, &view, 1e5), select(&copy, &view, 1e5));
    assert_eq!(sel.rebuilds(), r0 + 2);
    // Same tree and eye, other quality factors and viewports: the kept
    // importances and errors are not reused.
    for (qf, h) in [(1e3, 1080.0), (1e7, 1080.0), (1e7, 720.0), (1e5, 720.0)] {
        let mut cam = cam;
        cam.viewport_height_px = h;
        let view = View::new(&cam, r_min, r_max);
        assert_eq!(sel.select(&copy, &view, qf), select(&copy, &view, qf));
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 10, .. ProptestConfig::default() })]

    /// Random camera moves (position, direction, altitude, quality factor).
    #[test]
    fn selector_matches_select_on_random_moves(
        moves in proptest::collection::vec(
            ((-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0), 3.0f64..7.3, (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0), 1usize..6),
            1..6),
        qf_log in 2.0f64..7.0,
        latency in 0u64..3,
    ) {
        let mut c = client(10f64.powf(qf_log));
        let mut s = FakeServer::new(latency);
        let mut sel = Selector::new();
        for ((x, y, z), alt_log, (fx, fy, fz), frames) in moves {
            let dir = DVec3::new(x, y, z);
            let dir = if dir.length() < 1e-3 { DVec3::X } else { dir };
            let eye = surface(dir, 10f64.powf(alt_log));
            let f = DVec3::new(fx, fy, fz);
            let f = if f.length() < 1e-3 { -eye } else { f };
            for k in 0..frames * 4 {
                // Turn a little every frame around the same eye.
                let f = f + DVec3::new(0.0, 0.0, k as f64 * 0.01);
                let cam = Camera::look_at(eye, eye + f, eye.normalize());
                checked_step(&mut c, &mut s, &mut sel, &cam);
            }
        }
    }
}
