//! Fixed-size priority request queues with per-frame resubmission.
//!
//! Implements thesis §3.5.2 (see docs/REFERENCES.md): every frame the selection
//! rebuilds the list of triggered requests; the highest-importance ones fill
//! the free slots of a fixed-size queue of requests in flight; the others are
//! discarded and will be triggered again, with fresh importance, next frame.
//!
//! Beyond the thesis (not given there, docs/REFERENCES.md):
//! - a request already in flight is never sent twice (keyed by tree+block);
//! - an in-flight request is **cancelled** when its block is gone or no
//!   longer needs that LOD ([`RequestQueue::retain_relevant`]), when it has
//!   not been triggered for [`QueueConfig::cancel_after_frames`] frames
//!   (became invisible, or its LOD is no longer selected), or when the queue
//!   is full and a waiting request is more important than the worst in-flight
//!   one by [`QueueConfig::preempt_margin`];
//! - responses to unknown (cancelled) ids are recognised by
//!   [`RequestQueue::take`] returning `None`, and dropped by the caller;
//! - besides the count, the bytes in flight may be bounded by a window that
//!   the client sizes from the link ([`RequestQueue::set_window_bytes`],
//!   [`crate::link_estimate`]), and the new requests of one frame by
//!   [`QueueConfig::max_new_per_frame`] (CesiumJS's priority heap).
//!
//! A block whose request failed (transport or server error) or whose record
//! was rejected (corrupt) is not re-requested at once: [`RetryBackoff`]
//! holds it back for an exponentially growing delay per block, so a record
//! that keeps failing is not hammered every frame.
//!
//! The split/merge queue ([`select_tree_ops`]) is larger and has no network:
//! the most important triggered operations, up to a capacity per frame, are
//! executed at the start of the next frame.

use crate::tree::FastMap;
use planet_core::format::{ChildRef, Tree};
use planet_core::BlockId;

/// A request's importance as the priority of its response on the wire
/// (`Priority`, docs/PROTOCOL.md §4.10): an `i32` in the importance's
/// order, so the server sends answers in the order the client would ask
/// for them now (non-strictly: importances within a relative 2⁻²⁰ of each
/// other may share a priority, and are then answered in request order).
/// These are the high 32 bits of the `f64` in its total order (sign,
/// exponent and 20 bits of mantissa), so any importance keeps its order:
/// the positive ones of the screen-space policies, the negative ones of
/// their prefetch ([`crate::refinement::ahead_priority`]), zero and the
/// infinities. NaN, which ranks nothing, gets the lowest.
pub fn stream_priority(importance: f64) -> i32 {
    if importance.is_nan() {
        return i32::MIN;
    }
    let bits = importance.to_bits();
    // Sign-magnitude to an unsigned order: negatives reversed below the
    // positives (as `f64::total_cmp`).
    let ordered = if bits >> 63 == 1 {
        !bits
    } else {
        bits | 1 << 63
    };
    // The high half, from unsigned to signed order.
    ((ordered >> 32) as u32 ^ 0x8000_0000) as i32
}

/// Exponential backoff per block after a failed or rejected load: the
/// first retry waits [`RetryBackoff::INITIAL`] seconds, each further failure
/// doubles the wait up to [`RetryBackoff::MAX`]; a success forgets it.
#[derive(Debug, Default)]
pub struct RetryBackoff {
    failed: FastMap<(Tree, BlockId), (u32, f64)>,
}

impl RetryBackoff {
    /// Wait after the first failure (seconds).
    pub const INITIAL: f64 = 0.1;
    /// Longest wait (seconds).
    pub const MAX: f64 = 30.0;

    /// Notes a failure of `(tree, block)` at time `now`.
    pub fn failed(&mut self, tree: Tree, block: BlockId, now: f64) {
        let e = self.failed.entry((tree, block)).or_insert((0, now));
        e.0 = e.0.saturating_add(1);
        let wait = (Self::INITIAL * 2f64.powi(e.0.min(30) as i32 - 1)).min(Self::MAX);
        e.1 = now + wait;
    }

    /// Forgets the failures of `(tree, block)` (it loaded).
    pub fn succeeded(&mut self, tree: Tree, block: &BlockId) {
        self.failed.remove(&(tree, *block));
    }

    /// Whether `(tree, block)` may be requested at `now`.
    pub fn ready(&self, tree: Tree, block: &BlockId, now: f64) -> bool {
        self.failed.get(&(tree, *block)).is_none_or(|e| now >= e.1)
    }

    /// Blocks held back at `now` (a retry is scheduled later).
    pub fn waiting(&self, now: f64) -> usize {
        self.failed.values().filter(|e| now < e.1).count()
    }

    /// Blocks currently remembered as failing.
    pub fn len(&self) -> usize {
        self.failed.len()
    }

    /// True when no block is held back.
    pub fn is_empty(&self) -> bool {
        self.failed.is_empty()
    }
}

/// A triggered load (refine) request.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadRequest {
    /// The tree.
    pub tree: Tree,
    /// The block whose LOD 0 is wanted.
    pub block: BlockId,
    /// Where the record is.
    pub record: ChildRef,
    /// Request importance (higher is more urgent).
    pub importance: f64,
    /// Forced by a neighbour's split (§4.3.3): visibility was ignored.
    pub forced: bool,
}

/// Queue parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QueueConfig {
    /// Requests in flight at most (thesis: "fixed and relatively small").
    pub max_in_flight: usize,
    /// Cancel an in-flight request after this many frames without trigger.
    pub cancel_after_frames: u32,
    /// Pre-empt the worst in-flight request when a waiting one beats it by
    /// this much importance (`f64::INFINITY` disables pre-emption).
    pub preempt_margin: f64,
    /// Cancel a request still unanswered after this many frames (a lost
    /// response must not hold a slot forever).
    pub timeout_frames: u32,
    /// New requests sent in one frame at most (`usize::MAX`: no limit).
    pub max_new_per_frame: usize,
}

impl Default for QueueConfig {
    fn default() -> Self {
        QueueConfig {
            max_in_flight: 16,
            cancel_after_frames: 2,
            preempt_margin: 2.0,
            timeout_frames: 600,
            max_new_per_frame: usize::MAX,
        }
    }
}

/// An in-flight request.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InFlight {
    /// The request, with its latest importance.
    pub request: LoadRequest,
    /// Consecutive frames it was not triggered.
    pub missed: u32,
    /// Frames since it was sent.
    pub age: u32,
    /// The queue's clock ([`RequestQueue::set_clock`]) when it was sent.
    pub sent_at: f64,
}

/// What one frame's selection decided.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Selected {
    /// New requests to send, most important first.
    pub send: Vec<(u64, LoadRequest)>,
    /// In-flight requests to cancel.
    pub cancel: Vec<u64>,
}

/// The fixed-size queue of load requests in flight.
#[derive(Debug, Clone)]
pub struct RequestQueue {
    config: QueueConfig,
    next_id: u64,
    in_flight: FastMap<u64, InFlight>,
    by_block: FastMap<(Tree, BlockId), u64>,
    bytes_in_flight: u64,
    window_bytes: Option<u64>,
    clock: f64,
}

impl RequestQueue {
    /// An empty queue.
    pub fn new(config: QueueConfig) -> RequestQueue {
        RequestQueue {
            config,
            next_id: 1,
            in_flight: FastMap::default(),
            by_block: FastMap::default(),
            bytes_in_flight: 0,
            window_bytes: None,
            clock: 0.0,
        }
    }

    /// Bound the bytes in flight (record sizes) to `bytes`, `None` for no
    /// bound besides the count. The first request of an empty queue is
    /// always sent, whatever its size.
    pub fn set_window_bytes(&mut self, bytes: Option<u64>) {
        self.window_bytes = bytes;
    }

    /// The byte window in force.
    pub fn window_bytes(&self) -> Option<u64> {
        self.window_bytes
    }

    /// Record sizes of the requests in flight.
    pub fn bytes_in_flight(&self) -> u64 {
        self.bytes_in_flight
    }

    /// Set the clock (seconds) stamped on requests sent from now on.
    pub fn set_clock(&mut self, now: f64) {
        self.clock = now;
    }

    fn fits(&self, r: &LoadRequest) -> bool {
        if self.in_flight.len() >= self.config.max_in_flight {
            return false;
        }
        match self.window_bytes {
            Some(w) => {
                self.in_flight.is_empty() || self.bytes_in_flight + r.record.size as u64 <= w
            }
            None => true,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &QueueConfig {
        &self.config
    }

    /// Number of requests in flight.
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }

    /// The in-flight request `id`.
    pub fn get(&self, id: u64) -> Option<&InFlight> {
        self.in_flight.get(&id)
    }

    /// Whether a request for this block is in flight.
    pub fn is_in_flight(&self, tree: Tree, block: &BlockId) -> bool {
        self.by_block.contains_key(&(tree, *block))
    }

    /// Remove the in-flight request `id` (its response arrived or failed).
    /// `None` for an unknown or cancelled id: drop the response.
    pub fn take(&mut self, id: u64) -> Option<LoadRequest> {
        let f = self.in_flight.remove(&id)?;
        self.by_block.remove(&(f.request.tree, f.request.block));
        self.bytes_in_flight = self
            .bytes_in_flight
            .saturating_sub(f.request.record.size as u64);
        Some(f.request)
    }

    /// The requests in flight, in no particular order.
    pub fn in_flight_requests(&self) -> impl Iterator<Item = &LoadRequest> {
        self.in_flight.values().map(|f| &f.request)
    }

    /// Cancel every in-flight request for which `relevant` is false.
    pub fn retain_relevant(&mut self, mut relevant: impl FnMut(&LoadRequest) -> bool) -> Vec<u64> {
        let gone: Vec<u64> = self
            .in_flight
            .iter()
            .filter(|(_, f)| !relevant(&f.request))
            .map(|(id, _)| *id)
            .collect();
        for id in &gone {
            self.take(*id);
        }
        gone
    }

    /// One frame's selection from this frame's triggered requests.
    pub fn select(&mut self, triggered: Vec<LoadRequest>) -> Selected {
        let mut best: FastMap<(Tree, BlockId), LoadRequest> = FastMap::default();
        for r in triggered {
            if !r.importance.is_finite() {
                continue;
            }
            let e = best.entry((r.tree, r.block)).or_insert(r);
            if r.importance > e.importance {
                *e = r;
            }
        }
        let mut out = Selected::default();
        // Refresh or age in-flight requests.
        let mut stale = vec![];
        for (id, f) in self.in_flight.iter_mut() {
            f.age = f.age.saturating_add(1);
            if f.age > self.config.timeout_frames {
                stale.push(*id);
                continue;
            }
            match best.remove(&(f.request.tree, f.request.block)) {
                Some(r) => {
                    f.request.importance = r.importance;
                    f.missed = 0;
                }
                None => {
                    f.missed += 1;
                    if f.missed >= self.config.cancel_after_frames.max(1) {
                        stale.push(*id);
                    }
                }
            }
        }
        stale.sort_unstable();
        for id in stale {
            self.take(id);
            out.cancel.push(id);
        }
        let mut waiting: Vec<LoadRequest> = best.into_values().collect();
        waiting.sort_by(|a, b| {
            b.importance
                .total_cmp(&a.importance)
                .then(a.block.cmp(&b.block))
        });
        let mut waiting = waiting.into_iter().peekable();
        let new_max = self.config.max_new_per_frame;
        while out.send.len() < new_max {
            let Some(r) = waiting.peek() else { break };
            if !self.fits(r) {
                break;
            }
            let Some(r) = waiting.next() else { break };
            out.send.push((self.push(r), r));
        }
        // Pre-emption of the least important in-flight request.
        for _ in 0..self.config.max_in_flight {
            if out.send.len() >= new_max {
                break;
            }
            let Some(next) = waiting.peek() else { break };
            let worst = self
                .in_flight
                .iter()
                .min_by(|a, b| a.1.request.importance.total_cmp(&b.1.request.importance))
                .map(|(id, f)| (*id, f.request.importance));
            match worst {
                Some((id, imp)) if imp + self.config.preempt_margin < next.importance => {
                    self.take(id);
                    out.cancel.push(id);
                    if let Some(r) = waiting.next() {
                        out.send.push((self.push(r), r));
                    }
                }
                _ => break,
            }
        }
        out
    }

    fn push(&mut self, r: LoadRequest) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        self.in_flight.insert(
            id,
            InFlight {
                request: r,
                missed: 0,
                age: 0,
                sent_at: self.clock,
            },
        );
        self.by_block.insert((r.tree, r.block), id);
        self.bytes_in_flight += r.record.size as u64;
        id
    }
}

/// A split or merge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum OpKind {
    /// Split a fully loaded leaf.
    Split,
    /// Merge a block's leaf children back.
    Merge,
}

/// A triggered tree operation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TreeOp {
    /// Split or merge.
    pub kind: OpKind,
    /// The tree.
    pub tree: Tree,
    /// The block split, or the parent merged.
    pub block: BlockId,
    /// Request importance.
    pub importance: f64,
}

/// The split/merge queue: the `capacity` most important distinct triggered
/// operations (a block gets at most one), most important first.
pub fn select_tree_ops(triggered: Vec<TreeOp>, capacity: usize) -> Vec<TreeOp> {
    let mut best: FastMap<(Tree, BlockId), TreeOp> = FastMap::default();
    for op in triggered {
        if !op.importance.is_finite() {
            continue;
        }
        let e = best.entry((op.tree, op.block)).or_insert(op);
        if op.importance > e.importance {
            *e = op;
        }
    }
    let mut v: Vec<TreeOp> = best.into_values().collect();
    v.sort_by(|a, b| {
        b.importance
            .total_cmp(&a.importance)
            .then(a.block.cmp(&b.block))
    });
    v.truncate(capacity);
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use planet_core::Face;
    use proptest::prelude::*;

    /// Any f64 other than NaN, sign, exponent and mantissa at random.
    fn any_number() -> impl Strategy<Value = f64> {
        prop_oneof![
            any::<f64>().prop_filter("not NaN", |x| !x.is_nan()),
            Just(0.0),
            Just(-0.0),
            Just(f64::INFINITY),
            Just(f64::NEG_INFINITY),
            Just(f64::MIN_POSITIVE),
            -1.0f64..1.0,
        ]
    }

    proptest! {
        /// The wire priority keeps the importance's order: never reversed,
        /// and strict beyond a relative 2⁻²⁰ (the mantissa bits kept).
        #[test]
        fn stream_priority_keeps_the_order(a in any_number(), b in any_number()) {
            // In the total order: −0 below +0, as the map has them.
            let (lo, hi) = if a.total_cmp(&b).is_le() { (a, b) } else { (b, a) };
            let (p, q) = (stream_priority(lo), stream_priority(hi));
            prop_assert!(p <= q, "{lo} -> {p}, {hi} -> {q}");
            let apart = |x: f64, y: f64| x.abs() > y.abs() * (1.0 + 2f64.powi(-19));
            let same_sign = lo.signum() == hi.signum() && lo != 0.0;
            if lo.is_normal() && hi.is_normal() && same_sign && (apart(hi, lo) || apart(lo, hi)) {
                prop_assert!(p < q, "{lo} and {hi} share {p}");
            }
            prop_assert!(stream_priority(f64::NAN) <= p);
        }
    }

    #[test]
    fn stream_priorities_of_prefetch_zero_and_loads() {
        // A prefetch (negative) below a present load, zero between them.
        let prefetch = stream_priority(crate::refinement::ahead_priority(1e-3));
        assert!(prefetch < stream_priority(0.0) && stream_priority(0.0) < stream_priority(1e-9));
        assert!(stream_priority(1e-9) < stream_priority(1e-4));
        assert_eq!(stream_priority(f64::NAN), i32::MIN);
        assert!(stream_priority(f64::NEG_INFINITY) > i32::MIN);
        assert_eq!(stream_priority(f64::INFINITY), 0x7ff0_0000);
    }

    fn req(x: u32, imp: f64) -> LoadRequest {
        LoadRequest {
            tree: Tree::Elevation,
            block: BlockId::new(Face::NORTH, 5, x, 0).unwrap(),
            record: ChildRef::default(),
            importance: imp,
            forced: false,
        }
    }

    #[test]
    fn failing_blocks_back_off_exponentially_until_they_load() {
        let mut b = RetryBackoff::default();
        let (t, blk) = (Tree::Elevation, BlockId::root(planet_core::Face::ALL[0]));
        assert!(b.ready(t, &blk, 0.0));
        let mut now = 0.0;
        let mut waits = vec![];
        for _ in 0..12 {
            b.failed(t, blk, now);
            let mut later = now;
            while !b.ready(t, &blk, later) {
                later += 0.01;
            }
            waits.push(later - now);
            now = later;
        }
        assert!((waits[0] - 0.1).abs() < 0.02, "{waits:?}");
        assert!((waits[1] - 0.2).abs() < 0.02, "{waits:?}");
        assert!((waits[4] - 1.6).abs() < 0.02, "{waits:?}");
        assert!((waits[11] - RetryBackoff::MAX).abs() < 0.02, "{waits:?}");
        // Another block is not affected; success forgets.
        let other = blk.children()[0];
        assert!(b.ready(t, &other, now));
        b.succeeded(t, &blk);
        assert!(b.ready(t, &blk, now) && b.is_empty());
    }

    #[test]
    fn fills_dedups_and_cancels() {
        let mut q = RequestQueue::new(QueueConfig {
            max_in_flight: 2,
            cancel_after_frames: 1,
            preempt_margin: 2.0,
            timeout_frames: 100,
            max_new_per_frame: usize::MAX,
        });
        let s = q.select(vec![req(0, 1.0), req(1, 3.0), req(2, 2.0), req(1, 0.5)]);
        assert_eq!(
            s.send.iter().map(|s| s.1.block.x).collect::<Vec<_>>(),
            vec![1, 2]
        );
        assert!(s.cancel.is_empty());
        // Same triggers: nothing new, no duplicates.
        let s = q.select(vec![req(0, 1.0), req(1, 3.0), req(2, 2.0)]);
        assert!(s.send.is_empty() && s.cancel.is_empty());
        // Block 2 no longer triggered: cancelled, block 0 takes its slot.
        let s2 = q.select(vec![req(0, 1.0), req(1, 3.0)]);
        assert_eq!(s2.cancel.len(), 1);
        assert_eq!(s2.send.len(), 1);
        assert_eq!(s2.send[0].1.block.x, 0);
        // A much more important request pre-empts the worst.
        let s3 = q.select(vec![req(0, 1.0), req(1, 3.0), req(9, 10.0)]);
        assert_eq!(s3.cancel, vec![s2.send[0].0]);
        assert_eq!(s3.send[0].1.block.x, 9);
        assert_eq!(q.in_flight(), 2);
        // Responses: known once, then unknown.
        let id = s3.send[0].0;
        assert!(q.take(id).is_some());
        assert!(q.take(id).is_none());
    }

    #[test]
    fn byte_window_and_per_frame_cap() {
        let sized = |x: u32, size: u32| LoadRequest {
            record: ChildRef {
                size,
                ..ChildRef::default()
            },
            ..req(x, 10.0 - x as f64)
        };
        let mut q = RequestQueue::new(QueueConfig {
            max_in_flight: 100,
            max_new_per_frame: 3,
            ..QueueConfig::default()
        });
        q.set_window_bytes(Some(10_000));
        // The first is always sent, even over the window.
        let s = q.select(vec![sized(0, 20_000), sized(1, 100)]);
        assert_eq!(s.send.len(), 1);
        assert_eq!(q.bytes_in_flight(), 20_000);
        let id = s.send[0].0;
        q.take(id);
        assert_eq!(q.bytes_in_flight(), 0);
        // Four fit the window; three a frame.
        let v: Vec<_> = (1..6).map(|x| sized(x, 2_500)).collect();
        let s = q.select(v.clone());
        assert_eq!(s.send.len(), 3);
        let s = q.select(v);
        assert_eq!(s.send.len(), 1);
        assert_eq!(q.bytes_in_flight(), 10_000);
    }

    #[test]
    fn tree_ops_keep_best() {
        let b = BlockId::root(Face::NORTH);
        let op = |imp| TreeOp {
            kind: OpKind::Split,
            tree: Tree::Elevation,
            block: b,
            importance: imp,
        };
        let v = select_tree_ops(vec![op(1.0), op(3.0), op(f64::NAN)], 8);
        assert_eq!(v.len(), 1);
        assert_eq!(v[0].importance, 3.0);
    }
}
