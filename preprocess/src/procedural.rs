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

    /// The per-sample detail octaves.
    fn high(&self, p: [f64; 3]) -> f64 {
        let k0 = self.detail_octaves.saturating_sub(HIGH_OCTAVES);
        let mut f = DETAIL_F0 * 2f64.powi(k0 as i32);
        let mut a = 420.0 * 0.5f64.powi(k0 as i32);
        let mut h = 0.0;
        for k in k0..self.detail_octaves {
            h += a * noise(self.seed ^ (0x100 + k as u64), scale(p, f));
            f *= 2.0;
            a *= 0.5;
        }
        h
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
    fn leaf_elevation(&self, b: BlockId) -> (Vec<i16>, Vec<[f64; 3]>) {
        let (us, vs) = plane_axes(b);
        let lat = self.lattice(b, &us, &vs);
        let side = EW + 1;
        let n = EW / LATTICE + 1;
        let mut out = vec![0i16; side * side];
        for j in 0..side {
            let (lj, fj) = (j / LATTICE, (j % LATTICE) as f64 / LATTICE as f64);
            let lj1 = (lj + 1).min(n - 1);
            for i in 0..side {
                let (li, fi) = (i / LATTICE, (i % LATTICE) as f64 / LATTICE as f64);
                let li1 = (li + 1).min(n - 1);
                let interp = |c: usize| {
                    let a = lat[lj * n + li][c] + (lat[lj * n + li1][c] - lat[lj * n + li][c]) * fi;
                    let d =
                        lat[lj1 * n + li][c] + (lat[lj1 * n + li1][c] - lat[lj1 * n + li][c]) * fi;
                    a + (d - a) * fj
                };
                let p = normalize(b.face.cube_point(us[i], vs[j]));
                let h = interp(0) + interp(1) * self.high(p);
                out[j * side + i] = h.round().clamp(-8000.0, 8000.0) as i16;
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
        for j in 0..CW {
            let gy = (j as f64 + 0.5) * ratio;
            let (y0, fy) = (gy.floor() as usize, gy.fract());
            for i in 0..CW {
                let gx = (i as f64 + 0.5) * ratio;
                let (x0, fx) = (gx.floor() as usize, gx.fract());
                let at = |x: usize, y: usize| elev[y * side + x] as f64;
                let top = at(x0, y0) + (at(x0 + 1, y0) - at(x0, y0)) * fx;
                let bot = at(x0, y0 + 1) + (at(x0 + 1, y0 + 1) - at(x0, y0 + 1)) * fx;
                let h = top + (bot - top) * fy;
                let mx = gx / LATTICE as f64;
                let my = gy / LATTICE as f64;
                let (mi, mj) = (
                    (mx.floor() as usize).min(n - 2),
                    (my.floor() as usize).min(n - 2),
                );
                let (mfx, mfy) = (mx - mi as f64, my - mj as f64);
                let bil = |g: &[f64]| {
                    let a = g[mj * n + mi] + (g[mj * n + mi + 1] - g[mj * n + mi]) * mfx;
                    let c = g[(mj + 1) * n + mi]
                        + (g[(mj + 1) * n + mi + 1] - g[(mj + 1) * n + mi]) * mfx;
                    a + (c - a) * mfy
                };
                let m = bil(&moist);
                let lat = bil(&lats);
                // Slope (for rock on steep terrain), from the elevation grid.
                let slope = ((at(x0 + 1, y0) - at(x0, y0)).abs()
                    + (at(x0, y0 + 1) - at(x0, y0)).abs())
                    / (2.0f64.powi(-l) * 1.0e5);
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

/// Colour by altitude (m), |latitude| (degrees), moisture and slope.
fn palette(h: f64, lat: f64, moisture: f64, slope: f64) -> Rgb {
    let c = if h < 0.0 {
        lerp3([46.0, 110.0, 170.0], [8.0, 24.0, 72.0], -h / 6000.0)
    } else if h < 25.0 {
        [214.0, 200.0, 150.0]
    } else {
        let arid = smoothstep(0.0, 0.3, 1.0 - (lat - 24.0).abs() / 14.0 - moisture * 1.5);
        let green = lerp3([52.0, 110.0, 44.0], [96.0, 128.0, 64.0], h / 2000.0);
        let mut c = lerp3(green, [204.0, 172.0, 112.0], arid);
        c = lerp3(c, [120.0, 122.0, 96.0], smoothstep(50.0, 66.0, lat)); // tundra
        c = lerp3(
            c,
            [118.0, 106.0, 96.0],
            smoothstep(2200.0, 3200.0, h).max(slope.min(1.0) * 0.6),
        );
        let snowline = 5200.0 - 4200.0 * (lat / 75.0).min(1.0);
        lerp3(
            c,
            [244.0, 245.0, 250.0],
            smoothstep(snowline, snowline + 400.0, h),
        )
    };
    let ice = smoothstep(72.0, 78.0, lat + moisture * 4.0);
    let c = lerp3(c, [236.0, 242.0, 248.0], ice);
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

#[inline]
fn grad(h: u64, x: f64, y: f64, z: f64) -> f64 {
    match h & 15 {
        0 | 12 => x + y,
        1 | 13 => -x + y,
        2 => x - y,
        3 => -x - y,
        4 => x + z,
        5 => -x + z,
        6 => x - z,
        7 => -x - z,
        8 => y + z,
        9 | 14 => -y + z,
        10 => y - z,
        _ => -y - z,
    }
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

/// 3D gradient noise in about [-1, 1].
pub fn noise(seed: u64, p: [f64; 3]) -> f64 {
    let (xf, yf, zf) = (ffloor(p[0]), ffloor(p[1]), ffloor(p[2]));
    let (x, y, z) = (p[0] - xf, p[1] - yf, p[2] - zf);
    let (xi, yi, zi) = (xf as i64, yf as i64, zf as i64);
    let (u, v, w) = (fade(x), fade(y), fade(z));
    let g = |dx: i64, dy: i64, dz: i64| {
        grad(
            hash(seed, xi + dx, yi + dy, zi + dz),
            x - dx as f64,
            y - dy as f64,
            z - dz as f64,
        )
    };
    let l = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let x00 = l(g(0, 0, 0), g(1, 0, 0), u);
    let x10 = l(g(0, 1, 0), g(1, 1, 0), u);
    let x01 = l(g(0, 0, 1), g(1, 0, 1), u);
    let x11 = l(g(0, 1, 1), g(1, 1, 1), u);
    l(l(x00, x10, v), l(x01, x11, v), w) * 0.9
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
