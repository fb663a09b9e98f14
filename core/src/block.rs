//! Block addressing: (face, level, x, y), children, parents and neighbours.
//!
//! Each cube face is a quadtree (thesis §3.2, `subDepth = 1`): level `L` has
//! `2^L × 2^L` blocks, `x` counts along the face's `u` axis from `u = −1` and
//! `y` along `v` from `v = −1`. A block of level `L` covers the equal-angle
//! square `[x, x+1]/2^L × [y, y+1]/2^L` of its face.
//!
//! Neighbours across a cube edge follow thesis Table 4.1 (reconstructed in
//! docs/REFERENCES.md). Edge names are the thesis's: Left is `u = −1`, Top is
//! `v = +1`, Right is `u = +1`, Bottom is `v = −1`. Because the axes of two
//! faces point the same way along their shared edge, the coordinate along the
//! edge (`y` for Left/Right, `x` for Top/Bottom) is the same on both sides.

use crate::cube::Face;
use std::fmt;

/// The deepest level a block may have (`2^30` blocks per face side).
pub const MAX_LEVEL: u8 = 30;

/// One of the four edges of a face or a block.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Edge {
    /// `u = −1` side (x = 0).
    Left = 0,
    /// `v = +1` side (y = max).
    Top = 1,
    /// `u = +1` side (x = max).
    Right = 2,
    /// `v = −1` side (y = 0).
    Bottom = 3,
}

impl Edge {
    /// All four edges.
    pub const ALL: [Edge; 4] = [Edge::Left, Edge::Top, Edge::Right, Edge::Bottom];

    /// The edge on the other side of a block (inside one face).
    pub fn opposite(self) -> Edge {
        match self {
            Edge::Left => Edge::Right,
            Edge::Right => Edge::Left,
            Edge::Top => Edge::Bottom,
            Edge::Bottom => Edge::Top,
        }
    }

    /// Whether the edge runs along `v` (Left, Right) rather than `u`.
    pub fn is_vertical(self) -> bool {
        matches!(self, Edge::Left | Edge::Right)
    }

    /// The edge with this index (`0..4`).
    pub fn from_index(i: usize) -> Edge {
        Edge::ALL[i & 3]
    }
}

/// The neighbouring face across `edge` of `face`, and the neighbour's edge
/// that touches it (Thesis Table 4.1 as reconstructed in docs/REFERENCES.md).
pub fn face_neighbour(face: Face, edge: Edge) -> (Face, Edge) {
    let (offset, e) = if face.is_even() {
        match edge {
            Edge::Left => (5, Edge::Right),
            Edge::Top => (4, Edge::Right),
            Edge::Right => (2, Edge::Top),
            Edge::Bottom => (1, Edge::Top),
        }
    } else {
        match edge {
            Edge::Left => (4, Edge::Bottom),
            Edge::Top => (5, Edge::Bottom),
            Edge::Right => (1, Edge::Left),
            Edge::Bottom => (2, Edge::Left),
        }
    };
    let f = Face::new((face.index() + offset) % 6).unwrap_or(Face::NORTH);
    (f, e)
}

/// A block of a face quadtree.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct BlockId {
    /// The cube face.
    pub face: Face,
    /// Tree level, 0 is the face's root.
    pub level: u8,
    /// Column along `u`, in `0..2^level`.
    pub x: u32,
    /// Row along `v`, in `0..2^level`.
    pub y: u32,
}

impl fmt::Debug for BlockId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "B{}:{}:{}:{}",
            self.face.index(),
            self.level,
            self.x,
            self.y
        )
    }
}

impl BlockId {
    /// The root block of a face.
    pub fn root(face: Face) -> BlockId {
        BlockId {
            face,
            level: 0,
            x: 0,
            y: 0,
        }
    }

    /// A block, if the coordinates are inside the face at that level.
    pub fn new(face: Face, level: u8, x: u32, y: u32) -> Option<BlockId> {
        if level > MAX_LEVEL {
            return None;
        }
        let n = 1u64 << level;
        ((x as u64) < n && (y as u64) < n).then_some(BlockId { face, level, x, y })
    }

    /// Number of blocks per face side at this block's level.
    pub fn blocks_per_side(&self) -> u32 {
        1u32 << self.level
    }

    /// The child `(cx, cy)`, each in `0..2`. Child index `k` is
    /// `(k & 1, k >> 1)`: x varies fastest.
    pub fn child(&self, k: usize) -> BlockId {
        BlockId {
            face: self.face,
            level: self.level + 1,
            x: 2 * self.x + (k & 1) as u32,
            y: 2 * self.y + (k >> 1) as u32,
        }
    }

    /// The four children in index order.
    pub fn children(&self) -> [BlockId; 4] {
        [self.child(0), self.child(1), self.child(2), self.child(3)]
    }

    /// The index of this block among its parent's children.
    pub fn child_index(&self) -> usize {
        ((self.x & 1) | ((self.y & 1) << 1)) as usize
    }

    /// The parent, or `None` for a root.
    pub fn parent(&self) -> Option<BlockId> {
        (self.level > 0).then(|| BlockId {
            face: self.face,
            level: self.level - 1,
            x: self.x / 2,
            y: self.y / 2,
        })
    }

    /// The ancestor at `level` (itself if `level == self.level`).
    pub fn ancestor(&self, level: u8) -> BlockId {
        let d = self.level.saturating_sub(level);
        BlockId {
            face: self.face,
            level: self.level - d,
            x: self.x >> d,
            y: self.y >> d,
        }
    }

    /// Whether `self` is `other` or one of its ancestors.
    pub fn contains(&self, other: &BlockId) -> bool {
        self.face == other.face && other.level >= self.level && other.ancestor(self.level) == *self
    }

    /// The same-level neighbour across `edge`, and the neighbour's edge that
    /// faces back to this block. Crosses cube edges by thesis Table 4.1.
    pub fn neighbour(&self, edge: Edge) -> (BlockId, Edge) {
        let last = self.blocks_per_side() - 1;
        let inside = match edge {
            Edge::Left if self.x > 0 => Some((self.x - 1, self.y)),
            Edge::Right if self.x < last => Some((self.x + 1, self.y)),
            Edge::Bottom if self.y > 0 => Some((self.x, self.y - 1)),
            Edge::Top if self.y < last => Some((self.x, self.y + 1)),
            _ => None,
        };
        if let Some((x, y)) = inside {
            return (BlockId { x, y, ..*self }, edge.opposite());
        }
        let along = if edge.is_vertical() { self.y } else { self.x };
        let (face, back) = face_neighbour(self.face, edge);
        let (x, y) = match back {
            Edge::Left => (0, along),
            Edge::Right => (last, along),
            Edge::Top => (along, last),
            Edge::Bottom => (along, 0),
        };
        (
            BlockId {
                face,
                level: self.level,
                x,
                y,
            },
            back,
        )
    }

    /// The equal-angle extent `(s0, t0, s1, t1)` of the block on its face.
    pub fn extent(&self) -> (f64, f64, f64, f64) {
        let n = self.blocks_per_side() as f64;
        (
            self.x as f64 / n,
            self.y as f64 / n,
            (self.x + 1) as f64 / n,
            (self.y + 1) as f64 / n,
        )
    }

    /// A compact, order-preserving key (face, level, y, x) for maps and files.
    pub fn key(&self) -> u64 {
        ((self.face.index() as u64) << 61)
            | ((self.level as u64) << 55)
            | ((self.y as u64) << 27 & 0x7F_FFFF_F800_0000)
            | (self.x as u64 & 0x7FF_FFFF)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cube::{plane_from_angle, sample_coord};
    use proptest::prelude::*;

    #[test]
    fn face_table_is_reciprocal() {
        for f in Face::ALL {
            for e in Edge::ALL {
                let (g, back) = face_neighbour(f, e);
                assert_ne!(g, f);
                assert_ne!(g, f.opposite());
                assert_eq!(face_neighbour(g, back), (f, e), "{f:?} {e:?}");
            }
        }
    }

    proptest! {
        #[test]
        fn neighbours_are_reciprocal(f in 0u8..6, level in 0u8..12, x in any::<u32>(), y in any::<u32>(), e in 0usize..4) {
            let n = 1u32 << level;
            let b = BlockId::new(Face::new(f).unwrap(), level, x % n, y % n).unwrap();
            let edge = Edge::from_index(e);
            let (nb, back) = b.neighbour(edge);
            prop_assert!(BlockId::new(nb.face, nb.level, nb.x, nb.y).is_some());
            prop_assert_eq!(nb.neighbour(back), (b, edge));
        }

        /// The corner points of a block's edge coincide bit for bit with the
        /// neighbour's, across cube edges too, in the same order.
        #[test]
        fn shared_edges_are_bit_identical(f in 0u8..6, level in 0u8..10, x in any::<u32>(), y in any::<u32>(), e in 0usize..4, k in 0u64..=64) {
            let n = 1u32 << level;
            let b = BlockId::new(Face::new(f).unwrap(), level, x % n, y % n).unwrap();
            let edge = Edge::from_index(e);
            let (nb, back) = b.neighbour(edge);
            let w = 64u64;
            let point = |blk: BlockId, ed: Edge, k: u64| {
                let m = w << blk.level;
                let (i, j) = match ed {
                    Edge::Left => (0, k),
                    Edge::Right => (w, k),
                    Edge::Bottom => (k, 0),
                    Edge::Top => (k, w),
                };
                let s = sample_coord(blk.x as u64 * w + i, m);
                let t = sample_coord(blk.y as u64 * w + j, m);
                blk.face.cube_point(plane_from_angle(s), plane_from_angle(t))
            };
            let a = point(b, edge, k);
            let c = point(nb, back, k);
            prop_assert_eq!(a.map(f64::to_bits), c.map(f64::to_bits));
        }
    }

    #[test]
    fn family() {
        let r = BlockId::root(Face::new(2).unwrap());
        let c = r.child(3).child(1);
        assert_eq!(c, BlockId::new(r.face, 2, 3, 2).unwrap());
        assert_eq!(c.parent().unwrap().parent().unwrap(), r);
        assert!(r.contains(&c));
        assert_eq!(c.child_index(), 1);
        assert_eq!(c.ancestor(0), r);
    }
}
