//! The database build: thesis §5.3, Alg. 5.2 (BlockSubdiv; see
//! docs/REFERENCES.md), bottom-up, depth-first, written linearly.
//!
//! Per block: a leaf's full grid comes from the source at the leaf's
//! resolution; an inner block's full grid is gathered from its four
//! children's first LODs (`lod::merge_elevation`, `lod::merge_colour` of each
//! child's `lod::colour_filter`). The block's one record (`subDepth = 1`) is
//! then encoded and appended, *after* its children's, and the block returns
//! its first LOD and its [`ChildRef`] to the parent. The roots' first LODs and
//! references go into the header (thesis §3.3).
//!
//! Elevation and colour trees are built in the same traversal (linked trees,
//! thesis §4.4.1): the colour block `(f, L, x, y)` covers exactly the
//! elevation block with the same id, at twice the definition, and its
//! reference copies that block's elevation bounds.
//!
//! Parallelism: rayon over faces and children; records are encoded on the
//! workers and appended by one `Mutex<DbWriter>` that returns
//! `(offset, size)`. A parent is appended only after its children returned,
//! so the file is post-order within every subtree. Memory: each in-flight
//! block holds one grid plus its children's first LODs, so the total is
//! bounded by threads × depth grids; [`BuildOptions::grid_memory`] caps the
//! threads to keep that product under a bound.

use crate::error::BuildError;
use crate::plan::Plan;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use parking_lot::Mutex;
use planet_core::codec::{colour::HaarParams, ColourCodec, ElevationCodec};
use planet_core::format::{encode_record, ChildRef, DbWriter, Header, Tree, TreeInfo};
use planet_core::lod::{self, Rgb};
use planet_core::{BlockId, Datum, Face};
use rayon::prelude::*;
use std::io::IsTerminal;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

/// Elevation block width.
pub const EW: usize = crate::source::ELEVATION_WIDTH;
/// Colour block width.
pub const CW: usize = crate::source::COLOUR_WIDTH;

/// Where leaf grids come from.
pub trait GridSource: Sync {
    /// Fill the full `(W+1)²` elevation grid (stored units) of a leaf.
    fn elevation_leaf(&self, b: BlockId, out: &mut [i16]) -> Result<(), BuildError>;
    /// The full `Wc²` colour grid of a colour leaf; `elevation` is the full
    /// elevation grid of the same block.
    fn colour_leaf(&self, b: BlockId, elevation: &[i16]) -> Result<Vec<Rgb>, BuildError>;
    /// The reference surface.
    fn datum(&self) -> Datum;
    /// Metres per stored elevation unit.
    fn elevation_scale(&self) -> f64;
    /// Whether there is a colour tree.
    fn has_colour(&self) -> bool;
    /// Header description.
    fn description(&self) -> String;
}

/// Build knobs.
#[derive(Debug, Clone)]
pub struct BuildOptions {
    /// Worker threads (`None`: rayon's default).
    pub threads: Option<usize>,
    /// Hide progress bars.
    pub quiet: bool,
    /// Bytes the in-flight grids may take (`None`: unbounded). The worker
    /// count is capped so that threads × depth × [`GRID_BYTES_PER_LEVEL`]
    /// stays within it (at least one worker).
    pub grid_memory: Option<usize>,
    /// Record codecs.
    pub codecs: CodecOptions,
}

/// The elevation codec asked for (`planet-build build --max-error`,
/// `--elevation-codec`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ElevationChoice {
    /// Format v1's lossless lz4 byte planes (for comparisons).
    Legacy,
    /// Quantised in the loop and rANS-coded (codec id 3) with this maximum
    /// error in metres (0: the source's own exactness), rounded down to
    /// whole stored units.
    MaxError(f64),
    /// The same with format v2's first elevation codec (id 1, for
    /// comparisons).
    MaxErrorId1(f64),
    /// The same with id 2 (a fixed quantisation grid, for comparisons).
    MaxErrorId2(f64),
}

/// The colour quality asked for (`planet-build build --colour-quality`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ColourQuality {
    /// Format v1's lossless PTM deltas under lz4 (`lossless-legacy`).
    LosslessLegacy,
    /// The lossless PTM deltas under zstd (`lossless`).
    Lossless,
    /// Haar details quantised for this PSNR in dB against the source.
    Psnr(f32),
}

/// Default colour quality: a PSNR of 42 dB (web imagery at JPEG quality
/// 85–90).
pub const DEFAULT_COLOUR_PSNR: f32 = 42.0;

impl std::str::FromStr for ColourQuality {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "lossless" => Ok(ColourQuality::Lossless),
            "lossless-legacy" => Ok(ColourQuality::LosslessLegacy),
            _ => match s.parse::<f32>() {
                Ok(db) if db.is_finite() && (20.0..=80.0).contains(&db) => {
                    Ok(ColourQuality::Psnr(db))
                }
                _ => Err(format!(
                    "colour quality {s:?}: a PSNR in dB in [20, 80], `lossless` or `lossless-legacy`"
                )),
            },
        }
    }
}

/// The codecs of a build.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CodecOptions {
    /// Elevation.
    pub elevation: ElevationChoice,
    /// Colour.
    pub colour: ColourQuality,
}

impl Default for CodecOptions {
    /// Exact elevation, colour at [`DEFAULT_COLOUR_PSNR`].
    fn default() -> Self {
        CodecOptions {
            elevation: ElevationChoice::MaxError(0.0),
            colour: ColourQuality::Psnr(DEFAULT_COLOUR_PSNR),
        }
    }
}

impl CodecOptions {
    /// The header's codecs for a source of `scale` metres per stored unit.
    pub fn resolve(&self, scale: f64) -> Result<(ElevationCodec, ColourCodec), BuildError> {
        let e = match self.elevation {
            ElevationChoice::Legacy => ElevationCodec::Legacy,
            ElevationChoice::MaxError(m)
            | ElevationChoice::MaxErrorId1(m)
            | ElevationChoice::MaxErrorId2(m) => {
                let k = (m / scale).floor();
                if !(m >= 0.0 && k <= planet_core::codec::elevation::MAX_ERROR_LIMIT as f64) {
                    return Err(BuildError::Options(format!(
                        "--max-error {m}: must be in [0, {} m]",
                        planet_core::codec::elevation::MAX_ERROR_LIMIT as f64 * scale
                    )));
                }
                let max_error = k as u16;
                match self.elevation {
                    ElevationChoice::MaxErrorId1(_) => ElevationCodec::Quantised { max_error },
                    ElevationChoice::MaxErrorId2(_) => ElevationCodec::Laplace { max_error },
                    _ => ElevationCodec::InLoop { max_error },
                }
            }
        };
        let c = match self.colour {
            ColourQuality::LosslessLegacy => ColourCodec::Legacy,
            ColourQuality::Lossless => ColourCodec::Lossless,
            ColourQuality::Psnr(db) => ColourCodec::Haar(HaarParams::for_psnr(db)),
        };
        Ok((e, c))
    }
}

/// Upper estimate of what one in-flight block holds while its subtree is
/// built: its full elevation grid and scratch copy (2 × 65² × 2 B), its four
/// children's first LODs (4 × (33² × 2 + 64² × 3) B), its full colour grid
/// and first LOD (128² × 3 + 64² × 3 B), and the raw and lz4 payload buffers
/// (≈ 2 × 45 kB), ≈ 225 kB, rounded up; doubled for rayon nesting a stolen
/// subtree inside a waiting join.
pub const GRID_BYTES_PER_LEVEL: usize = 2 * 256 * 1024;

/// The worker count a grid-memory bound allows for a tree `depth` levels deep.
pub fn threads_for_memory(grid_memory: usize, depth: usize) -> usize {
    (grid_memory / (depth.max(1) * GRID_BYTES_PER_LEVEL)).max(1)
}

/// What a build produced.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct BuildStats {
    /// Elevation records written.
    pub elevation_records: u64,
    /// Colour records written.
    pub colour_records: u64,
    /// Elevation samples stored (new samples of every record plus the roots'
    /// first LODs: each face-map sample once, edges shared between blocks
    /// counted per block).
    pub elevation_samples: u64,
    /// Colour texels stored (same counting).
    pub colour_samples: u64,
    /// File length in bytes.
    pub file_bytes: u64,
    /// Bytes of elevation records.
    pub elevation_bytes: u64,
    /// Bytes of colour records.
    pub colour_bytes: u64,
    /// Wall time in seconds.
    pub seconds: f64,
    /// Deepest elevation level.
    pub max_level: u8,
    /// Deepest colour level.
    pub colour_max_level: u8,
}

impl BuildStats {
    /// Output samples (elevation + colour) per second.
    pub fn samples_per_second(&self) -> f64 {
        (self.elevation_samples + self.colour_samples) as f64 / self.seconds.max(1e-9)
    }
}

struct Out {
    elev_lod1: Vec<i16>,
    elev_ref: ChildRef,
    /// First LOD, reference, and colour levels below the block.
    colour: Option<(Vec<Rgb>, ChildRef, u8)>,
}

struct Ctx<'a> {
    src: &'a dyn GridSource,
    plan: &'a Plan,
    writer: Mutex<Option<DbWriter>>,
    out_path: &'a Path,
    scale: f64,
    elevation_codec: ElevationCodec,
    /// The final codec's max error, stored units (the references' errors
    /// include it whether or not this pass encodes with it).
    max_error: u16,
    colour_codec: ColourCodec,
    bar: ProgressBar,
    e_records: AtomicU64,
    c_records: AtomicU64,
    e_bytes: AtomicU64,
    c_bytes: AtomicU64,
}

/// Append a record to a build's shared writer: `(offset, size)`.
pub(crate) fn append(
    writer: &Mutex<Option<DbWriter>>,
    out: &Path,
    rec: &[u8],
) -> Result<(u64, u32), BuildError> {
    let mut g = writer.lock();
    let w = g.as_mut().ok_or_else(|| BuildError::Write {
        path: out.to_path_buf(),
        msg: "writer already closed".into(),
    })?;
    w.append(rec).map_err(|e| BuildError::write(out, e))
}

/// Write the header and move the file into place (`finish` removes its
/// temporary on error): the file's length.
pub(crate) fn finish(
    writer: Option<DbWriter>,
    header: &Header,
    out: &Path,
) -> Result<u64, BuildError> {
    let writer = writer.ok_or_else(|| BuildError::Write {
        path: out.to_path_buf(),
        msg: "writer lost".into(),
    })?;
    writer.finish(header).map_err(|e| BuildError::write(out, e))
}

impl Ctx<'_> {
    fn append(&self, rec: &[u8], tree: Tree) -> Result<(u64, u32), BuildError> {
        let r = append(&self.writer, self.out_path, rec)?;
        let (n, b) = match tree {
            Tree::Elevation => (&self.e_records, &self.e_bytes),
            Tree::Colour => (&self.c_records, &self.c_bytes),
        };
        n.fetch_add(1, Ordering::Relaxed);
        b.fetch_add(rec.len() as u64, Ordering::Relaxed);
        self.bar.inc(1);
        Ok(r)
    }
}

pub use planet_core::lod::{colour_lod_error, elevation_lod_error};

fn build_block(ctx: &Ctx, b: BlockId, colour_here: bool) -> Result<Out, BuildError> {
    let side = EW + 1;
    let esplit = ctx.plan.elevation_split(b);
    let csplit = colour_here && ctx.plan.colour_split(b);
    let mut full = vec![0i16; side * side];
    let (kids, child_err, lo, hi) = if esplit {
        let kids: Vec<Out> = b
            .children()
            .into_par_iter()
            .map(|c| build_block(ctx, c, csplit))
            .collect::<Result<_, _>>()?;
        let mut err = 0f64;
        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
        for (k, kid) in kids.iter().enumerate() {
            let mut tmp = vec![0i16; side * side];
            lod::elevation_place_first_lod(&kid.elev_lod1, EW, &mut tmp);
            lod::merge_elevation(&tmp, EW, k, &mut full);
            err = err.max(kid.elev_ref.error as f64);
            lo = lo.min(kid.elev_ref.min_elevation);
            hi = hi.max(kid.elev_ref.max_elevation);
        }
        (kids, err, lo, hi)
    } else {
        ctx.src.elevation_leaf(b, &mut full)?;
        let (mn, mx) = full
            .iter()
            .fold((i16::MAX, i16::MIN), |(a, c), &v| (a.min(v), c.max(v)));
        // The codec moves a decoded sample by up to its max error: the
        // geometric error of every reference above includes it (once, as
        // errors are carried up), and the bounds widen by it.
        let k = ctx.max_error as f64;
        (
            Vec::new(),
            k * ctx.scale,
            ((mn as f64 - k) * ctx.scale) as f32,
            ((mx as f64 + k) * ctx.scale) as f32,
        )
    };
    let erefs: Vec<ChildRef> = kids.iter().map(|k| k.elev_ref).collect();
    let error = (elevation_lod_error(&full, EW) * ctx.scale + child_err) as f32;
    let rec = encode_record(
        Tree::Elevation,
        b,
        &erefs,
        &ctx.elevation_codec.encode(&full, EW),
    );
    let (offset, size) = ctx.append(&rec, Tree::Elevation)?;
    let elev_ref = ChildRef {
        offset,
        size,
        error,
        min_elevation: lo,
        max_elevation: hi,
    };
    let colour = if colour_here {
        let (cfull, crefs, cerr, height) = if csplit {
            let mut cfull = vec![[0u8; 3]; CW * CW];
            let mut crefs = Vec::with_capacity(4);
            let mut cerr = 0f64;
            let mut height = 0u8;
            for (k, kid) in kids.iter().enumerate() {
                let (l1, r, h) = kid
                    .colour
                    .as_ref()
                    .ok_or_else(|| BuildError::Options(format!("colour child of {b:?} missing")))?;
                lod::merge_colour(l1, CW, k, &mut cfull);
                crefs.push(*r);
                cerr = cerr.max(r.error as f64);
                height = height.max(h + 1);
            }
            (cfull, crefs, cerr, height)
        } else {
            (ctx.src.colour_leaf(b, &full)?, Vec::new(), 0.0, 0)
        };
        let lod1 = lod::colour_filter(&cfull, CW);
        let (payload, codec_err) = ctx.colour_codec.encode(&cfull, &lod1, CW, height);
        let rec = encode_record(Tree::Colour, b, &crefs, &payload);
        let (offset, size) = ctx.append(&rec, Tree::Colour)?;
        // The codec's own error at this level adds to the filter's and the
        // children's (each level's error reaches the finest texels).
        let r = ChildRef {
            offset,
            size,
            error: (colour_lod_error(&cfull, &lod1, CW) + cerr + codec_err as f64) as f32,
            min_elevation: lo,
            max_elevation: hi,
        };
        Some((lod1, r, height))
    } else {
        None
    };
    Ok(Out {
        elev_lod1: lod::elevation_first_lod(&full, EW),
        elev_ref,
        colour,
    })
}

/// Build a database from `src` with tree shape `plan` into `out`.
pub fn build(
    src: &dyn GridSource,
    plan: &Plan,
    out: &Path,
    opts: &BuildOptions,
) -> Result<BuildStats, BuildError> {
    let pool = {
        let mut b = rayon::ThreadPoolBuilder::new();
        let mut n = opts
            .threads
            .unwrap_or_else(rayon::current_num_threads)
            .max(1);
        if let Some(m) = opts.grid_memory {
            n = n.min(threads_for_memory(m, plan.max_level() as usize + 1));
        }
        b = b.num_threads(n);
        b.build()?
    };
    pool.install(|| build_inner(src, plan, out, opts))
}

fn build_inner(
    src: &dyn GridSource,
    plan: &Plan,
    out: &Path,
    opts: &BuildOptions,
) -> Result<BuildStats, BuildError> {
    let start = Instant::now();
    let colour = src.has_colour() && plan.colour_level().is_some();
    let (ne, nc) = plan.block_counts();
    let total = ne + if colour { nc } else { 0 };
    let bar = if opts.quiet || !std::io::stderr().is_terminal() {
        ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::hidden())
    } else {
        let b = ProgressBar::new(total);
        if let Ok(style) = ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} records  ETA {eta}",
        ) {
            b.set_style(style);
        }
        b
    };
    let (elevation_codec, colour_codec) = opts.codecs.resolve(src.elevation_scale())?;
    // Id 3 at a nonzero bound encodes against decoded parents, which this
    // bottom-up pass does not have: the tree is written exact beside `out`
    // first, then re-encoded top-down ([`crate::transcode`]).
    let in_loop = matches!(elevation_codec, ElevationCodec::InLoop { max_error } if max_error > 0);
    let exact_pass = if in_loop {
        let mut name = out.file_name().unwrap_or_default().to_os_string();
        // The process id keeps a user's file and a concurrent build's
        // first pass out of its way.
        name.push(format!(".exact-pass-{}", std::process::id()));
        out.with_file_name(name)
    } else {
        out.to_path_buf()
    };
    let first = if in_loop {
        ElevationCodec::InLoop { max_error: 0 }
    } else {
        elevation_codec
    };
    let codecs = (first, elevation_codec.max_error(), colour_codec);
    let mut stats = build_pass(src, plan, &exact_pass, codecs, &bar, colour)?;
    if in_loop {
        bar.set_position(0);
        let t = crate::transcode::in_loop(&exact_pass, out, elevation_codec, &bar);
        let _ = std::fs::remove_file(&exact_pass);
        let t = t?;
        stats.file_bytes = t.file_bytes;
        stats.elevation_bytes = t.elevation_bytes;
    }
    bar.finish_and_clear();
    stats.seconds = start.elapsed().as_secs_f64();
    Ok(stats)
}

/// One bottom-up pass over `plan` into `out` with `(elevation codec, the
/// final max error, colour codec)`: the whole build, or an in-loop build's
/// exact first pass.
fn build_pass(
    src: &dyn GridSource,
    plan: &Plan,
    out: &Path,
    (elevation_codec, max_error, colour_codec): (ElevationCodec, u16, ColourCodec),
    bar: &ProgressBar,
    colour: bool,
) -> Result<BuildStats, BuildError> {
    let writer = DbWriter::create(out).map_err(|e| BuildError::write(out, e))?;
    let ctx = Ctx {
        elevation_codec,
        max_error,
        colour_codec,
        src,
        plan,
        writer: Mutex::new(Some(writer)),
        out_path: out,
        scale: src.elevation_scale(),
        bar: bar.clone(),
        e_records: AtomicU64::new(0),
        c_records: AtomicU64::new(0),
        e_bytes: AtomicU64::new(0),
        c_bytes: AtomicU64::new(0),
    };
    let roots: Result<Vec<Out>, BuildError> = Face::ALL
        .into_par_iter()
        .map(|f| build_block(&ctx, BlockId::root(f), colour))
        .collect();
    let roots = match roots {
        Ok(r) => r,
        Err(e) => {
            if let Some(w) = ctx.writer.lock().take() {
                w.abandon();
            }
            return Err(e);
        }
    };
    let min = roots
        .iter()
        .map(|r| r.elev_ref.min_elevation)
        .fold(f32::INFINITY, f32::min);
    let max = roots
        .iter()
        .map(|r| r.elev_ref.max_elevation)
        .fold(f32::NEG_INFINITY, f32::max);
    let header = Header {
        datum: src.datum(),
        elevation_scale: src.elevation_scale() as f32,
        elevation_offset: 0.0,
        min_elevation: min,
        max_elevation: max,
        elevation: TreeInfo {
            block_width: EW as u16,
            codec: elevation_codec,
            max_level: plan.max_level(),
            root_records: std::array::from_fn(|f| roots[f].elev_ref),
            root_first_lods: std::array::from_fn(|f| roots[f].elev_lod1.clone()),
        },
        colour: if colour {
            Some(TreeInfo {
                block_width: CW as u16,
                codec: colour_codec,
                max_level: plan.colour_max_level(),
                root_records: std::array::from_fn(|f| {
                    roots[f].colour.as_ref().map(|c| c.1).unwrap_or_default()
                }),
                root_first_lods: std::array::from_fn(|f| {
                    roots[f]
                        .colour
                        .as_ref()
                        .map(|c| c.0.clone())
                        .unwrap_or_default()
                }),
            })
        } else {
            None
        },
        description: src.description(),
    };
    let file_bytes = finish(ctx.writer.lock().take(), &header, out)?;
    let er = ctx.e_records.load(Ordering::Relaxed);
    let cr = ctx.c_records.load(Ordering::Relaxed);
    let ehalf = (EW / 2 + 1) as u64;
    let chalf = (CW / 2) as u64;
    Ok(BuildStats {
        elevation_records: er,
        colour_records: cr,
        elevation_samples: er * lod::elevation_new_samples(EW) as u64 + 6 * ehalf * ehalf,
        colour_samples: if colour {
            cr * (CW * CW - (CW / 2) * (CW / 2)) as u64 + 6 * chalf * chalf
        } else {
            0
        },
        file_bytes,
        elevation_bytes: ctx.e_bytes.load(Ordering::Relaxed),
        colour_bytes: ctx.c_bytes.load(Ordering::Relaxed),
        seconds: 0.0,
        max_level: plan.max_level(),
        colour_max_level: if colour { plan.colour_max_level() } else { 0 },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lod_error_matches_its_definition() {
        // The definition: max |LOD 0 − bilinear(LOD 1)|, the LOD 1 grid
        // being every other sample, interpolated within its 2 × 2 cells.
        let reference = |full: &[i16], w: usize| -> f64 {
            let side = w + 1;
            let at = |i: usize, j: usize| full[j * side + i] as f64;
            let mut e = 0f64;
            for j in 0..side {
                for i in 0..side {
                    let (i0, j0) = ((i / 2 * 2).min(w - 2), (j / 2 * 2).min(w - 2));
                    let v = [
                        at(i0, j0),
                        at(i0 + 2, j0),
                        at(i0, j0 + 2),
                        at(i0 + 2, j0 + 2),
                    ];
                    let (fc, fr) = ((i - i0) as f64 / 2.0, (j - j0) as f64 / 2.0);
                    e = e.max((at(i, j) - crate::source::bilinear(v, fc, fr)).abs());
                }
            }
            e
        };
        let mut x = 0x2545_f491_4f6c_dd1du64;
        for round in 0..200 {
            let w = 64;
            let amp = [1, 7, 300, 32767][round % 4];
            let full: Vec<i16> = (0..(w + 1) * (w + 1))
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    ((x % (2 * amp as u64 + 1)) as i64 - amp) as i16
                })
                .collect();
            assert_eq!(elevation_lod_error(&full, w), reference(&full, w));
        }
        // One odd sample out of a flat grid, at a cell centre and an edge middle.
        let mut flat = vec![5i16; 65 * 65];
        flat[65 + 1] = 9;
        assert_eq!(elevation_lod_error(&flat, 64), 4.0);
        flat[65 + 1] = 5;
        flat[2 * 65 + 1] = 3;
        assert_eq!(elevation_lod_error(&flat, 64), 2.0);
    }

    #[test]
    fn memory_bound_caps_threads() {
        // 1 GiB leaves any realistic machine's cores alone.
        assert!(threads_for_memory(1 << 30, 21) >= 64);
        // 8 levels deep in 8 MiB: 8 MiB / (8 × 512 KiB) = 2 workers.
        assert_eq!(threads_for_memory(8 << 20, 8), 2);
        // Never zero.
        assert_eq!(threads_for_memory(0, 12), 1);
    }
}
