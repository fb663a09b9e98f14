//! A second transport (ISSUE #19): the same reconnecting session over
//! HTTP/2 byte-range requests to any HTTPS server that serves the database
//! file (nginx, an object store, a CDN), with no planet-server at all.
//!
//! [`Session::spawn_http`] returns the same [`SessionHandle`] as the QUIC
//! session and emits the same [`NetEvent`]s, so the streaming client, its
//! scheduler, priorities and integrity checks are unchanged:
//!
//! - on (re)connection: `GET` the superblock (`Range: bytes=0-63`), then the
//!   whole header in one request (`bytes=header_offset-(file_len-1)`); a
//!   [`Welcome`] is made from them (the file's name, size and header, and
//!   the default [`Limits`]);
//! - the response's `ETag` (else `Last-Modified`) pins the file version:
//!   every later request carries `If-Match` (`If-Unmodified-Since`), and a
//!   `412 Precondition Failed` — the file was replaced — ends the
//!   connection, so the session reconnects and welcomes the client with the
//!   new header, as the QUIC path does on reload;
//! - each record request is one HTTP/2 stream, `Range: bytes=a-b`; a
//!   response that is not `206` with exactly `size` bytes fails that
//!   request (the client then checks the record's magic, length and CRC
//!   before drawing anything, as for QUIC);
//! - a byte range carries no child tables: [`SessionHandle::request_refs`]
//!   is a plain record request here (the record arrives without a trailer,
//!   docs/PROTOCOL.md §1.1);
//! - cancellation drops the request, which resets its HTTP/2 stream;
//! - a lost connection fails what is in flight with a connection error and
//!   reconnects with the same capped, jittered backoff.
//!
//! HTTP/2 (ALPN `h2`) is preferred. A server that offers only HTTP/1.1 gets
//! a pool of [`HTTP1_CONNECTIONS`] keep-alive connections, one request on
//! each at a time (HTTP/1.1 has no multiplexing); a cancelled request
//! closes its connection (HTTP/1.1 cannot abandon a response), and the next
//! request on that slot opens a new one.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::Bytes;
use http_body_util::{BodyExt, Empty};
use hyper::client::conn::http2::SendRequest;
use hyper::header::{
    HeaderValue, CONTENT_RANGE, ETAG, IF_MATCH, IF_UNMODIFIED_SINCE, LAST_MODIFIED, RANGE,
};
use hyper::{Request, StatusCode, Uri};
use planet_core::format::{Superblock, SUPERBLOCK_LEN};
use planet_protocol::{ErrorCode, ErrorMsg, Limits, Welcome, PROTOCOL_VERSION};
use tokio::sync::mpsc;

use crate::net::{
    jittered, serve_requests, set_status, while_disconnected, Cmd, NetError, NetEvent, Session,
    SessionHandle, Status,
};

/// Connections to a server that speaks only HTTP/1.1 (browsers open 6).
pub const HTTP1_CONNECTIONS: usize = 8;

/// Configuration of an HTTP [`Session`] ([`Session::spawn_http`]).
#[derive(Debug, Clone)]
pub struct HttpSessionConfig {
    /// `https://host[:port]/path/to/file.planetdb`.
    pub url: Uri,
    /// TLS configuration ([`crate::tls::https_config`]); its ALPN list is
    /// replaced by `h2`.
    pub tls: Arc<rustls::ClientConfig>,
    /// First reconnect delay.
    pub backoff_initial: Duration,
    /// Largest reconnect delay.
    pub backoff_max: Duration,
    /// Longest wait for the TCP and TLS handshakes and the header.
    pub connect_timeout: Duration,
}

impl HttpSessionConfig {
    /// [`HttpSessionConfig::new`] from a URL string.
    pub fn from_url(
        url: &str,
        tls: Arc<rustls::ClientConfig>,
    ) -> Result<HttpSessionConfig, HttpError> {
        let uri: Uri = url.parse().map_err(|_| HttpError::Url(url.to_string()))?;
        if uri.scheme_str() != Some("https") || uri.host().is_none() {
            return Err(HttpError::Url(url.to_string()));
        }
        Ok(HttpSessionConfig::new(uri, tls))
    }

    /// Defaults: backoff 100 ms doubling up to 5 s with jitter, 10 s
    /// connect timeout.
    pub fn new(url: Uri, tls: Arc<rustls::ClientConfig>) -> HttpSessionConfig {
        HttpSessionConfig {
            url,
            tls,
            backoff_initial: Duration::from_millis(100),
            backoff_max: Duration::from_secs(5),
            connect_timeout: Duration::from_secs(10),
        }
    }
}

/// Why an HTTP connection could not be set up (the source of
/// [`NetError::Connect`]).
#[derive(Debug, thiserror::Error)]
pub enum HttpError {
    /// The URL is not `https://host[:port]/path`.
    #[error("not an https URL with a host: {0}")]
    Url(String),
    /// Name resolution, TCP or TLS failed.
    #[error("cannot reach {host}:{port}: {source}")]
    Io {
        /// Host.
        host: String,
        /// Port.
        port: u16,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The HTTP handshake or a request failed.
    #[error("HTTP: {0}")]
    Http(#[source] hyper::Error),
    /// The server answered the superblock or header request wrongly.
    #[error("{what}: HTTP {status}")]
    Status {
        /// Which request.
        what: &'static str,
        /// Its status.
        status: u16,
    },
    /// The superblock or header does not decode.
    #[error("bad database file")]
    Format(#[source] planet_core::format::FormatError),
    /// The HTTP/1.1 connection pool was closed under a request.
    #[error("the HTTP/1.1 connection pool is closed")]
    PoolClosed,
}

/// Opens connections to the URL's server: TCP, then TLS with ALPN.
struct Dialer {
    host: String,
    port: u16,
    name: rustls::pki_types::ServerName<'static>,
    tls: tokio_rustls::TlsConnector,
}

type Tls = tokio_rustls::client::TlsStream<tokio::net::TcpStream>;
type Http1 = hyper::client::conn::http1::SendRequest<Empty<Bytes>>;

impl Dialer {
    async fn dial(&self) -> Result<Tls, HttpError> {
        let io_err = |source| HttpError::Io {
            host: self.host.clone(),
            port: self.port,
            source,
        };
        let tcp = tokio::net::TcpStream::connect((self.host.as_str(), self.port))
            .await
            .map_err(io_err)?;
        let _ = tcp.set_nodelay(true);
        self.tls
            .connect(self.name.clone(), tcp)
            .await
            .map_err(io_err)
    }

    /// An HTTP/1.1 connection over `stream` (its driver spawned).
    async fn http1(stream: Tls) -> Result<Http1, HttpError> {
        let (send, driver) =
            hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(stream))
                .await
                .map_err(HttpError::Http)?;
        tokio::spawn(async move {
            if let Err(e) = driver.await {
                tracing::debug!(error = %e, "HTTP/1.1 connection ended");
            }
        });
        Ok(send)
    }
}

/// A server that speaks only HTTP/1.1: [`HTTP1_CONNECTIONS`] slots, each
/// an idle connection, none yet, or one request in flight.
struct Http1Pool {
    dialer: Dialer,
    slots: Vec<tokio::sync::Mutex<Option<Http1>>>,
    free: tokio::sync::Semaphore,
    /// Kept so that the connection's `closed` never fires (a lost HTTP/1.1
    /// connection is redialled per request).
    _closed: tokio::sync::watch::Sender<bool>,
}

#[derive(Clone)]
enum Sender {
    H2(SendRequest<Empty<Bytes>>),
    H1(Arc<Http1Pool>),
}

/// One connection's state: the HTTP sender and the pinned file version.
#[derive(Clone)]
struct Conn {
    send: Sender,
    /// Becomes true when the HTTP/2 connection's driver ends.
    closed: tokio::sync::watch::Receiver<bool>,
    uri: Uri,
    /// `(header, value)` sent with every range request.
    pin: Option<(hyper::header::HeaderName, HeaderValue)>,
}

impl Conn {
    async fn get(
        &self,
        first: u64,
        last: u64,
    ) -> Result<(StatusCode, hyper::HeaderMap, Bytes), HttpError> {
        let mut b = match &self.send {
            // HTTP/2 takes `:authority` from the absolute URI (a Host header
            // as well makes nginx answer 400).
            Sender::H2(_) => Request::get(self.uri.clone()),
            // HTTP/1.1: the origin form and a Host header.
            Sender::H1(_) => {
                let path = self.uri.path_and_query().map_or("/", |p| p.as_str());
                let host = self.uri.authority().map_or("", |a| a.as_str());
                Request::get(path).header(hyper::header::HOST, host)
            }
        };
        b = b.header(RANGE, format!("bytes={first}-{last}"));
        if let Some((k, v)) = &self.pin {
            b = b.header(k, v);
        }
        // Building from valid parts cannot fail.
        let req = b.body(Empty::new()).unwrap_or_default();
        match &self.send {
            Sender::H2(send) => {
                let resp = send
                    .clone()
                    .send_request(req)
                    .await
                    .map_err(HttpError::Http)?;
                let (parts, body) = resp.into_parts();
                let bytes = body.collect().await.map_err(HttpError::Http)?.to_bytes();
                Ok((parts.status, parts.headers, bytes))
            }
            Sender::H1(pool) => pool.request(req).await,
        }
    }

    /// One record: `Ok` only for `206` with exactly `size` bytes.
    async fn fetch(&self, offset: u64, size: u32) -> Result<Vec<u8>, NetError> {
        if size == 0 {
            return Err(NetError::Server(ErrorMsg::new(
                ErrorCode::WrongSize,
                "empty range",
            )));
        }
        let last = offset + u64::from(size) - 1;
        let (status, _, body) = self.get(offset, last).await.map_err(lost)?;
        match status {
            StatusCode::PARTIAL_CONTENT if body.len() == size as usize => Ok(body.to_vec()),
            StatusCode::PARTIAL_CONTENT => Err(NetError::Server(ErrorMsg::new(
                ErrorCode::WrongSize,
                format!("HTTP 206 with {} bytes for a {size}-byte range", body.len()),
            ))),
            StatusCode::PRECONDITION_FAILED => Err(NetError::ConnectionLost {
                code: None,
                reason: "the file was replaced (HTTP 412): reconnecting".into(),
            }),
            StatusCode::RANGE_NOT_SATISFIABLE => Err(NetError::Server(ErrorMsg::new(
                ErrorCode::OutOfRange,
                "HTTP 416",
            ))),
            s => Err(NetError::Server(ErrorMsg::new(
                if s.is_server_error() {
                    ErrorCode::Internal
                } else {
                    ErrorCode::Malformed
                },
                format!("HTTP {} for a range request", s.as_u16()),
            ))),
        }
    }
}

impl Http1Pool {
    /// Sends `req` on a free slot's connection (opening one if the slot has
    /// none or its connection closed) and reads the whole response. The
    /// connection goes back to its slot only once the body is read: a
    /// request dropped before (cancelled) takes its connection with it.
    async fn request(
        &self,
        req: Request<Empty<Bytes>>,
    ) -> Result<(StatusCode, hyper::HeaderMap, Bytes), HttpError> {
        let _permit = self
            .free
            .acquire()
            .await
            .map_err(|_| HttpError::PoolClosed)?;
        // With a permit, some slot is free.
        let mut slot = None;
        for s in &self.slots {
            if let Ok(g) = s.try_lock() {
                slot = Some(g);
                break;
            }
        }
        let Some(mut slot) = slot else {
            // Unreachable while permits equal slots; fail the request
            // rather than panic.
            return Err(HttpError::PoolClosed);
        };
        let mut send = match slot.take() {
            Some(s) if !s.is_closed() => s,
            _ => Dialer::http1(self.dialer.dial().await?).await?,
        };
        send.ready().await.map_err(HttpError::Http)?;
        let resp = send.send_request(req).await.map_err(HttpError::Http)?;
        let (parts, body) = resp.into_parts();
        let bytes = body.collect().await.map_err(HttpError::Http)?.to_bytes();
        *slot = Some(send);
        Ok((parts.status, parts.headers, bytes))
    }
}

fn lost(e: HttpError) -> NetError {
    NetError::ConnectionLost {
        code: None,
        reason: format!("HTTP: {e}"),
    }
}

/// TCP + TLS (ALPN h2, http/1.1) + the HTTP handshake, then the superblock
/// and the header. Returns the connection and the welcome made from them.
async fn connect(cfg: &HttpSessionConfig) -> Result<(Conn, Welcome), HttpError> {
    let url = &cfg.url;
    if url.scheme_str() != Some("https") {
        return Err(HttpError::Url(url.to_string()));
    }
    let host = url
        .host()
        .ok_or_else(|| HttpError::Url(url.to_string()))?
        .trim_start_matches('[')
        .trim_end_matches(']')
        .to_string();
    let port = url.port_u16().unwrap_or(443);
    let mut tls = (*cfg.tls).clone();
    tls.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
    let name = rustls::pki_types::ServerName::try_from(host.clone())
        .map_err(|_| HttpError::Url(url.to_string()))?;
    let dialer = Dialer {
        host,
        port,
        name,
        tls: tokio_rustls::TlsConnector::from(Arc::new(tls)),
    };
    let stream = dialer.dial().await?;
    let (closed_tx, closed) = tokio::sync::watch::channel(false);
    let send = if stream.get_ref().1.alpn_protocol() == Some(b"h2") {
        let io = hyper_util::rt::TokioIo::new(stream);
        let (send, driver) =
            hyper::client::conn::http2::handshake(hyper_util::rt::TokioExecutor::new(), io)
                .await
                .map_err(HttpError::Http)?;
        tokio::spawn(async move {
            if let Err(e) = driver.await {
                tracing::debug!(error = %e, "HTTP/2 connection ended");
            }
            let _ = closed_tx.send(true);
        });
        Sender::H2(send)
    } else {
        // No HTTP/2 offered: a pool of HTTP/1.1 connections, this one first.
        tracing::info!(url = %cfg.url, "no HTTP/2: {HTTP1_CONNECTIONS} HTTP/1.1 connections");
        let first = Dialer::http1(stream).await?;
        let mut slots = vec![tokio::sync::Mutex::new(Some(first))];
        slots.extend((1..HTTP1_CONNECTIONS).map(|_| tokio::sync::Mutex::new(None)));
        Sender::H1(Arc::new(Http1Pool {
            dialer,
            slots,
            free: tokio::sync::Semaphore::new(HTTP1_CONNECTIONS),
            _closed: closed_tx,
        }))
    };
    let mut conn = Conn {
        send,
        closed,
        uri: url.clone(),
        pin: None,
    };
    // The superblock, and the version of the file it pins.
    let (status, headers, sb) = conn.get(0, SUPERBLOCK_LEN as u64 - 1).await?;
    if status != StatusCode::PARTIAL_CONTENT {
        return Err(HttpError::Status {
            what: "superblock (bytes=0-63; does the server support ranges?)",
            status: status.as_u16(),
        });
    }
    let superblock = Superblock::decode(&sb).map_err(HttpError::Format)?;
    conn.pin = if let Some(etag) = headers.get(ETAG) {
        Some((IF_MATCH, etag.clone()))
    } else {
        headers
            .get(LAST_MODIFIED)
            .map(|lm| (IF_UNMODIFIED_SINCE, lm.clone()))
    };
    // The file's size from Content-Range ("bytes 0-63/SIZE") must match.
    let total = headers
        .get(CONTENT_RANGE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.rsplit('/').next())
        .and_then(|v| v.parse::<u64>().ok());
    if let Some(total) = total.filter(|&t| t != superblock.file_len) {
        return Err(HttpError::Format(
            planet_core::format::FormatError::Length {
                what: "file (superblock file_len against the HTTP Content-Range size)",
                stored: superblock.file_len,
                got: total,
            },
        ));
    }
    let first = superblock.header_offset;
    let last = first + u64::from(superblock.header_len).max(1) - 1;
    let (status, _, header) = conn.get(first, last).await?;
    if status != StatusCode::PARTIAL_CONTENT || header.len() != superblock.header_len as usize {
        return Err(HttpError::Status {
            what: "header",
            status: status.as_u16(),
        });
    }
    let database = url
        .path()
        .rsplit('/')
        .next()
        .unwrap_or_default()
        .trim_end_matches(".planetdb")
        .to_string();
    let welcome = Welcome {
        version: PROTOCOL_VERSION,
        database,
        file_size: superblock.file_len,
        header: header.to_vec(),
        limits: Limits::default(),
    };
    Ok((conn, welcome))
}

impl Session {
    /// Starts an HTTP/2 session on `runtime` (module docs): the same
    /// handle, events and reconnection as [`Session::spawn`].
    pub fn spawn_http(runtime: &tokio::runtime::Handle, cfg: HttpSessionConfig) -> SessionHandle {
        SessionHandle::spawn_with(runtime, |cmd_rx, ev, status| {
            run_http(cfg, cmd_rx, ev, status)
        })
    }
}

async fn run_http(
    cfg: HttpSessionConfig,
    mut cmd_rx: mpsc::UnboundedReceiver<Cmd>,
    ev: crossbeam_channel::Sender<NetEvent>,
    status: Arc<Mutex<Status>>,
) {
    let mut backoff = cfg.backoff_initial;
    loop {
        let connect = tokio::time::timeout(cfg.connect_timeout, connect(&cfg));
        let Some(result) = while_disconnected(connect, &mut cmd_rx, &ev).await else {
            return;
        };
        match result {
            Ok(Ok((conn, welcome))) => {
                backoff = cfg.backoff_initial;
                set_status(&status, |s| {
                    s.connected = true;
                    s.welcome = Some(welcome.clone());
                });
                let _ = ev.send(NetEvent::Connected(welcome));
                let mut closed = conn.closed.clone();
                let c = conn.clone();
                let user_closed = serve_requests(
                    &mut cmd_rx,
                    &ev,
                    // The kind is ignored: a byte range is the record
                    // alone, so `request_refs` (and `request_refs_above`)
                    // is `request` on this transport. So is the priority:
                    // the requests go in the order they are made.
                    move |_id, offset, size, _kind, _priority| {
                        let c = c.clone();
                        async move { c.fetch(offset, size).await }
                    },
                    async move {
                        let _ = closed.wait_for(|c| *c).await;
                        NetError::ConnectionLost {
                            code: None,
                            reason: "HTTP/2 connection closed".into(),
                        }
                    },
                )
                .await;
                set_status(&status, |s| s.connected = false);
                if user_closed {
                    return;
                }
                let _ = ev.send(NetEvent::Disconnected);
            }
            Ok(Err(e)) => {
                tracing::debug!(error = %e, url = %cfg.url, "HTTP connect failed");
                set_status(&status, |s| s.last_error = Some(NetError::connect(e)));
            }
            Err(_) => set_status(&status, |s| s.last_error = Some(NetError::Timeout)),
        }
        let sleep = tokio::time::sleep(jittered(backoff));
        backoff = (backoff * 2).min(cfg.backoff_max);
        if while_disconnected(sleep, &mut cmd_rx, &ev).await.is_none() {
            return;
        }
    }
}
