//! Prometheus metrics (names and labels exactly as in
//! `deploy/metrics-contract.txt`) and the small HTTP server for `/metrics`,
//! `/healthz` and `/readyz`.
//!
//! HTTP stack: hyper 1 + hyper-util, not axum. Three fixed GET routes need no
//! router, extractors or tower middleware; hyper is already the HTTP engine
//! under axum, so this is the smaller dependency set for the same code.

use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use bytes::Bytes;
use http_body_util::Full;
use hyper::body::Incoming;
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::rt::TokioIo;
use prometheus::{
    exponential_buckets, Encoder, HistogramOpts, HistogramVec, IntCounterVec, IntGauge,
    IntGaugeVec, Opts, Registry, TextEncoder,
};
use tokio::net::TcpListener;
use tokio::sync::watch;

/// Outcome label values of `planet_requests_total`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RequestOutcome {
    /// Record sent.
    Ok,
    /// The request failed validation.
    Invalid,
    /// No established session (request before hello).
    Unauthorized,
    /// The client stopped the stream.
    Cancelled,
    /// Refused by the tenant's bandwidth limit.
    RateLimited,
    /// The record failed its checksum.
    Corrupt,
    /// Server-side failure or shutdown.
    Error,
    /// The request was not received within the request-read deadline, or
    /// its response could not be written within the write deadline.
    Timeout,
    /// The database file could not be read (truncated, I/O error).
    Storage,
}

/// Label values of `planet_connections_total{outcome}`: accepted (QUIC
/// handshake done), rejected at `max_connections` (its hello refused with
/// `server_busy`), refused by the pending-handshake or per-address budget
/// (before any cryptography), asked to validate its address (Retry).
pub const CONNECTION_OUTCOMES: [&str; 4] = ["accepted", "rejected", "refused", "retry"];

/// How an unauthenticated connection's handshake ended: the `outcome` of
/// `planet_handshakes_total`. Every connection that passes the accept
/// limits ends its pre-authentication phase with exactly one of these
/// (connections refused at `max_connections` are counted in
/// `planet_connections_total{outcome="rejected"}` instead).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HandshakeEnd {
    /// Welcome written: the session is established.
    Ok,
    /// Refused with this error code (unauthorized, forbidden, ...).
    Refused(planet_protocol::ErrorCode),
    /// The handshake deadline passed (QUIC handshake, control stream,
    /// Hello, or writing the Welcome or error reply).
    Timeout,
    /// The peer went away before an outcome.
    Lost,
    /// The pre-authentication budget was full and a newcomer from an
    /// address holding fewer pending connections took this one's slot.
    Evicted,
}

impl HandshakeEnd {
    /// Every label value, for pre-registration and the contract.
    pub const LABELS: [&'static str; 11] = [
        "ok",
        "unauthorized",
        "forbidden",
        "unknown_database",
        "unsupported_version",
        "malformed",
        "rate_limited",
        "busy",
        "timeout",
        "lost",
        "evicted",
    ];

    /// The label value.
    pub fn as_str(self) -> &'static str {
        use planet_protocol::ErrorCode as C;
        match self {
            HandshakeEnd::Ok => "ok",
            HandshakeEnd::Timeout => "timeout",
            HandshakeEnd::Lost => "lost",
            HandshakeEnd::Evicted => "evicted",
            HandshakeEnd::Refused(code) => match code {
                C::Unauthorized => "unauthorized",
                C::Forbidden => "forbidden",
                C::UnknownDatabase => "unknown_database",
                C::UnsupportedVersion => "unsupported_version",
                C::RateLimited => "rate_limited",
                C::ServerBusy => "busy",
                C::Timeout => "timeout",
                _ => "malformed",
            },
        }
    }
}

impl RequestOutcome {
    /// Every outcome.
    pub const ALL: [RequestOutcome; 9] = [
        RequestOutcome::Ok,
        RequestOutcome::Invalid,
        RequestOutcome::Unauthorized,
        RequestOutcome::Cancelled,
        RequestOutcome::RateLimited,
        RequestOutcome::Corrupt,
        RequestOutcome::Error,
        RequestOutcome::Timeout,
        RequestOutcome::Storage,
    ];

    /// The label value.
    pub fn as_str(self) -> &'static str {
        match self {
            RequestOutcome::Ok => "ok",
            RequestOutcome::Invalid => "invalid",
            RequestOutcome::Unauthorized => "unauthorized",
            RequestOutcome::Cancelled => "cancelled",
            RequestOutcome::RateLimited => "rate_limited",
            RequestOutcome::Corrupt => "corrupt",
            RequestOutcome::Error => "error",
            RequestOutcome::Timeout => "timeout",
            RequestOutcome::Storage => "storage",
        }
    }

    /// The outcome for an error code replied in a response head.
    pub fn for_code(code: planet_protocol::ErrorCode) -> RequestOutcome {
        use planet_protocol::ErrorCode as C;
        match code {
            C::HelloRequired | C::Unauthorized | C::Forbidden => RequestOutcome::Unauthorized,
            C::RateLimited => RequestOutcome::RateLimited,
            C::CorruptRecord => RequestOutcome::Corrupt,
            C::Cancelled => RequestOutcome::Cancelled,
            C::Internal | C::ShuttingDown | C::ServerBusy => RequestOutcome::Error,
            C::Timeout => RequestOutcome::Timeout,
            C::Storage => RequestOutcome::Storage,
            _ => RequestOutcome::Invalid,
        }
    }
}

/// All server metrics, in their own registry (several servers may run in one
/// process, e.g. in tests).
#[derive(Clone)]
pub struct Metrics {
    /// The registry `/metrics` encodes.
    pub registry: Registry,
    /// `planet_connections_active`.
    pub connections_active: IntGauge,
    /// `planet_connections_total{outcome}`.
    pub connections_total: IntCounterVec,
    /// `planet_handshakes_total{outcome}`.
    pub handshakes_total: IntCounterVec,
    /// `planet_handshakes_pending`.
    pub handshakes_pending: IntGauge,
    /// `planet_storage_errors_total{database}`.
    pub storage_errors_total: IntCounterVec,
    /// `planet_corrupt_records_total{database}`.
    pub corrupt_records_total: IntCounterVec,
    /// `planet_requests_total{tenant,database,outcome}`.
    pub requests_total: IntCounterVec,
    /// `planet_bytes_sent_total{tenant,database}`.
    pub bytes_sent_total: IntCounterVec,
    /// `planet_request_duration_seconds{database}`.
    pub request_duration: HistogramVec,
    /// `planet_record_size_bytes{database}`.
    pub record_size: HistogramVec,
    /// `planet_requests_in_flight`.
    pub requests_in_flight: IntGauge,
    /// `planet_database_reloads_total{database}`.
    pub database_reloads_total: IntCounterVec,
    /// `planet_database_size_bytes{database}`.
    pub database_size_bytes: IntGaugeVec,
    /// `planet_build_info{version}`.
    pub build_info: IntGaugeVec,
}

impl Metrics {
    /// Creates and registers every metric (plus the process collector).
    pub fn new() -> Result<Metrics, prometheus::Error> {
        let registry = Registry::new();
        let connections_active = IntGauge::new(
            "planet_connections_active",
            "QUIC connections currently open",
        )?;
        let connections_total = IntCounterVec::new(
            Opts::new(
                "planet_connections_total",
                "Incoming connections by outcome: accepted (QUIC handshake done), rejected (hello refused at max_connections), refused (pending-handshake or per-address budget, before any cryptography), retry (asked to validate its address)",
            ),
            &["outcome"],
        )?;
        let handshakes_total = IntCounterVec::new(
            Opts::new(
                "planet_handshakes_total",
                "How unauthenticated connections ended, by outcome",
            ),
            &["outcome"],
        )?;
        let handshakes_pending = IntGauge::new(
            "planet_handshakes_pending",
            "Connections not yet authenticated (max_pending_handshakes)",
        )?;
        let storage_errors_total = IntCounterVec::new(
            Opts::new(
                "planet_storage_errors_total",
                "Requests that failed because the database file could not be read",
            ),
            &["database"],
        )?;
        let corrupt_records_total = IntCounterVec::new(
            Opts::new(
                "planet_corrupt_records_total",
                "Distinct records found failing their checksum (each counted once per process)",
            ),
            &["database"],
        )?;
        let requests_total = IntCounterVec::new(
            Opts::new("planet_requests_total", "Record requests by outcome"),
            &["tenant", "database", "outcome"],
        )?;
        let bytes_sent_total = IntCounterVec::new(
            Opts::new("planet_bytes_sent_total", "Record bytes sent"),
            &["tenant", "database"],
        )?;
        let request_duration = HistogramVec::new(
            HistogramOpts::new(
                "planet_request_duration_seconds",
                "Time from reading a request to its last response byte handed to QUIC",
            )
            .buckets(exponential_buckets(0.0005, 2.5, 12)?),
            &["database"],
        )?;
        let record_size = HistogramVec::new(
            HistogramOpts::new("planet_record_size_bytes", "Size of records sent")
                .buckets(exponential_buckets(256.0, 4.0, 9)?),
            &["database"],
        )?;
        let requests_in_flight = IntGauge::new(
            "planet_requests_in_flight",
            "Requests being validated, paced or sent",
        )?;
        let database_reloads_total = IntCounterVec::new(
            Opts::new(
                "planet_database_reloads_total",
                "Times a replaced database file was mapped for new sessions",
            ),
            &["database"],
        )?;
        let database_size_bytes = IntGaugeVec::new(
            Opts::new(
                "planet_database_size_bytes",
                "Size of the database file new sessions get",
            ),
            &["database"],
        )?;
        let build_info = IntGaugeVec::new(
            Opts::new("planet_build_info", "Build information (value 1)"),
            &["version"],
        )?;
        registry.register(Box::new(connections_active.clone()))?;
        registry.register(Box::new(connections_total.clone()))?;
        registry.register(Box::new(handshakes_total.clone()))?;
        registry.register(Box::new(handshakes_pending.clone()))?;
        registry.register(Box::new(storage_errors_total.clone()))?;
        registry.register(Box::new(corrupt_records_total.clone()))?;
        registry.register(Box::new(requests_total.clone()))?;
        registry.register(Box::new(bytes_sent_total.clone()))?;
        registry.register(Box::new(request_duration.clone()))?;
        registry.register(Box::new(record_size.clone()))?;
        registry.register(Box::new(requests_in_flight.clone()))?;
        registry.register(Box::new(database_reloads_total.clone()))?;
        registry.register(Box::new(database_size_bytes.clone()))?;
        registry.register(Box::new(build_info.clone()))?;
        #[cfg(target_os = "linux")]
        registry.register(Box::new(
            prometheus::process_collector::ProcessCollector::for_self(),
        ))?;
        build_info
            .with_label_values(&[env!("CARGO_PKG_VERSION")])
            .set(1);
        for outcome in CONNECTION_OUTCOMES {
            connections_total.with_label_values(&[outcome]);
        }
        for outcome in HandshakeEnd::LABELS {
            handshakes_total.with_label_values(&[outcome]);
        }
        Ok(Metrics {
            registry,
            connections_active,
            connections_total,
            handshakes_total,
            handshakes_pending,
            storage_errors_total,
            corrupt_records_total,
            requests_total,
            bytes_sent_total,
            request_duration,
            record_size,
            requests_in_flight,
            database_reloads_total,
            database_size_bytes,
            build_info,
        })
    }

    /// Pre-creates the per-database series so they show up as 0.
    pub fn init_database(&self, db: &str, size: u64) {
        self.database_reloads_total.with_label_values(&[db]);
        self.storage_errors_total.with_label_values(&[db]);
        self.corrupt_records_total.with_label_values(&[db]);
        self.request_duration.with_label_values(&[db]);
        self.record_size.with_label_values(&[db]);
        self.database_size_bytes
            .with_label_values(&[db])
            .set(i64::try_from(size).unwrap_or(i64::MAX));
    }

    /// Pre-creates a tenant's series (every request outcome, bytes sent) for
    /// each database it may open, so they show up as 0: a counter first
    /// exported at 1 hides that first event from `rate()` and `increase()`
    /// (e.g. the first corrupt record from `PlanetDatabaseCorruptRecords`),
    /// and the dashboard's ratios would show no data instead of 0.
    pub fn init_tenant(&self, tenant: &str, databases: &[String]) {
        for db in databases {
            for outcome in RequestOutcome::ALL {
                self.requests_total
                    .with_label_values(&[tenant, db, outcome.as_str()]);
            }
            self.bytes_sent_total.with_label_values(&[tenant, db]);
        }
    }

    /// Counts how one unauthenticated connection ended.
    pub fn handshake(&self, end: HandshakeEnd) {
        self.handshakes_total
            .with_label_values(&[end.as_str()])
            .inc();
    }

    /// Counts one finished request.
    pub fn request(&self, tenant: &str, database: &str, outcome: RequestOutcome) {
        self.requests_total
            .with_label_values(&[tenant, database, outcome.as_str()])
            .inc();
    }

    /// The text exposition of every metric.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        let families = self.registry.gather();
        if let Err(e) = TextEncoder::new().encode(&families, &mut out) {
            tracing::warn!(error = %e, "cannot encode metrics");
        }
        out
    }
}

/// State the HTTP endpoints report.
pub struct HttpState {
    /// Metrics to encode.
    pub metrics: Metrics,
    /// True once databases are mapped and the QUIC endpoint accepts.
    pub ready: AtomicBool,
}

fn respond(status: StatusCode, content_type: &str, body: Vec<u8>) -> Response<Full<Bytes>> {
    let mut resp = Response::new(Full::new(Bytes::from(body)));
    *resp.status_mut() = status;
    if let Ok(v) = hyper::header::HeaderValue::from_str(content_type) {
        resp.headers_mut().insert(hyper::header::CONTENT_TYPE, v);
    }
    resp
}

async fn route(
    state: Arc<HttpState>,
    req: Request<Incoming>,
) -> Result<Response<Full<Bytes>>, Infallible> {
    let text = "text/plain; charset=utf-8";
    if req.method() != Method::GET && req.method() != Method::HEAD {
        return Ok(respond(
            StatusCode::METHOD_NOT_ALLOWED,
            text,
            b"method not allowed\n".to_vec(),
        ));
    }
    Ok(match req.uri().path() {
        "/metrics" => respond(
            StatusCode::OK,
            "text/plain; version=0.0.4; charset=utf-8",
            state.metrics.encode(),
        ),
        "/healthz" => respond(StatusCode::OK, text, b"ok\n".to_vec()),
        "/readyz" => {
            if state.ready.load(Ordering::Acquire) {
                respond(StatusCode::OK, text, b"ready\n".to_vec())
            } else {
                respond(
                    StatusCode::SERVICE_UNAVAILABLE,
                    text,
                    b"not ready\n".to_vec(),
                )
            }
        }
        _ => respond(StatusCode::NOT_FOUND, text, b"not found\n".to_vec()),
    })
}

/// Serves HTTP on `listener` until `stop` turns true.
pub async fn serve_http(
    listener: TcpListener,
    state: Arc<HttpState>,
    mut stop: watch::Receiver<bool>,
) {
    loop {
        let accepted = tokio::select! {
            r = listener.accept() => r,
            _ = stop.changed() => return,
        };
        let (tcp, peer): (_, SocketAddr) = match accepted {
            Ok(a) => a,
            Err(e) => {
                tracing::warn!(error = %e, "metrics accept failed");
                tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                continue;
            }
        };
        let state = Arc::clone(&state);
        tokio::spawn(async move {
            let svc = hyper::service::service_fn(move |req| route(Arc::clone(&state), req));
            let conn = hyper::server::conn::http1::Builder::new()
                .timer(hyper_util::rt::TokioTimer::new())
                .header_read_timeout(std::time::Duration::from_secs(5))
                .serve_connection(TokioIo::new(tcp), svc);
            if let Err(e) = conn.await {
                tracing::debug!(%peer, error = %e, "metrics connection error");
            }
        });
    }
}
