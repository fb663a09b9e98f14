//! The client's partial tree of blocks: two linked trees, split, merge,
//! refine, neighbours and constraints.
//!
//! Implements thesis §3.4 (see docs/REFERENCES.md): an incomplete, unbalanced
//! quadtree per cube face, for each of the two linked trees (elevation, and
//! colour when the header has one, §4.4.1). Nodes live in an arena keyed by
//! [`BlockId`]; only leaves own samples, in one grid at the resolution of
//! their last LOD:
//!
//! - elevation: `(W+1)²` `i16`, with LOD 1 at the even positions;
//! - colour: the filtered `(W/2)²` LOD 1 grid, plus the full `W²` grid once
//!   LOD 0 is loaded (filtered LODs are separate grids, §4.4.4).
//!
//! Every node stores the [`ChildRef`] of its own LOD 0 record (from the
//! parent's record, roots from the header) and, once refined, the children's.
//!
//! - **Split** (§3.4.1) hands the parent's full grid to the children as their
//!   first LOD ([`lod::split_elevation`], [`lod::split_colour`]).
//! - **Merge** rebuilds the parent's full grid from the children's LOD 1
//!   ([`lod::merge_elevation`], [`lod::merge_colour`]); children must be leaves.
//! - **Refine** (§3.4.2) writes a decoded LOD 0 in place; decoding
//!   ([`decode_record`]) is pure so it runs on worker threads, checks the
//!   record's tree and block, and never touches the tree.
//!
//! **Neighbours** (§4.3.2 Alg. 4.1, erratum: the maximum child coordinate is
//! `2^subDepth − 1`). Instead of maintaining the pointer table of Alg. 4.1 we
//! compute it by lookup: the neighbour across an edge is the deepest existing
//! node covering the same-level neighbour id ([`BlockId::neighbour`] crosses
//! cube faces by Table 4.1). That is exactly what Alg. 4.1's pointers hold
//! (a same-level or coarser block), costs `O(level)` hash lookups, and cannot
//! go stale after split/merge.
//!
//! **Constraints**, checked at trigger and again at execution:
//! - level difference (§4.3.3): neighbouring elevation leaves differ by at
//!   most [`lod::max_level_difference`]`(W)` levels (at least 1: a width not
//!   divisible by 4 cannot stitch any difference and we accept cracks rather
//!   than forbid every split). Only the elevation tree stitches edges;
//! - binding (§4.4.1): a colour block cannot split while the elevation block
//!   with the same id is a leaf (or absent), and an elevation block cannot
//!   merge while the colour block with the same id is split. Hence every
//!   colour node has an elevation node with the same id.

use crate::visibility::{BlockBounds, View};
use planet_core::codec::{CodecError, TreeCodec};
use planet_core::format::{self, ChildRef, FormatError, Header, Tree};
use planet_core::lod::{self, Rgb};
use planet_core::{BlockId, Edge, Face};
use std::collections::{HashMap, HashSet};
use std::hash::{BuildHasherDefault, Hasher};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use thiserror::Error;

/// A fast, non-cryptographic hasher (FxHash-like) for the client's small
/// keys ([`BlockId`], request ids): the per-frame traversal does tens of
/// thousands of lookups, for which SipHash dominated the frame time. Keys
/// come from the client itself, not from an adversary.
#[derive(Debug, Clone, Copy, Default)]
pub struct FastHasher(u64);

const FX_K: u64 = 0xf135_7aea_2e62_a9c5;

impl FastHasher {
    #[inline]
    fn add(&mut self, w: u64) {
        self.0 = (self.0.rotate_left(5) ^ w).wrapping_mul(FX_K);
    }
}

impl Hasher for FastHasher {
    #[inline]
    fn write(&mut self, bytes: &[u8]) {
        let mut c = bytes.chunks_exact(8);
        for w in &mut c {
            let mut a = [0u8; 8];
            a.copy_from_slice(w);
            self.add(u64::from_le_bytes(a));
        }
        let r = c.remainder();
        if !r.is_empty() {
            let mut a = [0u8; 8];
            a[..r.len()].copy_from_slice(r);
            self.add(u64::from_le_bytes(a) ^ ((r.len() as u64) << 56));
        }
    }
    #[inline]
    fn write_u8(&mut self, i: u8) {
        self.add(i as u64);
    }
    #[inline]
    fn write_u16(&mut self, i: u16) {
        self.add(i as u64);
    }
    #[inline]
    fn write_u32(&mut self, i: u32) {
        self.add(i as u64);
    }
    #[inline]
    fn write_u64(&mut self, i: u64) {
        self.add(i);
    }
    #[inline]
    fn write_usize(&mut self, i: usize) {
        self.add(i as u64);
    }
    #[inline]
    fn finish(&self) -> u64 {
        // hashbrown takes its 7 control bits from the top: spread the
        // multiply's well-mixed high bits to both ends.
        self.0.rotate_left(26)
    }
}

/// A `HashMap` with [`FastHasher`].
pub type FastMap<K, V> = HashMap<K, V, BuildHasherDefault<FastHasher>>;
/// A `HashSet` with [`FastHasher`].
pub type FastSet<K> = HashSet<K, BuildHasherDefault<FastHasher>>;

/// A record that cannot be applied.
#[derive(Debug, Error)]
pub enum RefineError {
    /// The bytes are not a valid record.
    #[error("invalid record: {0}")]
    Format(#[from] FormatError),
    /// The payload does not decode.
    #[error("payload does not decode: {0}")]
    Codec(#[from] CodecError),
    /// The record belongs to the other tree.
    #[error("record of the {got:?} tree, expected {expected:?}")]
    WrongTree {
        /// Tree requested.
        expected: Tree,
        /// Tree in the record.
        got: Tree,
    },
    /// The record is another block's.
    #[error("record of block {got:?}, expected {expected:?}")]
    WrongBlock {
        /// Block requested.
        expected: BlockId,
        /// Block in the record.
        got: BlockId,
    },
    /// The first-LOD snapshot has the wrong shape.
    #[error("first LOD snapshot does not match the tree")]
    Snapshot,
}

/// Why a split or merge is not allowed now.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum Blocked {
    /// No such node.
    #[error("no such node")]
    Missing,
    /// Split needs a leaf.
    #[error("not a leaf")]
    NotLeaf,
    /// Split needs LOD 0 and the children's records.
    #[error("not fully loaded")]
    NotLoaded,
    /// The database has no children for this block.
    #[error("no children in the database")]
    NoChildren,
    /// Split: this neighbouring leaf is already the maximum difference coarser.
    #[error("neighbour {0:?} too coarse")]
    NeighbourTooCoarse(BlockId),
    /// Merge: a neighbour's subtree is already the maximum difference finer.
    #[error("neighbour {0:?} too fine")]
    NeighbourTooFine(BlockId),
    /// Merge needs a split node whose children are all leaves.
    #[error("children are not all leaves")]
    ChildrenNotLeaves,
    /// Colour/elevation binding (§4.4.1).
    #[error("bound block of the other tree forbids it")]
    Binding,
}

/// A broken invariant found by [`PartialTree::validate`].
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("tree invariant broken: {0}")]
pub struct InvariantError(pub String);

/// A leaf's samples.
#[derive(Debug, Clone, PartialEq)]
pub enum Samples {
    /// `(W+1)²` elevation samples (LOD 1 at even positions).
    Elevation(Vec<i16>),
    /// Colour: the filtered LOD 1 `(W/2)²` and, at LOD 0, the full `W²`.
    Colour {
        /// Filtered LOD 1.
        lod1: Vec<Rgb>,
        /// Full grid, once LOD 0 is loaded.
        full: Option<Vec<Rgb>>,
    },
}

/// One node of a linked tree.
#[derive(Debug, Clone, PartialEq)]
pub struct Node {
    /// The block.
    pub id: BlockId,
    /// This block's LOD 0 record.
    pub record: ChildRef,
    /// The children's LOD 0 records, once LOD 0 is loaded (empty when the
    /// database has no children).
    pub child_refs: Option<Vec<ChildRef>>,
    /// Whether the node has (all four) children.
    pub split: bool,
    /// For a leaf: its last LOD (1 = first only, 0 = full).
    pub lod: u8,
    /// The samples; `Some` exactly for leaves.
    pub samples: Option<Samples>,
    /// Conservative bounds (elevation nodes; colour nodes use the elevation
    /// node with the same id). Shared, so that caches can hold them.
    pub bounds: Option<Arc<BlockBounds>>,
}

impl Node {
    /// Whether the node is a leaf.
    pub fn is_leaf(&self) -> bool {
        !self.split
    }

    /// The geometric error of the block drawn at LOD 0: the largest error
    /// of its children's records (0 before its record is loaded, or
    /// without children).
    pub fn child_error(&self) -> f64 {
        self.child_refs.as_ref().map_or(0.0, |c| {
            c.iter().map(|r| r.error as f64).fold(0.0, f64::max)
        })
    }

    /// Whether the node can split as far as its own data go.
    pub fn can_split_data(&self) -> Result<(), Blocked> {
        if self.split {
            return Err(Blocked::NotLeaf);
        }
        match &self.child_refs {
            _ if self.lod != 0 => Err(Blocked::NotLoaded),
            None => Err(Blocked::NotLoaded),
            Some(c) if c.len() != 4 => Err(Blocked::NoChildren),
            Some(_) => Ok(()),
        }
    }
}

/// A snapshot of a leaf's first LOD, handed to a decoder.
#[derive(Debug, Clone, PartialEq)]
pub enum FirstLod {
    /// The `(W+1)²` grid with LOD 1 set.
    Elevation(Vec<i16>),
    /// The filtered LOD 1 grid.
    Colour(Vec<Rgb>),
}

/// A decoded LOD 0 record, ready to apply.
#[derive(Debug, Clone, PartialEq)]
pub struct Decoded {
    /// Its tree.
    pub tree: Tree,
    /// Its block.
    pub block: BlockId,
    /// The full samples (elevation grid or colour `Samples::Colour` with `full`).
    pub samples: Samples,
    /// The children's records.
    pub children: Vec<ChildRef>,
}

/// Parse, check and decode a received LOD 0 record (pure; any thread).
pub fn decode_record(
    tree: Tree,
    block: BlockId,
    width: usize,
    codec: TreeCodec,
    bytes: &[u8],
    first: FirstLod,
) -> Result<Decoded, RefineError> {
    let rec = format::parse_record(bytes, None)?;
    if rec.header.tree != tree {
        return Err(RefineError::WrongTree {
            expected: tree,
            got: rec.header.tree,
        });
    }
    if rec.header.block != block {
        return Err(RefineError::WrongBlock {
            expected: block,
            got: rec.header.block,
        });
    }
    let samples = match (first, codec) {
        (FirstLod::Elevation(mut grid), TreeCodec::Elevation(c)) => {
            if grid.len() != (width + 1) * (width + 1) {
                return Err(RefineError::Snapshot);
            }
            rec.decode_elevation(&c, width, &mut grid)?;
            Samples::Elevation(grid)
        }
        (FirstLod::Colour(lod1), TreeCodec::Colour(c)) => {
            let full = rec.decode_colour(&c, &lod1, width)?;
            Samples::Colour {
                lod1,
                full: Some(full),
            }
        }
        _ => return Err(RefineError::Snapshot),
    };
    if matches!(
        (&samples, tree),
        (Samples::Elevation(_), Tree::Colour) | (Samples::Colour { .. }, Tree::Elevation)
    ) {
        return Err(RefineError::Snapshot);
    }
    Ok(Decoded {
        tree,
        block,
        samples,
        children: rec.header.children,
    })
}

/// One of the two linked trees.
#[derive(Debug, Clone)]
pub struct LinkedTree {
    /// Which tree.
    pub kind: Tree,
    /// Block width `W`.
    pub width: usize,
    /// The codec of the tree's records (from the header).
    pub codec: TreeCodec,
    /// Deepest level in the database.
    pub max_level: u8,
    nodes: FastMap<BlockId, Node>,
}

/// Most nodes [`LinkedTree::leaves_in_view`] visits before it answers yes.
pub const LEAF_TEST_BUDGET: usize = 64;

impl LinkedTree {
    /// The node of `id`, if present.
    pub fn get(&self, id: &BlockId) -> Option<&Node> {
        self.nodes.get(id)
    }

    /// All nodes (any order).
    pub fn nodes(&self) -> impl Iterator<Item = &Node> {
        self.nodes.values()
    }

    /// Number of nodes.
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    /// Whether the tree has no nodes (never, once built).
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// The deepest existing node covering `id` (itself or an ancestor).
    pub fn covering(&self, id: &BlockId) -> Option<&Node> {
        (0..=id.level)
            .rev()
            .find_map(|l| self.nodes.get(&id.ancestor(l)))
    }

    /// Whether a leaf of the subtree at `id` may be visible in `view`:
    /// split nodes are culled by their bounds on the way down (a node's
    /// bounds hold its subtree's), so a node whose own bounds are visible
    /// while every leaf under it is culled answers no. Conservative: yes
    /// when there is no node of that id or a node has no bounds, and after
    /// [`LEAF_TEST_BUDGET`] nodes.
    pub fn leaves_in_view(&self, id: &BlockId, view: &View) -> bool {
        if !self.nodes.contains_key(id) {
            return true;
        }
        let mut stack = vec![*id];
        let mut visited = 0;
        while let Some(id) = stack.pop() {
            visited += 1;
            if visited > LEAF_TEST_BUDGET {
                return true;
            }
            let Some(n) = self.nodes.get(&id) else {
                continue;
            };
            let Some(b) = n.bounds.as_ref() else {
                return true;
            };
            if !view.is_visible(b) {
                continue;
            }
            if !n.split {
                return true;
            }
            stack.extend(id.children());
        }
        false
    }

    /// The neighbour across `edge` (Alg. 4.1 by lookup): the deepest existing
    /// node covering the same-level neighbour. It is a leaf when coarser.
    pub fn neighbour(&self, id: &BlockId, edge: Edge) -> Option<&Node> {
        self.covering(&id.neighbour(edge).0)
    }

    /// Deepest leaf level of `id`'s subtree touching `edge` of `id`.
    pub fn deepest_along(&self, id: &BlockId, edge: Edge) -> u8 {
        match self.nodes.get(id) {
            Some(n) if n.split => {
                let ks: [usize; 2] = match edge {
                    Edge::Left => [0, 2],
                    Edge::Right => [1, 3],
                    Edge::Bottom => [0, 1],
                    Edge::Top => [2, 3],
                };
                ks.iter()
                    .map(|&k| self.deepest_along(&id.child(k), edge))
                    .max()
                    .unwrap_or(id.level)
            }
            _ => id.level,
        }
    }

    fn first_lod(&self, id: &BlockId) -> Option<FirstLod> {
        let n = self.nodes.get(id)?;
        if n.split || n.lod != 1 {
            return None;
        }
        match n.samples.as_ref()? {
            Samples::Elevation(g) => Some(FirstLod::Elevation(g.clone())),
            Samples::Colour { lod1, .. } => Some(FirstLod::Colour(lod1.clone())),
        }
    }
}

/// The partial tree: elevation and optional colour linked trees.
#[derive(Debug, Clone)]
pub struct PartialTree {
    header: Arc<Header>,
    elevation: LinkedTree,
    colour: Option<LinkedTree>,
    max_diff: u8,
    changes: Changes,
}

/// Identity of one tree value: a clone gets a new one, so a cache keyed by
/// it can never mistake a diverged clone for the tree it was built from.
#[derive(Debug)]
struct Instance(u64);

impl Instance {
    fn new() -> Instance {
        static NEXT: AtomicU64 = AtomicU64::new(1);
        Instance(NEXT.fetch_add(1, Ordering::Relaxed))
    }
}

impl Clone for Instance {
    fn clone(&self) -> Instance {
        Instance::new()
    }
}

/// Change tracking for caches derived from the tree (the per-frame
/// selection cache, [`crate::selection::Selector`]).
#[derive(Debug, Clone)]
struct Changes {
    instance: Instance,
    /// Entries dropped from the front of `log` so far: a stamp older than
    /// that cannot be served from the log.
    base: u64,
    /// Refines, splits and merges (also attempted ones) in order.
    log: Vec<TreeChange>,
}

/// Log entries kept; when full, the older half is dropped (a cache that
/// has not looked for that long rebuilds).
const MAX_CHANGE_LOG: usize = 4096;

/// A stamp of the tree's state for caches: see [`PartialTree::changes_since`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TreeStamp {
    instance: u64,
    /// Absolute position in the change log.
    pos: u64,
}

/// What happened to a block (thesis §3.4.1–3.4.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChangeKind {
    /// LOD 0 applied: its LOD, children's records and split readiness
    /// changed.
    Refined,
    /// Split attempted (after the constraint checks): it may now have
    /// children.
    Split,
    /// Merge attempted (after the constraint checks): its children may be
    /// gone and it may be a leaf.
    Merged,
}

/// One logged change of a tree.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TreeChange {
    /// What happened.
    pub kind: ChangeKind,
    /// In which tree.
    pub tree: Tree,
    /// To which block.
    pub block: BlockId,
}

/// What changed in a tree since a [`TreeStamp`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TreeChanges<'a> {
    /// Another tree, or too much changed to be listed: rebuild.
    Structure,
    /// Only these changes, in order; empty when nothing changed. A node
    /// absent from the list kept its split state, LOD and data, and every
    /// node without a listed ancestor-or-self kept its existence.
    Log(&'a [TreeChange]),
}

/// A header the client cannot start from.
#[derive(Debug, Error)]
#[error("unusable header: {0}")]
pub struct HeaderError(pub String);

impl PartialTree {
    /// The tree with the six roots of each tree at their first LOD.
    pub fn new(header: Arc<Header>) -> Result<PartialTree, HeaderError> {
        let ew = header.elevation.block_width as usize;
        if ew < 2 || !ew.is_multiple_of(2) {
            return Err(HeaderError(format!("elevation block width {ew}")));
        }
        let mut elevation = LinkedTree {
            kind: Tree::Elevation,
            width: ew,
            codec: TreeCodec::Elevation(header.elevation.codec),
            max_level: header.elevation.max_level,
            nodes: FastMap::default(),
        };
        let half = ew / 2 + 1;
        for f in Face::ALL {
            let i = f.index() as usize;
            let first = &header.elevation.root_first_lods[i];
            if first.len() != half * half {
                return Err(HeaderError(format!("elevation root {i} first LOD length")));
            }
            let mut grid = vec![0i16; (ew + 1) * (ew + 1)];
            lod::elevation_place_first_lod(first, ew, &mut grid);
            let id = BlockId::root(f);
            let record = header.elevation.root_records[i];
            elevation.nodes.insert(
                id,
                Node {
                    id,
                    record,
                    child_refs: None,
                    split: false,
                    lod: 1,
                    samples: Some(Samples::Elevation(grid)),
                    bounds: Some(Arc::new(bounds_of(&header, id, &record))),
                },
            );
        }
        let colour = match &header.colour {
            None => None,
            Some(c) => {
                let cw = c.block_width as usize;
                if cw < 2 || !cw.is_multiple_of(2) {
                    return Err(HeaderError(format!("colour block width {cw}")));
                }
                let mut t = LinkedTree {
                    kind: Tree::Colour,
                    width: cw,
                    codec: TreeCodec::Colour(c.codec),
                    max_level: c.max_level,
                    nodes: FastMap::default(),
                };
                for f in Face::ALL {
                    let i = f.index() as usize;
                    let first = &c.root_first_lods[i];
                    if first.len() != (cw / 2) * (cw / 2) {
                        return Err(HeaderError(format!("colour root {i} first LOD length")));
                    }
                    let id = BlockId::root(f);
                    t.nodes.insert(
                        id,
                        Node {
                            id,
                            record: c.root_records[i],
                            child_refs: None,
                            split: false,
                            lod: 1,
                            samples: Some(Samples::Colour {
                                lod1: first.clone(),
                                full: None,
                            }),
                            bounds: None,
                        },
                    );
                }
                Some(t)
            }
        };
        let max_diff = lod::max_level_difference(ew).clamp(1, 30) as u8;
        Ok(PartialTree {
            header,
            elevation,
            colour,
            max_diff,
            changes: Changes {
                instance: Instance::new(),
                base: 0,
                log: Vec::new(),
            },
        })
    }

    /// The current state, for a cache to compare with later
    /// ([`PartialTree::changes_since`]).
    pub fn stamp(&self) -> TreeStamp {
        TreeStamp {
            instance: self.changes.instance.0,
            pos: self.changes.base + self.changes.log.len() as u64,
        }
    }

    /// What changed since `stamp` was taken (of this very tree value).
    pub fn changes_since(&self, stamp: &TreeStamp) -> TreeChanges<'_> {
        let c = &self.changes;
        let end = c.base + c.log.len() as u64;
        if stamp.instance != c.instance.0 || stamp.pos < c.base || stamp.pos > end {
            return TreeChanges::Structure;
        }
        TreeChanges::Log(&c.log[(stamp.pos - c.base) as usize..])
    }

    fn log(&mut self, kind: ChangeKind, tree: Tree, block: BlockId) {
        let c = &mut self.changes;
        if c.log.len() >= MAX_CHANGE_LOG {
            let drop = MAX_CHANGE_LOG / 2;
            c.log.drain(..drop);
            c.base += drop as u64;
        }
        c.log.push(TreeChange { kind, tree, block });
    }

    /// The database header.
    pub fn header(&self) -> &Arc<Header> {
        &self.header
    }

    /// The largest allowed level difference between neighbouring leaves.
    pub fn max_level_difference(&self) -> u8 {
        self.max_diff
    }

    /// The elevation tree.
    pub fn elevation(&self) -> &LinkedTree {
        &self.elevation
    }

    /// The colour tree, if the database has colour.
    pub fn colour(&self) -> Option<&LinkedTree> {
        self.colour.as_ref()
    }

    /// The tree of `kind`.
    pub fn tree(&self, kind: Tree) -> Option<&LinkedTree> {
        match kind {
            Tree::Elevation => Some(&self.elevation),
            Tree::Colour => self.colour.as_ref(),
        }
    }

    fn tree_mut(&mut self, kind: Tree) -> Option<&mut LinkedTree> {
        match kind {
            Tree::Elevation => Some(&mut self.elevation),
            Tree::Colour => self.colour.as_mut(),
        }
    }

    /// Total number of nodes of both trees.
    pub fn node_count(&self) -> usize {
        self.elevation.len() + self.colour.as_ref().map_or(0, |c| c.len())
    }

    /// Snapshot of the first LOD of a leaf at LOD 1 (what a decoder needs);
    /// `None` when the block is gone or already has LOD 0.
    pub fn first_lod(&self, kind: Tree, id: &BlockId) -> Option<FirstLod> {
        self.tree(kind)?.first_lod(id)
    }

    /// Whether a received LOD 0 for this block would still be applied.
    pub fn wants_refine(&self, kind: Tree, id: &BlockId) -> bool {
        self.tree(kind)
            .and_then(|t| t.get(id))
            .is_some_and(|n| !n.split && n.lod == 1)
    }

    /// Apply a decoded LOD 0. Returns `false` (and changes nothing) when the
    /// block no longer exists, is split, or already has LOD 0.
    pub fn apply_refine(&mut self, d: Decoded) -> bool {
        if !self.wants_refine(d.tree, &d.block) {
            return false;
        }
        let Some(t) = self.tree_mut(d.tree) else {
            return false;
        };
        let width = t.width;
        let Some(n) = t.nodes.get_mut(&d.block) else {
            return false;
        };
        let ok = match &d.samples {
            Samples::Elevation(g) => {
                d.tree == Tree::Elevation && g.len() == (width + 1) * (width + 1)
            }
            Samples::Colour { lod1, full } => {
                d.tree == Tree::Colour
                    && lod1.len() == (width / 2) * (width / 2)
                    && full.as_ref().is_some_and(|f| f.len() == width * width)
            }
        };
        if !ok || !(d.children.is_empty() || d.children.len() == 4) {
            return false;
        }
        n.samples = Some(d.samples);
        n.child_refs = Some(d.children);
        n.lod = 0;
        self.log(ChangeKind::Refined, d.tree, d.block);
        true
    }

    /// Whether `id` of `kind` may split now (all constraints).
    pub fn can_split(&self, kind: Tree, id: &BlockId) -> Result<(), Blocked> {
        let t = self.tree(kind).ok_or(Blocked::Missing)?;
        let n = t.get(id).ok_or(Blocked::Missing)?;
        n.can_split_data()?;
        match kind {
            Tree::Elevation => {
                for e in Edge::ALL {
                    if let Some(nb) = t.neighbour(id, e) {
                        if nb.id.level < id.level && id.level + 1 - nb.id.level > self.max_diff {
                            return Err(Blocked::NeighbourTooCoarse(nb.id));
                        }
                    }
                }
            }
            Tree::Colour => {
                let bound = self.elevation.get(id);
                if !bound.is_some_and(|b| b.split) {
                    return Err(Blocked::Binding);
                }
            }
        }
        Ok(())
    }

    /// Whether `id` of `kind` may merge now (all constraints).
    pub fn can_merge(&self, kind: Tree, id: &BlockId) -> Result<(), Blocked> {
        let t = self.tree(kind).ok_or(Blocked::Missing)?;
        let n = t.get(id).ok_or(Blocked::Missing)?;
        if !n.split {
            return Err(Blocked::ChildrenNotLeaves);
        }
        for c in id.children() {
            if !t
                .get(&c)
                .is_some_and(|c| c.is_leaf() && c.samples.is_some())
            {
                return Err(Blocked::ChildrenNotLeaves);
            }
        }
        if kind == Tree::Elevation {
            if self
                .colour
                .as_ref()
                .and_then(|c| c.get(id))
                .is_some_and(|c| c.split)
            {
                return Err(Blocked::Binding);
            }
            for e in Edge::ALL {
                let (nid, back) = id.neighbour(e);
                if t.get(&nid).is_some() && t.deepest_along(&nid, back) > id.level + self.max_diff {
                    return Err(Blocked::NeighbourTooFine(nid));
                }
            }
        }
        Ok(())
    }

    /// Split `id` (after checking every constraint).
    pub fn split(&mut self, kind: Tree, id: &BlockId) -> Result<(), Blocked> {
        self.can_split(kind, id)?;
        // Conservative: any attempt past the checks counts as a change.
        self.log(ChangeKind::Split, kind, *id);
        let header = self.header.clone();
        let t = self.tree_mut(kind).ok_or(Blocked::Missing)?;
        let w = t.width;
        let n = t.nodes.get_mut(id).ok_or(Blocked::Missing)?;
        let refs = n.child_refs.clone().ok_or(Blocked::NotLoaded)?;
        let samples = n.samples.take().ok_or(Blocked::NotLoaded)?;
        let mut children = Vec::with_capacity(4);
        match &samples {
            Samples::Elevation(g) => {
                for (k, r) in refs.iter().enumerate() {
                    let mut cg = vec![0i16; (w + 1) * (w + 1)];
                    lod::split_elevation(g, w, k, &mut cg);
                    children.push((Samples::Elevation(cg), *r));
                }
            }
            Samples::Colour {
                full: Some(full), ..
            } => {
                for (k, r) in refs.iter().enumerate() {
                    let lod1 = lod::split_colour(full, w, k);
                    children.push((Samples::Colour { lod1, full: None }, *r));
                }
            }
            Samples::Colour { full: None, .. } => {
                n.samples = Some(samples);
                return Err(Blocked::NotLoaded);
            }
        }
        n.split = true;
        for (k, (s, r)) in children.into_iter().enumerate() {
            let cid = id.child(k);
            let bounds = (kind == Tree::Elevation).then(|| Arc::new(bounds_of(&header, cid, &r)));
            t.nodes.insert(
                cid,
                Node {
                    id: cid,
                    record: r,
                    child_refs: None,
                    split: false,
                    lod: 1,
                    samples: Some(s),
                    bounds,
                },
            );
        }
        Ok(())
    }

    /// The elevation leaves a split of `id` would create, without splitting:
    /// each child's id, LOD 0 record and bounds, as [`PartialTree::split`]
    /// makes them. `None` when `id` cannot split now.
    pub fn split_children(&self, id: &BlockId) -> Option<[(BlockId, ChildRef, BlockBounds); 4]> {
        self.can_split(Tree::Elevation, id).ok()?;
        let refs = self.elevation.get(id)?.child_refs.as_ref()?;
        if refs.len() != 4 {
            return None;
        }
        Some(std::array::from_fn(|k| {
            let cid = id.child(k);
            (cid, refs[k], bounds_of(&self.header, cid, &refs[k]))
        }))
    }

    /// The conservative bounds of elevation block `id` whose record is `r`
    /// (what [`PartialTree::split`] gives the node), for a block that is
    /// not in the tree yet.
    pub fn bounds_of(&self, id: BlockId, r: &ChildRef) -> BlockBounds {
        bounds_of(&self.header, id, r)
    }

    /// Merge `id`'s children back into it (after checking every constraint).
    pub fn merge(&mut self, kind: Tree, id: &BlockId) -> Result<(), Blocked> {
        self.can_merge(kind, id)?;
        self.log(ChangeKind::Merged, kind, *id);
        let t = self.tree_mut(kind).ok_or(Blocked::Missing)?;
        let w = t.width;
        let mut kids = Vec::with_capacity(4);
        for c in id.children() {
            kids.push(t.nodes.remove(&c).ok_or(Blocked::Missing)?);
        }
        let samples = match kind {
            Tree::Elevation => {
                let mut g = vec![0i16; (w + 1) * (w + 1)];
                for (k, c) in kids.iter().enumerate() {
                    if let Some(Samples::Elevation(cg)) = &c.samples {
                        lod::merge_elevation(cg, w, k, &mut g);
                    }
                }
                Samples::Elevation(g)
            }
            Tree::Colour => {
                let mut full = vec![[0u8; 3]; w * w];
                for (k, c) in kids.iter().enumerate() {
                    if let Some(Samples::Colour { lod1, .. }) = &c.samples {
                        lod::merge_colour(lod1, w, k, &mut full);
                    }
                }
                Samples::Colour {
                    lod1: lod::colour_filter(&full, w),
                    full: Some(full),
                }
            }
        };
        let n = t.nodes.get_mut(id).ok_or(Blocked::Missing)?;
        n.split = false;
        n.lod = 0;
        n.samples = Some(samples);
        Ok(())
    }

    /// Check every invariant: each point of each face covered by exactly one
    /// leaf (quadtree closure from the roots), every leaf has well-sized
    /// samples and no inner node has any, no orphan nodes, level-difference
    /// limits between neighbouring elevation leaves, and colour binding.
    pub fn validate(&self) -> Result<(), InvariantError> {
        let mut trees = vec![&self.elevation];
        trees.extend(self.colour.as_ref());
        for t in trees {
            let mut reached = 0usize;
            for f in Face::ALL {
                let mut stack = vec![BlockId::root(f)];
                while let Some(id) = stack.pop() {
                    let n = t
                        .get(&id)
                        .ok_or_else(|| InvariantError(format!("{:?} {id:?} missing", t.kind)))?;
                    reached += 1;
                    if n.id != id {
                        return Err(InvariantError(format!("{id:?} keyed wrongly")));
                    }
                    if n.split {
                        if n.samples.is_some() {
                            return Err(InvariantError(format!("inner {id:?} holds samples")));
                        }
                        stack.extend(id.children());
                        continue;
                    }
                    let w = t.width;
                    let ok = match &n.samples {
                        Some(Samples::Elevation(g)) => g.len() == (w + 1) * (w + 1),
                        Some(Samples::Colour { lod1, full }) => {
                            lod1.len() == (w / 2) * (w / 2)
                                && full
                                    .as_ref()
                                    .map_or(n.lod == 1, |f| n.lod == 0 && f.len() == w * w)
                        }
                        None => false,
                    };
                    if !ok || n.lod > 1 || (n.lod == 0) != n.child_refs.is_some() {
                        return Err(InvariantError(format!(
                            "{:?} leaf {id:?} samples/LOD",
                            t.kind
                        )));
                    }
                }
            }
            if reached != t.len() {
                return Err(InvariantError(format!(
                    "{:?}: {} nodes, {reached} reachable",
                    t.kind,
                    t.len()
                )));
            }
        }
        for n in self.elevation.nodes() {
            if n.split {
                continue;
            }
            for e in Edge::ALL {
                if let Some(nb) = self.elevation.neighbour(&n.id, e) {
                    if nb.id.level < n.id.level && n.id.level - nb.id.level > self.max_diff {
                        return Err(InvariantError(format!(
                            "{:?} and {:?} differ by more than {}",
                            n.id, nb.id, self.max_diff
                        )));
                    }
                }
            }
        }
        if let Some(c) = &self.colour {
            for n in c.nodes() {
                if n.split && !self.elevation.get(&n.id).is_some_and(|e| e.split) {
                    return Err(InvariantError(format!(
                        "colour {:?} split over elevation leaf",
                        n.id
                    )));
                }
            }
        }
        Ok(())
    }
}

fn bounds_of(header: &Header, id: BlockId, r: &ChildRef) -> BlockBounds {
    let (lo, hi) = if r.min_elevation.is_finite() && r.max_elevation.is_finite() {
        (r.min_elevation as f64, r.max_elevation as f64)
    } else {
        (header.min_elevation as f64, header.max_elevation as f64)
    };
    BlockBounds::new(&header.datum, id, lo, hi)
}
