//! Tree shape: which blocks are split (thesis §3.2, §4.3.3, §5.3).
//!
//! The thesis builds complete, uniform trees. A planet with high-resolution
//! insets over a coarse global base needs a depth that varies by region: a
//! block is split while its sample spacing is coarser than the finest source
//! covering it (capped by `max_level`). The tree is then *graded* so that
//! neighbouring leaves, across cube edges too, differ by at most
//! [`MAX_GRADE`] levels, within the `max_level_difference(64) = 5` the edge
//! strips can stitch (Thesis §4.3.3, docs/REFERENCES.md), with a margin of 1.
//!
//! The colour tree is the elevation tree truncated at the colour source's
//! level (linked trees, thesis §4.4.1): a truncation at a uniform level keeps
//! the grading.
//!
//! Procedural planets with detail regions ([`plan_for_caps`]) use the same
//! split-then-grade scheme: a uniform base, deepened inside spherical caps.
//! Their colour tree follows the elevation tree down to the caps' levels
//! where the caps deepened it (the blocks split before grading), and stops
//! at the base level elsewhere, including the graded band around the caps.
//! Every colour-split block is an elevation-split block, so a colour block
//! exists only where the elevation block of the same id does (§4.4.1); the
//! colour tree needs no grading (only elevation leaves stitch edges).

use crate::source::ElevationStack;
use planet_core::cube::{angle_between, normalize, plane_from_angle};
use planet_core::{BlockId, Edge, Face};
use std::collections::HashSet;

/// Largest level difference between neighbouring leaves this builder makes.
pub const MAX_GRADE: u8 = 4;

/// Which blocks of the six face quadtrees are split.
#[derive(Debug, Clone)]
pub enum Plan {
    /// Every leaf at `levels`.
    Uniform {
        /// Leaf level of the elevation tree.
        levels: u8,
        /// Leaf level of the colour tree, `None` for no colour.
        colour_level: Option<u8>,
    },
    /// An explicit set of split blocks.
    Explicit {
        /// Split elevation blocks.
        split: HashSet<BlockId>,
        /// Deepest leaf level.
        max_level: u8,
        /// Colour truncation level, `None` for no colour.
        colour_level: Option<u8>,
        /// Colour blocks split although at or below `colour_level` (detail
        /// regions): a subset of `split`, closed under parents down to
        /// `colour_level` (every one's parent is colour-split too).
        colour_deep: HashSet<BlockId>,
    },
}

impl Plan {
    /// Whether the elevation block is split (has children).
    pub fn elevation_split(&self, b: BlockId) -> bool {
        match self {
            Plan::Uniform { levels, .. } => b.level < *levels,
            Plan::Explicit { split, .. } => split.contains(&b),
        }
    }

    /// Whether the colour block (which must exist) is split: above the
    /// colour truncation level where the elevation block is, and in the
    /// deep colour set. Never where the elevation block is not (§4.4.1).
    pub fn colour_split(&self, b: BlockId) -> bool {
        match self.colour_level() {
            Some(c) => {
                self.elevation_split(b)
                    && (b.level < c
                        || matches!(self, Plan::Explicit { colour_deep, .. } if colour_deep.contains(&b)))
            }
            None => false,
        }
    }

    /// The colour truncation level.
    pub fn colour_level(&self) -> Option<u8> {
        match self {
            Plan::Uniform { colour_level, .. } | Plan::Explicit { colour_level, .. } => {
                *colour_level
            }
        }
    }

    /// The deepest elevation leaf level.
    pub fn max_level(&self) -> u8 {
        match self {
            Plan::Uniform { levels, .. } => *levels,
            Plan::Explicit { max_level, .. } => *max_level,
        }
    }

    /// The deepest colour level actually present.
    pub fn colour_max_level(&self) -> u8 {
        let truncated = self.colour_level().unwrap_or(0).min(self.max_level());
        match self {
            Plan::Explicit { colour_deep, .. } if self.colour_level().is_some() => colour_deep
                .iter()
                .map(|b| b.level + 1)
                .fold(truncated, u8::max),
            _ => truncated,
        }
    }

    /// Number of (elevation, colour) blocks in the trees.
    pub fn block_counts(&self) -> (u64, u64) {
        match self {
            Plan::Uniform {
                levels,
                colour_level,
            } => {
                let count = |l: u8| 6 * ((1u64 << (2 * (l as u32 + 1))) - 1) / 3;
                (
                    count(*levels),
                    colour_level.map_or(0, |c| count(c.min(*levels))),
                )
            }
            Plan::Explicit {
                split, colour_deep, ..
            } => {
                let e = 6 + 4 * split.len() as u64;
                let c = match self.colour_level() {
                    Some(cl) => {
                        let above = split.iter().filter(|b| b.level < cl).count();
                        let deep = colour_deep.iter().filter(|b| b.level >= cl).count();
                        6 + 4 * (above + deep) as u64
                    }
                    None => 0,
                };
                (e, c)
            }
        }
    }
}

/// The leaf (unsplit block) of `split` that contains block `b`'s area, or
/// `None` if `b` itself is split (its area holds several leaves).
pub fn leaf_containing(split: &HashSet<BlockId>, b: BlockId) -> Option<BlockId> {
    for l in 0..=b.level {
        let a = b.ancestor(l);
        if !split.contains(&a) {
            return Some(a);
        }
    }
    None
}

/// Plan the trees for a raster stack: split while a covering source is finer,
/// capped by `max_level`, then grade to [`MAX_GRADE`].
pub fn plan_for_sources(stack: &ElevationStack, colour_level: Option<u8>, max_level: u8) -> Plan {
    plan_by(|b| stack.level_needed(b).min(max_level), colour_level)
}

/// Split every block above the level `need(block)` asks for, then grade.
pub fn plan_by(need: impl Fn(BlockId) -> u8, colour_level: Option<u8>) -> Plan {
    let mut split = HashSet::new();
    let mut stackv: Vec<BlockId> = Face::ALL.iter().map(|&f| BlockId::root(f)).collect();
    while let Some(b) = stackv.pop() {
        let need = need(b);
        if b.level < need {
            split.insert(b);
            stackv.extend(b.children());
        }
    }
    grade(&mut split);
    let deepest = split.iter().map(|b| b.level + 1).max().unwrap_or(0);
    Plan::Explicit {
        split,
        max_level: deepest,
        colour_level,
        colour_deep: HashSet::new(),
    }
}

/// A region of the sphere to deepen: a spherical cap around a unit
/// direction, split down to `level`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cap {
    /// Unit direction of the cap's centre.
    pub centre: [f64; 3],
    /// Angular radius in radians.
    pub radius: f64,
    /// Leaf level inside the cap.
    pub level: u8,
}

/// The unit direction of a block's centre and its angular radius: the
/// largest angle from the centre to a corner. A block is a convex spherical
/// quadrilateral (its edges are great-circle arcs: constant gnomonic `u` or
/// `v`), so every point of it lies within that angle of the centre. Corners
/// come from `planet_core::cube`, so cube edges, corners, poles and the
/// antimeridian need no special case.
pub fn block_cap(b: BlockId) -> ([f64; 3], f64) {
    let (s0, t0, s1, t1) = b.extent();
    let dir =
        |s: f64, t: f64| normalize(b.face.cube_point(plane_from_angle(s), plane_from_angle(t)));
    let centre = dir(0.5 * (s0 + s1), 0.5 * (t0 + t1));
    let radius = [(s0, t0), (s1, t0), (s0, t1), (s1, t1)]
        .iter()
        .map(|&(s, t)| angle_between(centre, dir(s, t)))
        .fold(0.0, f64::max);
    (centre, radius)
}

/// Whether block `b`'s footprint may meet the cap (conservative: the
/// block's bounding cap meets it).
pub fn block_meets_cap(b: BlockId, cap: &Cap) -> bool {
    let (c, r) = block_cap(b);
    angle_between(cap.centre, c) - r < cap.radius
}

/// Plan a procedural planet (thesis §4.3.3, §5.3): every block split down to
/// `levels`; blocks whose footprint meets a cap split further, down to the
/// cap's level; then graded to [`MAX_GRADE`]. The colour tree is truncated
/// at `colour_level` (at most `levels`) except where the caps split blocks:
/// there colour follows elevation down to the cap's level
/// ([`Plan::Explicit::colour_deep`] holds the cap-split blocks at or below
/// `colour_level` whose parents are colour-split; the grading's extra
/// splits are elevation only). Without a cap deeper than `levels` this is
/// the [`Plan::Uniform`] plan.
pub fn plan_for_caps(levels: u8, caps: &[Cap], colour_level: Option<u8>) -> Plan {
    if caps.iter().all(|c| c.level <= levels) {
        return Plan::Uniform {
            levels,
            colour_level,
        };
    }
    let cl = colour_level.unwrap_or(0);
    let mut split = HashSet::new();
    let mut colour_deep = HashSet::new();
    // (block, whether its colour block exists).
    let mut stackv: Vec<(BlockId, bool)> = Face::ALL
        .iter()
        .map(|&f| (BlockId::root(f), colour_level.is_some()))
        .collect();
    while let Some((b, colour)) = stackv.pop() {
        let by_cap = caps
            .iter()
            .any(|c| b.level < c.level && block_meets_cap(b, c));
        if b.level < levels || by_cap {
            split.insert(b);
            let colour_split = colour && (b.level < cl || by_cap);
            if colour_split && b.level >= cl {
                colour_deep.insert(b);
            }
            stackv.extend(b.children().map(|c| (c, colour_split)));
        }
    }
    grade(&mut split);
    let deepest = split.iter().map(|b| b.level + 1).max().unwrap_or(0);
    Plan::Explicit {
        split,
        max_level: deepest,
        colour_level,
        colour_deep,
    }
}

/// Split leaves until no two neighbouring leaves differ by more than
/// [`MAX_GRADE`] levels (classic restricted-quadtree balancing).
pub fn grade(split: &mut HashSet<BlockId>) {
    let mut work: Vec<BlockId> = split.iter().flat_map(|b| b.children()).collect();
    work.retain(|b| !split.contains(b));
    while let Some(leaf) = work.pop() {
        if split.contains(&leaf) {
            continue;
        }
        for e in Edge::ALL {
            let (n, _) = leaf.neighbour(e);
            if let Some(coarse) = leaf_containing(split, n) {
                if coarse.level + MAX_GRADE < leaf.level {
                    // Split the coarse leaf (and its ancestors are split already).
                    split.insert(coarse);
                    for c in coarse.children() {
                        work.push(c);
                    }
                    work.push(leaf);
                }
            }
        }
    }
}

/// All leaves of a plan's elevation tree (explicit plans; for tests).
pub fn leaves(split: &HashSet<BlockId>) -> Vec<BlockId> {
    let mut out = Vec::new();
    let mut st: Vec<BlockId> = Face::ALL.iter().map(|&f| BlockId::root(f)).collect();
    while let Some(b) = st.pop() {
        if split.contains(&b) {
            st.extend(b.children());
        } else {
            out.push(b);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grading_limits_neighbour_difference() {
        // One deep block near a cube corner forces grading across faces.
        let mut split = HashSet::new();
        let deep = BlockId::new(Face::NORTH, 12, 0, 0).unwrap();
        for l in 0..12 {
            split.insert(deep.ancestor(l));
        }
        grade(&mut split);
        let ls = leaves(&split);
        assert!(ls.iter().any(|b| b.level == 12));
        let mut crossed = false;
        for leaf in &ls {
            for e in Edge::ALL {
                let (n, _) = leaf.neighbour(e);
                if let Some(c) = leaf_containing(&split, n) {
                    assert!(leaf.level <= c.level + MAX_GRADE, "{leaf:?} next to {c:?}");
                    if c.face != leaf.face && leaf.level >= 8 {
                        crossed = true;
                    }
                }
            }
        }
        assert!(crossed, "grading reached the neighbouring faces");
    }

    /// The leaves of a plan's colour tree.
    fn colour_leaves(plan: &Plan) -> Vec<BlockId> {
        let mut out = Vec::new();
        let mut st: Vec<BlockId> = Face::ALL.iter().map(|&f| BlockId::root(f)).collect();
        while let Some(b) = st.pop() {
            if plan.colour_split(b) {
                st.extend(b.children());
            } else {
                out.push(b);
            }
        }
        out
    }

    fn dir(lat: f64, lon: f64) -> [f64; 3] {
        planet_core::cube::direction_from_lat_lon(lat.to_radians(), lon.to_radians())
    }

    #[test]
    fn caps_deepen_only_their_region_and_are_graded() {
        // A cap on the north pole (a face centre) and one on a cube corner
        // at the antimeridian (three faces meet there).
        let corner_lat = (1.0f64 / 2f64.sqrt()).atan().to_degrees();
        let caps = [
            Cap {
                centre: dir(90.0, 0.0),
                radius: 2.0e-3,
                level: 9,
            },
            Cap {
                centre: dir(corner_lat, 135.0),
                radius: 2.0e-3,
                level: 9,
            },
            // On the antimeridian and on the edge of faces 0 and 5.
            Cap {
                centre: dir(45.0, 180.0),
                radius: 2.0e-3,
                level: 9,
            },
        ];
        let plan = plan_for_caps(3, &caps, Some(3));
        let Plan::Explicit {
            split, max_level, ..
        } = &plan
        else {
            panic!("expected an explicit plan");
        };
        assert_eq!(*max_level, 9);
        let ls = leaves(split);
        // Every leaf meeting a cap is at level 9; every level-9 leaf is the
        // child of a block meeting one.
        for leaf in &ls {
            if caps.iter().any(|c| block_meets_cap(*leaf, c)) {
                assert_eq!(leaf.level, 9, "{leaf:?}");
            }
            if leaf.level == 9 {
                let p = leaf.ancestor(8);
                assert!(caps.iter().any(|c| block_meets_cap(p, c)), "{leaf:?}");
            }
            assert!(leaf.level >= 3);
        }
        // The corner cap reached all three faces around the corner.
        let faces: HashSet<Face> = ls
            .iter()
            .filter(|b| b.level == 9 && block_meets_cap(**b, &caps[1]))
            .map(|b| b.face)
            .collect();
        assert_eq!(faces.len(), 3, "{faces:?}");
        let faces: HashSet<Face> = ls
            .iter()
            .filter(|b| b.level == 9 && block_meets_cap(**b, &caps[2]))
            .map(|b| b.face)
            .collect();
        assert_eq!(faces.len(), 2, "{faces:?}");
        // Graded.
        for leaf in &ls {
            for e in Edge::ALL {
                let (n, _) = leaf.neighbour(e);
                if let Some(c) = leaf_containing(split, n) {
                    assert!(leaf.level <= c.level + MAX_GRADE);
                }
            }
        }
        // Colour follows the caps down to level 9 and stops at the base
        // level 3 elsewhere, inside the elevation tree (§4.4.1).
        assert!(plan.colour_split(
            BlockId::new(Face::NORTH, 2, 0, 0).unwrap_or(BlockId::root(Face::NORTH))
        ));
        assert_eq!(plan.colour_max_level(), 9);
        let colour_leaves = colour_leaves(&plan);
        let (_, colour_blocks) = plan.block_counts();
        let mut colour_count = 0u64;
        let mut st: Vec<BlockId> = Face::ALL.iter().map(|&f| BlockId::root(f)).collect();
        while let Some(b) = st.pop() {
            colour_count += 1;
            if plan.colour_split(b) {
                assert!(
                    split.contains(&b),
                    "colour {b:?} split over an elevation leaf"
                );
                st.extend(b.children());
            }
        }
        assert_eq!(colour_blocks, colour_count);
        assert!(colour_blocks > 6 * 85);
        for leaf in &colour_leaves {
            if caps.iter().any(|c| block_meets_cap(*leaf, c)) {
                // Inside a cap: as deep as the elevation.
                assert_eq!(leaf.level, 9, "{leaf:?}");
                assert!(!split.contains(leaf));
            } else {
                // Outside: the base level, or the child of a cap's block.
                assert!(
                    leaf.level == 3
                        || caps
                            .iter()
                            .any(|c| block_meets_cap(leaf.ancestor(leaf.level - 1), c)),
                    "{leaf:?}"
                );
            }
        }
        // Without colour, no colour tree at all.
        let bare = plan_for_caps(3, &caps, None);
        assert_eq!(bare.block_counts().1, 0);
        assert!(!bare.colour_split(BlockId::root(Face::NORTH)));
        assert_eq!(bare.colour_max_level(), 0);
        // No cap deeper than the base: the uniform plan.
        assert!(matches!(
            plan_for_caps(
                3,
                &[Cap {
                    level: 3,
                    ..caps[0]
                }],
                None
            ),
            Plan::Uniform { levels: 3, .. }
        ));
    }

    #[test]
    fn block_cap_contains_its_corners_and_centre() {
        let b = BlockId::new(Face::NORTH, 4, 3, 9).unwrap_or(BlockId::root(Face::NORTH));
        let (c, r) = block_cap(b);
        assert!(r > 0.0 && r < 0.1);
        let cap = Cap {
            centre: c,
            radius: 1e-9,
            level: 5,
        };
        assert!(block_meets_cap(b, &cap));
        let far = Cap {
            centre: [-c[0], -c[1], -c[2]],
            radius: 1.0,
            level: 5,
        };
        assert!(!block_meets_cap(b, &far));
    }
}
