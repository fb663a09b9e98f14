//! A deterministic procedural planet, the project's own embedded default
//! database (instead of real data), built with the same Alg. 5.2 pipeline
//! (thesis §5.3) on a uniform tree.
//!
//! Elevation is a function of the unit direction (so it is seamless over cube
//! edges and poles), evaluated in f64: domain-warped fBm continents, ridged
//! mountain ranges, and fBm detail down to about two samples at the leaf
//! level, from about −8000 m to +8000 m. For speed, everything but the three
//! finest detail octaves is evaluated on a lattice of every 8th sample of a
//! leaf and interpolated bilinearly; a sample on a block edge then depends
//! only on lattice points on that edge, whose directions are bit-identical
//! from both blocks (thesis-notes §9.4), so shared edge samples agree exactly.
//! Colour is a function of altitude, latitude and a moisture field: ocean
//! blues, beaches, greens, deserts, rock, snow caps and polar ice.

use crate::build::{build, BuildOptions, BuildStats, GridSource, CW, EW};
use crate::error::BuildError;
use crate::plan::Plan;
use planet_core::cube::{normalize, plane_from_angle, sample_coord};
use planet_core::lod::{self, Rgb};
use planet_core::{BlockId, Datum};
use std::path::Path;

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
    }
}

/// Build a procedural planet database at `out`.
pub fn build_procedural(opts: &ProceduralOptions, out: &Path) -> Result<BuildStats, BuildError> {
    if opts.levels > 20 {
        return Err(BuildError::Options(format!(
            "--levels {} is too deep (at most 20)",
            opts.levels
        )));
    }
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
    /// Number of detail octaves.
    detail_octaves: u32,
}

const LATTICE: usize = 8;
const HIGH_OCTAVES: u32 = 3;
const DETAIL_F0: f64 = 4.0;

impl Procedural {
    /// A generator for these options.
    pub fn new(opts: &ProceduralOptions) -> Procedural {
        // Sample spacing at the leaves, in radians; finest octave ≈ 2 samples.
        let d = std::f64::consts::FRAC_PI_2 / (EW as f64 * 2f64.powi(opts.levels as i32));
        let fmax = 1.0 / (2.0 * d);
        let detail_octaves =
            ((fmax / DETAIL_F0).log2().floor() as i64 + 1).max(HIGH_OCTAVES as i64 + 1) as u32;
        Procedural {
            seed: opts.seed,
            levels: opts.levels,
            datum: opts.datum,
            colour: opts.colour,
            detail_octaves,
        }
    }

    /// The uniform tree plan.
    pub fn plan(&self) -> Plan {
        Plan::Uniform {
            levels: self.levels,
            colour_level: self.colour.then_some(self.levels),
        }
    }

    /// Low-frequency fields at a direction: (elevation m, roughness, moisture).
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
        let moisture = fbm(s ^ 0x77, scale(p, 2.2), 3);
        [h, 0.4 + 2.0 * mountains, moisture]
    }

    /// The per-sample detail octaves: `(seed, frequency, amplitude)` of each,
    /// computed as the original loop did (bit-identical factors).
    fn high_octaves(&self) -> Vec<(u64, f64, f64)> {
        let k0 = self.detail_octaves.saturating_sub(HIGH_OCTAVES);
        let mut f = DETAIL_F0 * 2f64.powi(k0 as i32);
        let mut a = 420.0 * 0.5f64.powi(k0 as i32);
        let mut out = Vec::with_capacity(HIGH_OCTAVES as usize);
        for k in k0..self.detail_octaves {
            out.push((self.seed ^ (0x100 + k as u64), f, a));
            f *= 2.0;
            a *= 0.5;
        }
        out
    }

    fn lattice(&self, b: BlockId, us: &[f64], vs: &[f64]) -> Vec<[f64; 3]> {
        let n = EW / LATTICE + 1;
        let mut out = Vec::with_capacity(n * n);
        for j in 0..n {
            for i in 0..n {
                let p = normalize(b.face.cube_point(us[i * LATTICE], vs[j * LATTICE]));
                out.push(self.low(p));
            }
        }
        out
    }

    /// Elevation (metres, before quantisation) of a leaf's samples.
    ///
    /// Per sample: the bilinear lattice fields and the [`HIGH_OCTAVES`] detail
    /// octaves, each through a [`CachedNoise`] (consecutive samples of a row
    /// share cells). The interpolation weights are per row and per column.
    fn leaf_elevation(&self, b: BlockId) -> (Vec<i16>, Vec<[f64; 3]>) {
        let (us, vs) = plane_axes(b);
        let lat = self.lattice(b, &us, &vs);
        let side = EW + 1;
        let n = EW / LATTICE + 1;
        let octaves = self.high_octaves();
        let mut caches: Vec<CachedNoise> = octaves.iter().map(|o| CachedNoise::new(o.0)).collect();
        let cols: Vec<(usize, usize, f64)> = (0..side)
            .map(|i| {
                let li = i / LATTICE;
                (
                    li,
                    (li + 1).min(n - 1),
                    (i % LATTICE) as f64 / LATTICE as f64,
                )
            })
            .collect();
        let mut out = vec![0i16; side * side];
        for j in 0..side {
            let (lj, fj) = (j / LATTICE, (j % LATTICE) as f64 / LATTICE as f64);
            let lj1 = (lj + 1).min(n - 1);
            let (r0, r1) = (&lat[lj * n..lj * n + n], &lat[lj1 * n..lj1 * n + n]);
            let row = &mut out[j * side..(j + 1) * side];
            for (i, o) in row.iter_mut().enumerate() {
                let (li, li1, fi) = cols[i];
                let interp = |c: usize| {
                    let a = r0[li][c] + (r0[li1][c] - r0[li][c]) * fi;
                    let d = r1[li][c] + (r1[li1][c] - r1[li][c]) * fi;
                    a + (d - a) * fj
                };
                let p = normalize(b.face.cube_point(us[i], vs[j]));
                let mut hi = 0.0;
                for (cache, &(_, f, a)) in caches.iter_mut().zip(&octaves) {
                    hi += a * cache.eval(scale(p, f));
                }
                let h = interp(0) + interp(1) * hi;
                *o = round_half_away(h).clamp(-8000.0, 8000.0) as i16;
            }
        }
        (out, lat)
    }

    /// The exact re-projected full elevation grid `(W+1)²` (stored units =
    /// metres) of any block: a leaf's generated grid, or an inner block's
    /// samples gathered from its descendants' leaves (what the database holds).
    pub fn elevation_grid(&self, b: BlockId) -> Vec<i16> {
        if b.level >= self.levels {
            return self.leaf_elevation(b).0;
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
        if b.level >= self.levels {
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

    /// The colour grid of a leaf from its elevation grid. The per-texel
    /// position arithmetic is done once per column and per row, the lattice
    /// fields' horizontal interpolation once per lattice row band; the
    /// arithmetic of each value is exactly the per-texel original's.
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
        let mut out = Vec::with_capacity(CW * CW);
        let ratio = EW as f64 / CW as f64;
        let l = b.level as i32;
        let slope_scale = 2.0f64.powi(-l) * 1.0e5;
        // Texel centre position in grid cells and lattice cells, per column
        // (and the same per row).
        struct Axis {
            x0: usize,
            fx: f64,
            mi: usize,
            mfx: f64,
        }
        let axis = |k: usize| {
            let g = (k as f64 + 0.5) * ratio;
            let m = g / LATTICE as f64;
            let mi = (m.floor() as usize).min(n - 2);
            Axis {
                x0: g.floor() as usize,
                fx: g.fract(),
                mi,
                mfx: m - mi as f64,
            }
        };
        let cols: Vec<Axis> = (0..CW).map(axis).collect();
        // Per lattice row band `mj`: for each column, the horizontally
        // interpolated moisture and latitude on lattice rows mj and mj + 1.
        let mut band = usize::MAX;
        let mut hm = vec![[0f64; 4]; CW];
        for j in 0..CW {
            let ra = axis(j);
            let (y0, fy, mj, mfy) = (ra.x0, ra.fx, ra.mi, ra.mfx);
            if mj != band {
                band = mj;
                for (c, h) in cols.iter().zip(hm.iter_mut()) {
                    let (mi, mfx) = (c.mi, c.mfx);
                    let row = |g: &[f64], r: usize| {
                        g[r * n + mi] + (g[r * n + mi + 1] - g[r * n + mi]) * mfx
                    };
                    *h = [
                        row(&moist, mj),
                        row(&moist, mj + 1),
                        row(&lats, mj),
                        row(&lats, mj + 1),
                    ];
                }
            }
            let e0 = &elev[y0 * side..(y0 + 1) * side];
            let e1 = &elev[(y0 + 1) * side..(y0 + 2) * side];
            for (c, h4) in cols.iter().zip(&hm) {
                let (x0, fx) = (c.x0, c.fx);
                let (a00, a10) = (e0[x0] as f64, e0[x0 + 1] as f64);
                let (a01, a11) = (e1[x0] as f64, e1[x0 + 1] as f64);
                let top = a00 + (a10 - a00) * fx;
                let bot = a01 + (a11 - a01) * fx;
                let h = top + (bot - top) * fy;
                let m = h4[0] + (h4[1] - h4[0]) * mfy;
                let lat = h4[2] + (h4[3] - h4[2]) * mfy;
                // Slope (for rock on steep terrain), from the elevation grid.
                let slope = ((a10 - a00).abs() + (a01 - a00).abs()) / slope_scale;
                out.push(palette(h, lat, m, slope));
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

fn lerp3(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    let t = t.clamp(0.0, 1.0);
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

/// [`lerp3`] that skips the arithmetic where `t ≤ 0` (the result is then `a`
/// exactly: `a + (b − a)·0 = a` for finite `a`), which is most texels for
/// most of the palette's layers.
#[inline(always)]
fn blend(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    if t > 0.0 {
        lerp3(a, b, t)
    } else {
        a
    }
}

/// `smoothstep(a, b, x)` where `x ≤ a` is 0 without the division (exactly
/// what the clamp makes of it).
#[inline(always)]
fn step_from(a: f64, b: f64, x: f64) -> f64 {
    if x <= a {
        0.0
    } else {
        smoothstep(a, b, x)
    }
}

/// Colour by altitude (m), |latitude| (degrees), moisture and slope.
fn palette(h: f64, lat: f64, moisture: f64, slope: f64) -> Rgb {
    let c = if h < 0.0 {
        lerp3([46.0, 110.0, 170.0], [8.0, 24.0, 72.0], -h / 6000.0)
    } else if h < 25.0 {
        [214.0, 200.0, 150.0]
    } else {
        let arid = step_from(0.0, 0.3, 1.0 - (lat - 24.0).abs() / 14.0 - moisture * 1.5);
        let green = lerp3([52.0, 110.0, 44.0], [96.0, 128.0, 64.0], h / 2000.0);
        let mut c = blend(green, [204.0, 172.0, 112.0], arid);
        c = blend(c, [120.0, 122.0, 96.0], step_from(50.0, 66.0, lat)); // tundra
        c = blend(
            c,
            [118.0, 106.0, 96.0],
            step_from(2200.0, 3200.0, h).max(slope.min(1.0) * 0.6),
        );
        let snowline = 5200.0 - 4200.0 * (lat / 75.0).min(1.0);
        blend(
            c,
            [244.0, 245.0, 250.0],
            step_from(snowline, snowline + 400.0, h),
        )
    };
    let ice = step_from(72.0, 78.0, lat + moisture * 4.0);
    let c = blend(c, [236.0, 242.0, 248.0], ice);
    [c[0] as u8, c[1] as u8, c[2] as u8]
}

impl GridSource for Procedural {
    fn elevation_leaf(&self, b: BlockId, out: &mut [i16]) -> Result<(), BuildError> {
        let (g, _) = self.leaf_elevation(b);
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
        format!(
            "procedural planet: seed {}, {} levels, {:?}",
            self.seed, self.levels, self.datum
        )
    }
}

/// `f64::round` (half away from zero) without the libm call, for the values
/// the generator produces; identical to `round` for |x| < 2^52, and beyond
/// that both clamp to the same stored value.
#[inline]
fn round_half_away(x: f64) -> f64 {
    if x.abs() >= 4_503_599_627_370_496.0 || x.is_nan() {
        return x.round();
    }
    let t = x as i64 as f64; // truncation, exact here
    let d = x - t; // exact (Sterbenz)
    if d >= 0.5 {
        t + 1.0
    } else if d <= -0.5 {
        t - 1.0
    } else {
        t
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

/// [`noise`] of one seed that keeps the corner hashes of the last cell it
/// was evaluated in: neighbouring samples mostly fall in the same cell.
/// Bit-identical to [`noise`].
#[derive(Debug, Clone)]
struct CachedNoise {
    seed: u64,
    cell: Option<[i64; 3]>,
    codes: [u8; 8],
}

impl CachedNoise {
    fn new(seed: u64) -> CachedNoise {
        CachedNoise {
            seed,
            cell: None,
            codes: [0; 8],
        }
    }

    #[inline]
    fn eval(&mut self, p: [f64; 3]) -> f64 {
        let (xf, yf, zf) = (ffloor(p[0]), ffloor(p[1]), ffloor(p[2]));
        let cell = [xf as i64, yf as i64, zf as i64];
        if self.cell != Some(cell) {
            self.codes = corner_codes(self.seed, cell[0], cell[1], cell[2]);
            self.cell = Some(cell);
        }
        noise_in_cell(&self.codes, p[0] - xf, p[1] - yf, p[2] - zf)
    }
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
