//! `planet-preprocess`: builds planet databases (thesis Chapter 5: §5.2
//! re-projection, §5.3 server-file build, Alg. 5.2) from GeoTIFF rasters or
//! from a deterministic procedural planet, and reads them back (verify,
//! inspect, point sampling).
//!
//! - [`geotiff`]: GeoTIFF and SRTM `.hgt` rasters read by chunks on demand.
//! - [`crs`]: their CRS (GeoKeys → PROJ string → `proj4rs`) and surface.
//! - [`geoid`]: vertical datums (EGM96, EGM2008) to ellipsoidal heights.
//! - [`inputs`]: directories of tiles and list files as raster inputs.
//! - [`index`]: which rasters of a stack (thousands of tiles) may hold a
//!   block or a point.
//! - [`source`]: the elevation stack (finest covering source, void filling)
//!   and colour source, re-projected per block (thesis §5.2, Eq. 5.1).
//! - [`amplify`]: procedural detail beyond the sources in regions
//!   (thesis §6.2.2).
//! - [`plan`]: the tree shape, depth by region, graded (thesis §4.3.3).
//! - [`build`](mod@build): the bottom-up, depth-first, linear build (thesis Alg. 5.2).
//! - [`procedural`]: the procedural planet and [`build_procedural`].
//! - [`builtin`]: the built-in planet of `planet-view --local` and its named
//!   places.
//! - [`db`]: verify, inspect and sample a database (thesis §3.3.2).
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod amplify;
pub mod build;
pub mod builtin;
pub mod crs;
pub mod db;
pub mod error;
pub mod geoid;
pub mod geotiff;
pub mod index;
pub mod inputs;
pub mod plan;
pub mod procedural;
pub mod source;
pub mod transcode;
pub mod voidfill;

pub use build::{
    build, BuildOptions, BuildStats, CodecOptions, ColourQuality, ElevationChoice, GridSource,
};
pub use error::{BuildError, DbError, GeoError, RecordError};
pub use procedural::{
    build_procedural, check_procedural_options, default_procedural_options, DetailRegion,
    Procedural, ProceduralOptions,
};

use std::path::Path;

/// Options of a build from rasters.
#[derive(Debug, Clone)]
pub struct RasterOptions {
    /// Deepest level allowed.
    pub max_level: u8,
    /// Memory bound in MiB (raster chunk caches get half of it, in-flight
    /// grids the other half: see [`BuildOptions::grid_memory`]).
    pub max_memory_mb: usize,
    /// Worker threads.
    pub threads: Option<usize>,
    /// Hide progress bars.
    pub quiet: bool,
    /// The vertical datum of the elevation inputs' heights: empty, what
    /// each file declares, else EGM96 for int16 geographic DEMs
    /// ([`source::vertical_datum_of`]); one, every input's; one per input,
    /// in the order given.
    pub vertical: Vec<geoid::VerticalDatum>,
    /// Record codecs.
    pub codecs: CodecOptions,
    /// Regions built deeper than the sources, with procedural detail
    /// beyond them ([`amplify`]; empty: the sources' depth).
    pub detail: Vec<DetailRegion>,
    /// Seed of the detail's noise.
    pub seed: u64,
}

impl Default for RasterOptions {
    fn default() -> Self {
        RasterOptions {
            max_level: 16,
            max_memory_mb: 1024,
            threads: None,
            quiet: true,
            vertical: Vec::new(),
            codecs: CodecOptions::default(),
            detail: Vec::new(),
            seed: 1,
        }
    }
}

/// Open raster sources and plan their tree (for tests and tools); notes
/// (how each input's vertical datum was chosen) go to `note`.
pub fn open_rasters_noting(
    elevation: &[&Path],
    colour: Option<&Path>,
    opts: &RasterOptions,
    note: &mut dyn FnMut(String),
) -> Result<(source::RasterSource, plan::Plan), BuildError> {
    if elevation.is_empty() && colour.is_none() {
        return Err(BuildError::Options(
            "no elevation or colour source given".into(),
        ));
    }
    let mut cache = opts.max_memory_mb.max(8) << 19; // half the bound, in bytes
                                                     // EGM96's synthesis memory (its coefficient table, paged in, and one
                                                     // scratch per worker) comes out of the raster caches' half when an
                                                     // input may need it.
    if !(opts.vertical.len() <= 1 || opts.vertical.len() == elevation.len()) {
        return Err(BuildError::Options(format!(
            "{} vertical datums for {} elevation inputs (give one, or one per input)",
            opts.vertical.len(),
            elevation.len()
        )));
    }
    if opts.vertical.is_empty() || opts.vertical.contains(&geoid::VerticalDatum::Egm96) {
        let threads = opts.threads.unwrap_or_else(rayon::current_num_threads);
        let geoid = geoid::EGM96_FIXED_BYTES + threads * geoid::EGM96_THREAD_BYTES;
        cache = cache.saturating_sub(geoid).max(cache / 4);
    }
    let stack = source::ElevationStack::open_capped(
        elevation,
        cache * 3 / 4,
        &opts.vertical,
        opts.max_level,
        note,
    )?;
    let colour = match colour {
        Some(p) => Some(source::ColourSource::open_capped(
            p,
            cache / 4,
            opts.max_level,
            note,
        )?),
        None => None,
    };
    let datum = source::check_same_datum(
        stack
            .layers
            .iter()
            .map(|l| &l.tiff)
            .chain(colour.as_ref().map(|c| &c.tiff)),
    )?
    .unwrap_or(planet_core::Datum::WGS84);
    let amplify = amplifier(&stack, &datum, opts)?;
    let plan = match (&colour, stack.layers.is_empty()) {
        // Colour alone: a zero elevation tree as deep as the colour needs
        // where the colour raster lies (colour blocks exist only where
        // elevation blocks do, thesis §4.4.1).
        (Some(c), true) => {
            let level = c.level.min(opts.max_level);
            plan::plan_by(
                |b| {
                    if source::footprint_intersects(&c.tiff, b) {
                        level
                    } else {
                        0
                    }
                },
                Some(level),
            )
        }
        _ => {
            let max_elev = stack.layers.iter().map(|l| l.level).max().unwrap_or(0);
            let colour_level = colour.as_ref().map(|c| c.level.min(max_elev));
            match &amplify {
                None => plan::plan_for_sources(&stack, colour_level, opts.max_level),
                Some(a) => plan::plan_by(
                    |b| {
                        a.caps()
                            .iter()
                            .filter(|c| plan::block_meets_cap(b, c))
                            .map(|c| c.level)
                            .fold(stack.level_needed(b).min(opts.max_level), u8::max)
                    },
                    colour_level,
                ),
            }
        }
    };
    Ok((
        source::RasterSource {
            elevation: stack,
            colour,
            scale: 1.0,
            datum,
            amplify,
        },
        plan,
    ))
}

/// The detail of `opts.detail` over the stack: regions must be deeper than
/// the finest elevation source and no deeper than `max_level`.
fn amplifier(
    stack: &source::ElevationStack,
    datum: &planet_core::Datum,
    opts: &RasterOptions,
) -> Result<Option<amplify::Amplifier>, BuildError> {
    if opts.detail.is_empty() {
        return Ok(None);
    }
    let Some(finest) = stack.layers.iter().map(|l| l.level).max() else {
        return Err(BuildError::Options(
            "--detail adds detail to elevation sources: give --elevation FILE...".into(),
        ));
    };
    for r in &opts.detail {
        if r.level <= finest || r.level > opts.max_level {
            return Err(BuildError::Options(format!(
                "--detail {r}: LEVEL {} must be deeper than the finest elevation source \
                 (level {finest}) and at most --max-level {}",
                r.level, opts.max_level
            )));
        }
    }
    Ok(Some(amplify::Amplifier::new(
        opts.seed,
        opts.detail.iter().map(|r| r.cap(datum)).collect(),
        finest,
        datum.equatorial_radius(),
    )))
}

/// [`open_rasters_noting`] with the notes dropped.
pub fn open_rasters(
    elevation: &[&Path],
    colour: Option<&Path>,
    opts: &RasterOptions,
) -> Result<(source::RasterSource, plan::Plan), BuildError> {
    open_rasters_noting(elevation, colour, opts, &mut |_| {})
}

/// Build a database from rasters (elevation stack and/or colour).
pub fn build_rasters(
    elevation: &[&Path],
    colour: Option<&Path>,
    out: &Path,
    opts: &RasterOptions,
) -> Result<BuildStats, BuildError> {
    build_rasters_noting(elevation, colour, out, opts, &mut |_| {})
}

/// [`build_rasters`], with notes on the inputs (vertical datums chosen).
pub fn build_rasters_noting(
    elevation: &[&Path],
    colour: Option<&Path>,
    out: &Path,
    opts: &RasterOptions,
    note: &mut dyn FnMut(String),
) -> Result<BuildStats, BuildError> {
    let (src, plan) = open_rasters_noting(elevation, colour, opts, note)?;
    build(
        &src,
        &plan,
        out,
        &BuildOptions {
            threads: opts.threads,
            quiet: opts.quiet,
            // The raster caches get half of the bound; the grids the rest.
            grid_memory: Some(opts.max_memory_mb.max(8) << 19),
            codecs: opts.codecs,
        },
    )
}

/// What [`resample_rasters`] did.
#[derive(Debug, Clone, Copy, Default)]
pub struct ResampleStats {
    /// Leaf grids re-projected.
    pub leaves: u64,
    /// Samples computed (`65²` per leaf grid).
    pub samples: u64,
    /// Wall time in seconds (re-projection and sampling only: the rasters
    /// are opened and the tree planned before the clock starts).
    pub seconds: f64,
    /// Sum of the stored heights (keeps the work observable).
    pub checksum: i64,
}

/// Re-project and sample every elevation leaf grid of the build's tree, in
/// parallel, and nothing else (no LODs, encoding or writing): the
/// re-projection part of a build, measured alone (`planet-build resample`).
pub fn resample_rasters(
    elevation: &[&Path],
    opts: &RasterOptions,
) -> Result<ResampleStats, BuildError> {
    use rayon::prelude::*;
    let (src, plan) = open_rasters(elevation, None, opts)?;
    let leaves = match &plan {
        plan::Plan::Explicit { split, .. } => plan::leaves(split),
        plan::Plan::Uniform { .. } => Vec::new(),
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.threads.unwrap_or_else(rayon::current_num_threads))
        .build()?;
    let side = source::ELEVATION_WIDTH + 1;
    let start = std::time::Instant::now();
    let checksum = pool.install(|| {
        leaves
            .par_iter()
            .map_init(
                || vec![0i16; side * side],
                |grid, &b| -> Result<i64, BuildError> {
                    src.elevation_leaf(b, grid)?;
                    Ok(grid.iter().map(|&v| v as i64).sum())
                },
            )
            .try_reduce(|| 0, |a, b| Ok(a + b))
    })?;
    Ok(ResampleStats {
        leaves: leaves.len() as u64,
        samples: (leaves.len() * side * side) as u64,
        seconds: start.elapsed().as_secs_f64(),
        checksum,
    })
}
