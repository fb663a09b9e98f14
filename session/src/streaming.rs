//! A [`Client`] driven over the network: the per-frame glue between the
//! reconnecting QUIC [`Session`] and the client's frame loop.
//!
//! Each [`StreamingClient::frame`]:
//!
//! 1. drains the session's events: records go to [`Client::deliver`];
//!    failures are delivered as errors, so the client forgets the request and
//!    a later frame's selection requests the block again (after a per-block
//!    exponential backoff when the record itself failed); `Disconnected`
//!    keeps the tree (the session reconnects by itself, and requests issued
//!    meanwhile fail at once and are re-requested after `Connected`);
//! 2. runs [`Client::frame`];
//! 3. sends every new request with [`SessionHandle::request`] and cancels
//!    with [`SessionHandle::cancel`].
//!
//! It counts every response byte received, including bytes the client drops
//! as irrelevant (responses to cancelled requests, stale blocks).
//!
//! If a reconnect welcomes the client with a different header (a new version
//! of the database), the partial tree is discarded and a new [`Client`] is
//! built from the new header.

use crate::http::HttpSessionConfig;
use crate::net::{NetError, NetEvent, Session, SessionConfig, SessionHandle};
use planet_client::{Camera, Client, ClientConfig, ClientError, FrameOutput, TransportError};
use planet_core::format::{FormatError, Header};
use std::collections::HashSet;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Why a [`StreamingClient`] could not start.
#[derive(Debug, Error)]
pub enum StreamingError {
    /// No welcome within the timeout.
    #[error("no welcome from the server within {timeout:?}{}", last.as_ref().map(|e| format!(" (last error: {e})")).unwrap_or_default())]
    Timeout {
        /// The timeout.
        timeout: Duration,
        /// The session's last connection error, if any.
        last: Option<NetError>,
    },
    /// The welcome's header does not decode.
    #[error("bad database header: {0}")]
    Header(#[from] FormatError),
    /// The client refused the header.
    #[error(transparent)]
    Client(#[from] ClientError),
}

/// Network-level counters of a [`StreamingClient`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NetCounters {
    /// Requests handed to the session.
    pub requests: u64,
    /// Cancellations handed to the session.
    pub cancels: u64,
    /// Response bytes received (all of them).
    pub bytes_received: u64,
    /// Of those, bytes of responses to requests cancelled before they
    /// arrived (the part of cancelled transfers that reached the client).
    pub bytes_after_cancel: u64,
    /// Records received.
    pub records: u64,
    /// Requests that failed (network or server error).
    pub failures: u64,
    /// `Connected` events (1 + reconnects).
    pub connects: u64,
    /// `Disconnected` events.
    pub disconnects: u64,
    /// Clients rebuilt because a reconnect brought a different header.
    pub header_changes: u64,
}

/// A [`Client`] streaming from a server through a [`SessionHandle`].
pub struct StreamingClient {
    /// The client (partial tree, queue, statistics).
    pub client: Client,
    session: SessionHandle,
    runtime: tokio::runtime::Handle,
    header: Header,
    header_bytes: Vec<u8>,
    client_cfg: ClientConfig,
    connected: bool,
    counters: NetCounters,
    cancelled: HashSet<u64>,
    connected_at: Option<Instant>,
}

impl StreamingClient {
    /// Spawns the session on `runtime`, waits up to `timeout` for the
    /// welcome, decodes its header and builds the client. Blocks: call it
    /// from outside the runtime's worker threads.
    pub fn connect(
        runtime: &tokio::runtime::Handle,
        session: SessionConfig,
        client_cfg: ClientConfig,
        timeout: Duration,
    ) -> Result<StreamingClient, StreamingError> {
        let handle = Session::spawn(runtime, session);
        StreamingClient::with_session(runtime, handle, client_cfg, timeout)
    }

    /// [`StreamingClient::connect`] over HTTP/2 byte ranges from any HTTPS
    /// server ([`crate::http`]).
    pub fn connect_http(
        runtime: &tokio::runtime::Handle,
        session: HttpSessionConfig,
        client_cfg: ClientConfig,
        timeout: Duration,
    ) -> Result<StreamingClient, StreamingError> {
        let handle = Session::spawn_http(runtime, session);
        StreamingClient::with_session(runtime, handle, client_cfg, timeout)
    }

    /// Waits up to `timeout` for the welcome of a session already spawned
    /// on `runtime` (any transport) and builds the client.
    pub fn with_session(
        runtime: &tokio::runtime::Handle,
        handle: SessionHandle,
        client_cfg: ClientConfig,
        timeout: Duration,
    ) -> Result<StreamingClient, StreamingError> {
        let deadline = Instant::now() + timeout;
        let mut counters = NetCounters::default();
        let welcome = loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                let last = handle.last_error();
                handle.close();
                return Err(StreamingError::Timeout { timeout, last });
            }
            if let Some(NetEvent::Connected(w)) =
                handle.wait_event(left.min(Duration::from_millis(50)))
            {
                break w;
            }
        };
        counters.connects = 1;
        let header = Header::decode(&welcome.header, Some(welcome.file_size))?;
        let client = Client::new(header.clone(), client_cfg)?;
        Ok(StreamingClient {
            client,
            session: handle,
            runtime: runtime.clone(),
            header,
            header_bytes: welcome.header,
            client_cfg,
            connected: true,
            counters,
            cancelled: HashSet::new(),
            connected_at: Some(Instant::now()),
        })
    }

    /// The database header (from the latest welcome).
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// The runtime the session runs on.
    pub fn runtime(&self) -> &tokio::runtime::Handle {
        &self.runtime
    }

    /// The session (e.g. for its last error).
    pub fn session(&self) -> &SessionHandle {
        &self.session
    }

    /// One frame: deliver what arrived, select, send and cancel.
    pub fn frame(&mut self, camera: &Camera, dt: f64) -> FrameOutput {
        self.drain_events();
        if let Some(rtt) = self.session.rtt() {
            self.client.observe_rtt(rtt.as_secs_f64());
        }
        let out = self.client.frame(camera, dt);
        for s in &out.send {
            self.session
                .request_with(s.id, s.record.offset, s.record.size, s.refs, s.priority);
        }
        self.counters.requests += out.send.len() as u64;
        for &id in &out.cancel {
            self.session.cancel(id);
            self.cancelled.insert(id);
        }
        self.counters.cancels += out.cancel.len() as u64;
        out
    }

    fn drain_events(&mut self) {
        for ev in self.session.poll_events() {
            match ev {
                NetEvent::Record { id, bytes } => {
                    let n = bytes.len() as u64;
                    self.counters.bytes_received += n;
                    self.counters.records += 1;
                    if self.cancelled.remove(&id) {
                        self.counters.bytes_after_cancel += n;
                    }
                    self.client.deliver(id, Ok(bytes));
                }
                NetEvent::Failed { id, error } => {
                    self.counters.failures += 1;
                    self.cancelled.remove(&id);
                    // A failure of the record backs its block off; one of
                    // the connection does not (reconnecting is the session's):
                    // the client tells them apart by the variant.
                    self.client.deliver(id, Err(TransportError::from(error)));
                }
                NetEvent::Cancelled { id } => {
                    self.cancelled.remove(&id);
                }
                NetEvent::Disconnected => {
                    self.connected = false;
                    self.counters.disconnects += 1;
                    self.connected_at = None;
                }
                NetEvent::Connected(w) => {
                    self.connected = true;
                    self.counters.connects += 1;
                    self.connected_at = Some(Instant::now());
                    if w.header != self.header_bytes {
                        if let Ok(h) = Header::decode(&w.header, Some(w.file_size)) {
                            if let Ok(c) = Client::new(h.clone(), self.client_cfg) {
                                self.client = c;
                                self.header = h;
                                self.header_bytes = w.header;
                                self.counters.header_changes += 1;
                                self.cancelled.clear();
                            }
                        }
                    }
                }
            }
        }
    }

    /// Response bytes received so far (including dropped ones).
    pub fn bytes_received(&self) -> u64 {
        self.counters.bytes_received
    }

    /// Network counters.
    pub fn counters(&self) -> NetCounters {
        self.counters
    }

    /// True while the session is connected (as of the last frame's events).
    pub fn is_connected(&self) -> bool {
        self.connected && self.session.is_connected()
    }

    /// When the current connection was welcomed (`None` while disconnected).
    pub fn connected_at(&self) -> Option<Instant> {
        self.connected_at
    }

    /// Closes the session gracefully and stops the client's workers.
    pub fn close(self) {
        self.session.close();
        drop(self);
    }
}
