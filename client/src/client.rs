//! The per-frame client loop: apply finished work, select, request.
//!
//! Implements thesis Alg. 3.1 and the threading of §3.5.2 (see
//! docs/REFERENCES.md), driven by the caller instead of owning threads for the
//! network:
//!
//! 1. at frame start, apply the refines finished by the decode workers
//!    (with [`ClientConfig::decode_wait_s`], after waiting that long at most
//!    for those delivered before the frame) and execute the split/merge
//!    operations selected last frame (re-checking their constraints), so a
//!    frame never sees half a change;
//! 2. update the quality factor from the previous frame's measurement;
//! 3. traverse both trees ([`crate::selection`]) with the horizon-fitted view;
//!    in a frame that applied a forced record (a coarse neighbour loaded so
//!    that a visible block may split, thesis §4.3.3), a first traversal
//!    executes the splits that record unblocks at once, so it is drawn in
//!    the frame it arrives;
//! 4. select load requests ([`crate::request_queue`]): new ones to send,
//!    in-flight ones to cancel; select the split/merge operations for the
//!    next frame start. With [`ClientConfig::eager_children`] the children
//!    of the blocks to split are asked now, from the references and bounds
//!    in their parent's record; one whose answer comes before the split is
//!    executed is held until it is. With [`ClientConfig::lookahead`] the
//!    children that those children's split would ask are asked too, from
//!    the child tables that came with a record ([`crate::lookahead`]).
//!    With [`ClientConfig::prefetch`] the traversal of step 3 also asks,
//!    after everything the present view wants, what the view predicted a
//!    little short of the answers' arrival wants ([`crate::view_prediction`]).
//!
//! The network layer sends each [`Outgoing`] request (one stream per request
//! in QUIC), cancels each id of [`FrameOutput::cancel`], and hands every
//! response (or failure) to [`Client::deliver`]. Decoding (lz4 + codec) runs
//! on `decode_threads` worker threads (std threads and channels); with 0
//! threads it runs inline in `deliver`, which is deterministic (tests).
//! A response whose id is unknown (cancelled), whose block was merged away or
//! already has LOD 0 is dropped and counted; a record that fails to parse,
//! check or decode is rejected and its block is requested again by a later
//! frame's selection.

use crate::link_estimate::LinkEstimator;
use crate::lookahead::{wants_tables, Lookahead};
use crate::quality::{QualityConfig, QualityController, QualityMode};
use crate::refinement::{sanitize_tolerance, Footprint, Kind, Policy, Refiner, DEFAULT_MAX_SSE_PX};
use crate::request_queue::{
    select_tree_ops, LoadRequest, OpKind, QueueConfig, RequestQueue, RetryBackoff, TreeOp,
};
use crate::selection::{children_loads, colour_holds_split, DrawBlock, Selector};
use crate::stats::{FrameStats, Totals};
use crate::tree::{
    decode_record, Decoded, FastMap, FastSet, FirstLod, HeaderError, PartialTree, RefineError,
};
use crate::view_prediction::ViewPredictor;
use crate::visibility::{Camera, View};
use planet_core::codec::TreeCodec;
use planet_core::format::{ChildRef, Header, Tree};
use planet_core::{BlockId, Edge};
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Client parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClientConfig {
    /// Refinement test and request order ([`crate::refinement`]).
    pub policy: Policy,
    /// Pixel tolerance of the screen-space error (every policy but the
    /// thesis's). With a frame-rate or triangle-budget quality mode, the
    /// controller coarsens it (never below this value).
    pub max_sse_px: f64,
    /// Bound the bytes in flight by the link's measured bandwidth-delay
    /// product ([`crate::link_estimate`]) besides the queue's count.
    pub link_window: bool,
    /// Budget of resident sample bytes ([`Client::resident_bytes`]); over
    /// it, the tolerance is coarsened until the least important blocks
    /// merge and the tree fits (`None`: no budget).
    pub memory_budget: Option<u64>,
    /// The load request queue.
    pub queue: QueueConfig,
    /// Split/merge operations executed per frame at most.
    pub tree_ops_per_frame: usize,
    /// Decode worker threads (0: decode inline in [`Client::deliver`]).
    pub decode_threads: usize,
    /// The quality-factor controller.
    pub quality: QualityConfig,
    /// Request only blocks still visible in the view predicted for when
    /// their answer is applied ([`crate::view_prediction`]).
    pub predict_view: bool,
    /// Request the LOD 0 of a splitting block's children in the frame that
    /// chooses the split, instead of in the next one, where the split is
    /// executed ([`Client::frame`]): one frame less per tree level on the
    /// way down.
    pub eager_children: bool,
    /// At frame start, wait up to this many seconds for the records
    /// delivered before the frame to finish decoding, so that they are
    /// applied in it rather than in the next (0: apply what is finished).
    pub decode_wait_s: f64,
    /// Ask the children's tables with the records of blocks likely to
    /// descend, and the children of a coming block's split before its
    /// record arrives ([`crate::lookahead`]): two tree levels per round
    /// trip. Needs a transport that carries `LodRefsRequest`
    /// ([`Outgoing::refs`]); without one, it only uses held records. Only
    /// while the link's window ([`ClientConfig::link_window`]) is at most
    /// half full: when the rate binds rather than the round trip, nothing
    /// is asked ahead.
    pub lookahead: bool,
    /// Prefetch for the view predicted a little short of when an answer
    /// asked now is applied ([`ClientConfig::predict_view`],
    /// [`crate::view_prediction::ViewPredictor::early_frames`]): a visible
    /// leaf that the present view neither loads nor splits is loaded or
    /// split when that view wants it, after everything the present view
    /// wants, and a split block merges only when that view lets it too. A
    /// block is then asked before the view needs it, and still needed when
    /// its answer comes: an approaching camera finds its data about one
    /// latency sooner.
    /// Only while the link's window ([`ClientConfig::link_window`]) is at
    /// most half full, as [`ClientConfig::lookahead`]: a prefetch in flight
    /// would otherwise hold back a request the present view needs.
    pub prefetch: bool,
    /// Give each request its importance as the priority of its response at
    /// the server ([`Outgoing::priority`], docs/PROTOCOL.md §4.10): a
    /// request made after others, when the view has changed, is answered
    /// before those less important still waiting in the server's send
    /// buffer, instead of after all of them.
    pub stream_priority: bool,
}

impl Default for ClientConfig {
    /// [`ClientConfig::for_policy`]`(Policy::Ours, 1 px)`.
    fn default() -> Self {
        ClientConfig::for_policy(Policy::Ours, DEFAULT_MAX_SSE_PX)
    }
}

impl ClientConfig {
    /// The configuration of `policy` at pixel tolerance `max_sse_px`, with
    /// the policy's own queue (see [`crate::refinement`] for the sources):
    ///
    /// | policy | in flight | new per frame | cancel untriggered | pre-empt | view predicted | window | frames from arrival to the children's requests | levels per round trip | prefetch for the view ahead | answers by priority |
    /// |---|---|---|---|---|---|---|---|---|---|---|
    /// | ours | 64 | any | after 10 frames | no | yes | 2 × BDP | 1 | 2 | yes | yes |
    /// | thesis | 16 | any | after 2 frames | by 2 | no | count | 3 | 1 | no | no |
    /// | cesium | 18 | 20 | never | no | no | count | 3 | 1 | no | no |
    /// | breadth | 16 | any | after 2 frames | no | no | count | 3 | 1 | no | no |
    ///
    /// Prefetch: [`ClientConfig::prefetch`] (it needs the view predicted).
    /// Answers by priority: [`ClientConfig::stream_priority`]; without it
    /// the server answers in the order of the requests, and CesiumJS's
    /// requests carry no priority that a server sees (its priority orders
    /// its own heap, `RequestScheduler`).
    /// Levels per round trip: [`ClientConfig::lookahead`]; CesiumJS
    /// requests a tile's children only once the tile is rendered
    /// (`QuadtreePrimitive`'s traversal refines loaded tiles only). The
    /// column before it: a record delivered before frame `a` is applied in
    /// frame `a` and its children requested at the end of it
    /// ([`ClientConfig::decode_wait_s`], [`ClientConfig::eager_children`]),
    /// or decoded on a worker during `a`, applied in `a + 1`, split at the
    /// start of `a + 2` and its children requested at its end. The latter
    /// is CesiumJS's pipeline (docs/REFERENCES.md, "CesiumJS tile
    /// pipeline"): a received tile is transformed on a web worker
    /// (`RECEIVED → TRANSFORMING`) by the load queue at the end of frame
    /// `a`, made `READY` at the end of `a + 1`, and refined by the
    /// selection of `a + 2`, whose load queue requests the children.
    pub fn for_policy(policy: Policy, max_sse_px: f64) -> ClientConfig {
        let base = QueueConfig::default();
        let (queue, predict_view, link_window) = match policy {
            Policy::Ours => (
                QueueConfig {
                    max_in_flight: 64,
                    cancel_after_frames: 10,
                    preempt_margin: f64::INFINITY,
                    ..base
                },
                true,
                true,
            ),
            Policy::Thesis => (base, false, false),
            Policy::Cesium => (
                QueueConfig {
                    max_in_flight: 18,
                    cancel_after_frames: u32::MAX,
                    preempt_margin: f64::INFINITY,
                    max_new_per_frame: 20,
                    ..base
                },
                false,
                false,
            ),
            Policy::Breadth => (
                QueueConfig {
                    preempt_margin: f64::INFINITY,
                    ..base
                },
                false,
                false,
            ),
        };
        ClientConfig {
            policy,
            max_sse_px: sanitize_tolerance(max_sse_px),
            link_window,
            memory_budget: None,
            queue,
            tree_ops_per_frame: 64,
            decode_threads: 2,
            quality: QualityConfig::default(),
            predict_view,
            eager_children: policy == Policy::Ours,
            lookahead: policy == Policy::Ours,
            prefetch: policy == Policy::Ours,
            stream_priority: policy == Policy::Ours,
            decode_wait_s: if policy == Policy::Ours {
                DECODE_WAIT_S
            } else {
                0.0
            },
        }
    }
}

/// [`ClientConfig::decode_wait_s`] of `ours`: 2 ms, an eighth of a 60 Hz
/// frame, against a few hundred microseconds to decode a record.
pub const DECODE_WAIT_S: f64 = 0.002;

/// Why a client cannot start.
#[derive(Debug, Error)]
pub enum ClientError {
    /// The header is unusable.
    #[error(transparent)]
    Header(#[from] HeaderError),
    /// A decode worker could not be started.
    #[error("cannot start decode worker")]
    Thread(#[source] std::io::Error),
}

/// The error a transport reports, kept as its source.
pub type BoxError = Box<dyn std::error::Error + Send + Sync + 'static>;

/// A failed request, as reported by the network layer (or any other
/// transport: a file, a fake server). The variant decides what the client
/// does with the request ([`Client::deliver`]); the transport's own error
/// stays attached as the source.
#[derive(Debug, Error)]
pub enum TransportError {
    /// The request failed because of its connection (lost, not connected),
    /// not because of its record: it is forgotten without the per-block
    /// backoff, so it is requested again as soon as the transport is back.
    #[error("connection failed")]
    Connection(#[source] BoxError),
    /// The request itself failed (server error, stream reset, timeout,
    /// unreadable record): its block is backed off exponentially before it
    /// is requested again.
    #[error("request failed")]
    Request(#[source] BoxError),
}

impl TransportError {
    /// A failure of the connection carrying `e`.
    pub fn connection(e: impl Into<BoxError>) -> TransportError {
        TransportError::Connection(e.into())
    }

    /// A failure of the request carrying `e`.
    pub fn request(e: impl Into<BoxError>) -> TransportError {
        TransportError::Request(e.into())
    }

    /// True for [`TransportError::Connection`].
    pub fn is_connection(&self) -> bool {
        matches!(self, TransportError::Connection(_))
    }
}

/// `e` and its chain of sources, `: `-separated (for [`Client::last_error`]).
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut source = e.source();
    while let Some(c) = source {
        s.push_str(": ");
        s.push_str(&c.to_string());
        source = c.source();
    }
    s
}

/// A request to send.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Outgoing {
    /// Request id, echoed in [`Client::deliver`].
    pub id: u64,
    /// The record to fetch (`offset`, `size`).
    pub record: ChildRef,
    /// Its tree.
    pub tree: Tree,
    /// Its block.
    pub block: BlockId,
    /// Request importance.
    pub importance: f64,
    /// The priority of the response at the server
    /// ([`crate::request_queue::stream_priority`] of the importance), when
    /// [`ClientConfig::stream_priority`] is on: a transport that can sends
    /// it with the request (a QUIC session's `Priority` frame).
    pub priority: Option<i32>,
    /// Forced by a neighbour's split (visibility ignored, §4.3.3).
    pub forced: bool,
    /// Ask for the child tables of the record's children too, each only
    /// if its references' largest error reaches the child's floor (metres,
    /// the record's child order; `LodRefsAboveRequest`, docs/PROTOCOL.md
    /// §4.9; [`crate::lookahead`]). A transport that cannot may send a
    /// `LodRefsRequest` (every table) or a plain request: the client then
    /// gets more tables, or the record alone.
    pub refs: Option<[f32; 4]>,
}

/// What one frame produced.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameOutput {
    /// Blocks to draw, with LODs, neighbour LOD differences and colour.
    pub draw: Vec<DrawBlock>,
    /// New requests to send.
    pub send: Vec<Outgoing>,
    /// In-flight request ids to cancel.
    pub cancel: Vec<u64>,
    /// Statistics.
    pub stats: FrameStats,
}

struct Job {
    tree: Tree,
    block: BlockId,
    forced: bool,
    /// The frame the request was sent in.
    sent_frame: u64,
    width: usize,
    codec: TreeCodec,
    bytes: Vec<u8>,
    first: FirstLod,
}

struct Done {
    tree: Tree,
    block: BlockId,
    forced: bool,
    sent_frame: u64,
    bytes: usize,
    result: Result<Decoded, RefineError>,
}

fn run_job(job: Job) -> Done {
    let result = decode_record(
        job.tree, job.block, job.width, job.codec, &job.bytes, job.first,
    );
    Done {
        tree: job.tree,
        block: job.block,
        forced: job.forced,
        sent_frame: job.sent_frame,
        bytes: job.bytes.len(),
        result,
    }
}

type Outstanding = Arc<(Mutex<usize>, Condvar)>;

/// The streaming client (no network, no GPU).
pub struct Client {
    tree: PartialTree,
    selector: Selector,
    queue: RequestQueue,
    quality: QualityController,
    config: ClientConfig,
    r_min: f64,
    r_max: f64,
    pending_ops: Vec<TreeOp>,
    /// Records that came before their block exists (its parent's split
    /// waits for the next frame start, or its parent's record is still
    /// coming, [`crate::lookahead`]), with the frame their request was sent
    /// in and the frame they came in.
    parked: Vec<(LoadRequest, Vec<u8>, u64, u64)>,
    /// Child references learned early ([`crate::lookahead`]).
    lookahead: Lookahead,
    decoding: FastSet<(Tree, BlockId)>,
    /// Blocks whose load failed or was rejected, held back exponentially.
    backoff: RetryBackoff,
    jobs: Option<Sender<Job>>,
    done_rx: Receiver<Done>,
    done_tx: Sender<Done>,
    outstanding: Outstanding,
    workers: Vec<JoinHandle<()>>,
    frame: u64,
    last_triangles: u64,
    /// The last frame's measured cost ([`Client::observe_frame_cost`]).
    frame_cost: Option<f64>,
    since_last: FrameStats,
    totals: Totals,
    last_error: Option<String>,
    predictor: ViewPredictor,
    link: LinkEstimator,
    clock: f64,
    /// Records applied but not drawn at their new LOD yet, with their bytes.
    not_drawn: FastMap<(Tree, BlockId), u64>,
    /// Factor ≥ 1 on the tolerance while the tree is over its memory budget.
    memory_factor: f64,
}

/// Whether the answer to a request for `block` of tree `t` would be drawn
/// in `view`: an elevation block is culled by its bounds (in view when it
/// has none yet). A colour record textures the elevation leaves under its
/// id, whose node's bounds stay in view well after every block under it
/// has left (on a low, fast flight, colour answers for the ground passing
/// under the camera arrived for nothing): it is culled by those leaves
/// (the walk starts at that node).
fn in_view(tree: &PartialTree, t: Tree, block: &BlockId, view: &View) -> bool {
    match t {
        Tree::Elevation => tree
            .elevation()
            .get(block)
            .and_then(|n| n.bounds.as_ref())
            .is_none_or(|b| view.is_visible(b)),
        Tree::Colour => tree.elevation().leaves_in_view(block, view),
    }
}

impl Client {
    /// A client for the database described by `header`.
    pub fn new(header: Header, config: ClientConfig) -> Result<Client, ClientError> {
        let r_min = (header.datum.polar_radius() + (header.min_elevation as f64).min(0.0)).max(0.0);
        let r_max = header.datum.equatorial_radius() + (header.max_elevation as f64).max(0.0);
        let tree = PartialTree::new(Arc::new(header))?;
        let (done_tx, done_rx) = channel::<Done>();
        let outstanding: Outstanding = Arc::new((Mutex::new(0), Condvar::new()));
        let mut workers = vec![];
        let jobs = if config.decode_threads > 0 {
            let (tx, rx) = channel::<Job>();
            let rx = Arc::new(Mutex::new(rx));
            for k in 0..config.decode_threads {
                let rx = rx.clone();
                let done = done_tx.clone();
                let outstanding = outstanding.clone();
                let h = std::thread::Builder::new()
                    .name(format!("planet-decode-{k}"))
                    .spawn(move || loop {
                        let job = match rx.lock() {
                            Ok(r) => r.recv(),
                            Err(_) => return,
                        };
                        let Ok(job) = job else { return };
                        let d = run_job(job);
                        let _ = done.send(d);
                        let (m, cv) = &*outstanding;
                        if let Ok(mut n) = m.lock() {
                            *n = n.saturating_sub(1);
                            cv.notify_all();
                        }
                    })
                    .map_err(ClientError::Thread)?;
                workers.push(h);
            }
            Some(tx)
        } else {
            None
        };
        Ok(Client {
            tree,
            selector: Selector::new(),
            queue: RequestQueue::new(config.queue),
            quality: QualityController::new(quality_config(&config)),
            config,
            r_min,
            r_max,
            pending_ops: vec![],
            parked: vec![],
            lookahead: Lookahead::new(),
            decoding: FastSet::default(),
            backoff: RetryBackoff::default(),
            jobs,
            done_rx,
            done_tx,
            outstanding,
            workers,
            frame: 0,
            last_triangles: 0,
            frame_cost: None,
            since_last: FrameStats::default(),
            totals: Totals::default(),
            last_error: None,
            predictor: ViewPredictor::new(),
            link: LinkEstimator::new(),
            clock: 0.0,
            not_drawn: FastMap::default(),
            memory_factor: 1.0,
        })
    }

    /// The partial tree.
    pub fn tree(&self) -> &PartialTree {
        &self.tree
    }

    /// The largest projected texel size in pixels of the colour drawn on
    /// `draw` (a frame's draw list) seen from `camera`: 0 where every drawn
    /// colour block is at its finest data or has no colour tree. The colour
    /// counterpart of [`FrameStats::max_screen_error`], measured as the
    /// colour refinement test measures it ([`Refiner::drawn_texel`]), with
    /// the client's tolerance. For reports (`planet-bench flight`): it
    /// measures every distinct colour block drawn, which the frame itself
    /// does not need.
    pub fn colour_screen_error(&self, camera: &Camera, draw: &[DrawBlock]) -> f64 {
        let Some(ct) = self.tree.colour() else {
            return 0.0;
        };
        let et = self.tree.elevation();
        let view = View::new(camera, self.r_min, self.r_max);
        let tol = sanitize_tolerance(self.config.max_sse_px);
        let refiner = Refiner::new(Policy::Ours, &view, 1.0, tol);
        let cw = ct.width as f64;
        let mut seen: FastSet<BlockId> = FastSet::default();
        let mut worst = 0.0f64;
        for c in draw.iter().filter_map(|d| d.colour) {
            if !seen.insert(c.block) {
                continue;
            }
            let (Some(n), Some(b)) = (
                ct.get(&c.block),
                et.get(&c.block).and_then(|e| e.bounds.as_ref()),
            ) else {
                continue;
            };
            let m = refiner.measure(
                Kind::Colour,
                &Footprint::of(b),
                cw,
                n.record.error as f64,
                n.child_error(),
            );
            worst = worst.max(refiner.drawn_texel(&m, c.lod));
        }
        worst
    }

    /// The selection cache (e.g. its rebuild count).
    pub fn selector(&self) -> &Selector {
        &self.selector
    }

    /// The request queue.
    pub fn queue(&self) -> &RequestQueue {
        &self.queue
    }

    /// The current quality factor.
    pub fn quality_factor(&self) -> f64 {
        self.quality.qf()
    }

    /// The configuration.
    pub fn config(&self) -> &ClientConfig {
        &self.config
    }

    /// The pixel tolerance in force: the configured one, coarsened by the
    /// quality controller when it regulates a frame rate or triangle budget
    /// (triangles ∝ 1/tolerance², so `tol = max_sse · sqrt(QF₀ / QF)`, never
    /// below `max_sse`).
    /// The memory budget ([`ClientConfig::memory_budget`]) coarsens it
    /// further while the tree is over budget.
    pub fn tolerance(&self) -> f64 {
        tolerance_for(&self.config, self.quality.qf()) * self.memory_factor
    }

    /// Approximate bytes of resident samples: a full grid per node of each
    /// tree (elevation `(W+1)²` 16-bit samples, colour `Wc²` RGB texels; the
    /// split nodes' grids are counted too, an over-estimate of at most a
    /// third).
    pub fn resident_bytes(&self) -> u64 {
        let e = self.tree.elevation();
        let mut b = e.len() as u64 * ((e.width + 1) * (e.width + 1) * 2) as u64;
        if let Some(c) = self.tree.colour() {
            b += c.len() as u64 * (c.width * c.width * 3) as u64;
        }
        b
    }

    /// The refiner this client would use for `view` now.
    pub fn refiner(&self, view: &View) -> Refiner {
        Refiner::new(
            self.config.policy,
            view,
            self.quality.qf(),
            self.tolerance(),
        )
    }

    /// A round-trip time measured by the transport (seconds), for the
    /// request window ([`crate::link_estimate`]).
    pub fn observe_rtt(&mut self, seconds: f64) {
        self.link.observe_rtt(seconds);
    }

    /// The link estimate behind the request window.
    pub fn link(&self) -> &LinkEstimator {
        &self.link
    }

    /// The measured cost of the last frame in seconds: the caller's CPU and
    /// GPU work for it, not the wait for a display refresh. The next
    /// [`Client::frame`] feeds it to the frame-rate controller instead of
    /// `dt`, which a vsynced display caps at its rate ([`crate::quality`]).
    pub fn observe_frame_cost(&mut self, seconds: f64) {
        self.frame_cost = Some(seconds);
    }

    /// The quality controller (e.g. to change its mode).
    pub fn quality_mut(&mut self) -> &mut QualityController {
        &mut self.quality
    }

    /// Min and max planet radii used for the horizon.
    pub fn radii(&self) -> (f64, f64) {
        (self.r_min, self.r_max)
    }

    /// Cumulative statistics.
    pub fn totals(&self) -> Totals {
        self.totals
    }

    /// The last rejection reason, if any.
    pub fn last_error(&self) -> Option<&str> {
        self.last_error.as_deref()
    }

    /// Split/merge operations waiting for the next frame start.
    pub fn pending_ops(&self) -> &[TreeOp] {
        &self.pending_ops
    }

    /// Blocks whose records are being decoded.
    pub fn decoding(&self) -> usize {
        self.decoding.len()
    }

    /// Block until every record handed to the workers has been decoded (for
    /// tests and benchmarks; a renderer never needs to wait).
    pub fn wait_for_decodes(&self) {
        self.wait_for_decodes_until(None);
    }

    /// At frame start: wait up to [`ClientConfig::decode_wait_s`] for the
    /// records delivered before the frame (none without workers).
    fn wait_for_delivered(&self) {
        if self.jobs.is_none() {
            return;
        }
        if let Ok(limit) = Duration::try_from_secs_f64(self.config.decode_wait_s) {
            if !limit.is_zero() {
                self.wait_for_decodes_until(Some(Instant::now() + limit));
            }
        }
    }

    /// Wait until the workers have decoded every record handed to them, or
    /// until `deadline`.
    fn wait_for_decodes_until(&self, deadline: Option<Instant>) {
        let (m, cv) = &*self.outstanding;
        let Ok(mut n) = m.lock() else { return };
        while *n > 0 {
            n = match deadline {
                None => match cv.wait(n) {
                    Ok(n) => n,
                    Err(_) => return,
                },
                Some(d) => {
                    let left = d.saturating_duration_since(Instant::now());
                    if left.is_zero() {
                        return;
                    }
                    match cv.wait_timeout(n, left) {
                        Ok((n, _)) => n,
                        Err(_) => return,
                    }
                }
            };
        }
    }

    /// Hand over the response to request `id` (or its failure). A
    /// [`TransportError::Connection`] is handled as
    /// [`Client::connection_failed`]; a [`TransportError::Request`] backs
    /// its block off.
    pub fn deliver(&mut self, id: u64, result: Result<Vec<u8>, TransportError>) {
        let result = match result {
            Err(e @ TransportError::Connection(_)) => {
                self.connection_failed(id, e);
                return;
            }
            r => r,
        };
        // The frame the request was sent in: its age counts the frames
        // begun since.
        let sent_frame = match self.queue.get(id) {
            Some(f) => {
                if result.is_ok() {
                    self.link.observe_rtt(self.clock - f.sent_at);
                }
                self.frame.saturating_sub(u64::from(f.age))
            }
            None => self.frame,
        };
        let Some(req) = self.queue.take(id) else {
            if let Ok(b) = &result {
                self.since_last.bytes_received += b.len() as u64;
                self.since_last.bytes_dropped += b.len() as u64;
            }
            return;
        };
        let mut bytes = match result {
            Ok(b) => b,
            Err(e) => {
                self.last_error = Some(error_chain(&e));
                self.backoff.failed(req.tree, req.block, self.clock);
                return;
            }
        };
        self.since_last.bytes_received += bytes.len() as u64;
        // The child tables after the record (`LodRefsRequest`).
        if bytes.len() > req.record.size as usize {
            let trailer = bytes.split_off(req.record.size as usize);
            self.since_last.bytes_tables += trailer.len() as u64;
            if req.tree == Tree::Elevation && self.config.lookahead {
                self.lookahead
                    .learn_tables(req.block, &bytes, &trailer, self.frame);
            }
        }
        // A record whose block does not exist yet: a child requested in the
        // frame that chose its parent's split
        // ([`ClientConfig::eager_children`]) whose answer came before the
        // split was executed (a link faster than a frame), or a grandchild
        // asked ahead of its parent's record ([`ClientConfig::lookahead`]).
        // Held until its block exists.
        let early = self
            .tree
            .tree(req.tree)
            .is_some_and(|t| t.get(&req.block).is_none());
        if early
            && (self.config.lookahead
                || self.pending_ops.iter().any(|o| {
                    o.kind == OpKind::Split
                        && o.tree == req.tree
                        && Some(o.block) == req.block.parent()
                }))
            && self.parked.len() < crate::lookahead::MAX_ENTRIES
        {
            if req.tree == Tree::Elevation && self.config.lookahead {
                self.lookahead.learn_record(req.block, &bytes, self.frame);
            }
            self.decoding.insert((req.tree, req.block));
            self.parked.push((req, bytes, sent_frame, self.frame));
            return;
        }
        self.dispatch(req, bytes, sent_frame);
    }

    /// Hand a received record to the decode workers (or decode it inline),
    /// or drop it when its block no longer wants it.
    fn dispatch(&mut self, req: LoadRequest, bytes: Vec<u8>, sent_frame: u64) {
        let first = self
            .tree
            .tree(req.tree)
            .map(|t| (t.width, t.codec))
            .zip(self.tree.first_lod(req.tree, &req.block));
        let Some(((width, codec), first)) = first else {
            self.decoding.remove(&(req.tree, req.block));
            self.since_last.bytes_dropped += bytes.len() as u64;
            return;
        };
        let job = Job {
            tree: req.tree,
            block: req.block,
            forced: req.forced,
            sent_frame,
            width,
            codec,
            bytes,
            first,
        };
        self.decoding.insert((req.tree, req.block));
        match &self.jobs {
            Some(tx) => {
                {
                    let (m, _) = &*self.outstanding;
                    if let Ok(mut n) = m.lock() {
                        *n += 1;
                    }
                }
                if let Err(e) = tx.send(job) {
                    let (m, _) = &*self.outstanding;
                    if let Ok(mut n) = m.lock() {
                        *n = n.saturating_sub(1);
                    }
                    let _ = self.done_tx.send(run_job(e.0));
                }
            }
            None => {
                let _ = self.done_tx.send(run_job(job));
            }
        }
    }

    /// A request failed with its connection (lost, not connected), not
    /// because of its record: it is forgotten without the per-block
    /// backoff, so it is requested again as soon as the session reconnects.
    pub fn connection_failed(&mut self, id: u64, error: TransportError) {
        if self.queue.take(id).is_some() {
            self.last_error = Some(error_chain(&error));
        }
    }

    /// Blocks whose failed or rejected load is held back by the per-block
    /// exponential backoff (a retry is scheduled): the client is not idle.
    pub fn retries_waiting(&self) -> usize {
        self.backoff.waiting(self.clock)
    }

    /// Apply the refines the decode workers have finished (frame step 1).
    fn apply_finished(
        &mut self,
        stats: &mut FrameStats,
        applied: &mut Vec<(Tree, BlockId, usize, bool)>,
    ) {
        while let Ok(d) = self.done_rx.try_recv() {
            self.decoding.remove(&(d.tree, d.block));
            match d.result {
                Ok(dec) => {
                    self.backoff.succeeded(d.tree, &d.block);
                    // Send to application (the frame whose view the record
                    // first serves): the horizon of the view prediction.
                    let frames = self.frame.saturating_sub(d.sent_frame);
                    self.predictor
                        .observe_latency(u32::try_from(frames).unwrap_or(u32::MAX));
                    if self.tree.apply_refine(dec) {
                        stats.refines_applied += 1;
                        applied.push((d.tree, d.block, d.bytes, d.forced));
                    } else {
                        stats.bytes_dropped += d.bytes as u64;
                    }
                }
                Err(e) => {
                    self.backoff.failed(d.tree, d.block, self.clock);
                    stats.records_rejected += 1;
                    self.totals.bytes_rejected += d.bytes as u64;
                    self.last_error = Some(format!("{:?} {:?}: {e}", d.tree, d.block));
                }
            }
        }
    }

    /// One frame: apply finished work, select, request.
    pub fn frame(&mut self, camera: &Camera, dt: f64) -> FrameOutput {
        self.frame += 1;
        let mut stats = std::mem::take(&mut self.since_last);
        stats.frame = self.frame;
        if dt.is_finite() && dt > 0.0 {
            self.clock += dt;
        }
        self.link
            .on_frame(dt, stats.bytes_received, self.queue.in_flight() > 0);
        // 1. Finished refines (those delivered before this frame, when the
        // configuration waits for them).
        self.wait_for_delivered();
        let mut applied: Vec<(Tree, BlockId, usize, bool)> = vec![];
        self.apply_finished(&mut stats, &mut applied);
        // 1b. Split/merge selected last frame, constraints re-checked.
        for op in std::mem::take(&mut self.pending_ops) {
            let r = match op.kind {
                OpKind::Split => self.tree.split(op.tree, &op.block),
                OpKind::Merge => self.tree.merge(op.tree, &op.block),
            };
            if r.is_ok() {
                match op.kind {
                    OpKind::Split => stats.splits += 1,
                    OpKind::Merge => stats.merges += 1,
                }
            }
        }
        // Children's records that came before their parent's split: the
        // split is done, they are applied now.
        // Children's records that came before their parent's split: the
        // split is done, they are applied now. Those whose block does not
        // exist yet wait (their parent's record is still coming), up to
        // KEEP_FRAMES.
        if !self.parked.is_empty() {
            let mut sent = false;
            for (req, bytes, sent_frame, came) in std::mem::take(&mut self.parked) {
                let exists = self
                    .tree
                    .tree(req.tree)
                    .is_some_and(|t| t.get(&req.block).is_some());
                if exists {
                    self.dispatch(req, bytes, sent_frame);
                    sent = true;
                } else if self.frame.saturating_sub(came) <= crate::lookahead::KEEP_FRAMES {
                    self.parked.push((req, bytes, sent_frame, came));
                } else {
                    self.decoding.remove(&(req.tree, req.block));
                    stats.bytes_dropped += bytes.len() as u64;
                }
            }
            if sent {
                self.wait_for_delivered();
                self.apply_finished(&mut stats, &mut applied);
            }
        }
        self.lookahead.prune(&self.tree, self.frame);
        // 2. Quality factor.
        let tris = self.last_triangles as f64;
        let qf = match self.frame_cost.take() {
            Some(cost) => self.quality.update_with_cost(cost, tris),
            None => self.quality.update(dt, tris),
        };
        // 3. Selection. Over the memory budget the tolerance coarsens by
        // 5 % a frame until the least needed blocks merge (MERGE_AT of the
        // tolerance) and the tree fits; under 90 % of it, it relaxes back.
        if let Some(budget) = self.config.memory_budget {
            let r = self.resident_bytes();
            if r > budget {
                self.memory_factor = (self.memory_factor * 1.05).min(1e6);
            } else if (r as f64) < budget as f64 * 0.9 {
                self.memory_factor = (self.memory_factor / 1.05).max(1.0);
            }
        }
        let view = View::new(camera, self.r_min, self.r_max);
        let tol = tolerance_for(&self.config, qf) * self.memory_factor;
        let refiner = Refiner::new(self.config.policy, &view, qf, tol);
        // 3a. A forced record is a coarse neighbour's LOD 0, loaded so that
        // a visible block may split (thesis §4.3.3). The splits it unblocks
        // (the neighbour's own, then the block's) are executed in the frame
        // the record is applied rather than the next: the neighbour is
        // drawn at its new LOD on arrival (its bytes are relevant, not
        // drawn a frame later) and the split comes a frame sooner. Frames
        // without a forced record skip this pass.
        let forced: Vec<(Tree, BlockId)> =
            applied.iter().filter(|a| a.3).map(|a| (a.0, a.1)).collect();
        if !forced.is_empty() {
            let pre = self.selector.select(&self.tree, &view, &refiner, None);
            for op in &pre.ops {
                if op.kind == OpKind::Split
                    && unblocked_by(&self.tree, op, &forced)
                    && self.tree.split(op.tree, &op.block).is_ok()
                {
                    stats.splits += 1;
                }
            }
            self.selector.recycle(pre.draw);
        }
        // Only blocks still visible when the answer will be applied
        // (view_prediction.rs); forced neighbour loads ignore visibility.
        // The answer's block must also be in view half a horizon after that
        // (`stay`, `STAY_HORIZONS`): one the camera is leaving just then
        // would be drawn for a frame or two at best, or not at all.
        let (predicted, stay) = match self
            .predictor
            .predict_stay(camera, self.r_min)
            .filter(|_| self.config.predict_view)
        {
            Some([arrival, after]) => (
                Some(View::new(&arrival, self.r_min, self.r_max)),
                Some(View::new(&after, self.r_min, self.r_max)),
            ),
            None => (None, None),
        };
        // ... and that still need the LOD then: a request whose answer
        // would arrive after it stopped being useful is not sent.
        let later = predicted
            .as_ref()
            .filter(|_| self.config.policy != Policy::Thesis)
            .map(|pv| Refiner::new(self.config.policy, pv, qf, tol));
        // Whether the link's window is at most half full. Asking ahead
        // (the prefetch below, the lookahead after the selection) shortens
        // a chain of round trips; when the window is fuller, the rate
        // binds, not the round trip, and a new request asked ahead (or a
        // child table) would only take the place of one needed now.
        let roomy = !self.config.link_window
            || self.queue.bytes_in_flight() * 2 <= self.link.window_bytes();
        // The prefetch, for the view a little short of that one
        // (`ViewPredictor::early`), while the window has room.
        let early = self
            .predictor
            .early()
            .filter(|_| self.config.prefetch && roomy && later.is_some())
            .map(|e| {
                Refiner::new(
                    self.config.policy,
                    &View::new(&e, self.r_min, self.r_max),
                    qf,
                    tol,
                )
            });
        let sel = self
            .selector
            .select(&self.tree, &view, &refiner, early.as_ref());
        // 4. Requests.
        let tree = &self.tree;

        let ops = select_tree_ops(sel.ops, self.config.tree_ops_per_frame);
        let eager = if self.config.eager_children {
            children_loads(
                tree,
                &ops,
                &view,
                &refiner,
                predicted.as_ref().zip(later.as_ref()),
            )
        } else {
            vec![]
        };
        // The view and refiner of a request's arrival (the present ones
        // without a prediction).
        let arrival = match predicted.as_ref().zip(later.as_ref()) {
            Some((pv, lr)) => (pv, lr),
            None => (&view, &refiner),
        };
        // The lookahead asks ahead only while the window has room
        // (`roomy`: nothing since changed what is in flight). Those already
        // in flight stay asked while the prediction holds: cancelling them
        // when the window fills, to ask them again when it empties, would
        // only waste the link.
        let lookahead = self.config.lookahead && roomy;
        let mut ahead_loads = if self.config.lookahead {
            let e = tree.elevation();
            let seeds: Vec<(BlockId, ChildRef)> = eager
                .iter()
                .map(|r| (r.block, r.record))
                .chain(
                    self.queue
                        .in_flight_requests()
                        .filter(|r| r.tree == Tree::Elevation)
                        .map(|r| (r.block, r.record)),
                )
                .chain(
                    self.parked
                        .iter()
                        .filter(|p| p.0.tree == Tree::Elevation)
                        .map(|p| (p.0.block, p.0.record)),
                )
                .chain(
                    self.decoding
                        .iter()
                        .filter(|(t, _)| *t == Tree::Elevation)
                        .filter_map(|(_, b)| e.get(b).map(|n| (*b, n.record))),
                )
                .collect();
            self.lookahead
                .loads(tree, seeds, &self.decoding, arrival, &refiner, self.frame)
        } else {
            vec![]
        };
        // In flight, a block that no longer wants its LOD 0 is cancelled; a
        // block asked ahead of its parent's split does not exist yet, and
        // stays in flight while this frame asks it.
        let asked_ahead: FastSet<BlockId> =
            eager.iter().chain(&ahead_loads).map(|r| r.block).collect();
        // With a moving camera (a prediction), a block that is neither in
        // view now nor in the view predicted for its answer has left it
        // and will not be drawn when the answer comes: cancelled at once,
        // rather than after `cancel_after_frames` untriggered frames, in
        // which answers kept arriving for the ground passed under a low,
        // fast camera (docs/BENCHMARKS.md, "edge-pass").
        let mut cancel = self.queue.retain_relevant(|r| {
            if r.tree == Tree::Elevation && asked_ahead.contains(&r.block) {
                return true;
            }
            tree.wants_refine(r.tree, &r.block)
                && (r.forced
                    || predicted.as_ref().is_none_or(|pv| {
                        in_view(tree, r.tree, &r.block, &view)
                            || in_view(tree, r.tree, &r.block, pv)
                    }))
        });
        if !lookahead {
            ahead_loads.retain(|r| self.queue.is_in_flight(r.tree, &r.block));
        }
        let (ew, cw) = (
            tree.elevation().width as f64,
            tree.colour().map_or(0.0, |c| c.width as f64),
        );
        let loads = sel
            .loads
            .into_iter()
            .filter(|r| !self.decoding.contains(&(r.tree, r.block)))
            .filter(|r| self.backoff.ready(r.tree, &r.block, self.clock))
            .filter(|r| {
                let (Some(pv), Some(sv)) = (&predicted, &stay) else {
                    return true;
                };
                if r.forced {
                    return true;
                }
                if !in_view(tree, r.tree, &r.block, pv) || !in_view(tree, r.tree, &r.block, sv) {
                    return false;
                }
                let bounds = tree
                    .tree(Tree::Elevation)
                    .and_then(|t| t.get(&r.block))
                    .and_then(|n| n.bounds.as_ref());
                let (Some(later), Some(b)) = (&later, bounds) else {
                    return true;
                };
                let Some(n) = tree.tree(r.tree).and_then(|t| t.get(&r.block)) else {
                    return true;
                };
                let (kind, w) = match r.tree {
                    Tree::Elevation => (Kind::Elevation, ew),
                    Tree::Colour => (Kind::Colour, cw),
                };
                if later.loads_at_arrival(kind, b, w, n.record.error as f64, n.lod) {
                    return true;
                }
                let fp = Footprint::ball(b);
                // An elevation load that colour asked for (its colour block
                // wants children finer than the geometry needs, and may
                // split only under a split elevation block, §4.4.1): kept
                // while the colour block still wants them at arrival.
                r.tree == Tree::Elevation && colour_holds_split(tree, later, &r.block, &fp)
            })
            .chain(
                eager
                    .into_iter()
                    .chain(ahead_loads)
                    .filter(|r| !self.decoding.contains(&(r.tree, r.block)))
                    .filter(|r| self.backoff.ready(r.tree, &r.block, self.clock)),
            )
            .collect();
        if self.config.link_window {
            self.queue.set_window_bytes(Some(self.link.window_bytes()));
        }
        self.queue.set_clock(self.clock);
        let chosen = self.queue.select(loads);
        cancel.extend(chosen.cancel);
        let known = &self.lookahead;
        let stream_priority = self.config.stream_priority;
        // How far the camera can come while a table asked now is kept.
        let approach = self.predictor.step() * crate::lookahead::KEEP_FRAMES as f64;
        let send: Vec<Outgoing> = chosen
            .send
            .into_iter()
            .map(|(id, r)| Outgoing {
                id,
                record: r.record,
                tree: r.tree,
                block: r.block,
                importance: r.importance,
                priority: stream_priority
                    .then(|| crate::request_queue::stream_priority(r.importance)),
                forced: r.forced,
                refs: if lookahead && r.tree == Tree::Elevation {
                    wants_tables(tree, known, arrival, approach, r.block, &r.record)
                } else {
                    None
                },
            })
            .collect();
        self.pending_ops = ops;
        // Stats.
        let draw = sel.draw;
        // A record's samples are drawn when its block is drawn at LOD 0, or
        // one of its children at LOD 1: a split block's LOD 0 is its
        // children's LOD 1 (thesis §3.3.2), so a record that arrived and let
        // the block split (a neighbour's constraint, or colour that refines
        // below the geometry) is drawn through its children. The selector
        // answers that for the few records accounted for (applied now or
        // earlier and not drawn yet) from its flat tree, without a scan of
        // the draw list (two hash probes a drawn block, for a moving eye).
        let selector = &self.selector;
        let drawn_at_lod0 = |t: Tree, b: &BlockId| selector.draws_lod0(t, b);
        // Records applied earlier and drawn now.
        if !self.not_drawn.is_empty() {
            let tree = &self.tree;
            let lookahead = &mut self.lookahead;
            let (mut later, mut tables) = (0u64, 0u64);
            self.not_drawn.retain(|(t, b), bytes| {
                if drawn_at_lod0(*t, b) {
                    let c = lookahead.credit(*t, b);
                    later += *bytes + c;
                    tables += c;
                    return false;
                }
                // Merged away: it can no longer be drawn (split, it may be
                // drawn through its children).
                tree.tree(*t)
                    .and_then(|x| x.get(b))
                    .is_some_and(|n| n.lod == 0)
            });
            self.totals.bytes_drawn_later += later;
            self.totals.bytes_tables_used += tables;
        }
        for (t, b, bytes, forced) in &applied {
            if drawn_at_lod0(*t, b) {
                let c = self.lookahead.credit(*t, b);
                self.totals.bytes_relevant += *bytes as u64 + c;
                self.totals.bytes_tables_used += c;
            } else {
                if *forced {
                    self.totals.bytes_forced += *bytes as u64;
                }
                self.not_drawn.insert((*t, *b), *bytes as u64);
            }
        }
        self.last_triangles = sel.triangles;
        stats.blocks_drawn = draw.len();
        stats.triangles = sel.triangles;
        stats.quality_factor = qf;
        stats.in_flight = self.queue.in_flight();
        stats.sent = send.len();
        stats.cancelled = cancel.len();
        if !draw.is_empty() {
            // One pass over the draw list (larger than a core's cache
            // with 10 000 blocks), summing in the list's order.
            let (mut max, mut sum, mut area, mut weighted) = (0.0, 0.0, 0.0, 0.0);
            for d in &draw {
                max = f64::max(max, d.screen_error);
                sum += d.screen_error;
                area += d.screen_area;
                weighted += d.screen_error * d.screen_area;
            }
            stats.max_screen_error = max;
            stats.mean_screen_error = sum / draw.len() as f64;
            if area > 0.0 {
                stats.pixel_mean_screen_error = weighted / area;
            }
        }
        stats.nodes = self.tree.node_count();
        stats.near = view.near;
        stats.far = view.far;
        self.totals.sent += send.len() as u64;
        self.totals.cancelled += cancel.len() as u64;
        self.totals.bytes_received += stats.bytes_received;
        self.totals.bytes_dropped += stats.bytes_dropped;
        self.totals.bytes_tables += stats.bytes_tables;
        self.totals.refines_applied += stats.refines_applied as u64;
        self.totals.records_rejected += stats.records_rejected as u64;
        stats.totals = self.totals;
        FrameOutput {
            draw,
            send,
            cancel,
            stats,
        }
    }
}

/// Whether `op` splits one of the `forced` blocks (a neighbour that must
/// be at most the level difference coarser splits once its LOD 0 is
/// there, and its record is drawn through its children) or a block that
/// has one of them as an edge neighbour (the split their loads were for).
fn unblocked_by(tree: &PartialTree, op: &TreeOp, forced: &[(Tree, BlockId)]) -> bool {
    let Some(t) = tree.tree(op.tree) else {
        return false;
    };
    forced.contains(&(op.tree, op.block))
        || Edge::ALL.iter().any(|&e| {
            t.neighbour(&op.block, e)
                .is_some_and(|nb| forced.contains(&(op.tree, nb.id)))
        })
}

/// The controller's configuration for `config`: where the pixel tolerance
/// is what QF moves (every policy but the thesis's, whose importance uses QF
/// itself), QF above its initial value leaves the tolerance at its floor
/// ([`tolerance_for`]), so the controller's ceiling is put there
/// (anti-windup, [`crate::quality`]).
fn quality_config(config: &ClientConfig) -> QualityConfig {
    let mut q = config.quality;
    if config.policy != Policy::Thesis {
        q.ceiling = q.ceiling.min(q.initial);
    }
    q
}

/// The tolerance of `config` at quality factor `qf` ([`Client::tolerance`]).
fn tolerance_for(config: &ClientConfig, qf: f64) -> f64 {
    let tol = sanitize_tolerance(config.max_sse_px);
    match config.quality.mode {
        QualityMode::Fixed => tol,
        _ => {
            let k = (config.quality.initial / qf).sqrt();
            if k.is_finite() && k > 1.0 {
                tol * k
            } else {
                tol
            }
        }
    }
}

impl Client {
    /// Hands the draw list of an earlier [`Client::frame`] back, so that
    /// the next frame reuses its allocation instead of allocating (and
    /// faulting in) a fresh one. Optional: a caller that drops its
    /// [`FrameOutput`] instead loses nothing but that reuse.
    pub fn recycle(&mut self, draw: Vec<DrawBlock>) {
        self.selector.recycle(draw);
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        self.jobs = None;
        for h in self.workers.drain(..) {
            let _ = h.join();
        }
    }
}
