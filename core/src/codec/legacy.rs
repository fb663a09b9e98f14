//! Format v1's lossless payload codecs (the raw stage; lz4 or zstd after).
//! Codec id 0 of both trees (and id 1 of colour, the same deltas under zstd).
//!
//! **Elevation** (thesis §3.3.2 "simple LOD compression"; our predictor is
//! beyond the thesis). A record carries the samples LOD 0 adds to LOD 1, in
//! row-major order skipping the LOD 1 positions. Each is stored as the
//! residual against a prediction made only from LOD 1 samples (the mean of the
//! two or four nearest LOD 1 samples), as a wrapping 16-bit difference,
//! zig-zag encoded, split into a low-byte plane followed by a high-byte plane.
//! Wrapping arithmetic makes the code exactly invertible for any `i16`; the
//! high plane is almost all zeros on real terrain, which lz4 then removes.
//!
//! **Colour** (Thesis §4.4.4 PTM, with the scheme derived in docs/REFERENCES.md).
//! LOD 1 is the floor of the mean of each 2×2 cell of LOD 0. The record stores,
//! per cell and channel, three of the four samples as wrapping byte deltas
//! against the cell's LOD 1 value, and the remainder `r = sum − 4·mean` in two
//! bits; the fourth sample is `4·mean + r − a − b − c`. That is `(3·8 + 2)/24`
//! = +8.3 % over point sampling, 18.75 % under redundant LODs, and lossless.
//! Layout: the delta plane `(W/2)² × 3 samples × 3 channels` (cell-major, then
//! sample, then channel), then the remainder plane, 2 bits per (cell, channel)
//! packed four to a byte, low bits first.

use super::CodecError;
use crate::lod::{is_first_lod, Rgb};

#[inline]
fn zigzag(v: i16) -> u16 {
    ((v << 1) ^ (v >> 15)) as u16
}

#[inline]
fn unzigzag(v: u16) -> i16 {
    ((v >> 1) as i16) ^ -((v & 1) as i16)
}

/// Prediction of elevation sample `(i, j)` (not in LOD 1) from LOD 1 only.
#[inline]
fn predict(grid: &[i16], side: usize, i: usize, j: usize) -> i16 {
    let at = |i: usize, j: usize| grid[j * side + i] as i32;
    let p = match (i % 2, j % 2) {
        (1, 0) => (at(i - 1, j) + at(i + 1, j)) >> 1,
        (0, 1) => (at(i, j - 1) + at(i, j + 1)) >> 1,
        _ => (at(i - 1, j - 1) + at(i + 1, j - 1) + at(i - 1, j + 1) + at(i + 1, j + 1)) >> 2,
    };
    p as i16
}

/// Encode the LOD 0 samples of a full `(w+1)²` elevation grid.
pub fn encode_elevation(grid: &[i16], w: usize) -> Vec<u8> {
    let side = w + 1;
    let n = crate::lod::elevation_new_samples(w);
    let mut out = vec![0u8; 2 * n];
    let mut k = 0;
    for j in 0..side {
        for i in 0..side {
            if is_first_lod(i, j) {
                continue;
            }
            let r = grid[j * side + i].wrapping_sub(predict(grid, side, i, j));
            let z = zigzag(r);
            out[k] = z as u8;
            out[n + k] = (z >> 8) as u8;
            k += 1;
        }
    }
    out
}

/// Decode LOD 0 samples into a `(w+1)²` grid whose LOD 1 positions are set.
pub fn decode_elevation(raw: &[u8], w: usize, grid: &mut [i16]) -> Result<(), CodecError> {
    let side = w + 1;
    let n = crate::lod::elevation_new_samples(w);
    if raw.len() != 2 * n {
        return Err(CodecError::Length {
            got: raw.len(),
            expected: 2 * n,
        });
    }
    let mut k = 0;
    for j in 0..side {
        for i in 0..side {
            if is_first_lod(i, j) {
                continue;
            }
            let z = raw[k] as u16 | (raw[n + k] as u16) << 8;
            grid[j * side + i] = predict(grid, side, i, j).wrapping_add(unzigzag(z));
            k += 1;
        }
    }
    Ok(())
}

/// Raw size of a colour LOD 0 payload for block width `w`.
pub fn colour_payload_len(w: usize) -> usize {
    let cells = (w / 2) * (w / 2);
    cells * 9 + (cells * 3).div_ceil(4)
}

/// Encode the LOD 0 of a full `w²` colour grid against its filtered LOD 1
/// (which must be [`crate::lod::colour_filter`] of it).
pub fn encode_colour(full: &[Rgb], lod1: &[Rgb], w: usize) -> Vec<u8> {
    let h = w / 2;
    let cells = h * h;
    let mut out = vec![0u8; colour_payload_len(w)];
    let (deltas, rems) = out.split_at_mut(cells * 9);
    for cj in 0..h {
        for ci in 0..h {
            let c = cj * h + ci;
            let m = lod1[c];
            let s = [
                full[2 * cj * w + 2 * ci],
                full[2 * cj * w + 2 * ci + 1],
                full[(2 * cj + 1) * w + 2 * ci],
                full[(2 * cj + 1) * w + 2 * ci + 1],
            ];
            for ch in 0..3 {
                for (q, sample) in s.iter().take(3).enumerate() {
                    deltas[c * 9 + q * 3 + ch] = sample[ch].wrapping_sub(m[ch]);
                }
                let sum: u16 = s.iter().map(|x| x[ch] as u16).sum();
                let r = (sum - 4 * m[ch] as u16) as u8 & 3;
                let bit = c * 3 + ch;
                rems[bit / 4] |= r << ((bit % 4) * 2);
            }
        }
    }
    out
}

/// Decode a colour LOD 0 `w²` grid from its LOD 1 and the payload.
pub fn decode_colour(raw: &[u8], lod1: &[Rgb], w: usize) -> Result<Vec<Rgb>, CodecError> {
    let h = w / 2;
    let cells = h * h;
    if raw.len() != colour_payload_len(w) || lod1.len() != cells {
        return Err(CodecError::Length {
            got: raw.len(),
            expected: colour_payload_len(w),
        });
    }
    let (deltas, rems) = raw.split_at(cells * 9);
    let mut full = vec![[0u8; 3]; w * w];
    for cj in 0..h {
        for ci in 0..h {
            let c = cj * h + ci;
            let m = lod1[c];
            for ch in 0..3 {
                let a = deltas[c * 9 + ch].wrapping_add(m[ch]);
                let b = deltas[c * 9 + 3 + ch].wrapping_add(m[ch]);
                let d = deltas[c * 9 + 6 + ch].wrapping_add(m[ch]);
                let bit = c * 3 + ch;
                let r = (rems[bit / 4] >> ((bit % 4) * 2)) & 3;
                let last = 4 * m[ch] as i32 + r as i32 - a as i32 - b as i32 - d as i32;
                if !(0..=255).contains(&last) {
                    return Err(CodecError::ColourRange(c));
                }
                full[2 * cj * w + 2 * ci][ch] = a;
                full[2 * cj * w + 2 * ci + 1][ch] = b;
                full[(2 * cj + 1) * w + 2 * ci][ch] = d;
                full[(2 * cj + 1) * w + 2 * ci + 1][ch] = last as u8;
            }
        }
    }
    Ok(full)
}

/// lz4 block compression (no size prefix; the record stores the raw length).
pub fn compress(raw: &[u8]) -> Vec<u8> {
    lz4_flex::block::compress(raw)
}

/// lz4 block decompression to exactly `raw_len` bytes.
pub fn decompress(data: &[u8], raw_len: usize) -> Result<Vec<u8>, CodecError> {
    let out = lz4_flex::block::decompress(data, raw_len).map_err(CodecError::Lz4)?;
    if out.len() != raw_len {
        return Err(CodecError::Length {
            got: out.len(),
            expected: raw_len,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::colour_filter;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn elevation_round_trip(samples in proptest::collection::vec(any::<i16>(), 17 * 17)) {
            let w = 16;
            let enc = encode_elevation(&samples, w);
            let mut grid = vec![0i16; 17 * 17];
            for j in (0..17).step_by(2) { for i in (0..17).step_by(2) { grid[j * 17 + i] = samples[j * 17 + i]; } }
            decode_elevation(&enc, w, &mut grid).unwrap();
            prop_assert_eq!(grid, samples);
        }

        #[test]
        fn colour_round_trip(samples in proptest::collection::vec(any::<[u8; 3]>(), 16 * 16)) {
            let w = 16;
            let lod1 = colour_filter(&samples, w);
            let enc = encode_colour(&samples, &lod1, w);
            prop_assert_eq!(enc.len(), colour_payload_len(w));
            prop_assert_eq!(decode_colour(&enc, &lod1, w).unwrap(), samples);
        }

        #[test]
        fn hostile_payloads_never_panic(raw in proptest::collection::vec(any::<u8>(), 0..1200)) {
            let mut grid = vec![0i16; 17 * 17];
            let _ = decode_elevation(&raw, 16, &mut grid);
            let _ = decode_colour(&raw, &[[0; 3]; 64], 16);
            let _ = decompress(&raw, 2000);
        }
    }

    #[test]
    fn ptm_overhead_is_8_3_percent() {
        let w = 128;
        let point_sampled = 3 * (w * w - (w / 2) * (w / 2));
        let ratio = colour_payload_len(w) as f64 / point_sampled as f64;
        assert!((ratio - 26.0 / 24.0).abs() < 1e-9, "{ratio}");
    }
}
