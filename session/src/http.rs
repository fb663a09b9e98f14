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
//! - cancellation drops the request, which resets its HTTP/2 stream;
//! - a lost connection fails what is in flight with a connection error and
//!   reconnects with the same capped, jittered backoff.
//!
//! Only HTTP/2 (ALPN `h2`) is spoken: without multiplexing, HTTP/1.1 would
//! need a pool of connections to keep requests in flight (not built yet).

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
    /// The server did not agree to HTTP/2.
    #[error("the server does not speak HTTP/2 (ALPN h2)")]
    NoHttp2,
    /// The HTTP/2 handshake or a request failed.
    #[error("HTTP/2")]
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
}

/// One connection's state: the HTTP/2 sender and the pinned file version.
#[derive(Clone)]
struct Conn {
    send: SendRequest<Empty<Bytes>>,
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
    ) -> Result<(StatusCode, hyper::HeaderMap, Bytes), hyper::Error> {
        // HTTP/2 takes `:authority` from the absolute URI (a Host header as
        // well makes nginx answer 400).
        let mut b = Request::get(self.uri.clone()).header(RANGE, format!("bytes={first}-{last}"));
        if let Some((k, v)) = &self.pin {
            b = b.header(k, v);
        }
        // Building from valid parts cannot fail.
        let req = b.body(Empty::new()).unwrap_or_default();
        let mut send = self.send.clone();
        let resp = send.send_request(req).await?;
        let (parts, body) = resp.into_parts();
        let bytes = body.collect().await?.to_bytes();
        Ok((parts.status, parts.headers, bytes))
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

fn lost(e: hyper::Error) -> NetError {
    NetError::ConnectionLost {
        code: None,
        reason: format!("HTTP/2: {e}"),
    }
}

/// TCP + TLS (ALPN h2) + HTTP/2 handshake, then the superblock and the
/// header. Returns the connection and the welcome made from them.
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
    let io_err = |source| HttpError::Io {
        host: host.clone(),
        port,
        source,
    };
    let tcp = tokio::net::TcpStream::connect((host.as_str(), port))
        .await
        .map_err(io_err)?;
    let _ = tcp.set_nodelay(true);
    let mut tls = (*cfg.tls).clone();
    tls.alpn_protocols = vec![b"h2".to_vec()];
    let name = rustls::pki_types::ServerName::try_from(host.clone())
        .map_err(|_| HttpError::Url(url.to_string()))?;
    let stream = tokio_rustls::TlsConnector::from(Arc::new(tls))
        .connect(name, tcp)
        .await
        .map_err(io_err)?;
    if stream.get_ref().1.alpn_protocol() != Some(b"h2") {
        return Err(HttpError::NoHttp2);
    }
    let io = hyper_util::rt::TokioIo::new(stream);
    let (send, driver) =
        hyper::client::conn::http2::handshake(hyper_util::rt::TokioExecutor::new(), io)
            .await
            .map_err(HttpError::Http)?;
    let (closed_tx, closed) = tokio::sync::watch::channel(false);
    tokio::spawn(async move {
        if let Err(e) = driver.await {
            tracing::debug!(error = %e, "HTTP/2 connection ended");
        }
        let _ = closed_tx.send(true);
    });
    let mut conn = Conn {
        send,
        closed,
        uri: url.clone(),
        pin: None,
    };
    // The superblock, and the version of the file it pins.
    let (status, headers, sb) = conn
        .get(0, SUPERBLOCK_LEN as u64 - 1)
        .await
        .map_err(HttpError::Http)?;
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
    let (status, _, header) = conn.get(first, last).await.map_err(HttpError::Http)?;
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
                    move |_id, offset, size| {
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
