//! Raster sources re-projected onto cube-face blocks (thesis §5.2, Eq. 5.1,
//! Alg. 5.1; thesis-notes §9.7).
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
//!   and kept (sparse: only the void pixels). The transient memory of a fill
//!   is about [`FILL_BYTES_PER_CELL`] bytes per window pixel and must fit
//!   the layer's share of the memory budget: a raster that fits (an SRTM
//!   tile of 1201² needs ~70 MB) is filled as a whole, so every void region
//!   sees its whole border; a larger one is filled per square tile within a
//!   window with a margin of a sixth of the window (the window's edge acts
//!   as a mirror, so only voids wider than the margin see less than their
//!   full border). One fill per layer runs at a time, bounding the peak.
//! - Colour comes from one RGB8 (or grey) raster, sampled bilinearly at texel
//!   centres `(x·Wc + i + ½)/(Wc·2^L)`.

use crate::build::GridSource;
use crate::error::{BuildError, GeoError};
use crate::geoid::{self, Egm96Grid, Egm96Reader, VerticalDatum};
use crate::geotiff::{GeoTiff, GridPoints, TiffReader};
use parking_lot::Mutex;
use planet_core::cube::{normalize, plane_from_angle, sample_coord};
use planet_core::lod::Rgb;
use planet_core::{BlockId, Datum, FaceCoord};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

/// Transient bytes per window pixel of a void fill (grids and pyramid).
pub const FILL_BYTES_PER_CELL: usize = 48;

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
    /// One fill computation per layer at a time (a fill of layer i only
    /// reads fills of coarser layers, so these never wait in a cycle).
    computing: Vec<Mutex<()>>,
    /// Bytes a layer's fill window may take.
    fill_budget: usize,
    /// EGM96 undulation nodes shared by the layers.
    geoid: Egm96Grid,
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
        let per = (cache_bytes / paths.len().max(1)).max(1 << 20);
        let mut layers = Vec::new();
        for (i, p) in paths.iter().enumerate() {
            let vertical = match vertical {
                [] => None,
                [one] => Some(*one),
                many => many.get(i).copied(),
            };
            let tiff = GeoTiff::open(p, per)?;
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
        let computing = layers.iter().map(|_| Mutex::new(())).collect();
        Ok(ElevationStack {
            layers,
            fills,
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
            layers: self.layers.iter().map(|l| l.tiff.reader()).collect(),
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
        for l in &self.layers {
            if l.level > best && footprint_intersects(&l.tiff, b) {
                best = l.level;
            }
        }
        best
    }
}

/// Reads of an [`ElevationStack`] by one worker (lock-free on chunk hits).
pub struct StackReader<'a> {
    stack: &'a ElevationStack,
    layers: Vec<TiffReader<'a>>,
    geoid: Egm96Reader<'a>,
}

impl StackReader<'_> {
    /// [`ElevationStack::sample`].
    pub fn sample(&mut self, lat: f64, lon: f64) -> Result<f64, GeoError> {
        for idx in (0..self.layers.len()).rev() {
            if self.layers[idx].tiff().covers(lat, lon) {
                return self.sample_layer(idx, lat, lon);
            }
        }
        Ok(0.0)
    }

    /// [`ElevationStack::sample_layer`].
    pub fn sample_layer(&mut self, idx: usize, lat: f64, lon: f64) -> Result<f64, GeoError> {
        let (c, r) = self.layers[idx].tiff().pixel_of(lat, lon);
        self.sample_layer_at(idx, lat, lon, c, r)
    }

    /// Elevations (m above the ellipsoid) of a row-major grid of `nx × ny`
    /// points, as [`StackReader::sample`] at each, with each layer's pixel
    /// coordinates from [`GeoTiff::pixels_of_grid`] (computed for a layer
    /// only once a point needs it).
    pub fn sample_grid(
        &mut self,
        pts: &mut GridPoints<'_>,
        nx: usize,
        ny: usize,
        out: &mut [f64],
    ) -> Result<(), GeoError> {
        let n = self.layers.len();
        let mut px: Vec<Option<Vec<(f64, f64)>>> = vec![None; n];
        for k in 0..pts.len() {
            out[k] = 0.0;
            for idx in (0..n).rev() {
                let grid = px[idx].get_or_insert_with(|| {
                    let mut v = Vec::new();
                    self.layers[idx].tiff().pixels_of_grid(pts, nx, ny, &mut v);
                    v
                });
                let (c, r) = grid[k];
                if self.layers[idx].tiff().covers_pixel(c, r) {
                    let (lat, lon) = if self.stack.layers[idx].vertical == VerticalDatum::Ellipsoid
                    {
                        (f64::NAN, f64::NAN)
                    } else {
                        pts.lat_lon(k)
                    };
                    out[k] = self.sample_layer_at(idx, lat, lon, c, r)?;
                    break;
                }
            }
        }
        Ok(())
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
        match self.layers[idx].quad(c0, r0)? {
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
        let top = v[0] + (v[1] - v[0]) * fc;
        let bot = v[2] + (v[3] - v[2]) * fc;
        let l = &self.stack.layers[idx];
        let n = geoid::undulation(l.vertical, &mut self.geoid, lat, lon, l.geoid_spacing);
        Ok(top + (bot - top) * fr + n)
    }

    /// [`ElevationStack::pixel`].
    pub fn pixel(&mut self, idx: usize, col: i64, row: i64) -> Result<f64, GeoError> {
        let v = self.layers[idx].elevation(col, row)?;
        if !v.is_nan() {
            return Ok(v as f64);
        }
        let t = self.layers[idx].tiff();
        let (c, r) = t.clamp_pixel(col, row);
        let key = (c as u64) + (r as u64) * t.width as u64;
        let table = self.stack.fill_table(idx, c, r)?;
        Ok(table.get(&key).copied().unwrap_or(0.0))
    }

    /// The value of the next coarser layer covering the position of pixel
    /// `(col, row)` of layer `idx`, if any.
    fn coarse_under(&mut self, idx: usize, col: i64, row: i64) -> Result<Option<f64>, GeoError> {
        let (lat, lon) = self.layers[idx].tiff().position_of(col, row);
        for j in (0..idx).rev() {
            if self.layers[j].tiff().covers(lat, lon) {
                return self.sample_layer(j, lat, lon).map(Some);
            }
        }
        Ok(None)
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
            return Ok(tb.clone());
        }
        let _one = self.computing[idx].lock();
        let tb = Arc::new(self.compute_fill(idx, whole, key, tile, margin)?);
        *slot = Some(tb.clone());
        Ok(tb)
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
        let mut raw = vec![0f64; w * h];
        for y in 0..h {
            for x in 0..w {
                raw[y * w + x] = rd.layers[idx].elevation(c0 + x as i64, r0 + y as i64)? as f64;
            }
        }
        // Delta field: known on the valid pixels bordering a void, unknown
        // (NaN) on the voids; other valid pixels do not enter the harmonic
        // fill and are left unknown too (the push-pull guess fills them).
        let mut delta = vec![f64::NAN; w * h];
        let mut base = vec![0f64; w * h];
        let mut voids = Vec::new();
        // Voids: no-data pixels, except outside a re-projected raster's
        // footprint (left unknown: neither void nor border).
        let is_void: Vec<bool> = (0..w * h)
            .map(|i| raw[i].is_nan() && !t.is_exterior(c0 + (i % w) as i64, r0 + (i / w) as i64))
            .collect();
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let void = is_void[i];
                let border = !raw[i].is_nan()
                    && ((x > 0 && is_void[i - 1])
                        || (x + 1 < w && is_void[i + 1])
                        || (y > 0 && is_void[i - w])
                        || (y + 1 < h && is_void[i + w]));
                if void || border {
                    if void {
                        voids.push(i);
                    }
                    let b = rd
                        .coarse_under(idx, c0 + x as i64, r0 + y as i64)?
                        .unwrap_or(0.0);
                    base[i] = b;
                    if border {
                        delta[i] = raw[i] - b;
                    }
                }
            }
        }
        let mut table = FillTable::new();
        if voids.is_empty() {
            return Ok(table);
        }
        crate::voidfill::harmonic_fill(&mut delta, w, h, &voids);
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let (c, r) = (c0 + x as i64, r0 + y as i64);
                let inside = c >= keep.0 && c < keep.1 && r >= keep.2 && r < keep.3;
                if is_void[i] && inside {
                    table.insert(c as u64 + r as u64 * t.width as u64, base[i] + delta[i]);
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
            let (la, lo) = fc.to_lat_lon();
            if t.covers(la.to_degrees(), lo.to_degrees()) {
                return true;
            }
        }
    }
    // Raster points inside the block (a raster smaller than the block).
    let (w, h) = (t.width as i64 - 1, t.height as i64 - 1);
    for j in 0..=n {
        for i in 0..=n {
            let (la, lo) = t.position_of(w * i / n, h * j / n);
            if !la.is_finite() {
                continue;
            }
            let fc = FaceCoord::from_lat_lon(la.to_radians(), lo.to_radians());
            if fc.face == b.face && fc.s >= s0 && fc.s <= s1 && fc.t >= t0 && fc.t <= t1 {
                return true;
            }
        }
    }
    false
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
        let tiff = GeoTiff::open(path, cache_bytes.max(1 << 20))?;
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
        let (us, vs) = (axis(b.x), axis(b.y));
        let mut dirs = Vec::with_capacity((w + 1) * (w + 1));
        for &v in &vs {
            for &u in &us {
                dirs.push(normalize(b.face.cube_point(u, v)));
            }
        }
        let mut pts = GridPoints::new(&dirs);
        let mut m = vec![0f64; dirs.len()];
        self.elevation
            .reader()
            .sample_grid(&mut pts, w + 1, w + 1, &mut m)?;
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
        let (us, vs) = (axis(b.x), axis(b.y));
        let mut dirs = Vec::with_capacity(w * w);
        for &v in &vs {
            for &u in &us {
                dirs.push(normalize(b.face.cube_point(u, v)));
            }
        }
        let mut px = Vec::new();
        let mut pts = GridPoints::new(&dirs);
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
