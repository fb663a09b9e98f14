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
//!
//! The coder (encoder and decoder alike) holds the grid's indices in four
//! planes (`Planes`: LOD 1, the two kinds of edge midpoint, the cell
//! centres) and computes each plane's predictions in loops of their own
//! before its samples are coded, so that only the loop over the rANS coder
//! is sequential; the payloads are byte for byte those of the grid walk
//! this replaced (`payloads_match_the_released_format`).

use super::elevation::{bucket, open, rans_encode, Quantiser, DIRECT};
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
    /// Context class, `0..CONTEXTS`.
    class: usize,
    /// Model centre, `0..CENTRES`.
    centre: usize,
}

/// The bit length of an activity, capped to a context class.
#[inline(always)]
fn class(a: u32) -> usize {
    ((32 - a.leading_zeros()) as usize).min(CONTEXTS - 1)
}

/// How the planes hold a grid and what a residual means: id 2 codes the
/// indices of a fixed grid ([`Fixed`]), id 3 values quantised in the loop
/// ([`InLoop`]). Everything else of the two codecs is one code.
pub(super) trait Quant: Copy {
    /// A source (or parent-decoded) value in plane units.
    fn unit(&self, v: i16) -> i32;
    /// One quantisation step in plane units (the models' centres measure a
    /// prediction's fraction in steps).
    fn step(&self) -> i32;
    /// An activity in plane units, in steps.
    fn act(&self, a: u32) -> u32;
    /// Encoder: the residual, in steps, of source value `v` (plane units)
    /// against the nearest prediction `p0`.
    fn residual(&self, v: i32, p0: i32) -> i32;
    /// Decoder (and encoder, for the planes): the plane value of residual
    /// `d` (`|d| < 2¹⁶`) against `p0`, or `None` where no source value
    /// decodes there.
    fn sample(&self, p0: i32, d: i32) -> Option<i32>;
    /// The stored value of a decoded plane value.
    fn stored(&self, x: i32) -> i16;
    /// The range of plane values.
    fn range(&self) -> (i32, i32);
}

/// Id 2: planes of quantisation indices `⌊(v + k)/s⌋`, pointwise, so a
/// LOD 1 index is the same from the source and from the parent's decoded
/// value.
#[derive(Clone, Copy)]
pub(super) struct Fixed {
    q: Quantiser,
    /// `q.range()`, which the coder's loop reads per sample.
    range: (i32, i32),
}

impl Fixed {
    pub(super) fn new(k: u16) -> Fixed {
        let q = Quantiser::new(k);
        Fixed {
            q,
            range: q.range(),
        }
    }
}

impl Quant for Fixed {
    #[inline(always)]
    fn unit(&self, v: i16) -> i32 {
        self.q.index(v)
    }
    #[inline(always)]
    fn step(&self) -> i32 {
        1
    }
    #[inline(always)]
    fn act(&self, a: u32) -> u32 {
        a
    }
    #[inline(always)]
    fn residual(&self, v: i32, p0: i32) -> i32 {
        v - p0
    }
    #[inline(always)]
    fn sample(&self, p0: i32, d: i32) -> Option<i32> {
        // |d| < 2¹⁶ and p₀ is in the i16 index range: no overflow.
        let v = p0 + d;
        let (lo, hi) = self.range;
        // `lo ≤ v ≤ hi` in one comparison.
        ((v - lo) as u32 <= (hi - lo) as u32).then_some(v)
    }
    #[inline(always)]
    fn stored(&self, x: i32) -> i16 {
        self.q.value(x)
    }
    fn range(&self) -> (i32, i32) {
        self.range
    }
}

/// Id 3: planes of stored values; a new sample's residual is quantised
/// against its own prediction, `d = ⌊(v − p₀ + k)/s⌋`, decoded as
/// `p₀ + d·s` clamped to `i16` (within `k` of `v`), so the cells are
/// centred on the prediction (id 2's fixed cells put half of the
/// predictions at a 1 m bound between two cells). The predictions read
/// decoded values, the parent's included: the encoder needs the parent's
/// decoded samples at LOD 1. At `k = 0` its payloads are id 2's.
#[derive(Clone, Copy)]
pub(super) struct InLoop {
    k: i32,
    s: i32,
    /// `⌈2¹⁶/s⌉`: activities in steps.
    inverse: u32,
    /// `⌈2¹⁶/s⌉·s`, which keeps the encoder's dividend positive.
    offset: i32,
    /// `⌊2⁴⁰/s⌋ + 1`: the encoder's division as a product.
    divisor: u64,
}

impl InLoop {
    pub(super) fn new(k: u16) -> InLoop {
        let s = 2 * k as i32 + 1;
        let inverse = (1u32 << 16).div_ceil(s as u32);
        InLoop {
            k: k as i32,
            s,
            inverse,
            offset: inverse as i32 * s,
            divisor: (1u64 << 40) / s as u64 + 1,
        }
    }
}

impl Quant for InLoop {
    #[inline(always)]
    fn unit(&self, v: i16) -> i32 {
        v as i32
    }
    #[inline(always)]
    fn step(&self) -> i32 {
        self.s
    }
    #[inline(always)]
    fn act(&self, a: u32) -> u32 {
        ((a as u64 * self.inverse as u64) >> 16) as u32
    }
    #[inline(always)]
    fn residual(&self, v: i32, p0: i32) -> i32 {
        // `⌊(v − p₀ + k)/s⌋` with n = v − p₀ + k + offset in [0, 2¹⁸): the
        // product exceeds n/s by less than 2¹⁸/2⁴⁰, less than the 1/s ≥
        // 2⁻¹⁵ by which a non-integer n/s falls short of the next integer.
        let n = (v - p0 + self.k + self.offset) as u64;
        ((n * self.divisor) >> 40) as i32 - self.inverse as i32
    }
    #[inline(always)]
    fn sample(&self, p0: i32, d: i32) -> Option<i32> {
        // |d| < 2¹⁶, s < 2¹⁵, |p₀| ≤ 2¹⁵: |p₀ + d·s| < 2³¹. A source value
        // decodes within k of itself, so within k of the i16 range.
        let v = p0 + d * self.s;
        let (lo, hi) = (i16::MIN as i32 - self.k, i16::MAX as i32 + self.k);
        ((v - lo) as u32 <= (hi - lo) as u32).then(|| v.clamp(i16::MIN as i32, i16::MAX as i32))
    }
    #[inline(always)]
    fn stored(&self, x: i32) -> i16 {
        x as i16
    }
    fn range(&self) -> (i32, i32) {
        (i16::MIN as i32, i16::MAX as i32)
    }
}

/// The cubic `−a + 9b + 9c − d` (16 times the interpolated midpoint).
#[inline(always)]
fn cubic(a: i32, b: i32, c: i32, d: i32) -> i32 {
    9 * (b + c) - a - d
}

/// A midpoint's fixed-point prediction and activity between `b` and `c`:
/// `Some((a, d))`, the LOD 1 samples beyond them, for the cubic, else the
/// mean of the two.
#[inline(always)]
fn midpoint(q: &impl Quant, b: i32, c: i32, far: Option<(i32, i32)>) -> (i32, u32) {
    let slope = b.abs_diff(c);
    let (p32, act) = match far {
        Some((a, d)) => (
            2 * cubic(a, b, c, d),
            (4 * (a - b - c + d).unsigned_abs() + slope) >> 3,
        ),
        None => (16 * (b + c), (3 * slope) >> 3),
    };
    (p32, q.act(act))
}

/// A cell centre's fixed-point prediction and activity from the four
/// midpoints around it `[l, r, u, d]`, their residuals' term `near` and
/// their prediction errors' `err`: `Some([l′, r′, u′, d′])`, the midpoints
/// beyond them, for the two cubics, else the mean of the four.
#[inline(always)]
fn centre(
    q: &impl Quant,
    [l, r, u, d]: [i32; 4],
    near: u32,
    err: i32,
    far: Option<[i32; 4]>,
) -> (i32, u32) {
    let slope = l.abs_diff(r).max(u.abs_diff(d));
    let (p32, act) = match far {
        Some([l2, r2, u2, d2]) => {
            let (cx, cy) = (cubic(l2, l, r, r2), cubic(u2, u, d, d2));
            (cx + cy, (cx.abs_diff(cy) >> 5) + (slope >> 3))
        }
        None => (8 * (l + r + u + d), slope),
    };
    (p32 + err, q.act(act).saturating_add(near))
}

/// The predictions of one plane's samples (below), computed before the
/// plane is coded, in arrays so that the loops vectorise: everything the
/// coder needs of a prediction but, for the midpoints, the part of the
/// activity that comes from the residuals coded just before.
#[derive(Default)]
struct Preds {
    /// Nearest index, clamped to the index range.
    p0: Vec<i32>,
    /// The fixed-point prediction (1/32 of an index).
    p32: Vec<i32>,
    /// Activity.
    act: Vec<u32>,
    /// `centre · 2 + flip`: the prediction lies 0, ¼ or ½ of an index
    /// from `p0` (the model's centre), below it (`flip`: the residual's
    /// sign is flipped).
    meta: Vec<u32>,
}

impl Preds {
    /// Room for `n` predictions (the values are written before they are
    /// read).
    fn resize(&mut self, n: usize) {
        self.p0.resize(n, 0);
        self.p32.resize(n, 0);
        self.act.resize(n, 0);
        self.meta.resize(n, 0);
    }

    /// Nearest indices, centres and flips of the predictions `p32`.
    fn finish(&mut self, q: &impl Quant) {
        let ((lo, hi), step) = (q.range(), q.step());
        let half = 1 << (FRAC_BITS - 1);
        for ((p0, meta), &p32) in self.p0.iter_mut().zip(&mut self.meta).zip(&self.p32) {
            let p = (p32 + half) >> FRAC_BITS;
            let frac = p32 - (p << FRAC_BITS); // −16..=15
            let f = frac.unsigned_abs();
            let centre = (f >= 4 * step as u32) as u32 + (f >= 12 * step as u32) as u32;
            *p0 = p.clamp(lo, hi);
            *meta = centre << 1 | (frac < 0) as u32;
        }
    }
}

/// The indices of a `(2h+1)²` grid in four planes, row-major, `(i, j)` the
/// grid's column and row: LOD 1 `l` (both even, `(h+1)²`), the edge
/// midpoints between LOD 1 samples along `i` (`mh`: `j` even, `i` odd,
/// `h+1` rows of `h`) and along `j` (`mv`: `j` odd, `i` even, `h` rows of
/// `h+1`), and the cell centres `c` (both odd, `h²`); with the midpoints'
/// zig-zagged residuals `z*` (the contexts of the samples after them) and
/// the errors `e*` of their fixed-point predictions (which correct the
/// centres'). The planes turn every neighbour the predictions read into a
/// contiguous slice.
#[derive(Default)]
struct Planes {
    h: usize,
    l: Vec<i32>,
    mh: Vec<i32>,
    mv: Vec<i32>,
    c: Vec<i32>,
    zh: Vec<u32>,
    zv: Vec<u32>,
    eh: Vec<i32>,
    ev: Vec<i32>,
}

/// Fill `out` with a plane of a `side²` grid's indices: the samples with
/// `i ≡ i0`, `j ≡ j0` (mod 2).
fn plane(out: &mut Vec<i32>, grid: &[i16], side: usize, (i0, j0): (usize, usize), q: &impl Quant) {
    out.clear();
    for row in grid.chunks_exact(side).skip(j0).step_by(2) {
        out.extend(row[i0..].iter().step_by(2).map(|&v| q.unit(v)));
    }
}

impl Planes {
    /// Fill the planes with a grid's indices: all four (`new`: the
    /// encoder's source), or LOD 1 (the others are written before they are
    /// read). Buffers keep their allocation from record to record.
    fn fill(&mut self, grid: &[i16], side: usize, quant: &impl Quant, new: bool) {
        let h = side / 2;
        self.h = h;
        plane(&mut self.l, grid, side, (0, 0), quant);
        if new {
            plane(&mut self.mh, grid, side, (1, 0), quant);
            plane(&mut self.mv, grid, side, (0, 1), quant);
            plane(&mut self.c, grid, side, (1, 1), quant);
        } else {
            self.mh.resize((h + 1) * h, 0);
            self.mv.resize(h * (h + 1), 0);
            self.c.resize(h * h, 0);
        }
        self.zh.resize((h + 1) * h, 0);
        self.zv.resize(h * (h + 1), 0);
        self.eh.resize((h + 1) * h, 0);
        self.ev.resize(h * (h + 1), 0);
    }

    /// Predictions of the midpoints along `i`, from LOD 1: the cubic
    /// through three LOD 1 samples on either side (grid `3 ≤ i ≤ w − 3`,
    /// here `1 ≤ x ≤ h − 2`), else the mean of the two nearest.
    fn predict_mh(&self, q: &impl Quant, p: &mut Preds) {
        let h = self.h;
        for (y, l) in self.l.chunks_exact(h + 1).enumerate() {
            let (p32, act) = (&mut p.p32[y * h..][..h], &mut p.act[y * h..][..h]);
            for x in 0..h {
                // Border samples here; the interior is overwritten below.
                (p32[x], act[x]) = midpoint(q, l[x], l[x + 1], None);
            }
            if h >= 3 {
                let n = h - 2;
                let (a, b, c, d) = (&l[..n], &l[1..][..n], &l[2..][..n], &l[3..][..n]);
                for (k, (p, s)) in p32[1..=n].iter_mut().zip(&mut act[1..=n]).enumerate() {
                    (*p, *s) = midpoint(q, b[k], c[k], Some((a[k], d[k])));
                }
            }
        }
        p.finish(q);
    }

    /// Predictions of the midpoints along `j`: the same down the columns
    /// of LOD 1 (the cubic for `1 ≤ y ≤ h − 2`).
    fn predict_mv(&self, q: &impl Quant, p: &mut Preds) {
        let h = self.h;
        let row = |y: usize| &self.l[y * (h + 1)..][..h + 1];
        for y in 0..h {
            let (b, c) = (row(y), row(y + 1));
            let (p32, act) = (
                &mut p.p32[y * (h + 1)..][..h + 1],
                &mut p.act[y * (h + 1)..][..h + 1],
            );
            if y >= 1 && y + 2 <= h {
                let (a, d) = (row(y - 1), row(y + 2));
                for x in 0..h + 1 {
                    (p32[x], act[x]) = midpoint(q, b[x], c[x], Some((a[x], d[x])));
                }
            } else {
                for x in 0..h + 1 {
                    (p32[x], act[x]) = midpoint(q, b[x], c[x], None);
                }
            }
        }
        p.finish(q);
    }

    /// Predictions of the cell centres from the decoded midpoints: the
    /// mean of the two cubics along `i` and `j` where three samples lie on
    /// either side in both directions (`1 ≤ x, y ≤ h − 2`), else the mean
    /// of the four nearest; plus half the mean error of the four
    /// midpoints' own predictions. The activity includes half the four
    /// midpoints' residuals.
    fn predict_c(&self, q: &impl Quant, p: &mut Preds) {
        let h = self.h;
        let mh = |y: usize| &self.mh[y * h..][..h];
        let mv = |y: usize| &self.mv[y * (h + 1)..][..h + 1];
        for y in 0..h {
            // Left and right: mv row y; up and down: mh rows y and y + 1.
            let (lr, up, dn) = (mv(y), mh(y), mh(y + 1));
            let (zlr, zup, zdn) = (
                &self.zv[y * (h + 1)..][..h + 1],
                &self.zh[y * h..][..h],
                &self.zh[(y + 1) * h..][..h],
            );
            let (elr, eup, edn) = (
                &self.ev[y * (h + 1)..][..h + 1],
                &self.eh[y * h..][..h],
                &self.eh[(y + 1) * h..][..h],
            );
            let (p32, act) = (&mut p.p32[y * h..][..h], &mut p.act[y * h..][..h]);
            // Half the four midpoints' residuals, an eighth of their
            // prediction errors.
            let (zl, zr, zu, zd) = (&zlr[..h], &zlr[1..][..h], &zup[..h], &zdn[..h]);
            let (el, er, eu, ed) = (&elr[..h], &elr[1..][..h], &eup[..h], &edn[..h]);
            for x in 0..h {
                act[x] = (zl[x] + zr[x] + zu[x] + zd[x]) >> 1;
                p32[x] = (el[x] + er[x] + eu[x] + ed[x]) >> 3;
            }
            let (l, r, u, d) = (&lr[..h], &lr[1..][..h], &up[..h], &dn[..h]);
            let mean = |x: usize, (p32, act): (&mut i32, &mut u32)| {
                (*p32, *act) = centre(q, [l[x], r[x], u[x], d[x]], *act, *p32, None);
            };
            if h >= 3 && y >= 1 && y + 2 <= h {
                // The cubics for x in 1..=h − 2, the means at the border.
                let n = h - 2;
                let (fu, fd) = (&mh(y - 1)[1..][..n], &mh(y + 2)[1..][..n]);
                let (ll, rr) = (&lr[..n], &lr[3..][..n]);
                let (li, ri, ui, di) = (&l[1..][..n], &r[1..][..n], &u[1..][..n], &d[1..][..n]);
                let (pi, ai) = (&mut p32[1..][..n], &mut act[1..][..n]);
                for k in 0..n {
                    let far = Some([ll[k], rr[k], fu[k], fd[k]]);
                    (pi[k], ai[k]) = centre(q, [li[k], ri[k], ui[k], di[k]], ai[k], pi[k], far);
                }
                for x in [0, h - 1] {
                    mean(x, (&mut p32[x], &mut act[x]));
                }
            } else {
                for (x, pa) in p32.iter_mut().zip(act.iter_mut()).enumerate() {
                    mean(x, pa);
                }
            }
        }
        p.finish(q);
    }
}

/// Code one sample of prediction `(p0, meta)` and context class `c`:
/// its plane value (checked by [`Quant::sample`]) and zig-zagged
/// residual. `v`: the source's plane value (encoder).
#[inline(always)]
fn put(
    code: &mut impl Sampler,
    quant: &impl Quant,
    p0: i32,
    meta: u32,
    c: usize,
    v: i32,
) -> Result<(i32, u32), CodecError> {
    let flip = meta & 1 != 0;
    let p = Pred {
        class: c,
        centre: (meta >> 1) as usize,
    };
    let z = code.sample(p, || {
        let d = quant.residual(v, p0);
        zigzag32(if flip { d } else { -d })
    })?;
    // |r| < 2¹⁶ for every symbol (`MAX_LEN`).
    let r = unzigzag32(z);
    let v = quant
        .sample(p0, if flip { r } else { -r })
        .ok_or_else(|| CodecError::Rans("a sample decodes outside the index range".into()))?;
    Ok((v, z))
}

/// Code one row of midpoints (`n` of them from `at` in the plane and its
/// predictions): the activity gains the residuals of the midpoint two rows
/// up (the plane's row before, none for the first row) and of the one
/// before it on its row.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn midpoint_row(
    code: &mut impl Sampler,
    p: &mut Preds,
    quant: &impl Quant,
    (at, n): (usize, usize),
    q: &mut [i32],
    zs: &mut [u32],
    es: &mut [i32],
) -> Result<(), CodecError> {
    let (done, rest) = zs.split_at_mut(at);
    let act = &mut p.act[at..][..n];
    if at >= n {
        for (a, &z) in act.iter_mut().zip(&done[at - n..]) {
            *a = a.saturating_add(z);
        }
    }
    let (q, zs, es) = (&mut q[at..][..n], &mut rest[..n], &mut es[at..][..n]);
    let (p0, p32, meta) = (&p.p0[at..][..n], &p.p32[at..][..n], &p.meta[at..][..n]);
    let mut prev = 0u32;
    let pre = p0.iter().zip(meta).zip(act.iter()).zip(p32);
    for (((q, zs), es), (((&p0, &meta), &act), &p32)) in q.iter_mut().zip(zs).zip(es).zip(pre) {
        // act < 2²⁰ and prev < 2¹⁷: no overflow.
        let (v, z) = put(code, quant, p0, meta, class(act + prev), *q)?;
        *q = v;
        *zs = z;
        *es = (v << FRAC_BITS) - p32;
        prev = z;
    }
    Ok(())
}

/// A coding's buffers: the planes and the predictions of the midpoints
/// along `i` (then of the centres) and along `j`, kept per thread from
/// record to record ([`with_scratch`]).
#[derive(Default)]
struct Scratch {
    planes: Planes,
    ph: Preds,
    pv: Preds,
    /// The decoder's rANS words.
    words: Vec<u32>,
}

/// Widest block whose buffers a thread keeps (about 1 MB at 256); a
/// wider one (the format allows 4096) gets buffers of its own, freed after.
const SCRATCH_MAX_WIDTH: usize = 256;

/// Run `f` with this thread's [`Scratch`] (blocks of width `w` up to
/// [`SCRATCH_MAX_WIDTH`]) or a fresh one.
fn with_scratch<T>(w: usize, f: impl FnOnce(&mut Scratch) -> T) -> T {
    thread_local! {
        static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::default();
    }
    if w > SCRATCH_MAX_WIDTH {
        return f(&mut Scratch::default());
    }
    SCRATCH.with_borrow_mut(f)
}

/// Code the new samples of the planes in the format's order (pass 1, the
/// edge midpoints row-major over the grid: a row of `mh`, then a row of
/// `mv`; pass 2, the cell centres row-major), each predicted from the
/// indices before it. `code` gets the prediction and the planes' index
/// there (the source's when encoding) and returns the zig-zagged residual.
/// Each plane's predictions are computed in loops of their own before the
/// samples are coded: only the coder's loop is sequential.
fn walk(code: &mut impl Sampler, quant: &impl Quant, s: &mut Scratch) -> Result<(), CodecError> {
    let Scratch {
        planes: g, ph, pv, ..
    } = s;
    let h = g.h;
    ph.resize((h + 1) * h);
    pv.resize(h * (h + 1));
    g.predict_mh(quant, ph);
    g.predict_mv(quant, pv);
    for y in 0..=h {
        midpoint_row(code, ph, quant, (y * h, h), &mut g.mh, &mut g.zh, &mut g.eh)?;
        if y < h {
            let at = y * (h + 1);
            midpoint_row(
                code,
                pv,
                quant,
                (at, h + 1),
                &mut g.mv,
                &mut g.zv,
                &mut g.ev,
            )?;
        }
    }
    // The centres' predictions in the midpoints' buffer.
    let pc = ph;
    pc.resize(h * h);
    g.predict_c(quant, pc);
    let pre = pc.p0.iter().zip(&pc.meta).zip(&pc.act);
    for (q, ((&p0, &meta), &act)) in g.c.iter_mut().zip(pre) {
        (*q, _) = put(code, quant, p0, meta, class(act), *q)?;
    }
    Ok(())
}

/// What the walker asks of a coder for each new sample: its zig-zagged
/// residual, from the source (`z`, which only the encoder calls) or the
/// payload (decoder).
trait Sampler {
    fn sample(&mut self, p: Pred, z: impl FnOnce() -> u32) -> Result<u32, CodecError>;
}

/// The encoder's first pass: the residuals with their models, and the
/// symbol counts.
struct Residuals {
    syms: Vec<(u32, u8)>,
    hist: [[[u32; SYMBOLS]; CENTRES]; CONTEXTS],
}

impl Sampler for Residuals {
    #[inline(always)]
    fn sample(&mut self, p: Pred, z: impl FnOnce() -> u32) -> Result<u32, CodecError> {
        let z = z();
        self.hist[p.class][p.centre][bucket(z).0] += 1;
        self.syms.push((z, (p.class * CENTRES + p.centre) as u8));
        Ok(z)
    }
}

/// Encode the LOD 0 samples of a full `(w+1)²` grid of source values with
/// max error `k`: the record payload (id 2).
pub fn encode(grid: &[i16], w: usize, k: u16) -> Vec<u8> {
    encode_with(grid, w, Fixed::new(k))
}

/// Id 3's payload of a full `(w+1)²` grid whose LOD 1 positions hold the
/// parent's decoded samples (the root's: its exact first LOD) and the
/// others the source values, with max error `k`.
pub fn encode_in_loop(grid: &[i16], w: usize, k: u16) -> Vec<u8> {
    // At k = 0 both are the identity on the samples: id 2's code skips
    // id 3's scaling and products (`in_loop_at_zero_is_id_2`).
    if k == 0 {
        return encode(grid, w, 0);
    }
    encode_with(grid, w, InLoop::new(k))
}

fn encode_with(grid: &[i16], w: usize, quant: impl Quant) -> Vec<u8> {
    let mut res = Residuals {
        syms: Vec::with_capacity(elevation_new_samples(w)),
        hist: [[[0u32; SYMBOLS]; CENTRES]; CONTEXTS],
    };
    with_scratch(w, |s| {
        s.planes.fill(grid, w + 1, &quant, true);
        // Source values are in range and decode within k of themselves.
        walk(&mut res, &quant, s).unwrap_or_else(|e| unreachable!("encoding in-range values: {e}"));
    });
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

/// The decoder: the rANS stack and the record's models, per context class
/// and centre (a fourth centre, never used, repeats the third, so that a
/// centre masked to two bits needs no bounds check).
struct Decoder {
    coder: DefaultAnsCoder,
    models: [[&'static CompactDecoder<SYMBOLS>; 4]; CONTEXTS],
    uniform: [Pow2Uniform; 9],
}

impl Sampler for Decoder {
    #[inline(always)]
    fn sample(&mut self, p: Pred, _: impl FnOnce() -> u32) -> Result<u32, CodecError> {
        let rans = |e| CodecError::Rans(format!("{e:?}"));
        let coder = &mut self.coder;
        let model = self.models[p.class][p.centre & 3];
        let b = coder.decode_symbol(model).map_err(rans)?;
        if b < DIRECT as usize {
            return Ok(b as u32);
        }
        // The low bits in `chunks(extra)`'s order, unrolled: `extra ≤ 16`
        // (`MAX_LEN`), so one chunk of `extra` bits, or 8 and `extra − 8`.
        let extra = (b - DIRECT as usize + 4) as u32;
        let low = extra.min(8);
        let mut bits = coder
            .decode_symbol(self.uniform[low as usize])
            .map_err(rans)? as u32;
        if extra > 8 {
            let high = coder
                .decode_symbol(self.uniform[(extra - 8) as usize])
                .map_err(rans)?;
            bits |= (high as u32) << 8;
        }
        Ok((1u32 << extra) | bits)
    }
}

/// Decode into a `(w+1)²` grid whose LOD 1 positions hold the parent's
/// decoded samples; every new sample ends within `k` of its source value.
pub fn decode(raw: &[u8], w: usize, k: u16, grid: &mut [i16]) -> Result<(), CodecError> {
    decode_with(raw, w, Fixed::new(k), grid)
}

/// Decode id 3's payload into a `(w+1)²` grid whose LOD 1 positions hold
/// the parent's decoded samples.
pub fn decode_in_loop(raw: &[u8], w: usize, k: u16, grid: &mut [i16]) -> Result<(), CodecError> {
    if k == 0 {
        return decode(raw, w, 0, grid);
    }
    decode_with(raw, w, InLoop::new(k), grid)
}

fn decode_with(
    raw: &[u8],
    w: usize,
    quant: impl Quant,
    grid: &mut [i16],
) -> Result<(), CodecError> {
    let side = w + 1;
    with_scratch(w, |s| {
        let (scales, coder) = open(raw, CONTEXTS, side, grid, std::mem::take(&mut s.words))?;
        let mut dec = Decoder {
            coder,
            models: std::array::from_fn(|c| {
                std::array::from_fn(|m| decoder_model(scales[c], m.min(CENTRES - 1)))
            }),
            uniform: std::array::from_fn(|w| Pow2Uniform::new(w as u32)),
        };
        s.planes.fill(grid, side, &quant, false);
        walk(&mut dec, &quant, s)?;
        if !dec.coder.is_empty() {
            return Err(CodecError::Rans("words left after the last sample".into()));
        }
        // The words' buffer, emptied, for the next record.
        s.words = dec.coder.into_raw_parts().0;
        // The new samples into the grid (every index is in the range: the
        // coder checked each): on even rows the midpoints along `i` between
        // the LOD 1 samples, odd rows whole, midpoints along `j` and centres
        // in turn.
        let g = &s.planes;
        let h = g.h;
        let value = |q: i32| quant.stored(q);
        for (j, row) in grid.chunks_exact_mut(side).enumerate() {
            let y = j / 2;
            if j.is_multiple_of(2) {
                for (x, &q) in g.mh[y * h..][..h].iter().enumerate() {
                    row[2 * x + 1] = value(q);
                }
            } else {
                let (mv, c) = (&g.mv[y * (h + 1)..][..h + 1], &g.c[y * h..][..h]);
                for ((pair, &a), &b) in row.chunks_exact_mut(2).zip(mv).zip(c) {
                    pair[0] = value(a);
                    pair[1] = value(b);
                }
                row[2 * h] = value(mv[h]);
            }
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::super::elevation::tests::{check_bound, max_errors, Codec};
    use super::*;
    use proptest::prelude::*;

    const ID2: Codec = (encode, decode, max_raw_len);

    /// CRC-32s of `payloads_match_the_released_format`'s payloads, widths
    /// 2, 4, 6, 8, 10, 16, 64 times max errors 0, 1, 7.
    const GOLDEN: [u32; 21] = [
        715772039, 2279218242, 3843189919, 3638387324, 3457991370, 313209893, 3887974277,
        2903500475, 3129170279, 453218759, 3932071727, 2611868173, 1919786406, 2066051690,
        1737728117, 435373094, 24316351, 3954251191, 2203149408, 3279711588, 573736350,
    ];

    /// Terrain for the format test: a ramp with a ridge, noise and (for
    /// the larger widths) a cliff, from a seeded generator.
    fn terrain(side: usize, seed: u32) -> Vec<i16> {
        let mut x = seed;
        (0..side * side)
            .map(|p| {
                x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                let (i, j) = ((p % side) as i32, (p / side) as i32);
                let ridge = 40 * (i - j).abs();
                let cliff = if side > 9 && i > side as i32 / 2 {
                    900
                } else {
                    0
                };
                (13 * i - 7 * j + ridge + cliff + (x >> 27) as i32 - 16) as i16
            })
            .collect()
    }

    /// The payload of a `(w+1)²` grid, checked to decode from its LOD 1
    /// (quantised as a parent's decoded samples are) within `k` of it.
    fn encode_checked(samples: &[i16], w: usize, k: u16) -> Vec<u8> {
        let side = w + 1;
        let payload = encode(samples, w, k);
        let quant = Quantiser::new(k);
        let mut grid = vec![0i16; side * side];
        for j in (0..side).step_by(2) {
            for i in (0..side).step_by(2) {
                grid[j * side + i] = quant.value(quant.index(samples[j * side + i]));
            }
        }
        decode(&payload, w, k, &mut grid).unwrap();
        for (a, b) in grid.iter().zip(samples) {
            assert!((*a as i32 - *b as i32).abs() <= k as i32, "w {w} k {k}");
        }
        payload
    }

    /// Blocks wider than [`SCRATCH_MAX_WIDTH`] (their own buffers) round-trip
    /// within the bound, and a narrow block after one still does (the
    /// thread's buffers untouched by it).
    #[test]
    fn wide_blocks_round_trip() {
        for w in [SCRATCH_MAX_WIDTH + 2, 8] {
            for k in [0u16, 1] {
                encode_checked(&terrain(w + 1, w as u32 + k as u32), w, k);
            }
        }
    }

    /// The payloads are byte for byte those of format v2's id 2 as first
    /// released, at block widths from the smallest (every sample at the
    /// border) to 64 and at three max errors: CRC-32s of payloads made by
    /// the grid walker of commit e1eb1bd. A change of the coding order, a
    /// prediction, a context or a model fails here. Each payload also
    /// decodes within its bound.
    #[test]
    fn payloads_match_the_released_format() {
        let mut crcs = Vec::new();
        for w in [2usize, 4, 6, 8, 10, 16, 64] {
            for k in [0u16, 1, 7] {
                let samples = terrain(w + 1, (w as u32) << 8 | k as u32);
                crcs.push(crc32fast::hash(&encode_checked(&samples, w, k)));
            }
        }
        assert_eq!(crcs, GOLDEN);
    }

    /// The encoder's division by a product is floor division over the
    /// whole range of residuals, at every step from 1 to the largest.
    #[test]
    fn in_loop_division_is_exact() {
        for k in [0u16, 1, 2, 3, 7, 100, 1000, 4097, 10_922, 16_382, 16_383] {
            let q = InLoop::new(k);
            for x in (-65_535..=65_535).step_by(if k < 8 { 1 } else { 7 }) {
                for v in [x, -65_535, 65_535] {
                    assert_eq!(
                        q.residual(v, 0),
                        (v + k as i32).div_euclid(2 * k as i32 + 1),
                        "k {k}, v {v}"
                    );
                }
            }
        }
    }

    /// Id 3 at max error 0 is id 2, byte for byte (its cells are single
    /// values, and a prediction's fraction is measured in the same units),
    /// so `encode_in_loop` and `decode_in_loop` run id 2's code there:
    /// checked here with id 3's own.
    #[test]
    fn in_loop_at_zero_is_id_2() {
        for w in [2usize, 4, 10, 16, 64] {
            let samples = terrain(w + 1, w as u32);
            let id2 = encode(&samples, w, 0);
            assert_eq!(encode_with(&samples, w, InLoop::new(0)), id2, "w {w}");
            let mut grid = samples.clone();
            decode_with(&id2, w, InLoop::new(0), &mut grid).unwrap();
            assert_eq!(grid, samples, "w {w}");
        }
    }

    /// Id 3 down a tree, as `planet-build`'s second pass codes it: a root
    /// (exact LOD 1), then each of its children from the root's decode,
    /// every decoded sample within `k` of the source at its level. Returns
    /// the bytes of id 3's payloads and of id 2's.
    fn in_loop_tree(source: &[i16], k: u16) -> (usize, usize) {
        let (w, side, big) = (16usize, 17usize, 33usize);
        let at = |i: usize, j: usize| source[j * big + i];
        let root: Vec<i16> = (0..side * side)
            .map(|p| at(2 * (p % side), 2 * (p / side)))
            .collect();
        let (mut b3, mut b2) = (0, 0);
        // The root's LOD 1 is exact (the header's first LOD).
        let mut dec = root.clone();
        let payload = encode_in_loop(&root, w, k);
        (b3, b2) = (b3 + payload.len(), b2 + encode(&root, w, k).len());
        decode_in_loop(&payload, w, k, &mut dec).unwrap();
        for (a, b) in dec.iter().zip(&root) {
            assert!((*a as i32 - *b as i32).abs() <= k as i32, "root, k {k}");
        }
        for child in 0..4 {
            let (ox, oy) = ((child & 1) * w, (child >> 1) * w);
            let src: Vec<i16> = (0..side * side)
                .map(|p| at(ox + p % side, oy + p / side))
                .collect();
            let mut grid = vec![0i16; side * side];
            crate::lod::split_elevation(&dec, w, child, &mut grid);
            let mut enc = src.clone();
            let lod1 = crate::lod::elevation_first_lod(&grid, w);
            crate::lod::elevation_place_first_lod(&lod1, w, &mut enc);
            let payload = encode_in_loop(&enc, w, k);
            (b3, b2) = (b3 + payload.len(), b2 + encode(&src, w, k).len());
            decode_in_loop(&payload, w, k, &mut grid).unwrap();
            for (a, b) in grid.iter().zip(&src) {
                assert!(
                    (*a as i32 - *b as i32).abs() <= k as i32,
                    "child {child}, k {k}"
                );
            }
        }
        (b3, b2)
    }

    #[test]
    fn in_loop_down_a_tree() {
        // A smooth slope with a little noise, at a bound of one and two
        // units: within the bound, and no larger than id 2 (on real data
        // 3 % smaller at one unit, docs/BENCHMARKS.md "Bytes per sample").
        for k in [1u16, 2] {
            let mut x = 7u32;
            let source: Vec<i16> = (0..33 * 33)
                .map(|p| {
                    x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    let (i, j) = (p % 33, p / 33);
                    (5 * i + 3 * j + (i * j) / 7 + (x >> 30) as i32) as i16
                })
                .collect();
            let (b3, b2) = in_loop_tree(&source, k);
            assert!(b3 <= b2, "k {k}: id 3 {b3} bytes, id 2 {b2}");
        }
    }

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

        #[test]
        fn in_loop_within_the_bound_down_a_tree(
            source in proptest::collection::vec(
                prop_oneof![any::<i16>(), Just(i16::MIN), Just(i16::MAX), -50i16..50],
                33 * 33,
            ),
            k in max_errors(),
        ) {
            in_loop_tree(&source, k);
        }
    }
}
