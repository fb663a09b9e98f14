//! The superblock and header of a database file a server may be handed, as
//! is and with its CRC repaired (`planet_testkit::fuzzing::db_header`, the
//! body this target and `server/tests/fuzz_regressions.rs` share).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| planet_testkit::fuzzing::db_header(data));
