//! A deterministic procedural planet, the project's own embedded default
//! database (instead of real data), built with the same Alg. 5.2 pipeline
//! (thesis §5.3), on a uniform tree or, with detail regions
//! ([`DetailRegion`]), on a tree deepened inside spherical caps and graded
//! (thesis §4.3.3, [`crate::plan::plan_for_caps`]).
//!
//! Elevation is a function of the unit direction (so it is seamless over cube
//! edges and poles): domain-warped fBm continents, ridged mountain ranges,
//! and fBm detail down to about two samples at the deepest leaf level, from
//! about −8000 m to +8000 m. For speed, everything but the finest detail
//! octaves is evaluated in f64 on a lattice of every 8th sample of the *base*
//! level (`levels`, the shallowest leaf level) and interpolated bilinearly; a
//! leaf at any level `L ≥ levels` interpolates that same lattice at each
//! sample's global index (power-of-two index arithmetic, exact in f64, one
//! expression order), so a sample's value does not depend on the level of
//! the leaf that computes it. A sample on a block edge depends only on
//! lattice points whose directions are bit-identical from both blocks
//! (Thesis Table 4.1, docs/REFERENCES.md), so shared edge samples agree exactly, across faces
//! and across a leaf/split-block boundary. The three octaves below the base
//! level's sample rate and every octave finer than the base lattice can
//! carry, down to the deepest level's ~2-sample frequency, are evaluated per
//! sample, a row at a time, in f32 within each noise cell
//! (`DetailOctave`), again a function of the sample's direction alone.
//!
//! The octaves finer than the base planet's own (present only with detail
//! regions) are *rough*: their amplitude falls by [`ROUGH_RATIO`] per octave
//! instead of 0.5, scaled by a gain that is large in mountains and zero in
//! the open ocean, so that slopes at 10–100 m scale reach a few tenths in
//! mountains and a deep tree has a geometric error worth streaming. A
//! uniform planet's octave list ends at its own leaf level, so its values are
//! unchanged by them. Colour is a function of altitude, latitude and a
//! moisture field: ocean blues, beaches, greens, deserts, rock, snow caps and
//! polar ice (`palette`, f32, branch-free).

use crate::build::{build, BuildOptions, BuildStats, GridSource, CW, EW};
use crate::error::BuildError;
use crate::plan::{plan_for_caps, Cap, Plan};
use planet_core::cube::{
    angle_between, direction_from_lat_lon, normalize, plane_from_angle, sample_coord,
};
use planet_core::lod::{self, Rgb};
use planet_core::{BlockId, Datum};
use std::path::Path;
use std::str::FromStr;

/// Deepest level a procedural tree may have.
pub const MAX_PROCEDURAL_LEVEL: u8 = 20;

/// Version of the generator, in every procedural database's description:
/// raise it whenever the same options would give other samples, so that
/// caches of the built-in planet ([`crate::builtin`]) are rebuilt.
pub const GENERATOR_VERSION: u32 = 3;

/// A region of a procedural planet built deeper than the base: a circle of
/// `radius_km` around (`lat`, `lon`) in degrees, down to leaf `level`
/// (`--detail LAT,LON,RADIUS_KM,LEVEL`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetailRegion {
    /// Latitude of the centre in degrees, in [-90, 90].
    pub lat: f64,
    /// Longitude of the centre in degrees, in [-180, 180].
    pub lon: f64,
    /// Radius in kilometres (> 0), measured on a sphere of the datum's
    /// equatorial radius.
    pub radius_km: f64,
    /// Leaf level inside the region (at least the base levels, at most
    /// [`MAX_PROCEDURAL_LEVEL`]).
    pub level: u8,
}

/// The expected form of a detail region, for error messages.
pub const DETAIL_FORM: &str = "LAT,LON,RADIUS_KM,LEVEL with LAT in [-90, 90], LON in [-180, 180], RADIUS_KM > 0 and LEVEL <= 20 (degrees, kilometres), e.g. 46.85,-121.76,60,14";

impl FromStr for DetailRegion {
    type Err = String;

    fn from_str(v: &str) -> Result<DetailRegion, String> {
        let bad = |why: &str| format!("bad detail region '{v}': {why}; expected {DETAIL_FORM}");
        let parts: Vec<&str> = v.split(',').map(str::trim).collect();
        let [lat, lon, radius, level] = parts.as_slice() else {
            return Err(bad(&format!("{} fields, not 4", parts.len())));
        };
        let num = |name: &str, s: &str| -> Result<f64, String> {
            match s.parse::<f64>() {
                Ok(x) if x.is_finite() => Ok(x),
                _ => Err(bad(&format!("{name} '{s}' is not a finite number"))),
            }
        };
        let lat = num("LAT", lat)?;
        let lon = num("LON", lon)?;
        let radius_km = num("RADIUS_KM", radius)?;
        let level: u8 = level
            .parse()
            .map_err(|_| bad(&format!("LEVEL '{level}' is not an integer in 0..=20")))?;
        if !(-90.0..=90.0).contains(&lat) {
            return Err(bad(&format!("LAT {lat} is outside [-90, 90]")));
        }
        if !(-180.0..=180.0).contains(&lon) {
            return Err(bad(&format!("LON {lon} is outside [-180, 180]")));
        }
        if radius_km <= 0.0 {
            return Err(bad(&format!("RADIUS_KM {radius_km} is not > 0")));
        }
        if level > MAX_PROCEDURAL_LEVEL {
            return Err(bad(&format!(
                "LEVEL {level} is deeper than {MAX_PROCEDURAL_LEVEL}"
            )));
        }
        Ok(DetailRegion {
            lat,
            lon,
            radius_km,
            level,
        })
    }
}

impl std::fmt::Display for DetailRegion {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{},{},{},{}",
            self.lat, self.lon, self.radius_km, self.level
        )
    }
}

impl DetailRegion {
    /// The region as a cap on the unit sphere (radius over the datum's
    /// equatorial radius).
    pub fn cap(&self, datum: &Datum) -> Cap {
        Cap {
            centre: direction_from_lat_lon(self.lat.to_radians(), self.lon.to_radians()),
            radius: self.radius_km * 1000.0 / datum.equatorial_radius(),
            level: self.level,
        }
    }
}

/// Options of a procedural planet.
#[derive(Debug, Clone)]
pub struct ProceduralOptions {
    /// Seed: the same seed and levels give the same database.
    pub seed: u64,
    /// Uniform leaf level of both trees.
    pub levels: u8,
    /// Reference surface.
    pub datum: Datum,
    /// Whether to build the colour tree.
    pub colour: bool,
    /// Worker threads (`None`: all cores).
    pub threads: Option<usize>,
    /// Hide progress bars.
    pub quiet: bool,
    /// Memory bound in MiB for the in-flight grids (`None`: unbounded; see
    /// [`BuildOptions::grid_memory`]).
    pub max_memory_mb: Option<usize>,
    /// Regions built deeper than `levels` (empty: a uniform planet).
    pub detail: Vec<DetailRegion>,
    /// Record codecs.
    pub codecs: crate::CodecOptions,
}

/// The small default planet other crates embed: seed 1, 4 levels (blocks of
/// 64 samples, a 1024-sample face map), WGS84, with colour. Builds in a few
/// seconds in release mode (about 2 MB).
pub fn default_procedural_options() -> ProceduralOptions {
    ProceduralOptions {
        seed: 1,
        levels: 4,
        datum: Datum::WGS84,
        colour: true,
        threads: None,
        quiet: true,
        max_memory_mb: None,
        detail: Vec::new(),
        codecs: crate::CodecOptions::default(),
    }
}

/// Check the options: `levels` and every region's level at most
/// [`MAX_PROCEDURAL_LEVEL`], regions' levels at least `levels`, their
/// centres and radii in range.
pub fn check_procedural_options(opts: &ProceduralOptions) -> Result<(), BuildError> {
    if opts.levels > MAX_PROCEDURAL_LEVEL {
        return Err(BuildError::Options(format!(
            "--levels {} is too deep (at most {MAX_PROCEDURAL_LEVEL})",
            opts.levels
        )));
    }
    for r in &opts.detail {
        // Re-parse the printed form: one place checks the ranges.
        DetailRegion::from_str(&r.to_string())
            .map_err(|e| BuildError::Options(format!("--detail {r}: {e}")))?;
        if r.level < opts.levels {
            return Err(BuildError::Options(format!(
                "--detail {r}: LEVEL {} is shallower than --levels {} (LEVEL must be in [--levels, {MAX_PROCEDURAL_LEVEL}])",
                r.level, opts.levels
            )));
        }
    }
    Ok(())
}

/// Build a procedural planet database at `out` (thesis §5.3, Alg. 5.2, on
/// the plan of [`Procedural::plan`]).
pub fn build_procedural(opts: &ProceduralOptions, out: &Path) -> Result<BuildStats, BuildError> {
    check_procedural_options(opts)?;
    let src = Procedural::new(opts);
    let plan = src.plan();
    build(
        &src,
        &plan,
        out,
        &BuildOptions {
            threads: opts.threads,
            quiet: opts.quiet,
            grid_memory: opts.max_memory_mb.map(|m| m << 20),
            codecs: opts.codecs,
        },
    )
}

/// The generator.
#[derive(Debug, Clone)]
pub struct Procedural {
    seed: u64,
    levels: u8,
    datum: Datum,
    colour: bool,
    /// Number of detail octaves of the base level (the lattice's and the
    /// [`HIGH_OCTAVES`] per-sample ones).
    detail_octaves: u32,
    /// Number of detail octaves of the deepest level: octaves
    /// `detail_octaves..all_octaves` are the rough per-sample ones.
    all_octaves: u32,
    /// The tree shape.
    plan: Plan,
    /// The detail regions (for the description).
    detail: Vec<DetailRegion>,
    /// The regions deeper than the base: where the rough octaves apply.
    rough_caps: Vec<Cap>,
}

const LATTICE: usize = 8;
const HIGH_OCTAVES: u32 = 3;
pub(crate) const DETAIL_F0: f64 = 4.0;
/// Amplitude ratio per octave of the rough octaves (fBm's is 0.5): the
/// amplitude ∝ wavelength^0.62, so slopes grow by 1.3 per finer octave.
pub const ROUGH_RATIO: f64 = 0.65;
/// The first rough octave: octave 10 has a wavelength of about 1.6 km on
/// the Earth (frequency `DETAIL_F0·2^10` per radian).
pub const ROUGH_FIRST: u32 = 10;
/// Amplitude in metres of rough octave 10, before the rough gain.
const ROUGH_A10: f64 = 120.0;

/// Number of detail octaves at a leaf level: the finest has a wavelength of
/// about two samples.
pub(crate) fn octaves_at(level: u8) -> u32 {
    // Sample spacing at the leaves, in radians; finest octave ≈ 2 samples.
    let d = std::f64::consts::FRAC_PI_2 / (EW as f64 * 2f64.powi(level as i32));
    let fmax = 1.0 / (2.0 * d);
    ((fmax / DETAIL_F0).log2().floor() as i64 + 1).max(HIGH_OCTAVES as i64 + 1) as u32
}

/// Amplitude in metres (before the rough gain) of rough octave `k`.
fn rough_amplitude(k: u32) -> f64 {
    ROUGH_A10 * ROUGH_RATIO.powi(k as i32 - ROUGH_FIRST as i32)
}

impl Procedural {
    /// A generator for these options.
    ///
    /// Regions are used as given (see [`check_procedural_options`]); a
    /// region level is clamped to `[levels, MAX_PROCEDURAL_LEVEL]`.
    pub fn new(opts: &ProceduralOptions) -> Procedural {
        let caps: Vec<Cap> = opts
            .detail
            .iter()
            .map(|r| Cap {
                level: r
                    .level
                    .clamp(opts.levels, MAX_PROCEDURAL_LEVEL.max(opts.levels)),
                ..r.cap(&opts.datum)
            })
            .collect();
        // Colour is truncated at the base level, except inside the regions,
        // where it follows the elevation down to the region's level
        // (`plan_for_caps`; not in the graded band around them).
        let plan = plan_for_caps(opts.levels, &caps, opts.colour.then_some(opts.levels));
        Procedural {
            seed: opts.seed,
            levels: opts.levels,
            datum: opts.datum,
            colour: opts.colour,
            detail_octaves: octaves_at(opts.levels),
            all_octaves: octaves_at(plan.max_level()),
            plan,
            detail: opts.detail.clone(),
            rough_caps: caps.into_iter().filter(|c| c.level > opts.levels).collect(),
        }
    }

    /// The tree plan: uniform at `levels`, or deepened in the detail regions
    /// and graded ([`plan_for_caps`], thesis §4.3.3).
    pub fn plan(&self) -> Plan {
        self.plan.clone()
    }

    /// Low-frequency fields at a direction: (elevation m, detail gain,
    /// rough gain). The rough gain is exactly 0 where `land` is (the open
    /// ocean), which lets a leaf skip the rough octaves without changing a
    /// value.
    fn low(&self, p: [f64; 3]) -> [f64; 3] {
        let s = self.seed;
        let q = [
            p[0] + 0.35 * fbm(s ^ 0x11, scale(p, 1.7), 3),
            p[1] + 0.35 * fbm(s ^ 0x22, scale(p, 1.7), 3),
            p[2] + 0.35 * fbm(s ^ 0x33, scale(p, 1.7), 3),
        ];
        let c = fbm(s, scale(q, 1.3), 5) + 0.08;
        let land = smoothstep(-0.02, 0.12, c);
        let ridge = ridged(s ^ 0x44, scale(q, 2.6), 5);
        let belt = smoothstep(0.05, 0.45, fbm(s ^ 0x55, scale(p, 1.1), 2) + 0.25);
        let mountains = ridge * ridge * belt * land;
        let mut h = if c < 0.0 {
            // Ocean: shelf, slope, abyssal plain, and ridged trenches.
            let depth = smoothstep(0.0, 0.25, -c);
            -150.0 - 4600.0 * depth - 2600.0 * depth * ridged(s ^ 0x66, scale(p, 3.0), 3).powi(4)
        } else {
            40.0 + 1900.0 * c + 6500.0 * mountains
        };
        let mut f = DETAIL_F0;
        let mut a = 420.0;
        for k in 0..self.detail_octaves.saturating_sub(HIGH_OCTAVES) {
            h += a * (0.4 + 2.0 * mountains) * noise(s ^ (0x100 + k as u64), scale(p, f));
            f *= 2.0;
            a *= 0.5;
        }
        // Rough gain: 0 in the open ocean (`land` is exactly 0 there), 0.05
        // on lowland plains, about 1 on high ground, more in ranges.
        let rough = land * (0.05 + 0.95 * smoothstep(0.0, 1000.0, h)) * (1.0 + mountains);
        [h, 0.4 + 2.0 * mountains, rough]
    }

    /// The per-sample detail octaves, each with its frequency and amplitude
    /// as the lattice octaves' loop would continue them.
    ///
    /// These are the base level's [`HIGH_OCTAVES`] and, in a deeper tree,
    /// the fBm octaves coarser than [`ROUGH_FIRST`] that the base lattice
    /// cannot carry.
    fn high_octaves(&self) -> Vec<DetailOctave> {
        let k0 = self.detail_octaves.saturating_sub(HIGH_OCTAVES);
        let k1 = self.detail_octaves.max(self.all_octaves.min(ROUGH_FIRST));
        let mut f = DETAIL_F0 * 2f64.powi(k0 as i32);
        let mut a = 420.0 * 0.5f64.powi(k0 as i32);
        let mut out = Vec::with_capacity(HIGH_OCTAVES as usize);
        for k in k0..k1 {
            out.push(DetailOctave::new(self.seed ^ (0x100 + k as u64), f, a));
            f *= 2.0;
            a *= 0.5;
        }
        out
    }

    /// Where the rough octaves apply: 1 within half the radius of a region
    /// deeper than the base, fading smoothly to exactly 0 at its radius
    /// (rough detail outside the deep leaves would only alias). A function
    /// of the direction alone, evaluated per sample (generator 3; on the
    /// base lattice before, whose points are 8 base samples apart, about
    /// 39 km at 4 levels: regions narrower than that had no rough detail).
    fn rough_mask(&self, caps: &[Cap], p: [f64; 3]) -> f64 {
        region_mask(caps, p)
    }

    /// The rough per-sample octaves (from the first octave the base planet
    /// lacks, but not coarser than [`ROUGH_FIRST`], to `all_octaves`; none
    /// for a uniform planet): fBm's frequencies, amplitudes falling by
    /// [`ROUGH_RATIO`] per octave ([`rough_amplitude`]).
    fn rough_octaves(&self) -> Vec<DetailOctave> {
        (self.detail_octaves.max(ROUGH_FIRST)..self.all_octaves)
            .map(|k| {
                DetailOctave::new(
                    self.seed ^ (0x100 + k as u64),
                    DETAIL_F0 * 2f64.powi(k as i32),
                    rough_amplitude(k),
                )
            })
            .collect()
    }

    /// The low-frequency fields on the base lattice points
    /// `(x0 + i, y0 + j)`, `i < nx`, `j < ny`, of `face`: lattice point `x`
    /// is base-level sample `LATTICE·x` (the base face map is
    /// `EW·2^levels` samples wide).
    fn lattice(
        &self,
        face: planet_core::Face,
        x0: u64,
        y0: u64,
        nx: usize,
        ny: usize,
    ) -> Vec<[f64; 3]> {
        let n = (EW as u64) << self.levels;
        let axis = |start: u64, count: usize| -> Vec<f64> {
            (0..count as u64)
                .map(|k| plane_from_angle(sample_coord((start + k) * LATTICE as u64, n)))
                .collect()
        };
        let (us, vs) = (axis(x0, nx), axis(y0, ny));
        let mut out = Vec::with_capacity(nx * ny);
        for v in &vs {
            for u in &us {
                let p = normalize(face.cube_point(*u, *v));
                out.push(self.low(p));
            }
        }
        out
    }

    /// Elevation (metres, quantised) of a leaf's samples.
    ///
    /// Per sample: the bilinear base-lattice fields, the [`HIGH_OCTAVES`]
    /// detail octaves times the detail gain and, below the base level, the
    /// rough octaves times the rough gain ([`DetailOctave`], a row of samples
    /// at a time). A leaf at level `L = levels + d` sees lattice cells of
    /// `LATTICE·2^d` of its samples; a sample at global index `g` lies in
    /// lattice cell `g / (LATTICE·2^d)` at fraction `(g mod LATTICE·2^d) /
    /// (LATTICE·2^d)` (exact), the same cell and fraction whatever level
    /// computes it. The lattice fields are interpolated between lattice rows
    /// once per sample row, then along the row; on a block edge this is the
    /// same `a + (b − a)·t` of the same two lattice points from both sides
    /// (the face axes run the same way along shared edges).
    fn leaf_elevation(&self, b: BlockId) -> Vec<i16> {
        let (us, vs) = plane_axes(b);
        let side = EW + 1;
        // Leaves are never shallower than the base level.
        let d = b.level.saturating_sub(self.levels) as u32;
        let cell = (LATTICE as u64) << d;
        let (gx, gy) = (b.x as u64 * EW as u64, b.y as u64 * EW as u64);
        let span = |g0: u64| -> (u64, usize) {
            let first = g0 / cell;
            let last = (g0 + EW as u64).div_ceil(cell);
            (first, (last - first + 1) as usize)
        };
        let ((lx0, nx), (ly0, ny)) = (span(gx), span(gy));
        let lat = self.lattice(b.face, lx0, ly0, nx, ny);
        // Per axis: (lattice index, next lattice index, fraction).
        let axis = |g0: u64, l0: u64, n: usize| -> Vec<(usize, usize, f64)> {
            (0..side as u64)
                .map(|i| {
                    let g = g0 + i;
                    let li = (g / cell - l0) as usize;
                    (li, (li + 1).min(n - 1), (g % cell) as f64 / cell as f64)
                })
                .collect()
        };
        let cols = axis(gx, lx0, nx);
        let rows = axis(gy, ly0, ny);
        let mut octaves = self.high_octaves();
        // The rough octaves are skipped where the rough gain is exactly 0 at
        // every lattice point the leaf interpolates (then every sample's
        // rough term is ±0 and adding it changes nothing).
        // Likewise outside every rough region (the mask is then exactly 0).
        let caps: Vec<Cap> = self
            .rough_caps
            .iter()
            .filter(|c| crate::plan::block_meets_cap(b, c))
            .copied()
            .collect();
        let mut rough_octs = if !caps.is_empty() && lat.iter().any(|l| l[2] != 0.0) {
            self.rough_octaves()
        } else {
            Vec::new()
        };
        let rough_on = !rough_octs.is_empty();
        let mut out = vec![0i16; side * side];
        // Per sample row: the lattice fields (base elevation, detail gain,
        // rough gain) interpolated between the two lattice rows, at each
        // lattice column.
        let mut base = vec![0f64; nx];
        let mut gain = vec![0f64; nx];
        let mut rgain = vec![0f64; nx];
        for (j, &(lj, lj1, fj)) in rows.iter().enumerate() {
            let (r0, r1) = (&lat[lj * nx..lj * nx + nx], &lat[lj1 * nx..lj1 * nx + nx]);
            for k in 0..nx {
                base[k] = r0[k][0] + (r1[k][0] - r0[k][0]) * fj;
                gain[k] = r0[k][1] + (r1[k][1] - r0[k][1]) * fj;
                rgain[k] = r0[k][2] + (r1[k][2] - r0[k][2]) * fj;
            }
            let (mut px, mut py, mut pz) = ([0f64; ROW], [0f64; ROW], [0f64; ROW]);
            for i in 0..ROW {
                [px[i], py[i], pz[i]] = b.face.cube_point(us[i], vs[j]);
            }
            for i in 0..ROW {
                let r = 1.0 / (px[i] * px[i] + py[i] * py[i] + pz[i] * pz[i]).sqrt();
                px[i] *= r;
                py[i] *= r;
                pz[i] *= r;
            }
            let mut hi = [0f32; ROW];
            for oct in octaves.iter_mut() {
                oct.add_row(&px, &py, &pz, &mut hi);
            }
            let mut rough = [0f32; ROW];
            for oct in rough_octs.iter_mut() {
                oct.add_row(&px, &py, &pz, &mut rough);
            }
            let row = &mut out[j * side..(j + 1) * side];
            for (i, o) in row.iter_mut().enumerate() {
                let (li, li1, fi) = cols[i];
                let h0 = base[li] + (base[li1] - base[li]) * fi;
                let g = gain[li] + (gain[li1] - gain[li]) * fi;
                let v = h0 + g * hi[i] as f64;
                *o = round_to_i16(if rough_on {
                    let mask = self.rough_mask(&caps, [px[i], py[i], pz[i]]);
                    let gr = (rgain[li] + (rgain[li1] - rgain[li]) * fi) * mask;
                    v + gr * rough[i] as f64
                } else {
                    v
                });
            }
        }
        out
    }

    /// The exact re-projected full elevation grid `(W+1)²` (stored units =
    /// metres) of any block: a leaf's generated grid, or an inner block's
    /// samples gathered from its descendants' leaves (what the database holds).
    pub fn elevation_grid(&self, b: BlockId) -> Vec<i16> {
        if !self.plan.elevation_split(b) {
            return self.leaf_elevation(b);
        }
        let side = EW + 1;
        let mut full = vec![0i16; side * side];
        for (k, c) in b.children().into_iter().enumerate() {
            let g = self.elevation_grid(c);
            lod::merge_elevation(&g, EW, k, &mut full);
        }
        full
    }

    /// The exact full colour grid `Wc²` of any block (what the database holds).
    pub fn colour_grid(&self, b: BlockId) -> Vec<Rgb> {
        if !self.plan.colour_split(b) {
            let e = self.elevation_grid(b);
            return self.colour_for(b, &e);
        }
        let mut full = vec![[0u8; 3]; CW * CW];
        for (k, c) in b.children().into_iter().enumerate() {
            let g = self.colour_grid(c);
            lod::merge_colour(&lod::colour_filter(&g, CW), CW, k, &mut full);
        }
        full
    }

    /// The colour grid of a leaf from its elevation grid, a texel row at a
    /// time: the inputs of every texel (bilinear elevation, moisture,
    /// latitude, slope) go into per-row arrays, then the branch-free f32
    /// [`palette`] runs over the row (it vectorises). The per-texel position
    /// arithmetic is done once per column and per row, the lattice fields'
    /// horizontal interpolation once per lattice row band, the elevation's
    /// vertical interpolation once per grid column.
    fn colour_for(&self, b: BlockId, elev: &[i16]) -> Vec<Rgb> {
        let (us, vs) = plane_axes(b);
        let n = EW / LATTICE + 1;
        // Moisture and |latitude| on the lattice (81 evaluations per block),
        // interpolated per texel.
        let mut moist = Vec::with_capacity(n * n);
        let mut lats = Vec::with_capacity(n * n);
        for j in 0..n {
            for i in 0..n {
                let p = normalize(b.face.cube_point(us[i * LATTICE], vs[j * LATTICE]));
                moist.push(fbm(self.seed ^ 0x77, scale(p, 2.2), 3));
                lats.push(p[2].clamp(-1.0, 1.0).asin().to_degrees().abs());
            }
        }
        let side = EW + 1;
        let ratio = EW as f64 / CW as f64;
        let l = b.level as i32;
        // `(|∂h/∂x| + |∂h/∂y|)` per grid cell times `1.56 / spacing` (the
        // spacing is about `1.57e5 m / 2^L` on the Earth), so a slope of 1
        // is a gradient of about 0.32 per axis at every level.
        let inv_slope_scale = (2.0f64.powi(l) * 1.0e-5) as f32;
        // Leaves below the base level (detail regions) take the slope at
        // each texel from the cell's bilinear gradient instead of one
        // forward difference per cell: the rough octaves vary from cell to
        // cell, and a per-cell slope paints 2×2-texel squares that the
        // record's LOD 1 already holds (an error of 0 or 1). The base
        // level's leaves keep the per-cell slope (uniform planets are
        // unchanged).
        let deep = b.level > self.levels;
        // Texel centre position in grid cells and lattice cells, per column
        // (and the same per row).
        struct Axis {
            x0: usize,
            fx: f32,
            mi: usize,
            mfx: f64,
        }
        let axis = |k: usize| {
            let g = (k as f64 + 0.5) * ratio;
            let m = g / LATTICE as f64;
            let mi = (m.floor() as usize).min(n - 2);
            Axis {
                x0: (g.floor() as usize).min(EW - 1),
                fx: g.fract() as f32,
                mi,
                mfx: m - mi as f64,
            }
        };
        let cols: Vec<Axis> = (0..CW).map(axis).collect();
        // Texel columns 2m and 2m + 1 lie in elevation cell m (CW = 2·EW):
        // per-column arrays are kept de-interleaved, even columns first
        // (position m), then odd ones (position H + m), so that a row needs
        // no gather.
        const H: usize = CW / 2;
        const _: () = assert!(CW == 2 * EW);
        let pos = |k: usize| (k % 2) * H + k / 2;
        let (fx_even, fx_odd) = (cols[0].fx, cols[1].fx);
        // Per lattice row band `mj`: for each column, the horizontally
        // interpolated moisture and latitude on lattice rows mj and mj + 1.
        let mut band = usize::MAX;
        let (mut m0, mut m1) = ([0f32; CW], [0f32; CW]);
        let (mut t0, mut t1) = ([0f32; CW], [0f32; CW]);
        let mut out = vec![[0u8; 3]; CW * CW];
        for (j, orow) in out.chunks_exact_mut(CW).enumerate() {
            let ra = axis(j);
            let (y0, fy, mj, mfy) = (ra.x0, ra.fx, ra.mi, ra.mfx as f32);
            if mj != band {
                band = mj;
                for (k, c) in cols.iter().enumerate() {
                    let (mi, mfx) = (c.mi, c.mfx);
                    let row = |g: &[f64], r: usize| {
                        (g[r * n + mi] + (g[r * n + mi + 1] - g[r * n + mi]) * mfx) as f32
                    };
                    let q = pos(k);
                    m0[q] = row(&moist, mj);
                    m1[q] = row(&moist, mj + 1);
                    t0[q] = row(&lats, mj);
                    t1[q] = row(&lats, mj + 1);
                }
            }
            let e0 = &elev[y0 * side..(y0 + 1) * side];
            let e1 = &elev[(y0 + 1) * side..(y0 + 2) * side];
            // Elevation between the two grid rows, per grid column, and the
            // slope of each grid cell (for rock on steep terrain).
            let mut v = [0f32; EW + 1];
            for (vi, (&a, &c)) in v.iter_mut().zip(e0.iter().zip(e1)) {
                let (a, c) = (a as f32, c as f32);
                *vi = a + (c - a) * fy;
            }
            let mut h = [0f32; CW];
            let mut slope = [0f32; CW];
            for m in 0..H {
                let d = v[m + 1] - v[m];
                h[m] = v[m] + d * fx_even;
                h[H + m] = v[m] + d * fx_odd;
            }
            if deep {
                // The gradient of the cell's bilinear surface at each texel
                // centre (the cell's corners only: seam-free): x along the
                // texel row, y between the two texel columns of the cell.
                for m in 0..H {
                    let (a00, a10) = (e0[m] as f32, e0[m + 1] as f32);
                    let (a01, a11) = (e1[m] as f32, e1[m + 1] as f32);
                    let gx = ((a10 - a00) + ((a11 - a01) - (a10 - a00)) * fy).abs();
                    let (dy0, dy1) = (a01 - a00, a11 - a10);
                    slope[m] = (gx + (dy0 + (dy1 - dy0) * fx_even).abs()) * inv_slope_scale;
                    slope[H + m] = (gx + (dy0 + (dy1 - dy0) * fx_odd).abs()) * inv_slope_scale;
                }
            } else {
                for m in 0..H {
                    let a00 = e0[m] as f32;
                    slope[m] = ((e0[m + 1] as f32 - a00).abs() + (e1[m] as f32 - a00).abs())
                        * inv_slope_scale;
                    slope[H + m] = slope[m];
                }
            }
            let (mut r, mut g, mut bl) = ([0f32; CW], [0f32; CW], [0f32; CW]);
            for q in 0..CW {
                let m = m0[q] + (m1[q] - m0[q]) * mfy;
                let lat = t0[q] + (t1[q] - t0[q]) * mfy;
                [r[q], g[q], bl[q]] = palette(h[q], lat, m, slope[q]);
            }
            for (m, o) in orow.chunks_exact_mut(2).enumerate() {
                o[0] = [to_u8(r[m]), to_u8(g[m]), to_u8(bl[m])];
                o[1] = [to_u8(r[H + m]), to_u8(g[H + m]), to_u8(bl[H + m])];
            }
        }
        out
    }
}

/// Gnomonic plane coordinates of the elevation sample columns and rows.
fn plane_axes(b: BlockId) -> (Vec<f64>, Vec<f64>) {
    let n = (EW as u64) << b.level;
    let us = (0..=EW as u64)
        .map(|i| plane_from_angle(sample_coord(b.x as u64 * EW as u64 + i, n)))
        .collect();
    let vs = (0..=EW as u64)
        .map(|j| plane_from_angle(sample_coord(b.y as u64 * EW as u64 + j, n)))
        .collect();
    (us, vs)
}

#[inline(always)]
fn lerp3(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

/// `x` clamped to `[0, 1]` (selects, no NaN handling: inputs are finite).
#[inline(always)]
fn sat(x: f32) -> f32 {
    let x = if x < 0.0 { 0.0 } else { x };
    if x > 1.0 {
        1.0
    } else {
        x
    }
}

/// `smoothstep(a, a + 1/inv, x)`.
#[inline(always)]
fn step32(a: f32, inv: f32, x: f32) -> f32 {
    let t = sat((x - a) * inv);
    t * t * (3.0 - 2.0 * t)
}

/// A colour channel in `[0, 255]` to the nearest byte, without a
/// float-to-int cast (it vectorises): `1.5 · 2^23` rounds to an integer.
#[inline(always)]
fn to_u8(c: f32) -> u8 {
    const M: f32 = 12_582_912.0;
    let c = if c < 0.0 { 0.0 } else { c };
    let c = if c > 255.0 { 255.0 } else { c };
    (c + M).to_bits() as u8
}

/// Colour by altitude (m), |latitude| (degrees), moisture and slope, as
/// channel values in `[0, 255]`. Branch-free: every layer is computed and the
/// water/beach/land choice is a select, so a row of texels vectorises.
#[inline(always)]
fn palette(h: f32, lat: f32, moisture: f32, slope: f32) -> [f32; 3] {
    let ocean = lerp3(
        [46.0, 110.0, 170.0],
        [8.0, 24.0, 72.0],
        sat(h * (-1.0 / 6000.0)),
    );
    let arid = step32(
        0.0,
        1.0 / 0.3,
        1.0 - (lat - 24.0).abs() * (1.0 / 14.0) - moisture * 1.5,
    );
    let green = lerp3(
        [52.0, 110.0, 44.0],
        [96.0, 128.0, 64.0],
        sat(h * (1.0 / 2000.0)),
    );
    let mut c = lerp3(green, [204.0, 172.0, 112.0], arid);
    c = lerp3(c, [120.0, 122.0, 96.0], step32(50.0, 1.0 / 16.0, lat)); // tundra
    let rock = step32(2200.0, 1.0 / 1000.0, h);
    let steep = if slope < 1.0 { slope } else { 1.0 } * 0.6;
    c = lerp3(
        c,
        [118.0, 106.0, 96.0],
        if steep > rock { steep } else { rock },
    );
    let snowline = 5200.0 - 4200.0 * sat(lat * (1.0 / 75.0));
    c = lerp3(c, [244.0, 245.0, 250.0], step32(snowline, 1.0 / 400.0, h));
    let beach = [214.0, 200.0, 150.0];
    let mut out = [0f32; 3];
    for k in 0..3 {
        out[k] = if h < 0.0 {
            ocean[k]
        } else if h < 25.0 {
            beach[k]
        } else {
            c[k]
        };
    }
    let ice = step32(72.0, 1.0 / 6.0, lat + moisture * 4.0);
    lerp3(out, [236.0, 242.0, 248.0], ice)
}

impl GridSource for Procedural {
    fn elevation_leaf(&self, b: BlockId, out: &mut [i16]) -> Result<(), BuildError> {
        let g = self.leaf_elevation(b);
        out.copy_from_slice(&g);
        Ok(())
    }

    fn colour_leaf(&self, b: BlockId, elevation: &[i16]) -> Result<Vec<Rgb>, BuildError> {
        Ok(self.colour_for(b, elevation))
    }

    fn datum(&self) -> Datum {
        self.datum
    }

    fn elevation_scale(&self) -> f64 {
        1.0
    }

    fn has_colour(&self) -> bool {
        self.colour
    }

    fn description(&self) -> String {
        let mut d = format!(
            "procedural planet (generator {GENERATOR_VERSION}): seed {}, {} levels, {:?}",
            self.seed, self.levels, self.datum
        );
        for r in &self.detail {
            d.push_str(&format!(", detail {r}"));
        }
        d
    }
}

// ---- noise -----------------------------------------------------------------

#[inline]
fn scale(p: [f64; 3], f: f64) -> [f64; 3] {
    [p[0] * f, p[1] * f, p[2] * f]
}

#[inline]
fn smoothstep(a: f64, b: f64, x: f64) -> f64 {
    let t = ((x - a) / (b - a)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Where detail below a region's base applies: 1 within half the radius of
/// any of `caps`, fading smoothly (smoothstep) to exactly 0 at its radius;
/// the largest over the caps. A function of the direction alone, so samples
/// with bit-identical directions agree whatever block computes them. Used by
/// the procedural planet's rough octaves and by the detail added to rasters
/// ([`crate::amplify`]).
pub(crate) fn region_mask(caps: &[Cap], p: [f64; 3]) -> f64 {
    caps.iter()
        .map(|c| 1.0 - smoothstep(0.5 * c.radius, c.radius, angle_between(p, c.centre)))
        .fold(0.0, f64::max)
}

#[inline]
fn hash(seed: u64, x: i64, y: i64, z: i64) -> u64 {
    let mut h = seed
        ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (z as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 33;
    h = h.wrapping_mul(0xff51_afd7_ed55_8ccd);
    h ^= h >> 33;
    h = h.wrapping_mul(0xc4ce_b9fe_1a85_ec53);
    h ^ (h >> 33)
}

/// The gradient of `grad`'s 16 cases, as (first operand, second operand,
/// negate first, negate second): case 0 is `x + y`, 1 `-x + y`, 2 `x - y`,
/// 3 `-x - y`, 4..7 the same with `x, z`, 8..11 with `y, z`, 12 `x + y`,
/// 13 `-x + y`, 14 `-y + z`, 15 `-y - z`.
const GRAD: [(u8, u8, bool, bool); 16] = [
    (0, 1, false, false),
    (0, 1, true, false),
    (0, 1, false, true),
    (0, 1, true, true),
    (0, 2, false, false),
    (0, 2, true, false),
    (0, 2, false, true),
    (0, 2, true, true),
    (1, 2, false, false),
    (1, 2, true, false),
    (1, 2, false, true),
    (1, 2, true, true),
    (0, 1, false, false),
    (0, 1, true, false),
    (1, 2, true, false),
    (1, 2, true, true),
];

/// The 16 gradient cases packed one byte each: bits 0–1 first operand,
/// 2–3 second operand, 4 negate first, 5 negate second.
const GRAD_PACKED: [u8; 16] = {
    let mut t = [0u8; 16];
    let mut k = 0;
    while k < 16 {
        let (a, b, na, nb) = GRAD[k];
        t[k] = a | (b << 2) | ((na as u8) << 4) | ((nb as u8) << 5);
        k += 1;
    }
    t
};

/// `±a ± b` of the hashed case, without data-dependent branches. Negation is
/// a sign-bit flip and `a - b` is `a + (-b)` in IEEE arithmetic, so this is
/// bit-identical to writing the 16 expressions out.
#[inline(always)]
fn grad(code: u8, x: f64, y: f64, z: f64) -> f64 {
    let v = [x, y, z];
    let a = v[(code & 3) as usize];
    let b = v[((code >> 2) & 3) as usize];
    let sa = ((code as u64 >> 4) & 1) << 63;
    let sb = ((code as u64 >> 5) & 1) << 63;
    f64::from_bits(a.to_bits() ^ sa) + f64::from_bits(b.to_bits() ^ sb)
}

/// `floor` without a libm call (exact for |x| < 2^52).
#[inline]
fn ffloor(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

#[inline]
fn fade(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// The gradient codes of the 8 corners of lattice cell `(xi, yi, zi)`, in the
/// order `(dx, dy, dz)` = 000, 100, 010, 110, 001, 101, 011, 111.
#[inline]
fn corner_codes(seed: u64, xi: i64, yi: i64, zi: i64) -> [u8; 8] {
    let mut out = [0u8; 8];
    for (k, o) in out.iter_mut().enumerate() {
        let (dx, dy, dz) = ((k & 1) as i64, ((k >> 1) & 1) as i64, (k >> 2) as i64);
        *o = GRAD_PACKED[(hash(seed, xi + dx, yi + dy, zi + dz) & 15) as usize];
    }
    out
}

/// Noise inside one cell from its corner codes and the fractional position.
#[inline(always)]
fn noise_in_cell(c: &[u8; 8], x: f64, y: f64, z: f64) -> f64 {
    let (u, v, w) = (fade(x), fade(y), fade(z));
    let (x1, y1, z1) = (x - 1.0, y - 1.0, z - 1.0);
    let l = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let x00 = l(grad(c[0], x, y, z), grad(c[1], x1, y, z), u);
    let x10 = l(grad(c[2], x, y1, z), grad(c[3], x1, y1, z), u);
    let x01 = l(grad(c[4], x, y, z1), grad(c[5], x1, y, z1), u);
    let x11 = l(grad(c[6], x, y1, z1), grad(c[7], x1, y1, z1), u);
    l(l(x00, x10, v), l(x01, x11, v), w) * 0.9
}

/// 3D gradient noise in about [-1, 1].
pub fn noise(seed: u64, p: [f64; 3]) -> f64 {
    let (xf, yf, zf) = (ffloor(p[0]), ffloor(p[1]), ffloor(p[2]));
    let c = corner_codes(seed, xf as i64, yf as i64, zf as i64);
    noise_in_cell(&c, p[0] - xf, p[1] - yf, p[2] - zf)
}

/// Samples in a row of a leaf's elevation grid.
pub(crate) const ROW: usize = EW + 1;

/// One per-sample detail octave: 3D gradient noise of the direction scaled
/// by `f`, times the amplitude, evaluated a row of samples at a time in three
/// passes so that the arithmetic vectorises:
///
/// 1. the lattice cell (f64, exact at any depth the builder allows: cells
///    stay below 2^31) and the position in it (f32) of every sample;
/// 2. a scalar pass that hashes the 8 corners of a cell only when the cell
///    changes (neighbouring samples mostly share it) and gives every sample
///    its cell's gradients packed in one word;
/// 3. the noise inside the cell, in f32, from the packed gradients.
///
/// The gradients are the 8 cube diagonals `(±1, ±1, ±1)`, so a corner's dot
/// product is `±x ± y ± z`, three sign-bit flips taken straight from the
/// hash bits (no table gather). The corner hash is a 32-bit integer mix.
/// Every step is a function of the sample's direction alone, so samples with
/// bit-identical directions (shared block and face edges) agree exactly.
#[derive(Debug, Clone)]
pub(crate) struct DetailOctave {
    seed: u32,
    f: f64,
    amp: f32,
    cell: [i32; 3],
    code: u32,
}

impl DetailOctave {
    pub(crate) fn new(seed: u64, f: f64, a: f64) -> DetailOctave {
        let mut o = DetailOctave {
            seed: fold_seed(seed),
            f,
            // The noise's 0.9 scale folded into the amplitude.
            amp: (a * 0.9) as f32,
            cell: [0; 3],
            code: 0,
        };
        o.set_cell([0; 3]);
        o
    }

    /// The packed gradient signs of the corners of `cell`: bits `3k..3k+3`
    /// are corner `k`'s (x, y, z) signs (1 = negative), corners in the order
    /// `(dx, dy, dz)` = 000, 100, 010, 110, 001, 101, 011, 111.
    fn set_cell(&mut self, cell: [i32; 3]) {
        self.cell = cell;
        let (x, y, z) = (cell[0] as u32, cell[1] as u32, cell[2] as u32);
        let hx = [
            x.wrapping_mul(0x9E37_79B1),
            x.wrapping_add(1).wrapping_mul(0x9E37_79B1),
        ];
        let hy = [
            y.wrapping_mul(0x85EB_CA77),
            y.wrapping_add(1).wrapping_mul(0x85EB_CA77),
        ];
        let hz = [
            z.wrapping_mul(0xC2B2_AE3D),
            z.wrapping_add(1).wrapping_mul(0xC2B2_AE3D),
        ];
        let mut code = 0u32;
        for k in 0..8 {
            let h = mix32(self.seed ^ hx[k & 1] ^ hy[(k >> 1) & 1] ^ hz[k >> 2]);
            code |= (h >> 29) << (3 * k);
        }
        self.code = code;
    }

    /// Add `amplitude · noise(f·p)` of the row's directions to `acc`.
    pub(crate) fn add_row(
        &mut self,
        px: &[f64; ROW],
        py: &[f64; ROW],
        pz: &[f64; ROW],
        acc: &mut [f32; ROW],
    ) {
        let f = self.f;
        let mut cx = [0i32; ROW];
        let mut cy = [0i32; ROW];
        let mut cz = [0i32; ROW];
        let mut fx = [0f32; ROW];
        let mut fy = [0f32; ROW];
        let mut fz = [0f32; ROW];
        for i in 0..ROW {
            (cx[i], fx[i]) = cell_of(px[i] * f);
            (cy[i], fy[i]) = cell_of(py[i] * f);
            (cz[i], fz[i]) = cell_of(pz[i] * f);
        }
        let mut codes = [0u32; ROW];
        for i in 0..ROW {
            let c = [cx[i], cy[i], cz[i]];
            if c != self.cell {
                self.set_cell(c);
            }
            codes[i] = self.code;
        }
        let amp = self.amp;
        for i in 0..ROW {
            acc[i] += amp * noise_diag(codes[i], fx[i], fy[i], fz[i]);
        }
    }
}

/// `1.5 · 2^52`: `x + MAGIC` rounds `x` to an integer (nearest, ties to
/// even) for |x| < 2^51, and the low 32 bits of the sum are that integer.
const MAGIC: f64 = 6_755_399_441_055_744.0;

/// The lattice cell of a coordinate (|x| < 2^31) and the position in it, in
/// `[0, 1)`, with adds, compares and bit operations only (they vectorise;
/// a float-to-int cast does not).
#[inline(always)]
fn cell_of(x: f64) -> (i32, f32) {
    let m = x + MAGIC;
    let r = m - MAGIC; // round(x), exact
    let down = r > x;
    let xf = if down { r - 1.0 } else { r };
    (
        (m.to_bits() as u32 as i32).wrapping_sub(down as i32),
        (x - xf) as f32,
    )
}

/// `x` (|x| ≤ 8000 here) rounded to the nearest integer, ties to even,
/// without a float-to-int cast (it vectorises).
#[inline(always)]
fn round_to_i16(x: f64) -> i16 {
    (x.clamp(-8000.0, 8000.0) + MAGIC).to_bits() as u16 as i16
}

/// `v` with its sign flipped where bit `k` of `code` is set.
#[inline(always)]
fn flip(v: f32, code: u32, k: u32) -> f32 {
    f32::from_bits(v.to_bits() ^ ((code >> k) << 31))
}

/// Gradient noise in a cell from its packed corner gradients (see
/// [`DetailOctave::set_cell`]) and the position in it, in about [-1, 1]
/// before the 0.9 scale.
#[inline(always)]
fn noise_diag(code: u32, x: f32, y: f32, z: f32) -> f32 {
    let (x1, y1, z1) = (x - 1.0, y - 1.0, z - 1.0);
    let d = |k: u32, x: f32, y: f32, z: f32| {
        flip(x, code, 3 * k) + flip(y, code, 3 * k + 1) + flip(z, code, 3 * k + 2)
    };
    let (u, v, w) = (fade32(x), fade32(y), fade32(z));
    let l = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = l(d(0, x, y, z), d(1, x1, y, z), u);
    let x10 = l(d(2, x, y1, z), d(3, x1, y1, z), u);
    let x01 = l(d(4, x, y, z1), d(5, x1, y, z1), u);
    let x11 = l(d(6, x, y1, z1), d(7, x1, y1, z1), u);
    // The diagonals are √3 long where the 12 edge gradients were √2: scale
    // to keep the octave's amplitude.
    l(l(x00, x10, v), l(x01, x11, v), w) * 0.816_496_6
}

#[inline(always)]
fn fade32(t: f32) -> f32 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// A 64-bit seed folded to 32 bits and mixed.
fn fold_seed(s: u64) -> u32 {
    mix32((s ^ (s >> 32)) as u32 ^ 0x2545_F491)
}

/// A 32-bit integer finaliser (two multiply–xorshift rounds).
#[inline(always)]
fn mix32(mut h: u32) -> u32 {
    h ^= h >> 16;
    h = h.wrapping_mul(0x7FEB_352D);
    h ^= h >> 15;
    h = h.wrapping_mul(0x846C_A68B);
    h ^ (h >> 16)
}

/// Fractal Brownian motion, `octaves` octaves, lacunarity 2, gain 0.5.
pub fn fbm(seed: u64, p: [f64; 3], octaves: u32) -> f64 {
    let (mut f, mut a, mut s) = (1.0, 0.5, 0.0);
    for k in 0..octaves {
        s += a * noise(seed.wrapping_add(k as u64 * 0x51), scale(p, f));
        f *= 2.0;
        a *= 0.5;
    }
    s * 1.6
}

/// Ridged multifractal in [0, 1] (sharp crests).
pub fn ridged(seed: u64, p: [f64; 3], octaves: u32) -> f64 {
    let (mut f, mut a, mut s, mut norm) = (1.0, 0.5, 0.0, 0.0);
    for k in 0..octaves {
        let n = 1.0 - noise(seed.wrapping_add(k as u64 * 0x53), scale(p, f)).abs();
        s += a * n * n;
        norm += a;
        f *= 2.0;
        a *= 0.5;
    }
    s / norm
}

#[cfg(test)]
mod tests {
    use super::*;
    use planet_core::{Edge, Face};

    fn gen(levels: u8) -> Procedural {
        Procedural::new(&ProceduralOptions {
            levels,
            ..default_procedural_options()
        })
    }

    #[test]
    fn shared_edges_agree_across_faces() {
        let g = gen(3);
        let w = EW;
        for f in Face::ALL {
            for e in Edge::ALL {
                let b = BlockId::new(
                    f,
                    3,
                    if e == Edge::Right { 7 } else { 0 },
                    if e == Edge::Top { 7 } else { 0 },
                )
                .unwrap();
                let (nb, back) = b.neighbour(e);
                let ga = g.elevation_grid(b);
                let gb = g.elevation_grid(nb);
                let edge = |grid: &[i16], ed: Edge| -> Vec<i16> {
                    (0..=w)
                        .map(|k| {
                            let (i, j) = match ed {
                                Edge::Left => (0, k),
                                Edge::Right => (w, k),
                                Edge::Bottom => (k, 0),
                                Edge::Top => (k, w),
                            };
                            grid[j * (w + 1) + i]
                        })
                        .collect()
                };
                assert_eq!(edge(&ga, e), edge(&gb, back), "{b:?} {e:?}");
            }
        }
    }

    #[test]
    fn cell_and_rounding_helpers_are_exact() {
        for &x in &[
            0.0,
            -0.0,
            0.25,
            -0.25,
            1.0,
            -1.0,
            2.5,
            -2.5,
            1e-300,
            -1e-300,
            0.999_999_999_999,
            -0.999_999_999_999,
            12_345.678,
            -12_345.678,
            1_073_741_823.5,
            -1_073_741_824.0,
            2_000_000_000.75,
            -2_000_000_000.75,
        ] {
            let (c, f) = cell_of(x);
            assert_eq!(c as f64, x.floor(), "cell of {x}");
            assert_eq!(f, (x - x.floor()) as f32, "position of {x}");
        }
        for &x in &[
            0.0, 0.4, 0.6, -0.4, -0.6, 1.5, 2.5, -1.5, 7999.6, -7999.6, 1e9, -1e9,
        ] {
            let r = round_to_i16(x);
            let want = x.clamp(-8000.0, 8000.0).round_ties_even();
            assert_eq!(r as f64, want, "round {x}");
        }
        for &c in &[0.0, 0.4, 0.6, 254.5, 255.0, 300.0, -3.0] {
            assert_eq!(to_u8(c) as f32, c.clamp(0.0, 255.0).round_ties_even());
        }
    }

    #[test]
    #[allow(clippy::needless_range_loop)] // `i` indexes the octaves' rows
    fn detail_noise_is_continuous_and_bounded() {
        // A row of directions finely spaced across many cells of the finest
        // octave: neighbouring values differ by at most a Lipschitz bound,
        // so the noise has no jumps at cell boundaries.
        let g = gen(6);
        let mut octs = g.high_octaves();
        let step = 1.0e-5;
        let mut prev: Option<[f32; HIGH_OCTAVES as usize]> = None;
        let mut spread = 0f32;
        for r in 0..200 {
            let (mut px, mut py, mut pz) = ([0f64; ROW], [0f64; ROW], [0f64; ROW]);
            for i in 0..ROW {
                let t = (r * ROW + i) as f64 * step - 0.05;
                [px[i], py[i], pz[i]] = normalize([t, 0.3 + 0.5 * t, 1.0]);
            }
            let mut vals = [[0f32; ROW]; HIGH_OCTAVES as usize];
            for (o, v) in octs.iter_mut().zip(vals.iter_mut()) {
                o.add_row(&px, &py, &pz, v);
            }
            for i in 0..ROW {
                let cur: [f32; HIGH_OCTAVES as usize] = std::array::from_fn(|k| vals[k][i]);
                if let Some(p) = prev {
                    for (k, o) in octs.iter().enumerate() {
                        // |∇noise| ≤ ~3 per cell; the step is f·step cells.
                        let bound = o.amp * 4.0 * (o.f * step * 1.2) as f32 + 1e-4;
                        assert!((cur[k] - p[k]).abs() <= bound, "octave {k} jumps");
                        assert!(cur[k].abs() <= o.amp * 1.2, "octave {k} out of range");
                        spread = spread.max(cur[k].abs() / o.amp);
                    }
                }
                prev = Some(cur);
            }
        }
        assert!(spread > 0.3, "noise too flat: {spread}");
    }

    fn deep(levels: u8, region: &str) -> Procedural {
        Procedural::new(&ProceduralOptions {
            levels,
            detail: vec![region.parse().expect("region")],
            ..default_procedural_options()
        })
    }

    /// A sample's value does not depend on the level of the leaf computing
    /// it: a split block computed as if it were a leaf equals the samples
    /// gathered from its deeper leaves, bit for bit.
    #[test]
    fn values_do_not_depend_on_the_leaf_level() {
        // Base lattice every ~78 km, a 300 km region (rough within it), to
        // level 8 (finest octave 10: the first rough one).
        let g = deep(4, "46.85,-121.76,300,8");
        let Plan::Explicit { split, .. } = g.plan() else {
            panic!("explicit plan expected");
        };
        assert_eq!(g.plan().max_level(), 8);
        assert_eq!(g.rough_octaves().len(), 1);
        assert_eq!(g.high_octaves().len(), 6);
        let mut smooth = g.clone();
        smooth.rough_caps.clear();
        let mut checked = 0;
        let mut rough = 0;
        for b in &split {
            if b.level >= 4 {
                let as_leaf = g.leaf_elevation(*b);
                let gathered = g.elevation_grid(*b);
                assert_eq!(as_leaf, gathered, "{b:?}");
                checked += 1;
                // The same block without its rough octaves differs.
                rough += (smooth.leaf_elevation(*b) != as_leaf) as usize;
            }
        }
        assert!(
            checked >= 8 && rough >= 4,
            "{checked} blocks, {rough} rough"
        );
    }

    /// A region narrower than the base lattice's spacing (8 base samples,
    /// about 39 km at 4 levels) is rough too: the mask is per sample
    /// (generator 2 evaluated it on the lattice, and the built-in planet's
    /// 12 km places came out as smooth ramps).
    #[test]
    fn narrow_regions_on_a_shallow_base_are_rough() {
        let g = deep(4, "-17.5,-107,12,14");
        let p = direction_from_lat_lon((-17.5f64).to_radians(), (-107f64).to_radians());
        let fc = planet_core::cube::FaceCoord::from_direction(p);
        let n = 1u32 << 14;
        let cell = |v: f64| ((v * n as f64) as u32).min(n - 1);
        let b = BlockId::new(fc.face, 14, cell(fc.s), cell(fc.t)).expect("block");
        let leaf = g.leaf_elevation(b);
        assert!(crate::build::elevation_lod_error(&leaf, EW) >= 3.0);
        let mut smooth = g.clone();
        smooth.rough_caps.clear();
        let diff = leaf
            .iter()
            .zip(smooth.leaf_elevation(b))
            .map(|(a, b)| (*a as i32 - b as i32).abs())
            .max()
            .unwrap_or(0);
        assert!(diff >= 20, "rough octaves add at most {diff} m");
    }

    /// The rough octaves make a deep planet's fine levels rough on high
    /// ground (slopes of tenths at ~10 m) while the uniform planet of the same
    /// seed is smooth there and lowlands stay smooth.
    #[test]
    fn deep_levels_are_rough_in_the_mountains() {
        let g = deep(6, "27.95,86.93,60,14");
        let p = direction_from_lat_lon(27.95f64.to_radians(), 86.93f64.to_radians());
        let fc = planet_core::cube::FaceCoord::from_direction(p);
        let n = 1u32 << 14;
        let cell = |v: f64| ((v * n as f64) as u32).min(n - 1);
        let b = BlockId::new(fc.face, 14, cell(fc.s), cell(fc.t)).expect("block");
        let mean_slope = |e: &[i16], spacing: f64| {
            let side = EW + 1;
            let mut s = 0f64;
            for j in 0..side {
                for i in 0..EW {
                    s += ((e[j * side + i + 1] - e[j * side + i]) as f64).abs();
                }
            }
            s / (side * EW) as f64 / spacing
        };
        // 64 samples over ~611 m at level 14.
        let leaf = g.leaf_elevation(b);
        let slope = mean_slope(&leaf, 9.5);
        assert!(g.low(p)[0] > 1000.0, "high ground expected");
        assert!((0.15..1.0).contains(&slope), "mean slope {slope}");
        assert!(crate::build::elevation_lod_error(&leaf, EW) >= 3.0);
        // A uniform level-6 planet's own leaves at the same place: fBm
        // detail only, slopes of thousandths at ~150 m spacing.
        let u = gen(6);
        let ub = b.ancestor(6);
        let ue = u.leaf_elevation(ub);
        assert!(mean_slope(&ue, 150.0) < 0.05);
        // Outside the region: no rough octaves.
        assert_eq!(
            g.rough_mask(&g.rough_caps, direction_from_lat_lon(0.5, 1.0)),
            0.0
        );
        assert_eq!(g.rough_mask(&g.rough_caps, p), 1.0);
        // Deep ocean: no rough gain at all.
        let mut oceans = 0;
        for lat in (-60..=60).step_by(10) {
            for lon in (-180..180).step_by(10) {
                let l = g.low(direction_from_lat_lon(
                    (lat as f64).to_radians(),
                    (lon as f64).to_radians(),
                ));
                if l[0] < -3000.0 {
                    assert_eq!(l[2], 0.0, "{lat} {lon}");
                    oceans += 1;
                }
            }
        }
        assert!(oceans > 20, "{oceans} deep-ocean points");
    }

    #[test]
    fn detail_regions_parse_and_reject_bad_input() {
        let r: DetailRegion = "46.85,-121.76,60,14".parse().expect("valid");
        assert_eq!(
            r,
            DetailRegion {
                lat: 46.85,
                lon: -121.76,
                radius_km: 60.0,
                level: 14
            }
        );
        for bad in [
            "",
            "1,2,3",
            "1,2,3,4,5",
            "x,2,3,4",
            "91,0,1,5",
            "0,-181,1,5",
            "0,0,0,5",
            "0,0,-1,5",
            "0,0,NaN,5",
            "0,0,inf,5",
            "0,0,1,21",
            "0,0,1,-1",
            "0,0,1,1.5",
        ] {
            let e = bad.parse::<DetailRegion>().expect_err(bad);
            assert!(
                e.contains(&format!("'{bad}'")) && e.contains("LAT,LON,RADIUS_KM,LEVEL"),
                "{e}"
            );
        }
        let mut o = default_procedural_options();
        o.levels = 6;
        o.detail = vec![r, "0,0,1,5".parse().expect("valid")];
        let e = check_procedural_options(&o).expect_err("shallow region");
        assert!(e.to_string().contains("shallower than --levels 6"), "{e}");
        o.detail.pop();
        assert!(check_procedural_options(&o).is_ok());
    }

    #[test]
    fn range_and_variety() {
        let g = gen(3);
        let (mut lo, mut hi) = (i16::MAX, i16::MIN);
        for f in Face::ALL {
            let grid = g.elevation_grid(BlockId::root(f));
            for v in grid {
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
        assert!(lo < -2000 && hi > 1500, "range {lo}..{hi}");
        assert!(lo >= -8000 && hi <= 8000);
        let c = g.colour_grid(BlockId::root(Face::new(2).unwrap()));
        let blue = c.iter().filter(|p| p[2] as u16 > p[0] as u16 + 30).count();
        let other = c.iter().filter(|p| p[2] <= p[0]).count();
        assert!(blue > 100 && other > 100, "ocean {blue} land {other}");
    }
}
