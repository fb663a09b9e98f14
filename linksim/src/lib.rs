//! `planet-linksim`: an in-process UDP relay that simulates a network link
//! between a real (QUIC) client and a real server, for tests and benchmarks
//! on machines without netem; and the same shaping for kernel TCP through
//! TUN devices and a network namespace ([`TcpLink`]).
//!
//! ```no_run
//! # async fn demo(server: std::net::SocketAddr) -> std::io::Result<()> {
//! use planet_linksim::{Link, LinkConfig};
//! let cfg: LinkConfig = "10mbit,50ms,1%loss".parse().expect("valid link");
//! let link = Link::start(server, cfg.clone(), cfg.with_seed(1)).await?;
//! // Point the client at link.local_addr() instead of `server`.
//! let _client_target = link.local_addr();
//! link.set_blackhole(true); // the link goes down ...
//! link.set_blackhole(false); // ... and comes back
//! println!("{:?}", link.stats());
//! # Ok(()) }
//! ```
//!
//! # Topology
//! [`Link::start`] binds one UDP socket on `127.0.0.1:0`. Each distinct client
//! address that sends to it gets its own upstream socket towards the server
//! (like a NAT mapping), so several clients can share a link and the server
//! sees them as different peers; the server's replies on that upstream socket
//! go back to that client. Datagrams reaching an upstream socket from anyone
//! but the server are ignored. A client idle for
//! [`SESSION_IDLE_TIMEOUT`] loses its mapping.
//!
//! # What is modelled
//! Each direction (up = client → server, down = server → client) has its own
//! [`LinkConfig`] and is shaped independently, and within a direction all
//! clients share it, as at a real bottleneck:
//! 1. **Bottleneck**: a drop-tail FIFO queue of `queue_limit_bytes` drained
//!    at `bandwidth_bps` (serialisation delay of payload +
//!    [`PER_PACKET_OVERHEAD`] bytes per datagram). A datagram that would
//!    overflow the queue is dropped (`packets_dropped_queue`).
//! 2. **Random loss**: Bernoulli with probability `loss`, after the
//!    bottleneck (a lost packet used its share of capacity).
//! 3. **Propagation**: `delay` ± uniform `jitter`. Jitter does *not* reorder
//!    packets: a packet is never delivered before one that entered the
//!    direction before it (unless that one was picked for reordering), so
//!    under dense traffic jitter shifts the delay slightly upwards.
//! 4. **Reordering**: with probability `reorder` a packet is held back an
//!    extra `reorder_delay` × U(0.5, 1.5) and packets behind it overtake it.
//! 5. **Blackhole** ([`Link::set_blackhole`]): every datagram is dropped,
//!    both arriving ones and those already in flight, until it is lifted.
//!
//! Random decisions come from a ChaCha8 RNG seeded with `seed` (the up and
//! down directions use different ChaCha streams, so equal seeds do not give
//! correlated patterns). Exactly four numbers are drawn per datagram entering
//! a direction, whatever happens to it, so for a given seed the n-th datagram
//! of a direction always gets the same loss / jitter / reorder draws. Timing
//! is real time (tokio timers, about 1 ms resolution), so queue drops and exact
//! delivery times are not reproducible.
//!
//! # What is not modelled
//! - no MTU (datagrams of any size pass, nothing is fragmented or dropped for
//!   size), no ICMP, no packet corruption, no duplication;
//! - no correlated (Gilbert-Elliott / burst) loss, no rate variation over
//!   time except through [`Link::set_up`] / [`Link::set_down`];
//! - no AQM (RED, CoDel, ECN marking): the queue is plain drop-tail;
//! - the two directions do not share capacity (full duplex);
//! - packets in flight are held in memory, at most [`MAX_IN_FLIGHT_BYTES`]
//!   per direction; the relay's own processing adds microseconds of delay.

mod config;
mod delivery;
mod relay;
mod shaper;
pub mod tun;

pub use config::{
    LinkConfig, ParseLinkConfigError, DEFAULT_QUEUE_LIMIT, DEFAULT_REORDER_DELAY,
    MIN_DEFAULT_QUEUE_LIMIT, PER_PACKET_OVERHEAD,
};
pub use relay::{Link, LinkStats, MAX_IN_FLIGHT_BYTES, SESSION_IDLE_TIMEOUT};
pub use tun::{TcpLink, TcpLinkStats};
