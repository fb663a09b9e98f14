//! Raster sources re-projected onto cube-face blocks (thesis §5.2, Eq. 5.1,
//! Alg. 5.1; see docs/REFERENCES.md).
//!
//! Instead of re-projecting whole face maps to disk first (Alg. 5.1), each
//! leaf block samples its grid straight from the sources: elevation sample
//! `(i, j)` of block `(face, L, x, y)` is at `s = (x·W + i)/(W·2^L)`,
//! `t = (y·W + j)/(W·2^L)`, mapped to latitude/longitude by the inverse
//! equal-angle map (with the erratum of Eq. 5.1 fixed in `planet_core::cube`).
//!
//! - Several elevation rasters stack: the finest one covering a point wins,
//!   with bilinear interpolation inside it. Longitude wraps at the
//!   antimeridian for global rasters; rows clamp at the poles.
//! - Voids (GDAL no-data, and -32768 in int16 SRTM) are never stored, nor
//!   stored as pits: a void pixel takes a "delta surface fill", the next
//!   coarser raster's value at its position (e.g. ETOPO5 under SRTM, as the
//!   thesis filled SRTM gaps from BMNG, §5.1) plus the harmonic (Laplace)
//!   interpolation over the void of the differences fine − coarse measured
//!   on the valid pixels bordering it ([`crate::voidfill`]). With no coarser
//!   raster under it, the fine values themselves are interpolated. The
//!   filled surface thus meets the surrounding terrain without a step even
//!   where the coarse value is 1000 m off (a 0.5° ETOPO5 cell at a summit).
//!
//!   Fills are computed lazily, the first time a void of a raster is read,
//!   and kept within a bound (sparse: only the void pixels). The transient memory of a fill
//!   is about [`FILL_BYTES_PER_CELL`] bytes per window pixel and must fit
//!   a fill's share of the memory budget (half of the rasters' budget, the
//!   chunk cache having the other half, divided among the fills that may
//!   run at once, one per worker and layer, and the fill tables kept, which
//!   are evicted least recently used first and computed again if needed
//!   again): a raster that fits (an SRTM
//!   tile of 1201² needs ~70 MB) is filled as a whole, so every void region
//!   sees its whole border; a larger one is filled per square tile within a
//!   window with a margin of a sixth of the window (the window's edge acts
//!   as a mirror, so only voids wider than the margin see less than their
//!   full border). The harmonic fill is solved on the bounding box of a
//!   window's voids and the pixels around it.
//! - Colour comes from one RGB8 (or grey) raster, sampled bilinearly at texel
//!   centres `(x·Wc + i + ½)/(Wc·2^L)`.

use crate::build::GridSource;
use crate::error::{BuildError, GeoError};
use crate::geoid::{self, Egm96Grid, Egm96Reader, VerticalDatum};
use crate::geotiff::{ChunkCache, GeoTiff, GridPoints, TiffReader};
use crate::index::LayerIndex;
use parking_lot::Mutex;
use planet_core::cube::{plane_from_angle, sample_coord};
use planet_core::lod::Rgb;
use planet_core::{BlockId, Datum, FaceCoord};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

/// Transient bytes per window pixel of a void fill (grids and pyramid).
pub const FILL_BYTES_PER_CELL: usize = 48;

/// Bytes a kept fill table takes per void pixel (a hash map of u64 to f64
/// with its control bytes and spare capacity).
pub const FILL_TABLE_BYTES_PER_VOID: usize = 40;

/// Fill tables kept: `(layer, window)` by use, with their bytes.
struct KeptFills {
    lru: lru::LruCache<(usize, (u32, u32)), usize>,
    bytes: usize,
}

/// Filled values (metres) of the void pixels of one fill window, by
/// `row · width + col` of the raster.
type FillTable = HashMap<u64, f64>;
/// Per layer: fill tables by window key, each computed once.
type FillCache = Mutex<HashMap<(u32, u32), Arc<Mutex<Option<Arc<FillTable>>>>>>;

/// Elevation block width used by this preprocessor.
pub const ELEVATION_WIDTH: usize = 64;
/// Colour block width used by this preprocessor.
pub const COLOUR_WIDTH: usize = 128;

/// The tree level whose sample spacing matches a raster: the smallest `L`
/// with `w·2^L ≥ cells per 90°`.
pub fn level_for(cells_per_quarter: f64, w: usize) -> u8 {
    let mut l = 0u8;
    while (w as f64) * 2f64.powi(l as i32) < cells_per_quarter - 1e-6 && l < 30 {
        l += 1;
    }
    l
}

/// One elevation raster of the stack.
pub struct Layer {
    /// The raster.
    pub tiff: GeoTiff,
    /// Its tree level (elevation width 64).
    pub level: u8,
    /// The vertical datum of its heights (converted to ellipsoidal heights
    /// when sampled, [`crate::geoid`]).
    pub vertical: VerticalDatum,
    /// EGM96 node spacing for this layer, degrees ([`geoid::spacing_for`]).
    pub geoid_spacing: f64,
}

/// A stack of elevation rasters, coarsest first.
pub struct ElevationStack {
    /// Layers sorted by increasing level (coarse to fine).
    pub layers: Vec<Layer>,
    fills: Vec<FillCache>,
    /// The fill tables kept (by layer and window), least recently used
    /// first out once their bytes pass `fill_budget`: the voids of
    /// thousands of tiles stay within the memory bound, a table evicted is
    /// computed again (the same) if needed again.
    kept: Mutex<KeptFills>,
    /// Per layer, the fill computations that may run at once (one per
    /// worker; a fill of layer i only reads fills of coarser layers, so
    /// these never wait in a cycle).
    computing: Vec<Permits>,
    /// Bytes a layer's fill window may take.
    fill_budget: usize,
    /// EGM96 undulation nodes shared by the layers.
    geoid: Egm96Grid,
    /// Which layers may hold a block or point.
    index: LayerIndex,
}

/// The vertical datum of an elevation raster: `chosen` if given, else what
/// the file declares, else EGM96 for an int16 DEM in a geographic Earth CRS
/// (SRTM, Copernicus and most national DEMs), else the ellipsoid. The
/// second value says which rule decided, for the build's notes.
pub fn vertical_datum_of(
    t: &GeoTiff,
    chosen: Option<VerticalDatum>,
) -> (VerticalDatum, &'static str) {
    if let Some(v) = chosen {
        return (v, "given");
    }
    if let Some(v) = t.vertical {
        return (v, "declared by the file");
    }
    if t.kind == crate::geotiff::SampleKind::I16
        && t.crs.geographic
        && t.crs.datum.body() == Some(planet_core::datum::Body::Earth)
    {
        return (
            VerticalDatum::Egm96,
            "not declared; taken as EGM96 for an int16 geographic DEM",
        );
    }
    (
        VerticalDatum::Ellipsoid,
        "not declared; taken as ellipsoidal",
    )
}

/// `t`, or its coarsest overview whose level (for blocks `w` samples wide)
/// is still at least `max_level` where `t` itself is finer than that.
pub fn overview_for(
    t: GeoTiff,
    max_level: u8,
    w: usize,
    note: &mut dyn FnMut(String),
) -> Result<GeoTiff, GeoError> {
    let full = level_for(t.cells_per_quarter(), w);
    if full <= max_level {
        return Ok(t);
    }
    for k in (0..t.overviews().len()).rev() {
        let (_, ow, oh) = t.overviews()[k];
        let estimate = t.cells_per_quarter() * ow as f64 / t.width as f64;
        if level_for(estimate, w) < max_level {
            continue;
        }
        let ov = t.overview(k)?;
        let level = level_for(ov.cells_per_quarter(), w);
        if level >= max_level {
            note(format!(
                "{}: overview {ow} × {oh} (level {level}) read for a tree of level {max_level} \
                 (the full {} × {} raster is level {full})",
                t.path().display(),
                t.width,
                t.height
            ));
            return Ok(ov);
        }
    }
    Ok(t)
}

/// Check that every raster lies on the same surface; the error names the
/// first two that differ.
pub fn check_same_datum<'a>(
    rasters: impl IntoIterator<Item = &'a GeoTiff>,
) -> Result<Option<Datum>, GeoError> {
    let mut first: Option<&GeoTiff> = None;
    for t in rasters {
        match first {
            None => first = Some(t),
            Some(f) if f.crs.datum != t.crs.datum => {
                let describe = |g: &GeoTiff| {
                    let d = g.crs.datum;
                    format!(
                        "{} ({}, a = {} m, b = {} m)",
                        g.crs.name,
                        d.name().unwrap_or_else(|| "unknown body".into()),
                        d.equatorial_radius(),
                        d.polar_radius()
                    )
                };
                return Err(GeoError::MixedDatums {
                    first: f.path().to_path_buf(),
                    first_datum: describe(f),
                    second: t.path().to_path_buf(),
                    second_datum: describe(t),
                });
            }
            Some(_) => {}
        }
    }
    Ok(first.map(|f| f.crs.datum))
}

impl ElevationStack {
    /// Open elevation rasters, heights kept as they are (no vertical datum
    /// conversion); the cache bound is shared between them.
    pub fn open(paths: &[&Path], cache_bytes: usize) -> Result<ElevationStack, GeoError> {
        ElevationStack::open_with(paths, cache_bytes, &[VerticalDatum::Ellipsoid], &mut |_| {})
    }

    /// Open elevation rasters whose heights are in `vertical` (empty: per
    /// file, see [`vertical_datum_of`]; one: all; else the i-th input's);
    /// `note` receives one line per file whose vertical datum was not given.
    pub fn open_with(
        paths: &[&Path],
        cache_bytes: usize,
        vertical: &[VerticalDatum],
        note: &mut dyn FnMut(String),
    ) -> Result<ElevationStack, GeoError> {
        ElevationStack::open_capped(paths, cache_bytes, vertical, u8::MAX, note)
    }

    /// [`ElevationStack::open_with`] for a tree no deeper than `max_level`:
    /// a raster finer than that level is read from its coarsest overview
    /// (Cloud-Optimized GeoTIFF) still at least as fine, and `note` says
    /// which.
    pub fn open_capped(
        paths: &[&Path],
        cache_bytes: usize,
        vertical: &[VerticalDatum],
        max_level: u8,
        note: &mut dyn FnMut(String),
    ) -> Result<ElevationStack, GeoError> {
        // One chunk cache for every layer, however many, with half of the
        // bound; the other half is shared by the fills that can run at once
        // (one window per worker) and the fill tables kept.
        let cache = ChunkCache::new((cache_bytes / 2).max(1 << 20));
        let concurrent = rayon::current_num_threads().max(1);
        let per = (cache_bytes / 2 / (concurrent + 1)).max(1 << 20);
        let mut layers = Vec::new();
        for (i, p) in paths.iter().enumerate() {
            let vertical = match vertical {
                [] => None,
                [one] => Some(*one),
                many => many.get(i).copied(),
            };
            let tiff = overview_for(
                GeoTiff::open_in(p, &cache)?,
                max_level,
                ELEVATION_WIDTH,
                note,
            )?;
            if !tiff.kind.is_elevation() {
                return Err(GeoError::Role {
                    path: p.to_path_buf(),
                    what: format!("{:?} is not an elevation sample type", tiff.kind),
                });
            }
            let (v, why) = vertical_datum_of(&tiff, vertical);
            if vertical.is_none() {
                note(format!("{}: vertical datum {v} ({why})", p.display()));
            }
            if v != VerticalDatum::Ellipsoid
                && tiff.crs.datum.body() != Some(planet_core::datum::Body::Earth)
            {
                return Err(GeoError::Role {
                    path: p.to_path_buf(),
                    what: format!(
                        "vertical datum {v} is an Earth geoid, but the raster is on {}",
                        tiff.crs
                            .datum
                            .name()
                            .unwrap_or_else(|| "another body".into())
                    ),
                });
            }
            let level = level_for(tiff.cells_per_quarter(), ELEVATION_WIDTH);
            let geoid_spacing = geoid::spacing_for(tiff.spacing_deg());
            layers.push(Layer {
                tiff,
                level,
                vertical: v,
                geoid_spacing,
            });
        }
        check_same_datum(layers.iter().map(|l| &l.tiff))?;
        layers.sort_by(|a, b| {
            a.tiff
                .cells_per_quarter()
                .partial_cmp(&b.tiff.cells_per_quarter())
                .unwrap_or(std::cmp::Ordering::Equal)
        });
        let fills = layers.iter().map(|_| Mutex::new(HashMap::new())).collect();
        let computing = layers.iter().map(|_| Permits::new(concurrent)).collect();
        Ok(ElevationStack {
            index: LayerIndex::new(layers.iter().map(|l| &l.tiff)),
            layers,
            fills,
            kept: Mutex::new(KeptFills {
                lru: lru::LruCache::unbounded(),
                bytes: 0,
            }),
            computing,
            fill_budget: per,
            geoid: Egm96Grid::new(),
        })
    }

    /// The surface the layers lie on (WGS84 for none).
    pub fn datum(&self) -> Datum {
        self.layers
            .first()
            .map_or(Datum::WGS84, |l| l.tiff.crs.datum)
    }

    /// A reader of the stack with per-layer chunk memos (one per worker and
    /// block: see [`crate::geotiff::TiffReader`]).
    pub fn reader(&self) -> StackReader<'_> {
        StackReader {
            stack: self,
            readers: Vec::new(),
            geoid: self.geoid.reader(),
        }
    }

    /// Elevation in metres above the ellipsoid at (lat, lon) degrees: the
    /// finest covering layer, bilinear, voids filled, converted from the
    /// layer's vertical datum. 0 where nothing covers the point.
    pub fn sample(&self, lat: f64, lon: f64) -> Result<f64, GeoError> {
        self.reader().sample(lat, lon)
    }

    /// Bilinear sample of layer `idx` (voids filled).
    pub fn sample_layer(&self, idx: usize, lat: f64, lon: f64) -> Result<f64, GeoError> {
        self.reader().sample_layer(idx, lat, lon)
    }

    /// Value of one pixel of layer `idx`, voids filled.
    pub fn pixel(&self, idx: usize, col: i64, row: i64) -> Result<f64, GeoError> {
        self.reader().pixel(idx, col, row)
    }

    /// The finest level of any layer whose footprint intersects the block.
    pub fn level_needed(&self, b: BlockId) -> u8 {
        let mut best = 0;
        for idx in self.index.near_block(b) {
            let l = &self.layers[idx];
            if l.level > best && footprint_intersects(&l.tiff, b) {
                best = l.level;
            }
        }
        best
    }

    /// The layers whose footprints may meet block `b` (stack order).
    pub fn layers_near(&self, b: BlockId) -> Vec<usize> {
        self.index.near_block(b)
    }
}

/// Reads of an [`ElevationStack`] by one worker (lock-free on chunk hits).
pub struct StackReader<'a> {
    stack: &'a ElevationStack,
    /// Readers of the layers used so far (a few of a stack's thousands).
    readers: Vec<(usize, TiffReader<'a>)>,
    geoid: Egm96Reader<'a>,
}

impl<'a> StackReader<'a> {
    /// The reader of layer `idx`.
    #[inline]
    fn rd(&mut self, idx: usize) -> &mut TiffReader<'a> {
        let pos = match self.readers.iter().position(|r| r.0 == idx) {
            Some(p) => p,
            None => {
                self.readers
                    .push((idx, self.stack.layers[idx].tiff.reader()));
                self.readers.len() - 1
            }
        };
        &mut self.readers[pos].1
    }

    /// Layer `idx`'s raster.
    #[inline]
    fn tiff(&self, idx: usize) -> &'a GeoTiff {
        &self.stack.layers[idx].tiff
    }

    /// [`ElevationStack::sample`].
    pub fn sample(&mut self, lat: f64, lon: f64) -> Result<f64, GeoError> {
        for idx in self.stack.index.near_point(lat, lon).into_iter().rev() {
            if self.tiff(idx).covers(lat, lon) {
                return self.sample_layer(idx, lat, lon);
            }
        }
        Ok(0.0)
    }

    /// [`ElevationStack::sample_layer`].
    pub fn sample_layer(&mut self, idx: usize, lat: f64, lon: f64) -> Result<f64, GeoError> {
        let (c, r) = self.tiff(idx).pixel_of(lat, lon);
        self.sample_layer_at(idx, lat, lon, c, r)
    }

    /// Elevations (m above the ellipsoid) of a row-major grid of `nx × ny`
    /// points, as [`StackReader::sample`] at each from the candidate
    /// `layers` (stack order, e.g. [`ElevationStack::layers_near`] its
    /// block), with each layer's pixel
    /// coordinates from [`GeoTiff::pixels_of_grid`] (computed for a layer
    /// only once a point needs it). The pixels around the points a layer
    /// holds are copied once into a `Window`; a point whose 4 pixels are
    /// valued there is interpolated from it (valued pixels are neither
    /// voids nor outside a footprint), others pixel by pixel (wrapping,
    /// clamping, void filling): the same values either way.
    pub fn sample_grid(
        &mut self,
        layers: &[usize],
        pts: &mut GridPoints<'_>,
        nx: usize,
        ny: usize,
        out: &mut [f64],
    ) -> Result<(), GeoError> {
        out.fill(0.0);
        // Points not yet given a value, finest layer first.
        let mut todo: Vec<usize> = (0..pts.len()).collect();
        let mut rest = Vec::new();
        let mut px = Vec::new();
        for &idx in layers.iter().rev() {
            if todo.is_empty() {
                break;
            }
            let t = self.tiff(idx);
            t.pixels_of_grid(pts, nx, ny, &mut px);
            let win = Window::around(self.rd(idx), &px, WINDOW_PIXELS_PER_POINT * pts.len())?;
            let (wmax, hmax) = ((t.width - 1) as f64, (t.height - 1) as f64);
            rest.clear();
            for &k in &todo {
                let (c, r) = px[k];
                let inside = c >= 0.0 && c <= wmax && r >= 0.0 && r <= hmax;
                // c, r ≥ 0: the casts are floors.
                let (ci, ri) = (c as i64, r as i64);
                let quad = match &win {
                    Some(w) if inside => w.quad(ci, ri),
                    _ => None,
                };
                if let Some(q) = quad {
                    let v = q.map(f64::from);
                    out[k] = self.height(idx, pts, k, v, c - ci as f64, r - ri as f64);
                } else if t.covers_pixel(c, r) {
                    let (lat, lon) = if self.stack.layers[idx].vertical == VerticalDatum::Ellipsoid
                    {
                        (f64::NAN, f64::NAN)
                    } else {
                        pts.lat_lon(k)
                    };
                    out[k] = self.sample_layer_at(idx, lat, lon, c, r)?;
                } else {
                    rest.push(k);
                }
            }
            std::mem::swap(&mut todo, &mut rest);
        }
        Ok(())
    }

    /// Height above the ellipsoid of grid point `k` from the bilinear
    /// interpolation of layer `idx`'s 4 pixels `v` at `(fc, fr)`.
    #[inline]
    fn height(
        &mut self,
        idx: usize,
        pts: &mut GridPoints<'_>,
        k: usize,
        v: [f64; 4],
        fc: f64,
        fr: f64,
    ) -> f64 {
        let l = &self.stack.layers[idx];
        let n = match l.vertical {
            VerticalDatum::Ellipsoid => 0.0,
            vd => {
                let (lat, lon) = pts.lat_lon(k);
                geoid::undulation(vd, &mut self.geoid, lat, lon, l.geoid_spacing)
            }
        };
        bilinear(v, fc, fr) + n
    }

    /// Bilinear sample of layer `idx` at pixel coordinates `(c, r)` of the
    /// point (lat, lon), voids filled, converted to ellipsoidal height.
    fn sample_layer_at(
        &mut self,
        idx: usize,
        lat: f64,
        lon: f64,
        c: f64,
        r: f64,
    ) -> Result<f64, GeoError> {
        let (c0, r0) = (c.floor(), r.floor());
        let (fc, fr) = (c - c0, r - r0);
        let (c0, r0) = (c0 as i64, r0 as i64);
        let mut v = [0f64; 4];
        // The 2 × 2 pixels from one chunk where they lie in one and hold no
        // void; else pixel by pixel (wrapping, clamping, filling).
        match self.rd(idx).quad(c0, r0)? {
            Some(q) if q.iter().all(|x| !x.is_nan()) => {
                for k in 0..4 {
                    v[k] = q[k] as f64;
                }
            }
            _ => {
                for (k, (dc, dr)) in [(0, 0), (1, 0), (0, 1), (1, 1)].into_iter().enumerate() {
                    v[k] = self.pixel(idx, c0 + dc, r0 + dr)?;
                }
            }
        }
        let l = &self.stack.layers[idx];
        let n = geoid::undulation(l.vertical, &mut self.geoid, lat, lon, l.geoid_spacing);
        Ok(bilinear(v, fc, fr) + n)
    }

    /// [`ElevationStack::pixel`].
    pub fn pixel(&mut self, idx: usize, col: i64, row: i64) -> Result<f64, GeoError> {
        let v = self.rd(idx).elevation(col, row)?;
        if !v.is_nan() {
            return Ok(v as f64);
        }
        let t = self.tiff(idx);
        let (c, r) = t.clamp_pixel(col, row);
        if t.is_exterior(c as i64, r as i64) {
            // Outside a re-projected raster's footprint: no void to fill
            // (and no fill window to compute for it).
            return Ok(0.0);
        }
        let key = (c as u64) + (r as u64) * t.width as u64;
        let table = self.stack.fill_table(idx, c, r)?;
        Ok(table.get(&key).copied().unwrap_or(0.0))
    }

    /// The value of the next coarser layer covering the position of pixel
    /// `(col, row)` of layer `idx`, if any.
    fn coarse_under(&mut self, idx: usize, col: i64, row: i64) -> Result<Option<f64>, GeoError> {
        let (lat, lon) = self.tiff(idx).position_of(col, row);
        let near = self.stack.index.near_point(lat, lon);
        for j in near.into_iter().filter(|&j| j < idx).rev() {
            if self.tiff(j).covers(lat, lon) {
                return self.sample_layer(j, lat, lon).map(Some);
            }
        }
        Ok(None)
    }
}

/// A counting semaphore (std has none): at most `n` holders at once.
struct Permits {
    free: Mutex<usize>,
    freed: parking_lot::Condvar,
}

/// A held [`Permits`] permit, given back when dropped.
struct Permit<'a>(&'a Permits);

impl Permits {
    fn new(n: usize) -> Permits {
        Permits {
            free: Mutex::new(n.max(1)),
            freed: parking_lot::Condvar::new(),
        }
    }

    fn acquire(&self) -> Permit<'_> {
        let mut free = self.free.lock();
        while *free == 0 {
            self.freed.wait(&mut free);
        }
        *free -= 1;
        Permit(self)
    }
}

impl Drop for Permit<'_> {
    fn drop(&mut self) {
        *self.0.free.lock() += 1;
        self.0.freed.notify_one();
    }
}

/// Bilinear interpolation of pixels `v` (`(c0, r0)`, `(c0+1, r0)`,
/// `(c0, r0+1)`, `(c0+1, r0+1)`) at fractions `(fc, fr)` from the first.
#[inline]
pub fn bilinear(v: [f64; 4], fc: f64, fr: f64) -> f64 {
    let top = v[0] + (v[1] - v[0]) * fc;
    let bot = v[2] + (v[3] - v[2]) * fc;
    top + (bot - top) * fr
}

/// Largest [`Window`] read for a grid, in pixels per grid point (a coarse
/// block over a fine raster is sampled pixel by pixel instead).
const WINDOW_PIXELS_PER_POINT: usize = 16;

/// A layer's raw pixels (NaN: void or outside the footprint) around the
/// points of one grid, copied from its chunks once.
struct Window {
    c0: i64,
    r0: i64,
    w: i64,
    h: i64,
    data: Vec<f32>,
}

impl Window {
    /// The pixels around the points of `grid` inside the raster, unless
    /// none is or they would take more than `max` pixels.
    fn around(
        rd: &mut TiffReader<'_>,
        grid: &[(f64, f64)],
        max: usize,
    ) -> Result<Option<Window>, GeoError> {
        let t = rd.tiff();
        let (wmax, hmax) = ((t.width - 1) as f64, (t.height - 1) as f64);
        let (mut c_lo, mut c_hi, mut r_lo, mut r_hi) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &(c, r) in grid {
            if c >= 0.0 && c <= wmax && r >= 0.0 && r <= hmax {
                c_lo = c_lo.min(c);
                c_hi = c_hi.max(c);
                r_lo = r_lo.min(r);
                r_hi = r_hi.max(r);
            }
        }
        if c_lo > c_hi {
            return Ok(None);
        }
        // Non-negative: the casts are floors.
        let (c0, r0) = (c_lo as u32, r_lo as u32);
        let c1 = (c_hi as u32 + 1).min(t.width - 1);
        let r1 = (r_hi as u32 + 1).min(t.height - 1);
        let (w, h) = (c1 - c0 + 1, r1 - r0 + 1);
        if w as usize * h as usize > max {
            return Ok(None);
        }
        let mut data = Vec::new();
        rd.window((c0, r0), (w, h), &mut data)?;
        Ok(Some(Window {
            c0: c0 as i64,
            r0: r0 as i64,
            w: w as i64,
            h: h as i64,
            data,
        }))
    }

    /// Pixels `(c, r)`, `(c+1, r)`, `(c, r+1)`, `(c+1, r+1)` where all 4
    /// lie in the window and are valued.
    #[inline]
    fn quad(&self, c: i64, r: i64) -> Option<[f32; 4]> {
        let (x, y) = (c - self.c0, r - self.r0);
        if x < 0 || y < 0 || x + 1 >= self.w || y + 1 >= self.h {
            return None;
        }
        let (i, w) = ((y * self.w + x) as usize, self.w as usize);
        let q = [
            *self.data.get(i)?,
            *self.data.get(i + 1)?,
            *self.data.get(i + w)?,
            *self.data.get(i + w + 1)?,
        ];
        q.iter().all(|v| !v.is_nan()).then_some(q)
    }
}

impl ElevationStack {
    /// Whether layer `idx` is void-filled as a whole, else the tile side and
    /// margin of its fill windows, from the memory budget.
    fn fill_geometry(&self, idx: usize) -> (bool, u32, u32) {
        let t = &self.layers[idx].tiff;
        let cap = (self.fill_budget / FILL_BYTES_PER_CELL).max(64 * 64) as u64;
        if t.width as u64 * t.height as u64 <= cap {
            return (true, 0, 0);
        }
        let side = (cap as f64).sqrt() as u32;
        let margin = (side / 6).clamp(8, 128);
        (false, side - 2 * margin, margin)
    }

    /// The fill table of the window holding pixel `(c, r)` (in the raster)
    /// of layer `idx`, computed on first use.
    fn fill_table(&self, idx: usize, c: u32, r: u32) -> Result<Arc<FillTable>, GeoError> {
        let (whole, tile, margin) = self.fill_geometry(idx);
        let key = if whole { (0, 0) } else { (c / tile, r / tile) };
        let slot = self.fills[idx].lock().entry(key).or_default().clone();
        let mut slot = slot.lock();
        if let Some(tb) = &*slot {
            self.kept.lock().lru.promote(&(idx, key));
            return Ok(tb.clone());
        }
        let permit = self.computing[idx].acquire();
        let tb = Arc::new(self.compute_fill(idx, whole, key, tile, margin)?);
        drop(permit);
        *slot = Some(tb.clone());
        drop(slot);
        self.keep(idx, key, tb.len() * FILL_TABLE_BYTES_PER_VOID);
        Ok(tb)
    }

    /// Count a new fill table in the kept set and evict the least recently
    /// used ones over the budget (never the newest).
    fn keep(&self, idx: usize, key: (u32, u32), bytes: usize) {
        let mut k = self.kept.lock();
        if let Some(old) = k.lru.put((idx, key), bytes) {
            k.bytes -= old;
        }
        k.bytes += bytes;
        while k.bytes > self.fill_budget && k.lru.len() > 1 {
            match k.lru.pop_lru() {
                Some(((l, old_key), b)) => {
                    k.bytes -= b;
                    self.fills[l].lock().remove(&old_key);
                }
                None => break,
            }
        }
    }

    /// Bytes of the fill tables kept now.
    pub fn kept_fill_bytes(&self) -> usize {
        self.kept.lock().bytes
    }

    /// Delta surface fill of one window of layer `idx` (see the module
    /// documentation).
    fn compute_fill(
        &self,
        idx: usize,
        whole: bool,
        key: (u32, u32),
        tile: u32,
        margin: u32,
    ) -> Result<FillTable, GeoError> {
        let t = &self.layers[idx].tiff;
        let (w_all, h_all) = (t.width as i64, t.height as i64);
        // Window [c0, c1) × [r0, r1) (columns may wrap for a global raster)
        // and the part of it whose voids are kept.
        let (c0, c1, r0, r1, keep) = if whole {
            (0, w_all, 0, h_all, (0, w_all, 0, h_all))
        } else {
            let (kc0, kr0) = (key.0 as i64 * tile as i64, key.1 as i64 * tile as i64);
            let (kc1, kr1) = (
                (kc0 + tile as i64).min(w_all),
                (kr0 + tile as i64).min(h_all),
            );
            let m = margin as i64;
            let (c0, c1) = if t.is_global() {
                (kc0 - m, kc1 + m)
            } else {
                ((kc0 - m).max(0), (kc1 + m).min(w_all))
            };
            (
                c0,
                c1,
                (kr0 - m).max(0),
                (kr1 + m).min(h_all),
                (kc0, kc1, kr0, kr1),
            )
        };
        let (w, h) = ((c1 - c0) as usize, (r1 - r0) as usize);
        let mut rd = self.reader();
        let mut raw = Vec::new();
        if c0 >= 0 && c1 <= w_all {
            rd.rd(idx)
                .window((c0 as u32, r0 as u32), (w as u32, h as u32), &mut raw)?;
        } else {
            // Columns wrap (a global raster's window across the antimeridian).
            raw.resize(w * h, 0.0);
            for y in 0..h {
                for x in 0..w {
                    raw[y * w + x] = rd.rd(idx).elevation(c0 + x as i64, r0 + y as i64)?;
                }
            }
        }
        // Voids: no-data pixels, except outside a re-projected raster's
        // footprint (left unknown: neither void nor border).
        let is_void: Vec<bool> = (0..w * h)
            .map(|i| raw[i].is_nan() && !t.is_exterior(c0 + (i % w) as i64, r0 + (i / w) as i64))
            .collect();
        // The fill is solved on the voids' bounding box and the pixels
        // bordering it: every void's 4 neighbours lie in it (or outside the
        // window, a mirror either way), so the harmonic system is the same.
        let (mut x_lo, mut x_hi, mut y_lo, mut y_hi) = (usize::MAX, 0, usize::MAX, 0);
        for (i, _) in is_void.iter().enumerate().filter(|v| *v.1) {
            let (x, y) = (i % w, i / w);
            (x_lo, x_hi, y_lo, y_hi) = (x_lo.min(x), x_hi.max(x), y_lo.min(y), y_hi.max(y));
        }
        let mut table = FillTable::new();
        if x_lo > x_hi {
            return Ok(table);
        }
        let (x_lo, y_lo) = (x_lo.saturating_sub(1), y_lo.saturating_sub(1));
        let (x_hi, y_hi) = ((x_hi + 1).min(w - 1), (y_hi + 1).min(h - 1));
        let (sw, sh) = (x_hi - x_lo + 1, y_hi - y_lo + 1);
        // Delta field: known on the valid pixels bordering a void, unknown
        // (NaN) on the voids; other valid pixels do not enter the harmonic
        // fill and are left unknown too (the push-pull guess fills them).
        let mut delta = vec![f64::NAN; sw * sh];
        let mut base = vec![0f64; sw * sh];
        let mut voids = Vec::new();
        for y in y_lo..=y_hi {
            for x in x_lo..=x_hi {
                let i = y * w + x;
                let void = is_void[i];
                let border = !raw[i].is_nan()
                    && ((x > 0 && is_void[i - 1])
                        || (x + 1 < w && is_void[i + 1])
                        || (y > 0 && is_void[i - w])
                        || (y + 1 < h && is_void[i + w]));
                if void || border {
                    let si = (y - y_lo) * sw + (x - x_lo);
                    if void {
                        voids.push(si);
                    }
                    let b = rd
                        .coarse_under(idx, c0 + x as i64, r0 + y as i64)?
                        .unwrap_or(0.0);
                    base[si] = b;
                    if border {
                        delta[si] = raw[i] as f64 - b;
                    }
                }
            }
        }
        crate::voidfill::harmonic_fill(&mut delta, sw, sh, &voids);
        for y in y_lo..=y_hi {
            for x in x_lo..=x_hi {
                let (si, i) = ((y - y_lo) * sw + (x - x_lo), y * w + x);
                let (c, r) = (c0 + x as i64, r0 + y as i64);
                let inside = c >= keep.0 && c < keep.1 && r >= keep.2 && r < keep.3;
                if is_void[i] && inside {
                    table.insert(c as u64 + r as u64 * t.width as u64, base[si] + delta[si]);
                }
            }
        }
        Ok(table)
    }
}

/// Whether a raster's footprint intersects a block (sampled test: block
/// points inside the raster, or raster points inside the block).
pub fn footprint_intersects(t: &GeoTiff, b: BlockId) -> bool {
    if t.is_global() {
        return true;
    }
    let (s0, t0, s1, t1) = b.extent();
    let n = 16i64;
    for j in 0..=n {
        for i in 0..=n {
            let fc = FaceCoord {
                face: b.face,
                s: s0 + (s1 - s0) * i as f64 / n as f64,
                t: t0 + (t1 - t0) * j as f64 / n as f64,
            };
            if !t.box_holds(fc.direction()) {
                continue;
            }
            let (la, lo) = fc.to_lat_lon();
            if t.covers(la.to_degrees(), lo.to_degrees()) {
                return true;
            }
        }
    }
    // Raster points inside the block (a raster smaller than the block).
    t.lattice_points()
        .iter()
        .any(|fc| fc.face == b.face && fc.s >= s0 && fc.s <= s1 && fc.t >= t0 && fc.t <= t1)
}

/// Face coordinates of the elevation samples of a block, per column/row.
pub fn elevation_coords(b: BlockId, w: usize) -> Vec<f64> {
    let n = (w as u64) << b.level;
    (0..=w as u64)
        .map(|i| sample_coord(b.x as u64 * w as u64 + i, n))
        .collect()
}

/// Latitude/longitude (radians) of elevation sample `(i, j)` of a block.
pub fn elevation_sample_lat_lon(b: BlockId, w: usize, i: usize, j: usize) -> (f64, f64) {
    let n = (w as u64) << b.level;
    FaceCoord {
        face: b.face,
        s: sample_coord(b.x as u64 * w as u64 + i as u64, n),
        t: sample_coord(b.y as u64 * w as u64 + j as u64, n),
    }
    .to_lat_lon()
}

/// Latitude/longitude (radians) of colour texel centre `(i, j)` of a block.
pub fn colour_texel_lat_lon(b: BlockId, w: usize, i: usize, j: usize) -> (f64, f64) {
    let n = (w as f64) * 2f64.powi(b.level as i32);
    FaceCoord {
        face: b.face,
        s: (b.x as f64 * w as f64 + i as f64 + 0.5) / n,
        t: (b.y as f64 * w as f64 + j as f64 + 0.5) / n,
    }
    .to_lat_lon()
}

/// Gnomonic plane coordinates of a block's elevation sample columns.
pub fn plane_coords(coords: &[f64]) -> Vec<f64> {
    coords.iter().map(|&s| plane_from_angle(s)).collect()
}

/// A single colour raster.
pub struct ColourSource {
    /// The raster.
    pub tiff: GeoTiff,
    /// Its tree level (colour width 128).
    pub level: u8,
}

impl ColourSource {
    /// Open a colour raster.
    pub fn open(path: &Path, cache_bytes: usize) -> Result<ColourSource, GeoError> {
        ColourSource::open_capped(path, cache_bytes, u8::MAX, &mut |_| {})
    }

    /// [`ColourSource::open`] for a tree no deeper than `max_level` (a
    /// finer raster's overview, as [`overview_for`]).
    pub fn open_capped(
        path: &Path,
        cache_bytes: usize,
        max_level: u8,
        note: &mut dyn FnMut(String),
    ) -> Result<ColourSource, GeoError> {
        let tiff = GeoTiff::open(path, cache_bytes.max(1 << 20))?;
        let tiff = overview_for(tiff, max_level, COLOUR_WIDTH, note)?;
        if tiff.kind.is_elevation() {
            return Err(GeoError::Role {
                path: path.to_path_buf(),
                what: format!("{:?} is not a colour sample type", tiff.kind),
            });
        }
        let level = level_for(tiff.cells_per_quarter(), COLOUR_WIDTH);
        Ok(ColourSource { tiff, level })
    }

    /// Bilinear colour at (lat, lon) degrees.
    pub fn sample(&self, lat: f64, lon: f64) -> Result<Rgb, GeoError> {
        Self::sample_with(&mut self.tiff.reader(), lat, lon)
    }

    /// [`ColourSource::sample`] through a worker's reader of this raster.
    pub fn sample_with(rd: &mut TiffReader<'_>, lat: f64, lon: f64) -> Result<Rgb, GeoError> {
        let (c, r) = rd.tiff().pixel_of(lat, lon);
        Self::sample_px(rd, c, r)
    }

    /// Bilinear colour at fractional pixel `(c, r)` (black where the
    /// projection does not reach).
    pub fn sample_px(rd: &mut TiffReader<'_>, c: f64, r: f64) -> Result<Rgb, GeoError> {
        if !(c.is_finite() && r.is_finite()) {
            return Ok([0; 3]);
        }
        let (c0, r0) = (c.floor(), r.floor());
        let (fc, fr) = (c - c0, r - r0);
        let (c0, r0) = (c0 as i64, r0 as i64);
        let p = [
            rd.colour(c0, r0)?,
            rd.colour(c0 + 1, r0)?,
            rd.colour(c0, r0 + 1)?,
            rd.colour(c0 + 1, r0 + 1)?,
        ];
        let mut out = [0u8; 3];
        for ch in 0..3 {
            let top = p[0][ch] as f64 + (p[1][ch] as f64 - p[0][ch] as f64) * fc;
            let bot = p[2][ch] as f64 + (p[3][ch] as f64 - p[2][ch] as f64) * fc;
            out[ch] = (top + (bot - top) * fr).round().clamp(0.0, 255.0) as u8;
        }
        Ok(out)
    }
}

/// Real-data source: an elevation stack and an optional colour raster. A
/// stack of no layers is a constant zero height on the datum (colour-only
/// databases: the header's elevation tree is required, so it holds zeros).
pub struct RasterSource {
    /// Elevation rasters.
    pub elevation: ElevationStack,
    /// Colour raster.
    pub colour: Option<ColourSource>,
    /// Metres per stored unit.
    pub scale: f64,
    /// The surface the rasters lie on.
    pub datum: Datum,
    /// Procedural detail beyond the sources in regions (`--detail`).
    pub amplify: Option<crate::amplify::Amplifier>,
}

/// The description token naming the vertical datum the elevation sources
/// were in (`planet-build sample` reads it back to print heights in it).
pub const VERTICAL_TOKEN: &str = "vertical-datum=";

/// Quantise metres to stored units.
#[inline]
pub fn quantise(m: f64, scale: f64) -> i16 {
    (m / scale)
        .round()
        .clamp(i16::MIN as f64 + 1.0, i16::MAX as f64) as i16
}

impl GridSource for RasterSource {
    fn elevation_leaf(&self, b: BlockId, out: &mut [i16]) -> Result<(), BuildError> {
        // Equal-angle grid: the tangents are per column and per row; each
        // sample's direction is then `normalize(cube_point(u, v))`, exactly
        // `elevation_sample_lat_lon`'s arithmetic.
        let w = ELEVATION_WIDTH;
        let n = (w as u64) << b.level;
        let axis = |o: u32| -> Vec<f64> {
            (0..=w as u64)
                .map(|i| plane_from_angle(sample_coord(o as u64 * w as u64 + i, n)))
                .collect()
        };
        let mut pts = GridPoints::from_axes(b.face, axis(b.x), axis(b.y));
        let mut m = vec![0f64; pts.len()];
        let near = self.elevation.layers_near(b);
        self.elevation
            .reader()
            .sample_grid(&near, &mut pts, w + 1, w + 1, &mut m)?;
        if let Some(a) = &self.amplify {
            a.add(&self.elevation, b, &pts, &near, &mut m)?;
        }
        for (o, v) in out.iter_mut().zip(&m) {
            *o = quantise(*v, self.scale);
        }
        Ok(())
    }

    fn colour_leaf(&self, b: BlockId, _elevation: &[i16]) -> Result<Vec<Rgb>, BuildError> {
        let w = COLOUR_WIDTH;
        let Some(c) = &self.colour else {
            return Ok(vec![[0; 3]; w * w]);
        };
        let n = (w as f64) * 2f64.powi(b.level as i32);
        let axis = |o: u32| -> Vec<f64> {
            (0..w)
                .map(|i| plane_from_angle((o as f64 * w as f64 + i as f64 + 0.5) / n))
                .collect()
        };
        let mut px = Vec::new();
        let mut pts = GridPoints::from_axes(b.face, axis(b.x), axis(b.y));
        c.tiff.pixels_of_grid(&mut pts, w, w, &mut px);
        let mut rd = c.tiff.reader();
        let mut out = Vec::with_capacity(w * w);
        for (k, &(col, row)) in px.iter().enumerate() {
            out.push(if col.is_finite() {
                ColourSource::sample_px(&mut rd, col, row)?
            } else {
                // Outside the raster's box: its nearest edge, as before.
                let (la, lo) = pts.lat_lon(k);
                ColourSource::sample_with(&mut rd, la, lo)?
            });
        }
        Ok(out)
    }

    fn datum(&self) -> Datum {
        self.datum
    }

    fn elevation_scale(&self) -> f64 {
        self.scale
    }

    fn has_colour(&self) -> bool {
        self.colour.is_some()
    }

    fn description(&self) -> String {
        let mut s = String::from("planet-build from rasters: elevation");
        if self.elevation.layers.is_empty() {
            s.push_str(" none (zero height on the datum)");
        }
        for l in &self.elevation.layers {
            s.push_str(&format!(
                " {} ({}, {}, L{})",
                l.tiff.path().display(),
                l.tiff.crs.name,
                l.vertical,
                l.level
            ));
        }
        if let Some(c) = &self.colour {
            s.push_str(&format!(
                "; colour {} ({}, L{})",
                c.tiff.path().display(),
                c.tiff.crs.name,
                c.level
            ));
        }
        if let Some(a) = &self.amplify {
            s.push_str(&format!(
                "; procedural detail beyond L{} in {} region(s) to L{}",
                a.source_level(),
                a.caps().len(),
                a.caps().iter().map(|c| c.level).max().unwrap_or(0)
            ));
        }
        // One vertical datum for the whole database where the sources
        // share one; heights are stored ellipsoidal in any case.
        let mut v = self.elevation.layers.iter().map(|l| l.vertical);
        if let Some(first) = v.next() {
            if v.all(|x| x == first) {
                s.push_str(&format!(
                    "; heights stored above the ellipsoid; {VERTICAL_TOKEN}{first}"
                ));
            } else {
                s.push_str(&format!(
                    "; heights stored above the ellipsoid; {VERTICAL_TOKEN}mixed"
                ));
            }
        }
        s
    }
}
