//! Perceptual colour (codec id 2): each LOD adds only the detail its coarser
//! LOD lacks, as the thesis's interleaving does for samples (thesis §3.2;
//! the filtered colour LODs of thesis §4.4.4), quantised to a quality target.
//!
//! LOD 1 is the floor of each 2×2 cell's mean ([`crate::lod::colour_filter`]).
//! Per cell the record stores the three 2×2 Haar details (horizontal,
//! vertical, diagonal) of the texels' deviations from that mean, in the YCoCg
//! colour space (Malvar & Sullivan 2003: `Y = (R + 2G + B)/4`,
//! `Co = (R − B)/2`, `Cg = (2G − R − B)/4`), each dead-zone quantised with
//! the luma or the (coarser) chroma step. The decoder rebuilds the four
//! texels from the parent's *decoded* mean, the dequantised details and the
//! mean of the floor's remainder (`+3/8`, since the filter's floor drops
//! 0–3 quarters), rounds and clamps to `0..=255`. The Haar details are
//! orthogonal to the cell mean, so each level's quantisation error adds to
//! the coarser levels' in mean square instead of compounding.
//!
//! Steps by level: a block `h` levels above the leaves under it uses the
//! header's steps divided by `2^h`. Each level's error spreads over all the
//! finest texels under it, so errors add across levels in mean square; with
//! the steps halving per level the total is about `1 + 1/4 + 1/16 + … = 4/3`
//! of the finest level's, while the coarser levels, four times fewer texels
//! each, cost few bytes (the rate-optimal allocation of step² ∝ texels per
//! level). The header's steps come from a calibration on real imagery
//! ([`PSNR_AT_UNIT_STEP`]); a record whose own PSNR (against its source
//! given the exact LOD 1) still falls under the target plus the 4/3 margin
//! ([`LEVEL_MARGIN_DB`]), such as noise, halves its steps again until it
//! meets it (at most [`MAX_SHIFT`] halvings in all).
//!
//! Raw layout: one byte `h` (the step shift), then 9 planes of `(W/2)²`
//! zig-zagged quantisation indices (Y H, V, D, then Co, then Cg; cells
//! row-major) as one `SymbolWriter` stream, then zstd.

use super::{unzigzag32, zigzag32, CodecError, SymbolReader, SymbolWriter};
use crate::lod::Rgb;

/// Quantiser rounding offset: `q = sign(c)·⌊|c|/step + ROUNDING⌋`; under ½
/// the zero bin is wider (a dead zone), which removes noise-level details.
pub const ROUNDING: f32 = 0.38;

/// Mean of the floor's dropped remainder in a 2×2 mean, per channel.
const FLOOR_BIAS: f32 = 0.375;

/// Parameters of the Haar colour codec (written in the header).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HaarParams {
    /// Quantiser step of the luma (Y) details, 8-bit units.
    pub luma_step: f32,
    /// Quantiser step of the chroma (Co, Cg) details.
    pub chroma_step: f32,
    /// The PSNR (dB) the steps were chosen for (informative).
    pub target_psnr: f32,
}

/// PSNR (dB) of the Haar steps `luma 1`, for [`HaarParams::for_psnr`]:
/// measured at the finest level of the real data and the procedural
/// planets (docs/BENCHMARKS.md "Bytes per sample"); the PSNR of a uniform
/// quantiser falls by 20·log10 of the step's growth.
pub const PSNR_AT_UNIT_STEP: f32 = 51.0;

/// Chroma step over luma step.
pub const CHROMA_RATIO: f32 = 2.0;

impl HaarParams {
    /// Steps for a target PSNR in dB against the source.
    pub fn for_psnr(psnr: f32) -> HaarParams {
        let luma_step = 10f32
            .powf((PSNR_AT_UNIT_STEP - psnr) / 20.0)
            .clamp(0.05, 256.0);
        HaarParams {
            luma_step,
            chroma_step: luma_step * CHROMA_RATIO,
            target_psnr: psnr,
        }
    }

    /// Whether the parameters are usable (a header check).
    pub fn check(&self) -> Result<(), CodecError> {
        let step_ok = |s: f32| s.is_finite() && (0.01..=1024.0).contains(&s);
        if !step_ok(self.luma_step)
            || !step_ok(self.chroma_step)
            || !self.target_psnr.is_finite()
            || self.target_psnr < 0.0
        {
            return Err(CodecError::Codec(format!("colour parameters {self:?}")));
        }
        Ok(())
    }
}

/// Largest step shift (levels above the leaves plus refinements) a record
/// uses: steps of 1/256 of the header's, lossless in practice.
pub const MAX_SHIFT: u8 = 8;

/// A record's own PSNR must beat the target by this much (`10·log10(4/3)`):
/// the share of the coarser levels' error in the finest texels.
pub const LEVEL_MARGIN_DB: f64 = 1.25;

/// Largest raw payload for block width `w` (every symbol escaped).
pub fn max_raw_len(w: usize) -> usize {
    1 + 5 * 9 * (w / 2) * (w / 2)
}

/// The (luma, chroma, chroma) steps of a record `shift` levels above the
/// leaves.
fn steps(p: &HaarParams, shift: u8) -> [f32; 3] {
    let f = 0.5f32.powi(shift as i32);
    [p.luma_step * f, p.chroma_step * f, p.chroma_step * f]
}

#[inline]
fn quantise(c: f32, step: f32) -> i32 {
    // Truncation is the floor of this non-negative value, without a libm
    // call (5 % of a build's time).
    let q = (c.abs() / step + ROUNDING) as i32;
    if c < 0.0 {
        -q
    } else {
        q
    }
}

/// Signs of the (H, V, D) details in texels TL, TR, BL, BR.
const SIGNS: [[f32; 3]; 4] = [
    [1.0, 1.0, 1.0],
    [1.0, -1.0, -1.0],
    [-1.0, 1.0, -1.0],
    [-1.0, -1.0, 1.0],
];

/// The four texels of a cell from its mean and dequantised YCoCg details
/// `d[channel][band]`.
#[inline(always)]
fn reconstruct(m: Rgb, d: &[[f32; 3]; 3]) -> [Rgb; 4] {
    let mut out = [[0u8; 3]; 4];
    for (t, s) in SIGNS.iter().enumerate() {
        let ycc: [f32; 3] =
            std::array::from_fn(|c| s[0] * d[c][0] + s[1] * d[c][1] + s[2] * d[c][2]);
        let rgb = [
            ycc[0] + ycc[1] - ycc[2],
            ycc[0] + ycc[2],
            ycc[0] - ycc[1] - ycc[2],
        ];
        for ch in 0..3 {
            out[t][ch] = (m[ch] as f32 + FLOOR_BIAS + rgb[ch] + 0.5).clamp(0.0, 255.0) as u8;
        }
    }
    out
}

#[inline]
fn cell(full: &[Rgb], w: usize, ci: usize, cj: usize) -> [Rgb; 4] {
    [
        full[2 * cj * w + 2 * ci],
        full[2 * cj * w + 2 * ci + 1],
        full[(2 * cj + 1) * w + 2 * ci],
        full[(2 * cj + 1) * w + 2 * ci + 1],
    ]
}

/// Encode the LOD 0 of a `w²` grid against its exact filtered LOD 1. Returns
/// the raw payload and the largest channel error of the decoded texels given
/// that LOD 1.
pub fn encode(full: &[Rgb], lod1: &[Rgb], w: usize, p: &HaarParams, height: u8) -> (Vec<u8>, f32) {
    let mut shift = height.min(MAX_SHIFT);
    loop {
        let (q, err, mse) = quantise_all(full, lod1, w, &steps(p, shift));
        let good = psnr_of_mse(mse) >= p.target_psnr as f64 + LEVEL_MARGIN_DB;
        if good || shift == MAX_SHIFT {
            let mut out = SymbolWriter::with_capacity(q.len());
            for &k in &q {
                out.push(zigzag32(k));
            }
            let mut raw = vec![shift];
            raw.extend_from_slice(&out.finish());
            return (raw, err as f32);
        }
        shift += 1;
    }
}

/// The quantised details of every cell with these steps, the largest channel
/// error and the mean squared error of the decoded texels.
fn quantise_all(full: &[Rgb], lod1: &[Rgb], w: usize, steps: &[f32; 3]) -> (Vec<i32>, u8, f64) {
    let h = w / 2;
    let cells = h * h;
    let mut q = vec![0i32; 9 * cells];
    let mut err = 0u8;
    let mut se = 0u64;
    for cj in 0..h {
        for ci in 0..h {
            let c = cj * h + ci;
            let m = lod1[c];
            let x = cell(full, w, ci, cj);
            // YCoCg of each texel's deviation from the mean.
            let ycc: [[f32; 3]; 4] = std::array::from_fn(|t| {
                let e: [f32; 3] = std::array::from_fn(|ch| x[t][ch] as f32 - m[ch] as f32);
                [
                    (e[0] + 2.0 * e[1] + e[2]) / 4.0,
                    (e[0] - e[2]) / 2.0,
                    (2.0 * e[1] - e[0] - e[2]) / 4.0,
                ]
            });
            let mut d = [[0f32; 3]; 3];
            for ch in 0..3 {
                for (band, dq) in d[ch].iter_mut().enumerate() {
                    let coef = (0..4).map(|t| SIGNS[t][band] * ycc[t][ch]).sum::<f32>() / 4.0;
                    let k = quantise(coef, steps[ch]);
                    q[(3 * ch + band) * cells + c] = k;
                    *dq = k as f32 * steps[ch];
                }
            }
            let rec = reconstruct(m, &d);
            for t in 0..4 {
                for ch in 0..3 {
                    let e = rec[t][ch].abs_diff(x[t][ch]);
                    err = err.max(e);
                    se += (e as u64) * (e as u64);
                }
            }
        }
    }
    (q, err, se as f64 / (3 * w * w) as f64)
}

/// Decode a `w²` grid from the parent's decoded LOD 1 and a raw payload.
pub fn decode(raw: &[u8], lod1: &[Rgb], w: usize, p: &HaarParams) -> Result<Vec<Rgb>, CodecError> {
    let h = w / 2;
    let cells = h * h;
    if lod1.len() != cells {
        return Err(CodecError::Grid {
            got: lod1.len(),
            expected: cells,
        });
    }
    let (&shift, raw) = raw.split_first().ok_or(CodecError::Length {
        got: 0,
        expected: 1 + 9 * cells,
    })?;
    if shift > MAX_SHIFT {
        return Err(CodecError::Codec(format!("colour step shift {shift}")));
    }
    let mut rd = SymbolReader::new(raw, 9 * cells)?;
    let mut q = vec![0i32; 9 * cells];
    for v in q.iter_mut() {
        *v = unzigzag32(rd.next()?);
    }
    rd.finish()?;
    let steps = steps(p, shift);
    let mut full = vec![[0u8; 3]; w * w];
    for cj in 0..h {
        for ci in 0..h {
            let c = cj * h + ci;
            let d: [[f32; 3]; 3] = std::array::from_fn(|ch| {
                std::array::from_fn(|band| q[(3 * ch + band) * cells + c] as f32 * steps[ch])
            });
            let rec = reconstruct(lod1[c], &d);
            full[2 * cj * w + 2 * ci] = rec[0];
            full[2 * cj * w + 2 * ci + 1] = rec[1];
            full[(2 * cj + 1) * w + 2 * ci] = rec[2];
            full[(2 * cj + 1) * w + 2 * ci + 1] = rec[3];
        }
    }
    Ok(full)
}

/// PSNR in dB of `a` against `b` (8-bit channels); infinite when equal.
pub fn psnr(a: &[Rgb], b: &[Rgb]) -> f64 {
    let se: f64 = a
        .iter()
        .zip(b)
        .flat_map(|(x, y)| (0..3).map(move |ch| (x[ch] as f64 - y[ch] as f64).powi(2)))
        .sum();
    psnr_of_mse(se / (3 * a.len().max(1)) as f64)
}

/// PSNR in dB of a mean squared error of 8-bit channels.
pub fn psnr_of_mse(mse: f64) -> f64 {
    10.0 * (255.0f64 * 255.0 / mse).log10()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::colour_filter;
    use proptest::prelude::*;

    /// A smooth-ish tile with noise: a random gradient, a random edge and
    /// per-texel noise of a random amplitude.
    fn tile(w: usize, seed: [u8; 8], noise: u8) -> Vec<Rgb> {
        let mut state = u64::from_le_bytes(seed) | 1;
        let mut rnd = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let base: [f32; 3] = std::array::from_fn(|_| (rnd() % 200) as f32 + 20.0);
        let grad: [f32; 3] = std::array::from_fn(|_| (rnd() % 100) as f32 / 50.0 - 1.0);
        let edge = (rnd() % w as u64) as usize;
        (0..w * w)
            .map(|p| {
                let (i, j) = (p % w, p / w);
                std::array::from_fn(|ch| {
                    let n = if noise > 0 {
                        (rnd() % (2 * noise as u64 + 1)) as f32 - noise as f32
                    } else {
                        0.0
                    };
                    let e = if i > edge { 30.0 } else { 0.0 };
                    (base[ch] + grad[ch] * (i + j) as f32 + e + n).clamp(0.0, 255.0) as u8
                })
            })
            .collect()
    }

    proptest! {
        #[test]
        fn one_level_meets_the_target(seed in any::<[u8; 8]>(), noise in 0u8..12, target in 36f32..50.0) {
            let w = 32;
            let full = tile(w, seed, noise);
            let lod1 = colour_filter(&full, w);
            let p = HaarParams::for_psnr(target);
            let (raw, err) = encode(&full, &lod1, w, &p, 0);
            let dec = decode(&raw, &lod1, w, &p).unwrap();
            let got = psnr(&dec, &full);
            prop_assert!(got >= target as f64, "psnr {} < {}", got, target);
            let max = dec.iter().zip(&full).flat_map(|(a, b)| (0..3).map(move |c| a[c].abs_diff(b[c]))).max().unwrap();
            prop_assert_eq!(max as f32, err);
        }

        #[test]
        fn hostile_payloads_are_typed_errors(raw in proptest::collection::vec(any::<u8>(), 0..2000)) {
            let p = HaarParams::for_psnr(42.0);
            let _ = decode(&raw, &[[9u8; 3]; 64], 16, &p);
        }
    }

    #[test]
    fn truncated_payloads_are_errors() {
        let w = 16;
        let full = tile(w, [3; 8], 40);
        let lod1 = colour_filter(&full, w);
        let p = HaarParams::for_psnr(60.0);
        let (raw, _) = encode(&full, &lod1, w, &p, 2);
        assert!(decode(&raw, &lod1, w, &p).is_ok());
        for cut in [0, 1, raw.len() / 2, raw.len() - 1] {
            assert!(decode(&raw[..cut], &lod1, w, &p).is_err(), "cut {cut}");
        }
        assert!(decode(&raw, &lod1[1..], w, &p).is_err());
    }

    #[test]
    fn params_check() {
        assert!(HaarParams::for_psnr(42.0).check().is_ok());
        let bad = HaarParams {
            luma_step: f32::NAN,
            chroma_step: 1.0,
            target_psnr: 42.0,
        };
        assert!(bad.check().is_err());
    }
}
