//! The one-file database: superblock, header and self-describing LOD records.
//!
//! Implements the explicit layout of thesis §3.3.2 (see
//! docs/REFERENCES.md): every stored LOD is a record that carries the file offset and size
//! of the next LODs (with `subDepth = 1`, the four children's records), the
//! roots' first LODs are in the header, no sample is stored twice, and the
//! file is written linearly bottom-up. Beyond the thesis, each record starts
//! with a magic and its own length and ends with a CRC-32, so a server checks
//! in O(1) that `(offset, size)` is exactly one record and a client proves
//! what it received is intact; and each pointer to a record carries what the
//! client needs to cull and rank it before requesting it (geometric error and
//! elevation bounds). Byte layouts are in `docs/FORMAT.md`.
//!
//! File layout: `[superblock 64 B][records …][header]`. The superblock is
//! written last, after the header, and the file is built under a temporary
//! name and renamed, so a half-written file never looks valid.

use crate::block::{BlockId, MAX_LEVEL};
use crate::codec::{self, CodecError, ColourCodec, ElevationCodec, Payload};
use crate::cube::Face;
use crate::datum::Datum;
use crate::lod::Rgb;
use std::fs::File;
use std::io::{self, BufWriter, Seek, SeekFrom, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Magic at offset 0 of a database file.
pub const SUPERBLOCK_MAGIC: [u8; 8] = *b"PLANETDB";
/// Length of the superblock.
pub const SUPERBLOCK_LEN: usize = 64;
/// Magic at the start of the header.
pub const HEADER_MAGIC: [u8; 4] = *b"PHDR";
/// Magic at the start of every LOD record.
pub const RECORD_MAGIC: [u8; 4] = *b"PLOD";
/// Format version written and accepted (2: per-tree codecs in the header).
pub const FORMAT_VERSION: u32 = 2;
/// Fixed part of a record before the child references.
pub const RECORD_FIXED_LEN: usize = 24;
/// Bytes of one child reference.
pub const CHILD_REF_LEN: usize = 24;
/// Smallest possible record (no children, empty payload, checksum).
pub const MIN_RECORD_LEN: usize = RECORD_FIXED_LEN + 4;
/// Largest record any valid file holds (a sanity bound for readers).
pub const MAX_RECORD_LEN: usize = 16 << 20;

/// Why bytes are not a valid database, header or record.
#[derive(Debug, Error)]
pub enum FormatError {
    /// An I/O error while reading or writing the file.
    #[error("i/o error: {0}")]
    Io(#[from] io::Error),
    /// The bytes do not start with the expected magic.
    #[error("bad magic: not a {0}")]
    BadMagic(&'static str),
    /// Fewer bytes than the structure needs.
    #[error("truncated {what}: {got} bytes, need {need}")]
    Truncated {
        /// What was being read.
        what: &'static str,
        /// Bytes available.
        got: usize,
        /// Bytes needed.
        need: usize,
    },
    /// The stored length disagrees with the bytes given.
    #[error("length mismatch in {what}: stored {stored}, got {got}")]
    Length {
        /// What was being read.
        what: &'static str,
        /// Length written in the structure.
        stored: u64,
        /// Length available or requested.
        got: u64,
    },
    /// The CRC-32 does not match.
    #[error("checksum mismatch in {0}")]
    Checksum(&'static str),
    /// The format version is not supported.
    #[error(
        "unsupported database format version {0}: this build reads version {FORMAT_VERSION} \
         only; rebuild the database with this planet-build"
    )]
    Version(u32),
    /// A field holds an impossible value.
    #[error("invalid field: {0}")]
    Field(String),
    /// A payload does not decode.
    #[error("payload: {0}")]
    Codec(#[from] CodecError),
    /// A declared length exceeds its limit (checked before allocating).
    #[error("{what} of {len} bytes exceeds the limit of {limit}")]
    TooLarge {
        /// What was being read.
        what: &'static str,
        /// The declared length.
        len: u64,
        /// The limit.
        limit: u64,
    },
}

/// Which of the two linked trees a record belongs to (thesis §4.4.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Tree {
    /// Elevation samples (odd grids, i16).
    Elevation = 0,
    /// Colour samples (even grids, RGB8, filtered LODs).
    Colour = 1,
}

impl Tree {
    fn from_u8(v: u8) -> Result<Tree, FormatError> {
        match v {
            0 => Ok(Tree::Elevation),
            1 => Ok(Tree::Colour),
            _ => Err(FormatError::Field(format!("tree {v}"))),
        }
    }
}

/// A pointer to a record, with what the client needs to cull and rank the
/// block before requesting it.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ChildRef {
    /// File offset of the record.
    pub offset: u64,
    /// Size of the record in bytes.
    pub size: u32,
    /// Geometric error in metres of the block rendered at its first LOD
    /// (without this record): the maximum vertical deviation of that surface
    /// from the full-resolution data under the block. For colour records, the
    /// maximum channel deviation in 8-bit units.
    pub error: f32,
    /// Minimum elevation in metres of the full-resolution data under the block.
    pub min_elevation: f32,
    /// Maximum elevation in metres of the full-resolution data under the block.
    pub max_elevation: f32,
}

impl ChildRef {
    fn write(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.offset.to_le_bytes());
        out.extend_from_slice(&self.size.to_le_bytes());
        out.extend_from_slice(&self.error.to_le_bytes());
        out.extend_from_slice(&self.min_elevation.to_le_bytes());
        out.extend_from_slice(&self.max_elevation.to_le_bytes());
    }

    fn read(b: &[u8]) -> ChildRef {
        ChildRef {
            offset: u64_at(b, 0),
            size: u32_at(b, 8),
            error: f32_at(b, 12),
            min_elevation: f32_at(b, 16),
            max_elevation: f32_at(b, 20),
        }
    }

    fn check(&self, file_len: Option<u64>) -> Result<(), FormatError> {
        let finite = self.error.is_finite()
            && self.error >= 0.0
            && self.min_elevation.is_finite()
            && self.max_elevation.is_finite()
            && self.min_elevation <= self.max_elevation;
        if !finite {
            return Err(FormatError::Field(format!("child reference {self:?}")));
        }
        if (self.size as usize) < MIN_RECORD_LEN || self.size as usize > MAX_RECORD_LEN {
            return Err(FormatError::Field(format!(
                "child record size {}",
                self.size
            )));
        }
        if let Some(len) = file_len {
            let end = self.offset.checked_add(self.size as u64);
            if self.offset < SUPERBLOCK_LEN as u64 || end.is_none_or(|e| e > len) {
                return Err(FormatError::Field(format!(
                    "child record {}+{} outside file of {len} bytes",
                    self.offset, self.size
                )));
            }
        }
        Ok(())
    }
}

#[inline]
fn u16_at(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}
#[inline]
fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}
#[inline]
fn u64_at(b: &[u8], at: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(a)
}
#[inline]
fn f32_at(b: &[u8], at: usize) -> f32 {
    f32::from_bits(u32_at(b, at))
}
#[inline]
fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_bits(u64_at(b, at))
}

fn need(what: &'static str, b: &[u8], n: usize) -> Result<(), FormatError> {
    if b.len() < n {
        Err(FormatError::Truncated {
            what,
            got: b.len(),
            need: n,
        })
    } else {
        Ok(())
    }
}

/// The fixed-size block at offset 0 that locates the header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Superblock {
    /// Offset of the header.
    pub header_offset: u64,
    /// Length of the header including its checksum.
    pub header_len: u32,
    /// Length of the whole file.
    pub file_len: u64,
}

impl Superblock {
    /// Encode to the 64 bytes written at offset 0.
    pub fn encode(&self) -> [u8; SUPERBLOCK_LEN] {
        let mut b = [0u8; SUPERBLOCK_LEN];
        b[0..8].copy_from_slice(&SUPERBLOCK_MAGIC);
        b[8..12].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
        b[16..24].copy_from_slice(&self.header_offset.to_le_bytes());
        b[24..28].copy_from_slice(&self.header_len.to_le_bytes());
        b[32..40].copy_from_slice(&self.file_len.to_le_bytes());
        let crc = crc32fast::hash(&b[..60]);
        b[60..64].copy_from_slice(&crc.to_le_bytes());
        b
    }

    /// Decode and check the first 64 bytes of a file.
    pub fn decode(b: &[u8]) -> Result<Superblock, FormatError> {
        need("superblock", b, SUPERBLOCK_LEN)?;
        if b[0..8] != SUPERBLOCK_MAGIC {
            return Err(FormatError::BadMagic("planet database (superblock)"));
        }
        if crc32fast::hash(&b[..60]) != u32_at(b, 60) {
            return Err(FormatError::Checksum("superblock"));
        }
        let version = u32_at(b, 8);
        if version != FORMAT_VERSION {
            return Err(FormatError::Version(version));
        }
        let sb = Superblock {
            header_offset: u64_at(b, 16),
            header_len: u32_at(b, 24),
            file_len: u64_at(b, 32),
        };
        let end = sb.header_offset.checked_add(sb.header_len as u64);
        if sb.header_offset < SUPERBLOCK_LEN as u64 || end.is_none_or(|e| e > sb.file_len) {
            return Err(FormatError::Field("header outside file".into()));
        }
        Ok(sb)
    }
}

/// One tree's parameters and roots in the header.
#[derive(Debug, Clone, PartialEq)]
pub struct TreeInfo<T, C> {
    /// Block width `W` (samples per side without the odd edge sample).
    pub block_width: u16,
    /// The codec of the tree's record payloads and its parameters.
    pub codec: C,
    /// The deepest level of any block.
    pub max_level: u8,
    /// Per face: the root's LOD 0 record.
    pub root_records: [ChildRef; 6],
    /// Per face: the root's first LOD (elevation: `(W/2+1)²` samples;
    /// colour: the filtered `(W/2)²` grid).
    pub root_first_lods: [Vec<T>; 6],
}

/// The database header: everything a client needs before its first request.
#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    /// The reference surface.
    pub datum: Datum,
    /// Metres per stored elevation unit.
    pub elevation_scale: f32,
    /// Metres added to every scaled elevation.
    pub elevation_offset: f32,
    /// Minimum elevation of the whole database, metres.
    pub min_elevation: f32,
    /// Maximum elevation of the whole database, metres.
    pub max_elevation: f32,
    /// The elevation tree.
    pub elevation: TreeInfo<i16, ElevationCodec>,
    /// The colour tree, if the database has colour.
    pub colour: Option<TreeInfo<Rgb, ColourCodec>>,
    /// Free text: what the database was built from.
    pub description: String,
}

const HEADER_FIXED_LEN: usize = 80;

impl Header {
    /// Elevation in metres of a stored sample.
    #[inline]
    pub fn metres(&self, q: i16) -> f64 {
        self.elevation_offset as f64 + self.elevation_scale as f64 * q as f64
    }

    /// Encode the header (with its trailing CRC-32).
    pub fn encode(&self) -> Vec<u8> {
        let mut b = Vec::with_capacity(64 * 1024);
        b.extend_from_slice(&HEADER_MAGIC);
        b.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        let (kind, a, e2) = match self.datum {
            Datum::Sphere { radius } => (0u8, radius, 0.0),
            Datum::Ellipsoid { a, e2 } => (1u8, a, e2),
        };
        b.push(kind);
        b.extend_from_slice(&[0u8; 7]);
        b.extend_from_slice(&a.to_le_bytes());
        b.extend_from_slice(&e2.to_le_bytes());
        for v in [
            self.elevation_scale,
            self.elevation_offset,
            self.min_elevation,
            self.max_elevation,
        ] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&self.elevation.block_width.to_le_bytes());
        b.push(self.elevation.max_level);
        b.push(self.colour.is_some() as u8);
        let (cw, cl) = self
            .colour
            .as_ref()
            .map_or((0, 0), |c| (c.block_width, c.max_level));
        b.extend_from_slice(&cw.to_le_bytes());
        b.push(cl);
        b.push(0);
        let desc = self.description.as_bytes();
        let desc = &desc[..desc.len().min(u16::MAX as usize)];
        b.extend_from_slice(&(desc.len() as u16).to_le_bytes());
        b.extend_from_slice(&[0u8; 2]);
        b.push(self.elevation.codec.id());
        b.push(0);
        b.extend_from_slice(&self.elevation.codec.param().to_le_bytes());
        let ccodec = self
            .colour
            .as_ref()
            .map_or(ColourCodec::Legacy, |c| c.codec);
        b.push(ccodec.id());
        b.extend_from_slice(&[0u8; 3]);
        for v in ccodec.params() {
            b.extend_from_slice(&v.to_le_bytes());
        }
        debug_assert_eq!(b.len(), HEADER_FIXED_LEN);
        for f in 0..6 {
            self.elevation.root_records[f].write(&mut b);
            let raw: Vec<u8> = self.elevation.root_first_lods[f]
                .iter()
                .flat_map(|v| v.to_le_bytes())
                .collect();
            let c = codec::compress(&raw);
            b.extend_from_slice(&(c.len() as u32).to_le_bytes());
            b.extend_from_slice(&c);
        }
        if let Some(colour) = &self.colour {
            for f in 0..6 {
                colour.root_records[f].write(&mut b);
                let raw: Vec<u8> = colour.root_first_lods[f]
                    .iter()
                    .flatten()
                    .copied()
                    .collect();
                let c = codec::compress(&raw);
                b.extend_from_slice(&(c.len() as u32).to_le_bytes());
                b.extend_from_slice(&c);
            }
        }
        b.extend_from_slice(desc);
        let crc = crc32fast::hash(&b);
        b.extend_from_slice(&crc.to_le_bytes());
        b
    }

    /// Decode and check a header. `file_len`, when known, bounds the root
    /// record references.
    pub fn decode(b: &[u8], file_len: Option<u64>) -> Result<Header, FormatError> {
        need("header", b, HEADER_FIXED_LEN + 4)?;
        if b[0..4] != HEADER_MAGIC {
            return Err(FormatError::BadMagic("planet database header"));
        }
        let body = &b[..b.len() - 4];
        if crc32fast::hash(body) != u32_at(b, b.len() - 4) {
            return Err(FormatError::Checksum("header"));
        }
        let version = u32_at(b, 4);
        if version != FORMAT_VERSION {
            return Err(FormatError::Version(version));
        }
        let datum = match b[8] {
            0 => Datum::Sphere {
                radius: f64_at(b, 16),
            },
            1 => Datum::Ellipsoid {
                a: f64_at(b, 16),
                e2: f64_at(b, 24),
            },
            k => return Err(FormatError::Field(format!("datum kind {k}"))),
        };
        if !datum.is_valid() {
            return Err(FormatError::Field(format!("datum {datum:?}")));
        }
        let elevation_scale = f32_at(b, 32);
        let elevation_offset = f32_at(b, 36);
        let min_elevation = f32_at(b, 40);
        let max_elevation = f32_at(b, 44);
        let scale_ok = elevation_scale.is_finite() && elevation_scale > 0.0;
        let range_ok = min_elevation.is_finite()
            && max_elevation.is_finite()
            && min_elevation <= max_elevation;
        if !scale_ok || !elevation_offset.is_finite() || !range_ok {
            return Err(FormatError::Field("elevation scale or range".into()));
        }
        let ew = u16_at(b, 48);
        let el = b[50];
        let has_colour = b[51];
        let cw = u16_at(b, 52);
        let cl = b[54];
        let desc_len = u16_at(b, 56) as usize;
        if b[61] != 0 || b[65..68] != [0, 0, 0] {
            return Err(FormatError::Field("reserved codec bytes".into()));
        }
        let ecodec = ElevationCodec::from_id(b[60], u16_at(b, 62))?;
        let ccodec = ColourCodec::from_id(b[64], [f32_at(b, 68), f32_at(b, 72), f32_at(b, 76)])?;
        if has_colour == 0 && ccodec != ColourCodec::Legacy {
            return Err(FormatError::Field("colour codec without colour".into()));
        }
        let check_width = |w: u16, what: &str| {
            if w < 2 || !w.is_multiple_of(2) || w > 4096 {
                Err(FormatError::Field(format!("{what} block width {w}")))
            } else {
                Ok(())
            }
        };
        check_width(ew, "elevation")?;
        if el > MAX_LEVEL || cl > MAX_LEVEL || has_colour > 1 {
            return Err(FormatError::Field("max level or colour flag".into()));
        }
        let mut at = HEADER_FIXED_LEN;
        let mut read_root = |raw_len: usize| -> Result<(ChildRef, Vec<u8>), FormatError> {
            need("header root", body, at + CHILD_REF_LEN + 4)?;
            let r = ChildRef::read(&body[at..]);
            r.check(file_len)?;
            let clen = u32_at(body, at + CHILD_REF_LEN) as usize;
            at += CHILD_REF_LEN + 4;
            need("header root LOD", body, at + clen)?;
            let raw = codec::decompress(&body[at..at + clen], raw_len)?;
            at += clen;
            Ok((r, raw))
        };
        let ehalf = ew as usize / 2 + 1;
        let mut elevation = TreeInfo {
            block_width: ew,
            codec: ecodec,
            max_level: el,
            root_records: [ChildRef::default(); 6],
            root_first_lods: Default::default(),
        };
        for f in 0..6 {
            let (r, raw) = read_root(ehalf * ehalf * 2)?;
            elevation.root_records[f] = r;
            elevation.root_first_lods[f] = raw
                .chunks_exact(2)
                .map(|c| i16::from_le_bytes([c[0], c[1]]))
                .collect();
        }
        let colour = if has_colour == 1 {
            check_width(cw, "colour")?;
            let chalf = cw as usize / 2;
            let mut t = TreeInfo {
                block_width: cw,
                codec: ccodec,
                max_level: cl,
                root_records: [ChildRef::default(); 6],
                root_first_lods: Default::default(),
            };
            for f in 0..6 {
                let (r, raw) = read_root(chalf * chalf * 3)?;
                t.root_records[f] = r;
                t.root_first_lods[f] = raw.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            }
            Some(t)
        } else {
            None
        };
        if body.len() != at + desc_len {
            return Err(FormatError::Length {
                what: "header",
                stored: (at + desc_len) as u64,
                got: body.len() as u64,
            });
        }
        let description = String::from_utf8_lossy(&body[at..]).into_owned();
        Ok(Header {
            datum,
            elevation_scale,
            elevation_offset,
            min_elevation,
            max_elevation,
            elevation,
            colour,
            description,
        })
    }
}

/// The decoded fixed part of a record and its child references.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordHeader {
    /// The tree the record belongs to.
    pub tree: Tree,
    /// The block whose LOD 0 this record holds.
    pub block: BlockId,
    /// Length of the payload after the entropy layer (lz4 or zstd), before
    /// the sample codec; checked against the codec's limit before decoding.
    pub raw_len: u32,
    /// The children's records (empty for a leaf).
    pub children: Vec<ChildRef>,
}

/// A checked record borrowed from a buffer.
#[derive(Debug, Clone, PartialEq)]
pub struct Record<'a> {
    /// The record's header fields.
    pub header: RecordHeader,
    /// The entropy-coded payload.
    pub payload: &'a [u8],
}

impl Record<'_> {
    /// Decode an elevation payload into a `(w+1)²` grid whose LOD 1
    /// positions hold the parent's decoded samples.
    pub fn decode_elevation(
        &self,
        codec: &ElevationCodec,
        w: usize,
        grid: &mut [i16],
    ) -> Result<(), FormatError> {
        Ok(codec.decode(self.payload, self.header.raw_len as usize, w, grid)?)
    }

    /// Decode a colour payload into a `w²` grid from its decoded LOD 1.
    pub fn decode_colour(
        &self,
        codec: &ColourCodec,
        lod1: &[Rgb],
        w: usize,
    ) -> Result<Vec<Rgb>, FormatError> {
        Ok(codec.decode(self.payload, self.header.raw_len as usize, lod1, w)?)
    }
}

/// Encode a record from its encoded payload ([`ElevationCodec::encode`],
/// [`ColourCodec::encode`]).
pub fn encode_record(
    tree: Tree,
    block: BlockId,
    children: &[ChildRef],
    payload: &Payload,
) -> Vec<u8> {
    let raw_len = payload.raw_len;
    let payload = &payload.bytes;
    let len = RECORD_FIXED_LEN + CHILD_REF_LEN * children.len() + payload.len() + 4;
    let mut b = Vec::with_capacity(len);
    b.extend_from_slice(&RECORD_MAGIC);
    b.extend_from_slice(&(len as u32).to_le_bytes());
    b.push(tree as u8);
    b.push(block.face.index());
    b.push(block.level);
    b.push(children.len() as u8);
    b.extend_from_slice(&block.x.to_le_bytes());
    b.extend_from_slice(&block.y.to_le_bytes());
    b.extend_from_slice(&raw_len.to_le_bytes());
    for c in children {
        c.write(&mut b);
    }
    b.extend_from_slice(payload);
    let crc = crc32fast::hash(&b);
    b.extend_from_slice(&crc.to_le_bytes());
    b
}

/// O(1) check of the first 8 bytes at a record offset: the magic, and the
/// record's own length (returned). A server compares it with the requested
/// size before reading anything else.
pub fn peek_record_len(first8: &[u8]) -> Result<u32, FormatError> {
    need("record", first8, 8)?;
    if first8[0..4] != RECORD_MAGIC {
        return Err(FormatError::BadMagic("LOD record"));
    }
    let len = u32_at(first8, 4);
    if (len as usize) < MIN_RECORD_LEN || len as usize > MAX_RECORD_LEN {
        return Err(FormatError::Field(format!("record length {len}")));
    }
    Ok(len)
}

/// Whether the record's trailing CRC-32 matches (no other check).
pub fn record_checksum_ok(bytes: &[u8]) -> bool {
    bytes.len() >= MIN_RECORD_LEN
        && crc32fast::hash(&bytes[..bytes.len() - 4]) == u32_at(bytes, bytes.len() - 4)
}

/// The stored length of the record in `bytes`, which must be all of it.
fn whole_record_len(bytes: &[u8]) -> Result<usize, FormatError> {
    let len = peek_record_len(bytes)? as usize;
    if len != bytes.len() {
        return Err(FormatError::Length {
            what: "record",
            stored: len as u64,
            got: bytes.len() as u64,
        });
    }
    Ok(len)
}

/// Parse and fully check a record: magic, length equal to `bytes.len()`,
/// checksum, and field ranges. `file_len`, when known, bounds the children.
pub fn parse_record(bytes: &[u8], file_len: Option<u64>) -> Result<Record<'_>, FormatError> {
    let len = whole_record_len(bytes)?;
    if !record_checksum_ok(bytes) {
        return Err(FormatError::Checksum("record"));
    }
    let tree = Tree::from_u8(bytes[8])?;
    let face =
        Face::new(bytes[9]).ok_or_else(|| FormatError::Field(format!("face {}", bytes[9])))?;
    let level = bytes[10];
    let count = bytes[11] as usize;
    let block = BlockId::new(face, level, u32_at(bytes, 12), u32_at(bytes, 16))
        .ok_or_else(|| FormatError::Field("block coordinates".into()))?;
    let raw_len = u32_at(bytes, 20);
    if raw_len as usize > MAX_RECORD_LEN * 4 {
        return Err(FormatError::Field(format!("raw length {raw_len}")));
    }
    let children = read_child_refs(bytes, file_len)?;
    let payload_at = RECORD_FIXED_LEN + CHILD_REF_LEN * count;
    Ok(Record {
        header: RecordHeader {
            tree,
            block,
            raw_len,
            children,
        },
        payload: &bytes[payload_at..len - 4],
    })
}

/// Marks a child whose table the server could not give (its record failed
/// to read or its checksum): the client learns nothing about it early.
pub const CHILD_TABLE_UNKNOWN: u8 = 0xff;

/// One child's full table in a trailer: its count byte and four references.
pub const CHILD_TABLE_LEN: usize = 1 + 4 * CHILD_REF_LEN;

/// Largest trailer of child tables: four children, each a full table.
pub const MAX_CHILD_TABLES_LEN: usize = 4 * CHILD_TABLE_LEN;

/// The child references of a record whose checksum was already checked:
/// the fixed fields and the references only (no CRC, no payload), each
/// reference checked against `file_len` when known.
pub fn record_child_refs(
    bytes: &[u8],
    file_len: Option<u64>,
) -> Result<Vec<ChildRef>, FormatError> {
    whole_record_len(bytes)?;
    read_child_refs(bytes, file_len)
}

/// The child count and references of a record of checked length: 0 or 4
/// children, room for them and the CRC, each reference checked.
fn read_child_refs(bytes: &[u8], file_len: Option<u64>) -> Result<Vec<ChildRef>, FormatError> {
    let count = bytes[11] as usize;
    if count != 0 && count != 4 {
        return Err(FormatError::Field(format!("{count} children")));
    }
    need(
        "record children",
        bytes,
        RECORD_FIXED_LEN + CHILD_REF_LEN * count + 4,
    )?;
    (0..count)
        .map(|k| {
            let c = ChildRef::read(&bytes[RECORD_FIXED_LEN + CHILD_REF_LEN * k..]);
            c.check(file_len).map(|()| c)
        })
        .collect()
}

/// Encodes the **child tables** of a record's children, the trailer of the
/// protocol's `LodRefsRequest` (docs/PROTOCOL.md §4.8, after Google Earth's
/// bulk metadata, docs/REFERENCES.md): for each child `k` of the record, in
/// order, one count byte (`0` leaf, `4`, or [`CHILD_TABLE_UNKNOWN`]), then
/// that many 24-byte [child references](ChildRef) (the grandchildren's).
pub fn encode_child_tables(tables: &[Option<Vec<ChildRef>>]) -> Vec<u8> {
    let mut out = Vec::with_capacity(tables.len() * (1 + 4 * CHILD_REF_LEN));
    for t in tables {
        match t {
            Some(refs) if refs.is_empty() || refs.len() == 4 => {
                out.push(refs.len() as u8);
                for r in refs {
                    r.write(&mut out);
                }
            }
            _ => out.push(CHILD_TABLE_UNKNOWN),
        }
    }
    out
}

/// The trailer of child tables for `record` (whose checksum the caller has
/// checked), reading each child's record with `read`: a child whose read
/// fails (`None`), whose checksum fails or whose references do not check
/// is marked unknown. What a server answers to `LodRefsRequest`
/// (`floors` `None`) and to `LodRefsAboveRequest` (docs/PROTOCOL.md §4.9):
/// there a child's table of four references whose largest `error` is under
/// `floors[k]` (metres, the record's child order) is marked unknown too, as
/// the client said it would not use it; a leaf's empty table is kept.
pub fn child_tables_for<B: AsRef<[u8]>>(
    record: &[u8],
    file_len: Option<u64>,
    floors: Option<[f32; 4]>,
    mut read: impl FnMut(&ChildRef) -> Option<B>,
) -> Result<Vec<u8>, FormatError> {
    let children = record_child_refs(record, file_len)?;
    let tables: Vec<Option<Vec<ChildRef>>> = children
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let b = read(c)?;
            let b = b.as_ref();
            let refs = (b.len() == c.size as usize && record_checksum_ok(b))
                .then(|| record_child_refs(b, file_len).ok())
                .flatten()?;
            // Only a request with floors pays for comparing the errors.
            match floors.and_then(|f| f.get(k).copied()) {
                Some(f) if !refs.is_empty() && refs.iter().all(|r| r.error < f) => None,
                _ => Some(refs),
            }
        })
        .collect();
    Ok(encode_child_tables(&tables))
}

/// Parses a trailer of [`encode_child_tables`] for a record with `count`
/// children: exactly `count` tables and no byte after them, every reference
/// checked as a record's own (finite, sizes and `file_len`). `None` is a
/// child the server marked unknown.
pub fn parse_child_tables(
    bytes: &[u8],
    count: usize,
    file_len: Option<u64>,
) -> Result<Vec<Option<Vec<ChildRef>>>, FormatError> {
    let mut at = 0usize;
    let mut out = Vec::with_capacity(count);
    for _ in 0..count {
        need("child tables", bytes, at + 1)?;
        let n = bytes[at];
        at += 1;
        match n {
            CHILD_TABLE_UNKNOWN => out.push(None),
            0 | 4 => {
                let n = n as usize;
                need("child tables", bytes, at + n * CHILD_REF_LEN)?;
                let mut refs = Vec::with_capacity(n);
                for k in 0..n {
                    let c = ChildRef::read(&bytes[at + k * CHILD_REF_LEN..]);
                    c.check(file_len)?;
                    refs.push(c);
                }
                at += n * CHILD_REF_LEN;
                out.push(Some(refs));
            }
            n => return Err(FormatError::Field(format!("child table of {n} references"))),
        }
    }
    if at != bytes.len() {
        return Err(FormatError::Length {
            what: "child tables",
            stored: at as u64,
            got: bytes.len() as u64,
        });
    }
    Ok(out)
}

/// Writes a database linearly under a temporary name; [`DbWriter::finish`]
/// appends the header, writes the superblock last, syncs and renames.
///
/// The temporary name is unique (`DEST.PID.N.tmp`, created exclusively), so
/// two builds of the same output never write one file; the last to finish
/// wins whole. `finish` removes the temporary on error and, after the
/// rename, syncs the directory so the new name survives a crash. A killed
/// build leaves the old output intact (only a stray temporary).
pub struct DbWriter {
    file: BufWriter<File>,
    tmp: PathBuf,
    dest: PathBuf,
    pos: u64,
}

/// Writers created by this process (part of the temporary names).
static WRITERS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

impl DbWriter {
    /// Start writing `dest` (under a unique temporary name until finished).
    pub fn create(dest: &Path) -> io::Result<DbWriter> {
        let (tmp, f) = loop {
            let n = WRITERS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let mut tmp = dest.as_os_str().to_owned();
            tmp.push(format!(".{}.{n}.tmp", std::process::id()));
            let tmp = PathBuf::from(tmp);
            match File::options().write(true).create_new(true).open(&tmp) {
                Ok(f) => break (tmp, f),
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(e),
            }
        };
        let mut file = BufWriter::with_capacity(1 << 20, f);
        if let Err(e) = file.write_all(&[0u8; SUPERBLOCK_LEN]) {
            drop(file);
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
        Ok(DbWriter {
            file,
            tmp,
            dest: dest.to_path_buf(),
            pos: SUPERBLOCK_LEN as u64,
        })
    }

    /// The temporary file being written.
    pub fn temporary_path(&self) -> &Path {
        &self.tmp
    }

    /// Bytes written so far.
    pub fn position(&self) -> u64 {
        self.pos
    }

    /// Append an encoded record; returns its `(offset, size)`.
    pub fn append(&mut self, record: &[u8]) -> io::Result<(u64, u32)> {
        let at = self.pos;
        self.file.write_all(record)?;
        self.pos += record.len() as u64;
        Ok((at, record.len() as u32))
    }

    /// Append the header, write the superblock, sync and rename into place,
    /// then sync the directory. Returns the final file length. On error the
    /// temporary is removed.
    pub fn finish(self, header: &Header) -> io::Result<u64> {
        let tmp = self.tmp.clone();
        let r = self.finish_inner(header);
        if r.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        r
    }

    fn finish_inner(mut self, header: &Header) -> io::Result<u64> {
        let h = header.encode();
        if h.len() > MAX_HEADER_LEN {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!(
                    "header of {} bytes exceeds the format's limit of {MAX_HEADER_LEN}",
                    h.len()
                ),
            ));
        }
        let header_offset = self.pos;
        self.file.write_all(&h)?;
        let file_len = header_offset + h.len() as u64;
        let sb = Superblock {
            header_offset,
            header_len: h.len() as u32,
            file_len,
        };
        self.file.flush()?;
        let mut f = self.file.into_inner().map_err(|e| e.into_error())?;
        f.sync_all()?;
        f.seek(SeekFrom::Start(0))?;
        f.write_all(&sb.encode())?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&self.tmp, &self.dest)?;
        // The rename is durable once the directory is synced (POSIX).
        #[cfg(unix)]
        {
            let dir = match self.dest.parent() {
                Some(d) if !d.as_os_str().is_empty() => d,
                _ => Path::new("."),
            };
            File::open(dir)?.sync_all()?;
        }
        Ok(file_len)
    }

    /// Remove the temporary file (on error paths).
    pub fn abandon(self) {
        let tmp = self.tmp.clone();
        drop(self);
        let _ = std::fs::remove_file(tmp);
    }
}

/// The largest header a database file may declare (8 MiB, the same as the
/// protocol's `MAX_HEADER_LEN`, since the header travels whole in the
/// Welcome; a server test holds the two equal).
pub const MAX_HEADER_LEN: usize = 8 * 1024 * 1024;

/// The checked superblock and header of a database file.
#[derive(Debug, Clone)]
pub struct ValidatedHead {
    /// The checked superblock.
    pub superblock: Superblock,
    /// The decoded header.
    pub header: Header,
    /// The header's bytes as stored (sent to clients in the welcome).
    pub header_bytes: Vec<u8>,
}

/// Reads and checks the superblock and header of an open database file of
/// `len` bytes (its length now): the file must hold a superblock that
/// places the header inside it, the superblock's length must equal `len`,
/// the header's declared length must be at most `max_header_len` (checked
/// before anything is allocated), and the header must decode. The one validation of
/// a database's head, for `DbFile::open` and the server.
pub fn read_validated_head(
    file: &File,
    len: u64,
    max_header_len: usize,
) -> Result<ValidatedHead, FormatError> {
    if len < SUPERBLOCK_LEN as u64 {
        return Err(FormatError::Truncated {
            what: "database file",
            got: len as usize,
            need: SUPERBLOCK_LEN,
        });
    }
    let mut sb = [0u8; SUPERBLOCK_LEN];
    file.read_exact_at(&mut sb, 0)?;
    let superblock = Superblock::decode(&sb)?;
    if superblock.file_len != len {
        return Err(FormatError::Length {
            what: "database file",
            stored: superblock.file_len,
            got: len,
        });
    }
    if superblock.header_len as usize > max_header_len {
        return Err(FormatError::TooLarge {
            what: "header",
            len: u64::from(superblock.header_len),
            limit: max_header_len as u64,
        });
    }
    // `Superblock::decode` checked that the header lies inside `file_len`,
    // which is `len`.
    let mut header_bytes = vec![0u8; superblock.header_len as usize];
    file.read_exact_at(&mut header_bytes, superblock.header_offset)?;
    let header = Header::decode(&header_bytes, Some(len))?;
    Ok(ValidatedHead {
        superblock,
        header,
        header_bytes,
    })
}

/// A record of the elevation tree that [`DbFile::walk_elevation`] could
/// not read, parse or decode.
#[derive(Debug, Error)]
#[error("elevation record at offset {offset}: {source}")]
pub struct WalkError {
    /// The record's offset.
    pub offset: u64,
    /// What was wrong.
    #[source]
    pub source: FormatError,
}

/// One record met by [`DbFile::walk_elevation`].
pub struct ElevationVisit<'a> {
    /// The block.
    pub block: BlockId,
    /// The record's bytes as stored.
    pub bytes: &'a [u8],
    /// The record, parsed and checked.
    pub record: &'a Record<'a>,
    /// The block's `(w+1)²` grid before its record: LOD 1 placed (the
    /// parent's decoded samples; the root's from the header).
    pub lod1: &'a [i16],
    /// The same grid after the record: the block's full decoded samples.
    pub full: &'a [i16],
}

/// A database file opened for reading with positioned reads.
pub struct DbFile {
    file: File,
    /// The checked superblock.
    pub superblock: Superblock,
    /// The decoded header.
    pub header: Header,
    /// The header's bytes as stored (sent to clients in the welcome).
    pub header_bytes: Vec<u8>,
}

impl DbFile {
    /// Open and check the superblock and header. A truncated or foreign file
    /// is refused with a typed error.
    pub fn open(path: &Path) -> Result<DbFile, FormatError> {
        let file = File::open(path)?;
        let len = file.metadata()?.len();
        let ValidatedHead {
            superblock,
            header,
            header_bytes,
        } = read_validated_head(&file, len, MAX_HEADER_LEN)?;
        Ok(DbFile {
            file,
            superblock,
            header,
            header_bytes,
        })
    }

    /// Read the bytes of one record (checked to be exactly one record).
    pub fn read_record(&self, r: &ChildRef) -> Result<Vec<u8>, FormatError> {
        let end = r.offset.checked_add(r.size as u64);
        if end.is_none_or(|e| e > self.superblock.header_offset) || r.offset < SUPERBLOCK_LEN as u64
        {
            return Err(FormatError::Field(format!(
                "record {}+{} out of range",
                r.offset, r.size
            )));
        }
        let mut buf = vec![0u8; r.size as usize];
        self.file.read_exact_at(&mut buf, r.offset)?;
        Ok(buf)
    }

    /// Walk the elevation tree depth-first from the six roots, a parent
    /// before its children, decoding each record from its parent's decoded
    /// samples, and call `f` with each; `f` returns `false` to stop the
    /// walk.
    pub fn walk_elevation(
        &self,
        mut f: impl FnMut(&ElevationVisit<'_>) -> bool,
    ) -> Result<(), WalkError> {
        let h = &self.header.elevation;
        let w = h.block_width as usize;
        let side = w + 1;
        for (fi, face) in Face::ALL.iter().enumerate() {
            let mut lod1 = vec![0i16; side * side];
            crate::lod::elevation_place_first_lod(&h.root_first_lods[fi], w, &mut lod1);
            let mut stack = vec![(BlockId::root(*face), h.root_records[fi], lod1)];
            while let Some((block, r, lod1)) = stack.pop() {
                let at = |source| WalkError {
                    offset: r.offset,
                    source,
                };
                let bytes = self.read_record(&r).map_err(at)?;
                let record = parse_record(&bytes, None).map_err(at)?;
                let mut full = lod1.clone();
                record
                    .decode_elevation(&h.codec, w, &mut full)
                    .map_err(at)?;
                let visit = ElevationVisit {
                    block,
                    bytes: &bytes,
                    record: &record,
                    lod1: &lod1,
                    full: &full,
                };
                if !f(&visit) {
                    return Ok(());
                }
                for (k, c) in record.header.children.iter().enumerate() {
                    let mut child = vec![0i16; side * side];
                    crate::lod::split_elevation(&full, w, k, &mut child);
                    stack.push((block.child(k), *c, child));
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn child_tables_round_trip_and_reject_garbage() {
        let r = |o: u64| ChildRef {
            offset: o,
            size: 40,
            error: 1.5,
            min_elevation: -3.0,
            max_elevation: 9.0,
        };
        let tables = vec![
            Some(vec![r(64), r(104), r(144), r(184)]),
            Some(vec![]),
            None,
            Some(vec![r(224), r(264), r(304), r(344)]),
        ];
        let b = encode_child_tables(&tables);
        assert_eq!(b.len(), 4 + 8 * CHILD_REF_LEN);
        assert!(b.len() <= MAX_CHILD_TABLES_LEN);
        assert_eq!(parse_child_tables(&b, 4, Some(1000)).unwrap(), tables);
        // Too few tables, a byte too many, a bad count, a reference past
        // the file's end: all errors.
        assert!(parse_child_tables(&b, 5, None).is_err());
        let mut longer = b.clone();
        longer.push(0);
        assert!(parse_child_tables(&longer, 4, None).is_err());
        let mut bad = b.clone();
        bad[0] = 3;
        assert!(parse_child_tables(&bad, 4, None).is_err());
        assert!(parse_child_tables(&b, 4, Some(300)).is_err());
        for cut in 0..b.len() {
            assert!(parse_child_tables(&b[..cut], 4, None).is_err());
        }
        // A record's references read back without its checksum.
        let rec = encode_record(
            Tree::Elevation,
            BlockId::new(Face::ALL[0], 1, 0, 1).unwrap(),
            &[r(64), r(104), r(144), r(184)],
            &crate::codec::Payload {
                raw_len: 3,
                bytes: vec![1, 2, 3],
            },
        );
        assert_eq!(record_child_refs(&rec, None).unwrap()[1], r(104));
        assert!(record_child_refs(&rec[..rec.len() - 1], None).is_err());
    }

    #[test]
    fn child_tables_above_floors_leave_out_the_tables_under_them() {
        let payload = crate::codec::Payload {
            raw_len: 3,
            bytes: vec![1, 2, 3],
        };
        let grand = |o: u64, error: f32| ChildRef {
            offset: o,
            size: 40,
            error,
            min_elevation: -3.0,
            max_elevation: 9.0,
        };
        let parent_id = BlockId::new(Face::ALL[0], 1, 0, 1).unwrap();
        // Child k's grandchildren's errors: the largest is 8, 2, 0.5 and
        // none (a leaf).
        let errors: [&[f32]; 4] = [&[1.0, 8.0, 0.0, 3.0], &[2.0, 2.0, 0.5, 1.0], &[0.5; 4], &[]];
        let mut file: Vec<(ChildRef, Vec<u8>)> = vec![];
        let mut at = 1000u64;
        for (k, e) in errors.iter().enumerate() {
            let refs: Vec<ChildRef> = e
                .iter()
                .enumerate()
                .map(|(i, &x)| grand(64 + 40 * i as u64, x))
                .collect();
            let rec = encode_record(Tree::Elevation, parent_id.child(k), &refs, &payload);
            let r = ChildRef {
                offset: at,
                size: rec.len() as u32,
                error: 9.0,
                min_elevation: -3.0,
                max_elevation: 9.0,
            };
            at += rec.len() as u64;
            file.push((r, rec));
        }
        let children: Vec<ChildRef> = file.iter().map(|f| f.0).collect();
        let parent = encode_record(Tree::Elevation, parent_id, &children, &payload);
        let read = |c: &ChildRef| file.iter().find(|f| f.0 == *c).map(|f| f.1.clone());
        let tables = |floors| {
            let b = child_tables_for(&parent, None, floors, read).unwrap();
            parse_child_tables(&b, 4, None).unwrap()
        };
        let all = tables(None);
        assert!(all[..3]
            .iter()
            .all(|t| t.as_ref().is_some_and(|t| t.len() == 4)));
        assert_eq!(all[3], Some(vec![]));
        // A floor of 0 is the LodRefsRequest's answer.
        assert_eq!(tables(Some([0.0; 4])), all);
        // Reached (8 ≥ 8, 2 ≥ 1.5) or not (0.5 < 0.6); a leaf whatever its
        // floor.
        let some = tables(Some([8.0, 1.5, 0.6, f32::INFINITY]));
        assert_eq!(some[0], all[0]);
        assert_eq!(some[1], all[1]);
        assert_eq!(some[2], None);
        assert_eq!(some[3], Some(vec![]));
        let none = tables(Some([f32::INFINITY; 4]));
        assert_eq!(none, vec![None, None, None, Some(vec![])]);
        // Each left-out table is one byte (0xff) instead of 97.
        let b = child_tables_for(&parent, None, Some([f32::INFINITY; 4]), read).unwrap();
        assert_eq!(
            b,
            vec![
                CHILD_TABLE_UNKNOWN,
                CHILD_TABLE_UNKNOWN,
                CHILD_TABLE_UNKNOWN,
                0
            ]
        );
    }

    fn sample_header(colour: bool) -> Header {
        let ew = 8u16;
        let eh = (ew as usize / 2 + 1).pow(2);
        let r = ChildRef {
            offset: 64,
            size: 100,
            error: 3.5,
            min_elevation: -10.0,
            max_elevation: 20.0,
        };
        Header {
            datum: Datum::WGS84,
            elevation_scale: 1.0,
            elevation_offset: 0.0,
            min_elevation: -10.0,
            max_elevation: 20.0,
            elevation: TreeInfo {
                block_width: ew,
                codec: ElevationCodec::Quantised { max_error: 2 },
                max_level: 3,
                root_records: [r; 6],
                root_first_lods: std::array::from_fn(|f| (0..eh).map(|v| (v * f) as i16).collect()),
            },
            colour: colour.then(|| TreeInfo {
                block_width: 16,
                codec: ColourCodec::Haar(codec::colour::HaarParams::for_psnr(42.0)),
                max_level: 2,
                root_records: [r; 6],
                root_first_lods: std::array::from_fn(|f| vec![[f as u8, 2, 3]; 64]),
            }),
            description: "test".into(),
        }
    }

    #[test]
    fn header_round_trip_and_corruption() {
        for colour in [false, true] {
            let h = sample_header(colour);
            let b = h.encode();
            assert_eq!(Header::decode(&b, Some(1000)).unwrap(), h);
            for i in 0..b.len() {
                let mut c = b.clone();
                c[i] ^= 0x10;
                assert!(
                    Header::decode(&c, Some(1000)).is_err(),
                    "flip at {i} accepted"
                );
            }
            assert!(Header::decode(&b[..b.len() - 1], Some(1000)).is_err());
        }
    }

    #[test]
    fn record_round_trip_and_corruption() {
        let block = BlockId::new(Face::new(4).unwrap(), 3, 5, 2).unwrap();
        let kids = [ChildRef {
            offset: 64,
            size: 40,
            error: 1.0,
            min_elevation: 0.0,
            max_elevation: 1.0,
        }; 4];
        let w = 8;
        let grid: Vec<i16> = (0..81).map(|v| (v * v % 91) as i16 - 40).collect();
        let codec = ElevationCodec::Quantised { max_error: 0 };
        let b = encode_record(Tree::Elevation, block, &kids, &codec.encode(&grid, w));
        let r = parse_record(&b, Some(10_000)).unwrap();
        assert_eq!(r.header.block, block);
        assert_eq!(r.header.children, kids.to_vec());
        let mut dec = vec![0i16; 81];
        crate::lod::elevation_place_first_lod(
            &crate::lod::elevation_first_lod(&grid, w),
            w,
            &mut dec,
        );
        r.decode_elevation(&codec, w, &mut dec).unwrap();
        assert_eq!(dec, grid);
        assert_eq!(peek_record_len(&b).unwrap() as usize, b.len());
        for i in 0..b.len() {
            let mut c = b.clone();
            c[i] ^= 0x01;
            assert!(
                parse_record(&c, Some(10_000)).is_err(),
                "flip at {i} accepted"
            );
        }
        assert!(parse_record(&b[..b.len() - 1], None).is_err());
        assert!(
            parse_record(&b, Some(100)).is_err(),
            "children past end of file"
        );
    }

    #[test]
    fn version_1_is_refused_with_a_rebuild_hint() {
        let mut b = sample_header(true).encode();
        b[4..8].copy_from_slice(&1u32.to_le_bytes());
        let n = b.len();
        let crc = crc32fast::hash(&b[..n - 4]);
        b[n - 4..].copy_from_slice(&crc.to_le_bytes());
        let e = Header::decode(&b, Some(1000)).unwrap_err();
        assert!(matches!(e, FormatError::Version(1)), "{e:?}");
        assert!(e.to_string().contains("version 1") && e.to_string().contains("rebuild"));
        let mut sb = Superblock {
            header_offset: 64,
            header_len: 100,
            file_len: 1000,
        }
        .encode();
        sb[8..12].copy_from_slice(&1u32.to_le_bytes());
        let crc = crc32fast::hash(&sb[..60]);
        sb[60..64].copy_from_slice(&crc.to_le_bytes());
        assert!(matches!(
            Superblock::decode(&sb),
            Err(FormatError::Version(1))
        ));
    }

    #[test]
    fn header_codecs_round_trip() {
        for (e, c) in [
            (ElevationCodec::Legacy, ColourCodec::Legacy),
            (
                ElevationCodec::Quantised { max_error: 0 },
                ColourCodec::Lossless,
            ),
            (
                ElevationCodec::Quantised { max_error: 7 },
                ColourCodec::Haar(codec::colour::HaarParams::for_psnr(38.0)),
            ),
            (
                ElevationCodec::Laplace { max_error: 1 },
                ColourCodec::Haar(codec::colour::HaarParams::for_psnr(42.0)),
            ),
            (
                ElevationCodec::InLoop { max_error: 16_383 },
                ColourCodec::Haar(codec::colour::HaarParams::for_psnr(42.0)),
            ),
        ] {
            let mut h = sample_header(true);
            h.elevation.codec = e;
            if let Some(t) = h.colour.as_mut() {
                t.codec = c;
            }
            assert_eq!(Header::decode(&h.encode(), Some(1000)).unwrap(), h);
        }
    }

    /// A header naming an elevation codec this reader does not know (a
    /// newer writer's), or a known one with a parameter out of range, is a
    /// typed error that names it.
    #[test]
    fn unknown_codec_ids_are_named() {
        let h = sample_header(true);
        for (offset, value, needle) in [
            (60, 4u8, "elevation codec id 4"),
            (63, 0x40, "max error up to 16383"),
            (64, 3, "colour codec id 3"),
        ] {
            let mut b = h.encode();
            b[offset] = value;
            let n = b.len();
            let crc = crc32fast::hash(&b[..n - 4]);
            b[n - 4..].copy_from_slice(&crc.to_le_bytes());
            match Header::decode(&b, Some(1000)) {
                Err(e @ FormatError::Codec(_)) => {
                    let msg = e.to_string();
                    assert!(msg.contains(needle) && msg.contains("newer"), "{msg}");
                }
                other => panic!("byte {offset} = {value}: {other:?}"),
            }
        }
    }

    #[test]
    fn writer_is_atomic() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.planetdb");
        let mut w = DbWriter::create(&path).unwrap();
        let block = BlockId::root(Face::NORTH);
        let rec = encode_record(Tree::Elevation, block, &[], &Payload::zstd(&[1, 2, 3]));
        let (off, size) = w.append(&rec).unwrap();
        assert!(!path.exists(), "visible before finish");
        let mut h = sample_header(false);
        h.elevation.root_records = [ChildRef {
            offset: off,
            size,
            error: 0.0,
            min_elevation: 0.0,
            max_elevation: 0.0,
        }; 6];
        w.finish(&h).unwrap();
        let db = DbFile::open(&path).unwrap();
        assert_eq!(db.header, h);
        let bytes = db.read_record(&h.elevation.root_records[0]).unwrap();
        assert_eq!(bytes, rec);
        // Truncation is refused.
        let all = std::fs::read(&path).unwrap();
        std::fs::write(&path, &all[..all.len() - 3]).unwrap();
        assert!(DbFile::open(&path).is_err());
    }

    #[test]
    fn validated_head_names_each_fault() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.planetdb");
        let mut w = DbWriter::create(&path).unwrap();
        let rec = encode_record(
            Tree::Elevation,
            BlockId::root(Face::NORTH),
            &[],
            &Payload::zstd(&[1, 2, 3]),
        );
        let (offset, size) = w.append(&rec).unwrap();
        let mut h = sample_header(false);
        h.elevation.root_records = [ChildRef {
            offset,
            size,
            error: 0.0,
            min_elevation: 0.0,
            max_elevation: 0.0,
        }; 6];
        w.finish(&h).unwrap();
        let good = std::fs::read(&path).unwrap();
        let len = good.len() as u64;
        let head = |bytes: &[u8], limit: usize| {
            std::fs::write(&path, bytes).unwrap();
            let f = File::open(&path).unwrap();
            read_validated_head(&f, bytes.len() as u64, limit)
        };
        let ok = head(&good, MAX_HEADER_LEN).unwrap();
        assert_eq!(ok.header, h);
        assert_eq!(ok.superblock.file_len, len);
        // Shorter than a superblock.
        assert!(matches!(
            head(&good[..10], MAX_HEADER_LEN),
            Err(FormatError::Truncated { got: 10, .. })
        ));
        // Truncated or extended: the superblock's length disagrees.
        let mut longer = good.clone();
        longer.extend_from_slice(&[0; 5]);
        assert!(matches!(
            head(&longer, MAX_HEADER_LEN),
            Err(FormatError::Length { stored, got, .. }) if stored == len && got == len + 5
        ));
        // A header over the caller's limit is refused before it is read.
        let hl = ok.superblock.header_len as usize;
        assert!(matches!(
            head(&good, hl - 1),
            Err(FormatError::TooLarge { what: "header", .. })
        ));
        // A damaged superblock.
        let mut bad = good.clone();
        bad[20] ^= 1;
        assert!(matches!(
            head(&bad, MAX_HEADER_LEN),
            Err(FormatError::Checksum("superblock"))
        ));
        // A damaged header.
        let mut bad = good.clone();
        let last = bad.len() - 1;
        bad[last] ^= 0x55;
        assert!(head(&bad, MAX_HEADER_LEN).is_err());
    }
}
