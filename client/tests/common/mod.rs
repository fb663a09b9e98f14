//! Shared setup of the client's integration tests: the synthetic database,
//! a client with a fixed quality factor, and random camera moves.

#![allow(dead_code)] // each test file uses a part

use std::sync::OnceLock;

use glam::DVec3;
use planet_client::quality::{QualityConfig, QualityMode};
use planet_client::{Client, ClientConfig, Policy};
use planet_testkit::testdb::{TestDb, TestDbConfig};
use proptest::prelude::*;

/// The default synthetic database, built once per test binary.
pub fn db() -> &'static TestDb {
    static DB: OnceLock<TestDb> = OnceLock::new();
    DB.get_or_init(|| TestDb::build(TestDbConfig::default()))
}

/// A client of [`db`] with the thesis's policy at a fixed quality factor
/// `qf` and `threads` decode threads (0: decode on the frame's thread).
pub fn fixed_qf_client(qf: f64, threads: usize) -> Client {
    let cfg = ClientConfig {
        decode_threads: threads,
        ..ClientConfig::for_policy(Policy::Thesis, 1.0)
    };
    let cfg = ClientConfig {
        quality: QualityConfig {
            mode: QualityMode::Fixed,
            initial: qf,
            ..QualityConfig::default()
        },
        ..cfg
    };
    Client::new(db().header.clone(), cfg).expect("client")
}

/// A client of [`db`] with the default policy (screen-space error) at
/// tolerance `max_sse` pixels and `threads` decode threads.
pub fn sse_client(max_sse: f64, threads: usize) -> Client {
    let cfg = ClientConfig {
        decode_threads: threads,
        ..ClientConfig::for_policy(Policy::Ours, max_sse)
    };
    Client::new(db().header.clone(), cfg).expect("client")
}

/// The point `alt` metres above the sphere of [`db`] in direction `dir`.
pub fn surface(dir: DVec3, alt: f64) -> DVec3 {
    dir.normalize() * (db().header.datum.equatorial_radius() + alt)
}

/// One random camera move: a direction from the centre, log10 of the
/// altitude, a view direction and a number of frames (× 4) to hold it.
pub type CameraMove = ((f64, f64, f64), f64, (f64, f64, f64), usize);

/// One to five random camera moves, from 1 km to 20 000 km altitude.
pub fn camera_moves() -> impl Strategy<Value = Vec<CameraMove>> {
    proptest::collection::vec(
        (
            (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
            3.0f64..7.3,
            (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
            1usize..6,
        ),
        1..6,
    )
}

/// The eye and the view direction of a move (degenerate directions
/// replaced: +X for the position, straight down for the view).
pub fn move_eye_forward(m: &CameraMove) -> (DVec3, DVec3) {
    let ((x, y, z), alt_log, (fx, fy, fz), _) = *m;
    let dir = DVec3::new(x, y, z);
    let dir = if dir.length() < 1e-3 { DVec3::X } else { dir };
    let eye = surface(dir, 10f64.powf(alt_log));
    let f = DVec3::new(fx, fy, fz);
    let f = if f.length() < 1e-3 { -eye } else { f };
    (eye, f)
}
