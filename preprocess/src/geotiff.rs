//! GeoTIFF (EPSG:4326) rasters read by strips or tiles on demand.
//!
//! The input side of thesis §5.1–5.2 (thesis-notes §9.7): the thesis reads a
//! "dually tiled map format" whose rectangular windows are loaded on demand;
//! here the TIFF's own strips/tiles are the unit, decoded lazily and kept in a
//! bounded LRU cache (`cache_bytes`), so a raster larger than the memory bound
//! is never loaded whole.
//!
//! Georeferencing: ModelPixelScale (33550), ModelTiepoint (33922), the
//! GeoKeyDirectory (34735: GTModelType must be 2 = geographic, GeographicType
//! 4326 or absent; GTRasterType 1 = pixel-is-area, the value of a pixel is at
//! its centre, 2 = pixel-is-point) and GDAL_NODATA (42113, ASCII).

use crate::error::GeoError;
use parking_lot::Mutex;
use std::collections::HashMap;
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tiff::decoder::{Decoder, DecodingResult, Limits};
use tiff::tags::Tag;
use tiff::ColorType;

/// The sample type of a raster.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleKind {
    /// Signed 16-bit elevation.
    I16,
    /// Unsigned 16-bit elevation.
    U16,
    /// 32-bit float elevation.
    F32,
    /// 8-bit RGB colour.
    Rgb8,
    /// 8-bit grey colour (replicated to RGB).
    Grey8,
}

impl SampleKind {
    /// Whether this is an elevation type.
    pub fn is_elevation(self) -> bool {
        matches!(self, SampleKind::I16 | SampleKind::U16 | SampleKind::F32)
    }
    fn bytes(self) -> usize {
        match self {
            SampleKind::Rgb8 | SampleKind::Grey8 => 3,
            _ => 4,
        }
    }
}

/// One decoded strip or tile.
enum Chunk {
    /// Elevation in source units, NaN for voids.
    Elev(Vec<f32>),
    /// Colour.
    Rgb(Vec<[u8; 3]>),
}

/// A cheap hasher for chunk indices (SipHash showed up at 14 % of a build).
#[derive(Default, Clone, Copy)]
struct IdxHasher(u64);

impl std::hash::Hasher for IdxHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ b as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        }
    }
    fn write_u32(&mut self, v: u32) {
        self.0 = (v as u64 ^ self.0).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }
}

type IdxBuild = std::hash::BuildHasherDefault<IdxHasher>;

struct Cache {
    map: HashMap<u32, (Arc<Chunk>, u64), IdxBuild>,
    stamp: u64,
    bytes: usize,
}

/// A georeferenced raster in geographic coordinates (degrees).
pub struct GeoTiff {
    path: PathBuf,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Sample type.
    pub kind: SampleKind,
    /// Longitude (degrees) of the value of pixel column 0.
    pub lon0: f64,
    /// Latitude (degrees) of the value of pixel row 0.
    pub lat0: f64,
    /// Degrees of longitude per column.
    pub dx: f64,
    /// Degrees of latitude per row (positive: rows go south).
    pub dy: f64,
    /// The GDAL no-data value, if any.
    pub nodata: Option<f64>,
    /// Whether the raster is pixel-is-point (else pixel-is-area).
    pub pixel_is_point: bool,
    chunk_w: u32,
    chunk_h: u32,
    chunks_across: u32,
    /// Idle decoders: a worker takes one (or opens a new one) to decode a
    /// chunk, so several chunks decode in parallel.
    decoders: Mutex<Vec<Decoder<BufReader<File>>>>,
    cache: Mutex<Cache>,
    cache_bytes: usize,
}

fn terr(path: &Path, e: impl std::fmt::Display) -> GeoError {
    GeoError::Tiff {
        path: path.to_path_buf(),
        msg: e.to_string(),
    }
}

impl GeoTiff {
    /// Open a GeoTIFF and read its georeferencing; `cache_bytes` bounds the
    /// decoded strips/tiles kept in memory (at least one chunk is kept).
    pub fn open(path: &Path, cache_bytes: usize) -> Result<GeoTiff, GeoError> {
        let file = File::open(path).map_err(|e| GeoError::Open {
            path: path.to_path_buf(),
            source: e,
        })?;
        let mut dec = Decoder::new(BufReader::new(file))
            .map_err(|e| terr(path, e))?
            .with_limits(Limits::unlimited());
        let (width, height) = dec.dimensions().map_err(|e| terr(path, e))?;
        let ct = dec.colortype().map_err(|e| terr(path, e))?;
        let fmt = dec
            .find_tag_unsigned::<u16>(Tag::SampleFormat)
            .ok()
            .flatten()
            .unwrap_or(1);
        let kind = match (ct, fmt) {
            (ColorType::Gray(16), 2) => SampleKind::I16,
            (ColorType::Gray(16), 1) => SampleKind::U16,
            (ColorType::Gray(32), 3) => SampleKind::F32,
            (ColorType::RGB(8), _) | (ColorType::YCbCr(8), _) => SampleKind::Rgb8,
            (ColorType::Gray(8), 1) => SampleKind::Grey8,
            (other, f) => {
                return Err(GeoError::UnsupportedSampleType {
                    path: path.to_path_buf(),
                    what: format!("{other:?} with sample format {f}"),
                })
            }
        };
        let missing = |what: &str| GeoError::Georeference {
            path: path.to_path_buf(),
            what: what.to_string(),
        };
        let scale = dec
            .get_tag_f64_vec(Tag::ModelPixelScaleTag)
            .map_err(|_| missing("no ModelPixelScale tag (33550)"))?;
        let tie = dec
            .get_tag_f64_vec(Tag::ModelTiepointTag)
            .map_err(|_| missing("no ModelTiepoint tag (33922)"))?;
        if scale.len() < 2 || tie.len() < 6 || !(scale[0] > 0.0 && scale[1] > 0.0) {
            return Err(missing("malformed pixel scale or tie point"));
        }
        let mut pixel_is_point = false;
        if let Ok(keys) = dec.get_tag_u16_vec(Tag::GeoKeyDirectoryTag) {
            let n = keys.get(3).copied().unwrap_or(0) as usize;
            for k in 0..n {
                let Some(e) = keys.get(4 + 4 * k..8 + 4 * k) else {
                    break;
                };
                let (id, loc, val) = (e[0], e[1], e[3]);
                if loc != 0 {
                    continue;
                }
                match id {
                    1024 if val != 2 => {
                        return Err(GeoError::WrongCrs {
                            path: path.to_path_buf(),
                            what: format!("GTModelType {val} (need 2, geographic)"),
                        })
                    }
                    1025 => pixel_is_point = val == 2,
                    2048 if val != 4326 => {
                        return Err(GeoError::WrongCrs {
                            path: path.to_path_buf(),
                            what: format!("GeographicType {val} (need 4326)"),
                        })
                    }
                    3072 => {
                        return Err(GeoError::WrongCrs {
                            path: path.to_path_buf(),
                            what: format!("projected CRS {val}"),
                        })
                    }
                    _ => {}
                }
            }
        }
        let nodata = dec
            .get_tag_ascii_string(Tag::GdalNodata)
            .ok()
            .and_then(|s| {
                s.trim_matches(|c: char| c == '\0' || c.is_whitespace())
                    .parse()
                    .ok()
            });
        let (dx, dy) = (scale[0], scale[1]);
        let a = if pixel_is_point { 0.0 } else { 0.5 };
        let lon0 = tie[3] + (a - tie[0]) * dx;
        let lat0 = tie[4] - (a - tie[1]) * dy;
        let (chunk_w, chunk_h) = dec.chunk_dimensions();
        if chunk_w == 0 || chunk_h == 0 {
            return Err(terr(path, "zero chunk dimensions"));
        }
        let chunks_across = width.div_ceil(chunk_w);
        Ok(GeoTiff {
            path: path.to_path_buf(),
            width,
            height,
            kind,
            lon0,
            lat0,
            dx,
            dy,
            nodata,
            pixel_is_point,
            chunk_w,
            chunk_h,
            chunks_across,
            decoders: Mutex::new(vec![dec]),
            cache: Mutex::new(Cache {
                map: HashMap::default(),
                stamp: 0,
                bytes: 0,
            }),
            cache_bytes,
        })
    }

    /// The file this raster was read from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether the raster spans all longitudes (columns wrap).
    pub fn is_global(&self) -> bool {
        self.width as f64 * self.dx >= 360.0 - 1e-9
    }

    /// Fractional pixel coordinates `(col, row)` of a point (degrees);
    /// longitude is shifted by ±360° to the raster's range where that helps.
    pub fn pixel_of(&self, lat: f64, lon: f64) -> (f64, f64) {
        let row = (self.lat0 - lat) / self.dy;
        let mut col = (lon - self.lon0) / self.dx;
        let span = 360.0 / self.dx;
        let w = self.width as f64;
        if !self.is_global() {
            if col < -0.5 && col + span <= w {
                col += span;
            } else if col > w - 0.5 && col - span >= -1.0 {
                col -= span;
            }
        }
        (col, row)
    }

    /// Position (lat, lon degrees) of a pixel's value.
    pub fn position_of(&self, col: i64, row: i64) -> (f64, f64) {
        (
            self.lat0 - row as f64 * self.dy,
            self.lon0 + col as f64 * self.dx,
        )
    }

    /// Whether the point lies between the first and last pixel values (so
    /// bilinear interpolation needs no extrapolation). Global rasters cover
    /// every longitude and clamp at the poles.
    pub fn covers(&self, lat: f64, lon: f64) -> bool {
        let (c, r) = self.pixel_of(lat, lon);
        if self.is_global() {
            return true;
        }
        c >= 0.0 && c <= (self.width - 1) as f64 && r >= 0.0 && r <= (self.height - 1) as f64
    }

    /// Bounding box `(lat_min, lat_max, lon_min, lon_max)` of the pixel values.
    pub fn bounds(&self) -> (f64, f64, f64, f64) {
        let lat1 = self.lat0;
        let lat0 = self.lat0 - (self.height - 1) as f64 * self.dy;
        let lon0 = self.lon0;
        let lon1 = self.lon0 + (self.width - 1) as f64 * self.dx;
        (lat0, lat1, lon0, lon1)
    }

    /// Wrap/clamp pixel indices into the raster.
    pub fn clamp_pixel(&self, col: i64, row: i64) -> (u32, u32) {
        let w = self.width as i64;
        let c = if self.is_global() {
            col.rem_euclid(w)
        } else {
            col.clamp(0, w - 1)
        };
        (c as u32, row.clamp(0, self.height as i64 - 1) as u32)
    }

    fn chunk(&self, idx: u32) -> Result<Arc<Chunk>, GeoError> {
        {
            let mut c = self.cache.lock();
            c.stamp += 1;
            let s = c.stamp;
            if let Some(e) = c.map.get_mut(&idx) {
                e.1 = s;
                return Ok(e.0.clone());
            }
        }
        let data = {
            let idle = self.decoders.lock().pop();
            let mut d = match idle {
                Some(d) => d,
                None => self.open_decoder()?,
            };
            let r = d.read_chunk(idx).map_err(|e| terr(&self.path, e));
            self.decoders.lock().push(d);
            r?
        };
        let nodata = self.nodata;
        let void = |v: f64| nodata.is_some_and(|n| v == n) || !v.is_finite();
        let bad = || GeoError::UnsupportedSampleType {
            path: self.path.clone(),
            what: "decoded sample type differs from the declared one".into(),
        };
        let chunk = match (self.kind, data) {
            (SampleKind::I16, DecodingResult::I16(v)) => Chunk::Elev(
                v.into_iter()
                    .map(|x| {
                        if x == i16::MIN || void(x as f64) {
                            f32::NAN
                        } else {
                            x as f32
                        }
                    })
                    .collect(),
            ),
            (SampleKind::U16, DecodingResult::U16(v)) => Chunk::Elev(
                v.into_iter()
                    .map(|x| if void(x as f64) { f32::NAN } else { x as f32 })
                    .collect(),
            ),
            (SampleKind::F32, DecodingResult::F32(v)) => Chunk::Elev(
                v.into_iter()
                    .map(|x| if void(x as f64) { f32::NAN } else { x })
                    .collect(),
            ),
            (SampleKind::Rgb8, DecodingResult::U8(v)) => {
                Chunk::Rgb(v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
            }
            (SampleKind::Grey8, DecodingResult::U8(v)) => {
                Chunk::Rgb(v.into_iter().map(|g| [g, g, g]).collect())
            }
            _ => return Err(bad()),
        };
        let size = match &chunk {
            Chunk::Elev(v) => v.len() * 4,
            Chunk::Rgb(v) => v.len() * 3,
        };
        let arc = Arc::new(chunk);
        let mut c = self.cache.lock();
        while c.bytes + size > self.cache_bytes && !c.map.is_empty() {
            let oldest = c.map.iter().min_by_key(|e| (e.1).1).map(|e| *e.0);
            if let Some(k) = oldest {
                if let Some((old, _)) = c.map.remove(&k) {
                    c.bytes -= match &*old {
                        Chunk::Elev(v) => v.len() * 4,
                        Chunk::Rgb(v) => v.len() * 3,
                    };
                }
            }
        }
        c.stamp += 1;
        let s = c.stamp;
        c.bytes += size;
        c.map.insert(idx, (arc.clone(), s));
        Ok(arc)
    }

    fn open_decoder(&self) -> Result<Decoder<BufReader<File>>, GeoError> {
        let file = File::open(&self.path).map_err(|e| GeoError::Open {
            path: self.path.clone(),
            source: e,
        })?;
        Ok(Decoder::new(BufReader::new(file))
            .map_err(|e| terr(&self.path, e))?
            .with_limits(Limits::unlimited()))
    }

    /// A reader with its own small memo of recently used chunks, so that
    /// consecutive pixel reads of one worker take no lock.
    pub fn reader(&self) -> TiffReader<'_> {
        TiffReader {
            tiff: self,
            memo: Vec::with_capacity(MEMO),
        }
    }

    fn locate(&self, col: u32, row: u32) -> (u32, usize) {
        let (cx, cy) = (col / self.chunk_w, row / self.chunk_h);
        let idx = cy * self.chunks_across + cx;
        let data_w = self.chunk_w.min(self.width - cx * self.chunk_w) as usize;
        let off = (row - cy * self.chunk_h) as usize * data_w + (col - cx * self.chunk_w) as usize;
        (idx, off)
    }

    /// Raw elevation of a pixel in source units (NaN = void); indices are
    /// wrapped/clamped into the raster.
    pub fn elevation(&self, col: i64, row: i64) -> Result<f32, GeoError> {
        self.reader().elevation(col, row)
    }

    /// Colour of a pixel; indices are wrapped/clamped into the raster.
    pub fn colour(&self, col: i64, row: i64) -> Result<[u8; 3], GeoError> {
        self.reader().colour(col, row)
    }

    /// Bytes one decoded chunk takes (for cache sizing).
    pub fn chunk_bytes(&self) -> usize {
        self.chunk_w as usize * self.chunk_h as usize * self.kind.bytes()
    }

    /// Cells per 90° of arc (longitude spacing).
    pub fn cells_per_quarter(&self) -> f64 {
        90.0 / self.dx
    }
}

/// Chunks a [`TiffReader`] keeps.
const MEMO: usize = 8;

/// Pixel reads of one raster by one worker: the last few chunks used are held
/// here (most recent first), so most reads take no lock. Holding a chunk
/// keeps it alive after the shared cache evicts it, so readers are meant to be
/// short-lived (one block).
pub struct TiffReader<'a> {
    tiff: &'a GeoTiff,
    memo: Vec<(u32, Arc<Chunk>)>,
}

impl TiffReader<'_> {
    /// The raster read.
    pub fn tiff(&self) -> &GeoTiff {
        self.tiff
    }

    #[inline]
    fn chunk(&mut self, idx: u32) -> Result<&Chunk, GeoError> {
        let pos = match self.memo.iter().position(|e| e.0 == idx) {
            Some(p) => p,
            None => {
                let c = self.tiff.chunk(idx)?;
                if self.memo.len() == MEMO {
                    self.memo.pop();
                }
                self.memo.insert(0, (idx, c));
                0
            }
        };
        if pos > 0 {
            self.memo.swap(0, pos);
        }
        Ok(&self.memo[0].1)
    }

    /// [`GeoTiff::elevation`].
    #[inline]
    pub fn elevation(&mut self, col: i64, row: i64) -> Result<f32, GeoError> {
        let (c, r) = self.tiff.clamp_pixel(col, row);
        let (idx, off) = self.tiff.locate(c, r);
        match self.chunk(idx)? {
            Chunk::Elev(v) => Ok(v.get(off).copied().unwrap_or(f32::NAN)),
            Chunk::Rgb(_) => Err(GeoError::UnsupportedSampleType {
                path: self.tiff.path.clone(),
                what: "colour raster used as elevation".into(),
            }),
        }
    }

    /// [`GeoTiff::colour`].
    #[inline]
    pub fn colour(&mut self, col: i64, row: i64) -> Result<[u8; 3], GeoError> {
        let (c, r) = self.tiff.clamp_pixel(col, row);
        let (idx, off) = self.tiff.locate(c, r);
        match self.chunk(idx)? {
            Chunk::Rgb(v) => Ok(v.get(off).copied().unwrap_or([0; 3])),
            Chunk::Elev(_) => Err(GeoError::UnsupportedSampleType {
                path: self.tiff.path.clone(),
                what: "elevation raster used as colour".into(),
            }),
        }
    }
}
