//! Reconstruction of surface points on an ellipsoid of revolution or a sphere.
//!
//! Implements thesis Eq. 4.2 (seed 003 §4.5.1) with its erratum fixed: the
//! thesis's `ecc` is the *first eccentricity squared* `e²` (WGS84:
//! 0.00669437999014), not `e`:
//!
//! ```text
//! N = a / sqrt(1 − e²·w²)
//! x = u·(N + h),  y = v·(N + h),  z = w·(N·(1 − e²) + h)
//! ```
//!
//! where `(u, v, w)` is the unit cube direction, used as the geodetic normal
//! (thesis-notes §9.3), and `h` the height above the ellipsoid in metres.
//! These are the standard geodetic-to-ECEF formulas; tests compare them with
//! geographiclib to 0.1 mm.

/// The largest radius a database may declare: 10⁷ km, fourteen times the
/// Sun's. A header is untrusted input; radii near 10³⁹ m would overflow the
/// renderer's f32 block-relative vertices (docs/NUMERICS.md), and no planet,
/// moon or game world needs more.
pub const MAX_RADIUS: f64 = 1.0e10;

/// The reference surface of a planet.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Datum {
    /// A sphere of this radius in metres (the Moon, test planets).
    Sphere {
        /// Radius in metres.
        radius: f64,
    },
    /// An ellipsoid of revolution about the polar (Z) axis.
    Ellipsoid {
        /// Equatorial radius `a` in metres.
        a: f64,
        /// First eccentricity squared `e² = (a² − b²) / a²`.
        e2: f64,
    },
}

impl Datum {
    /// WGS84: `a = 6378137 m`, `f = 1/298.257223563`.
    pub const WGS84: Datum = Datum::Ellipsoid {
        a: 6_378_137.0,
        e2: WGS84_E2,
    };

    /// The equatorial radius (the sphere's radius).
    pub fn equatorial_radius(&self) -> f64 {
        match *self {
            Datum::Sphere { radius } => radius,
            Datum::Ellipsoid { a, .. } => a,
        }
    }

    /// The polar radius `b = a·sqrt(1 − e²)`.
    pub fn polar_radius(&self) -> f64 {
        match *self {
            Datum::Sphere { radius } => radius,
            Datum::Ellipsoid { a, e2 } => a * (1.0 - e2).sqrt(),
        }
    }

    /// First eccentricity squared (0 for a sphere).
    pub fn e2(&self) -> f64 {
        match *self {
            Datum::Sphere { .. } => 0.0,
            Datum::Ellipsoid { e2, .. } => e2,
        }
    }

    /// Whether the parameters describe a usable surface: a positive radius
    /// up to [`MAX_RADIUS`], `0 ≤ e² < 1`.
    pub fn is_valid(&self) -> bool {
        let a = self.equatorial_radius();
        let e2 = self.e2();
        a.is_finite() && a > 0.0 && a <= MAX_RADIUS && e2.is_finite() && (0.0..1.0).contains(&e2)
    }

    /// Planet-space position (metres, f64) of the point at height `h` above
    /// the surface along the unit geodetic normal `n` (thesis Eq. 4.2).
    #[inline]
    pub fn position(&self, n: [f64; 3], h: f64) -> [f64; 3] {
        match *self {
            Datum::Sphere { radius } => {
                let r = radius + h;
                [n[0] * r, n[1] * r, n[2] * r]
            }
            Datum::Ellipsoid { a, e2 } => {
                let w = n[2];
                let big_n = a / (1.0 - e2 * w * w).sqrt();
                let r = big_n + h;
                [n[0] * r, n[1] * r, w * (big_n * (1.0 - e2) + h)]
            }
        }
    }

    /// The radius of the surface point with geodetic normal `n` (distance to
    /// the centre at `h = 0`).
    pub fn surface_radius(&self, n: [f64; 3]) -> f64 {
        let p = self.position(n, 0.0);
        (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
    }
}

/// WGS84 first eccentricity squared, `f·(2 − f)` with `f = 1/298.257223563`.
pub const WGS84_E2: f64 = (1.0 / 298.257_223_563) * (2.0 - 1.0 / 298.257_223_563);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cube::direction_from_lat_lon;
    use geographiclib_rs::{Geodesic, InverseGeodesic};
    use proptest::prelude::*;

    fn wgs84(lat: f64, lon: f64, h: f64) -> [f64; 3] {
        Datum::WGS84.position(
            direction_from_lat_lon(lat.to_radians(), lon.to_radians()),
            h,
        )
    }

    proptest! {
        /// Against map_3d's geodetic-to-ECEF (an independent implementation).
        #[test]
        fn wgs84_matches_map_3d(lat in -90.0f64..=90.0, lon in -180.0f64..=180.0, h in -11_000.0f64..9_000.0) {
            let (x, y, z) = map_3d::geodetic2ecef(lat.to_radians(), lon.to_radians(), h, map_3d::Ellipsoid::WGS84);
            let p = wgs84(lat, lon, h);
            let err = ((p[0] - x).powi(2) + (p[1] - y).powi(2) + (p[2] - z).powi(2)).sqrt();
            prop_assert!(err < 1e-4, "error {err} m at {lat} {lon} {h}");
        }

        /// Against geographiclib: for two surface points about 1 km apart the
        /// chord between our positions equals the geodesic distance to within
        /// the arc-chord difference (s³/24R² < 1e-5 m) plus 0.1 mm.
        #[test]
        fn wgs84_chords_match_geographiclib(lat in -89.9f64..=89.9, lon in -180.0f64..=180.0, dlat in -0.007f64..0.007, dlon in -0.007f64..0.007) {
            let g = Geodesic::wgs84();
            let s: f64 = g.inverse(lat, lon, lat + dlat, lon + dlon);
            let a = wgs84(lat, lon, 0.0);
            let b = wgs84(lat + dlat, lon + dlon, 0.0);
            let chord = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
            let arc_chord = s.powi(3) / (24.0 * 6.3e6f64.powi(2));
            prop_assert!((s - chord).abs() < 1e-4 + arc_chord, "geodesic {s} chord {chord}");
        }
    }

    #[test]
    fn radii() {
        assert!((Datum::WGS84.polar_radius() - 6_356_752.314_245).abs() < 1e-3);
        assert_eq!(Datum::Sphere { radius: 1737.4e3 }.polar_radius(), 1737.4e3);
        assert!(!Datum::Sphere { radius: f64::NAN }.is_valid());
        assert!(Datum::Sphere { radius: MAX_RADIUS }.is_valid());
        assert!(!Datum::Sphere {
            radius: MAX_RADIUS * 1.0001
        }
        .is_valid());
        assert!(!Datum::Sphere { radius: 1e39 }.is_valid());
        assert!(!Datum::Ellipsoid { a: 1.0, e2: 1.0 }.is_valid());
    }
}
