//! Test kit of the workspace (a dev-dependency only; also the benchmarks'
//! helpers): what several test suites share, in one place.
//!
//! - [`testdb`]: a synthetic in-memory database and a fake server, for the
//!   client model's tests without files or network.
//! - [`converge`]: one client frame against the fake server, when a client
//!   is idle, and the "step until idle" loop.
//! - `harness` (feature `harness`): an in-process `planet-server` on
//!   loopback with a development certificate, the pinned session
//!   configuration, small procedural databases, the tokio `runtime` and
//!   independent geometric checks (horizon, surface elevation).
//! - `nginx` (feature `harness`): nginx serving one file over HTTPS with
//!   HTTP/2 and byte ranges (the HTTP transport's tests, the benchmarks'
//!   peer).
//! - [`skip_or_fail`]: a test that cannot run here (no GPU, no FUSE, no
//!   nginx) passes with a note, except in CI where it fails.
//! - `fuzzing` (feature `fuzzing`): the fuzz targets' bodies, called by
//!   `fuzz/fuzz_targets/*.rs` and replayed by the server's
//!   `fuzz_regressions` test.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod converge;
#[cfg(feature = "fuzzing")]
pub mod fuzzing;
#[cfg(feature = "harness")]
pub mod harness;
#[cfg(feature = "harness")]
pub mod nginx;
pub mod testdb;

/// Skips a test that cannot run here (no adapter, no Xvfb, no FUSE, no
/// nginx): prints `reason`, and the caller returns. Under `PLANET_CI=1`
/// (set by `.ci/run`) or `PLANET_REQUIRE_ALL=1` it panics instead: in CI a
/// skip is a failure.
pub fn skip_or_fail(reason: &str) {
    let set = |v: &str| std::env::var(v).is_ok_and(|x| x == "1");
    if set("PLANET_CI") || set("PLANET_REQUIRE_ALL") {
        panic!("{reason} (PLANET_CI or PLANET_REQUIRE_ALL is set: a skip fails)");
    }
    eprintln!("NOTE: skipping, {reason}");
}

#[cfg(feature = "harness")]
pub use harness::runtime;
