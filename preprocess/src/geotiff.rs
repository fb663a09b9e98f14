//! Rasters (GeoTIFF in any CRS [`crate::crs`] reads, SRTM `.hgt`) read by
//! strips, tiles or row blocks on demand.
//!
//! The input side of thesis §5.1–5.2 (see docs/REFERENCES.md): the thesis reads a
//! "dually tiled map format" whose rectangular windows are loaded on demand;
//! here the TIFF's own strips/tiles are the unit, decoded lazily and kept in a
//! bounded LRU cache (`cache_bytes`), so a raster larger than the memory bound
//! is never loaded whole.
//!
//! Georeferencing: ModelPixelScale (33550), ModelTiepoint (33922), the
//! GeoKeyDirectory (34735, with its doubles 34736: the CRS, see
//! [`crate::crs`]; GTRasterType 1 = pixel-is-area, the value of a pixel is
//! at its centre, 2 = pixel-is-point) and GDAL_NODATA (42113, ASCII).
//! SRTM `.hgt` files carry their georeferencing in their name and length.

use crate::crs::{Crs, GeoKeys};
use crate::error::GeoError;
use crate::geoid::VerticalDatum;
use parking_lot::Mutex;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
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

/// A cheap hasher for chunk keys (SipHash showed up at 14 % of a build).
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
    fn write_u64(&mut self, v: u64) {
        self.0 = (v ^ (v >> 29) ^ self.0).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }
}

type IdxBuild = std::hash::BuildHasherDefault<IdxHasher>;

/// Decoded chunks of any number of rasters (keyed by raster and chunk),
/// bounded in bytes, least recently used out (the `lru` crate's list: an
/// eviction is O(1) however many chunks of however many tiles it holds),
/// and a bound on the TIFF decoders (open files) the rasters keep idle
/// between reads, so that thousands of tiles neither exceed the memory
/// bound nor the open-file limit.
pub struct ChunkCache {
    inner: Mutex<CacheInner>,
    budget: usize,
    idle_decoders: std::sync::atomic::AtomicUsize,
    next_id: std::sync::atomic::AtomicU32,
}

struct CacheInner {
    lru: lru::LruCache<u64, Arc<Chunk>, IdxBuild>,
    bytes: usize,
}

/// Idle TIFF decoders (each an open file) kept by all the rasters of one
/// [`ChunkCache`]; more are closed after use.
pub const MAX_IDLE_DECODERS: usize = 64;

impl Chunk {
    fn bytes(&self) -> usize {
        match self {
            Chunk::Elev(v) => v.len() * 4,
            Chunk::Rgb(v) => v.len() * 3,
        }
    }
}

impl ChunkCache {
    /// A cache of at most `budget` bytes of decoded chunks (at least one
    /// chunk is kept).
    pub fn new(budget: usize) -> Arc<ChunkCache> {
        Arc::new(ChunkCache {
            inner: Mutex::new(CacheInner {
                lru: lru::LruCache::unbounded_with_hasher(IdxBuild::default()),
                bytes: 0,
            }),
            budget,
            idle_decoders: std::sync::atomic::AtomicUsize::new(0),
            next_id: std::sync::atomic::AtomicU32::new(0),
        })
    }

    /// Bytes of decoded chunks held now.
    pub fn bytes(&self) -> usize {
        self.inner.lock().bytes
    }

    fn get(&self, key: u64) -> Option<Arc<Chunk>> {
        self.inner.lock().lru.get(&key).cloned()
    }

    fn put(&self, key: u64, chunk: Arc<Chunk>) {
        let size = chunk.bytes();
        let mut c = self.inner.lock();
        while c.bytes + size > self.budget {
            match c.lru.pop_lru() {
                Some((_, old)) => c.bytes -= old.bytes(),
                None => break,
            }
        }
        if let Some(old) = c.lru.put(key, chunk) {
            c.bytes -= old.bytes();
        }
        c.bytes += size;
    }

    /// Whether one more idle decoder may be kept (and count it).
    fn keep_decoder(&self) -> bool {
        use std::sync::atomic::Ordering;
        self.idle_decoders
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < MAX_IDLE_DECODERS).then_some(n + 1)
            })
            .is_ok()
    }

    fn take_decoder(&self) {
        self.idle_decoders
            .fetch_sub(1, std::sync::atomic::Ordering::AcqRel);
    }
}

/// How a raster's chunks are read.
enum Backend {
    /// TIFF strips or tiles. Idle decoders: a worker takes one (or opens a
    /// new one) to decode a chunk, so several chunks decode in parallel.
    Tiff(Mutex<Vec<Decoder<BufReader<File>>>>),
    /// An SRTM `.hgt` file: big-endian int16, row-major, chunks of rows
    /// (the file is opened for each chunk read).
    Hgt,
}

/// A georeferenced raster (GeoTIFF or SRTM `.hgt`) in any CRS [`Crs`] reads.
///
/// Pixel `(col, row)`'s value is at CRS coordinates
/// `(x0 + col·dx, y0 − row·dy)`: longitude/latitude in degrees for a
/// geographic CRS, easting/northing in the CRS's unit for a projected one.
pub struct GeoTiff {
    path: PathBuf,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Sample type.
    pub kind: SampleKind,
    /// CRS x (longitude or easting) of the value of pixel column 0.
    pub x0: f64,
    /// CRS y (latitude or northing) of the value of pixel row 0.
    pub y0: f64,
    /// CRS x units per column.
    pub dx: f64,
    /// CRS y units per row (positive: rows go south).
    pub dy: f64,
    /// The GDAL no-data value, if any.
    pub nodata: Option<f64>,
    /// Whether the raster is pixel-is-point (else pixel-is-area).
    pub pixel_is_point: bool,
    /// The raster's CRS and the surface it maps to.
    pub crs: Crs,
    /// The vertical datum the file declares (GeoKeys; EGM96 for `.hgt`).
    pub vertical: Option<VerticalDatum>,
    /// Bounding box `(lat_min, lat_max, lon_min, lon_max)` of the pixel values.
    bbox: (f64, f64, f64, f64),
    /// The bounding box as a test on unit directions ([`BoxTest`]).
    box_test: BoxTest,
    /// A 17 × 17 lattice of pixels over the raster, as face coordinates
    /// (computed on first use; NaN-free: pixels that do not map are left
    /// out).
    outline: std::sync::OnceLock<Vec<planet_core::FaceCoord>>,
    /// Ground distance between neighbouring pixels at the raster's centre, m.
    spacing_m: f64,
    /// Projected elevation rasters: per row, the first and last column
    /// holding a value. No-data before and after them is outside the
    /// re-projected footprint (the corners `gdalwarp` pads), not a void to
    /// fill: points there are not covered.
    spans: Option<Vec<(u32, u32)>>,
    /// The TIFF image (IFD) read: 0, or an overview's.
    image: usize,
    /// Reduced-resolution images of a TIFF (a Cloud-Optimized GeoTIFF's
    /// overviews): IFD index, width and height, finest first.
    overviews: Vec<(usize, u32, u32)>,
    chunk_w: u32,
    chunk_h: u32,
    chunks_across: u32,
    backend: Backend,
    /// The chunk cache (shared by the rasters of a build) and this
    /// raster's key in it.
    cache: Arc<ChunkCache>,
    id: u32,
}

fn terr(path: &Path, e: impl std::fmt::Display) -> GeoError {
    GeoError::Tiff {
        path: path.to_path_buf(),
        msg: e.to_string(),
    }
}

/// The points of a sampling grid as unit directions (planet space), with
/// their latitude/longitude (degrees) computed only where asked (two
/// `atan2` per point were a third of a projected build's time). The
/// directions are given, or computed on demand from a face's gnomonic
/// plane coordinates (a block's grid: most points of a projected raster's
/// grid are interpolated, never needing their direction).
pub struct GridPoints<'a> {
    dirs: Dirs<'a>,
    ll: Vec<(f64, f64)>,
}

enum Dirs<'a> {
    Given(&'a [[f64; 3]]),
    /// Point `k` is `normalize(face.cube_point(us[k % nx], vs[k / nx]))`.
    Axes {
        face: planet_core::Face,
        us: Vec<f64>,
        vs: Vec<f64>,
    },
}

impl<'a> GridPoints<'a> {
    /// Points at these unit directions.
    pub fn new(dirs: &'a [[f64; 3]]) -> GridPoints<'a> {
        GridPoints {
            dirs: Dirs::Given(dirs),
            ll: vec![(f64::NAN, f64::NAN); dirs.len()],
        }
    }

    /// The row-major grid of points `normalize(face.cube_point(u, v))`
    /// for `v` in `vs` (rows) and `u` in `us` (columns).
    pub fn from_axes(face: planet_core::Face, us: Vec<f64>, vs: Vec<f64>) -> GridPoints<'static> {
        let n = us.len() * vs.len();
        GridPoints {
            dirs: Dirs::Axes { face, us, vs },
            ll: vec![(f64::NAN, f64::NAN); n],
        }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.ll.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.ll.is_empty()
    }

    /// The unit direction of point `k`.
    #[inline]
    pub fn direction(&self, k: usize) -> [f64; 3] {
        match &self.dirs {
            Dirs::Given(d) => d[k],
            Dirs::Axes { face, us, vs } => {
                let nx = us.len();
                planet_core::cube::normalize(face.cube_point(us[k % nx], vs[k / nx]))
            }
        }
    }

    /// Latitude and longitude (degrees) of point `k`.
    #[inline]
    pub fn lat_lon(&mut self, k: usize) -> (f64, f64) {
        if self.ll[k].0.is_nan() {
            let (la, lo) = planet_core::cube::lat_lon_from_direction(self.direction(k));
            self.ll[k] = (la.to_degrees(), lo.to_degrees());
        }
        self.ll[k]
    }
}

/// [`GeoTiff`]'s latitude/longitude bounding box test (`in_bbox`, with
/// its 10⁻⁹° margin) on a unit direction, without its latitude and
/// longitude: `sin(lat)` is the direction's `z`, and a longitude range is a
/// wedge around its middle meridian (`cos` of the angle to it at least
/// `cos` of the half width).
#[derive(Debug, Clone, Copy, Default)]
struct BoxTest {
    all: bool,
    z: (f64, f64),
    mid: (f64, f64),
    cos_half: f64,
    all_lon: bool,
}

impl BoxTest {
    fn new((b0, b1, l0, l1): (f64, f64, f64, f64), all: bool) -> BoxTest {
        let e = 1e-9;
        let half = 0.5 * (l1 - l0) + e;
        let m = (0.5 * (l0 + l1)).to_radians();
        BoxTest {
            all,
            z: (
                (b0 - e).clamp(-90.0, 90.0).to_radians().sin(),
                (b1 + e).clamp(-90.0, 90.0).to_radians().sin(),
            ),
            mid: (m.cos(), m.sin()),
            cos_half: half.min(180.0).to_radians().cos(),
            all_lon: half >= 180.0,
        }
    }

    #[inline]
    fn holds(&self, d: [f64; 3]) -> bool {
        if self.all {
            return true;
        }
        if d[2] < self.z.0 || d[2] > self.z.1 {
            return false;
        }
        self.all_lon || d[0] * self.mid.0 + d[1] * self.mid.1 >= self.cos_half * d[0].hypot(d[1])
    }
}

/// Largest interpolation error [`GeoTiff::pixels_of_grid`] accepts, pixels
/// (gdalwarp's default `-et`).
pub const APPROX_ERROR_PX: f64 = 0.125;

/// TIFF images (IFDs) looked at for overviews.
const MAX_IMAGES: usize = 32;

/// Rows per chunk of an `.hgt` file.
const HGT_CHUNK_ROWS: u32 = 64;

/// Tag limits of the TIFF decoder: the `tiff` crate's defaults (256 MiB of
/// decoded chunk, 128 MiB intermediate, 1 MiB per tag value), so a crafted
/// header cannot make a read allocate without bound.
fn limits() -> Limits {
    Limits::default()
}

impl GeoTiff {
    /// Open a raster and read its georeferencing; `cache_bytes` bounds the
    /// decoded strips/tiles kept in memory (at least one chunk is kept).
    /// Files named `*.hgt` are read as SRTM height files, others as TIFF.
    pub fn open(path: &Path, cache_bytes: usize) -> Result<GeoTiff, GeoError> {
        GeoTiff::open_in(path, &ChunkCache::new(cache_bytes))
    }

    /// [`GeoTiff::open`], its chunks kept in a cache shared with other
    /// rasters.
    pub fn open_in(path: &Path, cache: &Arc<ChunkCache>) -> Result<GeoTiff, GeoError> {
        let cache_bytes = cache.clone();
        let is_hgt = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("hgt"));
        if is_hgt {
            return GeoTiff::open_hgt(path, cache_bytes);
        }
        let file = File::open(path).map_err(|e| GeoError::Open {
            path: path.to_path_buf(),
            source: e,
        })?;
        let mut dec = Decoder::new(BufReader::new(file))
            .map_err(|e| terr(path, e))?
            .with_limits(limits());
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
        if scale.len() < 2
            || tie.len() < 6
            || !(scale[0] > 0.0 && scale[1] > 0.0 && scale[0].is_finite() && scale[1].is_finite())
            || !tie.iter().all(|v| v.is_finite())
        {
            return Err(missing("malformed pixel scale or tie point"));
        }
        let dir = dec
            .get_tag_u16_vec(Tag::GeoKeyDirectoryTag)
            .unwrap_or_default();
        let doubles = dec
            .get_tag_f64_vec(Tag::GeoDoubleParamsTag)
            .unwrap_or_default();
        let keys = GeoKeys::parse(&dir, &doubles);
        let crs = Crs::from_geokeys(&keys).map_err(|what| GeoError::WrongCrs {
            path: path.to_path_buf(),
            what,
        })?;
        let pixel_is_point = keys.pixel_is_point();
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
        let x0 = tie[3] + (a - tie[0]) * dx;
        let y0 = tie[4] - (a - tie[1]) * dy;
        let (chunk_w, chunk_h) = dec.chunk_dimensions();
        if chunk_w == 0 || chunk_h == 0 {
            return Err(terr(path, "zero chunk dimensions"));
        }
        // Overviews: the reduced-resolution images (NewSubfileType bit 0,
        // not masks, bit 2) after the first, as a COG holds them.
        let mut overviews = Vec::new();
        let mut ifd = 0;
        while dec.more_images() && ifd < MAX_IMAGES {
            ifd += 1;
            if dec.next_image().is_err() {
                break;
            }
            let sub = dec
                .find_tag_unsigned::<u32>(Tag::NewSubfileType)
                .ok()
                .flatten()
                .unwrap_or(0);
            if let (1, 0, Ok((w, h))) = (sub & 1, sub & 4, dec.dimensions()) {
                if w > 0 && h > 0 && w < width && h <= height {
                    overviews.push((ifd, w, h));
                }
            }
        }
        if ifd > 0 {
            dec.seek_to_image(0).map_err(|e| terr(path, e))?;
        }
        let mut t = GeoTiff::assemble(
            path,
            (width, height, kind),
            (x0, y0, dx, dy),
            nodata,
            pixel_is_point,
            crs,
            keys.vertical(),
            (chunk_w, chunk_h),
            Backend::Tiff(Mutex::new(if cache_bytes.keep_decoder() {
                vec![dec]
            } else {
                Vec::new()
            })),
            cache_bytes,
        )?;
        t.overviews = overviews;
        Ok(t)
    }

    /// The raster's overviews (COG reduced-resolution images): IFD index,
    /// width and height, finest first.
    pub fn overviews(&self) -> &[(usize, u32, u32)] {
        &self.overviews
    }

    /// Overview `k` of [`GeoTiff::overviews`] as a raster of its own: the
    /// same CRS, extent (the outer edges of the edge pixels) and samples'
    /// meaning, coarser pixels, chunks in the same cache.
    pub fn overview(&self, k: usize) -> Result<GeoTiff, GeoError> {
        let &(image, w, h) = self
            .overviews
            .get(k)
            .ok_or_else(|| terr(&self.path, format!("no overview {k}")))?;
        let mut dec = self.open_decoder()?;
        dec.seek_to_image(image).map_err(|e| terr(&self.path, e))?;
        let (chunk_w, chunk_h) = dec.chunk_dimensions();
        if chunk_w == 0 || chunk_h == 0 {
            return Err(terr(&self.path, "zero chunk dimensions in an overview"));
        }
        let (dx, dy) = (
            self.dx * self.width as f64 / w as f64,
            self.dy * self.height as f64 / h as f64,
        );
        let (x0, y0) = (
            self.x0 - 0.5 * self.dx + 0.5 * dx,
            self.y0 + 0.5 * self.dy - 0.5 * dy,
        );
        let crs =
            Crs::from_definition(&self.crs.definition, self.crs.name.clone()).map_err(|what| {
                GeoError::WrongCrs {
                    path: self.path.clone(),
                    what,
                }
            })?;
        let mut t = GeoTiff::assemble(
            &self.path,
            (w, h, self.kind),
            (x0, y0, dx, dy),
            self.nodata,
            self.pixel_is_point,
            crs,
            self.vertical,
            (chunk_w, chunk_h),
            Backend::Tiff(Mutex::new(Vec::new())),
            self.cache.clone(),
        )?;
        t.image = image;
        if self.cache.keep_decoder() {
            if let Backend::Tiff(d) = &t.backend {
                d.lock().push(dec);
            }
        }
        Ok(t)
    }

    /// The TIFF image (IFD) this raster reads: 0, or an overview's.
    pub fn image(&self) -> usize {
        self.image
    }

    /// Open an SRTM `.hgt` file: `n × n` big-endian int16 heights (n = 1201
    /// for 3″, 3601 for 1″, from the file length), -32768 for voids, rows
    /// from north to south; the name (`N46W122.hgt`) gives the latitude
    /// and longitude of the south-west corner sample. Heights are above
    /// EGM96 (SRTM's vertical datum) on WGS84.
    fn open_hgt(path: &Path, cache_bytes: Arc<ChunkCache>) -> Result<GeoTiff, GeoError> {
        let bad = |what: String| GeoError::Georeference {
            path: path.to_path_buf(),
            what,
        };
        let file = File::open(path).map_err(|e| GeoError::Open {
            path: path.to_path_buf(),
            source: e,
        })?;
        let len = file
            .metadata()
            .map_err(|e| GeoError::Open {
                path: path.to_path_buf(),
                source: e,
            })?
            .len();
        let n: u32 = match len {
            2_884_802 => 1201,
            25_934_402 => 3601,
            l => {
                return Err(bad(format!(
                    "an SRTM .hgt file is 2884802 (3\") or 25934402 (1\") bytes, this one {l} (truncated?)"
                )))
            }
        };
        let (lat, lon) = parse_hgt_name(path).ok_or_else(|| {
            bad("an SRTM .hgt file is named like N46W122.hgt (its south-west corner)".into())
        })?;
        let d = 1.0 / (n - 1) as f64;
        GeoTiff::assemble(
            path,
            (n, n, SampleKind::I16),
            (lon as f64, lat as f64 + 1.0, d, d),
            Some(-32768.0),
            true,
            Crs::wgs84(),
            Some(VerticalDatum::Egm96),
            (n, HGT_CHUNK_ROWS),
            Backend::Hgt,
            cache_bytes,
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn assemble(
        path: &Path,
        (width, height, kind): (u32, u32, SampleKind),
        (x0, y0, dx, dy): (f64, f64, f64, f64),
        nodata: Option<f64>,
        pixel_is_point: bool,
        crs: Crs,
        vertical: Option<VerticalDatum>,
        (chunk_w, chunk_h): (u32, u32),
        backend: Backend,
        cache: Arc<ChunkCache>,
    ) -> Result<GeoTiff, GeoError> {
        if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
            return Err(terr(
                path,
                format!("raster of {width} × {height} pixels (1 to {MAX_SIDE} a side are read)"),
            ));
        }
        let chunks_across = width.div_ceil(chunk_w);
        let mut t = GeoTiff {
            path: path.to_path_buf(),
            width,
            height,
            kind,
            x0,
            y0,
            dx,
            dy,
            nodata,
            pixel_is_point,
            crs,
            vertical,
            bbox: (0.0, 0.0, 0.0, 0.0),
            box_test: BoxTest::default(),
            outline: std::sync::OnceLock::new(),
            spacing_m: 0.0,
            spans: None,
            image: 0,
            overviews: Vec::new(),
            chunk_w,
            chunk_h,
            chunks_across,
            backend,
            id: cache
                .next_id
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            cache,
        };
        t.bbox = t.compute_bbox().ok_or_else(|| GeoError::WrongCrs {
            path: path.to_path_buf(),
            what: format!(
                "{}: the raster's corners do not map to the surface",
                t.crs.name
            ),
        })?;
        t.box_test = BoxTest::new(t.bbox, t.is_global() || t.crs.is_identity());
        t.spacing_m = t.compute_spacing().ok_or_else(|| GeoError::WrongCrs {
            path: path.to_path_buf(),
            what: format!("{}: cannot measure the raster's pixel spacing", t.crs.name),
        })?;
        if !t.crs.geographic && t.kind.is_elevation() {
            t.spans = Some(t.compute_spans()?);
        }
        Ok(t)
    }

    /// First and last valued column of every row (one pass over the raster,
    /// a band of chunk rows per task, in parallel).
    fn compute_spans(&self) -> Result<Vec<(u32, u32)>, GeoError> {
        use rayon::prelude::*;
        let bands: Vec<u32> = (0..self.height.div_ceil(self.chunk_h)).collect();
        let parts = bands
            .par_iter()
            .map(|&band| {
                let r0 = band * self.chunk_h;
                let h = self.chunk_h.min(self.height - r0);
                let mut spans = vec![(u32::MAX, 0u32); h as usize];
                let mut rd = self.reader();
                let mut buf = Vec::new();
                for cx in 0..self.chunks_across {
                    let c0 = cx * self.chunk_w;
                    let w = self.chunk_w.min(self.width - c0);
                    rd.window((c0, r0), (w, h), &mut buf)?;
                    for (sp, row) in spans.iter_mut().zip(buf.chunks_exact(w as usize)) {
                        let first = row.iter().position(|v| !v.is_nan());
                        let last = row.iter().rposition(|v| !v.is_nan());
                        if let (Some(a), Some(b)) = (first, last) {
                            sp.0 = sp.0.min(c0 + a as u32);
                            sp.1 = sp.1.max(c0 + b as u32);
                        }
                    }
                }
                Ok(spans)
            })
            .collect::<Result<Vec<_>, GeoError>>()?;
        Ok(parts.concat())
    }

    /// Whether pixel `(col, row)` lies outside the raster's valued
    /// footprint (see the `spans` field); always false for geographic
    /// rasters, whose no-data pixels are voids to fill.
    #[inline]
    pub fn is_exterior(&self, col: i64, row: i64) -> bool {
        match &self.spans {
            None => false,
            Some(sp) => match sp.get(row.clamp(0, self.height as i64 - 1) as usize) {
                Some(&(a, b)) => col < a as i64 || col > b as i64,
                None => true,
            },
        }
    }

    /// The latitude/longitude box of the pixel values: the border pixels
    /// mapped through the CRS, widened to a pole a projected raster holds.
    fn compute_bbox(&self) -> Option<(f64, f64, f64, f64)> {
        let (w, h) = ((self.width - 1) as i64, (self.height - 1) as i64);
        if self.crs.is_identity() {
            let lat1 = self.y0;
            let lat0 = self.y0 - h as f64 * self.dy;
            return Some((lat0, lat1, self.x0, self.x0 + w as f64 * self.dx));
        }
        let (mut la0, mut la1, mut lo0, mut lo1) = (90f64, -90f64, 180f64, -180f64);
        let n = 64i64;
        let mut any = false;
        for k in 0..=n {
            let (c, r) = (w * k / n, h * k / n);
            for (col, row) in [(c, 0), (c, h), (0, r), (w, r)] {
                if let Some((la, lo)) = self.crs.inverse(
                    self.x0 + col as f64 * self.dx,
                    self.y0 - row as f64 * self.dy,
                ) {
                    any = true;
                    la0 = la0.min(la);
                    la1 = la1.max(la);
                    lo0 = lo0.min(lo);
                    lo1 = lo1.max(lo);
                }
            }
        }
        for pole in [90.0, -90.0] {
            if let Some((x, y)) = self.crs.forward(pole, 0.0) {
                let (c, r) = ((x - self.x0) / self.dx, (self.y0 - y) / self.dy);
                if c >= 0.0 && c <= w as f64 && r >= 0.0 && r <= h as f64 {
                    (la0, la1) = (la0.min(pole), la1.max(pole));
                    (lo0, lo1) = (-180.0, 180.0);
                }
            }
        }
        any.then_some((la0, la1, lo0, lo1))
    }

    /// Ground distance (metres, on the surface's sphere of equatorial
    /// radius) between the centre pixel and its right and lower
    /// neighbours: the smaller.
    fn compute_spacing(&self) -> Option<f64> {
        let (c, r) = ((self.width / 2) as i64, (self.height / 2) as i64);
        let p = self.position_of(c, r);
        let radius = self.crs.datum.equatorial_radius();
        let dist = |q: (f64, f64)| {
            let (a, b) = (
                planet_core::cube::direction_from_lat_lon(p.0.to_radians(), p.1.to_radians()),
                planet_core::cube::direction_from_lat_lon(q.0.to_radians(), q.1.to_radians()),
            );
            planet_core::cube::angle_between(a, b) * radius
        };
        let mut s = f64::INFINITY;
        for q in [
            self.position_of(c + 1, r),
            self.position_of(c - 1, r),
            self.position_of(c, r + 1),
            self.position_of(c, r - 1),
        ] {
            if q.0.is_finite() {
                s = s.min(dist(q));
            }
        }
        if self.crs.geographic {
            // Longitude spacing at the equator: the cells of a geographic
            // raster shrink towards the poles.
            s = s
                .max(self.dx.to_radians() * radius)
                .max(self.dy.to_radians() * radius);
        }
        (s.is_finite() && s > 0.0).then_some(s)
    }

    /// The file this raster was read from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether the raster spans all longitudes (columns wrap).
    pub fn is_global(&self) -> bool {
        self.crs.geographic && self.width as f64 * self.dx >= 360.0 - 1e-9
    }

    /// Fractional pixel coordinates `(col, row)` of a surface point
    /// (degrees), through the CRS (inverse mapping, thesis §5.2); NaN where
    /// the projection does not reach. For a geographic CRS longitude is
    /// shifted by ±360° to the raster's range where that helps.
    #[inline]
    pub fn pixel_of(&self, lat: f64, lon: f64) -> (f64, f64) {
        let Some((x, y)) = self.crs.forward(lat, lon) else {
            return (f64::NAN, f64::NAN);
        };
        let row = (self.y0 - y) / self.dy;
        let mut col = (x - self.x0) / self.dx;
        if self.crs.geographic && !self.is_global() {
            let span = 360.0 / self.dx;
            let w = self.width as f64;
            if col < -0.5 && col + span <= w {
                col += span;
            } else if col > w - 0.5 && col - span >= -1.0 {
                col -= span;
            }
        }
        (col, row)
    }

    /// Position (lat, lon degrees) of a pixel's value; NaN where the CRS
    /// does not map it to the surface.
    pub fn position_of(&self, col: i64, row: i64) -> (f64, f64) {
        self.crs
            .inverse(
                self.x0 + col as f64 * self.dx,
                self.y0 - row as f64 * self.dy,
            )
            .unwrap_or((f64::NAN, f64::NAN))
    }

    /// Whether a unit direction lies in the raster's latitude/longitude
    /// bounding box (as [`GeoTiff::covers`]' first test, without computing
    /// latitude and longitude).
    #[inline]
    pub fn box_holds(&self, d: [f64; 3]) -> bool {
        self.box_test.holds(d)
    }

    /// A 17 × 17 lattice of the raster's pixels (corners included) as face
    /// coordinates, for footprint tests.
    pub fn lattice_points(&self) -> &[planet_core::FaceCoord] {
        self.outline.get_or_init(|| {
            let n = 16i64;
            let (w, h) = (self.width as i64 - 1, self.height as i64 - 1);
            let mut v = Vec::new();
            for j in 0..=n {
                for i in 0..=n {
                    let (la, lo) = self.position_of(w * i / n, h * j / n);
                    if la.is_finite() && lo.is_finite() {
                        v.push(planet_core::FaceCoord::from_lat_lon(
                            la.to_radians(),
                            lo.to_radians(),
                        ));
                    }
                }
            }
            v
        })
    }

    /// Whether the point lies between the first and last pixel values (so
    /// bilinear interpolation needs no extrapolation). Global rasters cover
    /// every longitude and clamp at the poles.
    pub fn covers(&self, lat: f64, lon: f64) -> bool {
        if self.is_global() {
            return true;
        }
        if !self.in_bbox(lat, lon) {
            return false;
        }
        let (c, r) = self.pixel_of(lat, lon);
        self.covers_at(lat, lon, c, r)
    }

    /// The bounding-box test of [`GeoTiff::covers`] (a projection can map
    /// a point far outside the raster, e.g. beyond a transverse Mercator's
    /// zone, into its pixel range).
    #[inline]
    fn in_bbox(&self, lat: f64, lon: f64) -> bool {
        if self.is_global() {
            return true;
        }
        let (b0, b1, l0, l1) = self.bbox;
        if lat < b0 - 1e-9 || lat > b1 + 1e-9 {
            return false;
        }
        self.crs.is_identity() || (lon >= l0 - 1e-9 && lon <= l1 + 1e-9)
    }

    /// [`GeoTiff::covers`] for a point whose pixel coordinates `(c, r)` are
    /// known (from [`GeoTiff::pixel_of`] or [`GeoTiff::pixels_of_grid`]).
    #[inline]
    pub fn covers_at(&self, lat: f64, lon: f64, c: f64, r: f64) -> bool {
        self.in_bbox(lat, lon) && self.covers_pixel(c, r)
    }

    /// [`GeoTiff::covers`] for pixel coordinates from
    /// [`GeoTiff::pixels_of_grid`] (which applied the bounding-box test).
    #[inline]
    pub fn covers_pixel(&self, c: f64, r: f64) -> bool {
        if self.is_global() {
            return true;
        }
        let inside =
            c >= 0.0 && c <= (self.width - 1) as f64 && r >= 0.0 && r <= (self.height - 1) as f64;
        if !inside || self.spans.is_none() {
            return inside;
        }
        let (c0, r0) = (c.floor() as i64, r.floor() as i64);
        let (c1, r1) = (c.ceil() as i64, r.ceil() as i64);
        !(self.is_exterior(c0, r0)
            || self.is_exterior(c1, r0)
            || self.is_exterior(c0, r1)
            || self.is_exterior(c1, r1))
    }

    /// [`GeoTiff::pixel_of`] for a grid of `nx × ny` points (row-major),
    /// NaN for points outside the raster's bounding box, approximated as
    /// gdalwarp's approximate transformer does (GDALApproxTransform,
    /// `-et 0.125`), in two dimensions: a cell of the grid (at first the
    /// whole grid) has its 4 corners projected exactly, and its middle
    /// point and the middles of its 4 edges too; where the bilinear
    /// interpolation of the corners meets those 5 exact points within
    /// [`APPROX_ERROR_PX`] pixel (in column and in row), every other point
    /// of the cell is interpolated; else (or where a corner does not
    /// project or lies outside the bounding box) the cell is split in 4 at
    /// its middles and each quarter tried again, down to single grid cells,
    /// whose points are all exact. The error of bilinear interpolation of a
    /// smooth mapping is, to second order, largest at a cell's middle (the
    /// `xy` term is interpolated exactly; the `x²` and `y²` terms peak at
    /// the middle), so the middle's test bounds the cell; the edge middles
    /// guard the edges shared with neighbouring cells. Tests check the
    /// bound against exact projection at every point of UTM and polar
    /// grids. Rasters whose CRS is the surface's longitude/latitude are
    /// mapped exactly (that is as cheap).
    pub fn pixels_of_grid(
        &self,
        pts: &mut GridPoints<'_>,
        nx: usize,
        ny: usize,
        out: &mut Vec<(f64, f64)>,
    ) {
        out.clear();
        if self.crs.is_identity() || nx < 3 || ny < 3 {
            out.extend((0..pts.len()).map(|k| {
                let (la, lo) = pts.lat_lon(k);
                if self.in_bbox(la, lo) {
                    self.pixel_of(la, lo)
                } else {
                    (f64::NAN, f64::NAN)
                }
            }));
            return;
        }
        out.resize(nx * ny, (f64::NAN, f64::NAN));
        // Per point: 0 not set, 1 interpolated, 2 exact, 3 exact but
        // outside the bounding box (made NaN at the end: the projection
        // itself is smooth there and serves as a cell corner).
        let mut state = vec![0u8; nx * ny];
        let exact_at =
            |pts: &mut GridPoints<'_>, out: &mut [(f64, f64)], state: &mut [u8], k: usize| {
                if state[k] < 2 {
                    let (la, lo) = pts.lat_lon(k);
                    out[k] = self.pixel_of(la, lo);
                    state[k] = if self.in_bbox(la, lo) { 2 } else { 3 };
                }
                out[k]
            };
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let mut cells = vec![(0usize, nx - 1, 0usize, ny - 1)];
        while let Some((x0, x1, y0, y1)) = cells.pop() {
            let k = [
                exact_at(pts, out, &mut state, y0 * nx + x0),
                exact_at(pts, out, &mut state, y0 * nx + x1),
                exact_at(pts, out, &mut state, y1 * nx + x0),
                exact_at(pts, out, &mut state, y1 * nx + x1),
            ];
            let interp = |x: usize, y: usize| -> (f64, f64) {
                let fx = (x - x0) as f64 / (x1 - x0) as f64;
                let fy = (y - y0) as f64 / (y1 - y0) as f64;
                let top = (lerp(k[0].0, k[1].0, fx), lerp(k[0].1, k[1].1, fx));
                let bot = (lerp(k[2].0, k[3].0, fx), lerp(k[2].1, k[3].1, fx));
                (lerp(top.0, bot.0, fy), lerp(top.1, bot.1, fy))
            };
            let (mx, my) = ((x0 + x1) / 2, (y0 + y1) / 2);
            // NaN (outside the box or the projection) fails these.
            let mut good = k.iter().all(|c| c.0.is_finite() && c.1.is_finite());
            for (x, y) in [(mx, my), (mx, y0), (mx, y1), (x0, my), (x1, my)] {
                if !good {
                    break;
                }
                if (x == x0 || x == x1) && (y == y0 || y == y1) {
                    continue; // a corner (a cell one point wide)
                }
                let e = exact_at(pts, out, &mut state, y * nx + x);
                let g = interp(x, y);
                good = (g.0 - e.0).abs() <= APPROX_ERROR_PX && (g.1 - e.1).abs() <= APPROX_ERROR_PX;
            }
            if good {
                // Points outside the box are tested one by one (on their
                // directions) unless the 4 corners lie inside it.
                let boxed = [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
                    .iter()
                    .all(|&(x, y)| state[y * nx + x] == 2);
                // interp(x, y), a row at a time.
                let w = (x1 - x0) as f64;
                for y in y0..=y1 {
                    let fy = (y - y0) as f64 / (y1 - y0) as f64;
                    let l = (lerp(k[0].0, k[2].0, fy), lerp(k[0].1, k[2].1, fy));
                    let r = (lerp(k[1].0, k[3].0, fy), lerp(k[1].1, k[3].1, fy));
                    let row = y * nx;
                    for x in x0..=x1 {
                        let i = row + x;
                        if state[i] == 0 {
                            let fx = (x - x0) as f64 / w;
                            out[i] = if boxed || self.box_test.holds(pts.direction(i)) {
                                (lerp(l.0, r.0, fx), lerp(l.1, r.1, fx))
                            } else {
                                (f64::NAN, f64::NAN)
                            };
                            state[i] = 1;
                        }
                    }
                }
                continue;
            }
            // Split where the cell is wider than one grid step; a single
            // grid cell has only its (exact) corners.
            let xs: &[(usize, usize)] = if x1 - x0 >= 2 {
                &[(x0, mx), (mx, x1)]
            } else {
                &[(x0, x1)]
            };
            let ys: &[(usize, usize)] = if y1 - y0 >= 2 {
                &[(y0, my), (my, y1)]
            } else {
                &[(y0, y1)]
            };
            if xs.len() == 1 && ys.len() == 1 {
                continue;
            }
            for &(a, b) in xs {
                for &(c, d) in ys {
                    cells.push((a, b, c, d));
                }
            }
        }
        for (o, st) in out.iter_mut().zip(&state) {
            if *st == 3 {
                *o = (f64::NAN, f64::NAN);
            }
        }
    }

    /// Bounding box `(lat_min, lat_max, lon_min, lon_max)` of the pixel values.
    pub fn bounds(&self) -> (f64, f64, f64, f64) {
        self.bbox
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

    /// Ground distance between neighbouring pixels at the raster's centre
    /// (metres; for a geographic raster, the spacing at the equator).
    pub fn spacing_m(&self) -> f64 {
        self.spacing_m
    }

    /// Pixel spacing in degrees of arc on the surface.
    pub fn spacing_deg(&self) -> f64 {
        (self.spacing_m / self.crs.datum.equatorial_radius()).to_degrees()
    }

    fn chunk(&self, idx: u32) -> Result<Arc<Chunk>, GeoError> {
        let key = (self.id as u64) << 32 | idx as u64;
        if let Some(c) = self.cache.get(key) {
            return Ok(c);
        }
        let data = match &self.backend {
            Backend::Tiff(decoders) => {
                let idle = decoders.lock().pop();
                let mut d = match idle {
                    Some(d) => {
                        self.cache.take_decoder();
                        d
                    }
                    None => self.open_decoder()?,
                };
                let r = d.read_chunk(idx).map_err(|e| terr(&self.path, e));
                if self.cache.keep_decoder() {
                    decoders.lock().push(d);
                }
                r?
            }
            Backend::Hgt => DecodingResult::I16(self.read_hgt_rows(idx)?),
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
        let arc = Arc::new(chunk);
        self.cache.put(key, arc.clone());
        Ok(arc)
    }

    /// Rows `[idx·HGT_CHUNK_ROWS, …)` of an `.hgt` file.
    fn read_hgt_rows(&self, idx: u32) -> Result<Vec<i16>, GeoError> {
        let r0 = idx as u64 * self.chunk_h as u64;
        let rows = (self.chunk_h as u64).min((self.height as u64).saturating_sub(r0));
        let mut buf = vec![0u8; (rows * self.width as u64 * 2) as usize];
        let mut f = File::open(&self.path).map_err(|e| GeoError::Open {
            path: self.path.clone(),
            source: e,
        })?;
        f.seek(SeekFrom::Start(r0 * self.width as u64 * 2))
            .and_then(|_| f.read_exact(&mut buf))
            .map_err(|e| terr(&self.path, e))?;
        Ok(buf
            .chunks_exact(2)
            .map(|b| i16::from_be_bytes([b[0], b[1]]))
            .collect())
    }

    fn open_decoder(&self) -> Result<Decoder<BufReader<File>>, GeoError> {
        let file = File::open(&self.path).map_err(|e| GeoError::Open {
            path: self.path.clone(),
            source: e,
        })?;
        let mut dec = Decoder::new(BufReader::new(file))
            .map_err(|e| terr(&self.path, e))?
            .with_limits(limits());
        if self.image > 0 {
            dec.seek_to_image(self.image)
                .map_err(|e| terr(&self.path, e))?;
        }
        Ok(dec)
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

    /// Cells per 90° of arc on the surface.
    pub fn cells_per_quarter(&self) -> f64 {
        90.0 / self.spacing_deg()
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

    /// Pixels `(c0, r0)`, `(c0+1, r0)`, `(c0, r0+1)`, `(c0+1, r0+1)` (raw,
    /// NaN for voids) when all four lie inside the raster and in one chunk;
    /// `None` otherwise (read them one by one).
    #[inline]
    pub fn quad(&mut self, c0: i64, r0: i64) -> Result<Option<[f32; 4]>, GeoError> {
        let t = self.tiff;
        if c0 < 0 || r0 < 0 || c0 + 1 >= t.width as i64 || r0 + 1 >= t.height as i64 {
            return Ok(None);
        }
        let (c0, r0) = (c0 as u32, r0 as u32);
        let (cx, cy) = (c0 / t.chunk_w, r0 / t.chunk_h);
        if (c0 + 1) / t.chunk_w != cx || (r0 + 1) / t.chunk_h != cy {
            return Ok(None);
        }
        let (idx, off) = t.locate(c0, r0);
        let data_w = t.chunk_w.min(t.width - cx * t.chunk_w) as usize;
        match self.chunk(idx)? {
            Chunk::Elev(v) => {
                let at = |o: usize| v.get(o).copied().unwrap_or(f32::NAN);
                Ok(Some([
                    at(off),
                    at(off + 1),
                    at(off + data_w),
                    at(off + data_w + 1),
                ]))
            }
            Chunk::Rgb(_) => Err(GeoError::UnsupportedSampleType {
                path: t.path.clone(),
                what: "colour raster used as elevation".into(),
            }),
        }
    }

    /// Raw elevations (NaN for voids) of pixels `[c0, c0 + w) × [r0, r0 +
    /// h)`, which must lie inside the raster, into `buf` (row-major, `w`
    /// wide), copied a chunk row segment at a time.
    pub fn window(
        &mut self,
        (c0, r0): (u32, u32),
        (w, h): (u32, u32),
        buf: &mut Vec<f32>,
    ) -> Result<(), GeoError> {
        let t = self.tiff;
        buf.clear();
        buf.resize(w as usize * h as usize, f32::NAN);
        if w == 0 || h == 0 || c0 + w > t.width || r0 + h > t.height {
            return Ok(());
        }
        let (c1, r1) = (c0 + w, r0 + h);
        for cy in r0 / t.chunk_h..=(r1 - 1) / t.chunk_h {
            for cx in c0 / t.chunk_w..=(c1 - 1) / t.chunk_w {
                let (cc0, cr0) = (cx * t.chunk_w, cy * t.chunk_h);
                let data_w = t.chunk_w.min(t.width - cc0) as usize;
                let (a, b) = (c0.max(cc0), c1.min(cc0 + t.chunk_w));
                let idx = cy * t.chunks_across + cx;
                let v = match self.chunk(idx)? {
                    Chunk::Elev(v) => v,
                    Chunk::Rgb(_) => {
                        return Err(GeoError::UnsupportedSampleType {
                            path: t.path.clone(),
                            what: "colour raster used as elevation".into(),
                        })
                    }
                };
                for row in r0.max(cr0)..r1.min(cr0 + t.chunk_h) {
                    let src = (row - cr0) as usize * data_w + (a - cc0) as usize;
                    let dst = (row - r0) as usize * w as usize + (a - c0) as usize;
                    let n = (b - a) as usize;
                    if let Some(s) = v.get(src..src + n) {
                        buf[dst..dst + n].copy_from_slice(s);
                    }
                }
            }
        }
        Ok(())
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

/// South-west corner `(lat, lon)` of an SRTM tile from its file name
/// (`N46W122.hgt`, `s01e010.SRTMGL1.hgt`).
pub fn parse_hgt_name(path: &Path) -> Option<(i32, i32)> {
    let name = path.file_name()?.to_str()?.to_ascii_uppercase();
    let b = name.as_bytes();
    if b.len() < 7 {
        return None;
    }
    let lat: i32 = name.get(1..3)?.parse().ok()?;
    let lon: i32 = name.get(4..7)?.parse().ok()?;
    let lat = match b[0] {
        b'N' => lat,
        b'S' => -lat,
        _ => return None,
    };
    let lon = match b[3] {
        b'E' => lon,
        b'W' => -lon,
        _ => return None,
    };
    ((-90..90).contains(&lat) && (-180..180).contains(&lon)).then_some((lat, lon))
}

/// Largest width or height of a raster read (2²⁴: a 1″ global raster is
/// 1.3 M × 0.65 M); larger headers are refused before any allocation that
/// scales with them.
pub const MAX_SIDE: u32 = 1 << 24;

/// What the `raster_readers` fuzz target and its replay test run on
/// untrusted bytes at `path`: open the raster with a 1 MiB chunk cache,
/// map its corners and centre through its CRS and read those pixels, and
/// read a pixel of its coarsest overview.
pub fn probe(path: &Path) -> Result<(), GeoError> {
    let t = GeoTiff::open(path, 1 << 20)?;
    let (w, h) = (t.width as i64, t.height as i64);
    for (c, r) in [
        (0, 0),
        (w - 1, 0),
        (0, h - 1),
        (w - 1, h - 1),
        (w / 2, h / 2),
    ] {
        let (la, lo) = t.position_of(c, r);
        if la.is_finite() {
            let _ = t.pixel_of(la, lo);
            let _ = t.covers(la, lo);
        }
        if t.kind.is_elevation() {
            t.elevation(c, r)?;
        } else {
            t.colour(c, r)?;
        }
    }
    // The coarsest overview (COG), georeferenced from the full image.
    if let Some(k) = t.overviews().len().checked_sub(1) {
        let o = t.overview(k)?;
        if o.kind.is_elevation() {
            o.elevation(0, 0)?;
        } else {
            o.colour(0, 0)?;
        }
    }
    Ok(())
}
