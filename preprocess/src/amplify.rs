//! Procedural detail beyond the best available data (thesis §6.2.2, future
//! work "procedural detail").
//!
//! `planet-build build --elevation ... --detail LAT,LON,RADIUS_KM,LEVEL`
//! deepens the tree inside the region below the finest source's level (the
//! plan: [`crate::plan::plan_by`] with the regions' levels) and adds fractal
//! detail to the interpolated heights there, so that a real planet has data
//! where a camera a few hundred metres above it needs some, and a link is
//! slower than the database is deep.
//!
//! The detail is a sum of the procedural planet's gradient-noise octaves
//! (`procedural::DetailOctave`), those finer than the sources carry: from octave
//! `octaves_at(source level)` (wavelength just under two source samples,
//! about 97 m over a 90 m SRTM inset) to `octaves_at(leaf level)` (about
//! two leaf samples). Amplitudes fall by [`ROUGH_RATIO`] per octave (the
//! procedural planet's rough octaves: amplitude ∝ wavelength^0.62), and
//! scale with the source's own local slope `s` (m/m): octave `k` has
//! amplitude `AMPLIFY_GAIN · s · λ_first · ROUGH_RATIO^(k − first)`. Steep
//! ground gets rough, flat ground (a lake, the sea, a plain) gets none and
//! stays flat, so its blocks' geometric error stays 0 and a client never
//! refines them. The detail fades out with the procedural regions' mask
//! (`procedural::region_mask`): full within half the radius, 0 at the radius, where
//! the tree is graded back to the sources' levels.
//!
//! Every term is a function of the sample's direction alone, so blocks
//! sharing an edge (at any level, on either side of a cube edge) compute the
//! same heights there:
//! - the noise octaves are functions of the direction;
//! - the slope is the magnitude of forward differences of the interpolated
//!   sources to the east and to the north, one sample of the finest source
//!   level away (an angle, whatever the leaf's level): a frame that depends
//!   on the direction, not on the face (east is taken as +y at a pole);
//! - the octaves present depend on the leaf's level, which is uniform inside
//!   a region (every leaf meeting it is split to its level).

use crate::build::EW;
use crate::error::GeoError;
use crate::geotiff::GridPoints;
use crate::plan::Cap;
use crate::procedural::{octaves_at, region_mask, DetailOctave, DETAIL_F0, ROUGH_RATIO, ROW};
use crate::source::ElevationStack;
use planet_core::cube::{angle_between, normalize};
use planet_core::{BlockId, Edge};

/// Amplitude of the first detail octave per unit slope, in wavelengths:
/// on a 30° slope (`s` = 0.58) the first octave over a 90 m inset (97 m
/// wavelength) has an amplitude of 14 m, the next ones 9, 6, 4, 2.5 m.
///
/// Calibrated on the two SRTM3 tiles of `../shared/data` (Rainier,
/// Everest): their finest octave (the pixels less a 1-2-1 binomial
/// smoothing) has an RMS of about `κ·s·d`, `d` the pixel spacing (77 and
/// 87 m), `κ` 0.12–0.20 on slopes 0.3–1.0 (where mountains are). One octave
/// finer, with amplitude ∝ wavelength^0.62 ([`ROUGH_RATIO`]), that is
/// 0.68·κ·s·d ≈ 4 m RMS at `s` = 0.5; gradient noise of amplitude `a` has an
/// RMS of about 0.25–0.3·a, so 0.25·s·97 m (12 m at `s` = 0.5) gives the
/// same 3.5–4 m.
pub const AMPLIFY_GAIN: f64 = 0.25;

/// Slopes above this (m/m, about 63°) count as this: a cliff in the source
/// or a seam between sources does not make metres-high noise.
pub const MAX_SLOPE: f64 = 2.0;

/// The detail added to raster heights inside regions.
#[derive(Debug, Clone)]
pub struct Amplifier {
    seed: u64,
    caps: Vec<Cap>,
    /// The finest source level: detail starts at its first missing octave.
    source_level: u8,
    /// Equatorial radius of the datum in metres (the noise's metres).
    radius: f64,
}

impl Amplifier {
    /// Detail for `caps` (regions deeper than `source_level`) over sources
    /// whose finest level is `source_level`, on a body of equatorial radius
    /// `radius` metres.
    pub fn new(seed: u64, caps: Vec<Cap>, source_level: u8, radius: f64) -> Amplifier {
        Amplifier {
            seed,
            caps,
            source_level,
            radius,
        }
    }

    /// The regions.
    pub fn caps(&self) -> &[Cap] {
        &self.caps
    }

    /// The finest source level.
    pub fn source_level(&self) -> u8 {
        self.source_level
    }

    /// The octaves a leaf at `level` carries beyond the sources, with their
    /// amplitudes per unit slope (none at or above the source level).
    fn octaves(&self, level: u8) -> Vec<DetailOctave> {
        let first = octaves_at(self.source_level);
        let wavelength = self.radius / (DETAIL_F0 * 2f64.powi(first as i32));
        (first..octaves_at(level))
            .map(|k| {
                DetailOctave::new(
                    self.seed ^ (0xA_0000 + k as u64),
                    DETAIL_F0 * 2f64.powi(k as i32),
                    AMPLIFY_GAIN * wavelength * ROUGH_RATIO.powi((k - first) as i32),
                )
            })
            .collect()
    }

    /// Add the detail to leaf `b`'s full `(EW+1)²` grid of heights `m`
    /// (metres: the sources, layers `near` of the stack, interpolated at the
    /// grid's points `pts`). Leaves at or above the source level, and leaves
    /// no region meets, are left as they are.
    pub fn add(
        &self,
        stack: &ElevationStack,
        b: BlockId,
        pts: &GridPoints<'_>,
        near: &[usize],
        m: &mut [f64],
    ) -> Result<(), GeoError> {
        let side = EW + 1;
        debug_assert_eq!(m.len(), side * side);
        debug_assert_eq!(pts.len(), side * side);
        let caps: Vec<Cap> = self
            .caps
            .iter()
            .filter(|c| crate::plan::block_meets_cap(b, c))
            .copied()
            .collect();
        if caps.is_empty() {
            return Ok(());
        }
        let mut octaves = self.octaves(b.level);
        if octaves.is_empty() {
            return Ok(());
        }
        let dirs: Vec<[f64; 3]> = (0..pts.len()).map(|k| pts.direction(k)).collect();
        // Forward differences to the east and north, one source sample
        // (angle `step`) away: a frame that is a function of the direction
        // alone (not of the face), so the slope, and the heights, agree
        // across cube edges and need no clamping at face edges.
        let step = std::f64::consts::FRAC_PI_2 / ((EW as u64) << self.source_level) as f64;
        let mut east = Vec::with_capacity(dirs.len());
        let mut north = Vec::with_capacity(dirs.len());
        for &p in &dirs {
            let (e, n) = east_north(p);
            east.push(normalize(add_scaled(p, e, step)));
            north.push(normalize(add_scaled(p, n, step)));
        }
        // The shifted points lie up to one step beyond the block: the layers
        // near its neighbours too (stack order kept).
        let mut layers = near.to_vec();
        for e in [Edge::Left, Edge::Top, Edge::Right, Edge::Bottom] {
            layers.extend(stack.layers_near(b.neighbour(e).0));
        }
        layers.sort_unstable();
        layers.dedup();
        let mut rd = stack.reader();
        let mut he = vec![0f64; side * side];
        let mut hn = vec![0f64; side * side];
        rd.sample_grid(&layers, &mut GridPoints::new(&east), side, side, &mut he)?;
        rd.sample_grid(&layers, &mut GridPoints::new(&north), side, side, &mut hn)?;
        for j in 0..side {
            let (mut px, mut py, mut pz) = ([0f64; ROW], [0f64; ROW], [0f64; ROW]);
            let mut slope = [0f64; ROW];
            for i in 0..ROW {
                let k = j * side + i;
                let p = dirs[k];
                [px[i], py[i], pz[i]] = p;
                let d = |q: [f64; 3]| angle_between(p, q) * self.radius;
                let ge = (he[k] - m[k]) / d(east[k]);
                let gn = (hn[k] - m[k]) / d(north[k]);
                slope[i] = (ge * ge + gn * gn).sqrt().min(MAX_SLOPE);
            }
            let mut acc = [0f32; ROW];
            for oct in octaves.iter_mut() {
                oct.add_row(&px, &py, &pz, &mut acc);
            }
            for i in 0..ROW {
                let mask = region_mask(&caps, [px[i], py[i], pz[i]]);
                m[j * side + i] += mask * slope[i] * acc[i] as f64;
            }
        }
        Ok(())
    }
}

/// Unit east and north tangents at unit direction `p` (the planet's axis
/// is +z). At a pole, where east is undefined, east is +y.
fn east_north(p: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    let (x, y) = (p[0], p[1]);
    let r = (x * x + y * y).sqrt();
    let e = if r > 1e-12 {
        [-y / r, x / r, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    // north = p × east
    let n = [
        p[1] * e[2] - p[2] * e[1],
        p[2] * e[0] - p[0] * e[2],
        p[0] * e[1] - p[1] * e[0],
    ];
    (e, n)
}

fn add_scaled(p: [f64; 3], t: [f64; 3], s: f64) -> [f64; 3] {
    [p[0] + s * t[0], p[1] + s * t[1], p[2] + s * t[2]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn octaves_start_below_the_source_and_stop_at_two_leaf_samples() {
        let a = Amplifier::new(1, Vec::new(), 11, 6_378_137.0);
        assert!(a.octaves(11).is_empty());
        assert!(a.octaves(5).is_empty());
        // Level 14: 97, 49 and 24 m over level-11 sources (9.5 m samples).
        assert_eq!(a.octaves(14).len(), 3);
        assert_eq!(a.octaves(16).len(), 5);
    }
}
