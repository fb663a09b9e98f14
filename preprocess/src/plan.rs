//! Tree shape: which blocks are split (thesis §3.2, §4.3.3, §5.3).
//!
//! The thesis builds complete, uniform trees. A planet with high-resolution
//! insets over a coarse global base needs a depth that varies by region: a
//! block is split while its sample spacing is coarser than the finest source
//! covering it (capped by `max_level`). The tree is then *graded* so that
//! neighbouring leaves, across cube edges too, differ by at most
//! [`MAX_GRADE`] levels, within the `max_level_difference(64) = 5` the edge
//! strips can stitch (thesis §4.3.3, thesis-notes §7.6), with a margin of 1.
//!
//! The colour tree is the elevation tree truncated at the colour source's
//! level (linked trees, thesis §4.4.1): a truncation at a uniform level keeps
//! the grading.

use crate::source::ElevationStack;
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

    /// Whether the colour block (which must exist) is split.
    pub fn colour_split(&self, b: BlockId) -> bool {
        match self.colour_level() {
            Some(c) => b.level < c && self.elevation_split(b),
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
        self.colour_level().unwrap_or(0).min(self.max_level())
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
            Plan::Explicit { split, .. } => {
                let e = 6 + 4 * split.len() as u64;
                let c = match self.colour_level() {
                    Some(cl) => 6 + 4 * split.iter().filter(|b| b.level < cl).count() as u64,
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
    let mut split = HashSet::new();
    let mut stackv: Vec<BlockId> = Face::ALL.iter().map(|&f| BlockId::root(f)).collect();
    while let Some(b) = stackv.pop() {
        let need = stack.level_needed(b).min(max_level);
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
}
