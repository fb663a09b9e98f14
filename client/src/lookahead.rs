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

/// A block's own error projected at one of its children, in tolerances,
/// above which that child is likely to split and its table to be used: a
/// level roughly halves the error, and the child splits when its children's
/// error (two levels below) projects above the tolerance. A reference's
/// error is the largest in its subtree (errors are carried up), so a child
/// in the flatter part of its parent holds less than its parent's error:
/// one more factor of two for that. At 4 tolerances half of the tables a
/// flight over the real data learned were never used (docs/BENCHMARKS.md,
/// "Trajectories flown after tuning").
pub const REFS_AT: f64 = 8.0;

/// Frames a learned table or a held record is kept without being used.
pub const KEEP_FRAMES: u64 = 90;

/// Held records and learned tables at most (a bound on memory).
pub const MAX_ENTRIES: usize = 4096;

/// The child references learned before their blocks' records were applied.
#[derive(Debug, Default)]
pub struct Lookahead {
    known: FastMap<BlockId, (Vec<ChildRef>, u64)>,
    /// Blocks whose table came in a trailer and has not been credited yet
    /// ([`Lookahead::credit`]), with the frame it came.
    tables: FastMap<BlockId, u64>,
    /// Blocks asked ahead, with the block whose table asked them.
    asked_via: FastMap<BlockId, BlockId>,
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
                let child = block.child(k);
                self.insert(child, t, frame);
                if self.tables.len() < MAX_ENTRIES {
                    self.tables.insert(child, frame);
                }
            }
        }
        true
    }

    /// The trailer bytes to count as used now that the record of `block`
    /// in `tree` was drawn: the table (97 bytes) of the block whose child
    /// table asked `block` ahead, once per table. A table is used when one
    /// of its references led to a drawn record, as the references inside a
    /// record count with the record (stats.rs).
    pub fn credit(&mut self, tree: Tree, block: &BlockId) -> u64 {
        if tree != Tree::Elevation {
            return 0;
        }
        self.asked_via
            .remove(block)
            .and_then(|via| self.tables.remove(&via))
            .map_or(0, |_| format::CHILD_TABLE_LEN as u64)
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
        // A table is credited by a record drawn within a few round trips of
        // its arrival, or never.
        self.tables
            .retain(|_, at| frame.saturating_sub(*at) <= 2 * KEEP_FRAMES);
        let tables = &self.tables;
        self.asked_via.retain(|_, via| tables.contains_key(via));
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
                    importance: now.load_priority(
                        Kind::Elevation,
                        &m,
                        1,
                        cid.level,
                        b.centre,
                        r.size,
                    ),
                    forced: false,
                });
                if self.tables.contains_key(&id) && self.asked_via.len() < MAX_ENTRIES {
                    self.asked_via.insert(cid, id);
                }
                work.push((cid, *r));
            }
        }
        out
    }
}

/// The error floor of a child's table is this fraction of the error that
/// projects to one tolerance at the child's ball in the view of the
/// request's arrival (`wants_tables`), brought closer by as far as the
/// camera can come while the table is kept: the child's split is tested
/// with its own, tighter bounds (not always farther than that ball).
pub const TABLE_FLOOR_MARGIN: f64 = 0.5;

/// Whether a request for `block` (its record `record`) should ask for its
/// children's tables, and if so each child's error floor (metres, the
/// block's child order; docs/PROTOCOL.md §4.9): they are not known yet,
/// and one of its four children at least is likely to split. A child's
/// table is used when the child splits, that is when its own children (two
/// levels below `block`, their error about a quarter of `block`'s) project
/// above the tolerance: the child is visible and the block's error
/// projected at the child's ball is above [`REFS_AT`] tolerances, in the
/// view predicted for the record's arrival (`arrival`), when the tables are
/// used. The child's bounds are those of its area with `block`'s height
/// range (conservative: its own is inside it). Testing each child rather
/// than the block's nearest point leaves out the tables of a block whose
/// visible children are all far (docs/BENCHMARKS.md: unused tables on a low,
/// fast flight).
///
/// `block`'s error is the largest in its subtree, and may come from one
/// rough child while a sibling's own children project far under the
/// tolerance; only the server, which reads each child's table, knows. So
/// each child gets a floor: the error that projects to
/// [`TABLE_FLOOR_MARGIN`] tolerances at its ball, `approach` metres closer
/// (how far the camera can come while the table is kept, [`KEEP_FRAMES`]
/// frames at its present speed: a table asked on a dive is used lower
/// down), +∞ for a child out of view; the server leaves out a table whose
/// references all lie under it (docs/BENCHMARKS.md, "Why khumbu at
/// 10 Mbit/s sits at the relevance goal's edge").
pub(crate) fn wants_tables(
    tree: &PartialTree,
    known: &Lookahead,
    arrival: (&View, &Refiner),
    approach: f64,
    block: BlockId,
    record: &ChildRef,
) -> Option<[f32; 4]> {
    let (view, refiner) = arrival;
    if known.knows(&block) {
        return None;
    }
    let w = tree.elevation().width as f64;
    let tol = refiner.tolerance();
    let mut floors = [f32::INFINITY; 4];
    let mut wanted = false;
    for (k, c) in block.children().into_iter().enumerate() {
        let b = tree.bounds_of(c, record);
        if !view.is_visible(&b) {
            continue;
        }
        let m = refiner.measure(
            Kind::Elevation,
            &Footprint::ball(&b),
            w,
            record.error as f64,
            0.0,
        );
        wanted |= m.a > tol * REFS_AT;
        // The scale is inversely proportional to the distance (at least
        // 1 m here: a larger scale only lowers the floor).
        let closer = (m.dist - approach.max(0.0)).max(1.0);
        let scale = if closer < m.dist {
            m.scale * m.dist / closer
        } else {
            m.scale
        };
        floors[k] = table_floor(tol * TABLE_FLOOR_MARGIN, scale);
    }
    wanted.then_some(floors)
}

/// The largest `f32` error (metres) that projects to at most `px` pixels at
/// `scale` pixels per metre, at least 0: +∞ where nothing projects that far
/// (a zero scale), 0 where everything does.
fn table_floor(px: f64, scale: f64) -> f32 {
    let e = px / scale;
    if e.is_nan() || e < 0.0 {
        return 0.0;
    }
    let f = e as f32;
    if f as f64 > e {
        f.next_down().max(0.0)
    } else {
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The floor is the largest `f32` that projects to at most the given
    /// pixels, never negative or NaN: what `ErrorFloors` accepts.
    #[test]
    fn a_table_floor_projects_to_at_most_its_pixels() {
        for &(px, scale) in &[
            (0.5, 1.0),
            (0.5, 3.0),
            (0.5, 1e-7),
            (0.5, 7.3e4),
            (2.0, 0.1),
            (0.5, 1.0 / 3.0),
            (1e-3, 123.456),
        ] {
            let f = table_floor(px, scale);
            assert!(f >= 0.0 && f.is_finite(), "{px} {scale}: {f}");
            assert!(f as f64 * scale <= px, "{px} {scale}: {f}");
            assert!(
                f.next_up() as f64 * scale > px * (1.0 - 1e-6),
                "{px} {scale}: {f}"
            );
        }
        // Nothing projects that far: never; everything does: always.
        assert_eq!(table_floor(0.5, 0.0), f32::INFINITY);
        assert_eq!(table_floor(0.5, f64::MAX), 0.0);
        assert_eq!(table_floor(0.5, f64::INFINITY), 0.0);
        assert_eq!(table_floor(0.5, f64::NAN), 0.0);
        assert_eq!(table_floor(0.0, 5.0), 0.0);
    }
}
