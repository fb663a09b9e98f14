//! Horizon-fitted near and far planes for the renderer: the formula of
//! [`planet_core::horizon`] (thesis §4.5.4, Eq. 4.3, with its gap closed),
//! taking the renderer's `[f64; 3]` vectors. Its tests live there.

pub use planet_core::horizon::{ClipPlanes, MIN_NEAR};

/// Horizon-fitted clip planes ([`planet_core::horizon::horizon_planes`]).
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
    planet_core::horizon::horizon_planes(eye.into(), dir.into(), r_min, r_max, half_diagonal_fov)
}
