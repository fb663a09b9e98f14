//! Reading a built database back: `verify`, `inspect` and `sample`.
//!
//! Verification follows the explicit layout of thesis §3.3.2 (see
//! docs/REFERENCES.md): records are found only through the `(offset, size)` lists, starting
//! from the header's roots. `verify` (1) opens the superblock and header
//! (both checksummed), (2) scans the record area linearly from byte 64, so the
//! records must tile `[64, header_offset)` with no gap or overlap and every
//! record's magic, length and CRC-32 must hold, and (3) walks both trees from
//! the roots through every `ChildRef`, checks each record's tree and block id,
//! that every scanned record is referenced exactly once, decodes every payload
//! with its first LOD split from the parent (thesis §3.4.1), and checks the
//! decoded samples lie in the reference's elevation bounds. Any flipped byte
//! fails one of these.

use crate::build::GridSource;
use crate::error::{DbError, RecordError};
use planet_core::codec::{colour::psnr_of_mse, ColourCodec, ElevationCodec};
use planet_core::format::{
    parse_record, peek_record_len, ChildRef, DbFile, Header, Tree, SUPERBLOCK_LEN,
};
use planet_core::lod::{self, Rgb};
use planet_core::{BlockId, Face, FaceCoord};
use serde::Serialize;
use std::collections::HashMap;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

fn open(path: &Path) -> Result<DbFile, DbError> {
    DbFile::open(path).map_err(|source| DbError::Open {
        path: path.to_path_buf(),
        source,
    })
}

/// The error of a record at `offset` that cannot be read, parsed or decoded.
fn bad<E: Into<RecordError>>(offset: u64) -> impl FnOnce(E) -> DbError {
    move |e| DbError::Record {
        offset,
        source: e.into(),
    }
}

fn corrupt(offset: u64, reason: impl Into<String>) -> DbError {
    DbError::Corrupt {
        offset,
        reason: reason.into(),
    }
}

/// One record found by the linear scan.
#[derive(Debug, Clone, Copy)]
pub struct ScannedRecord {
    /// File offset.
    pub offset: u64,
    /// Length in bytes.
    pub size: u32,
    /// Tree.
    pub tree: Tree,
    /// Block.
    pub block: BlockId,
    /// Raw payload length.
    pub raw_len: u32,
    /// Number of child references.
    pub children: u8,
    /// The child references' `error` fields (the first `children`).
    pub child_errors: [f32; 4],
}

/// Linear scan of `[64, header_offset)`: every record parsed and checked.
pub fn scan(path: &Path) -> Result<(DbFile, Vec<ScannedRecord>), DbError> {
    let db = open(path)?;
    let end = db.superblock.header_offset;
    let file = std::fs::File::open(path).map_err(|source| DbError::Reopen { source })?;
    let mut r = BufReader::with_capacity(1 << 20, file);
    r.seek(SeekFrom::Start(SUPERBLOCK_LEN as u64))
        .map_err(bad(SUPERBLOCK_LEN as u64))?;
    let file_len = db.superblock.file_len;
    let mut at = SUPERBLOCK_LEN as u64;
    let mut out = Vec::new();
    let mut buf = Vec::new();
    while at < end {
        if end - at < 8 {
            return Err(corrupt(at, "gap of fewer than 8 bytes before the header"));
        }
        let mut first = [0u8; 8];
        r.read_exact(&mut first).map_err(bad(at))?;
        let len = peek_record_len(&first).map_err(bad(at))? as u64;
        if at + len > end {
            return Err(corrupt(at, "record runs past the header"));
        }
        buf.clear();
        buf.extend_from_slice(&first);
        buf.resize(len as usize, 0);
        r.read_exact(&mut buf[8..]).map_err(bad(at))?;
        let rec = parse_record(&buf, Some(file_len)).map_err(bad(at))?;
        out.push(ScannedRecord {
            offset: at,
            size: len as u32,
            tree: rec.header.tree,
            block: rec.header.block,
            raw_len: rec.header.raw_len,
            children: rec.header.children.len().min(4) as u8,
            child_errors: std::array::from_fn(|k| {
                rec.header.children.get(k).map_or(0.0, |c| c.error)
            }),
        });
        at += len;
    }
    Ok((db, out))
}

/// What `verify` found in a good database.
#[derive(Debug, Clone, Default, Serialize)]
pub struct VerifyReport {
    /// Elevation records.
    pub elevation_records: u64,
    /// Colour records.
    pub colour_records: u64,
    /// Deepest elevation leaf.
    pub max_level: u8,
    /// Against the source (when given): the codec's bound on elevation
    /// error, metres.
    pub elevation_bound_m: Option<f64>,
    /// Against the source: the largest error of a decoded leaf sample,
    /// metres (at most the bound, or verify fails).
    pub elevation_max_error_m: Option<f64>,
    /// Against the source: PSNR (dB) of every decoded colour leaf texel.
    pub colour_psnr: Option<f64>,
    /// Against the source: the lowest PSNR of one colour leaf record.
    pub colour_min_record_psnr: Option<f64>,
}

/// Fully verify a database; `Err(DbError::Corrupt)` names the first bad
/// offset found and why.
pub fn verify(path: &Path) -> Result<VerifyReport, DbError> {
    verify_against(path, None)
}

/// [`verify`], and with a source (the one the database was built from)
/// also check every decoded elevation leaf sample against the source's
/// full-resolution samples (within the codec's max error, else
/// `DbError::Corrupt`), and measure the colour leaves' PSNR against it.
/// Inner blocks' samples are their leaves' samples (point-sampled LODs), so
/// the leaves cover every record.
pub fn verify_against(
    path: &Path,
    source: Option<&dyn GridSource>,
) -> Result<VerifyReport, DbError> {
    let (db, scanned) = scan(path)?;
    let mut seen: HashMap<u64, (u32, bool)> = scanned
        .iter()
        .map(|s| (s.offset, (s.size, false)))
        .collect();
    let mut report = VerifyReport::default();
    let h = db.header.clone();
    let ew = h.elevation.block_width as usize;
    let side = ew + 1;
    let ecodec = h.elevation.codec;
    let bound = ecodec.max_error() as f64 * h.elevation_scale as f64;
    let mut max_err = 0f64;
    let mut src_grid = vec![0i16; side * side];
    for f in 0..6 {
        let face = Face::ALL[f];
        let mut full = vec![0i16; side * side];
        lod::elevation_place_first_lod(&h.elevation.root_first_lods[f], ew, &mut full);
        let mut stack = vec![(BlockId::root(face), h.elevation.root_records[f], full)];
        while let Some((b, r, mut grid)) = stack.pop() {
            let (kids, raw_len, payload) = check_ref(&db, &mut seen, &r, Tree::Elevation, b)?;
            ecodec
                .decode(&payload, raw_len, ew, &mut grid)
                .map_err(bad(r.offset))?;
            if let (Some(src), true) = (source, kids.is_empty()) {
                src.elevation_leaf(b, &mut src_grid)
                    .map_err(|e| DbError::Source {
                        offset: r.offset,
                        block: b,
                        source: Box::new(e),
                    })?;
                for (d, s) in grid.iter().zip(&src_grid) {
                    let e = (h.metres(*d) - h.metres(*s)).abs();
                    max_err = max_err.max(e);
                    if e > bound + 1e-6 {
                        return Err(corrupt(
                            r.offset,
                            format!(
                                "{b:?} decoded {} m vs source {} m: error {e} m over the bound {bound} m",
                                h.metres(*d),
                                h.metres(*s)
                            ),
                        ));
                    }
                }
            }
            let (lo, hi) = grid.iter().fold((f64::MAX, f64::MIN), |(a, c), &v| {
                (a.min(h.metres(v)), c.max(h.metres(v)))
            });
            if lo < r.min_elevation as f64 - 1e-3 || hi > r.max_elevation as f64 + 1e-3 {
                return Err(corrupt(
                    r.offset,
                    format!(
                        "{b:?} samples {lo}..{hi} outside its reference bounds {}..{}",
                        r.min_elevation, r.max_elevation
                    ),
                ));
            }
            report.elevation_records += 1;
            report.max_level = report.max_level.max(b.level);
            for (k, c) in kids.iter().enumerate() {
                let mut cg = vec![0i16; side * side];
                lod::split_elevation(&grid, ew, k, &mut cg);
                stack.push((b.child(k), *c, cg));
            }
        }
    }
    if source.is_some() {
        report.elevation_bound_m = Some(bound);
        report.elevation_max_error_m = Some(max_err);
    }
    if let Some(ct) = &h.colour {
        let cw = ct.block_width as usize;
        let ccodec = ct.codec;
        let lossless = matches!(ccodec, ColourCodec::Legacy | ColourCodec::Lossless);
        let (mut se, mut n, mut min_psnr) = (0f64, 0u64, f64::INFINITY);
        let mut src_elev = vec![0i16; side * side];
        for f in 0..6 {
            let face = Face::ALL[f];
            let mut stack = vec![(
                BlockId::root(face),
                ct.root_records[f],
                ct.root_first_lods[f].clone(),
            )];
            while let Some((b, r, lod1)) = stack.pop() {
                let (kids, raw_len, payload) = check_ref(&db, &mut seen, &r, Tree::Colour, b)?;
                let full = ccodec
                    .decode(&payload, raw_len, &lod1, cw)
                    .map_err(bad(r.offset))?;
                // Lossless codecs reproduce the filtered LOD 1 exactly.
                if lossless && lod::colour_filter(&full, cw) != lod1 {
                    return Err(corrupt(r.offset, format!("{b:?} colour LOD 1 mismatch")));
                }
                if let (Some(src), true) = (source, kids.is_empty()) {
                    src.elevation_leaf(b, &mut src_elev)
                        .map_err(|e| DbError::Source {
                            offset: r.offset,
                            block: b,
                            source: Box::new(e),
                        })?;
                    let want = src.colour_leaf(b, &src_elev).map_err(|e| DbError::Source {
                        offset: r.offset,
                        block: b,
                        source: Box::new(e),
                    })?;
                    let rse: f64 = full
                        .iter()
                        .zip(&want)
                        .flat_map(|(a, b)| (0..3).map(move |c| (a[c] as f64 - b[c] as f64).powi(2)))
                        .sum();
                    se += rse;
                    n += 3 * full.len() as u64;
                    min_psnr = min_psnr.min(psnr_of_mse(rse / (3 * full.len()) as f64));
                    if lossless && rse != 0.0 {
                        return Err(corrupt(
                            r.offset,
                            format!("{b:?} lossless colour differs from the source"),
                        ));
                    }
                }
                report.colour_records += 1;
                for (k, c) in kids.iter().enumerate() {
                    stack.push((b.child(k), *c, lod::split_colour(&full, cw, k)));
                }
            }
        }
        if source.is_some() && n > 0 {
            report.colour_psnr = Some(psnr_of_mse(se / n as f64));
            report.colour_min_record_psnr = Some(min_psnr);
        }
    }
    let mut unref: Vec<u64> = seen.iter().filter(|(_, v)| !v.1).map(|(k, _)| *k).collect();
    unref.sort_unstable();
    if let Some(o) = unref.first() {
        return Err(corrupt(*o, "record not referenced by any tree"));
    }
    Ok(report)
}

/// Check that a reference points at exactly one scanned record, not seen
/// before, of the expected tree and block; returns its child references,
/// raw length and (entropy-coded) payload.
fn check_ref(
    db: &DbFile,
    seen: &mut HashMap<u64, (u32, bool)>,
    r: &ChildRef,
    tree: Tree,
    b: BlockId,
) -> Result<(Vec<ChildRef>, usize, Vec<u8>), DbError> {
    match seen.get_mut(&r.offset) {
        None => {
            return Err(corrupt(
                r.offset,
                format!("reference to {b:?} does not point at a record start"),
            ))
        }
        Some((size, used)) => {
            if *size != r.size {
                return Err(corrupt(
                    r.offset,
                    format!("reference size {} but record is {}", r.size, size),
                ));
            }
            if *used {
                return Err(corrupt(r.offset, "record referenced twice"));
            }
            *used = true;
        }
    }
    let bytes = db.read_record(r).map_err(bad(r.offset))?;
    let rec = parse_record(&bytes, Some(db.superblock.file_len)).map_err(bad(r.offset))?;
    if rec.header.tree != tree || rec.header.block != b {
        return Err(corrupt(
            r.offset,
            format!(
                "expected {tree:?} {b:?}, found {:?} {:?}",
                rec.header.tree, rec.header.block
            ),
        ));
    }
    let payload = rec.payload.to_vec();
    Ok((rec.header.children, rec.header.raw_len as usize, payload))
}

/// Per-level statistics of one tree.
#[derive(Debug, Clone, Default, Serialize)]
pub struct LevelStats {
    /// Tree level.
    pub level: u8,
    /// Records at this level.
    pub records: u64,
    /// Bytes of those records.
    pub bytes: u64,
    /// Largest `error` of the references to this level's blocks (the
    /// geometric error in metres, for elevation, of drawing a block at its
    /// first LOD, plus its children's; thesis §3.3.2).
    pub max_error: f32,
    /// Mean of those errors.
    pub mean_error: f64,
}

/// Statistics of one tree.
#[derive(Debug, Clone, Default, Serialize)]
pub struct TreeStats {
    /// The codec's name (`planet_core::codec`).
    pub codec: String,
    /// The codec's id in the header.
    pub codec_id: u8,
    /// The codec's parameters: elevation `max_error_units` and
    /// `max_error_m`; colour `luma_step`, `chroma_step`, `target_psnr`.
    pub codec_params: std::collections::BTreeMap<String, f64>,
    /// Block width.
    pub block_width: u16,
    /// Deepest level.
    pub max_level: u8,
    /// Per level.
    pub levels: Vec<LevelStats>,
    /// Records.
    pub records: u64,
    /// Bytes of records.
    pub bytes: u64,
    /// Samples stored (new samples of each record plus the roots' first LODs).
    pub samples: u64,
    /// Bytes those samples take raw (i16 elevation, RGB8 colour).
    pub raw_bytes: u64,
    /// `bytes / raw_bytes`.
    pub compression_ratio: f64,
}

/// The datum of a database, as fields.
#[derive(Debug, Clone, Serialize)]
pub struct DatumReport {
    /// `sphere` or `ellipsoid`.
    pub kind: &'static str,
    /// Equatorial radius `a`, metres.
    pub semi_major_axis_m: f64,
    /// Polar radius `b`, metres.
    pub semi_minor_axis_m: f64,
    /// `a / (a − b)`; null for a sphere.
    pub inverse_flattening: Option<f64>,
    /// First eccentricity squared (0 for a sphere).
    pub e2: f64,
    /// The body, where the axes identify one (Earth, Moon, Mars, …).
    pub body: Option<&'static str>,
    /// A name (WGS84, GRS80, Moon sphere, …) where known.
    pub name: Option<String>,
}

impl From<planet_core::Datum> for DatumReport {
    fn from(d: planet_core::Datum) -> DatumReport {
        DatumReport {
            kind: match d {
                planet_core::Datum::Sphere { .. } => "sphere",
                planet_core::Datum::Ellipsoid { .. } => "ellipsoid",
            },
            semi_major_axis_m: d.equatorial_radius(),
            semi_minor_axis_m: d.polar_radius(),
            inverse_flattening: d.inverse_flattening(),
            e2: d.e2(),
            body: d.body().map(|b| b.name()),
            name: d.name(),
        }
    }
}

impl std::fmt::Display for DatumReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}), a = {} m",
            self.name.as_deref().unwrap_or(self.kind),
            self.body.unwrap_or("unknown body"),
            self.semi_major_axis_m
        )?;
        match self.inverse_flattening {
            Some(rf) => write!(f, ", 1/f = {rf}"),
            None => Ok(()),
        }
    }
}

/// What `inspect` reports.
#[derive(Debug, Clone, Serialize)]
pub struct InspectReport {
    /// File length.
    pub file_bytes: u64,
    /// The datum.
    pub datum: DatumReport,
    /// Metres per stored unit.
    pub elevation_scale: f32,
    /// Offset in metres.
    pub elevation_offset: f32,
    /// Global minimum elevation (m).
    pub min_elevation: f32,
    /// Global maximum elevation (m).
    pub max_elevation: f32,
    /// Header description.
    pub description: String,
    /// Elevation tree.
    pub elevation: TreeStats,
    /// Colour tree.
    pub colour: Option<TreeStats>,
}

/// Header fields and per-level record statistics.
pub fn inspect(path: &Path) -> Result<InspectReport, DbError> {
    let (db, scanned) = scan(path)?;
    let h = &db.header;
    let mut trees = [TreeStats::default(), TreeStats::default()];
    trees[0].block_width = h.elevation.block_width;
    trees[0].max_level = h.elevation.max_level;
    let ec: ElevationCodec = h.elevation.codec;
    trees[0].codec = ec.name().into();
    trees[0].codec_id = ec.id();
    if ec != ElevationCodec::Legacy {
        let max_error = ec.max_error();
        let p = &mut trees[0].codec_params;
        p.insert("max_error_units".into(), max_error as f64);
        p.insert(
            "max_error_m".into(),
            max_error as f64 * h.elevation_scale as f64,
        );
    }
    if let Some(c) = &h.colour {
        trees[1].block_width = c.block_width;
        trees[1].max_level = c.max_level;
        trees[1].codec = c.codec.name().into();
        trees[1].codec_id = c.codec.id();
        if let ColourCodec::Haar(p) = c.codec {
            let m = &mut trees[1].codec_params;
            m.insert("luma_step".into(), p.luma_step as f64);
            m.insert("chroma_step".into(), p.chroma_step as f64);
            m.insert("target_psnr".into(), p.target_psnr as f64);
        }
    }
    // Per tree and level: sum and max of the references' errors.
    let mut errs: [Vec<(f64, f32)>; 2] = [Vec::new(), Vec::new()];
    let mut add_err = |tree: usize, level: usize, e: f32| {
        let v = &mut errs[tree];
        if v.len() <= level {
            v.resize(level + 1, (0.0, 0.0));
        }
        v[level].0 += e as f64;
        v[level].1 = v[level].1.max(e);
    };
    for r in &h.elevation.root_records {
        add_err(0, 0, r.error);
    }
    if let Some(c) = &h.colour {
        for r in &c.root_records {
            add_err(1, 0, r.error);
        }
    }
    for s in &scanned {
        let t = &mut trees[s.tree as usize];
        let l = s.block.level as usize;
        if t.levels.len() <= l {
            t.levels.resize(l + 1, LevelStats::default());
        }
        t.levels[l].level = l as u8;
        t.levels[l].records += 1;
        t.levels[l].bytes += s.size as u64;
        t.records += 1;
        t.bytes += s.size as u64;
        for &e in &s.child_errors[..s.children as usize] {
            add_err(s.tree as usize, l + 1, e);
        }
    }
    for (t, e) in trees.iter_mut().zip(&errs) {
        for l in &mut t.levels {
            if let Some(&(sum, max)) = e.get(l.level as usize) {
                l.max_error = max;
                l.mean_error = sum / l.records.max(1) as f64;
            }
        }
    }
    let ew = h.elevation.block_width as u64;
    let e = &mut trees[0];
    e.samples = e.records * lod::elevation_new_samples(ew as usize) as u64
        + 6 * (ew / 2 + 1) * (ew / 2 + 1);
    e.raw_bytes = 2 * e.samples;
    e.compression_ratio = e.bytes as f64 / e.raw_bytes.max(1) as f64;
    if let Some(c) = &h.colour {
        let cw = c.block_width as u64;
        let t = &mut trees[1];
        t.samples = t.records * (cw * cw - (cw / 2) * (cw / 2)) + 6 * (cw / 2) * (cw / 2);
        t.raw_bytes = 3 * t.samples;
        t.compression_ratio = t.bytes as f64 / t.raw_bytes.max(1) as f64;
    }
    let [et, ct] = trees;
    Ok(InspectReport {
        file_bytes: db.superblock.file_len,
        datum: h.datum.into(),
        elevation_scale: h.elevation_scale,
        elevation_offset: h.elevation_offset,
        min_elevation: h.min_elevation,
        max_elevation: h.max_elevation,
        description: h.description.clone(),
        elevation: et,
        colour: h.colour.as_ref().map(|_| ct),
    })
}

/// An open database for point queries.
pub struct Sampler {
    db: DbFile,
}

/// The result of a point query.
#[derive(Debug, Clone, Copy)]
pub struct SampleResult {
    /// Elevation in metres (bilinear in the leaf's full grid).
    pub metres: f64,
    /// The leaf block used.
    pub leaf: BlockId,
}

impl Sampler {
    /// Open a database.
    pub fn open(path: &Path) -> Result<Sampler, DbError> {
        Ok(Sampler { db: open(path)? })
    }

    /// The header.
    pub fn header(&self) -> &Header {
        &self.db.header
    }

    /// The vertical datum the database's elevation sources were in, from
    /// its description ([`crate::source::VERTICAL_TOKEN`]); `None` where it
    /// names none (procedural databases, ellipsoidal heights) or a mix.
    pub fn vertical_datum(&self) -> Option<crate::geoid::VerticalDatum> {
        let d = &self.db.header.description;
        let at = d.find(crate::source::VERTICAL_TOKEN)? + crate::source::VERTICAL_TOKEN.len();
        let word: String = d[at..]
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric())
            .collect();
        word.parse().ok()
    }

    /// A height above the ellipsoid at (lat, lon) degrees expressed in
    /// vertical datum `v` (`h − N`, EGM96 on its 15′ nodes).
    pub fn in_vertical_datum(
        &self,
        lat: f64,
        lon: f64,
        h: f64,
        v: crate::geoid::VerticalDatum,
    ) -> f64 {
        let g = crate::geoid::Egm96Grid::new();
        let mut r = g.reader();
        h - crate::geoid::undulation(v, &mut r, lat, lon, crate::geoid::FINEST_SPACING)
    }

    /// Elevation at (lat, lon) in degrees: descend to the leaf containing the
    /// point, decoding every record on the way, and interpolate bilinearly.
    pub fn sample(&self, lat: f64, lon: f64) -> Result<SampleResult, DbError> {
        self.sample_cached(lat, lon, &mut HashMap::new())
    }

    /// [`Sampler::sample`] with a caller-owned cache of decoded full grids,
    /// for many queries (each entry is one `(W+1)²` grid).
    pub fn sample_cached(
        &self,
        lat: f64,
        lon: f64,
        cache: &mut HashMap<BlockId, (Vec<i16>, Vec<ChildRef>)>,
    ) -> Result<SampleResult, DbError> {
        if !(lat.is_finite() && lon.is_finite()) || lat.abs() > 90.0 {
            return Err(DbError::Query(format!("bad coordinates {lat}, {lon}")));
        }
        let fc = FaceCoord::from_lat_lon(lat.to_radians(), lon.to_radians());
        let h = &self.db.header;
        let w = h.elevation.block_width as usize;
        let side = w + 1;
        let f = fc.face.index() as usize;
        let mut grid = vec![0i16; side * side];
        lod::elevation_place_first_lod(&h.elevation.root_first_lods[f], w, &mut grid);
        let mut b = BlockId::root(fc.face);
        let mut r = h.elevation.root_records[f];
        loop {
            let children = if let Some((g, c)) = cache.get(&b) {
                grid.copy_from_slice(g);
                c.clone()
            } else {
                let bytes = self.db.read_record(&r).map_err(bad(r.offset))?;
                let rec = parse_record(&bytes, Some(self.db.superblock.file_len))
                    .map_err(bad(r.offset))?;
                if rec.header.block != b || rec.header.tree != Tree::Elevation {
                    return Err(corrupt(r.offset, "unexpected block"));
                }
                rec.decode_elevation(&h.elevation.codec, w, &mut grid)
                    .map_err(bad(r.offset))?;
                cache.insert(b, (grid.clone(), rec.header.children.clone()));
                rec.header.children
            };
            let n = (1u64 << b.level) as f64;
            let gx = ((fc.s * n - b.x as f64) * w as f64).clamp(0.0, w as f64);
            let gy = ((fc.t * n - b.y as f64) * w as f64).clamp(0.0, w as f64);
            if children.is_empty() {
                let (x0, y0) = (
                    (gx.floor() as usize).min(w - 1),
                    (gy.floor() as usize).min(w - 1),
                );
                let (fx, fy) = (gx - x0 as f64, gy - y0 as f64);
                let at = |i: usize, j: usize| h.metres(grid[j * side + i]);
                let top = at(x0, y0) + (at(x0 + 1, y0) - at(x0, y0)) * fx;
                let bot = at(x0, y0 + 1) + (at(x0 + 1, y0 + 1) - at(x0, y0 + 1)) * fx;
                return Ok(SampleResult {
                    metres: top + (bot - top) * fy,
                    leaf: b,
                });
            }
            let kx = usize::from(gx >= w as f64 / 2.0);
            let ky = usize::from(gy >= w as f64 / 2.0);
            let k = kx | (ky << 1);
            let mut child = vec![0i16; side * side];
            lod::split_elevation(&grid, w, k, &mut child);
            grid = child;
            b = b.child(k);
            r = children[k];
        }
    }

    /// Decode the full elevation grid of every block (depth-first) and call
    /// `f(block, grid)`; for tests and tools.
    pub fn for_each_elevation_block(
        &self,
        mut f: impl FnMut(BlockId, &[i16]),
    ) -> Result<(), DbError> {
        self.db
            .walk_elevation(|v| {
                f(v.block, v.full);
                true
            })
            .map_err(|e| bad(e.offset)(e.source))
    }

    /// Decode the full colour grid of every colour block and call `f`.
    pub fn for_each_colour_block(&self, mut f: impl FnMut(BlockId, &[Rgb])) -> Result<(), DbError> {
        let Some(ct) = &self.db.header.colour else {
            return Ok(());
        };
        let w = ct.block_width as usize;
        for (fi, face) in Face::ALL.iter().enumerate() {
            let mut stack = vec![(
                BlockId::root(*face),
                ct.root_records[fi],
                ct.root_first_lods[fi].clone(),
            )];
            while let Some((b, r, lod1)) = stack.pop() {
                let bytes = self.db.read_record(&r).map_err(bad(r.offset))?;
                let rec = parse_record(&bytes, None).map_err(bad(r.offset))?;
                let full = rec
                    .decode_colour(&ct.codec, &lod1, w)
                    .map_err(bad(r.offset))?;
                f(b, &full);
                for (k, c) in rec.header.children.iter().enumerate() {
                    stack.push((b.child(k), *c, lod::split_colour(&full, w, k)));
                }
            }
        }
        Ok(())
    }
}
