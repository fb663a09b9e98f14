//! A record as a client receives it from the network, or as a server reads it
//! from a hostile file: parse, check and decode every payload kind, as is and
//! with its length field and CRC repaired; also its child references alone
//! and the bytes as the child tables of a `LodRefsRequest` response
//! (`planet_testkit::fuzzing::db_record`, the body this target and
//! `server/tests/fuzz_regressions.rs` share).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| planet_testkit::fuzzing::db_record(data));
