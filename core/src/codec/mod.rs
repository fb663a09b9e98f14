//! Payload codecs of LOD records, chosen per tree in the header (format v2).
//!
//! A record's payload goes through two stages: a *sample codec* maps the
//! samples the record adds to a raw byte string, and an *entropy layer*
//! compresses those bytes (lz4 for the legacy codecs, zstd for the others);
//! the record stores the raw length so a reader checks it against the
//! codec's limit before it allocates anything. The codec of each tree and its
//! parameters are written in the header ([`ElevationCodec`], [`ColourCodec`]);
//! `docs/FORMAT.md` gives the byte layouts.
//!
//! - [`legacy`]: format v1's lossless codecs (thesis §3.3.2 simple LOD
//!   compression for elevation, thesis §4.4.4 PTM for colour), with lz4.
//!   Kept selectable for comparison (`--elevation-codec legacy`,
//!   `--colour-quality lossless-legacy`).
//! - [`elevation`]: error-bounded elevation, LERC-like (Esri's Limited Error
//!   Raster Compression): samples quantised on a grid of step `2k + 1`
//!   stored units, predicted from LOD 1 in the quantised domain, rANS with
//!   context models (the `constriction` crate; no further entropy layer).
//!   Codec id 1, still read.
//! - [`elevation2`]: the same quantisation with predictions kept to 1/32 of
//!   a step, curvature and neighbour contexts and Laplace models (codec
//!   id 2, the default).
//! - [`colour`]: perceptual colour, YCoCg Haar details of each 2×2 cell
//!   against its LOD 1 mean (non-redundant, like the thesis's interleaving),
//!   dead-zone quantised, zstd; and the lossless PTM deltas under zstd.

pub mod colour;
pub mod elevation;
pub mod elevation2;
pub mod legacy;
mod model;

pub use legacy::{compress, decompress};

use crate::lod::Rgb;
use std::cell::RefCell;
use thiserror::Error;

/// A payload that does not decode.
#[derive(Debug, Error)]
pub enum CodecError {
    /// The payload has the wrong length for the block width.
    #[error("payload is {got} bytes, expected {expected}")]
    Length {
        /// Bytes received.
        got: usize,
        /// Bytes the block width requires.
        expected: usize,
    },
    /// A declared raw length is over the codec's limit for the block width
    /// (checked before anything is allocated).
    #[error("declared raw length {declared} over the limit {limit}")]
    TooLarge {
        /// The length the record declares.
        declared: usize,
        /// The largest length the codec can produce for this block width.
        limit: usize,
    },
    /// lz4 decompression failed.
    #[error("lz4 decompression failed")]
    Lz4(#[source] lz4_flex::block::DecompressError),
    /// zstd decompression failed.
    #[error("zstd decompression failed")]
    Zstd(#[source] std::io::Error),
    /// rANS decoding failed or left words over.
    #[error("rANS decoding: {0}")]
    Rans(String),
    /// A reconstructed colour sample is outside `0..=255`.
    #[error("colour sample out of range at cell {0}")]
    ColourRange(usize),
    /// The escape section of a payload does not match its escape markers.
    #[error("escape section: {0}")]
    Escapes(String),
    /// The grid given to the decoder has the wrong size.
    #[error("grid of {got} samples, expected {expected}")]
    Grid {
        /// Samples given.
        got: usize,
        /// Samples the block width requires.
        expected: usize,
    },
    /// An unknown codec id or impossible parameter in a header.
    #[error("codec: {0}")]
    Codec(String),
}

/// zstd level of the new codecs: level 9 was the knee on real residuals
/// (docs/BENCHMARKS.md "Bytes per sample"): higher levels saved under 1 %
/// and built several times slower.
pub const ZSTD_LEVEL: i32 = 9;

/// An encoded payload: the entropy-coded bytes and the raw length before it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Payload {
    /// Length of the raw payload (after the sample codec, before the
    /// entropy layer).
    pub raw_len: u32,
    /// The compressed bytes stored in the record.
    pub bytes: Vec<u8>,
}

impl Payload {
    /// lz4 of a raw payload (legacy codecs).
    pub fn lz4(raw: &[u8]) -> Payload {
        Payload {
            raw_len: raw.len() as u32,
            bytes: compress(raw),
        }
    }

    /// A payload the sample codec entropy-coded itself (no further layer).
    pub fn unlayered(bytes: Vec<u8>) -> Payload {
        Payload {
            raw_len: bytes.len() as u32,
            bytes,
        }
    }

    /// zstd of a raw payload at [`ZSTD_LEVEL`] (one compression context
    /// per thread, reused).
    pub fn zstd(raw: &[u8]) -> Payload {
        thread_local! {
            static CCTX: RefCell<Option<zstd::bulk::Compressor<'static>>> =
                const { RefCell::new(None) };
        }
        // Compressing an in-memory slice into a Vec only fails on an
        // allocation failure or an invalid level, neither of which is input.
        let bytes = CCTX.with(|c| {
            let mut c = c.borrow_mut();
            let ctx = match c.as_mut() {
                Some(ctx) => ctx,
                None => c.insert(new_compressor()),
            };
            ctx.compress(raw)
                .unwrap_or_else(|e| unreachable!("zstd of an in-memory buffer: {e}"))
        });
        Payload {
            raw_len: raw.len() as u32,
            bytes,
        }
    }
}

/// A compression context for payloads of at most a few hundred kB: a
/// 256 kB window keeps each worker's context small.
fn new_compressor() -> zstd::bulk::Compressor<'static> {
    let mut c = zstd::bulk::Compressor::new(ZSTD_LEVEL)
        .unwrap_or_else(|e| unreachable!("zstd level {ZSTD_LEVEL} is valid: {e}"));
    c.set_parameter(zstd::zstd_safe::CParameter::WindowLog(18))
        .unwrap_or_else(|e| unreachable!("zstd window log 18 is valid: {e}"));
    c
}

/// zstd decompression of exactly `raw_len` bytes, `raw_len` checked against
/// `limit` before the buffer is allocated.
pub fn unzstd(data: &[u8], raw_len: usize, limit: usize) -> Result<Vec<u8>, CodecError> {
    if raw_len > limit {
        return Err(CodecError::TooLarge {
            declared: raw_len,
            limit,
        });
    }
    thread_local! {
        static DCTX: RefCell<Option<zstd::bulk::Decompressor<'static>>> =
            const { RefCell::new(None) };
    }
    let mut out = vec![0u8; raw_len];
    let n = DCTX.with(|d| {
        let mut d = d.borrow_mut();
        let ctx = match d.as_mut() {
            Some(ctx) => ctx,
            None => d.insert(zstd::bulk::Decompressor::new().map_err(CodecError::Zstd)?),
        };
        ctx.decompress_to_buffer(data, &mut out[..])
            .map_err(CodecError::Zstd)
    })?;
    if n != raw_len {
        return Err(CodecError::Length {
            got: n,
            expected: raw_len,
        });
    }
    Ok(out)
}

/// A payload without an entropy layer must declare its own length, within
/// the codec's `limit`.
fn check_unlayered(payload: &[u8], raw_len: usize, limit: usize) -> Result<(), CodecError> {
    if raw_len != payload.len() || raw_len > limit {
        return Err(CodecError::TooLarge {
            declared: raw_len,
            limit: limit.min(payload.len()),
        });
    }
    Ok(())
}

/// lz4 decompression with the declared length checked against `limit` first.
pub fn unlz4(data: &[u8], raw_len: usize, limit: usize) -> Result<Vec<u8>, CodecError> {
    if raw_len > limit {
        return Err(CodecError::TooLarge {
            declared: raw_len,
            limit,
        });
    }
    decompress(data, raw_len)
}

/// The elevation tree's codec and its parameters (header, format v2).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ElevationCodec {
    /// Id 0: format v1's lossless byte planes under lz4 ([`legacy`]).
    Legacy,
    /// Id 1: samples quantised to within `max_error` stored units (0:
    /// exact), predicted from LOD 1, rANS ([`elevation`]).
    Quantised {
        /// Largest absolute error of any decoded sample, stored units.
        max_error: u16,
    },
    /// Id 2: the same quantisation, sub-step predictions, curvature and
    /// neighbour contexts, Laplace models, rANS ([`elevation2`]).
    Laplace {
        /// Largest absolute error of any decoded sample, stored units.
        max_error: u16,
    },
    /// Id 3: id 2 with each residual quantised against its own prediction
    /// (in the loop, [`elevation2`]): its encoder needs the
    /// parent's decoded samples at LOD 1. At `max_error` 0 its payloads
    /// are id 2's.
    InLoop {
        /// Largest absolute error of any decoded sample, stored units.
        max_error: u16,
    },
}

impl ElevationCodec {
    /// The codec id written in the header.
    pub fn id(&self) -> u8 {
        match self {
            ElevationCodec::Legacy => 0,
            ElevationCodec::Quantised { .. } => 1,
            ElevationCodec::Laplace { .. } => 2,
            ElevationCodec::InLoop { .. } => 3,
        }
    }

    /// The parameter written in the header (max error in stored units).
    pub fn param(&self) -> u16 {
        match self {
            ElevationCodec::Legacy => 0,
            ElevationCodec::Quantised { max_error }
            | ElevationCodec::Laplace { max_error }
            | ElevationCodec::InLoop { max_error } => *max_error,
        }
    }

    /// From the header's id and parameter.
    pub fn from_id(id: u8, param: u16) -> Result<ElevationCodec, CodecError> {
        match (id, param) {
            (0, 0) => Ok(ElevationCodec::Legacy),
            (1, k) if k <= elevation::MAX_ERROR_LIMIT => {
                Ok(ElevationCodec::Quantised { max_error: k })
            }
            (2, k) if k <= elevation::MAX_ERROR_LIMIT => {
                Ok(ElevationCodec::Laplace { max_error: k })
            }
            (3, k) if k <= elevation::MAX_ERROR_LIMIT => {
                Ok(ElevationCodec::InLoop { max_error: k })
            }
            _ => Err(CodecError::Codec(format!(
                "elevation codec id {id} with parameter {param} is not one this reader \
                 knows (ids 0-3, max error up to {}): written by a newer planet-build?",
                elevation::MAX_ERROR_LIMIT
            ))),
        }
    }

    /// Largest absolute error of a decoded sample, stored units.
    pub fn max_error(&self) -> u16 {
        self.param()
    }

    /// A short name for reports.
    pub fn name(&self) -> &'static str {
        match self {
            ElevationCodec::Legacy => "legacy-lz4-planes",
            ElevationCodec::Quantised { .. } => "quantised-rans",
            ElevationCodec::Laplace { .. } => "quantised-rans-laplace",
            ElevationCodec::InLoop { .. } => "in-loop-rans-laplace",
        }
    }

    /// Encode the LOD 0 samples of a full `(w+1)²` grid of source values.
    /// Id 3 at a nonzero max error predicts from decoded samples: the LOD 1
    /// positions must then hold the parent's decoded samples (the decoder's
    /// LOD 1), not the source's.
    pub fn encode(&self, grid: &[i16], w: usize) -> Payload {
        match self {
            ElevationCodec::Legacy => Payload::lz4(&legacy::encode_elevation(grid, w)),
            // Entropy-coded by the sample codec itself (rANS).
            ElevationCodec::Quantised { max_error } => {
                Payload::unlayered(elevation::encode(grid, w, *max_error))
            }
            ElevationCodec::Laplace { max_error } => {
                Payload::unlayered(elevation2::encode(grid, w, *max_error))
            }
            ElevationCodec::InLoop { max_error } => {
                Payload::unlayered(elevation2::encode_in_loop(grid, w, *max_error))
            }
        }
    }

    /// Decode a record's payload into a `(w+1)²` grid whose LOD 1 positions
    /// hold the parent's decoded samples.
    pub fn decode(
        &self,
        payload: &[u8],
        raw_len: usize,
        w: usize,
        grid: &mut [i16],
    ) -> Result<(), CodecError> {
        let side = w + 1;
        if grid.len() != side * side {
            return Err(CodecError::Grid {
                got: grid.len(),
                expected: side * side,
            });
        }
        let n = crate::lod::elevation_new_samples(w);
        match self {
            ElevationCodec::Legacy => {
                let raw = unlz4(payload, raw_len, 2 * n)?;
                legacy::decode_elevation(&raw, w, grid)
            }
            ElevationCodec::Quantised { max_error } => {
                check_unlayered(payload, raw_len, elevation::max_raw_len(w))?;
                elevation::decode(payload, w, *max_error, grid)
            }
            ElevationCodec::Laplace { max_error } => {
                check_unlayered(payload, raw_len, elevation2::max_raw_len(w))?;
                elevation2::decode(payload, w, *max_error, grid)
            }
            ElevationCodec::InLoop { max_error } => {
                check_unlayered(payload, raw_len, elevation2::max_raw_len(w))?;
                elevation2::decode_in_loop(payload, w, *max_error, grid)
            }
        }
    }
}

/// The colour tree's codec and its parameters (header, format v2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ColourCodec {
    /// Id 0: format v1's lossless PTM deltas under lz4 ([`legacy`]).
    Legacy,
    /// Id 1: the same lossless PTM deltas under zstd.
    Lossless,
    /// Id 2: YCoCg Haar details quantised with these steps, zstd
    /// ([`colour`]).
    Haar(colour::HaarParams),
}

impl ColourCodec {
    /// The codec id written in the header.
    pub fn id(&self) -> u8 {
        match self {
            ColourCodec::Legacy => 0,
            ColourCodec::Lossless => 1,
            ColourCodec::Haar(_) => 2,
        }
    }

    /// From the header's id and parameters `[luma step, chroma step,
    /// target PSNR]`.
    pub fn from_id(id: u8, params: [f32; 3]) -> Result<ColourCodec, CodecError> {
        match id {
            0 | 1 if params == [0.0; 3] => Ok(if id == 0 {
                ColourCodec::Legacy
            } else {
                ColourCodec::Lossless
            }),
            2 => {
                let p = colour::HaarParams {
                    luma_step: params[0],
                    chroma_step: params[1],
                    target_psnr: params[2],
                };
                p.check()?;
                Ok(ColourCodec::Haar(p))
            }
            _ => Err(CodecError::Codec(format!(
                "colour codec id {id} with parameters {params:?} is not one this reader \
                 knows (ids 0-2): written by a newer planet-build?"
            ))),
        }
    }

    /// The parameters written in the header.
    pub fn params(&self) -> [f32; 3] {
        match self {
            ColourCodec::Legacy | ColourCodec::Lossless => [0.0; 3],
            ColourCodec::Haar(p) => [p.luma_step, p.chroma_step, p.target_psnr],
        }
    }

    /// A short name for reports.
    pub fn name(&self) -> &'static str {
        match self {
            ColourCodec::Legacy => "legacy-lz4-ptm",
            ColourCodec::Lossless => "lossless-zstd-ptm",
            ColourCodec::Haar(_) => "haar-ycocg-zstd",
        }
    }

    /// Encode the LOD 0 of a full `w²` colour grid against its filtered
    /// LOD 1 ([`crate::lod::colour_filter`] of it). `height` is the number of
    /// levels below the block (0 for a leaf): the Haar codec refines its
    /// steps by 2 per level above the leaves ([`colour`]). Also returns the
    /// largest channel error of the decoded grid (given this exact LOD 1).
    pub fn encode(&self, full: &[Rgb], lod1: &[Rgb], w: usize, height: u8) -> (Payload, f32) {
        match self {
            ColourCodec::Legacy => (Payload::lz4(&legacy::encode_colour(full, lod1, w)), 0.0),
            ColourCodec::Lossless => (Payload::zstd(&legacy::encode_colour(full, lod1, w)), 0.0),
            ColourCodec::Haar(p) => {
                let (raw, err) = colour::encode(full, lod1, w, p, height);
                (Payload::zstd(&raw), err)
            }
        }
    }

    /// Decode a colour LOD 0 `w²` grid from its LOD 1 and a payload.
    pub fn decode(
        &self,
        payload: &[u8],
        raw_len: usize,
        lod1: &[Rgb],
        w: usize,
    ) -> Result<Vec<Rgb>, CodecError> {
        let h = w / 2;
        if lod1.len() != h * h {
            return Err(CodecError::Grid {
                got: lod1.len(),
                expected: h * h,
            });
        }
        match self {
            ColourCodec::Legacy => {
                let raw = unlz4(payload, raw_len, legacy::colour_payload_len(w))?;
                legacy::decode_colour(&raw, lod1, w)
            }
            ColourCodec::Lossless => {
                let raw = unzstd(payload, raw_len, legacy::colour_payload_len(w))?;
                legacy::decode_colour(&raw, lod1, w)
            }
            ColourCodec::Haar(p) => {
                let raw = unzstd(payload, raw_len, colour::max_raw_len(w))?;
                colour::decode(&raw, lod1, w, p)
            }
        }
    }
}

/// Escape marker of a symbol stream.
const ESCAPE: u8 = 255;

/// A stream of unsigned symbols, one byte each when under 255 (most), else
/// the byte 255 and the value as a little-endian `u32` in a tail that
/// follows all the one-byte symbols. Keeping the rare large values out of
/// the byte stream keeps its statistics clean for the entropy layer.
pub(crate) struct SymbolWriter {
    head: Vec<u8>,
    tail: Vec<u8>,
}

impl SymbolWriter {
    pub(crate) fn with_capacity(n: usize) -> SymbolWriter {
        SymbolWriter {
            head: Vec::with_capacity(n),
            tail: Vec::new(),
        }
    }

    #[inline]
    pub(crate) fn push(&mut self, v: u32) {
        if v < ESCAPE as u32 {
            self.head.push(v as u8);
        } else {
            self.head.push(ESCAPE);
            self.tail.extend_from_slice(&v.to_le_bytes());
        }
    }

    pub(crate) fn finish(mut self) -> Vec<u8> {
        self.head.extend_from_slice(&self.tail);
        self.head
    }
}

/// Reads what [`SymbolWriter`] wrote, `count` symbols.
pub(crate) struct SymbolReader<'a> {
    head: &'a [u8],
    tail: &'a [u8],
    at: usize,
    tail_at: usize,
}

impl<'a> SymbolReader<'a> {
    pub(crate) fn new(raw: &'a [u8], count: usize) -> Result<SymbolReader<'a>, CodecError> {
        if raw.len() < count {
            return Err(CodecError::Length {
                got: raw.len(),
                expected: count,
            });
        }
        let (head, tail) = raw.split_at(count);
        if !tail.len().is_multiple_of(4) {
            return Err(CodecError::Escapes(format!(
                "tail of {} bytes is not whole u32 values",
                tail.len()
            )));
        }
        Ok(SymbolReader {
            head,
            tail,
            at: 0,
            tail_at: 0,
        })
    }

    /// The next symbol (the caller reads exactly `count`).
    #[inline]
    pub(crate) fn next(&mut self) -> Result<u32, CodecError> {
        let b = *self
            .head
            .get(self.at)
            .ok_or_else(|| CodecError::Escapes("read past the symbols".into()))?;
        self.at += 1;
        if b != ESCAPE {
            return Ok(b as u32);
        }
        let t = self
            .tail
            .get(self.tail_at..self.tail_at + 4)
            .ok_or_else(|| CodecError::Escapes("more escapes than tail values".into()))?;
        self.tail_at += 4;
        Ok(u32::from_le_bytes([t[0], t[1], t[2], t[3]]))
    }

    /// Check every tail value was used.
    pub(crate) fn finish(self) -> Result<(), CodecError> {
        if self.tail_at != self.tail.len() || self.at != self.head.len() {
            return Err(CodecError::Escapes(format!(
                "{} of {} tail bytes used",
                self.tail_at,
                self.tail.len()
            )));
        }
        Ok(())
    }
}

/// Zig-zag of a signed 32-bit value.
#[inline]
pub(crate) fn zigzag32(v: i32) -> u32 {
    ((v << 1) ^ (v >> 31)) as u32
}

/// Inverse of [`zigzag32`].
#[inline]
pub(crate) fn unzigzag32(v: u32) -> i32 {
    ((v >> 1) as i32) ^ -((v & 1) as i32)
}

/// One tree's codec: what decoding a record of either tree needs besides
/// its block width and first LOD.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TreeCodec {
    /// An elevation tree's codec.
    Elevation(ElevationCodec),
    /// A colour tree's codec.
    Colour(ColourCodec),
}
