//! Importance of blocks, LOD selection, triggers and screen-space error.
//!
//! Implements thesis Eq. 3.2–3.4 (§3.6.2–3.6.4) specialised to 3D (§4.2.4;
//! see docs/REFERENCES.md):
//!
//! ```text
//! distance   = |eye − centre of block bounding box| − blockRadius
//! quality    = sqrt(QF) · blockRadius / (blockWidth · distance)
//! importance = −log2(quality)
//! ```
//!
//! `blockRadius` [VAGUE in the thesis] is the footprint radius of
//! [`crate::visibility::BlockBounds`]. The "large negative constant" for
//! `distance ≤ 0` (not given by the thesis) is [`IMPORTANCE_NEAR`] `= −64`; importance is clamped
//! to `[−64, 64]` so it is finite for any input (QF 0, non-finite distances,
//! eye at the centre of the planet or 1e12 m away).
//!
//! LOD selection: `ceil(importance)` clamped to `[0, 1]` (`subDepth = 1`).
//! Triggers (Eq. 3.4): refine when the selected LOD is finer than the one
//! available (request importance `usedLOD − importance`); split a fully
//! loaded leaf when `importance < −1` (virtual LOD −1; request importance
//! `−importance`); merge a split block when `ceil(importance) ≥ 1` (its last
//! LOD is not selected; request importance `importance`).
//!
//! Screen-space error (for measurement): `ρ = ε·H / (2·d·tan(fov/2))`.

/// Importance given to a block whose distance is not positive or finite.
pub const IMPORTANCE_NEAR: f64 = -64.0;
/// Largest importance (QF 0, infinitely far).
pub const IMPORTANCE_FAR: f64 = 64.0;
/// Split threshold: the virtual LOD −1 of Eq. 3.4.
pub const SPLIT_THRESHOLD: f64 = -1.0;

/// Distance from the eye to the closest possible point of a block
/// (`|eye − centre| − radius`).
pub fn block_distance(eye: glam::DVec3, centre: glam::DVec3, radius: f64) -> f64 {
    (eye - centre).length() - radius
}

/// Importance of a block (Eq. 3.2, 3.3), always finite, in `[−64, 64]`.
pub fn importance(distance: f64, block_radius: f64, block_width: f64, qf: f64) -> f64 {
    Importance::new(qf).of(distance, block_radius, block_width)
}

/// [`importance`] for one quality factor, with `sqrt(QF)` computed once (the
/// same result for every block; the per-frame selection evaluates it for
/// thousands of blocks).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Importance {
    q1: f64,
}

impl Importance {
    /// For quality factor `qf`.
    pub fn new(qf: f64) -> Importance {
        // +∞ and NaN mean "best quality"; −∞ (like any negative QF) means
        // none, so importance stays monotone in QF over the whole extended
        // line.
        let q1 = if qf.is_finite() || qf == f64::NEG_INFINITY {
            qf.max(0.0).sqrt()
        } else {
            f64::MAX.sqrt()
        };
        Importance { q1 }
    }

    fn quality(&self, distance: f64, block_radius: f64, block_width: f64) -> f64 {
        self.q1 * block_radius.max(0.0) / (block_width.max(1.0) * distance)
    }

    /// [`importance`]`(distance, block_radius, block_width, qf)`.
    pub fn of(&self, distance: f64, block_radius: f64, block_width: f64) -> f64 {
        if distance.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return IMPORTANCE_NEAR;
        }
        let quality = self.quality(distance, block_radius, block_width);
        if quality.is_nan() {
            return IMPORTANCE_NEAR;
        }
        if quality <= 0.0 {
            return IMPORTANCE_FAR;
        }
        (-quality.log2()).clamp(IMPORTANCE_NEAR, IMPORTANCE_FAR)
    }

    /// [`importance`] of a split block where [`wants_merge`] may hold,
    /// `None` where it certainly does not, without the logarithm (the
    /// per-frame selection asks this of every split block, §3.6.4):
    /// `importance > 0` needs `quality < 1`, since `log2` (faithfully
    /// rounded, exact at 1) is `≥ 0` from 1 up. Where it returns `Some`, the
    /// value is [`Importance::of`]'s.
    pub fn if_may_merge(&self, distance: f64, block_radius: f64, block_width: f64) -> Option<f64> {
        if distance.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        if self.quality(distance, block_radius, block_width) >= 1.0 {
            return None;
        }
        Some(self.of(distance, block_radius, block_width))
    }
}

/// The LOD to render: `ceil(importance)` clamped to `[0, 1]`
/// (`ceil(x) ≥ 1` exactly when `x > 0`, also false for NaN).
pub fn selected_lod(importance: f64) -> u8 {
    if importance > 0.0 {
        1
    } else {
        0
    }
}

/// Request importance of a refine from `used_lod` (Eq. 3.4 family).
pub fn refine_importance(used_lod: u8, importance: f64) -> f64 {
    used_lod as f64 - importance
}

/// Whether a fully loaded leaf should split (virtual LOD −1).
pub fn wants_split(importance: f64) -> bool {
    importance < SPLIT_THRESHOLD
}

/// Request importance of a split.
pub fn split_importance(importance: f64) -> f64 {
    -importance
}

/// Whether a split block should merge: a LOD other than its last suffices
/// (`ceil(importance) ≥ 1`, i.e. `importance > 0`).
pub fn wants_merge(importance: f64) -> bool {
    importance > 0.0
}

/// Screen-space error in pixels of a geometric error `error` metres seen at
/// `distance` metres: `ε·H / (2·d·tan(fov_y/2))`, finite for any input.
pub fn screen_space_error(error: f64, distance: f64, viewport_height_px: f64, fov_y: f64) -> f64 {
    ScreenError::new(viewport_height_px, fov_y).of(error, distance)
}

/// [`screen_space_error`] for one camera, with the tangent computed once
/// (the same result for every block).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScreenError {
    h: f64,
    t: f64,
}

impl ScreenError {
    /// For a viewport `viewport_height_px` high with vertical fov `fov_y`.
    pub fn new(viewport_height_px: f64, fov_y: f64) -> ScreenError {
        ScreenError {
            h: viewport_height_px.max(0.0),
            t: (fov_y * 0.5).tan().abs().max(1e-9),
        }
    }

    /// Screen-space error in pixels of `error` metres at `distance` metres.
    pub fn of(&self, error: f64, distance: f64) -> f64 {
        self.apply(error, self.scale(distance))
    }

    /// Pixels per metre of error at `distance` metres, `H / (2·d·tan(fov/2))`
    /// (finite and non-negative; `distance` at least 1 mm): the factor of
    /// [`ScreenError::of`], computed once for the several errors of one
    /// block.
    pub fn scale(&self, distance: f64) -> f64 {
        let d = if distance.is_finite() {
            distance.max(1e-3)
        } else {
            f64::MAX
        };
        let k = self.h / (2.0 * d * self.t);
        if k.is_finite() {
            k
        } else {
            f64::MAX
        }
    }

    /// The distance at which `error` metres project to `px` pixels,
    /// `ε·H / (2·ρ·tan(fov/2))`: [`ScreenError::of`] solved for the
    /// distance (in real arithmetic; it may be infinite or NaN).
    pub fn distance_for(&self, error: f64, px: f64) -> f64 {
        error * self.h / (2.0 * px * self.t)
    }

    /// Screen-space error in pixels of `error` metres at the distance whose
    /// [`ScreenError::scale`] is `scale`.
    pub fn apply(&self, error: f64, scale: f64) -> f64 {
        let e = if error.is_finite() {
            error.max(0.0)
        } else {
            0.0
        };
        let rho = e * scale;
        if rho.is_finite() {
            rho
        } else {
            f64::MAX
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn finite_and_monotone(d1 in -1e13f64..1e13, d2 in -1e13f64..1e13, r in 0.0f64..1e7, qf in prop_oneof![Just(0.0), 0.0f64..1e12, Just(f64::INFINITY)]) {
            let (a, b) = (importance(d1, r, 64.0, qf), importance(d2, r, 64.0, qf));
            prop_assert!(a.is_finite() && b.is_finite());
            if d1 <= d2 { prop_assert!(a <= b); }
            prop_assert!(screen_space_error(3.0, d1, 1080.0, 1.0).is_finite());
        }
    }

    proptest! {
        /// `Importance::if_may_merge` is `importance` wherever a merge may be
        /// wanted, and `None` only where it is not (also around quality 1).
        #[test]
        fn merge_importance_agrees(d in -1e7f64..1e13, r in 0.0f64..1e7, w in prop_oneof![Just(8.0), Just(64.0)], qf in prop_oneof![Just(0.0), 0.0f64..1e12, Just(f64::INFINITY)], ulps in -4i64..4) {
            // Also put the quality within a few ulps of 1.
            let q1 = qf.sqrt();
            let d1 = if q1 > 0.0 && q1.is_finite() && r > 0.0 {
                f64::from_bits(((q1 * r / w).to_bits() as i64 + ulps) as u64)
            } else {
                d
            };
            for d in [d, d1] {
                let imp = importance(d, r, w, qf);
                match Importance::new(qf).if_may_merge(d, r, w) {
                    Some(m) => prop_assert_eq!(m.to_bits(), imp.to_bits()),
                    None => prop_assert!(!wants_merge(imp), "{} {} {} {}", d, r, w, qf),
                }
            }
        }
    }

    #[test]
    fn thresholds() {
        // Child (half radius) at the same distance is one unit more important.
        let p = importance(1000.0, 100.0, 64.0, 1e4);
        let c = importance(1000.0, 50.0, 64.0, 1e4);
        assert!((c - p - 1.0).abs() < 1e-12);
        assert_eq!(selected_lod(0.5), 1);
        assert_eq!(selected_lod(0.0), 0);
        assert_eq!(selected_lod(-3.0), 0);
        assert!(wants_split(-1.5) && !wants_split(-1.0));
        assert!(wants_merge(0.1) && !wants_merge(0.0));
        for x in [
            -1.5,
            -1.0,
            -0.5,
            -0.0,
            0.0,
            1e-300,
            0.5,
            1.0,
            1.5,
            f64::NAN,
            f64::INFINITY,
        ] {
            assert_eq!(selected_lod(x) == 1, x.ceil() >= 1.0, "{x}");
            assert_eq!(wants_merge(x), x.ceil() >= 1.0, "{x}");
        }
        assert_eq!(importance(0.0, 1.0, 64.0, 1.0), IMPORTANCE_NEAR);
        assert_eq!(importance(f64::NAN, 1.0, 64.0, 1.0), IMPORTANCE_NEAR);
        assert_eq!(importance(1.0, 1.0, 64.0, 0.0), IMPORTANCE_FAR);
        assert!(importance(f64::INFINITY, 1.0, 64.0, 1.0).is_finite());
    }
}
