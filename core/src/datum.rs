//! Reconstruction of surface points on an ellipsoid of revolution or a sphere.
//!
//! Implements thesis Eq. 4.2 (Thesis §4.5.1; docs/REFERENCES.md) with its erratum fixed: the
//! thesis's `ecc` is the *first eccentricity squared* `e²` (WGS84:
//! 0.00669437999014), not `e`:
//!
//! ```text
//! N = a / sqrt(1 − e²·w²)
//! x = u·(N + h),  y = v·(N + h),  z = w·(N·(1 − e²) + h)
//! ```
//!
//! where `(u, v, w)` is the unit cube direction, used as the geodetic normal
//! (docs/REFERENCES.md), and `h` the height above the ellipsoid in metres.
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

/// A body a datum's semi-axes identify (IAU WGCCRE 2015 radii for the
/// planets and the Moon). Used to name a database's datum and to tell Earth
/// CRSs (shifted to WGS84) from other bodies' (kept as they are).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Body {
    /// The Earth: any of its reference ellipsoids (equatorial radius within
    /// 6 377 km .. 6 379 km: Bessel, Clarke, GRS80, WGS84, International…),
    /// or a sphere of 6 371 km .. 6 379 km.
    Earth,
    /// The Moon (mean radius 1 737.4 km).
    Moon,
    /// Mars (3 396.19 km equatorial, 3 376.2 km polar).
    Mars,
    /// Mercury (2 440.53 km).
    Mercury,
    /// Venus (6 051.8 km).
    Venus,
}

impl Body {
    /// The body whose reference radius is within 0.5 % of `a` (Earth: see
    /// [`Body::Earth`]), if any.
    pub fn of_axes(a: f64, b: f64) -> Option<Body> {
        if (6_377_000.0..=6_379_000.0).contains(&a)
            || (a == b && (6_371_000.0..=6_379_000.0).contains(&a))
        {
            return Some(Body::Earth);
        }
        let near = |r: f64| (a - r).abs() <= 0.005 * r;
        [
            (Body::Moon, 1_737_400.0),
            (Body::Mars, 3_396_190.0),
            (Body::Mercury, 2_440_530.0),
            (Body::Venus, 6_051_800.0),
        ]
        .into_iter()
        .find(|&(_, r)| near(r))
        .map(|(body, _)| body)
    }

    /// The body's name.
    pub fn name(self) -> &'static str {
        match self {
            Body::Earth => "Earth",
            Body::Moon => "Moon",
            Body::Mars => "Mars",
            Body::Mercury => "Mercury",
            Body::Venus => "Venus",
        }
    }
}

impl Datum {
    /// The datum of semi-axes `a ≥ b` (metres): a sphere where they are
    /// equal, else an ellipsoid.
    pub fn from_axes(a: f64, b: f64) -> Datum {
        if a == b {
            Datum::Sphere { radius: a }
        } else {
            Datum::Ellipsoid {
                a,
                e2: 1.0 - (b / a) * (b / a),
            }
        }
    }

    /// Inverse flattening `1/f = a / (a − b)`; `None` for a sphere.
    pub fn inverse_flattening(&self) -> Option<f64> {
        let (a, b) = (self.equatorial_radius(), self.polar_radius());
        (a != b).then(|| a / (a - b))
    }

    /// The body this datum is a reference surface of, where known.
    pub fn body(&self) -> Option<Body> {
        Body::of_axes(self.equatorial_radius(), self.polar_radius())
    }

    /// A name: `WGS84`, `GRS80`, `Moon sphere`, … or `None`.
    pub fn name(&self) -> Option<String> {
        let a = self.equatorial_radius();
        if let Some(rf) = self.inverse_flattening() {
            if a == 6_378_137.0 && (rf - 298.257_223_563).abs() < 1e-6 {
                return Some("WGS84".into());
            }
            if a == 6_378_137.0 && (rf - 298.257_222_101).abs() < 1e-6 {
                return Some("GRS80".into());
            }
        }
        let kind = match self {
            Datum::Sphere { .. } => "sphere",
            Datum::Ellipsoid { .. } => "ellipsoid",
        };
        self.body().map(|b| format!("{} {kind}", b.name()))
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

    #[test]
    fn bodies_and_names() {
        assert_eq!(Datum::WGS84.body(), Some(Body::Earth));
        assert_eq!(Datum::WGS84.name().as_deref(), Some("WGS84"));
        let rf = Datum::WGS84.inverse_flattening().unwrap_or(0.0);
        assert!((rf - 298.257_223_563).abs() < 1e-6, "{rf}");
        let grs80 = Datum::from_axes(6_378_137.0, 6_378_137.0 * (1.0 - 1.0 / 298.257_222_101));
        assert_eq!(grs80.name().as_deref(), Some("GRS80"));
        let moon = Datum::from_axes(1_737_400.0, 1_737_400.0);
        assert_eq!(
            moon,
            Datum::Sphere {
                radius: 1_737_400.0
            }
        );
        assert_eq!(moon.body(), Some(Body::Moon));
        assert_eq!(moon.inverse_flattening(), None);
        assert_eq!(moon.name().as_deref(), Some("Moon sphere"));
        let mars = Datum::from_axes(3_396_190.0, 3_376_200.0);
        assert_eq!(mars.body(), Some(Body::Mars));
        assert!((mars.polar_radius() - 3_376_200.0).abs() < 1e-6);
        assert_eq!(Datum::Sphere { radius: 1000.0 }.body(), None);
        assert_eq!(
            Body::of_axes(6_377_397.155, 6_356_078.963),
            Some(Body::Earth)
        );
    }
}
