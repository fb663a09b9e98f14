//! Horizon-fitted near and far planes (thesis §4.5.4, Eq. 4.3; erratum in
//! `docs/REFERENCES.md`), computed in `f64` without cancellation. The one
//! home of the formula: the client culls with it and the renderer projects
//! with it.
//!
//! In the plane through the planet centre `O`, the eye `V` and the view
//! direction: `‖OT‖` is the minimum planet radius, `‖OM‖` the maximum, `α`
//! the angle between the view direction and `VO`:
//!
//! ```text
//! ‖VT‖ = sqrt((‖VO‖−‖OT‖)(‖VO‖+‖OT‖))      ‖TM‖ = sqrt((‖OM‖−‖OT‖)(‖OM‖+‖OT‖))
//! far  = (‖VT‖+‖TM‖)·((‖VT‖/‖VO‖)·cos α + (‖OT‖/‖VO‖)·sin α)     (Eq. 4.3)
//! ```
//!
//! - **Erratum / gap in Eq. 4.3.** Eq. 4.3 is the depth of the farthest point
//!   of the max sphere's *horizon ring*. When the view direction points above
//!   the tangent cone, the max-sphere point farthest along it, `O + ‖OM‖·f`,
//!   can be visible and deeper; we take its depth `‖VO‖·cos α + ‖OM‖` when
//!   the segment from the eye to it misses the min sphere. Then
//!   `far ≥ ‖VO‖ − ‖OT‖` as in the thesis, plus a relative margin of 1e-4.
//!   `far_bounds_every_visible_point` checks the result against brute force.
//! - **Near plane [VAGUE in the thesis].** The closest planet point is at
//!   `‖VO‖ − ‖OM‖`; seen in a screen corner it has depth
//!   `dist·cos(half diagonal fov)`, so `near = (‖VO‖ − ‖OM‖)·cos θc`, clamped
//!   to [`MIN_NEAR`].
//! - **Inside the min sphere** (or at the centre) there is no horizon: far is
//!   the far side of the max sphere, `‖VO‖ + ‖OM‖`. Degenerate inputs (NaN,
//!   a zero direction) give finite planes, never NaN.

use glam::DVec3;

use crate::camera::Camera;

/// Smallest near-plane distance in metres.
pub const MIN_NEAR: f64 = 0.05;

/// Relative margin added to the far plane.
const FAR_MARGIN: f64 = 1e-4;

/// Near and far plane distances along the view axis, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClipPlanes {
    /// Near plane distance (> 0).
    pub near: f64,
    /// Far plane distance (> near).
    pub far: f64,
}

impl Camera {
    /// Horizon-fitted clip planes of this camera for a planet whose surface
    /// lies between the radii `r_min` and `r_max` (see [`horizon_planes`]).
    pub fn clip_planes(&self, r_min: f64, r_max: f64) -> ClipPlanes {
        horizon_planes(
            self.eye,
            self.forward,
            r_min,
            r_max,
            self.half_diagonal_fov(),
        )
    }
}

/// Whether the segment `a → b` passes strictly inside the ball of radius `r`
/// centred on the origin.
pub fn segment_hits_ball(a: DVec3, b: DVec3, r: f64) -> bool {
    let d = b - a;
    let dd = d.length_squared();
    let t = if dd > 0.0 {
        (-a.dot(d) / dd).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (a + d * t).length() < r
}

/// Horizon-fitted clip planes.
///
/// - `eye`: the eye position relative to the planet centre (metres).
/// - `dir`: the view direction (need not be normalised).
/// - `r_min`, `r_max`: the minimum and maximum planet radius (datum plus the
///   minimum and maximum elevation).
/// - `half_diagonal_fov`: half the angle between opposite screen corners.
pub fn horizon_planes(
    eye: DVec3,
    dir: DVec3,
    r_min: f64,
    r_max: f64,
    half_diagonal_fov: f64,
) -> ClipPlanes {
    let vo = eye.length();
    let r_min = r_min.max(0.0);
    let r_max = r_max.max(r_min);
    let fallback = ClipPlanes {
        near: MIN_NEAR,
        // `min(f64::MAX)`: an eye at 1e300 m would overflow to +inf.
        far: ((vo + r_max).max(MIN_NEAR * 2.0) * (1.0 + FAR_MARGIN)).min(f64::MAX),
    };
    let Some(d) = dir.try_normalize() else {
        return fallback;
    };
    if !(vo.is_finite() && r_max.is_finite()) || vo == 0.0 {
        return fallback;
    }
    // cos α = d · (O − V)/‖VO‖; sin α ≥ 0 from the cross product (accurate
    // for small angles).
    let a = -eye / vo;
    let cos_a = d.dot(a).clamp(-1.0, 1.0);
    let sin_a = d.cross(a).length().min(1.0);

    let far = if vo <= r_min {
        // Inside the minimum sphere: anything up to the far side of the max
        // sphere may be visible.
        vo + r_max
    } else {
        let vt = ((vo - r_min) * (vo + r_min)).sqrt();
        let tm = ((r_max - r_min) * (r_max + r_min)).sqrt();
        let ring = (vt + tm) * ((vt / vo) * cos_a + (r_min / vo) * sin_a);
        let mut far = ring.max(vo - r_min);
        // The max-sphere point farthest along `d`, when it is visible.
        let q = d * r_max;
        if !segment_hits_ball(eye, q, r_min) {
            far = far.max(d.dot(q - eye));
        }
        far
    };
    let near = ((vo - r_max) * half_diagonal_fov.cos().max(0.0)).max(MIN_NEAR);
    let far = (far * (1.0 + FAR_MARGIN)).max(near * 2.0);
    if !(near.is_finite() && far.is_finite()) {
        return fallback;
    }
    ClipPlanes { near, far }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const R: f64 = 6_371_000.0;
    const R_MIN: f64 = R - 11_000.0;
    const R_MAX: f64 = R + 8_848.0;

    fn check(eye: DVec3, dir: DVec3) -> ClipPlanes {
        let p = horizon_planes(eye, dir, R_MIN, R_MAX, 0.6);
        assert!(
            p.near.is_finite() && p.far.is_finite(),
            "{eye:?} {dir:?} {p:?}"
        );
        assert!(p.near > 0.0 && p.near < p.far, "{eye:?} {dir:?} {p:?}");
        p
    }

    /// Brute force: the largest depth of a visible point of the max sphere.
    fn brute_far(eye: DVec3, dir: DVec3) -> f64 {
        let d = dir.normalize();
        let mut best = f64::MIN;
        let n = 400;
        for a in 0..n {
            for b in 0..n / 2 {
                let lon = a as f64 / n as f64 * std::f64::consts::TAU;
                let lat = (b as f64 / (n / 2) as f64 - 0.5) * std::f64::consts::PI;
                let p = DVec3::new(lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin()) * R_MAX;
                if segment_hits_ball(eye, p, R_MIN) {
                    continue;
                }
                best = best.max(d.dot(p - eye));
            }
        }
        best
    }

    #[test]
    fn altitudes_and_directions() {
        for h in [0.01, 1.0, 10_000.0, R, 1000.0 * R] {
            let eye = DVec3::new(0.0, 0.0, R_MAX + h);
            for dir in [
                DVec3::NEG_Z,
                DVec3::Z,
                DVec3::X,
                DVec3::new(1.0, 0.0, -0.3),
                DVec3::new(1.0, 0.0, 0.01),
                DVec3::new(0.3, 0.2, -1.0),
            ] {
                let p = check(eye, dir);
                // Looking straight down: near below the closest point.
                if dir == DVec3::NEG_Z {
                    assert!(p.near <= h.max(MIN_NEAR) + 1e-9, "{h} {p:?}");
                    assert!(p.far >= h + R_MAX - R_MIN);
                }
            }
        }
        // Inside the planet, at the centre, on the min sphere.
        for eye in [
            DVec3::new(0.0, 0.0, 1000.0),
            DVec3::ZERO,
            DVec3::new(R_MIN, 0.0, 0.0),
            DVec3::new(R, 0.0, 0.0),
        ] {
            for dir in [DVec3::X, DVec3::Y, DVec3::NEG_X] {
                check(eye, dir);
            }
        }
        // Degenerate inputs do not produce NaN.
        check(DVec3::X, DVec3::ZERO);
        check(DVec3::new(f64::NAN, 0.0, 0.0), DVec3::Z);
        check(DVec3::new(1e300, 0.0, 0.0), DVec3::NEG_X);
    }

    #[test]
    fn one_metre_above_everest_along_the_horizon() {
        let p = check(DVec3::new(R_MAX + 1.0, 0.0, 0.0), DVec3::Y);
        // VT ≈ TM ≈ 502 km for these radii.
        assert!(p.far > 900_000.0 && p.far < 1_100_000.0, "{p:?}");
        assert!((p.near - 0.6f64.cos()).abs() < 1e-6, "{p:?}");
        let p = check(DVec3::new(R + 1.0, 0.0, 0.0), DVec3::Y);
        assert_eq!(p.near, MIN_NEAR);
    }

    #[test]
    fn fields_of_view_from_1_to_170_degrees() {
        let eye = DVec3::new(0.0, 0.0, R_MAX + 1000.0);
        let mut near = Vec::new();
        for deg in [1.0f64, 60.0, 170.0] {
            let mut cam = Camera::look_at(eye, DVec3::ZERO, DVec3::X);
            cam.fov_y = deg.to_radians();
            let p = cam.clip_planes(R_MIN, R_MAX);
            assert!(p.near > 0.0 && p.near < p.far, "{deg} {p:?}");
            assert!(p.far >= 1000.0 + R_MAX - R_MIN, "{deg} {p:?}");
            near.push(p.near);
        }
        // A wider field of view moves the near plane closer.
        assert!(near[0] > near[1] && near[1] > near[2], "{near:?}");
    }

    #[test]
    fn far_bounds_every_visible_point() {
        for h in [100.0, 10_000.0, 1_000_000.0, R, 10.0 * R] {
            let eye = DVec3::new(R_MAX + h, 0.0, 0.0);
            for k in 0..=12 {
                let ang = k as f64 / 12.0 * std::f64::consts::PI;
                let dir = DVec3::new(-ang.cos(), ang.sin(), 0.0);
                let p = check(eye, dir);
                let b = brute_far(eye, dir);
                assert!(
                    p.far >= b * (1.0 - 1e-5),
                    "h {h} angle {ang}: far {} < {b}",
                    p.far
                );
            }
        }
    }

    fn unit(lat: f64, lon: f64) -> DVec3 {
        DVec3::new(lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin())
    }

    proptest! {
        /// No visible point between the two spheres is beyond the far plane
        /// or in front of the near plane, from inside the planet to 1.5
        /// million km away.
        #[test]
        fn planes_never_cull_visible_points(
            alt in prop_oneof![-2.0e6f64..0.0, 0.0f64..1.0e4, 1.0e4f64..1.0e8],
            ea in -1.5f64..1.5, eb in -3.2f64..3.2,
            fa in -1.5f64..1.5, fb in -3.2f64..3.2,
            pts in proptest::collection::vec((-1.5f64..1.5, -3.2f64..3.2, 0.0f64..1.0), 64),
            relief in 0.0f64..20_000.0,
        ) {
            let r_min = R - relief;
            let r_max = R + relief;
            let eye = unit(ea, eb) * (R + alt);
            let mut cam = Camera::look_at(eye, eye + unit(fa, fb), DVec3::Z);
            cam.fov_y = 1.0;
            let p = cam.clip_planes(r_min, r_max);
            prop_assert!(p.near.is_finite() && p.far.is_finite() && p.near > 0.0 && p.far > p.near);
            let b = cam.basis();
            for (a, bb, h) in pts {
                let q = unit(a, bb) * (r_min + (r_max - r_min) * h.sqrt());
                if segment_hits_ball(eye, q, r_min) { continue; }
                let depth = b.forward.dot(q - eye);
                prop_assert!(depth <= p.far, "depth {depth} far {}", p.far);
                // Inside the frustum's corner cone, nothing is nearer than near.
                let dist = (q - eye).length();
                if depth >= dist * cam.half_diagonal_fov().cos() {
                    prop_assert!(depth >= p.near * (1.0 - 1e-9) || p.near == MIN_NEAR,
                        "depth {depth} near {}", p.near);
                }
            }
            // The ring's farthest point and points toward the horizon.
            for k in 0..64 {
                let q = unit(fa + (k as f64 - 32.0) * 0.02, fb) * r_max;
                if segment_hits_ball(eye, q, r_min) { continue; }
                prop_assert!(b.forward.dot(q - eye) <= p.far);
            }
        }
    }
}
