//! The server's TOML configuration: parsing and validation never panic, a
//! parsed config is valid and its Debug output shows no token
//! (`planet_testkit::fuzzing::server_config`, the body this target and
//! `server/tests/fuzz_regressions.rs` share).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| planet_testkit::fuzzing::server_config(data));
