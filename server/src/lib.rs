//! `planet-server`: multi-tenant QUIC server of memory-mapped planet
//! databases.
//!
//! - [`config`]: TOML configuration and the checked [`ServerConfig`].
//! - [`db`]: validated, memory-mapped databases and their reload.
//! - [`metrics`]: Prometheus metrics and the `/metrics` `/healthz` `/readyz`
//!   HTTP server.
//! - [`tls`]: certificates (PEM or generated), rustls/ring, ALPN, no 0-RTT.
//! - [`limit`]: token buckets (tenant bandwidth and requests, failed
//!   hellos per address).
//! - [`token`]: tenant tokens, kept as SHA-256 hashes.
//! - `conn` (private): per-connection protocol handling.
//!
//! Start a server in-process with [`Server::start`]; the binary
//! (`src/main.rs`) adds the CLI, logging and signals.

pub mod config;
mod conn;
pub mod db;
pub mod limit;
pub mod metrics;
mod pending;
pub mod tls;
pub mod token;
pub mod udp;

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use planet_protocol::quic;
use quinn::VarInt;
use tokio::sync::watch;
use tokio::task::JoinHandle;

pub use config::{
    ConfigError, Congestion, DatabaseConfig, ServerConfig, StorageMode, TenantConfig, TlsSource,
};
pub use db::{DbError, ReloadOutcome};
pub use metrics::Metrics;
pub use token::Token;

/// Why the server could not start.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// Invalid configuration.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A database file cannot be served.
    #[error(transparent)]
    Database(#[from] DbError),
    /// Certificate or TLS configuration problem.
    #[error(transparent)]
    Tls(#[from] tls::TlsError),
    /// Binding a socket failed.
    #[error("cannot bind {what} on {addr}: {source}")]
    Bind {
        /// `QUIC` or `metrics`.
        what: &'static str,
        /// The address.
        addr: SocketAddr,
        /// The I/O error.
        source: std::io::Error,
    },
    /// Metrics registration failed (a bug).
    #[error("metrics: {0}")]
    Metrics(#[from] prometheus::Error),
}

/// A tenant at run time.
pub(crate) struct TenantRt {
    pub(crate) cfg: TenantConfig,
    /// Bandwidth bucket (`max_bytes_per_second`).
    pub(crate) bucket: Option<limit::TokenBucket>,
    /// Request bucket (`max_requests_per_second`).
    pub(crate) requests: Option<limit::TokenBucket>,
    /// Established sessions (`max_connections`).
    pub(crate) sessions: AtomicUsize,
}

impl TenantRt {
    pub(crate) fn token_matches(&self, presented: &str) -> bool {
        self.cfg.token.matches(presented)
    }
}

/// State shared by the accept loop and every connection.
pub(crate) struct Shared {
    pub(crate) cfg: ServerConfig,
    pub(crate) dbs: HashMap<String, db::DbSlot>,
    pub(crate) tenants: HashMap<String, Arc<TenantRt>>,
    pub(crate) dummy_token: Token,
    pub(crate) metrics: Metrics,
    http: Arc<metrics::HttpState>,
    active: AtomicUsize,
    /// Established sessions (`max_connections`).
    pub(crate) sessions: AtomicUsize,
    /// Connections not yet authenticated (`max_pending_handshakes`).
    pending: pending::PendingTable,
    /// Open connections (pending and established) per client IP.
    per_address: Mutex<HashMap<IpAddr, usize>>,
    /// Failed hellos per client IP.
    pub(crate) failed_hellos: limit::KeyedBuckets,
    /// New connections per client IP.
    handshakes: limit::KeyedBuckets,
    /// Log and alert rate limit per failing record.
    pub(crate) record_alerts: limit::RecordAlerts,
}

impl Shared {
    fn reload(&self) -> Vec<(String, ReloadOutcome)> {
        let mut out = Vec::new();
        for (name, slot) in &self.dbs {
            let outcome = slot.reload();
            match &outcome {
                ReloadOutcome::Unchanged => {
                    tracing::info!(database = %name, "reload: file unchanged")
                }
                ReloadOutcome::Reloaded => {
                    let size = slot.current().len();
                    tracing::info!(database = %name, path = %slot.path.display(), size, "reload: new file mapped for new sessions");
                    self.metrics
                        .database_reloads_total
                        .with_label_values(&[name])
                        .inc();
                    self.metrics
                        .database_size_bytes
                        .with_label_values(&[name])
                        .set(i64::try_from(size).unwrap_or(i64::MAX));
                }
                ReloadOutcome::Failed(e) => {
                    tracing::error!(database = %name, error = %e, "reload failed: keeping the previous file")
                }
            }
            out.push((name.clone(), outcome));
        }
        out.sort_by(|a, b| a.0.cmp(&b.0));
        out
    }
}

/// Decrements the connection gauges when a connection task ends.
struct ActiveGuard(Arc<Shared>);

impl Drop for ActiveGuard {
    fn drop(&mut self) {
        self.0.active.fetch_sub(1, Ordering::AcqRel);
        self.0.metrics.connections_active.dec();
    }
}

/// One connection of a client IP (`max_connections_per_address`).
struct AddressGuard(Arc<Shared>, IpAddr);

impl AddressGuard {
    fn try_new(shared: &Arc<Shared>, ip: IpAddr) -> Option<AddressGuard> {
        let mut map = match shared.per_address.lock() {
            Ok(m) => m,
            Err(p) => p.into_inner(),
        };
        let n = map.entry(ip).or_insert(0);
        if *n >= shared.cfg.max_connections_per_address {
            return None;
        }
        *n += 1;
        Some(AddressGuard(Arc::clone(shared), ip))
    }
}

impl Drop for AddressGuard {
    fn drop(&mut self) {
        let mut map = match self.0.per_address.lock() {
            Ok(m) => m,
            Err(p) => p.into_inner(),
        };
        if let Some(n) = map.get_mut(&self.1) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                map.remove(&self.1);
            }
        }
    }
}

/// An unauthenticated connection's slot in [`pending::PendingTable`]:
/// given back when its session is established or the connection ends.
pub(crate) struct PendingGuard {
    shared: Option<Arc<Shared>>,
    ip: IpAddr,
    id: u64,
    evict: Arc<tokio::sync::Notify>,
}

impl PendingGuard {
    /// A slot for a connection from `ip`, possibly by evicting another
    /// address's oldest pending connection; `None` when there is none.
    fn admit(shared: &Arc<Shared>, ip: IpAddr) -> Option<PendingGuard> {
        let a = shared
            .pending
            .admit(ip, shared.cfg.max_pending_handshakes)?;
        if a.evicted_other {
            tracing::debug!(%ip, "pending budget full: took the slot of a busier address");
        }
        shared
            .metrics
            .handshakes_pending
            .set(i64::try_from(shared.pending.len()).unwrap_or(i64::MAX));
        Some(PendingGuard {
            shared: Some(Arc::clone(shared)),
            ip,
            id: a.id,
            evict: a.evict,
        })
    }

    /// Notified when a newcomer from another address took this slot.
    pub(crate) fn eviction(&self) -> Arc<tokio::sync::Notify> {
        Arc::clone(&self.evict)
    }

    /// The session is authenticated: no longer pending. `false` if the
    /// slot had already been taken by eviction (the connection must then
    /// close, even though its Welcome was written).
    pub(crate) fn release(&mut self) -> bool {
        let Some(shared) = self.shared.take() else {
            return false;
        };
        let held = shared.pending.remove(self.ip, self.id);
        shared
            .metrics
            .handshakes_pending
            .set(i64::try_from(shared.pending.len()).unwrap_or(i64::MAX));
        held
    }
}

impl Drop for PendingGuard {
    fn drop(&mut self) {
        let _ = self.release();
    }
}

/// Entry point: [`Server::start`].
pub struct Server;

/// A running server.
pub struct ServerHandle {
    local_addr: SocketAddr,
    metrics_addr: Option<SocketAddr>,
    fingerprint: String,
    cert_der: Vec<u8>,
    shared: Arc<Shared>,
    endpoint: quinn::Endpoint,
    shutdown_tx: watch::Sender<bool>,
    accept_task: JoinHandle<()>,
    http_stop: watch::Sender<bool>,
    http_task: Option<JoinHandle<()>>,
}

impl Server {
    /// Opens and validates the databases, binds the QUIC endpoint and the
    /// metrics listener, and starts serving. Must be called inside a tokio
    /// runtime.
    pub async fn start(config: ServerConfig) -> Result<ServerHandle, ServerError> {
        tls::install_crypto_provider();
        config.validate()?;
        let metrics = Metrics::new()?;
        let mut dbs = HashMap::new();
        for d in &config.databases {
            let slot = db::DbSlot::open(&d.name, &d.path, config.storage)?;
            let cur = slot.current();
            tracing::info!(database = %d.name, path = %d.path.display(), size = cur.len(), "database mapped");
            metrics.init_database(&d.name, cur.len());
            dbs.insert(d.name.clone(), slot);
        }
        for t in &config.tenants {
            metrics.init_tenant(&t.name, &t.databases);
        }
        let tenants = config
            .tenants
            .iter()
            .map(|t| {
                let rt = TenantRt {
                    cfg: t.clone(),
                    bucket: (t.max_bytes_per_second > 0)
                        .then(|| limit::TokenBucket::new(t.max_bytes_per_second)),
                    requests: (t.max_requests_per_second > 0)
                        .then(|| limit::TokenBucket::new(u64::from(t.max_requests_per_second))),
                    sessions: AtomicUsize::new(0),
                };
                (t.name.clone(), Arc::new(rt))
            })
            .collect();

        let ck = match &config.tls {
            TlsSource::Pem { cert, key } => tls::CertKey::from_pem_files(cert, key)?,
            TlsSource::DevCert => tls::CertKey::dev_cert()?,
        };
        let fingerprint = tls::sha256_hex(ck.leaf_der());
        let cert_der = ck.leaf_der().to_vec();
        let rustls_cfg = tls::rustls_server_config(&ck, config.zero_rtt)?;
        let quic_crypto = quinn::crypto::rustls::QuicServerConfig::try_from(rustls_cfg)
            .map_err(tls::TlsError::Quic)?;
        let mut server_cfg = quinn::ServerConfig::with_crypto(Arc::new(quic_crypto));
        server_cfg.transport_config(Arc::new(transport_config(&config)?));

        let endpoint = udp::server_endpoint(server_cfg, config.listen).map_err(|source| {
            ServerError::Bind {
                what: "QUIC",
                addr: config.listen,
                source,
            }
        })?;
        let local_addr = endpoint.local_addr().map_err(|source| ServerError::Bind {
            what: "QUIC",
            addr: config.listen,
            source,
        })?;

        let http = Arc::new(metrics::HttpState {
            metrics: metrics.clone(),
            ready: std::sync::atomic::AtomicBool::new(false),
        });
        let (http_stop, http_stop_rx) = watch::channel(false);
        let (metrics_addr, http_task) = match config.metrics {
            Some(addr) => {
                let listener = tokio::net::TcpListener::bind(addr)
                    .await
                    .map_err(|source| ServerError::Bind {
                        what: "metrics",
                        addr,
                        source,
                    })?;
                let bound = listener.local_addr().map_err(|source| ServerError::Bind {
                    what: "metrics",
                    addr,
                    source,
                })?;
                let task = tokio::spawn(metrics::serve_http(
                    listener,
                    Arc::clone(&http),
                    http_stop_rx,
                ));
                (Some(bound), Some(task))
            }
            None => (None, None),
        };

        if let Some(m) = config.metrics.filter(|m| !m.ip().is_loopback()) {
            tracing::warn!(metrics = %m, "the metrics endpoint listens beyond loopback: keep it on a private network (docs/DEPLOY.md)");
        }
        let shared = Arc::new(Shared {
            dbs,
            tenants,
            dummy_token: Token::new("planet-server: no such tenant"),
            failed_hellos: limit::KeyedBuckets::per_minute(config.max_failed_hellos_per_minute),
            handshakes: limit::KeyedBuckets::per_second(
                config.max_handshakes_per_address_per_second,
                config
                    .max_connections_per_address
                    .max(config.max_handshakes_per_address_per_second as usize),
            ),
            cfg: config,
            metrics,
            http,
            active: AtomicUsize::new(0),
            sessions: AtomicUsize::new(0),
            pending: pending::PendingTable::default(),
            per_address: Mutex::new(HashMap::new()),
            record_alerts: limit::RecordAlerts::default(),
        });
        let (shutdown_tx, shutdown_rx) = watch::channel(false);
        let accept_task = tokio::spawn(accept_loop(
            endpoint.clone(),
            Arc::clone(&shared),
            shutdown_rx,
        ));
        shared.http.ready.store(true, Ordering::Release);
        tracing::info!(%local_addr, ?metrics_addr, %fingerprint, "planet-server listening");
        Ok(ServerHandle {
            local_addr,
            metrics_addr,
            fingerprint,
            cert_der,
            shared,
            endpoint,
            shutdown_tx,
            accept_task,
            http_stop,
            http_task,
        })
    }
}

fn transport_config(cfg: &ServerConfig) -> Result<quinn::TransportConfig, ServerError> {
    let mut t = quinn::TransportConfig::default();
    // Before authentication a client may open only the control stream; the
    // tenant's budget (`max_in_flight` + 1 + margin) is granted with the
    // Welcome (`Connection::set_max_concurrent_bi_streams`).
    t.max_concurrent_bidi_streams(VarInt::from_u32(1));
    t.max_concurrent_uni_streams(VarInt::from_u32(0));
    // No QUIC datagrams: the protocol does not use them, and with them
    // enabled quinn advertises `max_datagram_frame_size` and buffers about
    // 1.25 MB of unread datagrams per connection, before authentication.
    t.datagram_receive_buffer_size(None);
    // Clients send 25-byte requests: small receive windows bound the memory
    // a connection can make us buffer.
    t.stream_receive_window(VarInt::from_u32(64 * 1024));
    t.receive_window(VarInt::from_u32(256 * 1024));
    t.send_window(8 * 1024 * 1024);
    // Responses leave in the order they are written, which is the order
    // of the requests, which the client sends most important first: with
    // quinn's default round robin, six records asked at once all finish
    // near the end of the six, and the first one the client needed waits
    // for the others (docs/BENCHMARKS.md "Streaming"). Records are at most
    // tens of kB, so none holds the others back for long.
    t.send_fairness(false);
    let idle = Duration::from_millis(u64::from(cfg.idle_timeout_ms));
    let idle_timeout = quinn::IdleTimeout::try_from(idle).map_err(|_| {
        ConfigError::Invalid(format!(
            "idle_timeout_ms {} is too large",
            cfg.idle_timeout_ms
        ))
    })?;
    t.max_idle_timeout(Some(idle_timeout));
    t.keep_alive_interval(Some((idle / 3).max(Duration::from_millis(500))));
    // ACK frequency (draft-ietf-quic-ack-frequency, which quinn clients
    // support): ask the client to acknowledge every 11th ack-eliciting packet
    // rather than every 2nd, within min(its max_ack_delay, RTT), as quinn
    // caps the requested delay at the RTT (2 ms floor). A 7 kB response is
    // about 6 packets, so this removes most pure-ACK packets that the client
    // builds, encrypts and sends and the server receives, decrypts and
    // processes. Loss recovery is unaffected beyond the PTO accounting for the
    // requested delay; out-of-order packets are still acknowledged at once.
    let mut ack = quinn::AckFrequencyConfig::default();
    ack.ack_eliciting_threshold(VarInt::from_u32(10));
    t.ack_frequency_config(Some(ack));
    // Path-MTU discovery up to the configured ceiling (quinn probes
    // upwards from 1200 bytes and backs off on black holes).
    let mut mtu = quinn::MtuDiscoveryConfig::default();
    mtu.upper_bound(cfg.max_udp_payload);
    t.mtu_discovery_config(Some(mtu));
    // A larger initial congestion window: the Welcome (the database header)
    // goes out in one flight instead of 2–3 slow-start round trips.
    match cfg.congestion {
        Congestion::Cubic => {
            let mut cc = quinn::congestion::CubicConfig::default();
            cc.initial_window(cfg.initial_window);
            t.congestion_controller_factory(Arc::new(cc));
        }
        Congestion::Bbr => {
            let mut cc = quinn::congestion::BbrConfig::default();
            cc.initial_window(cfg.initial_window);
            t.congestion_controller_factory(Arc::new(cc));
        }
    }
    t.initial_rtt(Duration::from_millis(u64::from(cfg.initial_rtt_ms)));
    Ok(t)
}

async fn accept_loop(
    endpoint: quinn::Endpoint,
    shared: Arc<Shared>,
    mut shutdown: watch::Receiver<bool>,
) {
    let mut conns = tokio::task::JoinSet::new();
    loop {
        let incoming = tokio::select! {
            i = endpoint.accept() => i,
            Some(_) = conns.join_next(), if !conns.is_empty() => continue,
            _ = shutdown.wait_for(|s| *s) => break,
        };
        let Some(incoming) = incoming else { break };
        let peer = incoming.remote_address();
        let count = |outcome: &str| {
            shared
                .metrics
                .connections_total
                .with_label_values(&[outcome])
                .inc()
        };
        // Pre-authentication budget, checked before any cryptography:
        // refusing costs one stateless CONNECTION_CLOSE packet.
        // When the budget is full, a newcomer may still take the slot of
        // the oldest pending connection of the address holding the most
        // (`pending.rs`), so a flood from a few addresses cannot lock out
        // everyone else.
        let pending = shared.pending.len();
        if !shared
            .pending
            .would_admit(peer.ip(), shared.cfg.max_pending_handshakes)
        {
            count("refused");
            tracing::debug!(%peer, pending, "too many pending handshakes, refusing");
            incoming.refuse();
            continue;
        }
        // Under load, make clients prove their address (QUIC Retry) before
        // they get any state, so spoofed sources cannot hold slots.
        if pending >= shared.cfg.retry_above_pending
            && !incoming.remote_address_validated()
            && incoming.may_retry()
        {
            count("retry");
            if let Err(e) = incoming.retry() {
                tracing::debug!(%peer, error = %e, "retry failed");
            }
            continue;
        }
        // An address that spent its failed-hello budget is refused before
        // any cryptography: a wrong-token flood costs one stateless packet
        // per attempt, not a TLS handshake (its hellos would be answered
        // `rate_limited` anyway).
        if !shared.failed_hellos.allows(peer.ip()) {
            count("refused");
            tracing::debug!(%peer, "failed-hello budget spent, refusing");
            incoming.refuse();
            continue;
        }
        // New connections per address: beyond the burst, refused before any
        // cryptography, so a handshake flood costs stateless packets.
        if !shared.handshakes.try_spend(peer.ip()) {
            count("refused");
            tracing::debug!(%peer, "handshake rate of this address exceeded, refusing");
            incoming.refuse();
            continue;
        }
        let Some(address) = AddressGuard::try_new(&shared, peer.ip()) else {
            count("refused");
            tracing::debug!(%peer, "per-address connection limit reached, refusing");
            incoming.refuse();
            continue;
        };
        // One deadline for the whole unauthenticated phase, shorter under
        // load: a client that is not flooding completes in a few round
        // trips, while each slot a flooder holds costs it a handshake per
        // deadline.
        let timeout = if pending >= shared.cfg.retry_above_pending {
            shared
                .cfg
                .handshake_timeout_under_load
                .min(shared.cfg.handshake_timeout)
        } else {
            shared.cfg.handshake_timeout
        };
        let deadline = tokio::time::Instant::now() + timeout;
        let Some(pending) = PendingGuard::admit(&shared, peer.ip()) else {
            count("refused");
            tracing::debug!(%peer, "no pending slot, refusing");
            incoming.refuse();
            continue;
        };
        let evicted = pending.eviction();
        let shared = Arc::clone(&shared);
        let shutdown = shutdown.clone();
        conns.spawn(async move {
            let _address = address;
            shared.active.fetch_add(1, Ordering::AcqRel);
            shared.metrics.connections_active.inc();
            let guard = ActiveGuard(Arc::clone(&shared));
            let handshake = handshake(incoming, shared.cfg.zero_rtt);
            let conn = tokio::select! {
                r = tokio::time::timeout_at(deadline, handshake) => match r {
                    Ok(Some(conn)) => conn,
                    Ok(None) => {
                        shared.metrics.handshake(metrics::HandshakeEnd::Lost);
                        return;
                    }
                    Err(_) => {
                        shared.metrics.handshake(metrics::HandshakeEnd::Timeout);
                        tracing::debug!(%peer, "QUIC handshake not done within the handshake timeout");
                        return;
                    }
                },
                _ = evicted.notified() => {
                    // Dropping the handshake abandons it: quinn closes the
                    // connection.
                    shared.metrics.handshake(metrics::HandshakeEnd::Evicted);
                    tracing::debug!(%peer, "pending slot taken by another address, closing");
                    return;
                }
            };
            shared
                .metrics
                .connections_total
                .with_label_values(&["accepted"])
                .inc();
            conn::serve_connection(conn, Arc::clone(&shared), shutdown, deadline, pending).await;
            drop(guard);
        });
    }
    // Draining: refuse new connections, let the open ones finish.
    endpoint.set_server_config(None);
    let grace = shared.cfg.shutdown_grace + Duration::from_secs(3);
    let drained =
        tokio::time::timeout(grace, async { while conns.join_next().await.is_some() {} }).await;
    if drained.is_err() {
        tracing::warn!("connections still open after the grace period: closing them");
        conns.shutdown().await;
    }
}

/// Runs the server side of the handshake. With 0-RTT the connection is
/// handed over at once (0.5-RTT): a resuming client's `Hello` sent as early
/// data is read and answered before the client's handshake `Finished`
/// arrives, and a client without early data is served as soon as its
/// streams arrive after the handshake. Without 0-RTT it waits for the
/// handshake to complete.
async fn handshake(incoming: quinn::Incoming, zero_rtt: bool) -> Option<quinn::Connection> {
    let peer = incoming.remote_address();
    let connecting = match incoming.accept() {
        Ok(c) => c,
        Err(e) => {
            tracing::debug!(%peer, error = %e, "connection refused");
            return None;
        }
    };
    let connecting = if zero_rtt {
        match connecting.into_0rtt() {
            Ok((conn, _always_accepted_on_a_server)) => return Some(conn),
            Err(connecting) => connecting,
        }
    } else {
        connecting
    };
    match connecting.await {
        Ok(c) => Some(c),
        Err(e) => {
            tracing::debug!(%peer, error = %e, "handshake failed");
            None
        }
    }
}

impl ServerHandle {
    /// The bound QUIC (UDP) address.
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The bound HTTP metrics address, if enabled.
    pub fn metrics_addr(&self) -> Option<SocketAddr> {
        self.metrics_addr
    }

    /// Lower-case hex SHA-256 of the server certificate (DER).
    pub fn cert_fingerprint(&self) -> &str {
        &self.fingerprint
    }

    /// DER of the server's end-entity certificate.
    pub fn cert_der(&self) -> &[u8] {
        &self.cert_der
    }

    /// The metrics (e.g. to read counters in tests without HTTP).
    pub fn metrics(&self) -> &Metrics {
        &self.shared.metrics
    }

    /// Number of open connections.
    pub fn active_connections(&self) -> usize {
        self.shared.active.load(Ordering::Acquire)
    }

    /// Re-opens every database path; changed files are mapped for new
    /// sessions (what SIGHUP does).
    pub fn reload(&self) -> Vec<(String, ReloadOutcome)> {
        self.shared.reload()
    }

    /// Graceful shutdown: stop accepting, send `Goodbye{shutting_down}`,
    /// let in-flight responses finish up to the grace period, close
    /// connections with `CONNECTION_CLOSED_SHUTDOWN`, stop the metrics
    /// server. `/readyz` answers 503 from the start of the drain.
    pub async fn shutdown(self) {
        self.shared.http.ready.store(false, Ordering::Release);
        let _ = self.shutdown_tx.send(true);
        let _ = self.accept_task.await;
        self.endpoint.close(
            VarInt::from_u32(quic::CONNECTION_CLOSED_SHUTDOWN),
            b"shutting down",
        );
        let _ = tokio::time::timeout(Duration::from_secs(2), self.endpoint.wait_idle()).await;
        let _ = self.http_stop.send(true);
        if let Some(t) = self.http_task {
            let _ = t.await;
        }
        tracing::info!("planet-server stopped");
    }
}
