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
pub mod testdb;

#[cfg(feature = "harness")]
pub use harness::runtime;
