//! The raster readers of planet-build (GeoTIFF with its GeoKeys and CRS,
//! SRTM .hgt naming) on untrusted bytes: no panic, and allocation bounded
//! by the tiff decoder's limits and the 1 MiB chunk cache whatever the
//! header claims (`planet_preprocess::geotiff::probe`).
#![no_main]
use libfuzzer_sys::fuzz_target;
use planet_preprocess::crs::{Crs, GeoKeys};

fuzz_target!(|data: &[u8]| {
    let path = std::env::temp_dir().join(format!("planet-fuzz-raster-{}.tif", std::process::id()));
    if std::fs::write(&path, data).is_ok() {
        let _ = planet_preprocess::geotiff::probe(&path);
    }
    // The GeoKey directory alone: u16 keys then f64 parameters.
    let (keys, rest) = data.split_at(data.len() / 2);
    let dir: Vec<u16> = keys
        .chunks_exact(2)
        .map(|b| u16::from_le_bytes([b[0], b[1]]))
        .collect();
    let doubles: Vec<f64> = rest
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
        .collect();
    let _ = Crs::from_geokeys(&GeoKeys::parse(&dir, &doubles));
});
