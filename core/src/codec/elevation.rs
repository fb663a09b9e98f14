//! Error-bounded elevation (codec id 1), after Esri's LERC (Limited Error
//! Raster Compression): a user-set maximum error `k` (stored units) turns
//! every sample `v` into the index `q = ⌊(v + k) / s⌋` of a grid of step
//! `s = 2k + 1`, decoded as `q·s` clamped to `i16`, so `|decoded − v| ≤ k`
//! (`k = 0`: exact). The record carries the indices of the samples LOD 0 adds
//! to LOD 1 (thesis §3.3.2, the interleaved LODs of thesis §3.2) as residuals
//! against a prediction made from the indices the decoder already has, in
//! two passes (`predict`): edge midpoints from LOD 1 (cubic), then cell
//! centres from the four decoded midpoints around them.
//!
//! Because the quantisation is pointwise, the index of a LOD 1 sample is the
//! same whether computed from the source value (encoder) or from the
//! parent's decoded value (decoder: `⌊(q·s + k)/s⌋ = q`, also after the
//! `i16` clamp, which moves a value by at most `k`): the prediction is
//! closed-loop without the builder re-encoding from decoded parents, and no
//! error drifts down the levels.
//!
//! **Entropy coding** (rANS, the `constriction` crate): each zig-zagged
//! residual `z` is a bucket symbol (`z` itself under 16; above, its bit
//! length, the bits below the leading one following as uniform symbols of at
//! most 8 bits). The bucket's model depends on a context, the local
//! activity of the LOD 1 indices around the sample (`⌊log2⌋` of the
//! neighbours' difference, 8 classes): per record and context one byte, the
//! scale `σ = round(8·log2(1 + mean z))`, selects a geometric distribution
//! of mean `2^(σ/8) − 1` over `z`, summed into buckets and quantised to 12
//! bits (a compact table decoder model, `codec::model`; all 256 are built
//! once per process, when first used).
//! Measured on the real data's residuals (docs/BENCHMARKS.md "Bytes per
//! sample"), this is 8–12 % under zstd -9 of the same residual bytes and
//! within 2 % of their context-conditioned empirical entropy.
//!
//! Raw layout: 8 scale bytes (contexts 0–7), then the rANS words (`u32`
//! little-endian, as `constriction`'s `DefaultAnsCoder` leaves them: decode
//! pops from the end). There is no further entropy layer.

use super::model::{CompactDecoder, Pow2Uniform};
use super::{unzigzag32, zigzag32, CodecError};
use crate::lod::elevation_new_samples;
use constriction::stream::model::SmallContiguousCategoricalEntropyModel;
use constriction::stream::stack::DefaultAnsCoder;
use constriction::stream::{Decode, Encode};
use std::sync::OnceLock;

/// Largest max error in stored units (the step `2k + 1` stays under 2¹⁵).
pub const MAX_ERROR_LIMIT: u16 = 16_383;

/// Context classes.
const CONTEXTS: usize = 8;
/// Values coded directly as their own bucket.
pub(super) const DIRECT: u32 = 16;
/// Buckets: 16 direct values, then bit lengths 5..=32.
const BUCKETS: usize = DIRECT as usize + 28;

/// Largest raw payload for block width `w`: the scales and at most 6 words
/// of 32 bits per sample (a 32-bit residual in a 12-bit-precision bucket and
/// four uniform chunks), plus the coder's final state.
pub fn max_raw_len(w: usize) -> usize {
    CONTEXTS + 4 * (6 * elevation_new_samples(w) + 2)
}

/// The quantisation of max error `k`: step `s = 2k + 1`, with the division
/// by `s` as a multiplication (exact for every `i16`, see [`Self::index`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct Quantiser {
    k: i32,
    s: i32,
    /// A multiple of `s` at least 32 768, so that `v + k + offset ≥ 0`.
    offset: i32,
    /// `⌊2⁴⁰/s⌋ + 1`.
    inverse: u64,
    /// `offset / s`.
    base: i32,
}

impl Quantiser {
    pub(super) fn new(k: u16) -> Quantiser {
        let (k, s) = (k as i32, 2 * k as i32 + 1);
        let base = (32_768 + s - 1) / s;
        Quantiser {
            k,
            s,
            offset: s * base,
            inverse: (1u64 << 40) / s as u64 + 1,
            base,
        }
    }

    /// `⌊(v + k)/s⌋`: with `n = v + k + offset < 2¹⁷`, `n·inverse/2⁴⁰`
    /// exceeds `n/s` by less than `2¹⁷/2⁴⁰`, less than the `1/s ≥ 2⁻¹⁵` by
    /// which a non-integer `n/s` falls short of the next integer.
    #[inline(always)]
    pub(super) fn index(&self, v: i16) -> i32 {
        let n = (v as i32 + self.k + self.offset) as u64;
        ((n * self.inverse) >> 40) as i32 - self.base
    }

    /// The stored value of an index in [`Self::range`] (where `q·s` fits
    /// in `i32`: `|q·s| < 32 768 + s`), clamped to `i16`: [`value`] in
    /// `i32`.
    #[inline(always)]
    pub(super) fn value(&self, q: i32) -> i16 {
        debug_assert!((self.range().0..=self.range().1).contains(&q));
        (q * self.s).clamp(i16::MIN as i32, i16::MAX as i32) as i16
    }

    /// The indices of `i16::MIN` and `i16::MAX`.
    pub(super) fn range(&self) -> (i32, i32) {
        (self.index(i16::MIN), self.index(i16::MAX))
    }
}

/// Quantisation index of a stored value.
#[inline]
pub(super) fn index(v: i16, k: i32, s: i32) -> i32 {
    (v as i32 + k).div_euclid(s)
}

/// The stored value of an index, clamped to `i16`.
#[inline]
pub(super) fn value(q: i32, s: i32) -> i16 {
    (q as i64 * s as i64).clamp(i16::MIN as i64, i16::MAX as i64) as i16
}

/// Context class of an activity (difference of neighbouring indices).
#[inline]
fn context(a: i32) -> usize {
    ((32 - a.unsigned_abs().leading_zeros()) as usize).min(CONTEXTS - 1)
}

/// Prediction and context of index `(i, j)` from the indices the decoder has.
/// Pass 1 (edge midpoints, one odd coordinate): the cubic
/// `(−a + 9b + 9c − d)/16` along the odd axis through the LOD 1 samples,
/// the mean of the two nearest at the block's border. Pass 2 (cell centres):
/// the mean of the four pass-1 midpoints around it.
#[inline]
fn predict(idx: &[i32], side: usize, i: usize, j: usize) -> (i32, usize) {
    let at = |i: usize, j: usize| idx[j * side + i];
    let cubic = |a: i32, b: i32, c: i32, d: i32| {
        (-(a as i64) + 9 * b as i64 + 9 * c as i64 - d as i64 + 8).div_euclid(16) as i32
    };
    match (i % 2, j % 2) {
        (1, 0) => {
            let (b, c) = (at(i - 1, j), at(i + 1, j));
            let p = if i >= 3 && i + 3 < side {
                cubic(at(i - 3, j), b, c, at(i + 3, j))
            } else {
                ((b as i64 + c as i64) >> 1) as i32
            };
            (p, context(b.wrapping_sub(c)))
        }
        (0, 1) => {
            let (b, c) = (at(i, j - 1), at(i, j + 1));
            let p = if j >= 3 && j + 3 < side {
                cubic(at(i, j - 3), b, c, at(i, j + 3))
            } else {
                ((b as i64 + c as i64) >> 1) as i32
            };
            (p, context(b.wrapping_sub(c)))
        }
        _ => {
            let (l, r, u, d) = (at(i - 1, j), at(i + 1, j), at(i, j - 1), at(i, j + 1));
            let p = ((l as i64 + r as i64 + u as i64 + d as i64) >> 2) as i32;
            let a = l
                .wrapping_sub(r)
                .unsigned_abs()
                .max(u.wrapping_sub(d).unsigned_abs());
            (p, context(a.min(i32::MAX as u32) as i32))
        }
    }
}

/// The new positions of a `(w+1)²` grid in coding order: pass 1 (edge
/// midpoints) row-major, then pass 2 (cell centres) row-major.
fn for_each_new(
    side: usize,
    mut f: impl FnMut(usize, usize) -> Result<(), CodecError>,
) -> Result<(), CodecError> {
    for j in 0..side {
        let first = if j.is_multiple_of(2) { 1 } else { 0 };
        for i in (first..side).step_by(2) {
            f(i, j)?;
        }
    }
    for j in (1..side).step_by(2) {
        for i in (1..side).step_by(2) {
            f(i, j)?;
        }
    }
    Ok(())
}

/// Bucket of a zig-zagged residual and its extra bits `(count, value)`.
#[inline]
pub(super) fn bucket(z: u32) -> (usize, u32, u32) {
    if z < DIRECT {
        (z as usize, 0, 0)
    } else {
        let len = 32 - z.leading_zeros(); // 5..=32
        let extra = len - 1;
        (
            DIRECT as usize + (len - 5) as usize,
            extra,
            z & ((1u32 << extra) - 1),
        )
    }
}

/// Bucket probabilities of a geometric distribution of mean `2^(σ/8) − 1`.
fn bucket_probabilities(scale: u8) -> Vec<f64> {
    let mean = (2f64.powf(scale as f64 / 8.0) - 1.0).max(0.01);
    let rho = mean / (1.0 + mean);
    let ln_rho = rho.ln();
    // P(z in [lo, hi)) = rho^lo − rho^hi (normalised geometric).
    let mass = |lo: f64, hi: f64| (lo * ln_rho).exp() - (hi * ln_rho).exp();
    (0..BUCKETS)
        .map(|b| {
            let p = if b < DIRECT as usize {
                mass(b as f64, b as f64 + 1.0)
            } else {
                let len = (b - DIRECT as usize + 5) as f64;
                mass(2f64.powf(len - 1.0), 2f64.powf(len))
            };
            // Every bucket stays codable whatever the scale.
            p.max(1e-7)
        })
        .collect()
}

/// The encoder model of scale `σ`, built on first use.
fn encoder_model(scale: u8) -> &'static SmallContiguousCategoricalEntropyModel {
    static MODELS: [OnceLock<SmallContiguousCategoricalEntropyModel>; 256] =
        [const { OnceLock::new() }; 256];
    MODELS[scale as usize].get_or_init(|| {
        // The encoder and decoder models are built from the same
        // probabilities by the same ("perfect") quantisation, so they agree
        // bit for bit.
        SmallContiguousCategoricalEntropyModel::from_floating_point_probabilities_perfect(
            &bucket_probabilities(scale),
        )
        .unwrap_or_else(|_| unreachable!("finite positive probabilities"))
    })
}

/// The decoder model of scale `σ` (a [`CompactDecoder`]), built on first
/// use from the encoder's.
fn decoder_model(scale: u8) -> &'static CompactDecoder<BUCKETS> {
    static MODELS: [OnceLock<CompactDecoder<BUCKETS>>; 256] = [const { OnceLock::new() }; 256];
    MODELS[scale as usize].get_or_init(|| CompactDecoder::new(encoder_model(scale)))
}

/// Uniform chunks of at most 8 bits of `count` extra bits, low chunk first.
#[inline]
pub(super) fn chunks(count: u32) -> impl DoubleEndedIterator<Item = (u32, u32)> {
    (0..count.div_ceil(8)).map(move |c| (8 * c, (count - 8 * c).min(8)))
}

/// Encode the LOD 0 samples of a full `(w+1)²` grid of source values with
/// max error `k`: the record payload.
pub fn encode(grid: &[i16], w: usize, k: u16) -> Vec<u8> {
    let side = w + 1;
    let (k, s) = (k as i32, 2 * k as i32 + 1);
    let idx: Vec<i32> = grid.iter().map(|&v| index(v, k, s)).collect();
    let n = elevation_new_samples(w);
    let mut syms: Vec<(u32, u8)> = Vec::with_capacity(n);
    let mut sum = [0f64; CONTEXTS];
    let mut count = [0u32; CONTEXTS];
    let _ = for_each_new(side, |i, j| {
        let (p, c) = predict(&idx, side, i, j);
        let z = zigzag32(idx[j * side + i].wrapping_sub(p));
        sum[c] += z as f64;
        count[c] += 1;
        syms.push((z, c as u8));
        Ok(())
    });
    let scales: [u8; CONTEXTS] = std::array::from_fn(|c| {
        let mean = sum[c] / count[c].max(1) as f64;
        (8.0 * (1.0 + mean).log2()).round().clamp(0.0, 255.0) as u8
    });
    let m: [_; CONTEXTS] = std::array::from_fn(|c| encoder_model(scales[c]));
    let words = rans_encode(&syms, |c| m[c as usize]);
    let mut out = Vec::with_capacity(CONTEXTS + 4 * words.len());
    out.extend_from_slice(&scales);
    for w in words {
        out.extend_from_slice(&w.to_le_bytes());
    }
    out
}

/// rANS words of bucketed residuals `(z, model)` in coding order (written
/// in reverse so that the decoder reads them in coding order), each bucket
/// with the model `model` gives, the low bits uniform (ids 1 and 2).
pub(super) fn rans_encode(
    syms: &[(u32, u8)],
    model: impl Fn(u8) -> &'static SmallContiguousCategoricalEntropyModel,
) -> Vec<u32> {
    let uniform: [Pow2Uniform; 9] = std::array::from_fn(|w| Pow2Uniform::new(w as u32));
    let mut coder = DefaultAnsCoder::new();
    let fail = |e| unreachable!("rANS encoding into a Vec: {e:?}");
    for &(z, m) in syms.iter().rev() {
        let (b, extra, bits) = bucket(z);
        for (shift, width) in chunks(extra).rev() {
            let v = (bits >> shift) & ((1 << width) - 1);
            coder
                .encode_symbol(v as usize, uniform[width as usize])
                .unwrap_or_else(fail);
        }
        coder.encode_symbol(b, model(m)).unwrap_or_else(fail);
    }
    coder
        .into_compressed()
        .unwrap_or_else(|e| unreachable!("rANS into a Vec: {e:?}"))
}

/// The checks and parts of a quantised payload (ids 1 and 2) for a grid of
/// `side²` samples: `heads` scale bytes, then the rANS words, read into
/// `words` (a buffer whose allocation the coder takes over).
pub(super) fn open<'a>(
    raw: &'a [u8],
    heads: usize,
    side: usize,
    grid: &[i16],
    mut words: Vec<u32>,
) -> Result<(&'a [u8], DefaultAnsCoder), CodecError> {
    if grid.len() != side * side {
        return Err(CodecError::Grid {
            got: grid.len(),
            expected: side * side,
        });
    }
    if raw.len() < heads || !(raw.len() - heads).is_multiple_of(4) {
        return Err(CodecError::Length {
            got: raw.len(),
            expected: heads,
        });
    }
    let (scales, body) = raw.split_at(heads);
    words.clear();
    words.extend(
        body.chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])),
    );
    let coder = DefaultAnsCoder::from_compressed(words)
        .map_err(|_| CodecError::Rans("compressed data ends in a zero word".into()))?;
    Ok((scales, coder))
}

/// Decode into a `(w+1)²` grid whose LOD 1 positions hold the parent's
/// decoded samples; every new sample ends within `k` of its source value.
pub fn decode(raw: &[u8], w: usize, k: u16, grid: &mut [i16]) -> Result<(), CodecError> {
    let side = w + 1;
    let (scales, mut coder) = open(raw, CONTEXTS, side, grid, Vec::new())?;
    let m: [_; CONTEXTS] = std::array::from_fn(|c| decoder_model(scales[c]));
    let (k, s) = (k as i32, 2 * k as i32 + 1);
    let (lo, hi) = (index(i16::MIN, k, s), index(i16::MAX, k, s));
    let mut idx = vec![0i32; side * side];
    for j in (0..side).step_by(2) {
        for i in (0..side).step_by(2) {
            idx[j * side + i] = index(grid[j * side + i], k, s);
        }
    }
    // Uniform models of 1..=8 bits, built once per record.
    let uniform: [Pow2Uniform; 9] = std::array::from_fn(|w| Pow2Uniform::new(w as u32));
    let mut next = |c: usize| -> Result<u32, CodecError> {
        let rans = |e| CodecError::Rans(format!("{e:?}"));
        let b = coder.decode_symbol(m[c]).map_err(rans)?;
        if b < DIRECT as usize {
            return Ok(b as u32);
        }
        let extra = (b - DIRECT as usize + 4) as u32;
        let mut bits = 0u32;
        for (shift, width) in chunks(extra) {
            let v = coder.decode_symbol(uniform[width as usize]).map_err(rans)?;
            bits |= (v as u32) << shift;
        }
        Ok((1u32 << extra) | bits)
    };
    for_each_new(side, |i, j| {
        let (p, c) = predict(&idx, side, i, j);
        let q = p.wrapping_add(unzigzag32(next(c)?)).clamp(lo, hi);
        idx[j * side + i] = q;
        grid[j * side + i] = value(q, s);
        Ok(())
    })?;
    if !coder.is_empty() {
        return Err(CodecError::Rans("words left after the last sample".into()));
    }
    Ok(())
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn buckets_round_trip() {
        for z in [
            0u32,
            1,
            15,
            16,
            17,
            31,
            32,
            255,
            256,
            65_535,
            1 << 20,
            u32::MAX,
        ] {
            let (b, extra, bits) = bucket(z);
            assert!(b < BUCKETS);
            if z >= DIRECT {
                assert_eq!(extra as usize, b - DIRECT as usize + 4);
                assert_eq!((1u32 << extra) | bits, z);
            }
        }
    }

    /// A quantised codec's encoder, decoder and payload limit (ids 1 and
    /// 2; the tests below run on both).
    pub(in crate::codec) type Codec = (
        fn(&[i16], usize, u16) -> Vec<u8>,
        fn(&[u8], usize, u16, &mut [i16]) -> Result<(), CodecError>,
        fn(usize) -> usize,
    );

    /// A 17² grid of random values with extremes, cliffs and constant runs.
    pub(in crate::codec) fn hostile_grid() -> impl Strategy<Value = Vec<i16>> {
        proptest::collection::vec(
            prop_oneof![
                any::<i16>(),
                Just(i16::MIN),
                Just(i16::MAX),
                Just(-32767i16),
                Just(0i16),
                -50i16..50,
            ],
            17 * 17,
        )
    }

    /// Max errors to try: exact, 1, random and the largest.
    pub(in crate::codec) fn max_errors() -> impl Strategy<Value = u16> {
        prop_oneof![Just(0u16), Just(1), 0..2000u16, Just(MAX_ERROR_LIMIT)]
    }

    /// Encode a 17² grid and decode it from its LOD 1 as the parent
    /// decoded it (the source quantised the same way), which the encoder
    /// also sees there (id 3 predicts from it; ids 1 and 2 take the same
    /// index from it as from the source).
    pub(in crate::codec) fn round_trip(codec: Codec, samples: &[i16], k: u16) -> Vec<i16> {
        let w = 16;
        let side = w + 1;
        let s = 2 * k as i32 + 1;
        let mut grid = vec![0i16; side * side];
        for j in (0..side).step_by(2) {
            for i in (0..side).step_by(2) {
                let v = samples[j * side + i];
                grid[j * side + i] = value(index(v, k as i32, s), s);
            }
        }
        let mut source = samples.to_vec();
        for j in (0..side).step_by(2) {
            for i in (0..side).step_by(2) {
                source[j * side + i] = grid[j * side + i];
            }
        }
        let enc = codec.0(&source, w, k);
        assert!(enc.len() <= codec.2(w));
        codec.1(&enc, w, k, &mut grid).unwrap();
        grid
    }

    /// Every decoded sample is within `k` of the source; `k = 0` is exact.
    pub(in crate::codec) fn check_bound(codec: Codec, samples: &[i16], k: u16) {
        let dec = round_trip(codec, samples, k);
        for (p, (a, b)) in dec.iter().zip(samples).enumerate() {
            assert!(
                (*a as i32 - *b as i32).abs() <= k as i32,
                "sample {p} {a} vs {b} k {k}"
            );
        }
        if k == 0 {
            assert_eq!(dec, samples);
        }
    }

    /// Constant blocks round-trip exactly, cliffs between the extremes
    /// within the bound.
    pub(in crate::codec) fn check_constant_and_cliff(codec: Codec) {
        let side = 17;
        let constant = vec![1234i16; side * side];
        assert_eq!(round_trip(codec, &constant, 0), constant);
        let cliff: Vec<i16> = (0..side * side)
            .map(|p| if p % side < 8 { i16::MIN } else { i16::MAX })
            .collect();
        for k in [0, 1, 3, 100, MAX_ERROR_LIMIT] {
            check_bound(codec, &cliff, k);
        }
    }

    /// Truncated, padded and mis-sized inputs are errors.
    pub(in crate::codec) fn check_truncated_and_padded(codec: Codec) {
        let w = 16;
        let samples: Vec<i16> = (0..17 * 17)
            .map(|v| ((v * 37 % 1000) * 40 - 20000) as i16)
            .collect();
        let enc = codec.0(&samples, w, 0);
        let mut grid = vec![0i16; 17 * 17];
        for cut in [0, 1, enc.len() / 2, enc.len() - 1] {
            assert!(codec.1(&enc[..cut], w, 0, &mut grid).is_err(), "cut {cut}");
        }
        let mut long = enc.clone();
        long.extend_from_slice(&[0, 0, 0, 0]);
        assert!(codec.1(&long, w, 0, &mut grid).is_err());
        assert!(codec.1(&enc, w, 0, &mut [0i16; 4]).is_err());
    }

    /// Ids 1, 2 and 3.
    const CODECS: [Codec; 3] = [
        (encode, decode, max_raw_len),
        (
            super::super::elevation2::encode,
            super::super::elevation2::decode,
            super::super::elevation2::max_raw_len,
        ),
        (
            super::super::elevation2::encode_in_loop,
            super::super::elevation2::decode_in_loop,
            super::super::elevation2::max_raw_len,
        ),
    ];

    proptest! {
        #[test]
        fn every_sample_within_the_bound(samples in hostile_grid(), k in max_errors()) {
            for codec in CODECS {
                check_bound(codec, &samples, k);
            }
        }

        #[test]
        fn hostile_payloads_are_typed_errors(raw in proptest::collection::vec(any::<u8>(), 0..1500), k in 0..5u16) {
            for codec in CODECS {
                let mut grid = vec![7i16; 17 * 17];
                let _ = codec.1(&raw, 16, k, &mut grid);
            }
        }
    }

    #[test]
    fn constant_and_cliff_blocks() {
        for codec in CODECS {
            check_constant_and_cliff(codec);
        }
    }

    #[test]
    fn truncated_and_padded_payloads_are_errors() {
        for codec in CODECS {
            check_truncated_and_padded(codec);
        }
    }

    /// The multiplicative division equals floor division for every `i16`
    /// and a spread of max errors, the largest included.
    #[test]
    fn quantiser_divides_exactly() {
        for k in [0u16, 1, 2, 3, 7, 100, 1000, 4097, 16_382, MAX_ERROR_LIMIT] {
            let quant = Quantiser::new(k);
            let s = 2 * k as i32 + 1;
            for v in i16::MIN..=i16::MAX {
                assert_eq!(quant.index(v), index(v, k as i32, s), "v {v} k {k}");
            }
            assert_eq!(
                quant.range(),
                (index(i16::MIN, k as i32, s), index(i16::MAX, k as i32, s))
            );
        }
    }
}
