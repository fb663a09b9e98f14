//! The reference selection: one recursive traversal of both linked trees
//! per frame, as thesis Alg. 3.1 states it (see [`super`]).

use crate::refinement::{Footprint, Kind, Refiner};
use crate::request_queue::{OpKind, TreeOp};
use crate::tree::{FastMap, FastSet, PartialTree};
use crate::visibility::View;
use planet_core::format::Tree;
use planet_core::{BlockId, Edge, Face};

use super::{colour_holds_split, Ahead, ColourBinding, Ctx, Leaf, NeighbourLod, Selection};

/// Select the LODs to draw and trigger requests for one frame, with the
/// refinement test and request order of `refiner`
/// ([`crate::refinement`]), and with `ahead`, the refiner of the view
/// predicted for when an answer asked now is applied, the prefetch for it
/// (`None`: none; see [`crate::ClientConfig::prefetch`]).
pub fn select(
    tree: &PartialTree,
    view: &View,
    refiner: &Refiner,
    ahead: Option<&Refiner>,
) -> Selection {
    let ahead = Ahead::new(refiner, ahead);
    let mut cx = Ctx {
        tree,
        out: Selection::default(),
    };
    let et = tree.elevation();
    let ew = et.width as f64;
    // Elevation, per node: this frame's state (split, or leaf with its
    // drawn LOD when visible), for neighbours.
    let mut info: FastMap<BlockId, NodeFrame> = FastMap::default();
    info.reserve(et.len());
    let mut stack: Vec<(BlockId, bool)> = Vec::with_capacity(64);
    for f in Face::ALL {
        stack.push((BlockId::root(f), true));
        while let Some((id, parent_visible)) = stack.pop() {
            let Some(n) = et.get(&id) else { continue };
            let Some(b) = n.bounds.as_ref() else { continue };
            let visible = parent_visible && view.is_visible(b);
            let (err1, err0) = (n.record.error as f64, n.child_error());
            let m = refiner.measure(Kind::Elevation, &Footprint::of(b), ew, err1, err0);
            if n.split {
                info.insert(
                    id,
                    NodeFrame {
                        split: true,
                        drawn: None,
                    },
                );
                if let Some(p) = refiner.merge(&m) {
                    if tree.can_merge(Tree::Elevation, &id).is_ok()
                        && !colour_holds_split(tree, refiner, &id, &Footprint::of(b))
                        && ahead.as_ref().is_none_or(|a| {
                            a.lets_merge(Kind::Elevation, &Footprint::of(b), ew, (err1, err0))
                        })
                    {
                        cx.out.ops.push(TreeOp {
                            kind: OpKind::Merge,
                            tree: Tree::Elevation,
                            block: id,
                            importance: p,
                        });
                    }
                }
                stack.extend(id.children().map(|c| (c, visible)));
                continue;
            }
            let d = refiner.leaf(&m, n.lod);
            let lod = d.lod.max(n.lod);
            let lod = if visible
                && lod == 1
                && n.lod == 0
                && colour_holds_split(tree, refiner, &id, &Footprint::of(b))
            {
                0
            } else {
                lod
            };
            info.insert(
                id,
                NodeFrame {
                    split: false,
                    drawn: visible.then_some(lod),
                },
            );
            if !visible {
                continue;
            }
            if d.load {
                let p = refiner.load_priority(
                    Kind::Elevation,
                    &m,
                    n.lod,
                    id.level,
                    b.centre,
                    n.record.size,
                );
                cx.load(Tree::Elevation, id, p, false);
            } else if d.split && n.can_split_data().is_ok() {
                let p = refiner.split_priority(&m, id.level, b.centre);
                cx.trigger_split(Tree::Elevation, id, p, 0);
            } else if let Some(a) = &ahead {
                let fp = Footprint::of(b);
                let leaf = Leaf::of_node(Kind::Elevation, n, &fp, ew);
                cx.prefetch(a, refiner, &m, leaf);
            }
            let error = if lod == 1 { err1 } else { err0 };
            let sse = refiner.drawn_error(&m, error);
            let area = refiner.drawn_area(&m, b.radius);
            cx.draw(id, lod, et.width, d.importance, (sse, area));
        }
    }
    // Colour tree: only the leaves some drawn block is textured with (its
    // deepest colour node) load or split.
    let mut colour_drawn: FastMap<BlockId, u8> = FastMap::default();
    let bound: FastSet<BlockId> = tree.colour().map_or_else(FastSet::default, |c| {
        cx.out
            .draw
            .iter()
            .filter_map(|d| c.covering(&d.block).filter(|n| !n.split).map(|n| n.id))
            .collect()
    });
    if let Some(ct) = tree.colour() {
        let cw = ct.width as f64;
        for f in Face::ALL {
            stack.push((BlockId::root(f), true));
            while let Some((id, _)) = stack.pop() {
                let Some(n) = ct.get(&id) else { continue };
                let Some(b) = et.get(&id).and_then(|e| e.bounds.as_ref()) else {
                    continue;
                };
                let (err1, err0) = (n.record.error as f64, n.child_error());
                let m = refiner.measure(Kind::Colour, &Footprint::of(b), cw, err1, err0);
                if n.split {
                    if let Some(p) = refiner.merge(&m) {
                        if tree.can_merge(Tree::Colour, &id).is_ok()
                            && ahead.as_ref().is_none_or(|a| {
                                a.lets_merge(Kind::Colour, &Footprint::of(b), cw, (err1, err0))
                            })
                        {
                            cx.out.ops.push(TreeOp {
                                kind: OpKind::Merge,
                                tree: Tree::Colour,
                                block: id,
                                importance: p,
                            });
                        }
                    }
                    stack.extend(id.children().map(|c| (c, true)));
                    continue;
                }
                let d = refiner.leaf(&m, n.lod);
                colour_drawn.insert(id, d.lod.max(n.lod));
                if !bound.contains(&id) {
                    continue;
                }
                if d.load {
                    let p = refiner.load_priority(
                        Kind::Colour,
                        &m,
                        n.lod,
                        id.level,
                        b.centre,
                        n.record.size,
                    );
                    cx.load(Tree::Colour, id, p, false);
                } else if d.split && n.can_split_data().is_ok() {
                    let p = refiner.split_priority(&m, id.level, b.centre);
                    cx.split_colour(id, p);
                } else if let Some(a) = &ahead {
                    let fp = Footprint::of(b);
                    cx.prefetch(a, refiner, &m, Leaf::of_node(Kind::Colour, n, &fp, cw));
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
