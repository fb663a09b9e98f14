//! The cached selection: [`Selector`], the traversal of [`super::select`]
//! over a flat, incrementally patched copy of the trees (see [`super`]).

use crate::refinement::{Footprint, Kind, Measure, Refiner};
use crate::request_queue::{LoadRequest, OpKind, TreeOp};
use crate::tree::{ChangeKind, LinkedTree, PartialTree, TreeChange, TreeChanges, TreeStamp};
use crate::visibility::{BlockBounds, View};
use glam::DVec3;
use planet_core::format::{ChildRef, Tree};
use planet_core::{BlockId, Edge, Face};
use std::sync::Arc;

use super::{
    colour_holds_split, lod0_block, Ahead, ColourBinding, Ctx, DrawBlock, Leaf, NeighbourLod,
    Selection,
};

/// No node (index sentinel).
const NONE: u32 = u32::MAX;
/// Not drawn (per-frame LOD sentinel).
const NOT_DRAWN: u8 = u8::MAX;

/// Per-frame inputs of one elevation node of the cached flat tree
/// (pre-order, the traversal order of [`select`](super::select)), kept small: the frame
/// loop streams through them.
#[derive(Debug, Clone, Copy)]
struct Hot {
    /// A ball holding the bounding points of the node's whole subtree.
    sub: (DVec3, f64),
    parent: u32,
    /// Its [`Cold`] slot (stable while the node stays).
    slot: u32,
    split: bool,
    /// Its last LOD (leaves).
    lod: u8,
    /// `Node::can_split_data().is_ok()`.
    splittable: bool,
}

/// What the frame loop reads of a node only when it is undecided, drawn or
/// triggers something, with its visibility witnesses (§4.2.1). Kept in a
/// stable slot ([`Hot::slot`]) that a splice (§3.4.1) does not move.
#[derive(Debug, Clone)]
struct Cold {
    /// The bounding point last found in front of the horizon (blocks with
    /// parts: the part of the witness).
    hint: u32,
    /// A bounding point that proved the node visible last time.
    witness: Option<DVec3>,
    /// A ball holding the node's bounding points and its parts' points.
    own: (DVec3, f64),
    /// The bounds' [`BlockBounds::top_radius`].
    top: f64,
    bounds: Arc<BlockBounds>,
    /// Whether the bounds have parts.
    parts: bool,
    /// Geometric error at LOD 1 (own record) and LOD 0 (children's records).
    err1: f64,
    err0: f64,
    /// Where the block is, for its distance ([`Refiner::measure`]).
    fp: Footprint,
    record: ChildRef,
}

/// Where a drawn block's colour comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Binding {
    None,
    /// A colour leaf of the flat tree.
    Node(u32),
    /// A colour node that is split or that the traversal does not reach
    /// (only in a tree whose binding invariant is broken): its LOD is read
    /// from the tree, as [`select`](super::select) does.
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
    /// Geometric error at LOD 0 (children's records).
    err0: f64,
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
/// [`Selection`] of [`select`](super::select) (same draw list, loads and operations, in the
/// same order, bit for bit; `client/tests/selector.rs` compares them frame
/// by frame while the tree grows, is refined, splits and merges, and the
/// camera moves, turns and stands still), faster:
///
/// - the trees are flattened into arrays in traversal (pre-)order with the
///   per-node inputs of importance (§3.6.2, §4.2.4), errors, split
///   readiness and records; the neighbours of every node (Alg. 4.1,
///   top-down from the parent's) and the colour binding of every leaf
///   (§4.4.1) follow from the flat links. The tree's change log
///   ([`PartialTree::changes_since`]) patches refined blocks and splices
///   split and merged ones in (re-reading only the changed subtrees); the
///   arrays are rebuilt (each tree node read once) only for another tree
///   or when the log no longer reaches back far enough;
/// - visibility (§3.6.1, §4.2.1, §4.5.4) is hierarchical: a ball holding a
///   whole subtree's bounding points decides the subtree at once when it
///   lies inside the frustum and in front of the horizon (all visible) or
///   outside a plane or in the horizon's shadow (all hidden)
///   ([`View::classify_sphere`]); an undecided block is first tried with
///   the bounding point that proved it visible last time
///   ([`View::point_witnesses_visible`]), then with the exact test;
/// - importance (Eq. 3.2–3.3) and the screen-space error depend on the eye,
///   not on the view direction: they are kept per node while the eye,
///   quality factor, near distance and viewport stay the same (a camera
///   turning on the spot recomputes only visibility); hidden leaves skip
///   them, and split blocks take the logarithm only where they may merge;
/// - a split block found surely kept ([`Refiner::keep_slack`]), and a
///   colour leaf at its finest whose drawn LOD surely stays
///   ([`Refiner::finest_colour_slack`]), are not asked again until the eye
///   has travelled their slack (an odometer of the eye's path), so that a
///   moving frame reads nothing of them but their memo; the rest of what a
///   node keeps stays untouched, and is moved back into pre-order when
///   splices have scattered it.
#[derive(Debug, Default)]
pub struct Selector {
    stamp: Option<TreeStamp>,
    hot: Vec<Hot>,
    /// Cold slots ([`Hot::slot`]) and the free ones.
    cold: Vec<Cold>,
    free: Vec<u32>,
    /// Nodes placed since the slots were last in pre-order
    /// ([`Selector::compact_cold`]).
    scattered: usize,
    ids: Vec<BlockId>,
    cnodes: Vec<CNode>,
    /// Per elevation node: children (by child index), the deepest nodes
    /// covering the same-level neighbours (`Edge::ALL` order), and the
    /// colour node with the same id.
    children: Vec<[u32; 4]>,
    nb: Vec<[u32; 4]>,
    col_of_elev: Vec<u32>,
    /// Per elevation node: the deepest colour node covering it (leaves;
    /// split nodes `Binding::None`), in pre-order so that a splice
    /// rewrites it in one sweep ([`Selector::bind_colours`]).
    bind: Vec<Binding>,
    roots: [u32; 6],
    /// Per frame: 0 hidden, 1 visible, 2 visible with the whole subtree.
    state: Vec<u8>,
    /// Per frame: the drawn LOD of visible leaves.
    drawn: Vec<u8>,
    cdrawn: Vec<u8>,
    /// Per frame, per colour node: some drawn block is textured with it.
    cbound: Vec<bool>,
    /// Per drawn block: its elevation node and colour binding.
    draw_idx: Vec<(u32, Binding)>,
    /// Per frame: the colour bindings read from the tree
    /// ([`Binding::Tree`]), for [`Selector::draws_lod0`].
    tree_bound: Vec<ColourBinding>,
    /// A draw list handed back by the caller ([`Selector::recycle`]),
    /// reused so that a frame does not allocate (and fault in) a fresh one.
    spare_draw: Vec<DrawBlock>,
    last_draw: usize,
    rebuilds: u64,
    splices: u64,
    /// Scratch space (traversal stack, per-node indices).
    stack: Vec<(BlockId, u32)>,
    scratch: Vec<u32>,
    spare: Spare,
    /// Importance and screen-space error per elevation node and importance
    /// per colour node, valid while the inputs besides the node are the
    /// same ([`MemoKey`]; they do not depend on the view direction).
    memo_key: Option<MemoKey>,
    memo_gen: u64,
    memo: Vec<Memo>,
    cmemo: Vec<CMemo>,
    odometer: Odometer,
}

/// Emptied buffers of the arrays replaced by the last splice, reused by the
/// next one (no allocation, no fresh pages per frame).
#[derive(Debug, Default)]
struct Spare {
    ids: Vec<BlockId>,
    hot: Vec<Hot>,
    nb: Vec<[u32; 4]>,
    memo: Vec<Memo>,
    col: Vec<u32>,
    cnodes: Vec<CNode>,
    cmemo: Vec<CMemo>,
    children: Vec<[u32; 4]>,
    flags: Vec<bool>,
    cflags: Vec<bool>,
    remap: Vec<u32>,
    from_old: Vec<u32>,
}

impl Spare {
    fn clear(&mut self) {
        self.ids.clear();
        self.hot.clear();
        self.nb.clear();
        self.memo.clear();
        self.col.clear();
        self.cnodes.clear();
        self.cmemo.clear();
        self.children.clear();
        self.flags.clear();
        self.cflags.clear();
        self.remap.clear();
        self.from_old.clear();
    }
}

/// What a node's [`Measure`] and screen-space error depend on besides the
/// node: eye position, viewport height and field of view, and the refiner's
/// policy, tolerance, quality factor and near distance (bit patterns, so any
/// change counts).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct MemoKey([u64; 9]);

impl MemoKey {
    fn new(view: &View, refiner: &Refiner) -> MemoKey {
        let e = view.camera.eye;
        let [a, b, c, d] = refiner.memo_key();
        MemoKey([
            e.x.to_bits(),
            e.y.to_bits(),
            e.z.to_bits(),
            view.camera.viewport_height_px.to_bits(),
            view.camera.fov_y.to_bits(),
            a,
            b,
            c,
            d,
        ])
    }
}

/// Memoised per-node values (valid when `gen` is the selector's); a block
/// changing between leaf and split, or refined, is re-read with a fresh
/// entry.
#[derive(Debug, Clone, Copy, Default)]
struct Memo {
    gen: u64,
    m: Measure,
    /// The LOD `sse` was computed for (`NOT_DRAWN`: none).
    sse_lod: u8,
    sse: f64,
    keep: Keep,
}

/// A colour node's [`Memo`] (no drawn error: a colour leaf's drawn LOD is
/// all that is drawn of it). `keep` holds for a split node (surely kept)
/// or for a leaf at its finest, whose drawn LOD `lod` surely stays
/// ([`Refiner::finest_colour_slack`]).
#[derive(Debug, Clone, Copy, Default)]
struct CMemo {
    gen: u64,
    m: Measure,
    keep: Keep,
    lod: u8,
}

/// A split node found surely kept ([`Refiner::keep_slack`]), or a colour
/// leaf at its finest found keeping its drawn LOD
/// ([`Refiner::finest_colour_slack`]), at an earlier eye: it still is
/// while the selector's odometer ([`Odometer`]) reads below `until` and the
/// near distance is below `within`, and the frame loop then reads nothing
/// else of it (its [`Cold`] slot, which would cost a cache miss, stays
/// untouched).
#[derive(Debug, Clone, Copy)]
struct Keep {
    until: f64,
    within: f64,
}

impl Default for Keep {
    fn default() -> Keep {
        Keep {
            until: f64::NEG_INFINITY,
            within: 0.0,
        }
    }
}

impl Keep {
    fn holds(&self, odo: f64, refiner: &Refiner) -> bool {
        odo < self.until && refiner.near() < self.within
    }

    /// [`Refiner::keep_slack`] asked at odometer reading `odo`: remember
    /// (if kept) how far the eye may travel before the node must be asked
    /// again. The margin (10⁻⁹ of the slack and 1 mm) covers the rounding
    /// of the odometer's sums and of the upper distance. Whether it is
    /// kept now.
    fn refresh(&mut self, odo: f64, slack: Option<(f64, f64)>) -> bool {
        *self = match slack {
            Some((within, slack)) => Keep {
                until: odo + slack * (1.0 - 1e-9) - 1e-3,
                within,
            },
            None => Keep::default(),
        };
        slack.is_some()
    }
}

/// The length of the path the eye has travelled between frames (thesis
/// §3.6's frame-to-frame coherence): the eye's distance to anything moves
/// by at most that much, so a bound found at an earlier eye holds while
/// the path since is shorter than its slack ([`Keep`]). Reset (with every
/// [`Keep`]) when a step is not finite, when what the bounds depend on
/// besides the eye changes ([`Odometer::key`]), and after
/// [`Odometer::RESET_M`], so that its sums stay exact to far below a
/// millimetre.
#[derive(Debug, Clone, Copy, Default)]
struct Odometer {
    len: f64,
    eye: Option<DVec3>,
    key: Option<[u64; 5]>,
}

impl Odometer {
    const RESET_M: f64 = 1e6;

    /// What [`Refiner::keep_slack`] and [`Refiner::finest_colour_slack`]
    /// depend on besides the node and the eye:
    /// viewport height, field of view and the refiner's
    /// [`Refiner::memo_key`] but the near distance (which [`Keep::holds`]
    /// checks every frame).
    fn key(view: &View, refiner: &Refiner) -> [u64; 5] {
        let [tol, _near, policy, qf] = refiner.memo_key();
        [
            view.camera.viewport_height_px.to_bits(),
            view.camera.fov_y.to_bits(),
            tol,
            policy,
            qf,
        ]
    }

    /// Advance to `eye`; `false` when every [`Keep`] must be forgotten.
    fn step(&mut self, eye: DVec3, key: [u64; 5]) -> bool {
        let s = self.eye.map_or(f64::INFINITY, |p| (eye - p).length());
        self.eye = Some(eye);
        let same = self.key == Some(key);
        self.key = Some(key);
        if same && s.is_finite() && self.len + s < Self::RESET_M {
            self.len += s;
            true
        } else {
            self.len = 0.0;
            false
        }
    }
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

    /// Times splits and merges were applied to the cache without a rebuild
    /// (statistics and tests).
    pub fn splices(&self) -> u64 {
        self.splices
    }

    fn update(&mut self, tree: &PartialTree) {
        let changes = match &self.stamp {
            None => TreeChanges::Structure,
            Some(s) => tree.changes_since(s),
        };
        match changes {
            TreeChanges::Structure => self.rebuild(tree),
            TreeChanges::Log(list) => {
                if list.iter().any(|c| c.kind != ChangeKind::Refined) {
                    self.splice(tree, list);
                }
                // A patch reads the node's current state, so refines logged
                // before a split or merge are applied after the splice.
                for c in list.iter().filter(|c| c.kind == ChangeKind::Refined) {
                    self.patch(tree, c.tree, &c.block);
                }
            }
        }
        self.stamp = Some(tree.stamp());
    }

    /// The deepest node of the flat tree containing `target`, descending
    /// from node `from` (which contains it): what [`select`](super::select)'s lookups find
    /// among the traversed nodes.
    fn covering_from(&self, mut from: u32, target: &BlockId) -> u32 {
        if from as usize >= self.ids.len() {
            return NONE;
        }
        loop {
            let level = self.ids[from as usize].level;
            if !self.hot[from as usize].split || level >= target.level {
                return from;
            }
            let a = target.ancestor(level + 1);
            let c = self.children[from as usize][a.child_index()];
            if c == NONE || self.ids[c as usize] != a {
                return from;
            }
            from = c;
        }
    }

    /// The index of elevation node `id`, if the traversal reaches it.
    fn find(&self, id: &BlockId) -> Option<usize> {
        let c = self.covering_from(self.roots[id.face.index() as usize], id);
        (c != NONE && self.ids[c as usize] == *id).then_some(c as usize)
    }

    fn patch(&mut self, tree: &PartialTree, kind: Tree, id: &BlockId) {
        let Some(n) = tree.tree(kind).and_then(|t| t.get(id)) else {
            return;
        };
        let Some(i) = self.find(id) else { return };
        match kind {
            Tree::Elevation => {
                let h = &mut self.hot[i];
                h.split = n.split;
                h.lod = n.lod;
                h.splittable = n.can_split_data().is_ok();
                self.cold[h.slot as usize].err0 = n.child_error();
                // Generation 0 is never valid: the measure (LOD 0's error
                // came with the record) and the error are recomputed, and
                // what was kept is forgotten.
                self.memo[i] = Memo {
                    sse_lod: NOT_DRAWN,
                    ..Memo::default()
                };
            }
            Tree::Colour => {
                let j = self.col_of_elev[i];
                if j != NONE {
                    let c = &mut self.cnodes[j as usize];
                    c.split = n.split;
                    c.lod = n.lod;
                    c.splittable = n.can_split_data().is_ok();
                    c.err0 = n.child_error();
                    self.cmemo[j as usize] = CMemo::default();
                }
            }
        }
    }

    /// Append an elevation node (pre-order: its parent is already in) and
    /// link it to its parent (or as its face's root).
    fn push_node(&mut self, id: BlockId, mut hot: Hot, cold: Cold, memo: Memo) -> u32 {
        let i = self.hot.len() as u32;
        match hot.parent {
            NONE => self.roots[id.face.index() as usize] = i,
            p => self.children[p as usize][id.child_index()] = i,
        }
        self.scattered += 1;
        hot.slot = match self.free.pop() {
            Some(s) => {
                self.cold[s as usize] = cold;
                s
            }
            None => {
                self.cold.push(cold);
                (self.cold.len() - 1) as u32
            }
        };
        self.hot.push(hot);
        self.ids.push(id);
        self.children.push([NONE; 4]);
        self.memo.push(memo);
        i
    }

    /// Append the elevation subtree of `root` read from the tree
    /// (pre-order, one hash lookup per node), under node `parent`, with
    /// every subtree ball set to the node's own ball.
    fn push_subtree(&mut self, et: &LinkedTree, root: BlockId, parent: u32) {
        let mut stack = std::mem::take(&mut self.stack);
        stack.clear();
        stack.push((root, parent));
        while let Some((id, parent)) = stack.pop() {
            let Some(n) = et.get(&id) else { continue };
            let Some(b) = n.bounds.as_ref() else { continue };
            let own = b.parts.iter().fold((b.centre, b.sphere_radius), |s, p| {
                ball_union(s, (p.centre, p.sphere_radius))
            });
            let hot = Hot {
                sub: own,
                parent,
                slot: NONE,
                split: n.split,
                lod: n.lod,
                splittable: n.can_split_data().is_ok(),
            };
            let cold = Cold {
                hint: 0,
                witness: None,
                own,
                top: b.top_radius,
                bounds: b.clone(),
                parts: !b.parts.is_empty(),
                err1: n.record.error as f64,
                err0: n.child_error(),
                fp: Footprint::of(b),
                record: n.record,
            };
            let i = self.push_node(id, hot, cold, Memo::default());
            if n.split {
                stack.extend(id.children().map(|c| (c, i)));
            }
        }
        self.stack = stack;
    }

    /// Subtree balls of the nodes `range` (a subtree in pre-order whose
    /// balls are the nodes' own), children (later in pre-order) first.
    fn union_subtree_balls(&mut self, range: std::ops::Range<usize>) {
        for i in (range.start + 1..range.end).rev() {
            let (p, s) = (self.hot[i].parent, self.hot[i].sub);
            if p != NONE {
                let h = &mut self.hot[p as usize];
                h.sub = ball_union(h.sub, s);
            }
        }
    }

    /// The deepest node covering the same-level neighbour of node `i`
    /// across `Edge::ALL[k]` (Alg. 4.1 top-down): it is `i`'s sibling or
    /// found from its parent's neighbour (`self.nb` holds the parent's).
    fn neighbour_of(&self, i: usize, k: usize) -> u32 {
        let id = self.ids[i];
        let p = self.hot[i].parent;
        let e = Edge::ALL[k];
        let same = id.neighbour(e).0;
        let start = match same.parent() {
            Some(sp) if p != NONE && sp == self.ids[p as usize] => p,
            Some(sp) if p != NONE && self.ids[p as usize].neighbour(e).0 == sp => {
                self.nb[p as usize][k]
            }
            _ => self.roots[same.face.index() as usize],
        };
        self.covering_from(start, &same)
    }

    /// Colour bindings: the deepest colour node on each leaf's elevation
    /// path (every colour node has its elevation node, §4.4.1).
    fn bind_colours(&mut self) {
        let n = self.hot.len();
        let mut cov = std::mem::take(&mut self.scratch);
        cov.clear();
        cov.resize(n, NONE);
        self.bind.clear();
        self.bind.resize(n, Binding::None);
        for i in 0..n {
            let j = self.col_of_elev[i];
            cov[i] = if j != NONE {
                j
            } else {
                match self.hot[i].parent {
                    NONE => NONE,
                    p => cov[p as usize],
                }
            };
            self.bind[i] = if self.hot[i].split {
                Binding::None
            } else {
                match cov[i] {
                    NONE => Binding::None,
                    j if self.cnodes[j as usize].split => Binding::Tree(self.cnodes[j as usize].id),
                    j => Binding::Node(j),
                }
            };
        }
        self.scratch = cov;
    }

    /// Move the [`Cold`] slots back into pre-order (node `i` in slot `i`)
    /// and drop the free ones. A splice places re-read nodes in freed slots
    /// or at the end, out of order; once many are (more than 1/16 of the
    /// nodes), the frame loop, which reads the slots of visible leaves in
    /// pre-order, would miss the cache on more of them than the moves cost.
    fn compact_cold(&mut self) {
        let n = self.hot.len();
        // The node in each slot (`NONE`: free).
        let mut owner = std::mem::take(&mut self.scratch);
        owner.clear();
        owner.resize(self.cold.len(), NONE);
        for (i, h) in self.hot.iter().enumerate() {
            owner[h.slot as usize] = i as u32;
        }
        // Slots below `i` hold nodes below `i`, so node `i`'s is at `i` or
        // after: swap it down, and follow the node that was at `i`.
        for i in 0..n {
            let s = self.hot[i].slot as usize;
            if s != i {
                self.cold.swap(i, s);
                let j = owner[i];
                if j != NONE {
                    self.hot[j as usize].slot = s as u32;
                }
                owner[s] = j;
                owner[i] = i as u32;
                self.hot[i].slot = i as u32;
            }
        }
        self.cold.truncate(n);
        self.free.clear();
        self.scattered = 0;
        self.scratch = owner;
    }

    fn clear(&mut self) {
        self.hot.clear();
        self.ids.clear();
        self.children.clear();
        self.nb.clear();
        self.col_of_elev.clear();
        self.memo.clear();
        self.cmemo.clear();
        self.cnodes.clear();
        self.roots = [NONE; 6];
    }

    /// Flatten the trees (pre-order, as [`select`](super::select) traverses them). One
    /// hash lookup per node (the tree's own map); neighbours, colour nodes
    /// and bindings follow from the flat parent/children links.
    fn rebuild(&mut self, tree: &PartialTree) {
        self.rebuilds += 1;
        let old_ids = std::mem::take(&mut self.ids);
        let old_hot = std::mem::take(&mut self.hot);
        let old_cold = std::mem::take(&mut self.cold);
        self.clear();
        self.free.clear();
        let et = tree.elevation();
        for f in Face::ALL {
            self.push_subtree(et, BlockId::root(f), NONE);
        }
        let n = self.hot.len();
        // Keep the hints and witnesses of nodes that stay (same bounds).
        for (k, id) in old_ids.iter().enumerate() {
            let oc = &old_cold[old_hot[k].slot as usize];
            if oc.hint == 0 && oc.witness.is_none() {
                continue;
            }
            if let Some(i) = self.find(id) {
                let c = &mut self.cold[self.hot[i].slot as usize];
                if Arc::ptr_eq(&c.bounds, &oc.bounds) {
                    c.hint = oc.hint;
                    c.witness = oc.witness;
                }
            }
        }
        // Read in pre-order into an empty slot array: in order.
        self.scattered = 0;
        self.union_subtree_balls(0..n);
        for i in 0..n {
            let nb = std::array::from_fn(|k| self.neighbour_of(i, k));
            self.nb.push(nb);
        }
        // Colour nodes, with their elevation nodes (same ids).
        self.col_of_elev.resize(n, NONE);
        if let Some(ct) = tree.colour() {
            let mut stack: Vec<(BlockId, u32)> = Vec::with_capacity(64);
            for f in Face::ALL {
                stack.push((BlockId::root(f), self.roots[f.index() as usize]));
                while let Some((id, elev)) = stack.pop() {
                    let Some(cn) = ct.get(&id) else { continue };
                    if elev == NONE {
                        continue;
                    }
                    self.col_of_elev[elev as usize] = self.cnodes.len() as u32;
                    self.cmemo.push(CMemo::default());
                    self.cnodes.push(CNode {
                        id,
                        elev,
                        split: cn.split,
                        lod: cn.lod,
                        splittable: cn.can_split_data().is_ok(),
                        record: cn.record,
                        err0: cn.child_error(),
                    });
                    if cn.split {
                        let ec = self.children[elev as usize];
                        stack.extend((0..4).map(|k| {
                            let c = id.child(k);
                            let e = ec[k];
                            let e = if e != NONE && self.ids[e as usize] == c {
                                e
                            } else {
                                NONE
                            };
                            (c, e)
                        }));
                    }
                }
            }
        }
        self.bind_colours();
    }

    /// Apply logged splits and merges to the flat arrays (thesis §3.4.1)
    /// without reading the unchanged nodes from the tree: one pass over the
    /// old arrays in pre-order copies every node outside a changed subtree
    /// (with its memoised values; its bounds, records and witnesses stay in
    /// their stable [`Cold`] slot, so the copy moves about half the bytes)
    /// and re-reads each changed node's subtree from the tree in its place,
    /// reusing the slots of the removed nodes; then
    ///
    /// - subtree balls are recomputed in the re-read subtrees and up their
    ///   ancestor chains;
    /// - a kept node keeps its neighbours (Alg. 4.1) unless one of them was
    ///   changed or removed: the neighbour across an edge is the deepest
    ///   node covering the same-level neighbour, which only a split or merge
    ///   on its path can change, and a split or merge below it needs it to
    ///   be split and at least the same level, so that it still covers;
    /// - colour nodes (§4.4.1) are copied in elevation pre-order, which is
    ///   the colour tree's pre-order (a colour node exists exactly under a
    ///   split colour parent), re-read only where the colour tree changed;
    ///   bindings are recomputed from the flat links.
    fn splice(&mut self, tree: &PartialTree, list: &[TreeChange]) {
        self.splices += 1;
        let old_n = self.ids.len();
        // Old nodes to re-read (elevation: with their subtrees).
        let mut sp = std::mem::take(&mut self.spare);
        let mut edirty = std::mem::take(&mut sp.flags);
        edirty.clear();
        edirty.resize(old_n, false);
        let mut cdirty = std::mem::take(&mut sp.cflags);
        cdirty.clear();
        cdirty.resize(self.cnodes.len(), false);
        for c in list.iter().filter(|c| c.kind != ChangeKind::Refined) {
            // A changed node missing from the cache lies under a node that
            // was a leaf and is changed too.
            let Some(k) = self.find(&c.block) else {
                continue;
            };
            match c.tree {
                Tree::Elevation => edirty[k] = true,
                Tree::Colour => {
                    if let Some(j) = self.col_of_elev.get(k).filter(|j| **j != NONE) {
                        cdirty[*j as usize] = true;
                    }
                }
            }
        }
        // The old arrays; the new ones reuse the buffers of the last splice.
        let old_ids = std::mem::replace(&mut self.ids, std::mem::take(&mut sp.ids));
        let old_hot = std::mem::replace(&mut self.hot, std::mem::take(&mut sp.hot));
        let old_nb = std::mem::replace(&mut self.nb, std::mem::take(&mut sp.nb));
        let old_memo = std::mem::replace(&mut self.memo, std::mem::take(&mut sp.memo));
        let old_col = std::mem::replace(&mut self.col_of_elev, std::mem::take(&mut sp.col));
        let old_cnodes = std::mem::replace(&mut self.cnodes, std::mem::take(&mut sp.cnodes));
        let old_cmemo = std::mem::replace(&mut self.cmemo, std::mem::take(&mut sp.cmemo));
        let old_children = std::mem::replace(&mut self.children, std::mem::take(&mut sp.children));
        self.clear();
        self.hot.reserve(old_n + 64);
        self.ids.reserve(old_n + 64);
        self.children.reserve(old_n + 64);
        self.memo.reserve(old_n + 64);
        let et = tree.elevation();
        // Old index → new index (NONE: changed or removed), new → old.
        let mut remap = std::mem::take(&mut sp.remap);
        remap.clear();
        remap.resize(old_n, NONE);
        let mut from_old = std::mem::take(&mut sp.from_old);
        from_old.clear();
        let mut fresh: Vec<std::ops::Range<usize>> = Vec::new();
        let mut k = 0;
        while k < old_n {
            // A run of kept nodes, copied in bulk. A kept node's parent is
            // kept (a changed node's old subtree is skipped whole).
            let run = edirty[k..].iter().position(|d| *d).map_or(old_n, |r| k + r);
            if run > k {
                let i0 = self.hot.len();
                self.hot.extend_from_slice(&old_hot[k..run]);
                self.ids.extend_from_slice(&old_ids[k..run]);
                self.memo.extend_from_slice(&old_memo[k..run]);
                self.children.resize(self.hot.len(), [NONE; 4]);
                from_old.extend(k as u32..run as u32);
                for (o, i) in (k..run).zip(i0..) {
                    remap[o] = i as u32;
                    let id = self.ids[i];
                    match self.hot[i].parent {
                        NONE => self.roots[id.face.index() as usize] = i as u32,
                        p => {
                            let np = remap[p as usize];
                            self.hot[i].parent = np;
                            self.children[np as usize][id.child_index()] = i as u32;
                        }
                    }
                }
                k = run;
                continue;
            }
            let id = old_ids[k];
            let parent = match old_hot[k].parent {
                NONE => NONE,
                p => remap[p as usize],
            };
            let mut end = k + 1;
            while end < old_n && old_ids[end].level > id.level {
                end += 1;
            }
            let start = self.hot.len();
            self.push_subtree(et, id, parent);
            let now = self.hot.len();
            from_old.resize(now, NONE);
            if now > start {
                // A merged or split node keeps its bounds, and with them its
                // visibility witnesses.
                let os = old_hot[k].slot as usize;
                let ns = self.hot[start].slot as usize;
                if Arc::ptr_eq(&self.cold[ns].bounds, &self.cold[os].bounds) {
                    self.cold[ns].hint = self.cold[os].hint;
                    self.cold[ns].witness = self.cold[os].witness;
                }
                fresh.push(start..now);
            }
            // The old subtree's slots are free for the next re-read one.
            self.free.extend(old_hot[k..end].iter().map(|h| h.slot));
            k = end;
        }
        let n = self.hot.len();
        // Subtree balls: the re-read subtrees, then their ancestors
        // (descendants first: later in pre-order).
        let mut up: Vec<u32> = Vec::new();
        for r in &fresh {
            self.union_subtree_balls(r.clone());
            let mut p = self.hot[r.start].parent;
            while p != NONE {
                up.push(p);
                p = self.hot[p as usize].parent;
            }
        }
        up.sort_unstable_by(|a, b| b.cmp(a));
        up.dedup();
        for a in up {
            let a = a as usize;
            let mut s = self.cold[self.hot[a].slot as usize].own;
            for c in self.children[a] {
                if c != NONE {
                    s = ball_union(s, self.hot[c as usize].sub);
                }
            }
            self.hot[a].sub = s;
        }
        // Neighbours: kept where the old one is kept, else top-down.
        self.nb.reserve(n);
        for (i, &ok) in from_old.iter().enumerate() {
            let nb = std::array::from_fn(|e| {
                if ok != NONE {
                    let t = old_nb[ok as usize][e];
                    if t != NONE && remap[t as usize] != NONE {
                        return remap[t as usize];
                    }
                }
                self.neighbour_of(i, e)
            });
            self.nb.push(nb);
        }
        // Colour nodes in elevation pre-order.
        self.col_of_elev.resize(n, NONE);
        if let Some(ct) = tree.colour() {
            self.cnodes.reserve(old_cnodes.len() + 16);
            self.cmemo.reserve(old_cnodes.len() + 16);
            for (i, &ok) in from_old.iter().enumerate() {
                let exists = match self.hot[i].parent {
                    NONE => true,
                    p => {
                        let pc = self.col_of_elev[p as usize];
                        pc != NONE && self.cnodes[pc as usize].split
                    }
                };
                if !exists {
                    continue;
                }
                let oj = if ok != NONE {
                    old_col[ok as usize]
                } else {
                    NONE
                };
                let (c, m) = if oj != NONE && !cdirty[oj as usize] {
                    let mut c = old_cnodes[oj as usize].clone();
                    c.elev = i as u32;
                    (c, old_cmemo[oj as usize])
                } else {
                    let id = self.ids[i];
                    let Some(cn) = ct.get(&id) else { continue };
                    let c = CNode {
                        id,
                        elev: i as u32,
                        split: cn.split,
                        lod: cn.lod,
                        splittable: cn.can_split_data().is_ok(),
                        record: cn.record,
                        err0: cn.child_error(),
                    };
                    (c, CMemo::default())
                };
                self.col_of_elev[i] = self.cnodes.len() as u32;
                self.cnodes.push(c);
                self.cmemo.push(m);
            }
        }
        self.bind_colours();
        if self.scattered > n / 16 {
            self.compact_cold();
        }
        // Keep the old buffers (emptied) for the next splice.
        sp = Spare {
            ids: old_ids,
            hot: old_hot,
            nb: old_nb,
            memo: old_memo,
            col: old_col,
            cnodes: old_cnodes,
            cmemo: old_cmemo,
            children: old_children,
            flags: edirty,
            cflags: cdirty,
            remap,
            from_old,
        };
        sp.clear();
        self.spare = sp;
    }

    /// Compare the cache with one rebuilt from scratch from `tree` (a
    /// consistency check for tests and debugging: the splices of
    /// [`PartialTree::changes_since`]'s log must give the same flat trees).
    /// Subtree balls may differ but must hold the node's own ball and its
    /// children's. Call it right after [`Selector::select`] on the same
    /// tree.
    pub fn consistency_error(&self, tree: &PartialTree) -> Option<String> {
        let mut f = Selector::new();
        f.rebuild(tree);
        if self.ids != f.ids {
            return Some(format!(
                "node ids differ ({} cached, {} fresh)",
                self.ids.len(),
                f.ids.len()
            ));
        }
        if self.roots != f.roots || self.children != f.children || self.nb != f.nb {
            return Some("roots, children or neighbours differ".into());
        }
        for i in 0..self.ids.len() {
            let (a, b) = (&self.hot[i], &f.hot[i]);
            let (ca, cb) = (&self.cold[a.slot as usize], &f.cold[b.slot as usize]);
            let same = a.parent == b.parent
                && a.split == b.split
                && a.lod == b.lod
                && a.splittable == b.splittable
                && ca.own == cb.own
                && Arc::ptr_eq(&ca.bounds, &cb.bounds)
                && ca.err1 == cb.err1
                && ca.err0 == cb.err0
                && ca.record == cb.record
                && self.bind[i] == f.bind[i];
            if !same {
                return Some(format!("node {:?} differs", self.ids[i]));
            }
            let holds = |outer: (DVec3, f64), inner: (DVec3, f64)| {
                (outer.0 - inner.0).length() + inner.1 <= outer.1 * (1.0 + 1e-12) + 1e-6
            };
            let mut inner = vec![ca.own];
            inner.extend(
                self.children[i]
                    .iter()
                    .filter(|c| **c != NONE)
                    .map(|c| self.hot[*c as usize].sub),
            );
            if !inner.iter().all(|b| holds(a.sub, *b)) {
                return Some(format!("subtree ball of {:?} too small", self.ids[i]));
            }
        }
        if self.col_of_elev != f.col_of_elev {
            return Some("colour node links differ".into());
        }
        for (a, b) in self.cnodes.iter().zip(&f.cnodes) {
            let same = a.id == b.id
                && a.elev == b.elev
                && a.split == b.split
                && a.lod == b.lod
                && a.splittable == b.splittable
                && a.record == b.record;
            if !same {
                return Some(format!("colour node {:?} differs", a.id));
            }
        }
        (self.cnodes.len() != f.cnodes.len()).then(|| "colour node counts differ".into())
    }

    /// Select the LODs to draw and trigger requests for one frame: the same
    /// result as [`select`](super::select)`(tree, view, refiner, ahead)`.
    pub fn select(
        &mut self,
        tree: &PartialTree,
        view: &View,
        refiner: &Refiner,
        ahead: Option<&Refiner>,
    ) -> Selection {
        let ahead = Ahead::new(refiner, ahead);
        self.update(tree);
        let mut draw = std::mem::take(&mut self.spare_draw);
        draw.clear();
        draw.reserve(self.last_draw);
        let mut cx = Ctx {
            tree,
            out: Selection {
                draw,
                ..Selection::default()
            },
        };
        let et = tree.elevation();
        let ew = et.width as f64;
        // Generation 0 is never valid, so fresh entries are recomputed.
        let key = MemoKey::new(view, refiner);
        if self.memo_key != Some(key) || self.memo_gen == 0 {
            self.memo_key = Some(key);
            self.memo_gen += 1;
        }
        let gen = self.memo_gen;
        if !self
            .odometer
            .step(view.camera.eye, Odometer::key(view, refiner))
        {
            for m in &mut self.memo {
                m.keep = Keep::default();
            }
            for m in &mut self.cmemo {
                m.keep = Keep::default();
            }
        }
        let odo = self.odometer.len;
        let n = self.hot.len();
        self.state.clear();
        self.state.resize(n, 0);
        self.drawn.clear();
        self.drawn.resize(n, NOT_DRAWN);
        self.draw_idx.clear();
        self.tree_bound.clear();
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
                        let c = &mut self.cold[h.slot as usize];
                        // A leaf's subtree ball is its own ball.
                        let own = if h.split {
                            view.classify_sphere(c.own.0, c.own.1)
                        } else {
                            None
                        };
                        match own {
                            Some(v) => v as u8,
                            None => exact_visible(view, c) as u8,
                        }
                    }
                },
            };
            self.state[i] = st;
            if h.split {
                // Split blocks only ask whether to merge (visible or not);
                // most are surely kept, which needs no measure.
                let m = &mut self.memo[i];
                if m.gen != gen {
                    if m.keep.holds(odo, refiner) {
                        continue;
                    }
                    let c = &self.cold[h.slot as usize];
                    let slack = refiner.keep_slack(Kind::Elevation, &c.fp, ew, c.err1);
                    if m.keep.refresh(odo, slack) {
                        continue;
                    }
                    m.gen = gen;
                    m.m = refiner.measure(Kind::Elevation, &c.fp, ew, c.err1, c.err0);
                    m.sse_lod = NOT_DRAWN;
                }
                if let Some(p) = refiner.merge(&m.m) {
                    let c = &self.cold[h.slot as usize];
                    if tree.can_merge(Tree::Elevation, &self.ids[i]).is_ok()
                        && !colour_holds_split(tree, refiner, &self.ids[i], &c.fp)
                        && ahead.as_ref().is_none_or(|a| {
                            a.lets_merge(Kind::Elevation, &c.fp, ew, (c.err1, c.err0))
                        })
                    {
                        cx.out.ops.push(TreeOp {
                            kind: OpKind::Merge,
                            tree: Tree::Elevation,
                            block: self.ids[i],
                            importance: p,
                        });
                    }
                }
                continue;
            }
            // Hidden leaves trigger nothing and are not drawn.
            if st == 0 {
                continue;
            }
            let m = &mut self.memo[i];
            if m.gen != gen {
                let c = &self.cold[h.slot as usize];
                m.gen = gen;
                m.m = refiner.measure(Kind::Elevation, &c.fp, ew, c.err1, c.err0);
                m.sse_lod = NOT_DRAWN;
            }
            let mm = m.m;
            let id = self.ids[i];
            let c = &self.cold[h.slot as usize];
            let d = refiner.leaf(&mm, h.lod);
            let lod = d.lod.max(h.lod);
            let lod = if lod == 1 && h.lod == 0 && colour_holds_split(tree, refiner, &id, &c.fp) {
                0
            } else {
                lod
            };
            self.drawn[i] = lod;
            if d.load {
                cx.out.loads.push(LoadRequest {
                    tree: Tree::Elevation,
                    block: id,
                    record: c.record,
                    importance: refiner.load_priority(
                        Kind::Elevation,
                        &mm,
                        h.lod,
                        id.level,
                        c.fp.centre,
                        c.record.size,
                    ),
                    forced: false,
                });
            } else if d.split && h.splittable {
                let p = refiner.split_priority(&mm, id.level, c.fp.centre);
                cx.trigger_split(Tree::Elevation, id, p, 0);
            } else if let Some(a) = &ahead {
                let leaf = Leaf {
                    kind: Kind::Elevation,
                    id,
                    fp: &c.fp,
                    width: ew,
                    err: (c.err1, c.err0),
                    lod: h.lod,
                    size: c.record.size,
                    splittable: h.splittable,
                };
                cx.prefetch(a, refiner, &mm, leaf);
            }
            let m = &mut self.memo[i];
            if m.sse_lod != lod {
                let error = if lod == 1 { c.err1 } else { c.err0 };
                m.sse = refiner.drawn_error(&mm, error);
                m.sse_lod = lod;
            }
            let area = refiner.drawn_area(&mm, c.fp.radius);
            cx.draw(id, lod, et.width, d.importance, (m.sse, area));
            self.draw_idx.push((i as u32, self.bind[i]));
        }
        // Colour tree.
        self.cdrawn.clear();
        self.cdrawn.resize(self.cnodes.len(), NOT_DRAWN);
        // The colour leaves some drawn block is textured with: only those
        // load or split. A leaf whose elevation block is visible but split
        // into blocks that are all culled (behind the horizon, outside the
        // frustum) textures nothing.
        let mut bound = std::mem::take(&mut self.cbound);
        bound.clear();
        bound.resize(self.cnodes.len(), false);
        for &(_, b) in &self.draw_idx {
            if let Binding::Node(j) = b {
                bound[j as usize] = true;
            }
        }
        if let Some(ct) = tree.colour() {
            let cw = ct.width as f64;
            for (j, c) in self.cnodes.iter().enumerate() {
                // A leaf no drawn block is textured with triggers nothing,
                // and its drawn LOD is never asked for.
                if !c.split && !bound[j] {
                    continue;
                }
                let m = &mut self.cmemo[j];
                // Split blocks only ask whether to merge; most are surely
                // kept (as for elevation). A leaf at its finest only has its
                // drawn LOD to decide, which mostly stays.
                let finest = !c.split && c.lod == 0 && !c.splittable;
                if m.gen != gen && (c.split || finest) && m.keep.holds(odo, refiner) {
                    if finest {
                        self.cdrawn[j] = m.lod;
                    }
                    continue;
                }
                // Its elevation node's footprint (§4.4.3).
                let fp = &self.cold[self.hot[c.elev as usize].slot as usize].fp;
                let err1 = c.record.error as f64;
                let measured = m.gen != gen;
                if measured {
                    if c.split
                        && m.keep
                            .refresh(odo, refiner.keep_slack(Kind::Colour, fp, cw, err1))
                    {
                        continue;
                    }
                    m.gen = gen;
                    m.m = refiner.measure(Kind::Colour, fp, cw, err1, c.err0);
                }
                let mm = m.m;
                if c.split {
                    if let Some(p) = refiner.merge(&mm) {
                        let err = (c.record.error as f64, c.err0);
                        if tree.can_merge(Tree::Colour, &c.id).is_ok()
                            && ahead
                                .as_ref()
                                .is_none_or(|a| a.lets_merge(Kind::Colour, fp, cw, err))
                        {
                            cx.out.ops.push(TreeOp {
                                kind: OpKind::Merge,
                                tree: Tree::Colour,
                                block: c.id,
                                importance: p,
                            });
                        }
                    }
                    continue;
                }
                let d = refiner.leaf(&mm, c.lod);
                self.cdrawn[j] = d.lod.max(c.lod);
                if finest && measured {
                    m.keep
                        .refresh(odo, refiner.finest_colour_slack(fp, cw, err1, d.lod));
                    m.lod = d.lod;
                }
                if d.load {
                    cx.out.loads.push(LoadRequest {
                        tree: Tree::Colour,
                        block: c.id,
                        record: c.record,
                        importance: refiner.load_priority(
                            Kind::Colour,
                            &mm,
                            c.lod,
                            c.id.level,
                            fp.centre,
                            c.record.size,
                        ),
                        forced: false,
                    });
                } else if d.split && c.splittable {
                    cx.split_colour(c.id, refiner.split_priority(&mm, c.id.level, fp.centre));
                } else if let Some(a) = &ahead {
                    let leaf = Leaf {
                        kind: Kind::Colour,
                        id: c.id,
                        fp,
                        width: cw,
                        err: (c.record.error as f64, c.err0),
                        lod: c.lod,
                        size: c.record.size,
                        splittable: c.splittable,
                    };
                    cx.prefetch(a, refiner, &mm, leaf);
                }
            }
        }
        self.cbound = bound;
        // Neighbour LODs and colour bindings (split and hidden nodes have
        // no drawn LOD).
        let (drawn, ids) = (&self.drawn, &self.ids);
        for (d, &(i, binding)) in cx.out.draw.iter_mut().zip(&self.draw_idx) {
            let (lod, level) = (d.lod as i32, d.block.level as i32);
            // `NONE` is past the end of `drawn`: no neighbour.
            for (n, &j) in d.neighbours.iter_mut().zip(&self.nb[i as usize]) {
                if let Some(&nlod) = drawn.get(j as usize) {
                    if nlod != NOT_DRAWN {
                        let nid = ids[j as usize];
                        *n = Some(NeighbourLod {
                            block: nid,
                            lod: nlod,
                            lod_diff: (nlod as i32 - lod) + (level - nid.level as i32),
                        });
                    }
                }
            }
            d.colour = match binding {
                Binding::None => None,
                Binding::Node(j) => {
                    let cn = &self.cnodes[j as usize];
                    Some(ColourBinding {
                        block: cn.id,
                        lod: self.cdrawn[j as usize],
                    })
                }
                Binding::Tree(id) => {
                    let b = tree
                        .colour()
                        .and_then(|t| t.get(&id))
                        .map(|c| ColourBinding {
                            block: c.id,
                            lod: c.lod,
                        });
                    self.tree_bound.extend(b);
                    b
                }
            };
        }
        self.last_draw = cx.out.draw.len();
        cx.out
    }

    /// [`draws_lod0`](super::draws_lod0) of the last selection's draw list,
    /// from the flat tree: `block`'s node drawn (elevation) or textured
    /// onto a drawn block (colour) at LOD 0, or a child's at LOD 1. A few
    /// steps down the flat tree instead of a scan of the list (the client
    /// asks it for the records it accounts for, every frame).
    pub fn draws_lod0(&self, kind: Tree, block: &BlockId) -> bool {
        let in_tree = || {
            self.tree_bound
                .iter()
                .any(|c| lod0_block(c.block, c.lod) == Some(*block))
        };
        let Some(i) = self.find(block) else {
            return kind == Tree::Colour && in_tree();
        };
        let mut children = self.children[i].iter().filter(|c| **c != NONE);
        match kind {
            Tree::Elevation => {
                let drawn = |i: usize, lod: u8| self.drawn.get(i) == Some(&lod);
                drawn(i, 0) || children.any(|&c| drawn(c as usize, 1))
            }
            Tree::Colour => {
                // A colour leaf's drawn LOD is what the blocks it is bound
                // to (`cbound`) are textured with.
                let textured = |e: usize, lod: u8| match self.col_of_elev.get(e) {
                    Some(&j) if j != NONE => {
                        let j = j as usize;
                        self.cbound.get(j) == Some(&true) && self.cdrawn.get(j) == Some(&lod)
                    }
                    _ => false,
                };
                textured(i, 0) || children.any(|&c| textured(c as usize, 1)) || in_tree()
            }
        }
    }

    /// Hands a draw list of an earlier [`Selector::select`] back for reuse
    /// (its contents are dropped; only its allocation is kept).
    pub fn recycle(&mut self, mut draw: Vec<DrawBlock>) {
        if draw.capacity() > self.spare_draw.capacity() {
            draw.clear();
            self.spare_draw = draw;
        }
    }
}

/// [`View::is_visible`] of a node: by its witness point when that
/// still proves it visible, else by the full test (which finds a new
/// witness when it can).
///
/// A block with parts (§4.2.1, coarse blocks) is visible when its ball
/// meets the view cone and one part is visible; its witness is a bounding
/// point of one part (`hint` is then that part's index): inside every
/// frustum plane and in front of the horizon, it passes each test of that
/// part but the cone tests of the part's ball and top radius, which are
/// redone.
fn exact_visible(view: &View, c: &mut Cold) -> bool {
    let Cold {
        hint,
        witness,
        own,
        top,
        bounds,
        parts,
        ..
    } = c;
    if let Some(p) = *witness {
        // Without parts, `own` is the bounds' own ball (and the bounds are
        // not read).
        let proven = view.planet_in_view()
            && view.point_witnesses_visible(p)
            && if !*parts {
                view.top_in_view(*top) && view.sphere_in_cone(own.0, own.1)
            } else {
                let b = &**bounds;
                b.parts.get(*hint as usize).is_some_and(|part| {
                    part.parts.is_empty()
                        && view.top_in_view(part.top_radius)
                        && view.sphere_in_cone(b.centre, b.sphere_radius)
                        && view.sphere_in_cone(part.centre, part.sphere_radius)
                })
            };
        if proven {
            return true;
        }
    }
    *witness = None;
    let b = &**bounds;
    if !b.parts.is_empty() {
        let v = view.is_visible(b);
        if v {
            let found = b.parts.iter().enumerate().find_map(|(k, part)| {
                if !part.parts.is_empty()
                    || !view.top_in_view(part.top_radius)
                    || !view.sphere_in_cone(part.centre, part.sphere_radius)
                {
                    return None;
                }
                let p = part
                    .points
                    .iter()
                    .find(|q| view.point_witnesses_visible(**q))?;
                Some((k, *p))
            });
            if let Some((k, p)) = found {
                *hint = k as u32;
                *witness = Some(p);
            }
        }
        return v;
    }
    let v = view.is_visible_hinted(b, hint);
    if v {
        if let Some(&p) = b.points.get(*hint as usize) {
            if view.point_witnesses_visible(p) {
                *witness = Some(p);
            }
        }
    }
    v
}
