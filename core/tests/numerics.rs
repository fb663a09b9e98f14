//! Numerical stability of the cube mapping and the datum on extreme cases,
//! each against an independently computed reference (docs/NUMERICS.md).
//!
//! Run with `cargo test -p planet-core --test numerics -- --nocapture` to see
//! the measured worst cases (lines starting with `NUMERICS`).

use planet_core::cube::{
    angle_from_plane, direction_from_lat_lon, lat_lon_from_direction, plane_from_angle,
    sample_coord, FaceCoord,
};
use planet_core::{Datum, Face};
use std::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};

/// Angle between two unit vectors, `2·atan2(|a−b|, |a+b|)`: accurate for
/// tiny and for near-π angles (independent of `cube::angle_between`).
fn angle(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
    let s = ((a[0] + b[0]).powi(2) + (a[1] + b[1]).powi(2) + (a[2] + b[2]).powi(2)).sqrt();
    2.0 * d.atan2(s)
}

/// Great-circle angle between two (lat, lon) pairs, haversine form (stable
/// for tiny angles; periodic in longitude, so no wrapping is needed).
fn haversine(lat1: f64, lon1: f64, lat2: f64, lon2: f64) -> f64 {
    let a = ((lat2 - lat1) * 0.5).sin().powi(2)
        + lat1.cos() * lat2.cos() * ((lon2 - lon1) * 0.5).sin().powi(2);
    2.0 * a.sqrt().min(1.0).asin()
}

/// Longitude difference wrapped to `[-π, π]`.
fn dlon(a: f64, b: f64) -> f64 {
    let mut d = a - b;
    while d > PI {
        d -= 2.0 * PI;
    }
    while d < -PI {
        d += 2.0 * PI;
    }
    d
}

/// Latitudes at and next to the poles (1e-15 rad away), the equator, the
/// edges of the polar faces and the cube corners (`atan(1/√2)`), each with
/// its neighbours one ulp and 1e-15 rad away.
fn special_lats() -> Vec<f64> {
    let corner = (1.0f64 / 2f64.sqrt()).atan();
    let mut base = vec![
        0.0,
        FRAC_PI_2,
        FRAC_PI_2 - 1e-15,
        FRAC_PI_2 - 1e-12,
        FRAC_PI_2 - 1e-8,
        FRAC_PI_4,
        corner,
        1.0,
    ];
    for k in 0..8 {
        // Edges of the polar face at 8 longitudes: tan(lat) = max(|cos λ|, |sin λ|).
        let lon = k as f64 * FRAC_PI_4 / 2.0;
        base.push(lon.cos().abs().max(lon.sin().abs()).atan());
    }
    let mut out = vec![];
    for b in base {
        for x in [b, b + 1e-15, b - 1e-15, b.next_up(), b.next_down()] {
            for s in [1.0, -1.0] {
                let l = s * x;
                if l.abs() <= FRAC_PI_2 {
                    out.push(l);
                }
            }
        }
    }
    out
}

/// Longitudes on the antimeridian (±π and 1e-15 rad off), the prime
/// meridian, and the face edges (odd multiples of π/4) and centres.
fn special_lons() -> Vec<f64> {
    let mut out = vec![
        PI,
        -PI,
        PI.next_down(),
        (-PI).next_up(),
        PI - 1e-15,
        -PI + 1e-15,
    ];
    for k in -4..=4 {
        let b = k as f64 * FRAC_PI_4;
        for x in [b, b + 1e-15, b - 1e-15, b.next_up(), b.next_down()] {
            if x.abs() <= PI {
                out.push(x);
            }
        }
    }
    out
}

#[test]
fn lat_lon_round_trips_at_poles_edges_corners_and_antimeridian() {
    let (mut worst_ang, mut worst_ang_at) = (0.0f64, (0.0, 0.0));
    let (mut worst_lat, mut worst_lon) = (0.0f64, 0.0f64);
    let mut n = 0;
    for lat in special_lats() {
        for lon in special_lons() {
            let fc = FaceCoord::from_lat_lon(lat, lon);
            assert!((0.0..=1.0).contains(&fc.s) && (0.0..=1.0).contains(&fc.t));
            let (lat2, lon2) = fc.to_lat_lon();
            assert!(lat2.is_finite() && lon2.is_finite());
            assert!(lon2 > -PI - 1e-15 && lon2 <= PI, "{lon2}");
            let a = haversine(lat, lon, lat2, lon2);
            if a > worst_ang {
                worst_ang = a;
                worst_ang_at = (lat, lon);
            }
            worst_lat = worst_lat.max((lat2 - lat).abs());
            // Longitude is meaningful away from the poles only.
            if lat.cos() > 1e-3 {
                worst_lon = worst_lon.max(dlon(lon2, lon).abs());
            }
            n += 1;
        }
    }
    println!(
        "NUMERICS cube lat/lon->face->lat/lon: {n} cases, worst angle {worst_ang:.3e} rad at lat {:.17} lon {:.17}; worst |dlat| {worst_lat:.3e}; worst |dlon| (|lat| < 89.94 deg) {worst_lon:.3e}",
        worst_ang_at.0, worst_ang_at.1
    );
    assert!(worst_ang <= 1e-12, "{worst_ang}");
    assert!(worst_lat <= 1e-12, "{worst_lat}");
    assert!(worst_lon <= 1e-12, "{worst_lon}");
}

#[test]
fn exact_pole_and_antimeridian_conventions() {
    // At the pole hypot is 0: latitude exactly ±π/2, longitude 0.
    assert_eq!(lat_lon_from_direction([0.0, 0.0, 1.0]), (FRAC_PI_2, 0.0));
    assert_eq!(lat_lon_from_direction([0.0, 0.0, -1.0]), (-FRAC_PI_2, 0.0));
    assert_eq!(lat_lon_from_direction([-0.0, -0.0, 1.0]).0, FRAC_PI_2);
    // 1e-15 rad from the pole: atan2 keeps it (no asin(z) near 1).
    let (lat, _) = lat_lon_from_direction([1e-15, 0.0, 1.0]);
    assert!(
        (FRAC_PI_2 - lat - 1e-15).abs() < 3e-16,
        "{}",
        FRAC_PI_2 - lat
    );
    // The two sides of the antimeridian land on the same point of face 5.
    let a = FaceCoord::from_lat_lon(0.3, PI);
    let b = FaceCoord::from_lat_lon(0.3, -PI);
    assert_eq!(a.face, b.face);
    assert!(angle(a.direction(), b.direction()) < 1e-15);
    // Tiny and huge (unnormalised) directions: finite face coordinates.
    for d in [
        [1e-300, 2e-300, 3e-300],
        [1e300, -2e300, 3e300],
        [5e-324, 0.0, 0.0],
    ] {
        let fc = FaceCoord::from_direction(d);
        assert!(fc.s.is_finite() && fc.t.is_finite(), "{d:?} {fc:?}");
        let (la, lo) = lat_lon_from_direction(d);
        assert!(la.is_finite() && lo.is_finite());
    }
}

/// Face frames hard-coded from the table in `cube.rs` (u, v, w axes).
fn frame(face: u8) -> [[f64; 3]; 3] {
    let (x, y, z) = ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]);
    let neg = |v: [f64; 3]| [-v[0], -v[1], -v[2]];
    match face {
        0 => [x, y, z],
        1 => [x, z, neg(y)],
        2 => [y, z, x],
        3 => [y, x, neg(z)],
        4 => [z, x, y],
        _ => [z, y, neg(x)],
    }
}

/// Reference direction of face coordinates without `tan`: with
/// `a = (2s−1)π/4`, `b = (2t−1)π/4` the direction is proportional to
/// `(sin a·cos b, cos a·sin b, cos a·cos b)` in the face frame.
fn reference_direction(face: u8, s: f64, t: f64) -> [f64; 3] {
    let a = (2.0 * s - 1.0) * FRAC_PI_4;
    let b = (2.0 * t - 1.0) * FRAC_PI_4;
    let l = [a.sin() * b.cos(), a.cos() * b.sin(), a.cos() * b.cos()];
    let n = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt();
    let [u, v, w] = frame(face);
    let mut d = [0.0; 3];
    for k in 0..3 {
        d[k] = (l[0] * u[k] + l[1] * v[k] + l[2] * w[k]) / n;
    }
    d
}

fn special_st() -> Vec<f64> {
    let n = 1u64 << 24;
    vec![
        0.0,
        1e-16,
        1e-15,
        sample_coord(1, n),
        0.25,
        0.5,
        0.5 - 1e-15,
        0.5 + 1e-15,
        0.75,
        sample_coord(n - 1, n),
        1.0 - 1e-15,
        1.0f64.next_down(),
        1.0,
    ]
}

#[test]
fn face_round_trips_on_every_edge_and_corner() {
    let (mut worst_dir, mut worst_dir_at) = (0.0f64, (0, 0.0, 0.0));
    let (mut worst_rt, mut worst_st) = (0.0f64, 0.0f64);
    for face in 0..6u8 {
        for &s in &special_st() {
            for &t in &special_st() {
                let fc = FaceCoord {
                    face: Face::new(face).unwrap(),
                    s,
                    t,
                };
                let d = fc.direction();
                let e = angle(d, reference_direction(face, s, t));
                if e > worst_dir {
                    worst_dir = e;
                    worst_dir_at = (face, s, t);
                }
                let back = FaceCoord::from_direction(d);
                worst_rt = worst_rt.max(angle(back.direction(), d));
                if back.face == fc.face {
                    worst_st = worst_st.max((back.s - s).abs()).max((back.t - t).abs());
                } else {
                    // Only points on an edge may change face.
                    assert!(s == 0.0 || s == 1.0 || t == 0.0 || t == 1.0 || e > 0.0);
                }
                // Plane <-> angle inverse pair.
                let u = plane_from_angle(s);
                assert!((-1.0..=1.0).contains(&u));
                assert!((angle_from_plane(u) - s).abs() <= 4e-16, "{s}");
            }
        }
    }
    println!(
        "NUMERICS cube face->direction vs tan-free reference: worst {worst_dir:.3e} rad at face {} s {:e} t {:e}; face->direction->face worst angle {worst_rt:.3e} rad, worst |ds|,|dt| {worst_st:.3e}",
        worst_dir_at.0, worst_dir_at.1, worst_dir_at.2
    );
    assert!(worst_dir <= 1e-15, "{worst_dir}");
    assert!(worst_rt <= 1e-12 && worst_st <= 1e-12);
}

fn map3d(lat: f64, lon: f64, h: f64) -> [f64; 3] {
    let (x, y, z) = map_3d::geodetic2ecef(lat, lon, h, map_3d::Ellipsoid::WGS84);
    [x, y, z]
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Heights: int16 limits (raw SRTM void −32768 at 1 m/unit), 0, 1 cm, 1 m,
/// 10 km, Everest, the deepest trench.
const HEIGHTS: [f64; 9] = [
    -32768.0, -11_000.0, 0.0, 0.01, 1.0, 8848.0, 10_000.0, 32767.0, -1.0,
];

#[test]
fn wgs84_matches_map_3d_at_poles_edges_corners_and_antimeridian() {
    let (mut worst, mut worst_at) = (0.0f64, (0.0, 0.0, 0.0));
    let mut worst_cube = 0.0f64;
    for lat in special_lats() {
        for lon in special_lons() {
            for h in HEIGHTS {
                let r = map3d(lat, lon, h);
                let p = Datum::WGS84.position(direction_from_lat_lon(lat, lon), h);
                let e = dist(p, r);
                if e > worst {
                    worst = e;
                    worst_at = (lat, lon, h);
                }
                // Through the cube: lat/lon -> face -> gnomonic direction -> datum.
                let fc = FaceCoord::from_lat_lon(lat, lon);
                let q = Datum::WGS84.position(fc.direction(), h);
                worst_cube = worst_cube.max(dist(q, r));
            }
        }
    }
    println!(
        "NUMERICS datum WGS84 vs map_3d: worst {worst:.3e} m at lat {:.17} lon {:.17} h {}; through the cube faces worst {worst_cube:.3e} m",
        worst_at.0, worst_at.1, worst_at.2
    );
    assert!(worst <= 1e-4 && worst_cube <= 1e-4, "{worst} {worst_cube}");
}

#[test]
fn spheres_of_1_km_and_70000_km() {
    let mut worst_rel = 0.0f64;
    for radius in [1_000.0, 70_000_000.0, 6_371_000.0] {
        let d = Datum::Sphere { radius };
        for lat in special_lats() {
            for lon in special_lons() {
                for h in HEIGHTS {
                    let fc = FaceCoord::from_lat_lon(lat, lon);
                    let p = d.position(fc.direction(), h);
                    assert!(p.iter().all(|c| c.is_finite()));
                    let r = radius + h;
                    let (sl, cl) = lat.sin_cos();
                    let (so, co) = lon.sin_cos();
                    let reference = [r * cl * co, r * cl * so, r * sl];
                    let e = dist(p, reference) / (radius + h.abs());
                    worst_rel = worst_rel.max(e);
                }
            }
        }
    }
    println!("NUMERICS datum spheres 1 km / 6371 km / 70000 km: worst relative error {worst_rel:.3e} (of radius + |h|)");
    assert!(worst_rel <= 1e-14, "{worst_rel}");
}

#[test]
fn gnomonic_reconstruction_on_a_fine_grid_matches_the_ellipsoid() {
    // Samples of a level-20 face map (W = 64 · 2^20) next to a corner and
    // on an edge: reconstructed position vs map_3d at the geodetic lat/lon
    // of the tan-free reference direction.
    let n = 64u64 << 20;
    let mut worst = 0.0f64;
    for face in 0..6u8 {
        for (i, j) in [
            (0, 0),
            (1, 0),
            (1, 1),
            (0, n / 2),
            (n / 2, n / 2),
            (n - 1, n),
            (n, n),
        ] {
            let (s, t) = (sample_coord(i, n), sample_coord(j, n));
            let fc = FaceCoord {
                face: Face::new(face).unwrap(),
                s,
                t,
            };
            let (lat, lon) = lat_lon_from_direction(reference_direction(face, s, t));
            for h in [-32768.0, 0.0, 32767.0] {
                let e = dist(Datum::WGS84.position(fc.direction(), h), map3d(lat, lon, h));
                worst = worst.max(e);
            }
        }
    }
    println!("NUMERICS gnomonic+ellipsoid at level-20 samples (corners, edges): worst {worst:.3e} m vs map_3d");
    assert!(worst <= 1e-4, "{worst}");
}
