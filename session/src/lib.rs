//! The network side of the streaming client: the QUIC session of the
//! planet protocol over quinn, rustls (ring) and tokio.
//!
//! The client's model (partial tree, selection, request queue) is the
//! IO-free crate `planet-client`, as quinn-proto is to quinn; this crate
//! drives it over a real link:
//!
//! - [`net`]: one QUIC [`net::Connection`] (control-stream handshake, one
//!   stream per record) and the reconnecting [`net::Session`] driven from
//!   synchronous code through non-blocking channels.
//! - [`http`]: the same session over HTTP/2 byte ranges from any HTTPS
//!   server ([`net::Session::spawn_http`]).
//! - [`tls`]: client TLS configurations (certificate pinning, the system
//!   roots, the process-wide crypto provider).
//! - [`streaming`]: [`streaming::StreamingClient`], a `planet_client::Client`
//!   fed by a session, frame by frame.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod http;
pub mod net;
pub mod streaming;
pub mod tls;

pub use net::{NetError, NetEvent, Session, SessionConfig, SessionHandle};
pub use streaming::{NetCounters, StreamingClient, StreamingError};
