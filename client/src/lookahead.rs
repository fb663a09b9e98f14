//! Two tree levels per round trip on the way down: the client learns the
//! references of a block's grandchildren with its record, and asks a
//! child's children before the child's own record has arrived.
//!
//! Each record carries its children's references (thesis §3.3.2), so a
//! descent from orbit costs one round trip per level: the record of `B`
//! must arrive before `B`'s children can be asked, theirs before their
//! children. Google Earth sends several levels of metadata per packet for
//! this reason (docs/REFERENCES.md, "Google Earth metadata"). Here a request
//! may ask for the **child tables** of its record's children with it
//! (`LodRefsRequest`, docs/PROTOCOL.md §4.8), which the server reads from
//! the children's records. With them, when `B` splits, the client asks `B`'s
//! children *and* those of their children that the children's split would
//! ask: the split of a leaf at LOD 0 depends only on its own bounds and its
//! children's errors ([`Refiner::leaf`]), all in the tables. The grandchild
//! asks for its own grandchildren's tables, so every round trip brings two
//! levels.
//!
//! A record that arrives before its parent is split (its parent's record is
//! still in flight) is held by the client until it can be applied
//! ([`crate::Client`], `parked`), and its own children's references feed
//! this module too.
//!
//! Nothing here is drawn before its ancestors: a held record is decoded
//! only once its block exists in the partial tree, from its parent's
//! samples, and its checksum and block id are checked then as any other.

use crate::refinement::{Footprint, Kind, Refiner};
use crate::request_queue::LoadRequest;
use crate::tree::{FastMap, FastSet, PartialTree};
use crate::visibility::View;
use planet_core::format::{self, ChildRef, Tree};
use planet_core::BlockId;

/// A block's own projected error, in tolerances, above which its request
/// asks for its children's tables: its children are then likely to split
/// and its grandchildren to load (a level roughly halves the error), so
/// the tables will be used. Below it, the 97 bytes per child would mostly
/// travel for nothing.
pub const REFS_AT: f64 = 4.0;

/// Frames a learned table or a held record is kept without being used.
pub const KEEP_FRAMES: u64 = 90;

/// Held records and learned tables at most (a bound on memory).
pub const MAX_ENTRIES: usize = 4096;

/// The child references learned before their blocks' records were applied.
#[derive(Debug, Default)]
pub struct Lookahead {
    known: FastMap<BlockId, (Vec<ChildRef>, u64)>,
}

impl Lookahead {
    /// An empty store.
    pub fn new() -> Lookahead {
        Lookahead::default()
    }

    /// Whether the children's references of `block` are known early.
    pub fn knows(&self, block: &BlockId) -> bool {
        self.known.contains_key(block)
    }

    /// Learns the tables in `trailer` (the body after the record of `block`,
    /// `record` its bytes). Returns false, learning nothing, when the
    /// record's checksum or the trailer does not check.
    pub fn learn_tables(
        &mut self,
        block: BlockId,
        record: &[u8],
        trailer: &[u8],
        frame: u64,
    ) -> bool {
        if !format::record_checksum_ok(record) {
            return false;
        }
        let Ok(children) = format::record_child_refs(record, None) else {
            return false;
        };
        let Ok(tables) = format::parse_child_tables(trailer, children.len(), None) else {
            return false;
        };
        for (k, t) in tables.into_iter().enumerate() {
            if let Some(t) = t.filter(|t| t.len() == 4) {
                self.insert(block.child(k), t, frame);
            }
        }
        true
    }

    /// Learns the children's references of an elevation record that arrived
    /// before its block exists (held).
    pub fn learn_record(&mut self, block: BlockId, record: &[u8], frame: u64) {
        if !format::record_checksum_ok(record) {
            return;
        }
        if let Ok(c) = format::record_child_refs(record, None) {
            if c.len() == 4 {
                self.insert(block, c, frame);
            }
        }
    }

    fn insert(&mut self, block: BlockId, refs: Vec<ChildRef>, frame: u64) {
        if self.known.len() < MAX_ENTRIES || self.known.contains_key(&block) {
            self.known.insert(block, (refs, frame));
        }
    }

    /// Forgets what the tree now holds itself (the block's record is
    /// applied) and what was not used for [`KEEP_FRAMES`].
    pub fn prune(&mut self, tree: &PartialTree, frame: u64) {
        let e = tree.elevation();
        self.known.retain(|b, (_, at)| {
            frame.saturating_sub(*at) <= KEEP_FRAMES
                && e.get(b).is_none_or(|n| n.lod == 1 && !n.split)
        });
    }

    /// The loads of the children of blocks whose record is coming (`seeds`:
    /// asked this frame, in flight or held) and whose children's references
    /// are known: those that the block's split would ask once its record is
    /// applied, by the refiner of `arrival` (the view predicted for the
    /// arrival, when there is one) and visible in its view, and asked by
    /// the leaf rule of `now`. Each asked child is a seed in turn.
    /// `skip`: blocks whose record is held or decoding.
    pub(crate) fn loads(
        &mut self,
        tree: &PartialTree,
        seeds: impl IntoIterator<Item = (BlockId, ChildRef)>,
        skip: &FastSet<(Tree, BlockId)>,
        arrival: (&View, &Refiner),
        now: &Refiner,
        frame: u64,
    ) -> Vec<LoadRequest> {
        let (view, refiner) = arrival;
        let e = tree.elevation();
        let w = e.width as f64;
        let mut out = vec![];
        let mut seen: FastSet<BlockId> = FastSet::default();
        let mut work: Vec<(BlockId, ChildRef)> = seeds.into_iter().collect();
        while let Some((id, record)) = work.pop() {
            if !seen.insert(id) || out.len() >= MAX_ENTRIES {
                continue;
            }
            let Some((kids, at)) = self.known.get_mut(&id) else {
                continue;
            };
            *at = frame;
            let bounds = tree.bounds_of(id, &record);
            if !view.is_visible(&bounds) {
                continue;
            }
            let err0 = kids.iter().map(|r| r.error as f64).fold(0.0, f64::max);
            let m = refiner.measure(
                Kind::Elevation,
                &Footprint::of(&bounds),
                w,
                record.error as f64,
                err0,
            );
            if !refiner.leaf(&m, 0).split {
                continue;
            }
            for (k, r) in kids.iter().enumerate() {
                let cid = id.child(k);
                if e.get(&cid).is_some() || skip.contains(&(Tree::Elevation, cid)) {
                    continue;
                }
                // The leaf rule of the traversals now (a fresh leaf has no
                // child errors yet), then the request filter at arrival, as
                // for the children of a split chosen now
                // (`selection::children_loads`).
                let b = tree.bounds_of(cid, r);
                let m = now.measure(Kind::Elevation, &Footprint::of(&b), w, r.error as f64, 0.0);
                if !now.leaf(&m, 1).load
                    || !view.is_visible(&b)
                    || !refiner.loads_at_arrival(Kind::Elevation, &b, w, r.error as f64, 1)
                {
                    continue;
                }
                out.push(LoadRequest {
                    tree: Tree::Elevation,
                    block: cid,
                    record: *r,
                    importance: now.load_priority(&m, 1, cid.level, b.centre, r.size),
                    forced: false,
                });
                work.push((cid, *r));
            }
        }
        out
    }
}

/// Whether a request for `block` (its record `record`) should ask for its
/// children's tables: they are not known yet, and its own error projected
/// by `refiner` is above [`REFS_AT`] tolerances.
pub(crate) fn wants_tables(
    tree: &PartialTree,
    known: &Lookahead,
    refiner: &Refiner,
    block: BlockId,
    record: &ChildRef,
) -> bool {
    if known.knows(&block) {
        return false;
    }
    let b = tree.bounds_of(block, record);
    let w = tree.elevation().width as f64;
    let m = refiner.measure(
        Kind::Elevation,
        &Footprint::ball(&b),
        w,
        record.error as f64,
        0.0,
    );
    m.a > refiner.tolerance() * REFS_AT
}
