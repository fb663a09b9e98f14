//! One QUIC connection: the control stream (handshake, cancel, goodbye) and
//! the request streams (validation, pacing, checksum, zero-copy send).

use std::cell::RefCell;
use std::collections::HashSet;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use bytes::Bytes;
use futures_util::stream::{FuturesUnordered, StreamExt};
use futures_util::FutureExt;
use planet_core::format::{child_tables_for, record_checksum_ok, ChildRef, SUPERBLOCK_LEN};
use planet_protocol::{
    decode_prioritized_request_stream, quic, Authorizer, ErrorCode, ErrorMsg, Goodbye, Hello,
    InFlight, Limits, LodRequest, MessageType, ProtocolError, RequestKind, ResponseHead,
    ServerEvent, ServerSession, Welcome, MAX_REQUEST_STREAM_LEN,
};
use quinn::{RecvStream, SendStream, VarInt};
use tokio::sync::watch;

use crate::db::{MappedDb, RequestCheck};
use crate::metrics::{HandshakeEnd, RequestOutcome};
use crate::{PendingGuard, Shared, TenantRt};

/// How long a client has to send (and finish) a request on a request stream.
const REQUEST_READ_TIMEOUT: Duration = Duration::from_secs(10);
/// How long a fatal error / goodbye frame or an error reply on a request
/// stream gets to be written and reach the client: a peer that does not
/// read (or advertises a zero window) cannot hold the connection with it.
const FLUSH_TIMEOUT: Duration = Duration::from_millis(500);

/// Streams allowed beyond `max_in_flight` (the control stream, plus slack
/// so that an over-eager client gets `too_many_in_flight` heads rather than
/// silently blocking in `open_bi`).
pub(crate) const STREAM_MARGIN: u32 = 4;

/// Labels used for requests that arrive before the handshake.
const NO_TENANT: &str = "none";

fn code(c: u32) -> VarInt {
    VarInt::from_u32(c)
}

/// Takes one of `max` places of `counter` (0 = unlimited).
fn take_place(counter: &std::sync::atomic::AtomicUsize, max: usize) -> bool {
    counter
        .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
            (max == 0 || n < max).then_some(n + 1)
        })
        .is_ok()
}

/// One established session: a place of the server's `max_connections` and
/// of its tenant's `TenantConfig::max_connections`.
struct SessionSlot(Arc<TenantRt>, Arc<Shared>);

/// Why a session place was refused.
enum NoPlace {
    Server,
    Tenant,
}

impl SessionSlot {
    fn try_new(tenant: &Arc<TenantRt>, shared: &Arc<Shared>) -> Result<SessionSlot, NoPlace> {
        if !take_place(&shared.sessions, shared.cfg.max_connections) {
            return Err(NoPlace::Server);
        }
        if !take_place(&tenant.sessions, tenant.cfg.max_connections as usize) {
            shared.sessions.fetch_sub(1, Ordering::AcqRel);
            return Err(NoPlace::Tenant);
        }
        Ok(SessionSlot(Arc::clone(tenant), Arc::clone(shared)))
    }
}

impl Drop for SessionSlot {
    fn drop(&mut self) {
        self.0.sessions.fetch_sub(1, Ordering::AcqRel);
        self.1.sessions.fetch_sub(1, Ordering::AcqRel);
    }
}

/// What request futures need once the session is established.
struct Established {
    _slot: SessionSlot,
    tenant: Arc<TenantRt>,
    db: Arc<MappedDb>,
    session: ServerSession,
    in_flight: Mutex<InFlight>,
    ok: OkMetrics,
}

/// The labelled metrics a successful request updates, resolved once per
/// session: `with_label_values` hashes the label strings and takes a lock,
/// four times per request otherwise.
struct OkMetrics {
    requests: prometheus::IntCounter,
    bytes_sent: prometheus::IntCounter,
    record_size: prometheus::Histogram,
    duration: prometheus::Histogram,
}

impl OkMetrics {
    fn new(m: &crate::Metrics, tenant: &str, db: &str) -> OkMetrics {
        OkMetrics {
            requests: m.requests_total.with_label_values(&[
                tenant,
                db,
                RequestOutcome::Ok.as_str(),
            ]),
            bytes_sent: m.bytes_sent_total.with_label_values(&[tenant, db]),
            record_size: m.record_size.with_label_values(&[db]),
            duration: m.request_duration.with_label_values(&[db]),
        }
    }
}

/// Per-connection state shared with request futures.
struct ConnCtx {
    shared: Arc<Shared>,
    established: OnceLock<Established>,
    draining: AtomicBool,
    cancelled: Mutex<HashSet<u64>>,
}

/// The [`Authorizer`] for one connection: checks the hello against the
/// configuration and remembers the tenant and database version it chose.
struct ConnAuth<'a> {
    shared: &'a Arc<Shared>,
    peer: std::net::IpAddr,
    chosen: RefCell<Option<(SessionSlot, Arc<MappedDb>)>>,
}

impl Authorizer for ConnAuth<'_> {
    fn authorize(&self, hello: &Hello) -> Result<Welcome, ErrorMsg> {
        // Failed hellos are limited per address; once the budget is spent,
        // every hello from the address is refused without looking at the
        // token, so guessing gains nothing from a right answer.
        if !self.shared.failed_hellos.allows(self.peer) {
            return Err(ErrorMsg::new(
                ErrorCode::RateLimited,
                "too many failed hellos from this address",
            ));
        }
        let tenant = self.shared.tenants.get(&hello.tenant);
        // Always run the constant-time compare, even for an unknown tenant,
        // so that timing does not reveal which tenant names exist.
        let token_ok = match tenant {
            Some(t) => t.token_matches(&hello.token),
            None => {
                let _ = self.shared.dummy_token.matches(&hello.token);
                false
            }
        };
        let tenant = match tenant {
            Some(t) if token_ok => t,
            _ => {
                self.shared.failed_hellos.spend(self.peer);
                return Err(ErrorMsg::new(
                    ErrorCode::Unauthorized,
                    "unknown tenant or bad token",
                ));
            }
        };
        let Some(slot) = self.shared.dbs.get(&hello.database) else {
            return Err(ErrorMsg::new(
                ErrorCode::UnknownDatabase,
                format!("no database named {:?}", hello.database),
            ));
        };
        if !tenant.cfg.databases.iter().any(|d| d == &hello.database) {
            return Err(ErrorMsg::new(
                ErrorCode::Forbidden,
                format!(
                    "tenant {:?} may not read database {:?}",
                    tenant.cfg.name, hello.database
                ),
            ));
        }
        let session = match SessionSlot::try_new(tenant, self.shared) {
            Ok(s) => s,
            Err(NoPlace::Server) => {
                self.shared
                    .metrics
                    .connections_total
                    .with_label_values(&["rejected"])
                    .inc();
                tracing::warn!(
                    max = self.shared.cfg.max_connections,
                    "connection limit reached, refusing"
                );
                return Err(ErrorMsg::new(
                    ErrorCode::ServerBusy,
                    "server connection limit reached",
                ));
            }
            Err(NoPlace::Tenant) => {
                return Err(ErrorMsg::new(
                    ErrorCode::ServerBusy,
                    format!(
                        "tenant connection limit ({}) reached",
                        tenant.cfg.max_connections
                    ),
                ))
            }
        };
        let db = slot.current();
        let welcome = Welcome {
            version: planet_protocol::PROTOCOL_VERSION,
            database: slot.name.clone(),
            file_size: db.len(),
            header: db.header_bytes().to_vec(),
            limits: Limits {
                max_in_flight: tenant.cfg.max_in_flight,
                max_record_size: self.shared.cfg.max_record_size,
                max_bytes_per_second: tenant.cfg.max_bytes_per_second,
                idle_timeout_ms: self.shared.cfg.idle_timeout_ms,
            },
        };
        *self.chosen.borrow_mut() = Some((session, db));
        Ok(welcome)
    }
}

enum Step {
    Ctrl(Result<Option<quinn::Chunk>, quinn::ReadError>),
    Stream(Result<(SendStream, RecvStream), quinn::ConnectionError>),
    TaskDone,
    Shutdown,
    Deadline,
    HelloTimeout,
    /// Another address's newcomer took this pending slot (`pending.rs`).
    Evicted,
}

/// Why the connection loop ended, i.e. how to close.
enum End {
    /// The peer is gone: nothing to send.
    Lost,
    /// Close with this application code and reason.
    Close(u32, &'static str),
}

/// Serves one QUIC connection until it ends. `deadline` ends the
/// unauthenticated phase (control stream, `Hello`, the whole `Welcome`
/// written); `pending` is released once the session is established.
pub(crate) async fn serve_connection(
    conn: quinn::Connection,
    shared: Arc<Shared>,
    mut shutdown: watch::Receiver<bool>,
    deadline: tokio::time::Instant,
    mut pending: PendingGuard,
) {
    let peer = conn.remote_address();
    let evict = pending.eviction();
    let first = tokio::select! {
        r = conn.accept_bi() => Some(r),
        _ = tokio::time::sleep_until(deadline) => None,
        _ = evict.notified() => {
            evicted(&conn, &shared, peer);
            return;
        }
        _ = shutdown.wait_for(|s| *s) => {
            shared.metrics.handshake(HandshakeEnd::Lost);
            conn.close(code(quic::CONNECTION_CLOSED_SHUTDOWN), b"shutting down");
            return;
        }
    };
    let (mut ctrl_send, mut ctrl_recv) = match first {
        Some(Ok(streams)) => streams,
        Some(Err(e)) => {
            shared.metrics.handshake(HandshakeEnd::Lost);
            tracing::debug!(%peer, error = %e, "connection ended before the control stream");
            return;
        }
        None => {
            shared.metrics.handshake(HandshakeEnd::Timeout);
            conn.close(
                code(ErrorCode::HelloRequired.to_quic()),
                b"no control stream",
            );
            return;
        }
    };

    let ctx = Arc::new(ConnCtx {
        shared: Arc::clone(&shared),
        established: OnceLock::new(),
        draining: AtomicBool::new(false),
        cancelled: Mutex::new(HashSet::new()),
    });
    let (abort_tx, abort_rx) = watch::channel(false);
    let mut session = ServerSession::new();
    // The connection's requests, polled by this task rather than spawned
    // one task each: most complete in their first poll (the request frame
    // arrives with the stream, the response fits the flow-control window),
    // and a spawned task cost a scheduler round trip, a join and a wake-up
    // of this task per request.
    let mut tasks: FuturesUnordered<RequestFuture> = FuturesUnordered::new();
    let mut ctrl_open = true;
    let mut accepting = true;
    let mut draining: Option<(tokio::time::Instant, u32, &'static str)> = None;
    let hello_deadline = deadline;
    let mut handshake_counted = false;

    let end = loop {
        if let Some((_, code_, reason)) = draining {
            if tasks.is_empty() {
                break End::Close(code_, reason);
            }
        }
        let deadline = draining.map(|d| d.0);
        let established = ctx.established.get().is_some();
        let step = tokio::select! {
            r = ctrl_recv.read_chunk(16 * 1024, true), if ctrl_open => Step::Ctrl(r),
            r = conn.accept_bi(), if accepting => Step::Stream(r),
            Some(()) = tasks.next(), if !tasks.is_empty() => Step::TaskDone,
            _ = shutdown.wait_for(|s| *s), if draining.is_none() => Step::Shutdown,
            _ = sleep_until_opt(deadline), if deadline.is_some() => Step::Deadline,
            _ = tokio::time::sleep_until(hello_deadline), if !established && draining.is_none() => Step::HelloTimeout,
            _ = evict.notified(), if !established && draining.is_none() => Step::Evicted,
        };
        match step {
            Step::Ctrl(Ok(Some(chunk))) => {
                let auth = ConnAuth {
                    shared: &shared,
                    peer: peer.ip(),
                    chosen: RefCell::new(None),
                };
                let events = session.receive(&chunk.bytes, &auth);
                let mut fatal = None;
                let mut timed_out = false;
                for ev in events {
                    match ev {
                        ServerEvent::Welcomed { welcome, reply } => {
                            let Some((slot, db)) = auth.chosen.borrow_mut().take() else {
                                fatal = Some(ErrorMsg::new(ErrorCode::Internal, "no database"));
                                break;
                            };
                            let tenant = Arc::clone(&slot.0);
                            // Writing the Welcome must make progress at
                            // once: it is a few hundred bytes, and quinn
                            // takes stream data as soon as the peer's
                            // flow-control credit (its transport parameters)
                            // allows, without a round trip. A client that
                            // advertised no window at all would otherwise
                            // hold a place of `max_connections` (taken
                            // above) until the handshake deadline (ISSUE
                            // #17). A small window that the client opens as
                            // it reads may take the rest of the deadline,
                            // during which the slot stays evictable.
                            let write = match ctrl_send.write(&reply).now_or_never() {
                                None | Some(Ok(0)) => Err(HandshakeEnd::Timeout),
                                Some(Err(e)) => Ok(Err(e)),
                                Some(Ok(n)) => tokio::select! {
                                    r = tokio::time::timeout_at(
                                        hello_deadline,
                                        ctrl_send.write_all(&reply[n..]),
                                    ) => r.map_err(|_| HandshakeEnd::Timeout),
                                    _ = evict.notified() => Err(HandshakeEnd::Evicted),
                                },
                            };
                            match write {
                                Ok(Ok(())) => {}
                                Ok(Err(e)) => {
                                    tracing::debug!(%peer, error = %e, "cannot write welcome");
                                    break;
                                }
                                Err(end) => {
                                    tracing::debug!(%peer, outcome = end.as_str(), "welcome not written within the handshake phase");
                                    handshake_counted = true;
                                    shared.metrics.handshake(end);
                                    timed_out = true;
                                    break;
                                }
                            }
                            handshake_counted = true;
                            if !pending.release() {
                                // Evicted while the Welcome was written.
                                timed_out = true;
                                let _ = abort_tx.send(true);
                                evicted(&conn, &shared, peer);
                                break;
                            }
                            shared.metrics.handshake(HandshakeEnd::Ok);
                            conn.set_max_concurrent_bi_streams(VarInt::from_u32(
                                welcome.limits.max_in_flight + 1 + STREAM_MARGIN,
                            ));
                            tracing::info!(
                                %peer, tenant = %tenant.cfg.name, database = %db.name,
                                "session established"
                            );
                            let _ = ctx.established.set(Established {
                                _slot: slot,
                                in_flight: Mutex::new(InFlight::new(tenant.cfg.max_in_flight)),
                                ok: OkMetrics::new(&shared.metrics, &tenant.cfg.name, &db.name),
                                tenant,
                                db,
                                session: session.clone(),
                            });
                        }
                        ServerEvent::Fatal { error, reply } => {
                            if !handshake_counted {
                                handshake_counted = true;
                                shared.metrics.handshake(HandshakeEnd::Refused(error.code));
                            }
                            tracing::info!(%peer, error = %error, "control stream error, closing");
                            let _ =
                                tokio::time::timeout(FLUSH_TIMEOUT, ctrl_send.write_all(&reply))
                                    .await;
                            fatal = Some(error);
                            break;
                        }
                        ServerEvent::Cancel { id } => {
                            if let Ok(mut c) = ctx.cancelled.lock() {
                                if c.len() < 4096 {
                                    c.insert(id);
                                }
                            }
                        }
                        ServerEvent::Goodbye { reason } => {
                            tracing::debug!(%peer, %reason, "client said goodbye");
                            ctrl_open = false;
                            accepting = false;
                            draining.get_or_insert((
                                tokio::time::Instant::now() + shared.cfg.shutdown_grace,
                                quic::CONNECTION_CLOSED_NORMAL,
                                "goodbye",
                            ));
                        }
                        ServerEvent::PeerError(e) => {
                            tracing::debug!(%peer, error = %e, "client reported an error");
                        }
                    }
                }
                if timed_out {
                    let _ = abort_tx.send(true);
                    conn.close(code(ErrorCode::Timeout.to_quic()), b"handshake timeout");
                    break End::Lost;
                }
                if let Some(error) = fatal {
                    let _ = ctrl_send.finish();
                    let _ = tokio::time::timeout(FLUSH_TIMEOUT, ctrl_send.stopped()).await;
                    let _ = abort_tx.send(true);
                    conn.close(code(error.code.to_quic()), error.code.as_str().as_bytes());
                    break End::Lost;
                }
            }
            Step::Ctrl(Ok(None)) => {
                ctrl_open = false;
                if let Some(ServerEvent::Fatal { error, reply }) = session.finish() {
                    if !handshake_counted {
                        handshake_counted = true;
                        shared.metrics.handshake(HandshakeEnd::Refused(error.code));
                    }
                    let _ = tokio::time::timeout(FLUSH_TIMEOUT, ctrl_send.write_all(&reply)).await;
                    let _ = ctrl_send.finish();
                    let _ = tokio::time::timeout(FLUSH_TIMEOUT, ctrl_send.stopped()).await;
                    let _ = abort_tx.send(true);
                    conn.close(code(error.code.to_quic()), error.code.as_str().as_bytes());
                    break End::Lost;
                }
                // Finishing the control stream ends the session gracefully.
                accepting = false;
                draining.get_or_insert((
                    tokio::time::Instant::now() + shared.cfg.shutdown_grace,
                    quic::CONNECTION_CLOSED_NORMAL,
                    "done",
                ));
            }
            Step::Ctrl(Err(e)) => {
                tracing::debug!(%peer, error = %e, "control stream ended");
                break End::Lost;
            }
            Step::Stream(Ok((send, recv))) => {
                let ctx = Arc::clone(&ctx);
                let abort = abort_rx.clone();
                tasks.push(Box::pin(serve_request(ctx, send, recv, abort)));
            }
            Step::Stream(Err(e)) => {
                tracing::debug!(%peer, error = %e, "connection ended");
                break End::Lost;
            }
            Step::TaskDone => {}
            Step::Shutdown => {
                ctx.draining.store(true, Ordering::Release);
                if let Ok(frame) = (Goodbye {
                    reason: ErrorCode::ShuttingDown,
                })
                .encode_frame()
                {
                    let _ = tokio::time::timeout(FLUSH_TIMEOUT, ctrl_send.write_all(&frame)).await;
                }
                draining = Some((
                    tokio::time::Instant::now() + shared.cfg.shutdown_grace,
                    quic::CONNECTION_CLOSED_SHUTDOWN,
                    "shutting down",
                ));
            }
            Step::Deadline => {
                // Grace period over: reset whatever is still being sent.
                let _ = abort_tx.send(true);
                let _ = tokio::time::timeout(Duration::from_secs(1), async {
                    while tasks.next().await.is_some() {}
                })
                .await;
                let (c, r) = draining
                    .map_or((quic::CONNECTION_CLOSED_SHUTDOWN, "shutting down"), |d| {
                        (d.1, d.2)
                    });
                break End::Close(c, r);
            }
            Step::Evicted => {
                handshake_counted = true;
                let _ = abort_tx.send(true);
                evicted(&conn, &shared, peer);
                break End::Lost;
            }
            Step::HelloTimeout => {
                if !handshake_counted {
                    handshake_counted = true;
                    shared.metrics.handshake(HandshakeEnd::Timeout);
                }
                let _ = abort_tx.send(true);
                conn.close(code(ErrorCode::HelloRequired.to_quic()), b"hello timeout");
                break End::Lost;
            }
        }
    };
    if !handshake_counted {
        shared.metrics.handshake(HandshakeEnd::Lost);
    }
    if let End::Close(c, reason) = end {
        let _ = ctrl_send.finish();
        let _ = tokio::time::timeout(FLUSH_TIMEOUT, ctrl_send.stopped()).await;
        conn.close(code(c), reason.as_bytes());
    }
    // The connection is closed: what is left of its requests can send
    // nothing more, so dropping them cannot truncate a response.
    let _ = abort_tx.send(true);
    drop(tasks);
    let stats = conn.stats();
    tracing::debug!(
        %peer,
        path_mtu = stats.path.current_mtu,
        rtt_us = stats.path.rtt.as_micros() as u64,
        datagrams_sent = stats.udp_tx.datagrams,
        bytes_sent = stats.udp_tx.bytes,
        packets_lost = stats.path.lost_packets,
        mtu_probes = stats.path.sent_plpmtud_probes,
        mtu_probes_lost = stats.path.lost_plpmtud_probes,
        black_holes = stats.path.black_holes_detected,
        "connection ended"
    );
}

/// Closes a pending connection whose slot another address took
/// (`pending.rs`), with `server_busy`.
fn evicted(conn: &quinn::Connection, shared: &Shared, peer: std::net::SocketAddr) {
    shared.metrics.handshake(HandshakeEnd::Evicted);
    tracing::debug!(%peer, "pending slot taken by another address, closing");
    conn.close(
        code(ErrorCode::ServerBusy.to_quic()),
        b"pre-authentication slots full",
    );
}

/// One request stream being served ([`serve_request`]).
type RequestFuture = Pin<Box<dyn Future<Output = ()> + Send>>;

async fn sleep_until_opt(deadline: Option<tokio::time::Instant>) {
    match deadline {
        Some(d) => tokio::time::sleep_until(d).await,
        None => std::future::pending().await,
    }
}

/// Decrements the in-flight accounting when a request ends.
struct InFlightGuard<'a> {
    est: &'a Established,
    id: u64,
    gauge: &'a prometheus::IntGauge,
}

impl Drop for InFlightGuard<'_> {
    fn drop(&mut self) {
        if let Ok(mut f) = self.est.in_flight.lock() {
            f.end(self.id);
        }
        self.gauge.dec();
    }
}

/// Writes an error head and finishes the stream. Codes that exist only as
/// QUIC application codes (`timeout`, `storage`: added within protocol
/// version 1, docs/PROTOCOL.md §6) reset the stream with the code instead.
async fn reply_error(send: &mut SendStream, id: u64, error: ErrorMsg) {
    if matches!(error.code, ErrorCode::Timeout | ErrorCode::Storage) {
        let _ = send.reset(code(error.code.to_quic()));
        return;
    }
    match ResponseHead::error(id, error).encode_frame() {
        Ok(frame) => match tokio::time::timeout(FLUSH_TIMEOUT, send.write_all(&frame)).await {
            Ok(Ok(())) => {
                let _ = send.finish();
                let _ = tokio::time::timeout(FLUSH_TIMEOUT, send.stopped()).await;
            }
            Ok(Err(_)) => {}
            Err(_) => {
                let _ = send.reset(code(ErrorCode::Timeout.to_quic()));
            }
        },
        Err(_) => {
            let _ = send.reset(code(ErrorCode::Internal.to_quic()));
        }
    }
}

/// A read of the database file failed: a per-request `storage` error, a
/// metric, and a log line at most once a minute per record.
fn storage_error(ctx: &ConnCtx, db: &MappedDb, offset: u64, e: &std::io::Error) -> ErrorMsg {
    let shared = &ctx.shared;
    shared
        .metrics
        .storage_errors_total
        .with_label_values(&[&db.name])
        .inc();
    if shared.record_alerts.note(&db.name, offset).log {
        tracing::error!(
            database = %db.name, path = %db.path.display(), offset, error = %e,
            "cannot read the database file (truncated in place or failing storage)"
        );
    }
    ErrorMsg::new(
        ErrorCode::Storage,
        format!("the server cannot read the record at {offset}"),
    )
}

/// Checks a request against the session and the database
/// ([`MappedDb::check_request`]: reads only the 8-byte record prefix).
fn validate(ctx: &ConnCtx, est: &Established, req: &LodRequest) -> Result<(), ErrorMsg> {
    est.session.check_request(req)?;
    let db = &est.db;
    db.check_request(req.offset, req.size).map_err(|e| match e {
        RequestCheck::Refused(msg) => msg,
        RequestCheck::Storage(e) => storage_error(ctx, db, req.offset, &e),
    })
}

/// The trailer of a `LodRefsRequest` response (docs/PROTOCOL.md §4.8): the
/// child table of each child of `record` (whose checksum was checked), read
/// with the same storage read as a record. A child whose record cannot be
/// read, fails its checksum or whose references do not parse is unknown
/// (`0xff`), as is one the client could not request itself (outside the
/// record area, over `max_record_size`): a refs request never makes the
/// server read what it would refuse to serve. A record whose own references
/// do not parse (which the client refuses too) gets an empty trailer.
fn child_tables(
    est: &Established,
    record: &[u8],
    max_record_size: u32,
    floors: Option<[f32; 4]>,
) -> Vec<u8> {
    let db = &est.db;
    let read = |c: &ChildRef| {
        let in_area = c.offset >= SUPERBLOCK_LEN as u64
            && c.offset
                .checked_add(u64::from(c.size))
                .is_some_and(|end| end <= db.records_end());
        if !in_area || c.size > max_record_size {
            return None;
        }
        db.read(c.offset, c.size as usize)
            .map_err(|e| {
                tracing::debug!(
                    database = %db.name, offset = c.offset, error = %e,
                    "cannot read a child record for its child table"
                );
            })
            .ok()
    };
    child_tables_for(record, Some(db.len()), floors, read).unwrap_or_default()
}

async fn serve_request(
    ctx: Arc<ConnCtx>,
    mut send: SendStream,
    mut recv: RecvStream,
    mut abort: watch::Receiver<bool>,
) {
    let metrics = &ctx.shared.metrics;
    let read = tokio::time::timeout(
        REQUEST_READ_TIMEOUT,
        recv.read_to_end(MAX_REQUEST_STREAM_LEN),
    );
    let bytes = match read.await {
        Ok(Ok(b)) => b,
        Ok(Err(quinn::ReadToEndError::TooLong)) => {
            let _ = recv.stop(code(ErrorCode::Malformed.to_quic()));
            metrics.request(NO_TENANT, NO_TENANT, RequestOutcome::Invalid);
            reply_error(
                &mut send,
                0,
                ErrorMsg::new(
                    ErrorCode::Malformed,
                    "request stream longer than one request",
                ),
            )
            .await;
            return;
        }
        Ok(Err(quinn::ReadToEndError::Read(e))) => {
            tracing::debug!(error = %e, "request stream read failed");
            let _ = send.reset(code(quic::STREAM_CANCELLED));
            return;
        }
        Err(_) => {
            // The request never completed: free the stream with its own code
            // (not `malformed`: nothing invalid was received).
            let _ = recv.stop(code(ErrorCode::Timeout.to_quic()));
            let _ = send.reset(code(ErrorCode::Timeout.to_quic()));
            metrics.request(NO_TENANT, NO_TENANT, RequestOutcome::Timeout);
            return;
        }
    };
    // A `LodRequest`, a `LodRefsRequest` or a `LodRefsAboveRequest`: the
    // same record, the same checks; the latter two's responses add the
    // children's child tables (above the request's floors for 0x13). With
    // child tables turned off, 0x12 and 0x13 are unknown frames, as on a
    // server that predates them (id 0; docs/PROTOCOL.md §7), so clients
    // fall back; so is 0x14 with priorities turned off.
    let decoded = decode_prioritized_request_stream(&bytes).and_then(|s| {
        if s.kind.has_refs() && !ctx.shared.cfg.child_tables {
            Err(ProtocolError::UnknownMessageType(s.kind.msg_type().as_u8()))
        } else if s.priority.is_some() && !ctx.shared.cfg.stream_priority {
            Err(ProtocolError::UnknownMessageType(
                MessageType::Priority.as_u8(),
            ))
        } else {
            Ok(s)
        }
    });
    let (req, kind) = match decoded {
        Ok(s) => {
            // The response leaves before those of lower priority still in
            // QUIC's send buffer (docs/PROTOCOL.md §4.10); among equal
            // priorities, in the order written (`send_fairness(false)`).
            if let Some(p) = s.priority {
                // Fails only on a stream already reset.
                let _ = send.set_priority(p.priority);
            }
            (s.request, s.kind)
        }
        Err(e) => {
            let (t, d) = ctx.established.get().map_or((NO_TENANT, NO_TENANT), |e| {
                (e.tenant.cfg.name.as_str(), e.db.name.as_str())
            });
            metrics.request(t, d, RequestOutcome::Invalid);
            reply_error(&mut send, 0, e.to_error_msg()).await;
            return;
        }
    };
    let Some(est) = ctx.established.get() else {
        metrics.request(NO_TENANT, NO_TENANT, RequestOutcome::Unauthorized);
        reply_error(
            &mut send,
            req.id,
            ErrorMsg::new(
                ErrorCode::HelloRequired,
                "request before the handshake completed",
            ),
        )
        .await;
        return;
    };
    let tenant = est.tenant.cfg.name.as_str();
    let dbname = est.db.name.as_str();
    let fail = |e: ErrorMsg| {
        metrics.request(tenant, dbname, RequestOutcome::for_code(e.code));
        e
    };
    if ctx.draining.load(Ordering::Acquire) {
        let e = fail(ErrorMsg::new(
            ErrorCode::ShuttingDown,
            "server is shutting down",
        ));
        reply_error(&mut send, req.id, e).await;
        return;
    }
    if let Err(e) = validate(&ctx, est, &req) {
        let e = fail(e);
        reply_error(&mut send, req.id, e).await;
        return;
    }
    let begun = match est.in_flight.lock() {
        Ok(mut f) => f.begin(req.id).map_err(|e| e.to_error_msg()),
        Err(_) => Err(ErrorMsg::new(
            ErrorCode::Internal,
            "in-flight state poisoned",
        )),
    };
    if let Err(e) = begun {
        let e = fail(e);
        reply_error(&mut send, req.id, e).await;
        return;
    }
    metrics.requests_in_flight.inc();
    let guard = InFlightGuard {
        est,
        id: req.id,
        gauge: &metrics.requests_in_flight,
    };
    let started = Instant::now();
    let size = u64::from(req.size);

    // Per-tenant requests, then bandwidth: pace modest excess, refuse long
    // waits. A refs request reserves its largest response, the record plus
    // `MAX_REFS_TRAILER_LEN` (its trailer is not known before the children
    // are read, after pacing); what is not sent is refunded.
    let reserved = size + u64::from(kind.max_trailer_len());
    let refund = |bytes: u64| {
        if let Some(b) = est.tenant.bucket.as_ref().filter(|_| bytes > 0) {
            b.refund(bytes);
        }
    };
    let buckets = [
        (&est.tenant.requests, 1, "request"),
        (&est.tenant.bucket, reserved, "bandwidth"),
    ];
    for (bucket, amount, what) in buckets {
        let Some(bucket) = bucket else { continue };
        match bucket.reserve(amount, ctx.shared.cfg.max_rate_wait) {
            Ok(wait) if !wait.is_zero() => {
                let aborted = tokio::select! {
                    _ = tokio::time::sleep(wait) => false,
                    _ = abort.wait_for(|a| *a) => true,
                    _ = send.stopped() => true,
                };
                if aborted {
                    bucket.refund(amount);
                    let _ = send.reset(code(quic::STREAM_CANCELLED));
                    metrics.request(tenant, dbname, RequestOutcome::Cancelled);
                    return;
                }
            }
            Ok(_) => {}
            Err(wait) => {
                let e = fail(ErrorMsg::new(
                    ErrorCode::RateLimited,
                    format!(
                        "tenant {what} limit: would wait {:.1} s (limit {:.1} s)",
                        wait.as_secs_f64(),
                        ctx.shared.cfg.max_rate_wait.as_secs_f64()
                    ),
                ));
                reply_error(&mut send, req.id, e).await;
                return;
            }
        }
    }
    let was_cancelled = ctx
        .cancelled
        .lock()
        .map(|mut c| c.remove(&req.id))
        .unwrap_or(false);
    if was_cancelled {
        refund(reserved);
        let _ = send.reset(code(quic::STREAM_CANCELLED));
        metrics.request(tenant, dbname, RequestOutcome::Cancelled);
        return;
    }

    let body = match est.db.read(req.offset, req.size as usize) {
        Ok(b) => b,
        Err(e) => {
            refund(reserved);
            let e = fail(storage_error(&ctx, &est.db, req.offset, &e));
            reply_error(&mut send, req.id, e).await;
            return;
        }
    };
    if !record_checksum_ok(&body) {
        refund(reserved);
        let alert = ctx.shared.record_alerts.note(dbname, req.offset);
        if alert.first {
            metrics
                .corrupt_records_total
                .with_label_values(&[dbname])
                .inc();
        }
        if alert.log {
            tracing::error!(
                database = dbname, path = %est.db.path.display(), offset = req.offset, size = req.size,
                "record failed its checksum: the database file is corrupt"
            );
        }
        let e = fail(ErrorMsg::new(
            ErrorCode::CorruptRecord,
            format!("record at {} failed its checksum on the server", req.offset),
        ));
        reply_error(&mut send, req.id, e).await;
        return;
    }
    let trailer = match kind {
        RequestKind::Record => Vec::new(),
        RequestKind::RecordAndRefs => {
            child_tables(est, &body, ctx.shared.cfg.max_record_size, None)
        }
        RequestKind::RecordAndRefsAbove(floors) => child_tables(
            est,
            &body,
            ctx.shared.cfg.max_record_size,
            Some(floors.get()),
        ),
    };
    refund(reserved.saturating_sub(size + trailer.len() as u64));
    // `trailer.len() <= MAX_REFS_TRAILER_LEN` and `size <= max_record_size`.
    let body_len = u32::try_from(trailer.len())
        .ok()
        .and_then(|t| req.size.checked_add(t));
    let head = match body_len.map(|len| ResponseHead::ok(req.id, len).encode_frame()) {
        Some(Ok(h)) => h,
        _ => {
            let e = fail(ErrorMsg::new(ErrorCode::Internal, "cannot encode head"));
            reply_error(&mut send, req.id, e).await;
            return;
        }
    };
    let sent = size + trailer.len() as u64;
    let mut chunks = [Bytes::from(head), body, Bytes::from(trailer)];
    // No empty trailer chunk: a plain request writes exactly what it did
    // before refs requests existed.
    let n_chunks = if chunks[2].is_empty() { 2 } else { 3 };
    let write_deadline = tokio::time::sleep(ctx.shared.cfg.write_timeout);
    let written = tokio::select! {
        // The write usually completes in its first poll: try it before
        // registering with the abort signal and the timer (a `Sleep`
        // registers with the timer only when polled).
        biased;
        r = send.write_all_chunks(&mut chunks[..n_chunks]) => Some(Some(r)),
        _ = abort.wait_for(|a| *a) => None,
        _ = write_deadline => Some(None),
    };
    let outcome = match written {
        None => {
            let _ = send.reset(code(quic::CONNECTION_CLOSED_SHUTDOWN));
            RequestOutcome::Error
        }
        // The client did not take the response within the write deadline
        // (it stopped reading, or keeps its window closed).
        Some(None) => {
            let _ = send.reset(code(ErrorCode::Timeout.to_quic()));
            RequestOutcome::Timeout
        }
        Some(Some(written)) => match written {
            Err(quinn::WriteError::Stopped(_)) => RequestOutcome::Cancelled,
            // The client went away mid-response: not a server error.
            Err(quinn::WriteError::ConnectionLost(_)) => RequestOutcome::Cancelled,
            Err(e) => {
                tracing::warn!(error = %e, "response write failed");
                let _ = send.reset(code(ErrorCode::Internal.to_quic()));
                RequestOutcome::Error
            }
            Ok(()) => {
                // The whole response is in QUIC's send buffer and the stream is
                // finished: quinn delivers (and retransmits) it after `send` is
                // dropped. The request is no longer in flight, and the client,
                // which reads up to the FIN, may reuse its id at once. Buffered
                // memory stays bounded by the stream limit: a stream counts
                // against it until the client has acknowledged all of it. We do
                // not wait for that acknowledgement (until 2026-11-22 every
                // request did, to count a late STOP_SENDING as `cancelled`: a
                // timer and a wake-up per request for a metric).
                let _ = send.finish();
                RequestOutcome::Ok
            }
        },
    };
    drop(guard);
    if outcome == RequestOutcome::Ok {
        est.ok.requests.inc();
        // The record and the trailer of a refs request.
        est.ok.bytes_sent.inc_by(sent);
        est.ok.record_size.observe(size as f64);
        est.ok.duration.observe(started.elapsed().as_secs_f64());
    } else {
        metrics.request(tenant, dbname, outcome);
    }
}
