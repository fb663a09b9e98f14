//! Procedural detail beyond the sources (`--detail` on rasters, thesis
//! §6.2.2): the tree deepens inside the region, steep ground gets rough,
//! flat ground stays exactly flat, shared edges agree, and the database
//! verifies against the same options.

use planet_core::cube::{angle_between, direction_from_lat_lon, normalize, plane_from_angle};
use planet_core::BlockId;
use planet_preprocess::build::GridSource;
use planet_preprocess::geoid::VerticalDatum;
use planet_preprocess::plan::{self, Plan};
use planet_preprocess::{DetailRegion, RasterOptions};
use std::fs::File;
use std::path::Path;
use tiff::encoder::{colortype, TiffEncoder};
use tiff::tags::Tag;

const W: usize = 100;
/// Degrees per pixel.
const PX: f64 = 0.01;
/// Slope of the east half, m/m.
const SLOPE: f64 = 0.3;

/// A 1° × 1° int16 raster of 0.01° pixels over 10–11°E, 45–46°N (tree level
/// 8): flat at 500 m in the west half, a plane rising east at [`SLOPE`] in
/// the east half.
fn write_half_slope(path: &Path) {
    let dx = PX.to_radians() * 6_378_137.0 * 45.5f64.to_radians().cos();
    let data: Vec<i16> = (0..W * W)
        .map(|i| {
            let c = i % W;
            let rise = if c > W / 2 {
                SLOPE * dx * (c - W / 2) as f64
            } else {
                0.0
            };
            (500.0 + rise).round() as i16
        })
        .collect();
    write_geographic(path, W, W, PX, (10.0, 46.0), &data);
}

/// Writes an int16 geographic (WGS84, pixel-is-area) raster of `w × h`
/// pixels of `px` degrees, its upper-left corner at (`lon`, `lat`).
fn write_geographic(
    path: &Path,
    w: usize,
    h: usize,
    px: f64,
    (lon, lat): (f64, f64),
    data: &[i16],
) {
    let mut enc = TiffEncoder::new(File::create(path).unwrap()).unwrap();
    let mut img = enc
        .new_image::<colortype::GrayI16>(w as u32, h as u32)
        .unwrap();
    let d = img.encoder();
    d.write_tag(Tag::ModelPixelScaleTag, &[px, px, 0.0][..])
        .unwrap();
    d.write_tag(
        Tag::ModelTiepointTag,
        &[0.0f64, 0.0, 0.0, lon, lat, 0.0][..],
    )
    .unwrap();
    // Geographic model, pixel-is-area.
    d.write_tag(
        Tag::GeoKeyDirectoryTag,
        &[1u16, 1, 0, 2, 1024, 0, 1, 2, 1025, 0, 1, 1][..],
    )
    .unwrap();
    img.write_data(data).unwrap();
}

fn region(lat: f64, lon: f64, km: f64, level: u8) -> DetailRegion {
    format!("{lat},{lon},{km},{level}").parse().unwrap()
}

fn opts(detail: Vec<DetailRegion>) -> RasterOptions {
    RasterOptions {
        vertical: vec![VerticalDatum::Ellipsoid],
        detail,
        ..RasterOptions::default()
    }
}

fn centre(b: BlockId) -> [f64; 3] {
    let (s0, t0, s1, t1) = b.extent();
    normalize(b.face.cube_point(
        plane_from_angle(0.5 * (s0 + s1)),
        plane_from_angle(0.5 * (t0 + t1)),
    ))
}

fn grid(src: &dyn GridSource, b: BlockId) -> Vec<i16> {
    let mut g = vec![0i16; 65 * 65];
    src.elevation_leaf(b, &mut g).unwrap();
    g
}

#[test]
fn detail_deepens_the_region_roughens_slopes_and_leaves_flat_ground_flat() {
    let dir = tempfile::tempdir().unwrap();
    let tif = dir.path().join("half.tif");
    write_half_slope(&tif);
    let e = [tif.as_path()];
    let (plain, plain_plan) = planet_preprocess::open_rasters(&e, None, &opts(vec![])).unwrap();
    assert_eq!(plain_plan.max_level(), 8, "the source's level");
    // One region on the slope, one on the flat half, 25 km, level 10
    // (blocks of about 10 km).
    let (steep_c, flat_c) = ((45.5, 10.75), (45.5, 10.25));
    let regions = vec![
        region(steep_c.0, steep_c.1, 25.0, 10),
        region(flat_c.0, flat_c.1, 25.0, 10),
    ];
    let (amp, amp_plan) = planet_preprocess::open_rasters(&e, None, &opts(regions)).unwrap();
    assert_eq!(amp_plan.max_level(), 10);
    let Plan::Explicit { split, .. } = &amp_plan else {
        panic!("an explicit plan")
    };
    let r = 25_000.0 / 6_378_137.0;
    let inner = |c: (f64, f64), b: BlockId| {
        let d = direction_from_lat_lon(c.0.to_radians(), c.1.to_radians());
        angle_between(d, centre(b)) < 0.3 * r
    };
    let leaves = plan::leaves(split);
    let steep: Vec<BlockId> = leaves
        .iter()
        .copied()
        .filter(|&b| inner(steep_c, b))
        .collect();
    let flat: Vec<BlockId> = leaves
        .iter()
        .copied()
        .filter(|&b| inner(flat_c, b))
        .collect();
    assert!(!steep.is_empty() && !flat.is_empty());
    assert!(
        steep.iter().chain(&flat).all(|b| b.level == 10),
        "leaves in a region are at its level"
    );
    // Far from the regions the tree is the sources' (level 8).
    let far = direction_from_lat_lon(45.1f64.to_radians(), 10.5f64.to_radians());
    let far_leaf = leaves
        .iter()
        .find(|b| angle_between(centre(**b), far) < 0.002)
        .expect("a leaf near 45.1N 10.5E");
    assert_eq!(far_leaf.level, 8);

    // Flat ground: no detail at all.
    for &b in &flat {
        assert_eq!(grid(&amp, b), grid(&plain, b), "flat leaf {b:?} changed");
    }
    // Steep ground: metres of detail, bounded by the amplitude law.
    let mut sq = 0.0;
    let mut n = 0.0;
    let mut worst = 0f64;
    for &b in &steep {
        let (a, p) = (grid(&amp, b), grid(&plain, b));
        for (x, y) in a.iter().zip(&p) {
            let d = (*x as f64) - (*y as f64);
            sq += d * d;
            n += 1.0;
            worst = worst.max(d.abs());
        }
    }
    let rms = (sq / n).sqrt();
    // First octave over level 8 (λ ≈ 780 m): amplitude 0.25·0.3·780 ≈ 58 m,
    // the second 38 m; gradient noise's RMS is a fraction of that.
    eprintln!("detail on a {SLOPE} slope: RMS {rms:.1} m, largest {worst:.0} m");
    assert!(rms > 3.0 && rms < 60.0, "RMS {rms}");
    assert!(worst < 120.0, "largest {worst}");

    // Shared edges agree: each steep leaf's right column is its right
    // neighbour's left column, that neighbour a leaf of the same level.
    let mut checked = 0;
    for &b in &steep {
        let (nb, _) = b.neighbour(planet_core::Edge::Right);
        if nb.face != b.face || !leaves.contains(&nb) {
            continue;
        }
        let (g, h) = (grid(&amp, b), grid(&amp, nb));
        for j in 0..65 {
            assert_eq!(g[j * 65 + 64], h[j * 65], "{b:?} | {nb:?} row {j}");
        }
        checked += 1;
    }
    assert!(checked > 0, "no neighbouring pair checked");
}

#[test]
fn the_database_verifies_against_its_options_and_bad_levels_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let tif = dir.path().join("half.tif");
    write_half_slope(&tif);
    let e = [tif.as_path()];
    let out = dir.path().join("amp.planetdb");
    let o = opts(vec![region(45.5, 10.75, 6.0, 10)]);
    let st = planet_preprocess::build_rasters(&e, None, &out, &o).unwrap();
    assert_eq!(st.max_level, 10);
    let (src, _) = planet_preprocess::open_rasters(&e, None, &o).unwrap();
    let rep = planet_preprocess::db::verify_against(&out, Some(&src)).unwrap();
    assert_eq!(rep.max_level, 10);
    assert!(
        rep.elevation_max_error_m.unwrap() <= rep.elevation_bound_m.unwrap(),
        "{rep:?}"
    );
    // Without the detail the same file does not verify.
    let (plain, _) = planet_preprocess::open_rasters(&e, None, &opts(vec![])).unwrap();
    let bad = planet_preprocess::db::verify_against(&out, Some(&plain));
    assert!(bad.is_err(), "verified without its detail: {bad:?}");

    // A region no deeper than the source, or deeper than --max-level.
    for (lvl, max) in [(8u8, 16u8), (12, 11)] {
        let mut o = opts(vec![region(45.5, 10.75, 6.0, lvl)]);
        o.max_level = max;
        let err = planet_preprocess::open_rasters(&e, None, &o)
            .err()
            .expect("refused")
            .to_string();
        assert!(
            err.contains("must be deeper than the finest elevation source"),
            "{err}"
        );
    }
}

/// A global 36 × 18 raster of 10° pixels (tree level 0) with relief
/// everywhere (slopes of a few m/km).
fn write_global(path: &Path) {
    let data: Vec<i16> = (0..36 * 18)
        .map(|i| {
            let (c, r) = (i % 36, i / 36);
            ((c * 37 + r * 91) % 17) as i16 * 300
        })
        .collect();
    write_geographic(path, 36, 18, 10.0, (-180.0, 90.0), &data);
}

/// The direction of sample (i, j) of a block's grid, with the builder's
/// arithmetic.
fn sample_dir(b: BlockId, i: usize, j: usize) -> [f64; 3] {
    let n = 64u64 << b.level;
    let s = planet_core::cube::sample_coord(b.x as u64 * 64 + i as u64, n);
    let t = planet_core::cube::sample_coord(b.y as u64 * 64 + j as u64, n);
    normalize(b.face.cube_point(plane_from_angle(s), plane_from_angle(t)))
}

/// NUMERICS: regions on a cube corner, a pole and the antimeridian. Every
/// pair of same-level leaves sharing an edge, across cube edges too, agrees
/// on the shared samples (within the 1 m quantisation: the two faces'
/// directions differ in the last bits), and detail was added there.
#[test]
fn detail_agrees_across_cube_edges_poles_and_the_antimeridian() {
    let dir = tempfile::tempdir().unwrap();
    let tif = dir.path().join("global.tif");
    write_global(&tif);
    let e = [tif.as_path()];
    let corner = 35.264_389_682_754_654; // atan(1/√2), degrees
    for (lat, lon) in [(corner, 45.0), (90.0, 0.0), (0.0, 180.0), (-corner, -135.0)] {
        let regions = vec![region(lat, lon, 2500.0, 2)];
        let (amp, plan) = planet_preprocess::open_rasters(&e, None, &opts(regions)).unwrap();
        let (plain, _) = planet_preprocess::open_rasters(&e, None, &opts(vec![])).unwrap();
        let Plan::Explicit { split, .. } = &plan else {
            panic!("explicit")
        };
        let leaves: Vec<BlockId> = plan::leaves(split)
            .into_iter()
            .filter(|b| b.level == 2)
            .collect();
        let c = direction_from_lat_lon(lat.to_radians(), lon.to_radians());
        let near: Vec<BlockId> = leaves
            .iter()
            .copied()
            .filter(|b| angle_between(centre(*b), c) < 2500e3 / 6_378_137.0)
            .collect();
        assert!(near.len() >= 3, "({lat}, {lon}): {} leaves", near.len());
        let mut changed = 0;
        let (mut pairs, mut cross) = (0, 0);
        for &b in &near {
            let g = grid(&amp, b);
            changed += g
                .iter()
                .zip(grid(&plain, b))
                .filter(|(x, y)| **x != *y)
                .count();
            for edge in [
                planet_core::Edge::Left,
                planet_core::Edge::Top,
                planet_core::Edge::Right,
                planet_core::Edge::Bottom,
            ] {
                let (nb, _) = b.neighbour(edge);
                if !leaves.contains(&nb) {
                    continue;
                }
                let h = grid(&amp, nb);
                // b's edge samples, matched to nb's by direction.
                let border: Vec<(usize, usize)> = (0..65)
                    .flat_map(|k| [(0, k), (64, k), (k, 0), (k, 64)])
                    .collect();
                let mut matched = 0;
                for &(i, j) in &border {
                    let p = sample_dir(b, i, j);
                    if let Some(&(k, l)) = border
                        .iter()
                        .find(|&&(k, l)| angle_between(p, sample_dir(nb, k, l)) < 1e-12)
                    {
                        let (x, y) = (g[j * 65 + i], h[l * 65 + k]);
                        assert!(
                            (x - y).abs() <= 1,
                            "({lat}, {lon}): {b:?} ({i},{j}) = {x} but {nb:?} ({k},{l}) = {y}"
                        );
                        matched += 1;
                    }
                }
                assert!(matched >= 65, "{b:?}/{nb:?}: {matched} shared samples");
                pairs += 1;
                if nb.face != b.face {
                    cross += 1;
                }
            }
        }
        eprintln!("({lat:.2}, {lon}): {} leaves, {pairs} edges ({cross} across faces), {changed} samples changed", near.len());
        assert!(changed > 1000, "({lat}, {lon}): {changed} samples changed");
        // The corners' leaves meet three faces (the pole and the
        // antimeridian lie at face centres here).
        if (lat.abs() - corner).abs() < 1e-9 {
            assert!(cross > 0, "({lat}, {lon}): no edge across faces");
        }
    }
}
