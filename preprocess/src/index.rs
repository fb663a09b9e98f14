//! Which rasters of a stack may hold a block or a point: an index of the
//! rasters' footprints, built once when the stack opens, so that a build
//! from thousands of tiles (a national 1″ DEM) looks at the few tiles
//! near each block instead of all of them.
//!
//! Each raster's footprint is bounded by a spherical cap ([`Cap`]): the
//! normalised mean of the unit directions of a 17 × 17 lattice of its
//! pixels ([`GeoTiff::lattice_points`]), and the largest angle from there
//! to a lattice point plus the largest angle between neighbouring lattice
//! points (a border bulging between lattice points stays inside). Global
//! rasters, rasters whose lattice does not map whole, and caps wider than
//! [`WIDE`] are candidates everywhere. With more than [`LINEAR_MAX`]
//! rasters, the caps are also filed under the level-[`BUCKET_LEVEL`]
//! blocks they meet (block caps from [`crate::plan::block_cap`]), and a
//! query looks only at the rasters filed under its block's ancestor.

use crate::geotiff::GeoTiff;
use crate::plan::{block_cap, Cap};
use planet_core::cube::{angle_between, normalize};
use planet_core::{BlockId, Face, FaceCoord};
use std::collections::HashMap;

/// Rasters up to this count are tested one by one.
pub const LINEAR_MAX: usize = 16;
/// Level of the blocks the caps are filed under (≈ 300 km across).
pub const BUCKET_LEVEL: u8 = 5;
/// Caps wider than this (radians) are candidates everywhere.
pub const WIDE: f64 = 0.5;

/// The footprint index of a stack's rasters (by their index in the stack).
#[derive(Debug, Default)]
pub struct LayerIndex {
    /// Per raster: its cap, `None` for everywhere.
    caps: Vec<Option<Cap>>,
    /// Rasters that are candidates everywhere.
    everywhere: Vec<u32>,
    /// Rasters by the level-[`BUCKET_LEVEL`] blocks their caps meet (empty
    /// with at most [`LINEAR_MAX`] rasters).
    buckets: HashMap<BlockId, Vec<u32>>,
}

/// The bounding cap of a raster's footprint, `None` where there is none
/// worth testing (see the module documentation).
pub fn footprint_cap(t: &GeoTiff) -> Option<Cap> {
    if t.is_global() {
        return None;
    }
    let pts = t.lattice_points();
    if pts.len() != 17 * 17 {
        return None;
    }
    let dirs: Vec<[f64; 3]> = pts.iter().map(|p| p.direction()).collect();
    let sum = dirs
        .iter()
        .fold([0.0; 3], |a, d| [a[0] + d[0], a[1] + d[1], a[2] + d[2]]);
    if sum.iter().all(|v| *v == 0.0) {
        return None;
    }
    let centre = normalize(sum);
    let far = dirs
        .iter()
        .map(|&d| angle_between(centre, d))
        .fold(0.0, f64::max);
    let mut step = 0f64;
    for j in 0..17 {
        for i in 0..17 {
            let d = dirs[j * 17 + i];
            if i + 1 < 17 {
                step = step.max(angle_between(d, dirs[j * 17 + i + 1]));
            }
            if j + 1 < 17 {
                step = step.max(angle_between(d, dirs[(j + 1) * 17 + i]));
            }
        }
    }
    let radius = far + step;
    (radius.is_finite() && radius < WIDE).then_some(Cap {
        centre,
        radius,
        level: 0,
    })
}

impl LayerIndex {
    /// Index these rasters (in stack order).
    pub fn new<'a>(rasters: impl IntoIterator<Item = &'a GeoTiff>) -> LayerIndex {
        let caps: Vec<Option<Cap>> = rasters.into_iter().map(footprint_cap).collect();
        let mut ix = LayerIndex {
            everywhere: (0..caps.len() as u32)
                .filter(|&i| caps[i as usize].is_none())
                .collect(),
            caps,
            buckets: HashMap::new(),
        };
        if ix.caps.len() > LINEAR_MAX {
            for (i, cap) in ix.caps.iter().enumerate() {
                let Some(cap) = cap else { continue };
                let mut stack: Vec<BlockId> = Face::ALL.iter().map(|&f| BlockId::root(f)).collect();
                while let Some(b) = stack.pop() {
                    let (c, r) = block_cap(b);
                    if angle_between(cap.centre, c) - r >= cap.radius {
                        continue;
                    }
                    if b.level == BUCKET_LEVEL {
                        ix.buckets.entry(b).or_default().push(i as u32);
                    } else {
                        stack.extend(b.children());
                    }
                }
            }
        }
        ix
    }

    /// Rasters whose footprint may meet block `b`, in stack order.
    pub fn near_block(&self, b: BlockId) -> Vec<usize> {
        let (c, r) = block_cap(b);
        self.select(
            b.level >= BUCKET_LEVEL,
            b.ancestor(BUCKET_LEVEL.min(b.level)),
            |cap| angle_between(cap.centre, c) - r < cap.radius,
        )
    }

    /// Rasters whose footprint may hold the point (lat, lon degrees), in
    /// stack order.
    pub fn near_point(&self, lat: f64, lon: f64) -> Vec<usize> {
        let fc = FaceCoord::from_lat_lon(lat.to_radians(), lon.to_radians());
        let d = fc.direction();
        let n = 1u32 << BUCKET_LEVEL;
        let cell = |s: f64| ((s * n as f64) as u32).min(n - 1);
        let b = BlockId::new(fc.face, BUCKET_LEVEL, cell(fc.s), cell(fc.t));
        self.select(b.is_some(), b.unwrap_or(BlockId::root(fc.face)), |cap| {
            angle_between(cap.centre, d) <= cap.radius
        })
    }

    fn select(&self, bucketed: bool, bucket: BlockId, meets: impl Fn(&Cap) -> bool) -> Vec<usize> {
        let keep = |i: usize| self.caps[i].as_ref().is_none_or(&meets);
        let mut v: Vec<usize> = if bucketed && self.caps.len() > LINEAR_MAX {
            let filed = self
                .buckets
                .get(&bucket)
                .map(|v| v.as_slice())
                .unwrap_or(&[]);
            filed
                .iter()
                .chain(&self.everywhere)
                .map(|&i| i as usize)
                .filter(|&i| keep(i))
                .collect()
        } else {
            (0..self.caps.len()).filter(|&i| keep(i)).collect()
        };
        v.sort_unstable();
        v.dedup();
        v
    }
}
