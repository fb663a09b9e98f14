//! Vertical datums: heights above a geoid (EGM96, EGM2008) converted to
//! heights above the WGS84 ellipsoid, `h = H + N(lat, lon)`, where `N` is
//! the geoid undulation (NGA, "EGM96", NASA/TP-1998-206861, §11; the
//! renderer places samples on the ellipsoid, thesis Eq. 4.2).
//!
//! - EGM96: `N` from the `egm96` crate (NGA's spherical-harmonic synthesis
//!   to degree and order 360 with the height-anomaly correction, a port of
//!   NGA's F477 program). One synthesis costs about 1 ms, so `N` is
//!   synthesised on the nodes of a regular latitude/longitude grid and
//!   interpolated bilinearly between them, exactly as PROJ does with NGA's
//!   15′ grid (`egm96_15.gtx`): with the same 15′ nodes the two agree to
//!   the grid's float32 rounding (tests/vertical.rs compares them with
//!   `cs2cs` at 1 000 points). Nodes are computed lazily in tiles of
//!   [`TILE`]² cells, the first time a build touches them, in parallel.
//!   Coarse sources use a coarser node spacing (see [`spacing_for`]).
//! - EGM2008: the `egm2008` crate's grid (3° nodes, bilinear): metre-level,
//!   not centimetre-level, accuracy; said so on stderr when used.
//! - Ellipsoid: `N = 0`.

use parking_lot::Mutex;
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::Arc;

/// The vertical datum of a source's heights.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VerticalDatum {
    /// Heights above the WGS84 ellipsoid.
    Ellipsoid,
    /// Orthometric heights above the EGM96 geoid.
    Egm96,
    /// Orthometric heights above the EGM2008 geoid.
    Egm2008,
}

impl VerticalDatum {
    /// The name used on the command line and in database descriptions.
    pub fn name(self) -> &'static str {
        match self {
            VerticalDatum::Ellipsoid => "ellipsoid",
            VerticalDatum::Egm96 => "egm96",
            VerticalDatum::Egm2008 => "egm2008",
        }
    }
}

impl std::str::FromStr for VerticalDatum {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "ellipsoid" | "wgs84" => Ok(VerticalDatum::Ellipsoid),
            "egm96" => Ok(VerticalDatum::Egm96),
            "egm2008" | "egm08" => Ok(VerticalDatum::Egm2008),
            o => Err(format!(
                "unknown vertical datum {o:?} (egm96, egm2008 or ellipsoid)"
            )),
        }
    }
}

impl std::fmt::Display for VerticalDatum {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Resident bytes of the `egm96` crate's coefficient table once used
/// (65 342 × 4 f64).
pub const EGM96_FIXED_BYTES: usize = 65_342 * 4 * 8;
/// Bytes of one thread's synthesis scratch (the `egm96` crate's buffers).
pub const EGM96_THREAD_BYTES: usize = (65_342 + 4 * 362) * 8;

/// The finest EGM96 node spacing, degrees (NGA's and PROJ's 15′ grid).
pub const FINEST_SPACING: f64 = 0.25;
/// The coarsest node spacing, degrees.
pub const COARSEST_SPACING: f64 = 2.0;
/// Cells per tile side.
pub const TILE: i64 = 8;

/// The EGM96 node spacing used for a source whose pixels are `pixel_deg`
/// degrees apart: `15′·2^k`, the largest not above 4 pixels, between 15′
/// and 2°. A 90 m SRTM tile gets 15′ (PROJ's grid); the 30′ ETOPO5 gets 2°,
/// which differs from 15′ nodes by up to 6.4 m where the geoid is steepest
/// (`geoid::tests::coarse_grid_error_bound`), against that source's own
/// 55 km cells, and costs 16 k syntheses (about 16 s of CPU) for the globe
/// instead of a million.
pub fn spacing_for(pixel_deg: f64) -> f64 {
    let mut s = FINEST_SPACING;
    while s * 2.0 <= 4.0 * pixel_deg && s * 2.0 <= COARSEST_SPACING {
        s *= 2.0;
    }
    s
}

/// A tile's key: (spacing index k, tile row, tile column).
type TileKey = (u8, i64, i64);
/// A tile's `(TILE+1)²` node undulations, metres.
type Tile = Arc<Vec<f32>>;

/// EGM96 undulations on lazily computed node tiles, shared by every layer
/// and worker of a build.
#[derive(Default)]
pub struct Egm96Grid {
    tiles: Mutex<HashMap<TileKey, Arc<Mutex<Option<Tile>>>>>,
}

/// A worker's view of an [`Egm96Grid`] (the last tile used, lock-free).
pub struct Egm96Reader<'a> {
    grid: &'a Egm96Grid,
    last: Option<(TileKey, Tile)>,
}

impl Egm96Grid {
    /// An empty grid.
    pub fn new() -> Egm96Grid {
        Egm96Grid::default()
    }

    /// A reader.
    pub fn reader(&self) -> Egm96Reader<'_> {
        Egm96Reader {
            grid: self,
            last: None,
        }
    }

    fn tile(&self, k: u8, ti: i64, tj: i64, spacing: f64) -> Arc<Vec<f32>> {
        let slot = self.tiles.lock().entry((k, ti, tj)).or_default().clone();
        let mut slot = slot.lock();
        if let Some(t) = &*slot {
            return t.clone();
        }
        let n = (TILE + 1) as usize;
        let nodes: Vec<f32> = (0..n * n)
            .into_par_iter()
            .map(|i| {
                let lat = (-90.0 + ((ti * TILE) as f64 + (i / n) as f64) * spacing).min(90.0);
                let lon = -180.0 + ((tj * TILE) as f64 + (i % n) as f64) * spacing;
                egm96::egm96_compute_altitude_offset(lat, lon) as f32
            })
            .collect();
        let t = Arc::new(nodes);
        *slot = Some(t.clone());
        t
    }
}

impl Egm96Reader<'_> {
    /// `N` (metres) at (lat, lon) degrees, bilinear between nodes `spacing`
    /// degrees apart (a power-of-two multiple of 15′).
    pub fn undulation(&mut self, lat: f64, lon: f64, spacing: f64) -> f64 {
        let k = (spacing / FINEST_SPACING).log2().round() as u8;
        let lon = (lon + 180.0).rem_euclid(360.0);
        let lat = (lat + 90.0).clamp(0.0, 180.0);
        let (fr, fc) = (lat / spacing, lon / spacing);
        let rows = (180.0 / spacing).round() as i64;
        let r = (fr.floor() as i64).min(rows - 1);
        let c = fc.floor() as i64;
        let (ti, tj) = (r.div_euclid(TILE), c.div_euclid(TILE));
        let key = (k, ti, tj);
        let tile = match &self.last {
            Some((kk, t)) if *kk == key => t.clone(),
            _ => {
                let t = self.grid.tile(k, ti, tj, spacing);
                self.last = Some((key, t.clone()));
                t
            }
        };
        let n = (TILE + 1) as usize;
        let (i, j) = ((r - ti * TILE) as usize, (c - tj * TILE) as usize);
        let (wy, wx) = (fr - r as f64, fc - c as f64);
        let at = |y: usize, x: usize| tile[y * n + x] as f64;
        let top = at(i, j) + (at(i, j + 1) - at(i, j)) * wx;
        let bot = at(i + 1, j) + (at(i + 1, j + 1) - at(i + 1, j)) * wx;
        top + (bot - top) * wy
    }
}

/// `N` (metres) of a vertical datum at (lat, lon) degrees: 0 for the
/// ellipsoid; EGM96 through `reader` with node `spacing`.
pub fn undulation(
    datum: VerticalDatum,
    reader: &mut Egm96Reader<'_>,
    lat: f64,
    lon: f64,
    spacing: f64,
) -> f64 {
    match datum {
        VerticalDatum::Ellipsoid => 0.0,
        VerticalDatum::Egm96 => reader.undulation(lat, lon, spacing),
        VerticalDatum::Egm2008 => {
            let lon = (lon + 180.0).rem_euclid(360.0) - 180.0;
            egm2008::geoid_height(lat.clamp(-90.0, 90.0) as f32, lon as f32)
                .map(f64::from)
                .unwrap_or(0.0)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spacing_follows_the_source() {
        assert_eq!(spacing_for(3.0 / 3600.0), 0.25);
        assert_eq!(spacing_for(0.5), 2.0);
        assert_eq!(spacing_for(0.1), 0.25);
        assert_eq!(spacing_for(0.2), 0.5);
        assert_eq!(spacing_for(10.0), 2.0);
    }

    #[test]
    fn nodes_are_the_synthesis_and_between_is_bilinear() {
        let g = Egm96Grid::new();
        let mut r = g.reader();
        for &(lat, lon) in &[(46.75, -121.75), (-10.0, 80.0), (27.5, 86.75)] {
            let n = r.undulation(lat, lon, 0.25);
            let want = egm96::egm96_compute_altitude_offset(lat, lon);
            assert!((n - want).abs() < 1e-4, "{lat} {lon}: {n} vs {want}");
        }
        // Midway between four nodes: their mean.
        let corners: f64 = [
            (46.75, -121.75),
            (46.75, -121.5),
            (47.0, -121.75),
            (47.0, -121.5),
        ]
        .iter()
        .map(|&(a, b)| r.undulation(a, b, 0.25))
        .sum();
        let mid = r.undulation(46.875, -121.625, 0.25);
        assert!((mid - corners / 4.0).abs() < 1e-4);
        // Longitude wraps.
        assert!((r.undulation(10.0, 190.0, 0.25) - r.undulation(10.0, -170.0, 0.25)).abs() < 1e-6);
    }

    /// The bound stated in [`spacing_for`]: EGM96 on 2° nodes against 15′
    /// nodes, at 15′ cell centres over steep geoid (New Guinea, the
    /// Himalaya): within 7 m (measured 6.4 m; 1° nodes: 4.3 m, 4° nodes:
    /// 16.5 m, over four such regions).
    #[test]
    fn coarse_grid_error_bound() {
        let g = Egm96Grid::new();
        let mut r = g.reader();
        let mut worst: f64 = 0.0;
        for &(la0, lo0) in &[(-6.0, 140.0), (28.0, 86.0)] {
            for i in 0..8 {
                for j in 0..8 {
                    let (la, lo) = (la0 + 0.25 * i as f64 + 0.125, lo0 + 0.25 * j as f64 + 0.125);
                    worst =
                        worst.max((r.undulation(la, lo, 2.0) - r.undulation(la, lo, 0.25)).abs());
                }
            }
        }
        assert!(worst < 7.0 && worst > 0.5, "2° grid off by {worst} m");
    }
}
