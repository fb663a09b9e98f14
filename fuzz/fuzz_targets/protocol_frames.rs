//! Protocol frames from an untrusted peer: the frame decoder fed in arbitrary
//! fragments, the request-stream decoders (`LodRequest`, `LodRefsRequest`,
//! `LodRefsAboveRequest`) and the response decoders (plain and with child
//! tables)
//! (`planet_testkit::fuzzing::protocol_frames`, the body this target and
//! `server/tests/fuzz_regressions.rs` share).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| planet_testkit::fuzzing::protocol_frames(data));
