//! Adaptive LOD selection: one traversal of both trees per frame.
//!
//! Implements the selection part of thesis Alg. 3.1 (§3.6, see
//! docs/REFERENCES.md): for every block compute visibility and importance, choose the LOD
//! to render, and trigger refine / split / merge requests (§3.6.4, Eq. 3.4):
//!
//! - visible leaf whose selected LOD is finer than its last: refine
//!   (request importance `1 − importance`); it is drawn at the nearest
//!   available LOD meanwhile;
//! - visible fully loaded leaf with `importance < −1`: split (importance
//!   `−importance`); when a neighbour is already the maximum level
//!   difference coarser (§4.3.3), that neighbour is forced to refine or
//!   split instead, with this block's importance, ignoring its visibility;
//! - split block with `ceil(importance) ≥ 1` whose children are leaves:
//!   merge (importance `importance`), visible or not. Invisible blocks
//!   trigger nothing else (§3.6.1).
//!
//! Colour blocks use the visibility of the elevation block with the same id
//! (§4.4.3) and their own block width in the importance. Constraints are
//! checked here (trigger time) and again when executing.
//!
//! The draw list carries, per edge, the neighbour's drawn LOD and
//! `lodDiff = (neighbor.lod − this.lod) + (this.level − neighbor.level)`
//! (erratum of Thesis §4.3.1, docs/REFERENCES.md): the block adapts on that edge
//! when it is positive; split (finer) or invisible neighbours give `None`.
//!
//! Two implementations of the one traversal, one file each:
//!
//! - [`reference`](mod@reference): [`select`], the traversal as the thesis states it,
//!   recursive over the linked trees (the reference the tests compare with);
//! - [`cached`]: [`Selector`], the same selection bit for bit over a cached
//!   flat form of the trees, the one the client runs.
//!
//! This module holds what both share: the draw list and the triggers.

use crate::refinement::{ahead_priority, Footprint, Kind, Measure, Policy, Refiner};
use crate::request_queue::{LoadRequest, OpKind, TreeOp};
use crate::tree::{Blocked, Node, PartialTree};
use crate::visibility::View;
use planet_core::format::Tree;
use planet_core::{BlockId, Edge};

pub mod cached;
pub mod reference;

pub use cached::Selector;
pub use reference::select;

/// A neighbour's LOD across one edge of a drawn block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NeighbourLod {
    /// The neighbouring (same-level or coarser) leaf.
    pub block: BlockId,
    /// Its drawn LOD.
    pub lod: u8,
    /// `(neighbor.lod − this.lod) + (this.level − neighbor.level)`; the
    /// block skips samples on this edge when positive.
    pub lod_diff: i32,
}

/// The colour block textured onto a drawn elevation block (its bound block
/// or the nearest colour ancestor, §4.4.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ColourBinding {
    /// The colour leaf.
    pub block: BlockId,
    /// Its drawn LOD.
    pub lod: u8,
}

/// A block to draw this frame.
#[derive(Debug, Clone, PartialEq)]
pub struct DrawBlock {
    /// The elevation leaf.
    pub block: BlockId,
    /// The LOD to draw (0 full, 1 first).
    pub lod: u8,
    /// Per edge (`Edge::ALL` order: left, top, right, bottom).
    pub neighbours: [Option<NeighbourLod>; 4],
    /// The colour to use, when the database has colour.
    pub colour: Option<ColourBinding>,
    /// The block's importance.
    pub importance: f64,
    /// Screen-space error in pixels at the drawn LOD (capped at the
    /// viewport height).
    pub screen_error: f64,
    /// Approximate screen area of the block in pixels (its footprint's
    /// side projected at its distance, squared, at most the viewport): the
    /// weight of its error in the per-pixel mean.
    pub screen_area: f64,
}

/// The result of one traversal.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Selection {
    /// Visible elevation leaves with their LODs.
    pub draw: Vec<DrawBlock>,
    /// Triggered load requests.
    pub loads: Vec<LoadRequest>,
    /// Triggered splits and merges.
    pub ops: Vec<TreeOp>,
    /// Triangles of the draw list.
    pub triangles: u64,
}

/// Whether the draw list `draw` draws the LOD 0 samples of `block` of tree
/// `kind`: the block drawn (elevation) or textured onto a drawn block
/// (colour) at LOD 0, or one of its children at LOD 1, as a split block's
/// LOD 0 is its children's LOD 1 (thesis §3.3.2). The definition, by a
/// scan of the list; [`Selector::draws_lod0`] answers the same for its
/// last selection without the scan.
pub fn draws_lod0(draw: &[DrawBlock], kind: Tree, block: &BlockId) -> bool {
    let at = |b: BlockId, lod: u8| lod0_block(b, lod) == Some(*block);
    draw.iter().any(|d| match kind {
        Tree::Elevation => at(d.block, d.lod),
        Tree::Colour => d.colour.is_some_and(|c| at(c.block, c.lod)),
    })
}

/// The block whose LOD 0 samples block `b` shows when drawn at `lod`: `b`
/// itself at LOD 0, its parent at LOD 1 (thesis §3.3.2).
pub(crate) fn lod0_block(b: BlockId, lod: u8) -> Option<BlockId> {
    match lod {
        0 => Some(b),
        1 => b.parent(),
        _ => None,
    }
}

/// The view predicted for when an answer asked now is applied, for the
/// prefetch of both traversals ([`crate::ClientConfig::prefetch`]): a
/// visible leaf that the present view neither loads nor splits is loaded
/// or split when that view wants it, at [`ahead_priority`] (after
/// everything the present view wants), and a split block merges only when
/// that view lets it too, so that a block split for the view ahead is not
/// merged again before the camera gets there. The screen-space policies
/// only.
pub(crate) struct Ahead<'a> {
    refiner: &'a Refiner,
    /// How far its eye is from the present one.
    moved: f64,
}

impl<'a> Ahead<'a> {
    /// `ahead`'s view against `present`'s (`None` without a prediction or
    /// with the thesis's policy).
    pub(crate) fn new(present: &Refiner, ahead: Option<&'a Refiner>) -> Option<Ahead<'a>> {
        let refiner = ahead?;
        if present.policy() == Policy::Thesis || refiner.policy() == Policy::Thesis {
            return None;
        }
        Some(Ahead {
            refiner,
            moved: (refiner.eye() - present.eye()).length(),
        })
    }

    /// Whether a split block that the present view merges may merge as far
    /// as the view ahead goes.
    pub(crate) fn lets_merge(
        &self,
        kind: Kind,
        fp: &Footprint,
        width: f64,
        err: (f64, f64),
    ) -> bool {
        let m = self.refiner.measure(kind, fp, width, err.0, err.1);
        self.refiner.merge(&m).is_some()
    }
}

/// A visible leaf the present view neither loads nor splits, for
/// [`Ctx::prefetch`].
pub(crate) struct Leaf<'b> {
    pub(crate) kind: Kind,
    pub(crate) id: BlockId,
    pub(crate) fp: &'b Footprint,
    /// Block width of its tree.
    pub(crate) width: f64,
    /// Errors at LOD 1 and LOD 0.
    pub(crate) err: (f64, f64),
    /// Its LOD (0 or 1).
    pub(crate) lod: u8,
    /// Its record's size in bytes.
    pub(crate) size: u32,
    /// Its data let it split.
    pub(crate) splittable: bool,
}

impl<'b> Leaf<'b> {
    /// The leaf of tree node `n` (of tree `kind`, block width `width`)
    /// whose elevation block's footprint is `fp`.
    pub(crate) fn of_node(kind: Kind, n: &Node, fp: &'b Footprint, width: f64) -> Leaf<'b> {
        Leaf {
            kind,
            id: n.id,
            fp,
            width,
            err: (n.record.error as f64, n.child_error()),
            lod: n.lod,
            size: n.record.size,
            splittable: n.can_split_data().is_ok(),
        }
    }
}

/// The output of a traversal under construction, and the triggers both
/// traversals share.
pub(crate) struct Ctx<'a> {
    pub(crate) tree: &'a PartialTree,
    pub(crate) out: Selection,
}

impl Ctx<'_> {
    /// Adds an elevation block to the draw list at `lod` (neighbours and
    /// colour are filled in later) and counts its triangles: `2·w²`, with
    /// `w` the block width for `lod` 0 and half of it for `lod` 1.
    pub(crate) fn draw(
        &mut self,
        block: BlockId,
        lod: u8,
        width: usize,
        importance: f64,
        sse: (f64, f64),
    ) {
        let w = if lod == 0 { width } else { width / 2 } as u64;
        self.out.triangles += 2 * w * w;
        self.out.draw.push(DrawBlock {
            block,
            lod,
            neighbours: [None; 4],
            colour: None,
            importance,
            screen_error: sse.0,
            screen_area: sse.1,
        });
    }

    /// The prefetch of a visible leaf whose present measure is `m` (see
    /// [`Ahead`]).
    #[inline]
    pub(crate) fn prefetch(&mut self, ahead: &Ahead, present: &Refiner, m: &Measure, leaf: Leaf) {
        // A leaf with its LOD 0 that cannot split has nothing to ask.
        if (leaf.lod == 0 && !leaf.splittable)
            || !present.may_want_ahead(ahead.refiner, ahead.moved, m, leaf.lod)
        {
            return;
        }
        self.prefetch_wanted(ahead, leaf);
    }

    /// [`Ctx::prefetch`] of a leaf that passed its cheap test.
    #[inline(never)]
    fn prefetch_wanted(&mut self, ahead: &Ahead, leaf: Leaf) {
        let a = ahead.refiner;
        let ma = a.measure(leaf.kind, leaf.fp, leaf.width, leaf.err.0, leaf.err.1);
        let d = a.leaf(&ma, leaf.lod);
        let tree = match leaf.kind {
            Kind::Elevation => Tree::Elevation,
            Kind::Colour => Tree::Colour,
        };
        if d.load {
            let p = a.load_priority(
                leaf.kind,
                &ma,
                leaf.lod,
                leaf.id.level,
                leaf.fp.centre,
                leaf.size,
            );
            self.load(tree, leaf.id, ahead_priority(p), false);
        } else if d.split && leaf.splittable {
            let p = ahead_priority(a.split_priority(&ma, leaf.id.level, leaf.fp.centre));
            match tree {
                Tree::Elevation => self.trigger_split(tree, leaf.id, p, 0),
                Tree::Colour => self.split_colour(leaf.id, p),
            }
        }
    }

    pub(crate) fn load(&mut self, tree: Tree, block: BlockId, importance: f64, forced: bool) {
        let Some(n) = self.tree.tree(tree).and_then(|t| t.get(&block)) else {
            return;
        };
        self.out.loads.push(LoadRequest {
            tree,
            block,
            record: n.record,
            importance,
            forced,
        });
    }

    /// Split colour leaf `id` (LOD 0 loaded, with children); when its
    /// elevation block is not split (the binding of §4.4.1), refine the
    /// elevation block instead, so that colour can refine by texel size
    /// where the geometry alone would not: load its LOD 0, or split it.
    pub(crate) fn split_colour(&mut self, id: BlockId, importance: f64) {
        match self.tree.can_split(Tree::Colour, &id) {
            Ok(()) => self.out.ops.push(TreeOp {
                kind: OpKind::Split,
                tree: Tree::Colour,
                block: id,
                importance,
            }),
            Err(Blocked::Binding) => {
                let Some(e) = self.tree.elevation().get(&id) else {
                    return;
                };
                if e.split {
                    return;
                }
                match e.can_split_data() {
                    Ok(()) => self.trigger_split(Tree::Elevation, id, importance, 0),
                    Err(Blocked::NotLoaded) => self.load(Tree::Elevation, id, importance, false),
                    Err(_) => {}
                }
            }
            Err(_) => {}
        }
    }

    /// Trigger a split, or force the neighbours that block it (§4.3.3).
    pub(crate) fn trigger_split(&mut self, tree: Tree, id: BlockId, importance: f64, depth: u8) {
        match self.tree.can_split(tree, &id) {
            Ok(()) => self.out.ops.push(TreeOp {
                kind: OpKind::Split,
                tree,
                block: id,
                importance,
            }),
            Err(Blocked::NeighbourTooCoarse(_)) if depth < 32 => {
                let Some(t) = self.tree.tree(tree) else {
                    return;
                };
                for e in Edge::ALL {
                    let Some(nb) = t.neighbour(&id, e) else {
                        continue;
                    };
                    if nb.split || nb.id.level + self.tree.max_level_difference() > id.level {
                        continue;
                    }
                    let nid = nb.id;
                    match nb.can_split_data() {
                        Ok(()) => self.trigger_split(tree, nid, importance, depth + 1),
                        Err(Blocked::NotLoaded) if nb.lod == 1 => {
                            self.load(tree, nid, importance, true)
                        }
                        Err(_) => {}
                    }
                }
            }
            Err(_) => {}
        }
    }
}

/// The loads that the children of the elevation blocks split by `ops`
/// would trigger as visible leaves at LOD 1 (the leaf rule of both
/// traversals: a fresh leaf has no child errors yet), asked in the frame
/// that chooses the split rather than in the next, where it is executed
/// ([`ClientConfig::eager_children`](crate::ClientConfig::eager_children)).
/// With `later` (the view predicted for the answer's arrival and its
/// refiner), a child is asked only if it is visible there too and still
/// needs its LOD 0 by the ball's distance, as every other request is.
pub(crate) fn children_loads(
    tree: &PartialTree,
    ops: &[TreeOp],
    view: &View,
    refiner: &Refiner,
    later: Option<(&View, &Refiner)>,
) -> Vec<LoadRequest> {
    let w = tree.elevation().width as f64;
    let mut out = vec![];
    for op in ops {
        if op.kind != OpKind::Split || op.tree != Tree::Elevation {
            continue;
        }
        let Some(children) = tree.split_children(&op.block) else {
            continue;
        };
        for (id, record, bounds) in children {
            if !view.is_visible(&bounds) {
                continue;
            }
            let err1 = record.error as f64;
            let m = refiner.measure(Kind::Elevation, &Footprint::of(&bounds), w, err1, 0.0);
            if !refiner.leaf(&m, 1).load {
                continue;
            }
            if let Some((pv, lr)) = later {
                if !pv.is_visible(&bounds)
                    || !lr.loads_at_arrival(Kind::Elevation, &bounds, w, err1, 1)
                {
                    continue;
                }
            }
            out.push(LoadRequest {
                tree: Tree::Elevation,
                block: id,
                record,
                importance: refiner.load_priority(
                    Kind::Elevation,
                    &m,
                    1,
                    id.level,
                    bounds.centre,
                    record.size,
                ),
                forced: false,
            });
        }
    }
    out
}

/// Whether the colour leaf with the id of an elevation block wants its
/// children (its LOD 0 is loaded, has children, and its texels are coarser
/// than the tolerance). Colour can split only under a split elevation block
/// (§4.4.1's binding), so a split elevation block then stays split, and a
/// leaf whose LOD 0 colour asked for ([`Ctx::split_colour`]) is drawn at
/// LOD 0: it splits in the next frame, its children drawn at LOD 1 from the
/// same samples and triangles.
pub(crate) fn colour_holds_split(
    tree: &PartialTree,
    refiner: &Refiner,
    id: &BlockId,
    fp: &Footprint,
) -> bool {
    let Some(ct) = tree.colour() else {
        return false;
    };
    let Some(c) = ct.get(id) else { return false };
    if c.split || c.can_split_data().is_err() {
        return false;
    }
    let m = refiner.measure(
        Kind::Colour,
        fp,
        ct.width as f64,
        c.record.error as f64,
        c.child_error(),
    );
    refiner.leaf(&m, c.lod).split
}
