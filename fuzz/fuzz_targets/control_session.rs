//! Stateful: the server's control-stream state machine (`ServerSession`,
//! sans IO) driven by a sequence of operations taken from the input (see
//! `planet_testkit::fuzzing::control_session`, the body this target and the
//! replay test `server/tests/fuzz_regressions.rs` share).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| planet_testkit::fuzzing::control_session(data));
