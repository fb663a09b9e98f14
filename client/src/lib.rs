//! Streaming client model for planet databases: partial tree, importance,
//! request queue and per-frame selection. No GPU and no network: no socket,
//! no async runtime, no TLS (`scripts/check-deps.sh` checks the dependency
//! tree). The QUIC session that drives it over a real link is the crate
//! `planet-session` (as quinn drives quinn-proto); tests drive it with the
//! fake server of `planet-testkit`.
//!
//! Implements thesis chapter 3 (§3.4–3.6, Alg. 3.1) and the 3D / planetary
//! parts of chapter 4 (§4.2.4, §4.3, §4.4.1, §4.5.4), each concept in one
//! module:
//!
//! - [`tree`]: the two linked partial trees, split / merge / refine,
//!   neighbours by lookup (Alg. 4.1), level-difference and binding
//!   constraints, `validate()`.
//! - [`importance`]: Eq. 3.2–3.4, LOD selection, triggers, screen-space error.
//! - [`refinement`]: the policy: refinement by screen-space error against a
//!   pixel tolerance (default) or by the thesis's importance, and the
//!   request order of ours and of the peers' schedulers.
//! - [`link_estimate`]: the request window sized by the measured
//!   bandwidth-delay product.
//! - [`quality`]: the quality-factor controller (frame rate or triangle budget).
//! - [`visibility`]: camera, frustum, horizon-fitted near/far (Eq. 4.3) and
//!   horizon occlusion.
//! - [`request_queue`]: fixed-size priority queues with per-frame
//!   resubmission and cancellation (§3.5.2).
//! - [`view_prediction`]: the camera extrapolated over the request latency,
//!   so no block about to leave the view is requested.
//! - [`selection`]: the per-frame traversal (draw list, triggers), and its
//!   cached form [`selection::Selector`] that the client runs.
//! - [`client`]: the frame loop, decode workers, and the interface a network
//!   layer and a renderer drive.
//! - [`stats`]: per-frame and cumulative statistics.
//!
//! **Driving it.** Each frame: `let out = client.frame(&camera, dt);` draw
//! `out.draw`, send every `out.send` request (`record.offset`, `record.size`)
//! and cancel every id in `out.cancel`; whenever a response (or an error)
//! arrives, call `client.deliver(id, result)` from the same thread.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod client;
pub mod importance;
pub mod link_estimate;
pub mod lookahead;
pub mod quality;
pub mod refinement;
pub mod request_queue;
pub mod selection;
pub mod stats;
pub mod trajectory;
pub mod tree;
pub mod view_prediction;
pub mod visibility;

pub use client::{
    BoxError, Client, ClientConfig, ClientError, FrameOutput, Outgoing, TransportError,
};
pub use refinement::Policy;
pub use selection::{ColourBinding, DrawBlock, NeighbourLod};
pub use visibility::Camera;
