//! QUIC transport of the planet protocol (client side).
//!
//! - [`Connection`]: one QUIC connection: control-stream handshake, then
//!   [`Connection::fetch`] per record (one bidirectional stream each), or
//!   [`Connection::fetch_refs`] for a record and its children's child
//!   tables (`LodRefsRequest`, docs/PROTOCOL.md §4.8), or
//!   [`Connection::fetch_refs_above`] for those that reach their floors
//!   (`LodRefsAboveRequest`, §4.9).
//!   Dropping a fetch future, or [`FetchHandle::cancel`], stops the stream
//!   with `STREAM_CANCELLED` so the server stops sending.
//! - [`Session`] / [`SessionHandle`]: a reconnecting wrapper running on a
//!   tokio runtime, driven from synchronous code (e.g. a per-frame loop)
//!   through non-blocking channels: `request`, `request_refs`,
//!   `request_refs_above`, `cancel`, `poll_events`.
//!
//! TLS configurations come from [`crate::tls`].

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use planet_client::TransportError;
use planet_protocol::{
    quic, ClientHandshake, ErrorCode, ErrorFloors, ErrorMsg, FrameDecoder, HandshakeOutcome, Hello,
    LodRequest, Message, ProtocolError, RequestKind, Response, ResponseDecoder, StreamPriority,
    Welcome,
};
use quinn::VarInt;
use tokio::sync::{mpsc, oneshot, watch};
use tokio::task::{JoinHandle, JoinSet};

/// Why a connection or a fetch failed.
#[derive(Debug, Clone, thiserror::Error)]
pub enum NetError {
    /// The server answered the request with an error head.
    #[error("server error: {0}")]
    Server(ErrorMsg),
    /// The server refused the handshake (`Error` on the control stream).
    #[error("handshake rejected: {0}")]
    Rejected(ErrorMsg),
    /// The connection is gone (closed by the server, idle timeout, network).
    #[error("connection lost: {reason}")]
    ConnectionLost {
        /// The server's close code, when it closed with a protocol code
        /// (e.g. `ServerBusy`, `ShuttingDown`).
        code: Option<ErrorCode>,
        /// Description.
        reason: String,
    },
    /// A local timeout (connect or fetch) expired.
    #[error("timed out")]
    Timeout,
    /// The server reset the response stream with this code.
    #[error("stream reset by the server (code {0})")]
    Reset(u64),
    /// The server's bytes violate the protocol.
    #[error("protocol error: {0}")]
    Protocol(ProtocolError),
    /// Endpoint or TLS setup failed (the source says why; shared, so the
    /// error stays `Clone` for the session's events).
    #[error("cannot connect")]
    Connect(#[source] Arc<dyn std::error::Error + Send + Sync + 'static>),
    /// The request was cancelled locally.
    #[error("cancelled")]
    Cancelled,
    /// The session is not connected (request while reconnecting).
    #[error("not connected")]
    NotConnected,
}

impl NetError {
    /// The protocol error code, when there is one (server error head,
    /// handshake rejection, close or reset code).
    pub fn code(&self) -> Option<ErrorCode> {
        match self {
            NetError::Server(e) | NetError::Rejected(e) => Some(e.code),
            NetError::ConnectionLost { code, .. } => *code,
            NetError::Reset(c) => ErrorCode::from_quic(*c),
            NetError::Protocol(p) => Some(p.code()),
            _ => None,
        }
    }

    /// A [`NetError::Connect`] with `e` as its source.
    pub fn connect(e: impl std::error::Error + Send + Sync + 'static) -> NetError {
        NetError::Connect(Arc::new(e))
    }

    /// True if the connection is unusable (reconnect), false for a
    /// per-request failure.
    pub fn is_connection_error(&self) -> bool {
        matches!(
            self,
            NetError::ConnectionLost { .. } | NetError::Connect(_) | NetError::NotConnected
        )
    }
}

/// The client's view of a failed request: [`TransportError::Connection`]
/// when the connection is unusable ([`NetError::is_connection_error`]),
/// [`TransportError::Request`] otherwise; the [`NetError`] is the source.
impl From<NetError> for TransportError {
    fn from(e: NetError) -> Self {
        if e.is_connection_error() {
            TransportError::connection(e)
        } else {
            TransportError::request(e)
        }
    }
}

impl From<ProtocolError> for NetError {
    fn from(e: ProtocolError) -> Self {
        NetError::Protocol(e)
    }
}

impl From<quinn::ConnectionError> for NetError {
    fn from(e: quinn::ConnectionError) -> Self {
        let code = match &e {
            quinn::ConnectionError::ApplicationClosed(c) => {
                ErrorCode::from_quic(c.error_code.into_inner())
            }
            _ => None,
        };
        NetError::ConnectionLost {
            code,
            reason: e.to_string(),
        }
    }
}

impl From<quinn::WriteError> for NetError {
    fn from(e: quinn::WriteError) -> Self {
        match e {
            quinn::WriteError::ConnectionLost(c) => c.into(),
            quinn::WriteError::Stopped(code) => NetError::Reset(code.into_inner()),
            other => NetError::ConnectionLost {
                code: None,
                reason: other.to_string(),
            },
        }
    }
}

impl From<quinn::ReadError> for NetError {
    fn from(e: quinn::ReadError) -> Self {
        match e {
            quinn::ReadError::ConnectionLost(c) => c.into(),
            quinn::ReadError::Reset(code) => NetError::Reset(code.into_inner()),
            other => NetError::ConnectionLost {
                code: None,
                reason: other.to_string(),
            },
        }
    }
}

/// Connection tuning.
#[derive(Clone)]
pub struct ConnectOptions {
    /// Limit on the QUIC + TLS handshake and the protocol handshake.
    pub connect_timeout: Duration,
    /// Limit on one fetch; `None` = no limit beyond the connection's.
    pub fetch_timeout: Option<Duration>,
    /// QUIC transport parameters; `None` = [`default_transport`].
    pub transport: Option<Arc<quinn::TransportConfig>>,
    /// Send the `Hello` as 0-RTT early data when resuming a TLS session
    /// with this server (the session tickets live in the rustls
    /// `ClientConfig`): the `Welcome` then arrives one round trip after the
    /// first packet. If the server refuses the early data the `Hello` is
    /// sent again after the handshake.
    pub zero_rtt: bool,
    /// QUIC address-validation tokens (NEW_TOKEN) received from servers,
    /// shared by every connection made with these options (clones share
    /// it). A token lifts the server's anti-amplification limit on a later
    /// connection, so a 0.5-RTT `Welcome` larger than three times the
    /// client's first flight is not held back a round trip.
    pub tokens: Arc<dyn quinn::TokenStore>,
    /// Largest UDP payload the connection's own endpoint accepts (QUIC's
    /// `max_udp_payload_size` transport parameter, which bounds the
    /// server's path-MTU discovery); `None` = [`auto_max_udp_payload`] of
    /// the server address. Set it (up to 65 527) on jumbo-frame networks.
    /// Connections on a shared endpoint ([`Connection::connect_on`]) use
    /// that endpoint's setting ([`new_endpoint_with`]).
    pub max_udp_payload: Option<u16>,
}

impl Default for ConnectOptions {
    fn default() -> Self {
        ConnectOptions {
            connect_timeout: Duration::from_secs(5),
            fetch_timeout: Some(Duration::from_secs(30)),
            transport: None,
            zero_rtt: true,
            tokens: Arc::new(quinn::TokenMemoryCache::default()),
            max_udp_payload: None,
        }
    }
}

impl std::fmt::Debug for ConnectOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ConnectOptions")
            .field("connect_timeout", &self.connect_timeout)
            .field("fetch_timeout", &self.fetch_timeout)
            .field("custom_transport", &self.transport.is_some())
            .field("zero_rtt", &self.zero_rtt)
            .field("max_udp_payload", &self.max_udp_payload)
            .finish_non_exhaustive()
    }
}

/// Client transport defaults: keep-alive under the server's idle timeout,
/// no unidirectional streams.
pub fn default_transport() -> Arc<quinn::TransportConfig> {
    let mut t = quinn::TransportConfig::default();
    t.keep_alive_interval(Some(Duration::from_secs(5)));
    t.max_concurrent_uni_streams(VarInt::from_u32(0));
    if let Ok(idle) = quinn::IdleTimeout::try_from(Duration::from_secs(30)) {
        t.max_idle_timeout(Some(idle));
    }
    Arc::new(t)
}

struct Inner {
    // Kept so the endpoint (and its socket) lives as long as the connection.
    _endpoint: quinn::Endpoint,
    conn: quinn::Connection,
    // Kept open for the life of the connection: dropping it would finish the
    // control stream, which ends the session on the server.
    ctrl_send: Mutex<Option<quinn::SendStream>>,
    goodbye: watch::Receiver<Option<ErrorCode>>,
    ctrl_task: JoinHandle<()>,
    // Opens request streams in the order the requests are made
    // ([`open_in_order`]).
    opener: mpsc::UnboundedSender<Open>,
    opener_task: JoinHandle<()>,
    welcome: Welcome,
    fetch_timeout: Option<Duration>,
    zero_rtt: bool,
    zero_rtt_refused: bool,
    // The server answered a `LodRefsRequest` as an unknown frame: it
    // predates 0x12 or has it turned off. Every request is a `LodRequest`
    // from then on.
    refs_refused: AtomicBool,
    /// The server answered a `LodRefsAboveRequest` (0x13) as unknown.
    floors_refused: AtomicBool,
    /// The server answered a request stream that began with a `Priority`
    /// frame (0x14) as unknown: requests go without it from then on.
    priority_refused: AtomicBool,
}

impl Inner {
    /// Where this connection records that its server refused requests of
    /// `kind` (an unknown frame, docs/PROTOCOL.md §7); none for a plain
    /// `LodRequest`, which every server answers.
    fn refused(&self, kind: RequestKind) -> Option<&AtomicBool> {
        match kind {
            RequestKind::Record => None,
            RequestKind::RecordAndRefs => Some(&self.refs_refused),
            RequestKind::RecordAndRefsAbove(_) => Some(&self.floors_refused),
        }
    }
}

impl Drop for Inner {
    fn drop(&mut self) {
        self.ctrl_task.abort();
        self.opener_task.abort();
        self.conn
            .close(VarInt::from_u32(quic::CONNECTION_CLOSED_NORMAL), b"done");
    }
}

/// A connected, welcomed planet session on one QUIC connection. Cheap to
/// clone (shared); the connection closes when the last clone is dropped or
/// on [`Connection::close`].
#[derive(Clone)]
pub struct Connection {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for Connection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Connection")
            .field("remote", &self.inner.conn.remote_address())
            .field("database", &self.inner.welcome.database)
            .finish()
    }
}

/// `fut` bounded by `opts.connect_timeout` ([`NetError::Timeout`] past it).
async fn within_connect_timeout<T>(
    opts: &ConnectOptions,
    fut: impl std::future::Future<Output = Result<T, NetError>>,
) -> Result<T, NetError> {
    tokio::time::timeout(opts.connect_timeout, fut)
        .await
        .unwrap_or(Err(NetError::Timeout))
}

impl Connection {
    /// Connects with default [`ConnectOptions`].
    pub async fn connect(
        addr: SocketAddr,
        server_name: &str,
        tls: Arc<rustls::ClientConfig>,
        hello: Hello,
    ) -> Result<(Connection, Welcome), NetError> {
        Self::connect_with(addr, server_name, tls, hello, &ConnectOptions::default()).await
    }

    /// Opens a QUIC connection (client endpoint on an ephemeral port of the
    /// address family of `addr`), opens the control stream, sends `hello`
    /// and waits for `Welcome`.
    pub async fn connect_with(
        addr: SocketAddr,
        server_name: &str,
        tls: Arc<rustls::ClientConfig>,
        hello: Hello,
        opts: &ConnectOptions,
    ) -> Result<(Connection, Welcome), NetError> {
        let fut = Self::connect_own_endpoint(addr, server_name, tls, hello, opts);
        within_connect_timeout(opts, fut).await
    }

    /// Like [`Connection::connect_with`], but on an existing client
    /// `endpoint` (one UDP socket) that may carry many connections, e.g. one
    /// from [`new_endpoint`] shared by every connection of a benchmark or a
    /// multi-server client. The endpoint lives as long as any connection
    /// opened on it.
    pub async fn connect_on(
        endpoint: &quinn::Endpoint,
        addr: SocketAddr,
        server_name: &str,
        tls: Arc<rustls::ClientConfig>,
        hello: Hello,
        opts: &ConnectOptions,
    ) -> Result<(Connection, Welcome), NetError> {
        let fut = Self::connect_inner(endpoint.clone(), addr, server_name, tls, hello, opts);
        within_connect_timeout(opts, fut).await
    }

    async fn connect_own_endpoint(
        addr: SocketAddr,
        server_name: &str,
        tls: Arc<rustls::ClientConfig>,
        hello: Hello,
        opts: &ConnectOptions,
    ) -> Result<(Connection, Welcome), NetError> {
        let endpoint = new_endpoint_with(addr, opts.max_udp_payload)?;
        Self::connect_inner(endpoint, addr, server_name, tls, hello, opts).await
    }

    async fn connect_inner(
        endpoint: quinn::Endpoint,
        addr: SocketAddr,
        server_name: &str,
        tls: Arc<rustls::ClientConfig>,
        hello: Hello,
        opts: &ConnectOptions,
    ) -> Result<(Connection, Welcome), NetError> {
        let crypto =
            quinn::crypto::rustls::QuicClientConfig::try_from(tls).map_err(NetError::connect)?;
        let mut cfg = quinn::ClientConfig::new(Arc::new(crypto));
        cfg.transport_config(opts.transport.clone().unwrap_or_else(default_transport));
        cfg.token_store(Arc::clone(&opts.tokens));
        let connecting = endpoint
            .connect_with(cfg, addr, server_name)
            .map_err(NetError::connect)?;
        let (conn, early) = if opts.zero_rtt {
            match connecting.into_0rtt() {
                Ok((conn, accepted)) => (conn, Some(accepted)),
                Err(connecting) => (connecting.await?, None),
            }
        } else {
            (connecting.await?, None)
        };
        let tried_early = early.is_some();
        let first = hello_exchange(&conn, &hello).await;
        // Resolves when the handshake completes: a Welcome sent in 0.5-RTT
        // data comes behind the server's Finished, so after it this is
        // immediate.
        let zero_rtt = match early {
            Some(accepted) => accepted.await,
            None => false,
        };
        let refused = tried_early && !zero_rtt;
        let (send, recv, hs, welcome) = match first {
            Ok(x) => x,
            Err(e) if refused && conn.close_reason().is_none() => {
                // The server refused the early data (unknown or used
                // ticket, 0-RTT disabled): the Hello never reached it.
                tracing::debug!(error = %e, "0-RTT refused, sending Hello again");
                hello_exchange(&conn, &hello).await?
            }
            Err(e) => return Err(e),
        };
        let (goodbye_tx, goodbye) = watch::channel(None);
        let ctrl_task = tokio::spawn(read_control(recv, hs.into_decoder(), goodbye_tx));
        let (opener, opens) = mpsc::unbounded_channel();
        let opener_task = tokio::spawn(open_in_order(conn.clone(), opens));
        let inner = Inner {
            _endpoint: endpoint,
            conn,
            ctrl_send: Mutex::new(Some(send)),
            goodbye,
            ctrl_task,
            opener,
            opener_task,
            welcome: welcome.clone(),
            fetch_timeout: opts.fetch_timeout,
            zero_rtt,
            zero_rtt_refused: refused,
            refs_refused: AtomicBool::new(false),
            floors_refused: AtomicBool::new(false),
            priority_refused: AtomicBool::new(false),
        };
        Ok((
            Connection {
                inner: Arc::new(inner),
            },
            welcome,
        ))
    }

    /// The server's welcome (header, file size, limits).
    pub fn welcome(&self) -> &Welcome {
        &self.inner.welcome
    }

    /// True if the `Hello` went out as 0-RTT early data and the server
    /// accepted it (a resumed session).
    pub fn used_zero_rtt(&self) -> bool {
        self.inner.zero_rtt
    }

    /// True if the `Hello` went out as 0-RTT early data, the server refused
    /// it (e.g. a restarted server that does not know the ticket) and the
    /// `Hello` was sent again after the handshake.
    pub fn zero_rtt_refused(&self) -> bool {
        self.inner.zero_rtt_refused
    }

    /// True if the server answered a `LodRefsRequest` as an unknown frame
    /// (it predates 0x12, or its operator turned child tables off:
    /// docs/PROTOCOL.md §7). [`Connection::fetch_refs`] then sends a
    /// `LodRequest` and returns the record alone.
    pub fn child_tables_refused(&self) -> bool {
        self.inner.refs_refused.load(Ordering::Relaxed)
    }

    /// Whether the server answered a request stream that began with a
    /// `Priority` frame (0x14) as unknown: later requests on this
    /// connection are sent without one ([`Connection::fetch_as`]).
    pub fn priority_refused(&self) -> bool {
        self.inner.priority_refused.load(Ordering::Relaxed)
    }

    /// Whether the server answered a `LodRefsAboveRequest` (0x13) as an
    /// unknown frame: later ones on this connection are sent as
    /// `LodRefsRequest` (or `LodRequest`, [`Connection::child_tables_refused`]).
    pub fn table_floors_refused(&self) -> bool {
        self.inner.floors_refused.load(Ordering::Relaxed)
    }

    /// The server's address.
    pub fn remote_address(&self) -> SocketAddr {
        self.inner.conn.remote_address()
    }

    /// `Some(reason)` once the server sent `Goodbye`.
    pub fn goodbye(&self) -> Option<ErrorCode> {
        *self.inner.goodbye.borrow()
    }

    /// The underlying quinn connection (advanced use, tests).
    pub fn quinn(&self) -> &quinn::Connection {
        &self.inner.conn
    }

    /// Resolves when the connection is closed, with the reason.
    pub async fn closed(&self) -> NetError {
        self.inner.conn.closed().await.into()
    }

    /// Sends `Goodbye{reason}`-free graceful close: finishes the control
    /// stream and closes the connection with `CONNECTION_CLOSED_NORMAL`.
    pub fn close(&self) {
        if let Ok(mut g) = self.inner.ctrl_send.lock() {
            if let Some(mut s) = g.take() {
                let _ = s.finish();
            }
        }
        self.inner
            .conn
            .close(VarInt::from_u32(quic::CONNECTION_CLOSED_NORMAL), b"bye");
    }

    /// Fetches the record at `offset` of `size` bytes. Dropping the future
    /// cancels the request (`recv.stop(STREAM_CANCELLED)`).
    ///
    /// The request takes its place in the connection's order when this is
    /// called, not when the future is first polled: requests made one after
    /// the other open their streams, reach the server and are answered in
    /// that order (the server sends responses in the order of the requests,
    /// docs/PROTOCOL.md §5.2), whatever order the tasks awaiting them run in.
    pub fn fetch(
        &self,
        id: u64,
        offset: u64,
        size: u32,
    ) -> impl std::future::Future<Output = Result<Vec<u8>, NetError>> + Send + 'static {
        self.fetch_kind(id, offset, size, RequestKind::Record, None)
    }

    /// Fetches the record at `offset` of `size` bytes with a
    /// `LodRefsRequest` (docs/PROTOCOL.md §4.8): the result is the record's
    /// `size` bytes followed by the trailer of its children's child tables
    /// (at most [`planet_protocol::MAX_REFS_TRAILER_LEN`] bytes, empty for a
    /// leaf; `planet_core::format::parse_child_tables` reads it). Dropping
    /// the future cancels the request, and the request takes its place in
    /// the connection's order when this is called, as for
    /// [`Connection::fetch`].
    ///
    /// A server that does not answer 0x12 (it predates it, or has it turned
    /// off) answers with an error head of id 0 (§7): the request is then
    /// made again as a `LodRequest`, and so is every later one on this
    /// connection ([`Connection::child_tables_refused`]); the result is the
    /// record alone, as from a transport without child tables.
    pub fn fetch_refs(
        &self,
        id: u64,
        offset: u64,
        size: u32,
    ) -> impl std::future::Future<Output = Result<Vec<u8>, NetError>> + Send + 'static {
        self.fetch_as(id, offset, size, RequestKind::RecordAndRefs, None)
    }

    /// As [`Connection::fetch_refs`], with a `LodRefsAboveRequest`
    /// (docs/PROTOCOL.md §4.9): child `k`'s table comes only if its
    /// references' largest error reaches `floors`' `k`-th floor, and is
    /// marked unknown (`0xff`) otherwise. A server that does not answer
    /// 0x13 gets the request again as a `LodRefsRequest`, and so does every
    /// later one on this connection
    /// ([`Connection::table_floors_refused`]); one that does not answer
    /// 0x12 either, as a `LodRequest`.
    pub fn fetch_refs_above(
        &self,
        id: u64,
        offset: u64,
        size: u32,
        floors: ErrorFloors,
    ) -> impl std::future::Future<Output = Result<Vec<u8>, NetError>> + Send + 'static {
        self.fetch_as(
            id,
            offset,
            size,
            RequestKind::RecordAndRefsAbove(floors),
            None,
        )
    }

    /// A request of `kind`, or of the kind it falls back to when this
    /// connection's server refused it before, after a `Priority` frame
    /// (docs/PROTOCOL.md §4.10) when `priority` is given and the server did
    /// not refuse one before ([`Connection::priority_refused`]).
    pub fn fetch_as(
        &self,
        id: u64,
        offset: u64,
        size: u32,
        mut kind: RequestKind,
        priority: Option<StreamPriority>,
    ) -> impl std::future::Future<Output = Result<Vec<u8>, NetError>> + Send + 'static {
        // Down the fallback chain (0x13 → 0x12 → 0x10) past every kind
        // this connection's server refused before.
        while self
            .inner
            .refused(kind)
            .is_some_and(|r| r.load(Ordering::Relaxed))
        {
            match kind.fallback() {
                Some(next) => kind = next,
                None => break,
            }
        }
        let priority = priority.filter(|_| !self.priority_refused());
        self.fetch_kind(id, offset, size, kind, priority)
    }

    fn fetch_kind(
        &self,
        id: u64,
        offset: u64,
        size: u32,
        kind: RequestKind,
        priority: Option<StreamPriority>,
    ) -> impl std::future::Future<Output = Result<Vec<u8>, NetError>> + Send + 'static {
        let req = LodRequest { id, offset, size };
        // Queued now, in call order.
        let opened = self.enqueue(&req, kind, priority);
        // The connection lives while one of its requests does.
        let this = self.clone();
        async move {
            let fut = async {
                let (mut opened, mut kind, mut priority) = (opened, kind, priority);
                loop {
                    match read_response(opened, req, kind).await {
                        // A server that does not know the `Priority` frame
                        // answers as it answers an unknown request type:
                        // the same request again without it, and none on
                        // this connection from then on. (If the unknown
                        // frame was the request's type, the retry falls
                        // down its kinds next.)
                        Err(e) if priority.is_some() && frame_unknown(&e, req.id) => {
                            this.inner.priority_refused.store(true, Ordering::Relaxed);
                            tracing::debug!(
                                "server does not answer a priority frame; sending none"
                            );
                            priority = None;
                            opened = this.enqueue(&req, kind, None);
                        }
                        Err(e) if kind.has_refs() && frame_unknown(&e, req.id) => {
                            if let Some(refused) = this.inner.refused(kind) {
                                refused.store(true, Ordering::Relaxed);
                            }
                            let Some(next) = kind.fallback() else {
                                return Err(e);
                            };
                            tracing::debug!(
                                refused = %kind.msg_type(),
                                using = %next.msg_type(),
                                "server does not answer a request type; falling back"
                            );
                            kind = next;
                            opened = this.enqueue(&req, kind, None);
                        }
                        r => return r,
                    }
                }
            };
            let r = match this.inner.fetch_timeout {
                Some(t) => tokio::time::timeout(t, fut)
                    .await
                    .unwrap_or(Err(NetError::Timeout)),
                None => fut.await,
            };
            drop(this);
            r
        }
    }

    /// Queues `req` as a request of `kind` for [`open_in_order`], after a
    /// `Priority` frame when `priority` is given.
    fn enqueue(
        &self,
        req: &LodRequest,
        kind: RequestKind,
        priority: Option<StreamPriority>,
    ) -> Result<oneshot::Receiver<Opened>, NetError> {
        let frame = req.encode_stream(kind, priority)?;
        let (reply, opened) = oneshot::channel();
        self.inner
            .opener
            .send(Open { frame, reply })
            .map_err(|_| closed_error())?;
        Ok(opened)
    }

    /// Spawns [`Connection::fetch`] on the current tokio runtime and returns
    /// a handle that can cancel it.
    pub fn spawn_fetch(&self, id: u64, offset: u64, size: u32) -> FetchHandle {
        let fut = self.fetch(id, offset, size);
        let task = tokio::spawn(fut);
        FetchHandle { id, task }
    }
}

/// Whether `e`, the answer to a well-formed `LodRefsRequest` (or
/// `LodRefsAboveRequest`, or any request after a `Priority` frame) of id
/// `id`, says the server does not know 0x12 (0x13, 0x14): an error head
/// with id 0 (a server answers id 0 only to a request stream it cannot
/// decode, §5.2), which the response decoder reports as an id mismatch, or
/// `unknown_message` itself when the request's id was 0.
fn frame_unknown(e: &NetError, id: u64) -> bool {
    match e {
        NetError::Protocol(ProtocolError::ResponseIdMismatch { got: 0, .. }) => true,
        NetError::Server(m) => id == 0 && m.code == ErrorCode::UnknownMessage,
        _ => false,
    }
}

/// The streams of a request whose frame is written and finished.
type Opened = Result<(quinn::SendStream, quinn::RecvStream), NetError>;

/// A request waiting for its stream ([`open_in_order`]).
struct Open {
    frame: Vec<u8>,
    reply: oneshot::Sender<Opened>,
}

/// The error of a request whose connection's opener is gone.
fn closed_error() -> NetError {
    NetError::ConnectionLost {
        code: None,
        reason: "connection closed".into(),
    }
}

/// Opens each request's stream and writes its frame, one request at a
/// time in the order they were made. The server answers in the order the
/// requests arrive (its send fairness is off, server/src/lib.rs) and the
/// client makes them most important first; a task per request opening its
/// own stream would race the others (tokio runs the task spawned last
/// first), and the first record the client needed could come last. A
/// request cancelled before its turn opens no stream.
async fn open_in_order(conn: quinn::Connection, mut opens: mpsc::UnboundedReceiver<Open>) {
    while let Some(mut o) = opens.recv().await {
        let streams = tokio::select! {
            r = conn.open_bi() => r,
            _ = o.reply.closed() => continue,
        };
        let opened = match streams {
            Ok((mut send, recv)) => match send.write_all(&o.frame).await {
                Ok(()) => {
                    let _ = send.finish();
                    Ok((send, recv))
                }
                Err(e) => Err(NetError::from(e)),
            },
            Err(e) => Err(NetError::from(e)),
        };
        // Cancelled meanwhile: the guard of the streams stops them.
        if let Err(Ok((send, recv))) = o.reply.send(opened) {
            drop(StreamGuard {
                send,
                recv,
                finished: true,
                done: false,
            });
        }
    }
}

/// Waits for the request's streams ([`open_in_order`]) and reads its
/// response.
async fn read_response(
    opened: Result<oneshot::Receiver<Opened>, NetError>,
    req: LodRequest,
    kind: RequestKind,
) -> Result<Vec<u8>, NetError> {
    let (send, recv) = opened?.await.map_err(|_| closed_error())??;
    let mut guard = StreamGuard {
        send,
        recv,
        finished: true,
        done: false,
    };
    let mut dec = ResponseDecoder::for_kind(req, kind);
    loop {
        match guard.recv.read_chunk(1 << 20, true).await {
            Ok(Some(chunk)) => dec.push(&chunk.bytes)?,
            Ok(None) => break,
            Err(e) => {
                guard.done = true;
                return Err(e.into());
            }
        }
    }
    guard.done = true;
    match dec.finish()? {
        Response::Record { body, .. } => Ok(body),
        Response::Error { error, .. } => Err(NetError::Server(error)),
    }
}

/// Stops / resets a request stream that is abandoned before completion.
struct StreamGuard {
    send: quinn::SendStream,
    recv: quinn::RecvStream,
    finished: bool,
    done: bool,
}

impl Drop for StreamGuard {
    fn drop(&mut self) {
        if !self.done {
            let _ = self.recv.stop(VarInt::from_u32(quic::STREAM_CANCELLED));
            if !self.finished {
                let _ = self.send.reset(VarInt::from_u32(quic::STREAM_CANCELLED));
            }
        }
    }
}

/// Opens the control stream, sends `hello` and reads up to the `Welcome`
/// (thesis §3.3; docs/PROTOCOL.md). Returns the streams and the decoder
/// state that the control-stream reader continues from.
async fn hello_exchange(
    conn: &quinn::Connection,
    hello: &Hello,
) -> Result<
    (
        quinn::SendStream,
        quinn::RecvStream,
        ClientHandshake,
        Welcome,
    ),
    NetError,
> {
    let (mut send, mut recv) = conn.open_bi().await?;
    let (mut hs, bytes) = ClientHandshake::new(hello.clone())?;
    send.write_all(&bytes).await?;
    loop {
        match recv.read_chunk(64 * 1024, true).await {
            Ok(Some(chunk)) => match hs.receive(&chunk.bytes)? {
                Some(HandshakeOutcome::Welcomed(w)) => return Ok((send, recv, hs, w)),
                Some(HandshakeOutcome::Rejected(e)) => return Err(NetError::Rejected(e)),
                None => {}
            },
            Ok(None) => {
                hs.finish()?;
                return Err(NetError::Protocol(ProtocolError::UnexpectedEnd {
                    during: "before Welcome",
                }));
            }
            Err(e) => return Err(e.into()),
        }
    }
}

async fn read_control(
    mut recv: quinn::RecvStream,
    mut dec: FrameDecoder,
    goodbye: watch::Sender<Option<ErrorCode>>,
) {
    loop {
        loop {
            match dec.next_frame() {
                Ok(Some(Message::Goodbye(g))) => {
                    tracing::info!(reason = %g.reason, "server said goodbye");
                    let _ = goodbye.send(Some(g.reason));
                }
                Ok(Some(Message::Error(e))) => tracing::warn!(error = %e, "server error"),
                Ok(Some(other)) => {
                    tracing::debug!(msg = %other.msg_type(), "unexpected control message")
                }
                Ok(None) => break,
                Err(e) => {
                    tracing::warn!(error = %e, "bad control stream from server");
                    return;
                }
            }
        }
        match recv.read_chunk(64 * 1024, true).await {
            Ok(Some(chunk)) => dec.push(&chunk.bytes),
            Ok(None) | Err(_) => return,
        }
    }
}

/// A spawned fetch that can be cancelled.
#[derive(Debug)]
pub struct FetchHandle {
    id: u64,
    task: JoinHandle<Result<Vec<u8>, NetError>>,
}

impl FetchHandle {
    /// The request id.
    pub fn id(&self) -> u64 {
        self.id
    }

    /// Cancels the fetch: the stream is stopped with `STREAM_CANCELLED`.
    pub fn cancel(&self) {
        self.task.abort();
    }

    /// True once the fetch finished (or was cancelled).
    pub fn is_finished(&self) -> bool {
        self.task.is_finished()
    }

    /// Waits for the result; [`NetError::Cancelled`] after [`Self::cancel`].
    pub async fn join(self) -> Result<Vec<u8>, NetError> {
        match self.task.await {
            Ok(r) => r,
            Err(_) => Err(NetError::Cancelled),
        }
    }
}

/// What a [`SessionHandle`] reports.
#[derive(Debug, Clone)]
pub enum NetEvent {
    /// (Re)connected; the welcome may differ after a reconnect (e.g. a new
    /// database version).
    Connected(Welcome),
    /// A requested record arrived.
    Record {
        /// The request id.
        id: u64,
        /// The record bytes; after [`SessionHandle::request_refs`] on a QUIC
        /// session, followed by the trailer of child tables.
        bytes: Vec<u8>,
    },
    /// A request failed; re-request it if still needed (after `Connected`
    /// when `error.is_connection_error()`).
    Failed {
        /// The request id.
        id: u64,
        /// Why.
        error: NetError,
    },
    /// The connection was lost; reconnecting with backoff.
    Disconnected,
    /// A request was cancelled by [`SessionHandle::cancel`].
    Cancelled {
        /// The request id.
        id: u64,
    },
}

/// Configuration of a reconnecting [`Session`].
#[derive(Debug, Clone)]
pub struct SessionConfig {
    /// Server address.
    pub addr: SocketAddr,
    /// TLS server name (`localhost` for a dev certificate).
    pub server_name: String,
    /// TLS configuration (see [`crate::tls`]).
    pub tls: Arc<rustls::ClientConfig>,
    /// The hello sent on every (re)connection.
    pub hello: Hello,
    /// Connection options.
    pub options: ConnectOptions,
    /// First reconnect delay.
    pub backoff_initial: Duration,
    /// Largest reconnect delay.
    pub backoff_max: Duration,
}

impl SessionConfig {
    /// Defaults: backoff 100 ms doubling up to 5 s, with jitter.
    pub fn new(
        addr: SocketAddr,
        server_name: impl Into<String>,
        tls: Arc<rustls::ClientConfig>,
        hello: Hello,
    ) -> Self {
        SessionConfig {
            addr,
            server_name: server_name.into(),
            tls,
            hello,
            options: ConnectOptions::default(),
            backoff_initial: Duration::from_millis(100),
            backoff_max: Duration::from_secs(5),
        }
    }
}

pub(crate) enum Cmd {
    /// `kind`: with child tables or not (QUIC; the HTTP transport sends
    /// every kind as a plain byte range).
    /// `priority`: the response's, before the request (QUIC; the HTTP
    /// transport has none).
    Request {
        id: u64,
        offset: u64,
        size: u32,
        kind: RequestKind,
        priority: Option<StreamPriority>,
    },
    Cancel {
        id: u64,
    },
    Close,
}

#[derive(Default)]
pub(crate) struct Status {
    pub(crate) connected: bool,
    zero_rtt: bool,
    zero_rtt_refused: bool,
    pub(crate) welcome: Option<Welcome>,
    pub(crate) last_error: Option<NetError>,
    /// The current connection (for its path statistics).
    quic: Option<quinn::Connection>,
}

/// A reconnecting session; see [`Session::spawn`].
pub struct Session;

/// Synchronous, non-blocking control of a [`Session`] running on a tokio
/// runtime. Dropping it closes the session.
pub struct SessionHandle {
    cmd: mpsc::UnboundedSender<Cmd>,
    events: crossbeam_channel::Receiver<NetEvent>,
    status: Arc<Mutex<Status>>,
    task: JoinHandle<()>,
}

impl Session {
    /// Starts the session task on `runtime`: it connects, reconnects with
    /// capped exponential backoff and jitter after any loss, and serves
    /// requests. Requests issued while disconnected fail at once with
    /// [`NetError::NotConnected`]; requests in flight when the link drops
    /// fail with a connection error. Either way, re-request after
    /// [`NetEvent::Connected`].
    pub fn spawn(runtime: &tokio::runtime::Handle, cfg: SessionConfig) -> SessionHandle {
        SessionHandle::spawn_with(runtime, |cmd_rx, ev, status| {
            run_session(cfg, cmd_rx, ev, status)
        })
    }
}

impl SessionHandle {
    /// Spawns a session task made by `task` from the command receiver, the
    /// event sender and the status (one per transport).
    pub(crate) fn spawn_with<F>(
        runtime: &tokio::runtime::Handle,
        task: impl FnOnce(
            mpsc::UnboundedReceiver<Cmd>,
            crossbeam_channel::Sender<NetEvent>,
            Arc<Mutex<Status>>,
        ) -> F,
    ) -> SessionHandle
    where
        F: std::future::Future<Output = ()> + Send + 'static,
    {
        let (cmd, cmd_rx) = mpsc::unbounded_channel();
        let (ev_tx, events) = crossbeam_channel::unbounded();
        let status = Arc::new(Mutex::new(Status::default()));
        let task = runtime.spawn(task(cmd_rx, ev_tx, Arc::clone(&status)));
        SessionHandle {
            cmd,
            events,
            status,
            task,
        }
    }
}

impl SessionHandle {
    /// Requests a record (non-blocking). The result arrives as
    /// [`NetEvent::Record`] or [`NetEvent::Failed`].
    pub fn request(&self, id: u64, offset: u64, size: u32) {
        self.request_with(id, offset, size, None, None);
    }

    /// Requests a record and the child tables of its children
    /// (non-blocking; [`Connection::fetch_refs`]). The result arrives as
    /// [`NetEvent::Record`], whose bytes are the record's `size` bytes
    /// followed by the trailer (docs/PROTOCOL.md §4.8), or
    /// [`NetEvent::Failed`].
    ///
    /// On an HTTP session ([`Session::spawn_http`]) a byte range cannot
    /// carry the trailer: this is exactly [`SessionHandle::request`], and
    /// the bytes are the record alone. Tell the two apart by the length:
    /// `bytes.len() == size` means no trailer.
    pub fn request_refs(&self, id: u64, offset: u64, size: u32) {
        let _ = self.cmd.send(Cmd::Request {
            id,
            offset,
            size,
            kind: RequestKind::RecordAndRefs,
            priority: None,
        });
    }

    /// As [`SessionHandle::request_refs`], but child `k`'s table comes only
    /// if its references' largest error reaches `floors[k]` (metres;
    /// `LodRefsAboveRequest`, docs/PROTOCOL.md §4.9); a table left out is
    /// marked unknown (`0xff`). A floor that is NaN or negative asks for
    /// that table whatever its errors. A server that predates 0x13 gets the
    /// request as a `LodRefsRequest` ([`Connection::fetch_refs_above`]).
    pub fn request_refs_above(&self, id: u64, offset: u64, size: u32, floors: [f32; 4]) {
        self.request_with(id, offset, size, Some(floors), None);
    }

    /// A request of any kind with any priority (non-blocking): as
    /// [`SessionHandle::request_refs_above`] with `floors`, as
    /// [`SessionHandle::request`] without. A `priority` is sent before the
    /// request in a `Priority` frame (docs/PROTOCOL.md §4.10): the server
    /// sends the response before those of this connection's requests with a
    /// lower one (a request without has priority 0). A server that predates
    /// the frame gets the request again without it
    /// ([`Connection::fetch_as`]); an HTTP session ignores it.
    pub fn request_with(
        &self,
        id: u64,
        offset: u64,
        size: u32,
        floors: Option<[f32; 4]>,
        priority: Option<i32>,
    ) {
        let kind = floors.map_or(RequestKind::Record, |floors| {
            let floors = floors.map(|f| if f >= 0.0 { f } else { 0.0 });
            ErrorFloors::new(floors)
                .map_or(RequestKind::RecordAndRefs, RequestKind::RecordAndRefsAbove)
        });
        let _ = self.cmd.send(Cmd::Request {
            id,
            offset,
            size,
            kind,
            priority: priority.map(|priority| StreamPriority { priority }),
        });
    }

    /// Cancels a request (non-blocking); [`NetEvent::Cancelled`] follows if
    /// it was still in flight.
    pub fn cancel(&self, id: u64) {
        let _ = self.cmd.send(Cmd::Cancel { id });
    }

    /// All events received since the last call (never blocks).
    pub fn poll_events(&self) -> Vec<NetEvent> {
        self.events.try_iter().collect()
    }

    /// Blocks up to `timeout` for the next event. Do not call from a tokio
    /// worker thread.
    pub fn wait_event(&self, timeout: Duration) -> Option<NetEvent> {
        self.events.recv_timeout(timeout).ok()
    }

    /// True while connected.
    pub fn is_connected(&self) -> bool {
        self.status.lock().map(|s| s.connected).unwrap_or(false)
    }

    /// True if the current (or last) connection sent its `Hello` as
    /// accepted 0-RTT early data (a resumed session).
    pub fn used_zero_rtt(&self) -> bool {
        self.status.lock().map(|s| s.zero_rtt).unwrap_or(false)
    }

    /// True if the current (or last) connection's 0-RTT `Hello` was refused
    /// and sent again after the handshake.
    pub fn zero_rtt_refused(&self) -> bool {
        self.status
            .lock()
            .map(|s| s.zero_rtt_refused)
            .unwrap_or(false)
    }

    /// The QUIC path's smoothed round-trip time while connected.
    pub fn rtt(&self) -> Option<Duration> {
        self.status
            .lock()
            .ok()
            .and_then(|s| s.quic.as_ref().map(|c| c.rtt()))
    }

    /// The latest welcome.
    pub fn welcome(&self) -> Option<Welcome> {
        self.status.lock().ok().and_then(|s| s.welcome.clone())
    }

    /// The latest connection error (e.g. a rejected handshake).
    pub fn last_error(&self) -> Option<NetError> {
        self.status.lock().ok().and_then(|s| s.last_error.clone())
    }

    /// Closes the session (graceful close of the connection, no reconnect).
    pub fn close(&self) {
        let _ = self.cmd.send(Cmd::Close);
    }
}

impl Drop for SessionHandle {
    fn drop(&mut self) {
        let _ = self.cmd.send(Cmd::Close);
        if self.cmd.is_closed() {
            self.task.abort();
        }
    }
}

pub(crate) fn set_status(status: &Mutex<Status>, f: impl FnOnce(&mut Status)) {
    if let Ok(mut s) = status.lock() {
        f(&mut s);
    }
}

pub(crate) fn jittered(d: Duration) -> Duration {
    // "Equal jitter": between half and all of the nominal delay.
    d.mul_f64(0.5 + 0.5 * rand::random::<f64>())
}

async fn run_session(
    cfg: SessionConfig,
    mut cmd_rx: mpsc::UnboundedReceiver<Cmd>,
    ev: crossbeam_channel::Sender<NetEvent>,
    status: Arc<Mutex<Status>>,
) {
    let mut backoff = cfg.backoff_initial;
    loop {
        let connect = Connection::connect_with(
            cfg.addr,
            &cfg.server_name,
            Arc::clone(&cfg.tls),
            cfg.hello.clone(),
            &cfg.options,
        );
        let Some(result) = while_disconnected(connect, &mut cmd_rx, &ev).await else {
            return;
        };
        match result {
            Ok((conn, welcome)) => {
                backoff = cfg.backoff_initial;
                set_status(&status, |s| {
                    s.connected = true;
                    s.zero_rtt = conn.used_zero_rtt();
                    s.zero_rtt_refused = conn.zero_rtt_refused();
                    s.welcome = Some(welcome.clone());
                    s.quic = Some(conn.quinn().clone());
                });
                let _ = ev.send(NetEvent::Connected(welcome));
                let c = conn.clone();
                let user_closed = serve_requests(
                    &mut cmd_rx,
                    &ev,
                    // Called in the order of the requests: each takes its
                    // place in the connection's order at once.
                    move |id, offset, size, kind, priority| {
                        c.fetch_as(id, offset, size, kind, priority)
                    },
                    conn.closed(),
                )
                .await;
                set_status(&status, |s| {
                    s.connected = false;
                    s.quic = None;
                });
                if user_closed {
                    conn.close();
                    return;
                }
                let _ = ev.send(NetEvent::Disconnected);
            }
            Err(e) => {
                tracing::debug!(error = %e, addr = %cfg.addr, "connect failed");
                set_status(&status, |s| s.last_error = Some(e));
            }
        }
        let sleep = tokio::time::sleep(jittered(backoff));
        backoff = (backoff * 2).min(cfg.backoff_max);
        if while_disconnected(sleep, &mut cmd_rx, &ev).await.is_none() {
            return;
        }
    }
}

/// Runs `fut` (a connection attempt or a backoff pause) while requests fail
/// at once with [`NetError::NotConnected`]; `None` if the user closed the
/// session meanwhile. Shared by the QUIC and HTTP sessions.
pub(crate) async fn while_disconnected<F: std::future::Future>(
    fut: F,
    cmd_rx: &mut mpsc::UnboundedReceiver<Cmd>,
    ev: &crossbeam_channel::Sender<NetEvent>,
) -> Option<F::Output> {
    tokio::pin!(fut);
    loop {
        tokio::select! {
            r = &mut fut => return Some(r),
            c = cmd_rx.recv() => match c {
                None | Some(Cmd::Close) => return None,
                Some(Cmd::Request { id, .. }) => {
                    let _ = ev.send(NetEvent::Failed { id, error: NetError::NotConnected });
                }
                Some(Cmd::Cancel { .. }) => {}
            },
        }
    }
}

/// Serves requests on one connection, one task per request made by
/// `fetch(id, offset, size, kind)` (`kind`: [`SessionHandle::request_refs`]
/// and [`SessionHandle::request_refs_above`] ask for child tables),
/// until the user closes the session (`true`) or the connection is lost
/// (`false`): `closed` completes, or a request fails with a connection error
/// (an HTTP `412`, a reset connection). Shared by the QUIC and HTTP sessions.
pub(crate) async fn serve_requests<Fetch, Fut>(
    cmd_rx: &mut mpsc::UnboundedReceiver<Cmd>,
    ev: &crossbeam_channel::Sender<NetEvent>,
    fetch: Fetch,
    closed: impl std::future::Future<Output = NetError>,
) -> bool
where
    Fetch: Fn(u64, u64, u32, RequestKind, Option<StreamPriority>) -> Fut,
    Fut: std::future::Future<Output = Result<Vec<u8>, NetError>> + Send + 'static,
{
    let mut tasks: JoinSet<(u64, Result<Vec<u8>, NetError>)> = JoinSet::new();
    let mut pending: HashMap<u64, tokio::task::AbortHandle> = HashMap::new();
    let fail_all = |pending: &mut HashMap<u64, tokio::task::AbortHandle>, error: &NetError| {
        for (id, h) in pending.drain() {
            h.abort();
            let _ = ev.send(NetEvent::Failed {
                id,
                error: error.clone(),
            });
        }
    };
    tokio::pin!(closed);
    let user_closed = loop {
        tokio::select! {
            c = cmd_rx.recv() => match c {
                None | Some(Cmd::Close) => break true,
                Some(Cmd::Request { id, offset, size, kind, priority }) => {
                    if pending.contains_key(&id) {
                        let _ = ev.send(NetEvent::Failed {
                            id,
                            error: NetError::Server(ErrorMsg::new(
                                ErrorCode::DuplicateRequest,
                                "request id already in flight (client side)",
                            )),
                        });
                        continue;
                    }
                    let f = fetch(id, offset, size, kind, priority);
                    let h = tasks.spawn(async move { (id, f.await) });
                    pending.insert(id, h);
                }
                Some(Cmd::Cancel { id }) => {
                    // Aborting the task drops the request: QUIC stops its
                    // stream, HTTP/2 resets it.
                    if let Some(h) = pending.remove(&id) {
                        h.abort();
                        let _ = ev.send(NetEvent::Cancelled { id });
                    }
                }
            },
            Some(done) = tasks.join_next(), if !tasks.is_empty() => {
                let Ok((id, result)) = done else { continue };
                if pending.remove(&id).is_none() {
                    continue;
                }
                match result {
                    Ok(bytes) => {
                        let _ = ev.send(NetEvent::Record { id, bytes });
                    }
                    Err(error) if error.is_connection_error() => {
                        tracing::info!(%error, "connection lost");
                        let _ = ev.send(NetEvent::Failed { id, error: error.clone() });
                        fail_all(&mut pending, &error);
                        break false;
                    }
                    Err(error) => {
                        let _ = ev.send(NetEvent::Failed { id, error });
                    }
                }
            }
            reason = &mut closed => {
                tracing::info!(error = %reason, "connection lost");
                fail_all(&mut pending, &reason);
                break false;
            }
        }
    };
    if user_closed {
        for (id, h) in pending.drain() {
            h.abort();
            let _ = ev.send(NetEvent::Cancelled { id });
        }
    }
    tasks.shutdown().await;
    user_closed
}

/// Largest UDP payload a client endpoint accepts from a server on the
/// loopback interface (MTU 65 536) unless configured. The server still
/// decides (its `max_udp_payload`, default 1452): with 16 384 there, a 7 kB
/// response travels in one datagram instead of five or six, which cuts the
/// server's CPU per request on loopback by a quarter (docs/BENCHMARKS.md).
pub const LOOPBACK_MAX_UDP_PAYLOAD: u16 = 16_384;

/// Largest UDP payload a client endpoint accepts from other servers unless
/// configured: quinn's default, a 1 500-byte Ethernet MTU less the IPv4 and
/// UDP headers. Announcing more would make the server probe for sizes that
/// Internet paths drop, for nothing.
pub const NETWORK_MAX_UDP_PAYLOAD: u16 = 1472;

/// The `max_udp_payload_size` a client announces to the server at `peer`
/// when not configured: [`LOOPBACK_MAX_UDP_PAYLOAD`] for a loopback address,
/// [`NETWORK_MAX_UDP_PAYLOAD`] otherwise. The server's path-MTU discovery
/// never probes above it, so off loopback the datagram sizes are those of
/// quinn's defaults.
pub fn auto_max_udp_payload(peer: SocketAddr) -> u16 {
    if peer.ip().is_loopback() {
        LOOPBACK_MAX_UDP_PAYLOAD
    } else {
        NETWORK_MAX_UDP_PAYLOAD
    }
}

/// A client endpoint (one UDP socket on an ephemeral port of the address
/// family of `peer`, 4 MiB socket buffers, datagrams up to
/// [`auto_max_udp_payload`]) for [`Connection::connect_on`].
/// Any number of connections may share it; it is closed when the last handle
/// and connection are dropped.
pub fn new_endpoint(peer: SocketAddr) -> Result<quinn::Endpoint, NetError> {
    new_endpoint_with(peer, None)
}

/// [`new_endpoint`] accepting UDP payloads up to `max_udp_payload` (1 200 to
/// 65 527 bytes; `None` = [`auto_max_udp_payload`] of `peer`). The endpoint
/// reserves `max_udp_payload` × 2 048 bytes of receive buffer (32 MiB at
/// 16 384; pages are touched only as datagrams arrive).
pub fn new_endpoint_with(
    peer: SocketAddr,
    max_udp_payload: Option<u16>,
) -> Result<quinn::Endpoint, NetError> {
    let bind: SocketAddr = if peer.is_ipv6() {
        (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
    } else {
        (std::net::Ipv4Addr::UNSPECIFIED, 0).into()
    };
    let max = max_udp_payload.unwrap_or_else(|| auto_max_udp_payload(peer));
    let mut cfg = quinn::EndpointConfig::default();
    cfg.max_udp_payload_size(max)
        .map_err(|source| NetError::connect(UdpPayloadOutOfRange { max, source }))?;
    client_endpoint(cfg, bind).map_err(NetError::connect)
}

/// A maximum UDP payload quinn refuses.
#[derive(Debug, thiserror::Error)]
#[error("max_udp_payload {max} is outside 1200..=65527")]
pub struct UdpPayloadOutOfRange {
    /// The payload asked for.
    pub max: u16,
    /// quinn's refusal.
    #[source]
    pub source: quinn::ConfigError,
}

/// A client endpoint on a UDP socket with 4 MiB buffers (capped by the
/// kernel's `rmem_max`/`wmem_max`): with the default 208 KiB, bursts of
/// responses overflowed the receive buffer on loaded machines and QUIC stalled
/// on probe timeouts. The server does the same in `planet_server::udp`.
fn client_endpoint(
    cfg: quinn::EndpointConfig,
    bind: SocketAddr,
) -> std::io::Result<quinn::Endpoint> {
    use socket2::{Domain, Protocol, Socket, Type};
    const SOCKET_BUFFER: usize = 4 * 1024 * 1024;
    let socket = Socket::new(Domain::for_address(bind), Type::DGRAM, Some(Protocol::UDP))?;
    let _ = socket.set_recv_buffer_size(SOCKET_BUFFER);
    let _ = socket.set_send_buffer_size(SOCKET_BUFFER);
    socket.bind(&bind.into())?;
    let runtime = quinn::default_runtime()
        .ok_or_else(|| std::io::Error::other("no async runtime for the QUIC endpoint"))?;
    quinn::Endpoint::new(cfg, None, socket.into(), runtime)
}
