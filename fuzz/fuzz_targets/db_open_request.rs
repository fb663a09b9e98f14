//! A database file a server is handed, opened as `planet-server` opens it,
//! with the requests a client sends for it checked as the server checks
//! them (`planet_testkit::fuzzing::db_open_request`, the body this target
//! and `server/tests/fuzz_regressions.rs` share).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    planet_testkit::fuzzing::db_open_request(data);
});
