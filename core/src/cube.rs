//! The cube faces and the adjusted gnomonic (equal-angle) sampling.
//!
//! Implements thesis §4.5.1–4.5.3 and §5.2 with the face frames of
//! Thesis Table 4.1 as reconstructed in docs/REFERENCES.md:
//!
//! | face | w (outward) | u axis | v axis | centre            |
//! |------|-------------|--------|--------|-------------------|
//! | 0    | +Z          | +X     | +Y     | north pole        |
//! | 1    | −Y          | +X     | +Z     | 0° N, 90° W       |
//! | 2    | +X          | +Y     | +Z     | 0° N, 0° E        |
//! | 3    | −Z          | +Y     | +X     | south pole        |
//! | 4    | +Y          | +Z     | +X     | 0° N, 90° E       |
//! | 5    | −X          | +Z     | +Y     | 0° N, 180° (antimeridian) |
//!
//! `X` points to (0° N, 0° E), `Y` to (0° N, 90° E) and `Z` to the north pole.
//! Each `(u, v, w)` frame is right-handed with `w` outward, and the axes of two
//! faces point the same way along their shared edge, so the blocks (and
//! samples) along an edge are listed in the same order from both sides.
//!
//! **Equal-angle sampling.** A face is parameterised by `(s, t) ∈ [0, 1]²`.
//! The gnomonic plane coordinate is `u = tan(u')` with `u' = (2s − 1)·π/4`, so
//! regular steps in `s` are regular steps in angle (thesis §4.5.2). Sample `i`
//! of a face map of width `n` sits at `s = i / n`, so samples lie exactly on
//! the face edges and the odd-width centre sample lies on the face centre.
//!
//! **Bit-identical edges.** The plane coordinates of the edges are exactly ±1
//! (not `tan(π/4)`, which rounds to 0.9999999999999999), the along-edge
//! coordinate is computed from the same `(i, n)` on both faces, and the cube
//! point is assembled by assignment (no multiply-add by axis vectors, which
//! would introduce signed zeros and summation-order differences). A sample on
//! a shared edge therefore has bit-identical coordinates from both faces.
//!
//! **Inverse map (erratum of thesis Eq. 5.1).** The thesis writes
//! `λ' = arctan(u / (cos φ − v sin φ)) + λ`, which loses the quadrant on the
//! polar faces (`cos φ = 0`). We go through the unit direction instead:
//! `λ = atan2(y, x)`, `φ = atan2(z, hypot(x, y))`; at the poles `hypot` is 0
//! and `atan2` returns exactly ±π/2 with longitude 0 by convention.

use std::f64::consts::FRAC_PI_4;

/// One of the six cube faces, numbered as in thesis Table 4.1.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Face(u8);

impl Face {
    /// All six faces in order.
    pub const ALL: [Face; 6] = [Face(0), Face(1), Face(2), Face(3), Face(4), Face(5)];
    /// The face centred on the north pole.
    pub const NORTH: Face = Face(0);
    /// The face centred on the south pole.
    pub const SOUTH: Face = Face(3);

    /// The face with this number, if it is in `0..6`.
    pub fn new(index: u8) -> Option<Face> {
        (index < 6).then_some(Face(index))
    }

    /// The face number in `0..6`.
    pub fn index(self) -> u8 {
        self.0
    }

    /// Whether the face number is even (thesis Table 4.1 depends on parity).
    pub fn is_even(self) -> bool {
        self.0.is_multiple_of(2)
    }

    /// The opposite face (`f + 3 mod 6`).
    pub fn opposite(self) -> Face {
        Face((self.0 + 3) % 6)
    }

    /// The face's frame `(u, v, w)` as signed axis vectors in planet space.
    pub fn frame(self) -> [[f64; 3]; 3] {
        const X: [f64; 3] = [1.0, 0.0, 0.0];
        const Y: [f64; 3] = [0.0, 1.0, 0.0];
        const Z: [f64; 3] = [0.0, 0.0, 1.0];
        const NX: [f64; 3] = [-1.0, 0.0, 0.0];
        const NY: [f64; 3] = [0.0, -1.0, 0.0];
        const NZ: [f64; 3] = [0.0, 0.0, -1.0];
        match self.0 {
            0 => [X, Y, Z],
            1 => [X, Z, NY],
            2 => [Y, Z, X],
            3 => [Y, X, NZ],
            4 => [Z, X, Y],
            _ => [Z, Y, NX],
        }
    }

    /// The point `u·U + v·V + W` on the cube surface, built by assignment so
    /// that equal `(u, v)` on a shared edge give bit-identical vectors.
    #[inline]
    pub fn cube_point(self, u: f64, v: f64) -> [f64; 3] {
        match self.0 {
            0 => [u, v, 1.0],
            1 => [u, -1.0, v],
            2 => [1.0, u, v],
            3 => [v, u, -1.0],
            4 => [v, 1.0, u],
            _ => [-1.0, v, u],
        }
    }

    /// The face whose outward axis is the dominant component of `d`, and the
    /// gnomonic plane coordinates `(u, v)` of `d` on it (each in `[-1, 1]`).
    ///
    /// Ties (points on edges and corners) go to the lowest face number, so the
    /// choice is deterministic; either face gives the same point.
    pub fn from_direction(d: [f64; 3]) -> (Face, f64, f64) {
        let [x, y, z] = d;
        let (ax, ay, az) = (x.abs(), y.abs(), z.abs());
        // Candidates in face order, each with its dominance.
        let face = if az >= ax && az >= ay && z > 0.0 {
            0
        } else if ay >= ax && ay >= az && y < 0.0 {
            1
        } else if ax >= ay && ax >= az && x > 0.0 {
            2
        } else if az >= ax && az >= ay && z < 0.0 {
            3
        } else if ay >= ax && ay >= az && y > 0.0 {
            4
        } else {
            5
        };
        let (u, v) = match face {
            0 => (x / z, y / z),
            1 => (x / -y, z / -y),
            2 => (y / x, z / x),
            3 => (y / -z, x / -z),
            4 => (z / y, x / y),
            _ => (z / -x, y / -x),
        };
        (Face(face), u.clamp(-1.0, 1.0), v.clamp(-1.0, 1.0))
    }
}

/// Equal-angle coordinate `s ∈ [0, 1]` to gnomonic plane coordinate
/// `tan((2s − 1)·π/4)`, exactly ±1 at the edges and odd-symmetric about 0.5.
#[inline]
pub fn plane_from_angle(s: f64) -> f64 {
    let a = 2.0 * s - 1.0;
    if a >= 1.0 {
        1.0
    } else if a <= -1.0 {
        -1.0
    } else if a < 0.0 {
        -(-a * FRAC_PI_4).tan()
    } else {
        (a * FRAC_PI_4).tan()
    }
}

/// Gnomonic plane coordinate in `[-1, 1]` to equal-angle coordinate `s`.
#[inline]
pub fn angle_from_plane(u: f64) -> f64 {
    if u >= 1.0 {
        1.0
    } else if u <= -1.0 {
        0.0
    } else {
        0.5 + u.atan() / (2.0 * FRAC_PI_4)
    }
}

/// Equal-angle coordinate of sample `i` of a face map `n` samples wide
/// (`n + 1` samples per row, `i ∈ [0, n]`). `i / n` is a correctly rounded
/// quotient, so sample `2i` of a map `2n` wide gives the same value.
#[inline]
pub fn sample_coord(i: u64, n: u64) -> f64 {
    i as f64 / n as f64
}

/// A point on a cube face in equal-angle coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FaceCoord {
    /// The face.
    pub face: Face,
    /// Equal-angle coordinate along the face's `u` axis, in `[0, 1]`.
    pub s: f64,
    /// Equal-angle coordinate along the face's `v` axis, in `[0, 1]`.
    pub t: f64,
}

impl FaceCoord {
    /// The unnormalised point on the cube surface.
    pub fn cube_point(&self) -> [f64; 3] {
        self.face
            .cube_point(plane_from_angle(self.s), plane_from_angle(self.t))
    }

    /// The unit direction from the planet centre (the geodetic normal, as in
    /// thesis Eq. 4.2 and 5.1).
    pub fn direction(&self) -> [f64; 3] {
        normalize(self.cube_point())
    }

    /// Geodetic latitude and longitude in radians of this point.
    pub fn to_lat_lon(&self) -> (f64, f64) {
        lat_lon_from_direction(self.direction())
    }

    /// The face coordinates of the direction `d` (need not be normalised).
    pub fn from_direction(d: [f64; 3]) -> FaceCoord {
        let (face, u, v) = Face::from_direction(d);
        FaceCoord {
            face,
            s: angle_from_plane(u),
            t: angle_from_plane(v),
        }
    }

    /// The face coordinates of a geodetic latitude and longitude in radians.
    pub fn from_lat_lon(lat: f64, lon: f64) -> FaceCoord {
        FaceCoord::from_direction(direction_from_lat_lon(lat, lon))
    }
}

/// Unit direction of a geodetic latitude and longitude (radians).
#[inline]
pub fn direction_from_lat_lon(lat: f64, lon: f64) -> [f64; 3] {
    let (sl, cl) = lat.sin_cos();
    let (so, co) = lon.sin_cos();
    [cl * co, cl * so, sl]
}

/// Geodetic latitude and longitude (radians, longitude in `(-π, π]`) of a
/// direction. At the poles longitude is 0.
#[inline]
pub fn lat_lon_from_direction(d: [f64; 3]) -> (f64, f64) {
    let h = d[0].hypot(d[1]);
    let lat = d[2].atan2(h);
    let lon = if h == 0.0 { 0.0 } else { d[1].atan2(d[0]) };
    (lat, lon)
}

/// Normalise a 3-vector (f64).
#[inline]
pub fn normalize(p: [f64; 3]) -> [f64; 3] {
    let len = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
    [p[0] / len, p[1] / len, p[2] / len]
}

/// Angle in radians between two unit directions, accurate for tiny angles
/// (`2·asin(|a − b| / 2)`, not `acos` of a dot product).
pub fn angle_between(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let c = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    2.0 * (c / 2.0).min(1.0).asin()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::f64::consts::{FRAC_PI_2, PI};

    #[test]
    fn frames_are_right_handed_and_outward() {
        for f in Face::ALL {
            let [u, v, w] = f.frame();
            let c = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            assert_eq!(c, w, "face {f:?}");
            // cube_point agrees with the frame.
            let p = f.cube_point(0.25, -0.5);
            for k in 0..3 {
                assert_eq!(p[k], 0.25 * u[k] + -0.5 * v[k] + w[k]);
            }
        }
    }

    #[test]
    fn pole_faces_and_centres() {
        let c = |f: u8| {
            FaceCoord {
                face: Face::new(f).unwrap(),
                s: 0.5,
                t: 0.5,
            }
            .to_lat_lon()
        };
        assert_eq!(c(0).0, FRAC_PI_2);
        assert_eq!(c(3).0, -FRAC_PI_2);
        assert_eq!(c(2), (0.0, 0.0));
        assert_eq!(c(4), (0.0, FRAC_PI_2));
        assert_eq!(c(1), (0.0, -FRAC_PI_2));
        assert_eq!(c(5), (0.0, PI));
    }

    #[test]
    fn edges_are_exact() {
        assert_eq!(plane_from_angle(0.0), -1.0);
        assert_eq!(plane_from_angle(1.0), 1.0);
        assert_eq!(plane_from_angle(0.5), 0.0);
        for i in 0..=64u64 {
            let s = sample_coord(i, 64);
            assert_eq!(plane_from_angle(s), -plane_from_angle(1.0 - s));
            assert_eq!(sample_coord(2 * i, 128), s);
        }
    }

    proptest! {
        #[test]
        fn lat_lon_round_trip(lat in -FRAC_PI_2..=FRAC_PI_2, lon in -PI..=PI) {
            let fc = FaceCoord::from_lat_lon(lat, lon);
            prop_assert!((0.0..=1.0).contains(&fc.s) && (0.0..=1.0).contains(&fc.t));
            let d0 = direction_from_lat_lon(lat, lon);
            let d1 = fc.direction();
            prop_assert!(angle_between(d0, d1) < 1e-12, "{lat} {lon} {:?}", fc);
        }

        #[test]
        fn face_round_trip(f in 0u8..6, s in 0.0f64..=1.0, t in 0.0f64..=1.0) {
            let fc = FaceCoord { face: Face::new(f).unwrap(), s, t };
            let back = FaceCoord::from_direction(fc.direction());
            prop_assert!(angle_between(back.direction(), fc.direction()) < 1e-12);
            if back.face == fc.face {
                prop_assert!((back.s - s).abs() < 1e-12 && (back.t - t).abs() < 1e-12);
            }
        }
    }
}
