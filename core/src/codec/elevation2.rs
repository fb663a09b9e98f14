//! Error-bounded elevation with sub-unit prediction and Laplace models
//! (codec id 2, format v2's default from this version on; id 1 in
//! [`super::elevation`] stays readable).
//!
//! The quantisation is id 1's: index `q = ⌊(v + k)/s⌋` of step `s = 2k + 1`,
//! decoded as `q·s` clamped to `i16`, pointwise, so a LOD 1 sample's index is
//! the same from the source and from the parent's decoded value and the
//! builder needs no decoded parents (see [`super::elevation`]). What changes
//! is the modelling of the indices LOD 0 adds, measured on the real data's
//! residuals (docs/BENCHMARKS.md "Bytes per sample"):
//!
//! - **Prediction keeps its fraction.** Predictions are made in 1/32 of an
//!   index (pass 1, edge midpoints: the cubic `(−a + 9b + 9c − d)/16` along
//!   the odd axis, the mean of the two nearest at the border; pass 2, cell
//!   centres: the mean of the two cubics through the decoded midpoints along
//!   `i` and along `j`, the mean of the four nearest at the border, plus
//!   half the mean error of the four midpoints' own predictions). The
//!   residual is taken against the nearest index `p₀`, its sign flipped so
//!   that the prediction lies at or above `p₀`, and the fraction's distance
//!   (0, ¼ or ½ of an index) selects the model's centre: at a 1 m bound
//!   (step 3 m) half the predictions fall between two indices, which id 1's
//!   integer prediction coded as if one of them were twice as likely.
//! - **Contexts from curvature and decoded neighbours.** 12 classes, the bit
//!   length of the local curvature of the coarser samples (the cubic's
//!   `|a − b − c + d|`, or the two centre cubics' disagreement) plus the
//!   residuals already decoded next to the sample.
//! - **Laplace models.** Per record and context one scale byte `σ`, chosen by
//!   the encoder for the fewest bits, selects a discrete Laplace distribution
//!   of the residual `r` centred on the fraction, `P(r) ∝ exp(−|r − f|/θ)`,
//!   `θ = (2^(σ/8) − 0.99)/2 + 0.05`, over id 1's buckets (16 direct values,
//!   then bit lengths with uniform low bits), quantised to 12 bits.
//!
//! Raw layout: 12 scale bytes (contexts 0–11), then the rANS words (`u32`
//! little-endian, as `constriction`'s `DefaultAnsCoder` leaves them).

use super::elevation::{bucket, chunks, open, rans_encode, Quantiser, DIRECT};
use super::model::{CompactDecoder, Pow2Uniform};
use super::{unzigzag32, zigzag32, CodecError};
use crate::lod::elevation_new_samples;
use constriction::stream::model::{EncoderModel, SmallContiguousCategoricalEntropyModel};
use constriction::stream::stack::DefaultAnsCoder;
use constriction::stream::Decode;
use std::sync::OnceLock;

/// Context classes.
const CONTEXTS: usize = 12;
/// Model centres: a residual's prediction lies 0, ¼ or ½ of an index above
/// the nearest index.
const CENTRES: usize = 3;
/// Longest zig-zagged residual in bits: indices and the clamped prediction
/// both lie in the `i16` range, so `|r| < 2¹⁶`.
const MAX_LEN: usize = 17;
/// Symbols: the direct values, then bit lengths 5..=17.
const SYMBOLS: usize = DIRECT as usize + MAX_LEN - 4;
/// Fixed-point fraction of predictions (1/32 of an index).
const FRAC_BITS: u32 = 5;

/// Largest raw payload for block width `w`: the scales and at most 32 bits
/// per sample (a 12-bit bucket and 16 low bits), plus the coder's state.
pub fn max_raw_len(w: usize) -> usize {
    CONTEXTS + 4 * (elevation_new_samples(w) + 2)
}

/// Symbol probabilities of scale `σ` and centre `c` (0, ¼, ½).
fn probabilities(scale: u8, centre: usize) -> Vec<f64> {
    let theta = (2f64.powf(scale as f64 / 8.0) - 0.99) / 2.0 + 0.05;
    let f = centre as f64 / 4.0;
    let decay = (-1.0 / theta).exp();
    // Mass of the residuals r ≥ 1 from r = a to r = b − 1, and of r ≤ 0 from
    // r = −a to r = −(b − 1) (geometric sums; the zig-zag maps r ≥ 1 to the
    // odd z = 2r − 1 and r ≤ 0 to the even z = −2r).
    let pos = |a: f64, b: f64| (-(a - f) / theta).exp() * (1.0 - decay.powf(b - a)) / (1.0 - decay);
    let neg = |a: f64, b: f64| (-(a + f) / theta).exp() * (1.0 - decay.powf(b - a)) / (1.0 - decay);
    // z in [lo, hi): odd z from r = (lo+1)/2 .., even z from r = −lo/2 ...
    let mass = |lo: u64, hi: u64| {
        let (plo, phi) = (
            (lo / 2 + 1) as f64,
            (hi.div_ceil(2) + hi.is_multiple_of(2) as u64) as f64,
        );
        let (nlo, nhi) = (lo.div_ceil(2) as f64, hi.div_ceil(2) as f64);
        let p = if phi > plo { pos(plo, phi) } else { 0.0 };
        let n = if nhi > nlo { neg(nlo, nhi) } else { 0.0 };
        p + n
    };
    let p: Vec<f64> = (0..SYMBOLS)
        .map(|b| {
            let (lo, hi) = if b < DIRECT as usize {
                (b as u64, b as u64 + 1)
            } else {
                let len = (b - DIRECT as usize + 5) as u32;
                (1u64 << (len - 1), 1u64 << len)
            };
            mass(lo, hi)
        })
        .collect();
    let total: f64 = p.iter().sum();
    // Every symbol stays codable whatever the scale.
    p.iter().map(|x| (x / total).max(1e-7)).collect()
}

/// An encoder model and its cost in bits of each symbol.
type CostedModel = (SmallContiguousCategoricalEntropyModel, [f32; SYMBOLS]);

/// The encoder model of `(σ, centre)` and its costs, built on first use.
fn encoder_model(scale: u8, centre: usize) -> &'static CostedModel {
    static MODELS: [[OnceLock<CostedModel>; CENTRES]; 256] =
        [const { [const { OnceLock::new() }; CENTRES] }; 256];
    MODELS[scale as usize][centre].get_or_init(|| {
        // The encoder and decoder models are built from the same
        // probabilities by the same ("perfect") quantisation, so they agree
        // bit for bit.
        let m = SmallContiguousCategoricalEntropyModel::from_floating_point_probabilities_perfect(
            &probabilities(scale, centre),
        )
        .unwrap_or_else(|_| unreachable!("finite positive probabilities"));
        let cost = std::array::from_fn(|s| {
            let p = m
                .left_cumulative_and_probability(s)
                .map_or(1, |(_, p)| p.get());
            12.0 - (p as f32).log2()
        });
        (m, cost)
    })
}

/// The decoder model of `(σ, centre)` (a [`CompactDecoder`]), built on
/// first use from the encoder's.
fn decoder_model(scale: u8, centre: usize) -> &'static CompactDecoder<SYMBOLS> {
    static MODELS: [[OnceLock<CompactDecoder<SYMBOLS>>; CENTRES]; 256] =
        [const { [const { OnceLock::new() }; CENTRES] }; 256];
    MODELS[scale as usize][centre]
        .get_or_init(|| CompactDecoder::new(&encoder_model(scale, centre).0))
}

/// What the coder needs of one new sample's prediction.
#[derive(Clone, Copy)]
struct Pred {
    /// Nearest index to the prediction, clamped to the index range.
    p0: i32,
    /// The prediction lies below `p0`: the residual's sign is flipped.
    flip: bool,
    /// Model: `context · CENTRES + centre`.
    model: usize,
}

/// The bit length of an activity, capped to a context class.
#[inline(always)]
fn class(a: u32) -> usize {
    ((32 - a.leading_zeros()) as usize).min(CONTEXTS - 1)
}

/// Prediction from a fixed-point value `p32` (1/32 of an index) and an
/// activity.
#[inline(always)]
fn pred(p32: i32, act: u32, lo: i32, hi: i32) -> Pred {
    let half = 1 << (FRAC_BITS - 1);
    let p0 = (p32 + half) >> FRAC_BITS;
    let frac = p32 - (p0 << FRAC_BITS); // −16..=15
    let f = frac.unsigned_abs();
    let centre = (f >= 4) as usize + (f >= 12) as usize;
    Pred {
        p0: p0.clamp(lo, hi),
        flip: frac < 0,
        model: class(act) * CENTRES + centre,
    }
}

/// The cubic `−a + 9b + 9c − d` (16 times the interpolated midpoint).
#[inline(always)]
fn cubic(a: i32, b: i32, c: i32, d: i32) -> i32 {
    9 * (b + c) - a - d
}

/// The grids the walker fills: indices `q`, zig-zagged residuals `zs` (the
/// neighbours' residuals of the contexts) and the errors of the fixed-point
/// predictions `es` (which correct the cell centres').
struct Grids<'a> {
    q: &'a mut [i32],
    zs: &'a mut [u32],
    es: &'a mut [i32],
    side: usize,
    /// The index range.
    range: (i32, i32),
}

impl Grids<'_> {
    /// Code one sample: `p32` is its fixed-point prediction, `act` its
    /// activity. The index `p₀ ± unzigzag(z)` must be in the range.
    /// `KEEP`: record its residual and prediction error (a midpoint's,
    /// which the samples after it read; a cell centre's are never read).
    #[inline(always)]
    fn put<const KEEP: bool>(
        &mut self,
        code: &mut impl Sampler,
        at: usize,
        p32: i32,
        act: u32,
    ) -> Result<(), CodecError> {
        let (lo, hi) = self.range;
        let p = pred(p32, act, lo, hi);
        let z = code.sample(p, self.q[at])?;
        // |r| < 2¹⁶ for every symbol (`MAX_LEN`) and p₀ is in the i16
        // index range, so this cannot overflow.
        let r = unzigzag32(z);
        let v = if p.flip { p.p0 + r } else { p.p0 - r };
        if v < lo || v > hi {
            return Err(CodecError::Rans(format!(
                "sample {at} decodes outside the index range"
            )));
        }
        self.q[at] = v;
        if KEEP {
            self.zs[at] = z;
            self.es[at] = (v << FRAC_BITS) - p32;
        }
        Ok(())
    }

    /// An edge midpoint `(i, j)`: between LOD 1 samples along `i` on even
    /// rows, along `j` on odd rows (`ALONG_J`); `CUBIC`: three LOD 1
    /// samples on either side (else the mean of the two nearest).
    #[inline(always)]
    fn midpoint<const ALONG_J: bool, const CUBIC: bool>(
        &mut self,
        code: &mut impl Sampler,
        (i, j): (usize, usize),
    ) -> Result<(), CodecError> {
        let side = self.side;
        let (q, zs) = (&*self.q, &*self.zs);
        let at = j * side + i;
        let step = if ALONG_J { side } else { 1 };
        let (b, c) = (q[at - step], q[at + step]);
        let slope = b.abs_diff(c);
        let (p32, act) = if CUBIC {
            let (a, d) = (q[at - 3 * step], q[at + 3 * step]);
            (
                2 * cubic(a, b, c, d),
                (4 * (a - b - c + d).unsigned_abs() + slope) >> 3,
            )
        } else {
            (16 * (b + c), (3 * slope) >> 3)
        };
        // The residuals of the same kind of midpoint before it on its row
        // and two rows up.
        let near = if i >= 2 { zs[at - 2] } else { 0 } + if j >= 2 { zs[at - 2 * side] } else { 0 };
        self.put::<true>(code, at, p32, act.saturating_add(near))
    }

    /// A cell centre `(i, j)`; `CUBIC`: three samples on either side in
    /// both directions (else the mean of the four nearest).
    #[inline(always)]
    fn centre<const CUBIC: bool>(
        &mut self,
        code: &mut impl Sampler,
        (i, j): (usize, usize),
    ) -> Result<(), CodecError> {
        let side = self.side;
        let (q, zs, es) = (&*self.q, &*self.zs, &*self.es);
        let at = j * side + i;
        let (l, r, u, d) = (q[at - 1], q[at + 1], q[at - side], q[at + side]);
        let slope = l.abs_diff(r).max(u.abs_diff(d));
        let (p32, act) = if CUBIC {
            let cx = cubic(q[at - 3], l, r, q[at + 3]);
            let cy = cubic(q[at - 3 * side], u, d, q[at + 3 * side]);
            (cx + cy, (cx.abs_diff(cy) >> 5) + (slope >> 3))
        } else {
            (8 * (l + r + u + d), slope)
        };
        let near = (zs[at - 1] + zs[at + 1] + zs[at - side] + zs[at + side]) >> 1;
        // Half the mean error of the four midpoints' own predictions.
        let p32 = p32 + ((es[at - 1] + es[at + 1] + es[at - side] + es[at + side]) >> 3);
        self.put::<false>(code, at, p32, act.saturating_add(near))
    }
}

/// Walk the new samples of a `(w+1)²` index grid in coding order (pass 1,
/// edge midpoints row-major; pass 2, cell centres row-major), each
/// predicted from the indices before it. `code` gets the prediction and
/// the grid's index there (the source's when encoding) and returns the
/// zig-zagged residual. Each row's loop calls the predictor of its case
/// (along `i` or `j`; the cubic, which needs three LOD 1 samples on either
/// side, or the mean at the border), chosen once per row where the row
/// decides it (odd rows) and per sample where the column does (even rows,
/// cell centres).
fn walk(code: &mut impl Sampler, g: &mut Grids) -> Result<(), CodecError> {
    let side = g.side;
    let w = side - 1;
    // Interior: 3 ≤ t ≤ w − 3.
    let inner = |t: usize| t >= 3 && t + 3 <= w;
    for j in 0..side {
        if j.is_multiple_of(2) {
            // Odd columns: the first and last are at the border.
            for i in (1..side).step_by(2) {
                if inner(i) {
                    g.midpoint::<false, true>(code, (i, j))?;
                } else {
                    g.midpoint::<false, false>(code, (i, j))?;
                }
            }
        } else if inner(j) {
            for i in (0..side).step_by(2) {
                g.midpoint::<true, true>(code, (i, j))?;
            }
        } else {
            for i in (0..side).step_by(2) {
                g.midpoint::<true, false>(code, (i, j))?;
            }
        }
    }
    for j in (1..side).step_by(2) {
        for i in (1..side).step_by(2) {
            if inner(i) && inner(j) {
                g.centre::<true>(code, (i, j))?;
            } else {
                g.centre::<false>(code, (i, j))?;
            }
        }
    }
    Ok(())
}

/// What the walker asks of a coder for each new sample: its zig-zagged
/// residual, from the source's index `v` (encoder) or the payload
/// (decoder).
trait Sampler {
    fn sample(&mut self, p: Pred, v: i32) -> Result<u32, CodecError>;
}

/// The encoder's first pass: the residuals with their models, and the
/// symbol counts.
struct Residuals {
    syms: Vec<(u32, u8)>,
    hist: [[[u32; SYMBOLS]; CENTRES]; CONTEXTS],
}

impl Sampler for Residuals {
    #[inline(always)]
    fn sample(&mut self, p: Pred, v: i32) -> Result<u32, CodecError> {
        let r = v - p.p0;
        let z = zigzag32(if p.flip { r } else { -r });
        self.hist[p.model / CENTRES][p.model % CENTRES][bucket(z).0] += 1;
        self.syms.push((z, p.model as u8));
        Ok(z)
    }
}

/// Encode the LOD 0 samples of a full `(w+1)²` grid of source values with
/// max error `k`: the record payload.
pub fn encode(grid: &[i16], w: usize, k: u16) -> Vec<u8> {
    let side = w + 1;
    let quant = Quantiser::new(k);
    let mut q: Vec<i32> = grid.iter().map(|&v| quant.index(v)).collect();
    let (mut zs, mut es) = (vec![0u32; side * side], vec![0i32; side * side]);
    let n = elevation_new_samples(w);
    let mut res = Residuals {
        syms: Vec::with_capacity(n),
        hist: [[[0u32; SYMBOLS]; CENTRES]; CONTEXTS],
    };
    let mut g = Grids {
        q: &mut q,
        zs: &mut zs,
        es: &mut es,
        side,
        range: quant.range(),
    };
    // Source indices are in range and every residual is exact.
    walk(&mut res, &mut g).unwrap_or_else(|e| unreachable!("encoding in-range indices: {e}"));
    let scales: [u8; CONTEXTS] = std::array::from_fn(|c| best_scale(&res.hist[c]));
    let models: [&CostedModel; CONTEXTS * CENTRES] =
        std::array::from_fn(|m| encoder_model(scales[m / CENTRES], m % CENTRES));
    let words = rans_encode(&res.syms, |m| &models[m as usize].0);
    let mut out = Vec::with_capacity(CONTEXTS + 4 * words.len());
    out.extend_from_slice(&scales);
    for w in words {
        out.extend_from_slice(&w.to_le_bytes());
    }
    out
}

/// The scale of fewest bits for one context's symbol counts per centre:
/// a search around the scale of the counts' mean.
fn best_scale(hist: &[[u32; SYMBOLS]; CENTRES]) -> u8 {
    let (mut n, mut sum) = (0u64, 0f64);
    for h in hist {
        for (b, &c) in h.iter().enumerate() {
            n += c as u64;
            // A bucket's lowest value stands for its mean here.
            let lo = if b < DIRECT as usize {
                b as f64
            } else {
                (1u64 << (b - DIRECT as usize + 4)) as f64
            };
            sum += c as f64 * lo;
        }
    }
    if n == 0 {
        return 0;
    }
    let guess = (8.0 * (1.0 + sum / n as f64).log2()).round() as i32;
    let cost = |s: i32| -> f32 {
        let s = s.clamp(0, 255) as u8;
        hist.iter()
            .enumerate()
            .map(|(centre, h)| {
                let (_, bits) = encoder_model(s, centre);
                h.iter().zip(bits).map(|(&c, &b)| c as f32 * b).sum::<f32>()
            })
            .sum()
    };
    // The cost is unimodal in σ near the guess: walk downhill by steps of 1.
    let mut best = guess.clamp(0, 255);
    let mut best_cost = cost(best);
    for dir in [-1, 1] {
        let mut s = best + dir;
        while (0..=255).contains(&s) {
            let c = cost(s);
            if c >= best_cost {
                break;
            }
            (best, best_cost) = (s, c);
            s += dir;
        }
    }
    best as u8
}

/// The decoder: the rANS stack and the record's models.
struct Decoder {
    coder: DefaultAnsCoder,
    models: [&'static CompactDecoder<SYMBOLS>; CONTEXTS * CENTRES],
    uniform: [Pow2Uniform; 9],
}

impl Sampler for Decoder {
    #[inline(always)]
    fn sample(&mut self, p: Pred, _: i32) -> Result<u32, CodecError> {
        let rans = |e| CodecError::Rans(format!("{e:?}"));
        let coder = &mut self.coder;
        let b = coder.decode_symbol(self.models[p.model]).map_err(rans)?;
        if b < DIRECT as usize {
            return Ok(b as u32);
        }
        let extra = (b - DIRECT as usize + 4) as u32;
        let mut bits = 0u32;
        for (shift, width) in chunks(extra) {
            let v = coder
                .decode_symbol(self.uniform[width as usize])
                .map_err(rans)?;
            bits |= (v as u32) << shift;
        }
        Ok((1u32 << extra) | bits)
    }
}

/// Decode into a `(w+1)²` grid whose LOD 1 positions hold the parent's
/// decoded samples; every new sample ends within `k` of its source value.
pub fn decode(raw: &[u8], w: usize, k: u16, grid: &mut [i16]) -> Result<(), CodecError> {
    let side = w + 1;
    let (scales, coder) = open(raw, CONTEXTS, side, grid)?;
    let mut dec = Decoder {
        coder,
        models: std::array::from_fn(|m| decoder_model(scales[m / CENTRES], m % CENTRES)),
        uniform: std::array::from_fn(|w| Pow2Uniform::new(w as u32)),
    };
    let quant = Quantiser::new(k);
    let mut q = vec![0i32; side * side];
    for j in (0..side).step_by(2) {
        for i in (0..side).step_by(2) {
            q[j * side + i] = quant.index(grid[j * side + i]);
        }
    }
    let (mut zs, mut es) = (vec![0u32; side * side], vec![0i32; side * side]);
    let mut g = Grids {
        q: &mut q,
        zs: &mut zs,
        es: &mut es,
        side,
        range: quant.range(),
    };
    walk(&mut dec, &mut g)?;
    if !dec.coder.is_empty() {
        return Err(CodecError::Rans("words left after the last sample".into()));
    }
    for j in 0..side {
        // Even rows: the odd columns are new; odd rows: every column.
        let (first, step) = if j.is_multiple_of(2) { (1, 2) } else { (0, 1) };
        for at in (j * side + first..(j + 1) * side).step_by(step) {
            grid[at] = quant.value(q[at]);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::elevation::tests::{check_bound, max_errors, Codec};
    use super::*;
    use proptest::prelude::*;

    const ID2: Codec = (encode, decode, max_raw_len);

    #[test]
    fn probabilities_cover_every_symbol() {
        for scale in [0u8, 1, 40, 128, 255] {
            for centre in 0..CENTRES {
                let p = probabilities(scale, centre);
                assert_eq!(p.len(), SYMBOLS);
                assert!(p.iter().all(|&x| x.is_finite() && x > 0.0));
                // Normalised before the floor.
                assert!(
                    (p.iter().sum::<f64>() - 1.0).abs() < 1e-4,
                    "{scale} {centre}"
                );
            }
        }
        // The centre moves mass from 0 to +1 (z = 1): at ½ they are equal.
        let p = probabilities(24, 2);
        assert!((p[0] - p[1]).abs() < 1e-9, "{} {}", p[0], p[1]);
        let p = probabilities(24, 0);
        assert!(p[0] > p[1] && p[1] > p[2] * 0.999);
    }

    /// The residual ranges: the largest index difference still codes.
    #[test]
    fn extreme_residuals_fit_the_symbols() {
        let z = zigzag32(-65_535);
        assert!(bucket(z).0 < SYMBOLS);
        assert!(bucket(zigzag32(65_535)).0 < SYMBOLS);
    }

    proptest! {
        #[test]
        fn smooth_terrain_within_the_bound(
            seed in any::<u32>(),
            slope in -300i32..300,
            k in max_errors(),
        ) {
            // Ramps with small noise: the sub-step predictions' home.
            let samples: Vec<i16> = (0..17 * 17i32)
                .map(|p| {
                    let (i, j) = (p % 17, p / 17);
                    let h = (p as u32).wrapping_mul(2_654_435_761).wrapping_add(seed) >> 29;
                    (slope * i + 7 * j + h as i32 - 3).clamp(-32768, 32767) as i16
                })
                .collect();
            check_bound(ID2, &samples, k);
        }
    }
}
