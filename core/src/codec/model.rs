//! A compact decoder model for `constriction`'s rANS coder: the quantile
//! function of a 12-bit categorical model over fewer than 64 symbols.
//!
//! `constriction`'s own lookup decoder keeps one entry per quantile (8 kB a
//! model); a record that uses three dozen models then reads from 300 kB of
//! tables in random order, and the decoder waited on the cache for most of
//! its time (docs/BENCHMARKS.md "Bytes per sample"). Here a model is 256
//! entries, one per 16 quantiles, each the symbol, left cumulative and
//! probability packed in a `u32` when one symbol holds all 16 quantiles
//! (one load decodes most symbols), else the first symbol there, from which
//! the cumulative distribution is walked (1152 bytes a model; entries of 32
//! quantiles, half the size, decoded real records 5 % slower, as more
//! symbols needed the walk). The model is
//! built from the encoder's, so the two agree bit for bit by construction.

use constriction::stream::model::{DecoderModel, EncoderModel, EntropyModel};
use std::num::NonZeroU16;

/// Precision of the models, bits (`constriction`'s "small" models).
const PRECISION: usize = 12;
/// Quantiles per coarse entry, as a shift.
const COARSE_SHIFT: usize = 4;
/// A coarse entry whose 16 quantiles all belong to its symbol.
const PURE: u32 = 1 << 31;

/// Decoder model over symbols `0..N`.
#[derive(Debug, Clone)]
pub(crate) struct CompactDecoder<const N: usize> {
    /// `cdf[s]`: the left cumulative of symbol `s`; `cdf[s] = 4096` for
    /// `s ≥ N`.
    cdf: [u16; 64],
    /// Per 16 quantiles: `PURE | prob << 18 | left << 6 | symbol`, or the
    /// symbol holding the first of them.
    coarse: [u32; 1 << (PRECISION - COARSE_SHIFT)],
}

impl<const N: usize> CompactDecoder<N> {
    /// The decoder of an encoder model over `0..N` (every symbol with a
    /// nonzero probability).
    pub(crate) fn new<M>(m: &M) -> CompactDecoder<N>
    where
        M: EncoderModel<PRECISION, Symbol = usize, Probability = u16>,
    {
        const { assert!(N < 64) };
        let mut cdf = [1u16 << PRECISION; 64];
        cdf[0] = 0;
        for s in 0..N {
            let (left, p) = m
                .left_cumulative_and_probability(s)
                .unwrap_or_else(|| unreachable!("every symbol has a nonzero probability"));
            debug_assert_eq!(left, cdf[s]);
            cdf[s + 1] = left + p.get();
        }
        debug_assert_eq!(cdf[N] as usize, 1 << PRECISION);
        let mut coarse = [0u32; 1 << (PRECISION - COARSE_SHIFT)];
        let mut s = 0usize;
        for (t, c) in coarse.iter_mut().enumerate() {
            let first = t << COARSE_SHIFT;
            while cdf[s + 1] as usize <= first {
                s += 1;
            }
            let last = first + (1 << COARSE_SHIFT) - 1;
            *c = if (cdf[s + 1] as usize) > last {
                let p = (cdf[s + 1] - cdf[s]) as u32;
                PURE | p << 18 | (cdf[s] as u32) << 6 | s as u32
            } else {
                s as u32
            };
        }
        CompactDecoder { cdf, coarse }
    }
}

impl<const N: usize> EntropyModel<PRECISION> for CompactDecoder<N> {
    type Symbol = usize;
    type Probability = u16;
}

impl<const N: usize> DecoderModel<PRECISION> for CompactDecoder<N> {
    #[inline(always)]
    fn quantile_function(&self, quantile: u16) -> (usize, u16, NonZeroU16) {
        // The coder passes quantiles below 4096 (its state modulo 2¹²).
        let q = quantile & ((1 << PRECISION) - 1);
        let e = self.coarse[(q >> COARSE_SHIFT) as usize];
        let (s, left, p) = if e & PURE != 0 {
            (
                (e & 63) as usize,
                ((e >> 6) & 0xfff) as u16,
                ((e >> 18) & 0x1fff) as u16,
            )
        } else {
            // `cdf[1..=s] ≤ q < cdf[s + 1]`; cdf[N] = 4096 > q ends the walk
            // at a symbol below N ≤ 63.
            let mut s = (e & 63) as usize;
            while s < 62 && self.cdf[s + 1] <= q {
                s += 1;
            }
            (s, self.cdf[s], self.cdf[s + 1].wrapping_sub(self.cdf[s]))
        };
        let p = NonZeroU16::new(p)
            .unwrap_or_else(|| unreachable!("every symbol has a nonzero probability"));
        (s, left, p)
    }
}

/// A uniform model over `2^bits` symbols (`1 ≤ bits ≤ 12`) at 12-bit
/// precision: `constriction`'s `SmallUniformModel` for a power of two, bit
/// for bit (every symbol `2^(12 − bits)` quantiles, the left cumulative
/// `s · 2^(12 − bits)`), with shifts where that model divides by a value
/// known only at run time, which took a sixth of the elevation decoder's
/// time on real data's long residuals.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Pow2Uniform {
    /// `12 − bits`.
    shift: u16,
}

impl Pow2Uniform {
    /// The model of `bits`-bit symbols, `1 ≤ bits ≤ 12` (0 reads as 1, as
    /// the coders' table of widths has an unused entry 0).
    pub(crate) const fn new(bits: u32) -> Pow2Uniform {
        let bits = if bits == 0 { 1 } else { bits };
        assert!(bits as usize <= PRECISION);
        Pow2Uniform {
            shift: (PRECISION as u32 - bits) as u16,
        }
    }
}

impl EntropyModel<PRECISION> for Pow2Uniform {
    type Symbol = usize;
    type Probability = u16;
}

impl EncoderModel<PRECISION> for Pow2Uniform {
    #[inline(always)]
    fn left_cumulative_and_probability(
        &self,
        symbol: impl std::borrow::Borrow<usize>,
    ) -> Option<(u16, NonZeroU16)> {
        let symbol = *symbol.borrow();
        if symbol >= 1 << (PRECISION as u16 - self.shift) {
            return None;
        }
        let p = NonZeroU16::new(1 << self.shift)?;
        Some(((symbol as u16) << self.shift, p))
    }
}

impl DecoderModel<PRECISION> for Pow2Uniform {
    #[inline(always)]
    fn quantile_function(&self, quantile: u16) -> (usize, u16, NonZeroU16) {
        let q = quantile & ((1 << PRECISION) - 1);
        let s = q >> self.shift;
        let p =
            NonZeroU16::new(1 << self.shift).unwrap_or_else(|| unreachable!("a shift below 16"));
        (s as usize, s << self.shift, p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use constriction::stream::model::SmallContiguousCategoricalEntropyModel;

    fn check<const N: usize>(probs: &[f64]) {
        let m = SmallContiguousCategoricalEntropyModel::from_floating_point_probabilities_perfect(
            probs,
        )
        .unwrap();
        let d = CompactDecoder::<N>::new(&m);
        for q in 0..4096u16 {
            let (s, left, p) = d.quantile_function(q);
            assert!(s < N);
            let (l2, p2) = m.left_cumulative_and_probability(s).unwrap();
            assert_eq!((left, p), (l2, p2), "quantile {q}");
            assert!(left <= q && q < left + p.get(), "{q} in {s}");
        }
    }

    /// The shift-only uniform model is `constriction`'s uniform model of a
    /// power of two at every quantile.
    #[test]
    fn pow2_uniform_is_constrictions() {
        use constriction::stream::model::SmallUniformModel;
        for bits in 1..=8u32 {
            let ours = Pow2Uniform::new(bits);
            let theirs = SmallUniformModel::new(1usize << bits);
            for s in 0..(1usize << bits) + 1 {
                assert_eq!(
                    ours.left_cumulative_and_probability(s),
                    theirs.left_cumulative_and_probability(s),
                    "bits {bits}, symbol {s}"
                );
            }
            for q in 0..4096u16 {
                assert_eq!(
                    ours.quantile_function(q),
                    theirs.quantile_function(q),
                    "bits {bits}, quantile {q}"
                );
            }
        }
    }

    /// The compact model's quantile function is the encoder model's inverse
    /// at every quantile: skewed, geometric with a tail of floor
    /// probabilities, and uniform models.
    #[test]
    fn inverts_the_encoder_model() {
        check::<5>(&[0.9, 0.05, 0.03, 0.01, 0.01]);
        check::<2>(&[0.999_99, 0.000_01]);
        check::<29>(&(0..29).map(|s| 0.5f64.powi(s) + 1e-7).collect::<Vec<_>>());
        check::<44>(&[1.0; 44]);
        check::<63>(&(0..63).map(|s| 1.0 + s as f64).collect::<Vec<_>>());
    }
}
