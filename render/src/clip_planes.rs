//! Horizon-fitted near and far planes (Thesis §4.5.4, Eq. 4.3; see
//! docs/REFERENCES.md), computed in f64 without cancellation.
//!
//! In the plane through the planet centre `O`, the eye `V` and the view
//! direction: `‖OT‖` is the minimum planet radius, `‖OM‖` the maximum, `α`
//! the angle between the view direction and `VO`, `β = ∠TVO` the angle of the
//! tangent cone to the minimum sphere:
//!
//! ```text
//! ‖VT‖ = sqrt((‖VO‖−‖OT‖)(‖VO‖+‖OT‖))      ‖TM‖ = sqrt((‖OM‖−‖OT‖)(‖OM‖+‖OT‖))
//! far  = (‖VT‖+‖TM‖)·((‖VT‖/‖VO‖)·cos α + (‖OT‖/‖VO‖)·sin α)     (Eq. 4.3)
//! ```
//!
//! Eq. 4.3 is the depth of the farthest horizon point `M`. It is not always an
//! upper bound: when the view direction points above the tangent cone, a
//! point of the maximum sphere outside the cone can be deeper; we also take
//! the maximum of the depth over the whole max sphere, `‖VO‖·cos α + ‖OM‖`,
//! when its maximiser lies outside the cone (so it may be visible). Then
//! `far ≥ ‖VO‖ − ‖OT‖` as in the thesis, plus a small relative margin.
//!
//! Near: the closest planet point is at `‖VO‖ − ‖OM‖`; a point at that
//! distance seen in a screen corner has depth `dist·cos(half diagonal fov)`,
//! so `near = (‖VO‖ − ‖OM‖)·cos(half diagonal fov)`, clamped to
//! [`MIN_NEAR`].

/// Smallest near-plane distance in metres.
pub const MIN_NEAR: f64 = 0.05;

/// Near and far plane distances along the view axis, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClipPlanes {
    /// Near plane distance (> 0).
    pub near: f64,
    /// Far plane distance (> near).
    pub far: f64,
}

/// Horizon-fitted clip planes.
///
/// - `eye`: the eye position relative to the planet centre (metres).
/// - `dir`: the view direction (need not be normalised).
/// - `r_min`, `r_max`: the minimum and maximum planet radius (datum plus the
///   minimum and maximum elevation).
/// - `half_diagonal_fov`: half the angle between opposite screen corners.
pub fn horizon_planes(
    eye: [f64; 3],
    dir: [f64; 3],
    r_min: f64,
    r_max: f64,
    half_diagonal_fov: f64,
) -> ClipPlanes {
    let vo = norm(eye);
    let dl = norm(dir);
    let r_min = r_min.max(0.0);
    let r_max = r_max.max(r_min);
    let fallback = ClipPlanes {
        near: MIN_NEAR,
        // `min(f64::MAX)`: an eye at 1e300 m would overflow to +inf.
        far: ((vo + r_max).max(MIN_NEAR * 2.0) * 1.001).min(f64::MAX),
    };
    if !(vo.is_finite() && dl.is_finite() && dl > 0.0 && r_max.is_finite()) || vo == 0.0 {
        return fallback;
    }
    let d = [dir[0] / dl, dir[1] / dl, dir[2] / dl];
    // cos α = d · (O − V)/‖VO‖; sin α ≥ 0 from the cross product (accurate
    // for small angles).
    let a = [-eye[0] / vo, -eye[1] / vo, -eye[2] / vo];
    let cos_a = (d[0] * a[0] + d[1] * a[1] + d[2] * a[2]).clamp(-1.0, 1.0);
    let cr = [
        d[1] * a[2] - d[2] * a[1],
        d[2] * a[0] - d[0] * a[2],
        d[0] * a[1] - d[1] * a[0],
    ];
    let sin_a = norm(cr).min(1.0);

    let far = if vo <= r_min {
        // Inside the minimum sphere: anything up to the far side of the max
        // sphere may be visible.
        vo + r_max
    } else {
        let vt = ((vo - r_min) * (vo + r_min)).sqrt();
        let tm = ((r_max - r_min) * (r_max + r_min)).sqrt();
        let mut far = (vt + tm) * ((vt / vo) * cos_a + (r_min / vo) * sin_a);
        // Max of the depth over the max sphere, at Q = O + r_max·d, if Q is
        // outside the shadow cone of the min sphere (angle from VO ≥ β).
        let q_rel = [
            -eye[0] + r_max * d[0],
            -eye[1] + r_max * d[1],
            -eye[2] + r_max * d[2],
        ];
        let ql = norm(q_rel);
        let cos_theta = if ql > 0.0 {
            (q_rel[0] * a[0] + q_rel[1] * a[1] + q_rel[2] * a[2]) / ql
        } else {
            1.0
        };
        let cos_beta = vt / vo;
        if cos_theta <= cos_beta || vo <= r_max {
            far = far.max(vo * cos_a + r_max);
        }
        far.max(vo - r_min)
    };
    let near_dist = vo - r_max;
    let near = (near_dist * half_diagonal_fov.cos().max(0.0)).max(MIN_NEAR);
    let far = (far * (1.0 + 1e-4)).max(near * 2.0);
    if !(near.is_finite() && far.is_finite()) {
        return fallback;
    }
    ClipPlanes { near, far }
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    const R: f64 = 6_371_000.0;
    const R_MIN: f64 = R - 11_000.0;
    const R_MAX: f64 = R + 8_848.0;

    fn check(eye: [f64; 3], dir: [f64; 3]) -> ClipPlanes {
        let p = horizon_planes(eye, dir, R_MIN, R_MAX, 0.6);
        assert!(
            p.near.is_finite() && p.far.is_finite(),
            "{eye:?} {dir:?} {p:?}"
        );
        assert!(p.near > 0.0 && p.near < p.far, "{eye:?} {dir:?} {p:?}");
        p
    }

    /// Brute force: the largest depth of a visible point of the max sphere
    /// (sampled in the plane of O, V and the view direction and out of it).
    fn brute_far(eye: [f64; 3], dir: [f64; 3]) -> f64 {
        let dl = norm(dir);
        let d = [dir[0] / dl, dir[1] / dl, dir[2] / dl];
        let mut best = f64::MIN;
        let n = 400;
        for a in 0..n {
            for b in 0..n / 2 {
                let lon = a as f64 / n as f64 * std::f64::consts::TAU;
                let lat = (b as f64 / (n / 2) as f64 - 0.5) * std::f64::consts::PI;
                let u = [lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin()];
                let p = [u[0] * R_MAX, u[1] * R_MAX, u[2] * R_MAX];
                // Visible if the segment eye→p misses the min sphere.
                let v = [p[0] - eye[0], p[1] - eye[1], p[2] - eye[2]];
                let l2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
                let t = (-(eye[0] * v[0] + eye[1] * v[1] + eye[2] * v[2]) / l2).clamp(0.0, 1.0);
                let c = [eye[0] + t * v[0], eye[1] + t * v[1], eye[2] + t * v[2]];
                if norm(c) < R_MIN {
                    continue;
                }
                best = best.max(v[0] * d[0] + v[1] * d[1] + v[2] * d[2]);
            }
        }
        best
    }

    #[test]
    fn altitudes_and_directions() {
        let down = |h: f64| ([0.0, 0.0, R_MAX + h], [0.0, 0.0, -1.0]);
        for h in [0.01, 1.0, 10_000.0, R, 1000.0 * R] {
            let (eye, _) = down(h);
            for dir in [
                [0.0, 0.0, -1.0],
                [0.0, 0.0, 1.0],
                [1.0, 0.0, 0.0],
                [1.0, 0.0, -0.3],
                [1.0, 0.0, 0.01],
                [0.3, 0.2, -1.0],
            ] {
                let p = check(eye, dir);
                // Looking straight down: near below the closest point.
                if dir == [0.0, 0.0, -1.0] {
                    assert!(p.near <= h.max(MIN_NEAR) + 1e-9, "{h} {p:?}");
                    assert!(p.far >= h + R_MAX - R_MIN);
                }
            }
        }
        // Inside the planet, at the centre, on the min sphere.
        for eye in [
            [0.0, 0.0, 1000.0],
            [0.0; 3],
            [R_MIN, 0.0, 0.0],
            [R, 0.0, 0.0],
        ] {
            for dir in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]] {
                check(eye, dir);
            }
        }
        // Degenerate inputs do not produce NaN.
        check([1.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
        check([f64::NAN, 0.0, 0.0], [0.0, 0.0, 1.0]);
    }

    #[test]
    fn one_metre_above_everest_along_the_horizon() {
        let eye = [R_MAX + 1.0, 0.0, 0.0];
        let p = check(eye, [0.0, 1.0, 0.0]);
        // VT ≈ TM ≈ 502 km for these radii.
        assert!(p.far > 900_000.0 && p.far < 1_100_000.0, "{p:?}");
        assert!((p.near - 1.0 * 0.6f64.cos()).abs() < 1e-6, "{p:?}");
        let p = check([R + 1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
        assert_eq!(p.near, MIN_NEAR);
    }

    #[test]
    fn far_bounds_every_visible_point() {
        for h in [100.0, 10_000.0, 1_000_000.0, R, 10.0 * R] {
            let eye = [R_MAX + h, 0.0, 0.0];
            for k in 0..=12 {
                let ang = k as f64 / 12.0 * std::f64::consts::PI;
                let dir = [-ang.cos(), ang.sin(), 0.0];
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
}
