//! Real-world inputs made by GDAL's own tools from the real SRTM tile in
//! ../shared/data: the tile re-projected to UTM and to polar stereographic
//! (`gdalwarp`), as an SRTM `.hgt` file (`gdal_translate -of SRTMHGT`), on
//! the Moon (`gdal_translate -a_srs` with a sphere), and EGM96 compared with
//! PROJ's `cs2cs` (NGA's 15′ grid). These tests need gdal-bin and proj-bin
//! (`.ci/run` installs them) and FAIL, saying so, where they are missing;
//! like the other real-data tests they skip with a note where ../shared/data
//! is absent (and fail under `PLANET_CI=1`, `common::skip_or_fail`).
//!
//! Agreement bound for re-projected data, derived: the database value at a
//! point P is the bilinear interpolation of the 4 samples at the corners of
//! its leaf cell (each within `d_leaf` of P); each corner sample is the
//! bilinear interpolation of the 4 re-projected pixels around it (within
//! `d_w`, their diagonal), rounded to 1 m; each re-projected pixel is
//! gdalwarp's bilinear value, a convex combination of source pixels within
//! `d_s` of it (at most two source pixel diagonals, the kernel widened
//! where a target pixel spans more than one source pixel). Every step is a
//! convex combination, so the database value lies within [min, max] of the
//! source pixels within `R = d_leaf + d_w + d_s` of P, ±0.5 m of rounding,
//! and so does the source's own bilinear value at P. Hence
//! `|db − src| ≤ relief(P, R) + 0.5 m`. With 90 m target pixels, level-11
//! leaves (≤ 76 m samples, diagonal ≤ 108 m) and 3″ source pixels
//! (diagonal ≤ 110 m): R = 108 + 127 + 220 ≈ 455 m; the test uses 500 m.
//! The re-projection itself (where a lat/lon falls in the projected raster)
//! is compared with PROJ's `gdaltransform` to 10⁻⁴ pixel (9 mm).

mod common;

use planet_preprocess::db::Sampler;
use planet_preprocess::geoid::{Egm96Grid, VerticalDatum};
use planet_preprocess::geotiff::{GeoTiff, GridPoints};
use planet_preprocess::source::ElevationStack;
use planet_preprocess::{build_rasters, RasterOptions};
use rand::{Rng, SeedableRng};
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

fn rainier() -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/mt_rainier_90m.tif");
    p.exists().then_some(p)
}

/// Run a GDAL/PROJ tool, feeding `stdin`; its stdout. Fails the test,
/// naming the package, when the tool is not installed.
fn tool(name: &str, args: &[&str], stdin: &str) -> String {
    let mut child = match Command::new(name)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
    {
        Ok(c) => c,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => panic!(
            "`{name}` not found: this test makes its inputs with gdal-bin and checks them \
             with proj-bin (apt-get install gdal-bin proj-bin; .ci/run installs them)"
        ),
        Err(e) => panic!("cannot run {name}: {e}"),
    };
    let mut sin = child.stdin.take().expect("stdin");
    sin.write_all(stdin.as_bytes()).expect("write stdin");
    drop(sin);
    let out = child.wait_with_output().expect("wait");
    assert!(
        out.status.success(),
        "{name} {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn planet_build(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_planet-build"))
        .args(args)
        .output()
        .expect("run planet-build")
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// Max − min of the source pixels within `r_m` metres of (lat, lon).
fn relief(src: &GeoTiff, lat: f64, lon: f64, r_m: f64) -> f64 {
    let (c, r) = src.pixel_of(lat, lon);
    let dr = (r_m / 111_000.0 / src.dy).ceil() as i64;
    let dc = (r_m / (111_000.0 * lat.to_radians().cos()) / src.dx).ceil() as i64;
    let (mut lo, mut hi) = (f64::MAX, f64::MIN);
    for y in r.floor() as i64 - dr..=r.ceil() as i64 + dr {
        for x in c.floor() as i64 - dc..=c.ceil() as i64 + dc {
            let v = src.elevation(x, y).expect("pixel") as f64;
            if !v.is_nan() {
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
    }
    hi - lo
}

/// The last line of `planet-build sample`, and the ellipsoidal height line.
fn cli_sample(db: &Path, lat: f64, lon: f64) -> (f64, f64) {
    let out = planet_build(&[
        "sample",
        s(db),
        "--lat",
        &lat.to_string(),
        "--lon",
        &lon.to_string(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    let last: f64 = text
        .lines()
        .last()
        .expect("a line")
        .trim()
        .parse()
        .expect("number");
    let ell: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("ellipsoidal_height_m "))
        .expect("ellipsoidal line")
        .trim()
        .parse()
        .expect("number");
    (ell, last)
}

#[test]
fn utm_and_polar_stereographic_tiles_build_and_agree_with_the_source() {
    let Some(rainier) = rainier() else {
        common::skip_or_fail("../shared/data not found");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // A 0.25° crop of the real tile keeps the test quick.
    let crop = dir.path().join("crop.tif");
    tool(
        "gdal_translate",
        &[
            "-q",
            "-srcwin",
            "450",
            "450",
            "300",
            "300",
            s(&rainier),
            s(&crop),
        ],
        "",
    );
    let src = ElevationStack::open(&[crop.as_path()], 64 << 20).unwrap();
    let st = &src.layers[0].tiff;
    let (la0, la1, lo0, lo1) = st.bounds();
    for (name, srs) in [("utm", "EPSG:32610"), ("polar", "EPSG:3413")] {
        let warped = dir.path().join(format!("{name}.tif"));
        tool(
            "gdalwarp",
            &[
                "-q",
                "-t_srs",
                srs,
                "-r",
                "bilinear",
                "-tr",
                "90",
                "90",
                s(&crop),
                s(&warped),
            ],
            "",
        );
        let t = GeoTiff::open(&warped, 64 << 20).unwrap();
        assert!(!t.crs.geographic, "{name}: {:?}", t.crs);
        // (a) Where latitude/longitude fall in the projected raster, against
        // PROJ (gdaltransform's pixel/line has pixel corners at integers).
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let pts: Vec<(f64, f64)> = (0..300)
            .map(|_| {
                (
                    rng.random_range(la0 + 0.03..la1 - 0.03),
                    rng.random_range(lo0 + 0.03..lo1 - 0.03),
                )
            })
            .collect();
        let input: String = pts.iter().map(|(la, lo)| format!("{lo} {la}\n")).collect();
        let proj = tool(
            "gdaltransform",
            &["-i", "-t_srs", "EPSG:4326", s(&warped)],
            &input,
        );
        let mut worst_px: f64 = 0.0;
        for ((la, lo), line) in pts.iter().zip(proj.lines()) {
            let v: Vec<f64> = line
                .split_whitespace()
                .map(|x| x.parse().unwrap())
                .collect();
            let (c, r) = t.pixel_of(*la, *lo);
            worst_px = worst_px
                .max((c + 0.5 - v[0]).abs())
                .max((r + 0.5 - v[1]).abs());
        }
        assert!(worst_px < 1e-4, "{name}: {worst_px} pixel from PROJ");
        // (b) The build, against the geographic source, within the bound.
        let db = dir.path().join(format!("{name}.db"));
        build_rasters(
            &[warped.as_path()],
            None,
            &db,
            &RasterOptions {
                vertical: vec![VerticalDatum::Ellipsoid],
                ..Default::default()
            },
        )
        .unwrap();
        let sampler = Sampler::open(&db).unwrap();
        let mut cache = HashMap::new();
        let (mut n, mut sum, mut worst_excess) = (0, 0.0, f64::MIN);
        for _ in 0..1500 {
            let lat = rng.random_range(la0 + 0.03..la1 - 0.03);
            let lon = rng.random_range(lo0 + 0.03..lo1 - 0.03);
            let r = sampler.sample_cached(lat, lon, &mut cache).unwrap();
            assert_eq!(r.leaf.level, 11, "{name}");
            let want = src.sample(lat, lon).unwrap();
            let err = (r.metres - want).abs();
            let bound = relief(st, lat, lon, 500.0) + 0.5;
            assert!(
                err <= bound,
                "{name} at {lat} {lon}: db {} src {want} bound {bound}",
                r.metres
            );
            worst_excess = worst_excess.max(err - bound);
            sum += err;
            n += 1;
        }
        let mean = sum / n as f64;
        eprintln!(
            "{name}: {n} points, mean |db − src| {mean:.2} m, pixel error vs PROJ {worst_px:.1e}"
        );
        // The command line prints the same value on its last line.
        let (lat, lon) = (0.5 * (la0 + la1), 0.5 * (lo0 + lo1));
        let (ell, last) = cli_sample(&db, lat, lon);
        let want = sampler.sample(lat, lon).unwrap().metres;
        assert!((last - want).abs() < 1e-9 && (ell - want).abs() < 1e-9);
    }
}

#[test]
fn srtm_hgt_reads_like_its_geotiff_and_converts_egm96() {
    let Some(rainier) = rainier() else {
        common::skip_or_fail("../shared/data not found");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let hgt = dir.path().join("N46W122.hgt");
    tool(
        "gdal_translate",
        &["-q", "-of", "SRTMHGT", s(&rainier), s(&hgt)],
        "",
    );
    let h = GeoTiff::open(&hgt, 64 << 20).unwrap();
    let t = GeoTiff::open(&rainier, 64 << 20).unwrap();
    assert_eq!((h.width, h.height), (1201, 1201));
    assert_eq!(h.vertical, Some(VerticalDatum::Egm96));
    // Same pixels at the same places.
    for r in (0..1201).step_by(7) {
        for c in 0..1201 {
            let (a, b) = (h.elevation(c, r).unwrap(), t.elevation(c, r).unwrap());
            assert!(
                a == b || (a.is_nan() && b.is_nan()),
                "({c}, {r}): {a} vs {b}"
            );
        }
    }
    for &(la, lo) in &[(46.5, -121.5), (46.01, -121.99), (46.99, -121.01)] {
        let (p, q) = (h.pixel_of(la, lo), t.pixel_of(la, lo));
        assert!((p.0 - q.0).abs() < 1e-6 && (p.1 - q.1).abs() < 1e-6);
    }
    // Build with no flag: EPSG:4326 int16 → EGM96 as the file type says;
    // `sample` prints the ellipsoidal height and, last, the EGM96 height.
    let db = dir.path().join("hgt.db");
    let out = planet_build(&["build", "--elevation", s(&hgt), "--out", s(&db), "--quiet"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("vertical datum egm96"), "{err}");
    let src = ElevationStack::open(&[hgt.as_path()], 64 << 20).unwrap();
    let geoid = Egm96Grid::new();
    let mut gr = geoid.reader();
    for &(la, lo) in &[(46.85, -121.76), (46.2, -121.3), (46.7, -121.9)] {
        let (ell, last) = cli_sample(&db, la, lo);
        let n = gr.undulation(la, lo, 0.25);
        assert!((-25.0..-15.0).contains(&n), "N = {n}");
        // The database holds H + N at its samples; last line is that − N.
        assert!((ell - n - last).abs() < 1e-6, "{ell} {n} {last}");
        let want = src.sample(la, lo).unwrap();
        let bound = relief(&h, la, lo, 300.0) + 0.5 + 0.01;
        assert!(
            (last - want).abs() <= bound,
            "{la} {lo}: {last} vs {want} (bound {bound})"
        );
    }
    // One vertical datum per input, in order; a count that fits neither
    // one nor every input is refused.
    let both = ElevationStack::open_with(
        &[hgt.as_path(), rainier.as_path()],
        64 << 20,
        &[VerticalDatum::Ellipsoid, VerticalDatum::Egm2008],
        &mut |_| {},
    )
    .unwrap();
    let mut got: Vec<(String, VerticalDatum)> = both
        .layers
        .iter()
        .map(|l| (l.tiff.path().display().to_string(), l.vertical))
        .collect();
    got.sort_by(|a, b| a.0.cmp(&b.0));
    assert!(got
        .iter()
        .any(|(p, v)| p.ends_with(".hgt") && *v == VerticalDatum::Ellipsoid));
    assert!(got
        .iter()
        .any(|(p, v)| p.ends_with(".tif") && *v == VerticalDatum::Egm2008));
    let e = build_rasters(
        &[hgt.as_path()],
        None,
        &dir.path().join("x.db"),
        &RasterOptions {
            vertical: vec![VerticalDatum::Egm96, VerticalDatum::Egm96],
            ..Default::default()
        },
    )
    .expect_err("two datums for one input refused")
    .to_string();
    assert!(
        e.contains("2 vertical datums for 1 elevation inputs"),
        "{e}"
    );
    // Truncated and misnamed files are refused, naming the file.
    let bad = dir.path().join("N46W123.hgt");
    std::fs::write(&bad, vec![0u8; 1000]).unwrap();
    let e = GeoTiff::open(&bad, 1 << 20)
        .err()
        .expect("truncated hgt refused")
        .to_string();
    assert!(e.contains("N46W123.hgt") && e.contains("truncated"), "{e}");
    let misnamed = dir.path().join("tile.hgt");
    std::fs::copy(&hgt, &misnamed).unwrap();
    let e = GeoTiff::open(&misnamed, 1 << 20)
        .err()
        .expect("misnamed refused")
        .to_string();
    assert!(e.contains("tile.hgt") && e.contains("N46W122"), "{e}");
}

#[test]
fn egm96_agrees_with_proj_cs2cs_at_1000_points_within_5_cm() {
    // 1000 points in four 2° boxes (Rainier, the Himalaya, New Guinea, the
    // Indian Ocean low): PROJ's EGM96 (NGA's 15′ grid, egm96_15.gtx, from
    // Debian's proj-data) against the egm96 crate's synthesis on 15′ nodes.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(96);
    let boxes = [(46.0, -122.5), (27.0, 85.5), (-6.0, 140.0), (-2.0, 78.0)];
    let pts: Vec<(f64, f64)> = (0..1000)
        .map(|i| {
            let (a, b) = boxes[i % 4];
            (
                a + rng.random_range(0.0..2.0),
                b + rng.random_range(0.0..2.0),
            )
        })
        .collect();
    let input: String = pts
        .iter()
        .map(|(la, lo)| format!("{la} {lo} 0\n"))
        .collect();
    let out = tool(
        "cs2cs",
        &["-f", "%.6f", "EPSG:4326+5773", "EPSG:4979"],
        &input,
    );
    let g = Egm96Grid::new();
    let mut r = g.reader();
    let mut worst: f64 = 0.0;
    let mut lines = 0;
    for ((la, lo), line) in pts.iter().zip(out.lines()) {
        let n_proj: f64 = line
            .split_whitespace()
            .nth(2)
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| {
                panic!("cs2cs printed {line:?}: is proj-data's egm96_15.gtx installed?")
            });
        let n = r.undulation(*la, *lo, 0.25);
        worst = worst.max((n - n_proj).abs());
        lines += 1;
    }
    assert_eq!(lines, 1000);
    assert!(worst < 0.05, "EGM96 differs from PROJ by {worst} m");
    eprintln!("EGM96 vs PROJ at 1000 points: at most {:.4} m", worst);
}

/// A GeoTIFF on a user-defined sphere of 1 737 400 m (the Moon) builds a
/// sphere of that radius with no flag; colour alone builds too; mixing
/// bodies is refused naming both files.
#[test]
fn moon_sphere_from_gdal_keys_colour_alone_and_mixed_bodies() {
    let Some(rainier) = rainier() else {
        common::skip_or_fail("../shared/data not found");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // A small raster re-labelled onto the Moon's sphere by GDAL (so the
    // GeoKeys are GDAL's own user-defined ones).
    let moon = dir.path().join("moon.tif");
    tool(
        "gdal_translate",
        &[
            "-q",
            "-outsize",
            "200",
            "200",
            "-a_srs",
            "+proj=longlat +a=1737400 +b=1737400 +no_defs",
            s(&rainier),
            s(&moon),
        ],
        "",
    );
    let db = dir.path().join("moon.db");
    let out = planet_build(&["build", "--elevation", s(&moon), "--out", s(&db), "--quiet"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = planet_build(&["inspect", "--json", s(&db)]);
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(j["datum"]["kind"], "sphere");
    assert_eq!(j["datum"]["semi_major_axis_m"], 1_737_400.0);
    assert_eq!(j["datum"]["body"], "Moon");
    assert!(j["datum"]["inverse_flattening"].is_null());
    // Not converted with an Earth geoid: heights are the file's.
    let (ell, last) = cli_sample(&db, 46.5, -121.5);
    assert_eq!(ell, last);
    // An RGB colour map on the same sphere, alone.
    let colour = dir.path().join("moon_rgb.tif");
    tool(
        "gdal_translate",
        &[
            "-q",
            "-ot",
            "Byte",
            "-scale",
            "0",
            "4400",
            "0",
            "255",
            "-b",
            "1",
            "-b",
            "1",
            "-b",
            "1",
            s(&moon),
            s(&colour),
        ],
        "",
    );
    let cdb = dir.path().join("colour.db");
    let out = planet_build(&["build", "--colour", s(&colour), "--out", s(&cdb), "--quiet"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = planet_build(&["inspect", "--json", s(&cdb)]);
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(j["datum"]["semi_major_axis_m"], 1_737_400.0);
    assert!(j["colour"]["records"].as_u64().unwrap_or(0) > 6, "{j}");
    let out = planet_build(&["verify", s(&cdb)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    let (ell, _) = cli_sample(&cdb, 46.5, -121.5);
    assert_eq!(ell, 0.0, "colour alone lies on the datum's surface");
    // The Moon's elevation with an Earth colour map: refused, naming both.
    let out = planet_build(&[
        "build",
        "--elevation",
        s(&moon),
        "--colour",
        s(&PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/data/earth_bluemarble_2048x1024.tif")),
        "--out",
        s(&dir.path().join("mixed.db")),
        "--quiet",
    ]);
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        e.contains("moon.tif") && e.contains("earth_bluemarble") && e.contains("Moon"),
        "{e}"
    );
    assert!(!dir.path().join("mixed.db").exists());
}

/// Every projection family the issue names, as GDAL writes it (EPSG codes
/// and user-defined keys from PROJ strings), and geographic CRSs on other
/// Earth datums: where a latitude/longitude falls in the raster agrees with
/// PROJ's `gdaltransform` to 10⁻⁴ pixel.
#[test]
fn projection_families_map_like_proj() {
    let Some(rainier) = rainier() else {
        common::skip_or_fail("../shared/data not found");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let crop = dir.path().join("crop.tif");
    tool(
        "gdal_translate",
        &[
            "-q",
            "-srcwin",
            "500",
            "500",
            "100",
            "100",
            s(&rainier),
            s(&crop),
        ],
        "",
    );
    let c = GeoTiff::open(&crop, 1 << 20).unwrap();
    let (la0, la1, lo0, lo1) = c.bounds();
    let cases: &[(&str, &str)] = &[
        ("tmerc", "+proj=tmerc +lat_0=46 +lon_0=-121 +k=0.9996 +x_0=500000 +y_0=0 +datum=WGS84 +units=m"),
        ("lcc2sp", "+proj=lcc +lat_1=45 +lat_2=48 +lat_0=46 +lon_0=-121 +x_0=1000 +y_0=2000 +datum=WGS84 +units=m"),
        ("lcc_ft", "EPSG:2285"),
        ("albers", "EPSG:5070"),
        ("albers_user", "+proj=aea +lat_1=40 +lat_2=50 +lat_0=45 +lon_0=-120 +ellps=GRS80 +units=m"),
        ("merc", "EPSG:3395"),
        ("webmerc", "EPSG:3857"),
        ("stere_user", "+proj=stere +lat_0=90 +lat_ts=60 +lon_0=-100 +datum=WGS84 +units=m"),
        ("nad83", "EPSG:4269"),
        ("etrs89", "EPSG:4258"),
    ];
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    for (name, srs) in cases {
        let out = dir.path().join(format!("{name}.tif"));
        tool("gdalwarp", &["-q", "-t_srs", srs, s(&crop), s(&out)], "");
        let t = GeoTiff::open(&out, 1 << 20).unwrap_or_else(|e| panic!("{name} ({srs}): {e}"));
        let pts: Vec<(f64, f64)> = (0..100)
            .map(|_| (rng.random_range(la0..la1), rng.random_range(lo0..lo1)))
            .collect();
        let input: String = pts.iter().map(|(la, lo)| format!("{lo} {la}\n")).collect();
        let proj = tool(
            "gdaltransform",
            &["-i", "-t_srs", "EPSG:4326", s(&out)],
            &input,
        );
        let mut worst: f64 = 0.0;
        for ((la, lo), line) in pts.iter().zip(proj.lines()) {
            let v: Vec<f64> = line
                .split_whitespace()
                .map(|x| x.parse().unwrap())
                .collect();
            let (c, r) = t.pixel_of(*la, *lo);
            worst = worst
                .max((c + 0.5 - v[0]).abs())
                .max((r + 0.5 - v[1]).abs());
        }
        assert!(
            worst < 1e-4,
            "{name} ({srs}, read as {:?}): {worst} pixel from PROJ",
            t.crs
        );
        assert!(t.covers(0.5 * (la0 + la1), 0.5 * (lo0 + lo1)), "{name}");
        // The approximate grid mapping (gdalwarp's -et 0.125) stays within
        // 0.125 pixel of the exact one, on a 65 × 65 grid over the tile
        // and a margin around it (points outside the box map to NaN).
        let n = 65;
        let (m_la, m_lo) = (0.2 * (la1 - la0), 0.2 * (lo1 - lo0));
        let ll: Vec<(f64, f64)> = (0..n * n)
            .map(|k| {
                let (i, j) = ((k % n) as f64 / 64.0, (k / n) as f64 / 64.0);
                (
                    la1 + m_la - (la1 - la0 + 2.0 * m_la) * j,
                    lo0 - m_lo + (lo1 - lo0 + 2.0 * m_lo) * i,
                )
            })
            .collect();
        let dirs: Vec<[f64; 3]> = ll
            .iter()
            .map(|&(la, lo)| {
                planet_core::cube::direction_from_lat_lon(la.to_radians(), lo.to_radians())
            })
            .collect();
        let mut approx = Vec::new();
        t.pixels_of_grid(&mut GridPoints::new(&dirs), n, n, &mut approx);
        let (mut worst_approx, mut inside): (f64, usize) = (0.0, 0);
        for (&(la, lo), a) in ll.iter().zip(&approx) {
            let e = t.pixel_of(la, lo);
            if t.covers(la, lo) {
                inside += 1;
                assert!(
                    t.covers_pixel(a.0, a.1) || (e.0 - a.0).abs().max((e.1 - a.1).abs()) < 0.2,
                    "{name}: covered point {la} {lo} lost"
                );
                worst_approx = worst_approx.max((e.0 - a.0).abs()).max((e.1 - a.1).abs());
            }
        }
        assert!(inside > 1000, "{name}: {inside}");
        assert!(
            worst_approx <= 0.125,
            "{name}: approximate mapping off by {worst_approx} px"
        );
    }
}

/// The leaves of a raster plan's elevation tree, sorted.
fn sorted_leaves(p: &planet_preprocess::plan::Plan) -> Vec<planet_core::BlockId> {
    match p {
        planet_preprocess::plan::Plan::Explicit { split, .. } => {
            let mut l = planet_preprocess::plan::leaves(split);
            l.sort();
            l
        }
        _ => panic!("raster plans are explicit"),
    }
}

/// Open file descriptors of this process (Linux), if readable.
fn open_fds() -> Option<usize> {
    std::fs::read_dir("/proc/self/fd").ok().map(|d| d.count())
}

/// Many tiles: the real tile cut by `gdal_translate -srcwin` into 16 × 16
/// tiles of 76 pixels (one pixel shared with each neighbour, as SRTM tiles
/// share their edges), given as a directory over ETOPO5. Every leaf grid
/// sample whose source pixels hold no void equals the one built from the
/// whole tile over ETOPO5 (the tiles, finer, win over ETOPO5 everywhere
/// they cover, and bilinear inside any tile reads the same 4 pixels), the
/// trees have the same shape, the raster readers keep at most
/// `MAX_IDLE_DECODERS` files open, and the command-line build from the
/// directory stays under its `--max-memory` and verifies.
#[test]
fn a_directory_of_many_tiles_builds_like_the_whole_tile() {
    use planet_preprocess::build::GridSource;
    use planet_preprocess::geotiff::MAX_IDLE_DECODERS;
    use planet_preprocess::source::{elevation_sample_lat_lon, ELEVATION_WIDTH};
    let Some(rainier) = rainier() else {
        common::skip_or_fail("../shared/data not found");
        return;
    };
    let etopo = rainier.with_file_name("earth_etopo5_30arcmin.tif");
    let dir = tempfile::tempdir().unwrap();
    let tiles = dir.path().join("tiles");
    std::fs::create_dir(&tiles).unwrap();
    let (n, step, size) = (16usize, 75usize, 76usize);
    let jobs: Vec<(usize, usize)> = (0..n).flat_map(|j| (0..n).map(move |i| (i, j))).collect();
    std::thread::scope(|sc| {
        for part in jobs.chunks(jobs.len().div_ceil(4)) {
            let (rainier, tiles) = (&rainier, &tiles);
            sc.spawn(move || {
                for &(i, j) in part {
                    let out = tiles.join(format!("r{j:02}/t{j:02}_{i:02}.tif"));
                    std::fs::create_dir_all(out.parent().unwrap()).unwrap();
                    let (x, y, sz) = (
                        (i * step).to_string(),
                        (j * step).to_string(),
                        size.to_string(),
                    );
                    tool(
                        "gdal_translate",
                        &["-q", "-srcwin", &x, &y, &sz, &sz, s(rainier), s(&out)],
                        "",
                    );
                }
            });
        }
    });
    let tile_paths = planet_preprocess::inputs::expand(std::slice::from_ref(&tiles)).unwrap();
    assert_eq!(tile_paths.len(), n * n);
    let opts = RasterOptions {
        vertical: vec![VerticalDatum::Ellipsoid],
        ..Default::default()
    };
    let (whole, whole_plan) =
        planet_preprocess::open_rasters(&[etopo.as_path(), rainier.as_path()], None, &opts)
            .unwrap();
    let fds_before = open_fds();
    let mut stack: Vec<&Path> = vec![etopo.as_path()];
    stack.extend(tile_paths.iter().map(|p| p.as_path()));
    let (tiled, tiled_plan) = planet_preprocess::open_rasters(&stack, None, &opts).unwrap();
    assert_eq!(tiled.elevation.layers.len(), n * n + 1);
    let deepest: Vec<_> = sorted_leaves(&whole_plan)
        .into_iter()
        .filter(|b| b.level == whole_plan.max_level())
        .collect();
    assert_eq!(
        sorted_leaves(&whole_plan),
        sorted_leaves(&tiled_plan),
        "tree shapes differ"
    );
    let w = ELEVATION_WIDTH;
    let src = &whole.elevation.layers[1].tiff;
    let (mut a, mut b) = (vec![0i16; (w + 1) * (w + 1)], vec![0i16; (w + 1) * (w + 1)]);
    let (mut same, mut compared) = (0usize, 0usize);
    for &blk in &deepest {
        whole.elevation_leaf(blk, &mut a).unwrap();
        tiled.elevation_leaf(blk, &mut b).unwrap();
        for j in 0..=w {
            for i in 0..=w {
                let (la, lo) = elevation_sample_lat_lon(blk, w, i, j);
                let (c, r) = src.pixel_of(la.to_degrees(), lo.to_degrees());
                let (c0, r0) = (c.floor() as i64, r.floor() as i64);
                let clean = (0..2)
                    .all(|dy| (0..2).all(|dx| !src.elevation(c0 + dx, r0 + dy).unwrap().is_nan()));
                if !clean {
                    continue;
                }
                compared += 1;
                let k = j * (w + 1) + i;
                assert_eq!(a[k], b[k], "{blk:?} ({i}, {j}) at {la} {lo}");
                same += 1;
            }
        }
    }
    assert!(compared > 500_000, "{compared} samples compared");
    // Point samples (the index's point queries) agree too.
    let (la0, la1, lo0, lo1) = src.bounds();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(16);
    let mut points = 0;
    for _ in 0..3000 {
        let (la, lo) = (rng.random_range(la0..la1), rng.random_range(lo0..lo1));
        let (c, r) = src.pixel_of(la, lo);
        let (c0, r0) = (c.floor() as i64, r.floor() as i64);
        if (0..2).all(|dy| (0..2).all(|dx| !src.elevation(c0 + dx, r0 + dy).unwrap().is_nan())) {
            let (x, y) = (
                whole.elevation.sample(la, lo).unwrap(),
                tiled.elevation.sample(la, lo).unwrap(),
            );
            // The same 4 pixels; the fractions differ by rounding only
            // (pixel coordinates taken from another tile's origin).
            assert!((x - y).abs() < 1e-6, "point {la} {lo}: {x} vs {y}");
            points += 1;
        }
    }
    assert!(points > 2500, "{points}");
    eprintln!(
        "{same} of {compared} void-free samples equal over {} leaves",
        deepest.len()
    );
    if let (Some(before), Some(after)) = (fds_before, open_fds()) {
        assert!(
            after <= before + MAX_IDLE_DECODERS + 16,
            "{} files open for {} tiles",
            after.saturating_sub(before),
            n * n
        );
    }
    drop(tiled);
    // The command line: a directory, under a tight memory bound.
    let db = dir.path().join("tiles.db");
    let bound_mib = 32u64;
    let out = planet_build(&[
        "build",
        "--elevation",
        s(&etopo),
        s(&tiles),
        "--vertical-datum",
        "ellipsoid",
        "--max-memory",
        &bound_mib.to_string(),
        "--report-memory",
        "--quiet",
        "--out",
        s(&db),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    if let Some(kib) = text
        .lines()
        .find_map(|l| l.strip_prefix("peak_rss_kib "))
        .and_then(|v| v.trim().parse::<u64>().ok())
    {
        eprintln!("{} tiles: peak {kib} KiB, bound {bound_mib} MiB", n * n);
        assert!(
            kib < bound_mib * 1024,
            "peak {kib} KiB over {bound_mib} MiB"
        );
    }
    planet_preprocess::db::verify(&db).unwrap();
}

/// A Cloud-Optimized GeoTIFF (`gdal_translate -of COG`: 256² tiles, LZW,
/// overviews 600², 300², 150²) reads pixel for pixel like the tile it was
/// made from; a tree as deep as the tile reads the full image, and one
/// capped two levels above it reads the 300² overview (said in a note),
/// whose every leaf grid equals the one built from that overview extracted
/// by GDAL itself (`gdal_translate -ovr 1`).
#[test]
fn cog_overviews_serve_coarser_trees() {
    use planet_preprocess::build::GridSource;
    use planet_preprocess::source::ELEVATION_WIDTH;
    let Some(rainier) = rainier() else {
        common::skip_or_fail("../shared/data not found");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cog = dir.path().join("rainier-cog.tif");
    let ovr = dir.path().join("rainier-ovr1.tif");
    tool(
        "gdal_translate",
        &[
            "-q",
            "-of",
            "COG",
            "-co",
            "BLOCKSIZE=256",
            s(&rainier),
            s(&cog),
        ],
        "",
    );
    tool("gdal_translate", &["-q", "-ovr", "1", s(&cog), s(&ovr)], "");
    let plain = GeoTiff::open(&rainier, 64 << 20).unwrap();
    let tiled = GeoTiff::open(&cog, 64 << 20).unwrap();
    let sizes: Vec<(u32, u32)> = tiled.overviews().iter().map(|o| (o.1, o.2)).collect();
    assert_eq!(sizes, vec![(600, 600), (300, 300), (150, 150)]);
    for r in 0..plain.height as i64 {
        for c in 0..plain.width as i64 {
            let (a, b) = (
                plain.elevation(c, r).unwrap(),
                tiled.elevation(c, r).unwrap(),
            );
            assert!(
                a == b || (a.is_nan() && b.is_nan()),
                "pixel ({c}, {r}): {a} vs {b}"
            );
        }
    }
    let open = |p: &Path, max_level: u8, notes: &mut Vec<String>| {
        planet_preprocess::open_rasters_noting(
            &[p],
            None,
            &RasterOptions {
                max_level,
                vertical: vec![VerticalDatum::Ellipsoid],
                ..Default::default()
            },
            &mut |n| notes.push(n),
        )
        .unwrap()
    };
    let mut notes = Vec::new();
    let (full, _) = open(&cog, 16, &mut notes);
    assert_eq!(full.elevation.layers[0].tiff.width, 1201);
    assert!(notes.iter().all(|n| !n.contains("overview")), "{notes:?}");
    let (capped, plan) = open(&cog, 9, &mut notes);
    let (extracted, plan_x) = open(&ovr, 9, &mut Vec::new());
    let t = &capped.elevation.layers[0].tiff;
    assert_eq!((t.width, t.height, t.image()), (300, 300, 2));
    assert!(
        notes.iter().any(|n| n.contains("overview 300 × 300")),
        "{notes:?}"
    );
    assert_eq!(plan.max_level(), 9);
    assert_eq!(sorted_leaves(&plan), sorted_leaves(&plan_x));
    let w = ELEVATION_WIDTH;
    let (mut a, mut b) = (vec![0i16; (w + 1) * (w + 1)], vec![0i16; (w + 1) * (w + 1)]);
    for blk in sorted_leaves(&plan).into_iter().filter(|b| b.level == 9) {
        capped.elevation_leaf(blk, &mut a).unwrap();
        extracted.elevation_leaf(blk, &mut b).unwrap();
        assert_eq!(a, b, "{blk:?}");
    }
}
