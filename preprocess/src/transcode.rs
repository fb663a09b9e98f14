//! The second pass of a build whose elevation codec quantises in the loop
//! (codec id 3 at a nonzero max error; docs/FORMAT.md "Codec ids").
//!
//! Id 3 predicts every new sample from *decoded* samples, the parent's
//! included, so a record can be encoded only after its parent, while the
//! build (thesis §5.3, [`mod@crate::build`]) makes a block's grid from its
//! children's and writes children first. The build therefore writes the
//! tree exact first (id 3 at max error 0, whose payloads are the source's
//! samples), and this pass re-encodes it top-down: each block's exact grid
//! is decoded from that file, its LOD 1 replaced by the parent's id 3
//! decode, encoded, and decoded again for its children. Records are
//! appended in the first file's order (children before their parent,
//! elevation before colour), so the file stays post-order within every
//! subtree; colour records keep their payloads and get the new child
//! references. The references' errors and bounds are the first pass's,
//! which already include the codec's max error.

use crate::error::BuildError;
use indicatif::ProgressBar;
use parking_lot::Mutex;
use planet_core::codec::{ElevationCodec, Payload};
use planet_core::format::{
    encode_record, parse_record, ChildRef, DbFile, DbWriter, FormatError, Record, Tree,
};
use planet_core::lod;
use planet_core::{BlockId, Face};
use rayon::prelude::*;
use std::path::Path;

/// What the second pass wrote.
pub struct Transcoded {
    /// File length in bytes.
    pub file_bytes: u64,
    /// Bytes of elevation records.
    pub elevation_bytes: u64,
}

struct Pass<'a> {
    exact: &'a DbFile,
    exact_path: &'a Path,
    codec: ElevationCodec,
    w: usize,
    writer: Mutex<Option<DbWriter>>,
    out: &'a Path,
    bar: &'a ProgressBar,
    elevation_bytes: std::sync::atomic::AtomicU64,
}

impl Pass<'_> {
    fn read(&self, r: &ChildRef) -> Result<Vec<u8>, BuildError> {
        self.exact.read_record(r).map_err(|e| self.corrupt(e))
    }

    fn corrupt(&self, e: FormatError) -> BuildError {
        BuildError::ExactPass {
            path: self.exact_path.to_path_buf(),
            source: e,
        }
    }

    fn parse<'b>(&self, bytes: &'b [u8]) -> Result<Record<'b>, BuildError> {
        parse_record(bytes, None).map_err(|e| self.corrupt(e))
    }

    fn append(&self, rec: &[u8]) -> Result<(u64, u32), BuildError> {
        let r = crate::build::append(&self.writer, self.out, rec)?;
        self.bar.inc(1);
        Ok(r)
    }

    /// Re-encode block `b` and its subtree: `src` and `dec` are its grid
    /// with the exact and the id 3 LOD 1 (the parent's decodes) placed.
    /// Returns its new elevation and colour references.
    fn block(
        &self,
        b: BlockId,
        (e_ref, c_ref): (ChildRef, Option<ChildRef>),
        mut src: Vec<i16>,
        mut dec: Vec<i16>,
    ) -> Result<(ChildRef, Option<ChildRef>), BuildError> {
        let (w, side) = (self.w, self.w + 1);
        let bytes = self.read(&e_ref)?;
        let rec = self.parse(&bytes)?;
        let exact = &self.exact.header.elevation.codec;
        rec.decode_elevation(exact, w, &mut src)
            .map_err(|e| self.corrupt(e))?;
        // The encoder's grid: the decoder's LOD 1, the source elsewhere.
        let mut grid = src.clone();
        lod::elevation_place_first_lod(&lod::elevation_first_lod(&dec, w), w, &mut grid);
        let payload = self.codec.encode(&grid, w);
        self.codec
            .decode(&payload.bytes, payload.raw_len as usize, w, &mut dec)
            .map_err(|e| self.corrupt(e.into()))?;
        let colour = match &c_ref {
            Some(r) => Some(self.read(r)?),
            None => None,
        };
        let colour = colour.as_deref().map(|c| self.parse(c)).transpose()?;
        let kids: Vec<(ChildRef, Option<ChildRef>)> = rec
            .header
            .children
            .par_iter()
            .enumerate()
            .map(|(k, &r)| {
                let mut cs = vec![0i16; side * side];
                let mut cd = vec![0i16; side * side];
                lod::split_elevation(&src, w, k, &mut cs);
                lod::split_elevation(&dec, w, k, &mut cd);
                let c = colour
                    .as_ref()
                    .and_then(|c| c.header.children.get(k).copied());
                self.block(b.child(k), (r, c), cs, cd)
            })
            .collect::<Result<_, _>>()?;
        let erefs: Vec<ChildRef> = kids.iter().map(|k| k.0).collect();
        let rec = encode_record(Tree::Elevation, b, &erefs, &payload);
        self.elevation_bytes
            .fetch_add(rec.len() as u64, std::sync::atomic::Ordering::Relaxed);
        let (offset, size) = self.append(&rec)?;
        let e_new = ChildRef {
            offset,
            size,
            ..e_ref
        };
        let c_new = match (colour, c_ref) {
            (Some(c), Some(r)) => {
                // Colour splits only where elevation does (the build's
                // linked trees): every child then returned its colour.
                let crefs: Vec<ChildRef> = if c.header.children.is_empty() {
                    Vec::new()
                } else {
                    kids.iter()
                        .map(|k| k.1)
                        .collect::<Option<Vec<_>>>()
                        .filter(|v| v.len() == c.header.children.len())
                        .ok_or_else(|| {
                            self.corrupt(FormatError::Field(format!(
                                "colour record of {b:?} splits where elevation does not"
                            )))
                        })?
                };
                let payload = Payload {
                    raw_len: c.header.raw_len,
                    bytes: c.payload.to_vec(),
                };
                let (offset, size) =
                    self.append(&encode_record(Tree::Colour, b, &crefs, &payload))?;
                Some(ChildRef { offset, size, ..r })
            }
            _ => None,
        };
        Ok((e_new, c_new))
    }
}

/// Re-encode the exact database `exact` (elevation id 3 at max error 0)
/// into `out` with elevation codec `codec`.
pub fn in_loop(
    exact_path: &Path,
    out: &Path,
    codec: ElevationCodec,
    bar: &ProgressBar,
) -> Result<Transcoded, BuildError> {
    let exact = DbFile::open(exact_path).map_err(|e| BuildError::ExactPass {
        path: exact_path.to_path_buf(),
        source: e,
    })?;
    let h = exact.header.clone();
    let w = h.elevation.block_width as usize;
    let writer = DbWriter::create(out).map_err(|e| BuildError::write(out, e))?;
    let pass = Pass {
        exact: &exact,
        exact_path,
        codec,
        w,
        writer: Mutex::new(Some(writer)),
        out,
        bar,
        elevation_bytes: Default::default(),
    };
    let roots: Result<Vec<(ChildRef, Option<ChildRef>)>, BuildError> = Face::ALL
        .into_par_iter()
        .enumerate()
        .map(|(f, face)| {
            let mut grid = vec![0i16; (w + 1) * (w + 1)];
            lod::elevation_place_first_lod(&h.elevation.root_first_lods[f], w, &mut grid);
            let c = h.colour.as_ref().map(|c| c.root_records[f]);
            pass.block(
                BlockId::root(face),
                (h.elevation.root_records[f], c),
                grid.clone(),
                grid,
            )
        })
        .collect();
    let writer = pass.writer.lock().take();
    let roots = match roots {
        Ok(r) => r,
        Err(e) => {
            if let Some(w) = writer {
                w.abandon();
            }
            return Err(e);
        }
    };
    let mut header = h;
    header.elevation.codec = codec;
    header.elevation.root_records = std::array::from_fn(|f| roots[f].0);
    if let Some(c) = header.colour.as_mut() {
        for (f, r) in c.root_records.iter_mut().enumerate() {
            *r = roots[f].1.unwrap_or_default();
        }
    }
    let file_bytes = crate::build::finish(writer, &header, out)?;
    Ok(Transcoded {
        file_bytes,
        elevation_bytes: pass
            .elevation_bytes
            .load(std::sync::atomic::Ordering::Relaxed),
    })
}
