//! `planet-preprocess`: builds planet databases (thesis Chapter 5: §5.2
//! re-projection, §5.3 server-file build, Alg. 5.2) from GeoTIFF rasters or
//! from a deterministic procedural planet, and reads them back (verify,
//! inspect, point sampling).
//!
//! - [`geotiff`]: EPSG:4326 GeoTIFF rasters read by strips/tiles on demand.
//! - [`source`]: the elevation stack (finest covering source, void filling)
//!   and colour source, re-projected per block (thesis §5.2, Eq. 5.1).
//! - [`plan`]: the tree shape, depth by region, graded (thesis §4.3.3).
//! - [`build`]: the bottom-up, depth-first, linear build (thesis Alg. 5.2).
//! - [`procedural`]: the procedural planet and [`build_procedural`].
//! - [`db`]: verify, inspect and sample a database (thesis §3.3.2).
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod build;
pub mod db;
pub mod error;
pub mod geotiff;
pub mod plan;
pub mod procedural;
pub mod source;
pub mod voidfill;

pub use build::{
    build, BuildOptions, BuildStats, CodecOptions, ColourQuality, ElevationChoice, GridSource,
};
pub use error::{BuildError, DbError, GeoError};
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
    /// Record codecs.
    pub codecs: CodecOptions,
}

impl Default for RasterOptions {
    fn default() -> Self {
        RasterOptions {
            max_level: 16,
            max_memory_mb: 1024,
            threads: None,
            quiet: true,
            codecs: CodecOptions::default(),
        }
    }
}

/// Open raster sources and plan their tree (for tests and tools).
pub fn open_rasters(
    elevation: &[&Path],
    colour: Option<&Path>,
    opts: &RasterOptions,
) -> Result<(source::RasterSource, plan::Plan), BuildError> {
    if elevation.is_empty() {
        return Err(BuildError::Options("no elevation source given".into()));
    }
    let cache = opts.max_memory_mb.max(8) << 19; // half the bound, in bytes
    let stack = source::ElevationStack::open(elevation, cache * 3 / 4)?;
    let colour = match colour {
        Some(p) => Some(source::ColourSource::open(p, cache / 4)?),
        None => None,
    };
    let max_elev = stack.layers.iter().map(|l| l.level).max().unwrap_or(0);
    let colour_level = colour.as_ref().map(|c| c.level.min(max_elev));
    let plan = plan::plan_for_sources(&stack, colour_level, opts.max_level);
    Ok((
        source::RasterSource {
            elevation: stack,
            colour,
            scale: 1.0,
        },
        plan,
    ))
}

/// Build a database from GeoTIFF rasters (elevation stack, optional colour).
pub fn build_rasters(
    elevation: &[&Path],
    colour: Option<&Path>,
    out: &Path,
    opts: &RasterOptions,
) -> Result<BuildStats, BuildError> {
    let (src, plan) = open_rasters(elevation, colour, opts)?;
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
