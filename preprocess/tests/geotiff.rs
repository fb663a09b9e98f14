//! GeoTIFF reader on small files written with the `tiff` encoder.

use planet_preprocess::geotiff::{GeoTiff, SampleKind};
use planet_preprocess::source::ElevationStack;
use planet_preprocess::GeoError;
use std::fs::File;
use std::path::Path;
use tiff::encoder::{colortype, TiffEncoder};
use tiff::tags::Tag;

/// Geo tags: pixel scale 1°, tie point (0,0) → (10°E, 50°N).
fn geo_keys(model: u16, raster: u16, extra: &[u16]) -> Vec<u16> {
    let n = 2 + extra.len() as u16 / 4;
    let mut k = vec![1, 1, 0, n, 1024, 0, 1, model, 1025, 0, 1, raster];
    k.extend_from_slice(extra);
    k
}

macro_rules! write_tiff {
    ($path:expr, $ct:ty, $w:expr, $h:expr, $data:expr, $keys:expr, $nodata:expr) => {{
        let mut enc = TiffEncoder::new(File::create($path).unwrap()).unwrap();
        let mut img = enc.new_image::<$ct>($w, $h).unwrap();
        let d = img.encoder();
        d.write_tag(Tag::ModelPixelScaleTag, &[1.0f64, 1.0, 0.0][..])
            .unwrap();
        d.write_tag(
            Tag::ModelTiepointTag,
            &[0.0f64, 0.0, 0.0, 10.0, 50.0, 0.0][..],
        )
        .unwrap();
        d.write_tag(Tag::GeoKeyDirectoryTag, &$keys[..]).unwrap();
        if let Some(nd) = $nodata {
            d.write_tag(Tag::GdalNodata, nd).unwrap();
        }
        img.write_data($data).unwrap();
    }};
}

#[test]
fn int16_with_nodata_pixel_is_area() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("a.tif");
    // 4 × 3, one void (-9999) at (1, 1).
    let data: Vec<i16> = vec![100, 110, 120, 130, 200, -9999, 220, 230, 300, 310, 320, 330];
    write_tiff!(
        &p,
        colortype::GrayI16,
        4,
        3,
        &data,
        geo_keys(2, 1, &[2048, 0, 1, 4326]),
        Some("-9999")
    );
    let t = GeoTiff::open(&p, 1 << 20).unwrap();
    assert_eq!(t.kind, SampleKind::I16);
    assert_eq!((t.width, t.height), (4, 3));
    assert!(!t.pixel_is_point);
    assert_eq!(t.nodata, Some(-9999.0));
    // Pixel-is-area: pixel (0,0)'s value is at its centre (10.5°E, 49.5°N).
    assert_eq!((t.x0, t.y0), (10.5, 49.5));
    assert!(t.elevation(1, 1).unwrap().is_nan());
    assert_eq!(t.elevation(2, 1).unwrap(), 220.0);
    let s = ElevationStack::open(&[p.as_path()], 1 << 20).unwrap();
    assert_eq!(s.sample(49.5, 10.5).unwrap(), 100.0);
    // Bilinear between pixel centres.
    assert!((s.sample(49.5, 11.0).unwrap() - 105.0).abs() < 1e-9);
    // The void is filled from its valid neighbours (mean of the ring), never -9999.
    let v = s.sample(48.5, 11.5).unwrap();
    let ring = [100.0, 110.0, 120.0, 200.0, 220.0, 300.0, 310.0, 320.0];
    let mean: f64 = ring.iter().sum::<f64>() / 8.0;
    assert!((v - mean).abs() < 1e-9, "{v} vs {mean}");
}

#[test]
fn srtm_minus_32768_is_void_and_filled_from_coarser() {
    let dir = tempfile::tempdir().unwrap();
    let fine = dir.path().join("fine.tif");
    let coarse = dir.path().join("coarse.tif");
    let data: Vec<i16> = vec![10, 10, 10, 10, -32768, 10, 10, 10, 10];
    write_tiff!(
        &fine,
        colortype::GrayI16,
        3,
        3,
        &data,
        geo_keys(2, 1, &[]),
        None::<&str>
    );
    // Coarser: 2 × 2 pixels of 2°, constant 500 m.
    let mut enc = TiffEncoder::new(File::create(&coarse).unwrap()).unwrap();
    let mut img = enc.new_image::<colortype::GrayI16>(6, 6).unwrap();
    let d = img.encoder();
    d.write_tag(Tag::ModelPixelScaleTag, &[2.0f64, 2.0, 0.0][..])
        .unwrap();
    d.write_tag(
        Tag::ModelTiepointTag,
        &[0.0f64, 0.0, 0.0, 6.0, 54.0, 0.0][..],
    )
    .unwrap();
    d.write_tag(Tag::GeoKeyDirectoryTag, &geo_keys(2, 1, &[])[..])
        .unwrap();
    img.write_data(&[500i16; 36]).unwrap();
    let s = ElevationStack::open(&[fine.as_path(), coarse.as_path()], 1 << 20).unwrap();
    assert_eq!(s.layers.len(), 2);
    // Centre of the void pixel: never -32768, and no pit down to the coarse
    // 500 m either: the coarse value plus the fine − coarse difference of
    // its neighbours (all -490 m), i.e. the surrounding 10 m (delta fill).
    assert!((s.sample(48.5, 11.5).unwrap() - 10.0).abs() < 1e-9);
    assert_eq!(s.sample(49.5, 10.5).unwrap(), 10.0);
}

#[test]
fn float32_pixel_is_point() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("f.tif");
    let data: Vec<f32> = vec![1.5, 2.5, 3.5, 4.5];
    write_tiff!(
        &p,
        colortype::Gray32Float,
        2,
        2,
        &data,
        geo_keys(2, 2, &[]),
        None::<&str>
    );
    let t = GeoTiff::open(&p, 1 << 20).unwrap();
    assert_eq!(t.kind, SampleKind::F32);
    assert!(t.pixel_is_point);
    // Pixel-is-point: pixel (0,0)'s value is exactly at the tie point.
    assert_eq!((t.x0, t.y0), (10.0, 50.0));
    let s = ElevationStack::open(&[p.as_path()], 1 << 20).unwrap();
    assert_eq!(s.sample(50.0, 10.0).unwrap(), 1.5);
    assert!((s.sample(49.5, 10.5).unwrap() - 3.0).abs() < 1e-9);
}

#[test]
fn unknown_or_unusable_crs_is_refused_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    // A projected CRS by an EPSG code that does not exist.
    let p = dir.path().join("unknown.tif");
    write_tiff!(
        &p,
        colortype::GrayI16,
        2,
        2,
        &[0i16; 4],
        geo_keys(1, 1, &[3072, 0, 1, 1234]),
        None::<&str>
    );
    match GeoTiff::open(&p, 1 << 20) {
        Err(e @ GeoError::WrongCrs { .. }) => {
            let m = e.to_string();
            assert!(m.contains("1234") && m.contains("unknown.tif"), "{m}")
        }
        Err(e) => panic!("unexpected error {e}"),
        Ok(_) => panic!("unknown CRS accepted"),
    }
    // NAD27 needs datum-shift grids PROJ 4 style transforms do not ship.
    let q = dir.path().join("nad27.tif");
    write_tiff!(
        &q,
        colortype::GrayI16,
        2,
        2,
        &[0i16; 4],
        geo_keys(2, 1, &[2048, 0, 1, 4267]),
        None::<&str>
    );
    match GeoTiff::open(&q, 1 << 20) {
        Err(e @ GeoError::WrongCrs { .. }) => {
            assert!(e.to_string().contains("EPSG:4267"), "{e}")
        }
        Err(e) => panic!("unexpected error {e}"),
        Ok(_) => panic!("NAD27 accepted"),
    }
    // A projected CRS by a known code opens.
    let u = dir.path().join("utm.tif");
    write_tiff!(
        &u,
        colortype::GrayI16,
        2,
        2,
        &[0i16; 4],
        geo_keys(1, 1, &[3072, 0, 1, 32610]),
        None::<&str>
    );
    let t = GeoTiff::open(&u, 1 << 20).unwrap();
    assert!(!t.crs.geographic);
}

#[test]
fn unsupported_sample_type_and_missing_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("u32.tif");
    write_tiff!(
        &p,
        colortype::Gray32,
        2,
        2,
        &[0u32; 4],
        geo_keys(2, 1, &[]),
        None::<&str>
    );
    match GeoTiff::open(&p, 1 << 20) {
        Err(e @ GeoError::UnsupportedSampleType { .. }) => {
            assert!(e.to_string().contains("unsupported sample type"))
        }
        Err(e) => panic!("unexpected error {e}"),
        Ok(_) => panic!("u32 accepted"),
    }
    // Colour used as elevation is refused too.
    let c = dir.path().join("rgb.tif");
    write_tiff!(
        &c,
        colortype::RGB8,
        2,
        2,
        &[0u8; 12],
        geo_keys(2, 1, &[]),
        None::<&str>
    );
    assert!(GeoTiff::open(&c, 1 << 20).is_ok());
    assert!(ElevationStack::open(&[c.as_path()], 1 << 20).is_err());
    assert!(matches!(
        GeoTiff::open(Path::new("/nonexistent/x.tif"), 1 << 20),
        Err(GeoError::Open { .. })
    ));
}

/// Writes a constant int16 raster of 2° pixels, 30 × 20, tie point (6°E,
/// 54°N): the coarse source under the 1° test rasters.
fn write_flat_coarse(path: &Path, value: i16) {
    let mut enc = TiffEncoder::new(File::create(path).unwrap()).unwrap();
    let mut img = enc.new_image::<colortype::GrayI16>(30, 20).unwrap();
    let d = img.encoder();
    d.write_tag(Tag::ModelPixelScaleTag, &[2.0f64, 2.0, 0.0][..])
        .unwrap();
    d.write_tag(
        Tag::ModelTiepointTag,
        &[0.0f64, 0.0, 0.0, 6.0, 54.0, 0.0][..],
    )
    .unwrap();
    d.write_tag(Tag::GeoKeyDirectoryTag, &geo_keys(2, 1, &[])[..])
        .unwrap();
    img.write_data(&vec![value; 600][..]).unwrap();
}

#[test]
fn void_on_steep_slope_over_low_coarse_is_no_pit() {
    let dir = tempfile::tempdir().unwrap();
    let fine = dir.path().join("slope.tif");
    let coarse = dir.path().join("low.tif");
    let (w, h) = (40usize, 30usize);
    let plane = |c: usize, r: usize| 500.0 + 150.0 * c as f64 + 40.0 * r as f64;
    let void = |c: usize, r: usize| (12..28).contains(&c) && (10..20).contains(&r);
    let data: Vec<i16> = (0..w * h)
        .map(|i| {
            let (c, r) = (i % w, i / w);
            if void(c, r) {
                -32768
            } else {
                plane(c, r) as i16
            }
        })
        .collect();
    write_tiff!(
        &fine,
        colortype::GrayI16,
        w as u32,
        h as u32,
        &data,
        geo_keys(2, 1, &[]),
        None::<&str>
    );
    // The coarse source is flat and 3 km below the whole slope.
    write_flat_coarse(&coarse, -3000);
    for stack in [vec![fine.as_path(), coarse.as_path()], vec![fine.as_path()]] {
        let s = ElevationStack::open(&stack, 1 << 20).unwrap();
        let fi = s.layers.len() - 1;
        // Boundary values: valid pixels 4-adjacent to the void.
        let (mut lo, mut hi) = (f64::MAX, f64::MIN);
        for r in 0..h {
            for c in 0..w {
                let next = [(1, 0), (-1, 0), (0, 1), (0, -1)].iter().any(|(dc, dr)| {
                    let (nc, nr) = (c as i64 + dc, r as i64 + dr);
                    nc >= 0
                        && nr >= 0
                        && (nc as usize) < w
                        && (nr as usize) < h
                        && void(nc as usize, nr as usize)
                });
                if !void(c, r) && next {
                    lo = lo.min(plane(c, r));
                    hi = hi.max(plane(c, r));
                }
            }
        }
        let tol = 1.0;
        let mut worst_plane = 0f64;
        for r in 0..h {
            for c in 0..w {
                if !void(c, r) {
                    continue;
                }
                let v = s.pixel(fi, c as i64, r as i64).unwrap();
                assert!(
                    v >= lo - tol && v <= hi + tol,
                    "{} layers: pixel ({c},{r}) = {v} outside [{lo}, {hi}]",
                    stack.len()
                );
                // A harmonic fill reproduces the plane it is cut from.
                worst_plane = worst_plane.max((v - plane(c, r)).abs());
                // Bilinear samples across the void stay in range too.
                let v = s
                    .sample(49.5 - r as f64 - 0.3, 10.5 + c as f64 + 0.7)
                    .unwrap();
                assert!(v >= lo - tol && v <= hi + tol, "sample {v}");
            }
        }
        assert!(
            worst_plane < 0.5,
            "worst departure from the plane {worst_plane}"
        );
        eprintln!(
            "{} layers: void fill within [{lo}, {hi}], worst |fill - plane| = {worst_plane:.4} m",
            stack.len()
        );
    }
}

/// A synthetic planetary GeoTIFF whose GeoKeys declare a user-defined
/// geographic CRS on a sphere of 1 737 400 m (GeographicType, datum and
/// ellipsoid 32767, GeogSemiMajorAxis and GeogSemiMinorAxis in the double
/// parameters): it builds a sphere of that radius with no option, and its
/// heights are not converted with an Earth geoid.
#[test]
fn user_defined_moon_sphere_builds_a_sphere_of_its_radius() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("moon.tif");
    // 36 × 18 pixels of 10°, global; heights vary with longitude.
    let data: Vec<f32> = (0..18 * 36)
        .map(|i| (i % 36) as f32 * 100.0 - 1000.0)
        .collect();
    let keys: Vec<u16> = vec![
        1, 1, 0, 7, //
        1024, 0, 1, 2, // GTModelType geographic
        1025, 0, 1, 1, // pixel-is-area
        2048, 0, 1, 32767, // GeographicType user-defined
        2050, 0, 1, 32767, // GeogGeodeticDatum user-defined
        2054, 0, 1, 9102, // degrees
        2057, 34736, 1, 0, // GeogSemiMajorAxis = doubles[0]
        2058, 34736, 1, 1, // GeogSemiMinorAxis = doubles[1]
    ];
    {
        let mut enc = TiffEncoder::new(File::create(&p).unwrap()).unwrap();
        let mut img = enc.new_image::<colortype::Gray32Float>(36, 18).unwrap();
        let d = img.encoder();
        d.write_tag(Tag::ModelPixelScaleTag, &[10.0f64, 10.0, 0.0][..])
            .unwrap();
        d.write_tag(
            Tag::ModelTiepointTag,
            &[0.0f64, 0.0, 0.0, -180.0, 90.0, 0.0][..],
        )
        .unwrap();
        d.write_tag(Tag::GeoKeyDirectoryTag, &keys[..]).unwrap();
        d.write_tag(Tag::GeoDoubleParamsTag, &[1_737_400.0f64, 1_737_400.0][..])
            .unwrap();
        img.write_data(&data).unwrap();
    }
    let t = GeoTiff::open(&p, 1 << 20).unwrap();
    assert_eq!(
        t.crs.datum,
        planet_core::Datum::Sphere {
            radius: 1_737_400.0
        }
    );
    let out = dir.path().join("moon.db");
    planet_preprocess::build_rasters(&[p.as_path()], None, &out, &Default::default()).unwrap();
    let s = planet_preprocess::db::Sampler::open(&out).unwrap();
    assert_eq!(
        s.header().datum,
        planet_core::Datum::Sphere {
            radius: 1_737_400.0
        }
    );
    assert_eq!(
        s.header().datum.body(),
        Some(planet_core::datum::Body::Moon)
    );
    assert_eq!(
        s.vertical_datum(),
        Some(planet_preprocess::geoid::VerticalDatum::Ellipsoid)
    );
    // Pixel (18, 9)'s value (800 m) is at its centre (5°E, 5°S): no geoid.
    let v = s.sample(-5.0, 5.0).unwrap().metres;
    assert!((v - 800.0).abs() < 1.0, "{v}");
}
