//! Camera-relative vertex positions in f32 with one rounding (Thesis §4.5.5,
//! see docs/REFERENCES.md: a local frame per block plus a viewpoint-centred one).
//!
//! The thesis renders block-relative f32 vertices and notes 0.5–1 m of error
//! for a global f32 frame and 3 mm for its fixed-point proposal. Adding an
//! f32 block offset `centre − eye` to an f32 block-relative position rounds
//! three times (the position, the offset and the sum); at 8–10 km from the
//! eye the f32 ulp is 0.98 mm, so those three roundings reach ≈ 1–2 mm, and
//! for coarse blocks near the eye (a database whose leaves are coarse there)
//! the position's own rounding is `2⁻²⁴ · block radius`: metres for a level-0
//! block.
//!
//! Here both terms are carried as an unevaluated sum of a high and a low part
//! ("double-single"):
//!
//! - per vertex, `pos_hi = f32(p − centre)` and `pos_lo = f16(p − centre −
//!   pos_hi)` (the residual is at most half an f32 ulp of the position, so an
//!   f16 keeps it to 2⁻¹² of that: 0.5 mm for a 64 000 km block, 0.1 µm for a
//!   10 km one);
//! - per block, `off_hi = f32(centre − eye)` and `off_lo = f32(centre − eye −
//!   off_hi)`, the difference taken in f64 on the CPU;
//! - in the vertex shader, `pos_hi + off_hi` is added with Knuth's TwoSum
//!   (`s + err` equals the exact sum), and the small terms are added to the
//!   error before the one rounding that matters: `s + (err + (lo + off_lo))`.
//!
//! The result is the f64 camera-relative position rounded once to f32 (half
//! an ulp: ≤ 0.49 mm per coordinate within 16 km) plus the low parts' tiny
//! roundings, whatever the block size. [`camera_relative`] is the CPU replica
//! of the shader function in `camera_relative.wgsl`, operation for operation;
//! `render/tests/gpu_precision.rs` checks that the GPU's results are the same
//! bits. It caught lavapipe (Mesa's NIR treats float ops as reassociable and
//! folds `(a + b) − a` to `b`) zeroing the TwoSum error in 917 of 4 096
//! cases; the shader now passes its intermediate sums through an OR with an
//! integer zero read from a uniform, which no float rule can see through.
//! (Were a compiler still to fold the TwoSum, the error term would become 0
//! and the result would fall back to the plain two-rounding sum.)

/// The WGSL source of `camera_relative(pos_hi, pos_lo, off_hi, off_lo)`,
/// prepended to the renderer's shader.
pub const WGSL: &str = include_str!("camera_relative.wgsl");

/// A block's `centre − eye` as an f32 high part and an f32 low part.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplitOffset {
    /// `f32(centre − eye)`.
    pub hi: [f32; 3],
    /// `f32((centre − eye) − hi)`.
    pub lo: [f32; 3],
}

impl SplitOffset {
    /// Split an f64 camera-relative offset.
    pub fn new(rel: [f64; 3]) -> SplitOffset {
        let (hi, lo) = split_f32(rel);
        SplitOffset { hi, lo }
    }
}

/// `(f32(v), f32(v − f32(v)))` per coordinate. Non-finite inputs give a
/// non-finite high part and a zero low part (never NaN from `∞ − ∞`).
pub fn split_f32(v: [f64; 3]) -> ([f32; 3], [f32; 3]) {
    let hi = v.map(|c| c as f32);
    let mut lo = [0.0f32; 3];
    for k in 0..3 {
        let h = hi[k] as f64;
        if h.is_finite() && v[k].is_finite() {
            lo[k] = (v[k] - h) as f32;
        }
    }
    (hi, lo)
}

/// A vertex's low part as f16 bits `[x, y, z, 0]` (the `Float16x4` vertex
/// attribute): the residual `v − f32(v)` of each coordinate.
pub fn low_part_f16(v: [f64; 3], hi: [f32; 3]) -> [u16; 4] {
    let mut out = [0u16; 4];
    for k in 0..3 {
        let h = hi[k] as f64;
        if h.is_finite() && v[k].is_finite() {
            out[k] = half::f16::from_f64(v[k] - h).to_bits();
        }
    }
    out
}

/// The f32 value of an f16 low part.
pub fn low_part_f32(bits: [u16; 4]) -> [f32; 3] {
    [0, 1, 2].map(|k| half::f16::from_bits(bits[k]).to_f32())
}

/// The CPU replica of the shader's `camera_relative`: the same f32
/// operations in the same order.
pub fn camera_relative(
    pos_hi: [f32; 3],
    pos_lo: [f32; 3],
    off_hi: [f32; 3],
    off_lo: [f32; 3],
) -> [f32; 3] {
    let mut out = [0.0f32; 3];
    for k in 0..3 {
        let (a, b) = (pos_hi[k], off_hi[k]);
        // TwoSum (Knuth): s + err == a + b exactly, for any order of |a|, |b|.
        let s = a + b;
        let bb = s - a;
        let err = (a - (s - bb)) + (b - bb);
        out[k] = s + (err + (pos_lo[k] + off_lo[k]));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn exact_error(pos: [f64; 3], off: [f64; 3]) -> (f64, f64) {
        let (hi, _) = split_f32(pos);
        let lo = low_part_f32(low_part_f16(pos, hi));
        let o = SplitOffset::new(off);
        let r = camera_relative(hi, lo, o.hi, o.lo);
        let mut worst_ulps = 0.0f64;
        let mut worst_m = 0.0f64;
        for k in 0..3 {
            let exact = pos[k] + off[k];
            let e = (r[k] as f64 - exact).abs();
            // Half an ulp of the result (one rounding), in units of ulp.
            let ulp = f32::EPSILON as f64 * (exact.abs().max(f32::MIN_POSITIVE as f64));
            worst_ulps = worst_ulps.max(e / ulp);
            worst_m = worst_m.max(e);
        }
        (worst_ulps, worst_m)
    }

    #[test]
    fn twosum_recovers_what_plain_f32_loses() {
        // A 10 km block centre 8.5 km from the eye: the plain sum of f32 parts
        // loses about a millimetre, the split sum keeps half an ulp.
        let pos = [4_321.123_456_789, -2_468.987_654_321, 1_234.5];
        let off = [4_200.000_123_4, 7_100.777_777_7, -3_000.000_000_9];
        let plain: Vec<f64> = (0..3)
            .map(|k| ((pos[k] as f32 + off[k] as f32) as f64 - (pos[k] + off[k])).abs())
            .collect();
        let (ulps, m) = exact_error(pos, off);
        assert!(ulps <= 0.5 + 1e-6, "{ulps} ulps");
        assert!(m < 0.5e-3, "{m} m");
        assert!(plain.iter().cloned().fold(0.0, f64::max) > m);
    }

    #[test]
    fn non_finite_offsets_do_not_make_nan_low_parts() {
        let o = SplitOffset::new([f64::INFINITY, 1e300, f64::NAN]);
        assert_eq!(o.lo, [0.0, 0.0, 0.0]);
        let lo = low_part_f16([1e300, 0.0, 0.0], [f32::INFINITY, 0.0, 0.0]);
        assert_eq!(lo, [0, 0, 0, 0]);
    }

    proptest! {
        /// Any block-relative position (up to 10 000 km) and offset whose sum
        /// is within 100 km of the eye: one rounding of the exact f64 sum,
        /// up to the low parts' own (f16) rounding.
        #[test]
        fn one_rounding_whatever_the_block_size(
            p in prop::array::uniform3(-1.0e7f64..1.0e7),
            d in prop::array::uniform3(-1.0e5f64..1.0e5),
        ) {
            let off = [d[0] - p[0], d[1] - p[1], d[2] - p[2]];
            let (hi, _) = split_f32(p);
            let lo16 = low_part_f16(p, hi);
            let lo = low_part_f32(lo16);
            let o = SplitOffset::new(off);
            let r = camera_relative(hi, lo, o.hi, o.lo);
            for k in 0..3 {
                let exact = p[k] + off[k];
                let e = (r[k] as f64 - exact).abs();
                // f16 residual of the position: ≤ 2⁻¹¹ of half an f32 ulp of p.
                let f16_err = (p[k] - hi[k] as f64).abs() * 2f64.powi(-11) + 6e-8;
                let bound = 0.5 * f32::EPSILON as f64 * exact.abs() * 1.0001 + f16_err + 1e-9;
                prop_assert!(e <= bound, "k={} e={} bound={}", k, e, bound);
            }
        }
    }
}
