//! Adaptive LOD selection: one traversal of both trees per frame.
//!
//! Implements the selection part of thesis Alg. 3.1 (§3.6, thesis-notes
//! §6.6): for every block compute visibility and importance, choose the LOD
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
//! (erratum of §4.3.1, thesis-notes §7.4): the block adapts on that edge
//! when it is positive; split (finer) or invisible neighbours give `None`.

use crate::importance::{
    block_distance, importance, refine_importance, screen_space_error, selected_lod,
    split_importance, wants_merge, wants_split,
};
use crate::request_queue::{LoadRequest, OpKind, TreeOp};
use crate::tree::{Blocked, FastMap, PartialTree};
use crate::visibility::View;
use planet_core::format::Tree;
use planet_core::{BlockId, Edge, Face};

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
    /// Screen-space error in pixels at the drawn LOD.
    pub screen_error: f64,
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

struct Ctx<'a> {
    tree: &'a PartialTree,
    out: Selection,
}

/// Select the LODs to draw and trigger requests for one frame.
pub fn select(tree: &PartialTree, view: &View, qf: f64) -> Selection {
    let mut cx = Ctx {
        tree,
        out: Selection::default(),
    };
    let et = tree.elevation();
    let ew = et.width as f64;
    // Elevation, per node: visibility and this frame's state (split, or
    // leaf with its drawn LOD when visible), for colour and neighbours.
    let mut info: FastMap<BlockId, NodeFrame> = FastMap::default();
    info.reserve(et.len());
    let mut stack: Vec<(BlockId, bool)> = Vec::with_capacity(64);
    for f in Face::ALL {
        stack.push((BlockId::root(f), true));
        while let Some((id, parent_visible)) = stack.pop() {
            let Some(n) = et.get(&id) else { continue };
            let Some(b) = n.bounds.as_ref() else { continue };
            let visible = parent_visible && view.is_visible(b);
            let dist = block_distance(view.camera.eye, b.centre, b.radius);
            let imp = importance(dist, b.radius, ew, qf);
            if n.split {
                info.insert(
                    id,
                    NodeFrame {
                        visible,
                        split: true,
                        drawn: None,
                    },
                );
                if wants_merge(imp) && tree.can_merge(Tree::Elevation, &id).is_ok() {
                    cx.out.ops.push(TreeOp {
                        kind: OpKind::Merge,
                        tree: Tree::Elevation,
                        block: id,
                        importance: imp,
                    });
                }
                stack.extend(id.children().map(|c| (c, visible)));
                continue;
            }
            let sel = selected_lod(imp);
            let lod = sel.max(n.lod);
            info.insert(
                id,
                NodeFrame {
                    visible,
                    split: false,
                    drawn: visible.then_some(lod),
                },
            );
            if !visible {
                continue;
            }
            if sel < n.lod {
                cx.load(Tree::Elevation, id, refine_importance(n.lod, imp), false);
            } else if wants_split(imp) && n.can_split_data().is_ok() {
                cx.trigger_split(Tree::Elevation, id, split_importance(imp), 0);
            }
            let error = if lod == 1 {
                n.record.error as f64
            } else {
                n.child_refs.as_ref().map_or(0.0, |c| {
                    c.iter().map(|r| r.error as f64).fold(0.0, f64::max)
                })
            };
            let sse = screen_space_error(
                error,
                dist.max(view.near),
                view.camera.viewport_height_px,
                view.camera.fov_y,
            );
            let w = if lod == 0 { et.width } else { et.width / 2 } as u64;
            cx.out.triangles += 2 * w * w;
            cx.out.draw.push(DrawBlock {
                block: id,
                lod,
                neighbours: [None; 4],
                colour: None,
                importance: imp,
                screen_error: sse,
            });
        }
    }
    // Colour tree.
    let mut colour_drawn: FastMap<BlockId, u8> = FastMap::default();
    if let Some(ct) = tree.colour() {
        let cw = ct.width as f64;
        for f in Face::ALL {
            stack.push((BlockId::root(f), true));
            while let Some((id, _)) = stack.pop() {
                let Some(n) = ct.get(&id) else { continue };
                let Some(b) = et.get(&id).and_then(|e| e.bounds.as_ref()) else {
                    continue;
                };
                let visible = info.get(&id).is_some_and(|i| i.visible);
                let dist = block_distance(view.camera.eye, b.centre, b.radius);
                let imp = importance(dist, b.radius, cw, qf);
                if n.split {
                    if wants_merge(imp) && tree.can_merge(Tree::Colour, &id).is_ok() {
                        cx.out.ops.push(TreeOp {
                            kind: OpKind::Merge,
                            tree: Tree::Colour,
                            block: id,
                            importance: imp,
                        });
                    }
                    stack.extend(id.children().map(|c| (c, true)));
                    continue;
                }
                let sel = selected_lod(imp);
                colour_drawn.insert(id, sel.max(n.lod));
                if !visible {
                    continue;
                }
                if sel < n.lod {
                    cx.load(Tree::Colour, id, refine_importance(n.lod, imp), false);
                } else if wants_split(imp) && tree.can_split(Tree::Colour, &id).is_ok() {
                    cx.out.ops.push(TreeOp {
                        kind: OpKind::Split,
                        tree: Tree::Colour,
                        block: id,
                        importance: split_importance(imp),
                    });
                }
            }
        }
    }
    // Neighbour LODs and colour bindings.
    let colour = tree.colour();
    for d in cx.out.draw.iter_mut() {
        for (k, e) in Edge::ALL.iter().enumerate() {
            d.neighbours[k] = neighbour_lod(&info, &d.block, d.lod, *e);
        }
        d.colour = colour
            .and_then(|c| c.covering(&d.block))
            .map(|c| ColourBinding {
                block: c.id,
                lod: colour_drawn.get(&c.id).copied().unwrap_or(c.lod),
            });
    }
    cx.out
}

/// One elevation node's state in this frame's traversal.
#[derive(Clone, Copy)]
struct NodeFrame {
    visible: bool,
    split: bool,
    /// Drawn LOD (visible leaves).
    drawn: Option<u8>,
}

/// The neighbour across `edge`: the deepest traversed node covering the
/// same-level neighbour (as [`crate::tree::LinkedTree::neighbour`], every node being
/// traversed), looked up in the frame's map (one map for existence,
/// split state and drawn LOD).
fn neighbour_lod(
    info: &FastMap<BlockId, NodeFrame>,
    id: &BlockId,
    lod: u8,
    edge: Edge,
) -> Option<NeighbourLod> {
    let same = id.neighbour(edge).0;
    let (nid, nb) = (0..=same.level).rev().find_map(|l| {
        let a = same.ancestor(l);
        info.get(&a).map(|n| (a, n))
    })?;
    if nb.split {
        return None;
    }
    let nlod = nb.drawn?;
    Some(NeighbourLod {
        block: nid,
        lod: nlod,
        lod_diff: (nlod as i32 - lod as i32) + (id.level as i32 - nid.level as i32),
    })
}

impl Ctx<'_> {
    fn load(&mut self, tree: Tree, block: BlockId, importance: f64, forced: bool) {
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

    /// Trigger a split, or force the neighbours that block it (§4.3.3).
    fn trigger_split(&mut self, tree: Tree, id: BlockId, importance: f64, depth: u8) {
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
