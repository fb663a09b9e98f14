//! The raster readers of planet-build (GeoTIFF with its GeoKeys and CRS) on
//! untrusted bytes: no panic, and allocation bounded whatever the header
//! claims (`planet_testkit::fuzzing::raster_readers`).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| planet_testkit::fuzzing::raster_readers(data));
