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
    split_importance, wants_merge, wants_split, ScreenError,
};
use crate::request_queue::{LoadRequest, OpKind, TreeOp};
use crate::tree::{Blocked, FastMap, Node, PartialTree, TreeChanges, TreeStamp};
use crate::visibility::{BlockBounds, View};
use glam::DVec3;
use planet_core::format::{ChildRef, Tree};
use planet_core::{BlockId, Edge, Face};
use std::sync::Arc;

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

/// No node (index sentinel).
const NONE: u32 = u32::MAX;
/// Not drawn (per-frame LOD sentinel).
const NOT_DRAWN: u8 = u8::MAX;

/// Per-frame inputs of one elevation node of the cached flat tree
/// (pre-order, the traversal order of [`select`]), kept small: the frame
/// loop streams through them.
#[derive(Debug, Clone, Copy)]
struct Hot {
    /// A ball holding the bounding points of the node's whole subtree.
    sub: (DVec3, f64),
    /// Bounding-box centre and footprint radius (importance, §4.2.4).
    centre: DVec3,
    radius: f64,
    parent: u32,
    split: bool,
    /// Its last LOD (leaves).
    lod: u8,
    /// `Node::can_split_data().is_ok()`.
    splittable: bool,
}

/// What the frame loop reads of a node only when it is undecided, drawn or
/// triggers something.
#[derive(Debug, Clone)]
struct Cold {
    /// A ball holding the node's bounding points and its parts' points.
    own: (DVec3, f64),
    bounds: Arc<BlockBounds>,
    /// Geometric error at LOD 1 (own record) and LOD 0 (children's records).
    err1: f64,
    err0: f64,
    record: ChildRef,
    /// Deepest node covering the same-level neighbour per edge (leaves).
    nb: [u32; 4],
    /// Deepest colour node covering this block (leaves).
    colour: Binding,
}

/// Where a drawn block's colour comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Binding {
    None,
    /// A colour leaf of the flat tree.
    Node(u32),
    /// A colour node that is split or that the traversal does not reach
    /// (only in a tree whose binding invariant is broken): its LOD is read
    /// from the tree, as [`select`] does.
    Tree(BlockId),
}

/// One colour node of the cached flat tree.
#[derive(Debug, Clone)]
struct CNode {
    id: BlockId,
    /// The elevation node with the same id (bounds and visibility, §4.4.3).
    elev: u32,
    split: bool,
    lod: u8,
    splittable: bool,
    record: ChildRef,
}

/// A ball holding two balls (slightly enlarged for rounding).
fn ball_union(a: (DVec3, f64), b: (DVec3, f64)) -> (DVec3, f64) {
    let d = (b.0 - a.0).length();
    if d + b.1 <= a.1 {
        return a;
    }
    if d + a.1 <= b.1 {
        return b;
    }
    let r = (d + a.1 + b.1) * 0.5;
    let c = if d > 0.0 {
        a.0 + (b.0 - a.0) * ((r - a.1) / d)
    } else {
        a.0
    };
    (c, r * (1.0 + 1e-9) + 1e-3)
}

/// The per-frame selection with a cache of the tree (thesis §3.6,
/// Alg. 3.1): the work per frame is a linear pass over compact arrays.
///
/// On a valid tree ([`PartialTree::validate`]) it gives exactly the
/// [`Selection`] of [`select`] (same draw list, loads and operations, in the
/// same order, bit for bit; the test `selector_matches_select` compares them
/// frame by frame while the tree grows, refines and merges), faster:
///
/// - the trees are flattened into arrays in traversal (pre-)order, with the
///   per-node inputs of importance (§3.6.2, §4.2.4), errors, split readiness
///   and records, the neighbours of every leaf (Alg. 4.1, by lookup, once)
///   and its colour binding (§4.4.1); the cache is rebuilt when nodes are
///   added or removed and patched when blocks are refined
///   ([`PartialTree::changes_since`]);
/// - visibility (§3.6.1, §4.2.1, §4.5.4) is hierarchical: a ball holding a
///   whole subtree's bounding points decides the subtree at once when it
///   lies inside the frustum and in front of the horizon (all visible) or
///   outside a plane or in the horizon's shadow (all hidden)
///   ([`View::classify_sphere`]); only undecided nodes run the exact test on
///   their bounding points ([`View::is_visible_hinted`]).
#[derive(Debug, Default)]
pub struct Selector {
    stamp: Option<TreeStamp>,
    hot: Vec<Hot>,
    cold: Vec<Cold>,
    ids: Vec<BlockId>,
    cnodes: Vec<CNode>,
    eindex: FastMap<BlockId, u32>,
    cindex: FastMap<BlockId, u32>,
    /// Per node: the bounding point last found in front of the horizon.
    hint: Vec<u32>,
    /// Per node: a bounding point that proved it visible last time.
    witness: Vec<Option<DVec3>>,
    /// Per frame: 0 hidden, 1 visible, 2 visible with the whole subtree.
    state: Vec<u8>,
    /// Per frame: the drawn LOD of visible leaves.
    drawn: Vec<u8>,
    cdrawn: Vec<u8>,
    draw_idx: Vec<u32>,
    last_draw: usize,
    rebuilds: u64,
}

impl Selector {
    /// An empty cache (built on the first frame).
    pub fn new() -> Selector {
        Selector::default()
    }

    /// Times the cache was rebuilt from the tree (statistics and tests).
    pub fn rebuilds(&self) -> u64 {
        self.rebuilds
    }

    fn update(&mut self, tree: &PartialTree) {
        let changes = match &self.stamp {
            None => TreeChanges::Structure,
            Some(s) => tree.changes_since(s),
        };
        match changes {
            TreeChanges::Structure => self.rebuild(tree),
            TreeChanges::Refined(list) => {
                for (kind, id) in list {
                    self.patch(tree, *kind, id);
                }
            }
        }
        self.stamp = Some(tree.stamp());
    }

    fn patch(&mut self, tree: &PartialTree, kind: Tree, id: &BlockId) {
        let Some(n) = tree.tree(kind).and_then(|t| t.get(id)) else {
            return;
        };
        match kind {
            Tree::Elevation => {
                if let Some(&i) = self.eindex.get(id) {
                    let h = &mut self.hot[i as usize];
                    h.split = n.split;
                    h.lod = n.lod;
                    h.splittable = n.can_split_data().is_ok();
                    self.cold[i as usize].err0 = child_error(n);
                }
            }
            Tree::Colour => {
                if let Some(&i) = self.cindex.get(id) {
                    let c = &mut self.cnodes[i as usize];
                    c.split = n.split;
                    c.lod = n.lod;
                    c.splittable = n.can_split_data().is_ok();
                }
            }
        }
    }

    fn rebuild(&mut self, tree: &PartialTree) {
        self.rebuilds += 1;
        // Keep the hints of nodes that stay (with the same bounds).
        let mut old: FastMap<BlockId, (Arc<BlockBounds>, u32, Option<DVec3>)> = FastMap::default();
        for (k, id) in self.ids.iter().enumerate() {
            if self.hint[k] != 0 || self.witness[k].is_some() {
                old.insert(
                    *id,
                    (self.cold[k].bounds.clone(), self.hint[k], self.witness[k]),
                );
            }
        }
        self.hot.clear();
        self.cold.clear();
        self.ids.clear();
        self.hint.clear();
        self.witness.clear();
        self.cnodes.clear();
        self.eindex.clear();
        self.cindex.clear();
        let et = tree.elevation();
        let mut stack: Vec<(BlockId, u32)> = Vec::with_capacity(64);
        for f in Face::ALL {
            stack.push((BlockId::root(f), NONE));
            while let Some((id, parent)) = stack.pop() {
                let Some(n) = et.get(&id) else { continue };
                let Some(b) = n.bounds.as_ref() else { continue };
                let i = self.hot.len() as u32;
                let own = b.parts.iter().fold((b.centre, b.sphere_radius), |s, p| {
                    ball_union(s, (p.centre, p.sphere_radius))
                });
                self.hot.push(Hot {
                    sub: own,
                    centre: b.centre,
                    radius: b.radius,
                    parent,
                    split: n.split,
                    lod: n.lod,
                    splittable: n.can_split_data().is_ok(),
                });
                self.cold.push(Cold {
                    own,
                    bounds: b.clone(),
                    err1: n.record.error as f64,
                    err0: child_error(n),
                    record: n.record,
                    nb: [NONE; 4],
                    colour: Binding::None,
                });
                self.ids.push(id);
                let (hint, witness) = match old.get(&id) {
                    Some((ob, h, w)) if Arc::ptr_eq(ob, b) => (*h, *w),
                    _ => (0, None),
                };
                self.hint.push(hint);
                self.witness.push(witness);
                self.eindex.insert(id, i);
                if n.split {
                    stack.extend(id.children().map(|c| (c, i)));
                }
            }
        }
        // Subtree balls, children (later in pre-order) first.
        for i in (1..self.hot.len()).rev() {
            let (p, s) = (self.hot[i].parent, self.hot[i].sub);
            if p != NONE {
                let h = &mut self.hot[p as usize];
                h.sub = ball_union(h.sub, s);
            }
        }
        if let Some(ct) = tree.colour() {
            for f in Face::ALL {
                stack.push((BlockId::root(f), NONE));
                while let Some((id, _)) = stack.pop() {
                    let Some(n) = ct.get(&id) else { continue };
                    let Some(&elev) = self.eindex.get(&id) else {
                        continue;
                    };
                    self.cindex.insert(id, self.cnodes.len() as u32);
                    self.cnodes.push(CNode {
                        id,
                        elev,
                        split: n.split,
                        lod: n.lod,
                        splittable: n.can_split_data().is_ok(),
                        record: n.record,
                    });
                    if n.split {
                        stack.extend(id.children().map(|c| (c, NONE)));
                    }
                }
            }
        }
        // Neighbours and colour bindings of the leaves.
        let colour = tree.colour();
        for i in 0..self.hot.len() {
            if self.hot[i].split {
                continue;
            }
            let id = self.ids[i];
            let mut nb = [NONE; 4];
            for (k, e) in Edge::ALL.iter().enumerate() {
                let same = id.neighbour(*e).0;
                nb[k] = (0..=same.level)
                    .rev()
                    .find_map(|l| self.eindex.get(&same.ancestor(l)).copied())
                    .unwrap_or(NONE);
            }
            let binding = match colour.and_then(|c| c.covering(&id)) {
                None => Binding::None,
                Some(c) => match self.cindex.get(&c.id) {
                    Some(&j) if !self.cnodes[j as usize].split => Binding::Node(j),
                    _ => Binding::Tree(c.id),
                },
            };
            let c = &mut self.cold[i];
            c.nb = nb;
            c.colour = binding;
        }
    }

    /// Select the LODs to draw and trigger requests for one frame: the same
    /// result as [`select`]`(tree, view, qf)`.
    pub fn select(&mut self, tree: &PartialTree, view: &View, qf: f64) -> Selection {
        self.update(tree);
        let mut cx = Ctx {
            tree,
            out: Selection {
                draw: Vec::with_capacity(self.last_draw),
                ..Selection::default()
            },
        };
        let et = tree.elevation();
        let ew = et.width as f64;
        let eye = view.camera.eye;
        let sse = ScreenError::new(view.camera.viewport_height_px, view.camera.fov_y);
        let n = self.hot.len();
        self.state.clear();
        self.state.resize(n, 0);
        self.drawn.clear();
        self.drawn.resize(n, NOT_DRAWN);
        self.draw_idx.clear();
        for (i, h) in self.hot.iter().enumerate() {
            let st = match h.parent {
                NONE => 1,
                p => self.state[p as usize],
            };
            let st = match st {
                0 => 0,
                2 => 2,
                _ => match view.classify_sphere(h.sub.0, h.sub.1) {
                    Some(true) => 2,
                    Some(false) => 0,
                    None => {
                        let c = &self.cold[i];
                        match view.classify_sphere(c.own.0, c.own.1) {
                            Some(v) => v as u8,
                            None => exact_visible(view, c, &mut self.hint[i], &mut self.witness[i])
                                as u8,
                        }
                    }
                },
            };
            self.state[i] = st;
            if h.split {
                let imp = importance(block_distance(eye, h.centre, h.radius), h.radius, ew, qf);
                if wants_merge(imp) && tree.can_merge(Tree::Elevation, &self.ids[i]).is_ok() {
                    cx.out.ops.push(TreeOp {
                        kind: OpKind::Merge,
                        tree: Tree::Elevation,
                        block: self.ids[i],
                        importance: imp,
                    });
                }
                continue;
            }
            if st == 0 {
                continue;
            }
            let id = self.ids[i];
            let dist = block_distance(eye, h.centre, h.radius);
            let imp = importance(dist, h.radius, ew, qf);
            let sel = selected_lod(imp);
            let lod = sel.max(h.lod);
            self.drawn[i] = lod;
            if sel < h.lod {
                cx.out.loads.push(LoadRequest {
                    tree: Tree::Elevation,
                    block: id,
                    record: self.cold[i].record,
                    importance: refine_importance(h.lod, imp),
                    forced: false,
                });
            } else if wants_split(imp) && h.splittable {
                cx.trigger_split(Tree::Elevation, id, split_importance(imp), 0);
            }
            let c = &self.cold[i];
            let error = if lod == 1 { c.err1 } else { c.err0 };
            let w = if lod == 0 { et.width } else { et.width / 2 } as u64;
            cx.out.triangles += 2 * w * w;
            cx.out.draw.push(DrawBlock {
                block: id,
                lod,
                neighbours: [None; 4],
                colour: None,
                importance: imp,
                screen_error: sse.of(error, dist.max(view.near)),
            });
            self.draw_idx.push(i as u32);
        }
        // Colour tree.
        self.cdrawn.clear();
        self.cdrawn.resize(self.cnodes.len(), NOT_DRAWN);
        if let Some(ct) = tree.colour() {
            let cw = ct.width as f64;
            for (j, c) in self.cnodes.iter().enumerate() {
                let h = &self.hot[c.elev as usize];
                let visible = self.state[c.elev as usize] != 0;
                let imp = importance(block_distance(eye, h.centre, h.radius), h.radius, cw, qf);
                if c.split {
                    if wants_merge(imp) && tree.can_merge(Tree::Colour, &c.id).is_ok() {
                        cx.out.ops.push(TreeOp {
                            kind: OpKind::Merge,
                            tree: Tree::Colour,
                            block: c.id,
                            importance: imp,
                        });
                    }
                    continue;
                }
                let sel = selected_lod(imp);
                self.cdrawn[j] = sel.max(c.lod);
                if !visible {
                    continue;
                }
                if sel < c.lod {
                    cx.out.loads.push(LoadRequest {
                        tree: Tree::Colour,
                        block: c.id,
                        record: c.record,
                        importance: refine_importance(c.lod, imp),
                        forced: false,
                    });
                } else if wants_split(imp)
                    && c.splittable
                    && tree.can_split(Tree::Colour, &c.id).is_ok()
                {
                    cx.out.ops.push(TreeOp {
                        kind: OpKind::Split,
                        tree: Tree::Colour,
                        block: c.id,
                        importance: split_importance(imp),
                    });
                }
            }
        }
        // Neighbour LODs and colour bindings (split and hidden nodes have
        // no drawn LOD).
        for (d, &i) in cx.out.draw.iter_mut().zip(&self.draw_idx) {
            let c = &self.cold[i as usize];
            for (k, &j) in c.nb.iter().enumerate() {
                if j == NONE {
                    continue;
                }
                let nlod = self.drawn[j as usize];
                if nlod == NOT_DRAWN {
                    continue;
                }
                let nid = self.ids[j as usize];
                d.neighbours[k] = Some(NeighbourLod {
                    block: nid,
                    lod: nlod,
                    lod_diff: (nlod as i32 - d.lod as i32)
                        + (d.block.level as i32 - nid.level as i32),
                });
            }
            d.colour = match c.colour {
                Binding::None => None,
                Binding::Node(j) => {
                    let cn = &self.cnodes[j as usize];
                    Some(ColourBinding {
                        block: cn.id,
                        lod: self.cdrawn[j as usize],
                    })
                }
                Binding::Tree(id) => {
                    tree.colour()
                        .and_then(|t| t.get(&id))
                        .map(|c| ColourBinding {
                            block: c.id,
                            lod: c.lod,
                        })
                }
            };
        }
        self.last_draw = cx.out.draw.len();
        cx.out
    }
}

/// [`View::is_visible`] of a node: by its witness point when that
/// still proves it visible, else by the full test (which finds a new
/// witness when it can).
fn exact_visible(view: &View, c: &Cold, hint: &mut u32, witness: &mut Option<DVec3>) -> bool {
    let b = &*c.bounds;
    if b.parts.is_empty() {
        if let Some(p) = *witness {
            if view.planet_in_view()
                && view.sphere_in_cone(b.centre, b.sphere_radius)
                && view.point_witnesses_visible(p)
            {
                return true;
            }
        }
    }
    let v = view.is_visible_hinted(b, hint);
    *witness = None;
    if v && b.parts.is_empty() {
        if let Some(&p) = b.points.get(*hint as usize) {
            if view.point_witnesses_visible(p) {
                *witness = Some(p);
            }
        }
    }
    v
}

/// Largest error of the children's records (the error at LOD 0), 0 without.
fn child_error(n: &Node) -> f64 {
    n.child_refs.as_ref().map_or(0.0, |c| {
        c.iter().map(|r| r.error as f64).fold(0.0, f64::max)
    })
}
