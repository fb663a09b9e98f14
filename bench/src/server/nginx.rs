//! The nginx peer: HTTPS byte ranges of the same file over HTTP/1.1 and
//! HTTP/2.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, Context, Result};

use super::*;

/// nginx serving the database at `/db` (the same server as the HTTP
/// transport's tests: `planet_testkit::nginx`).
pub use planet_testkit::nginx::Nginx;

/// Starts `bin` serving `db` at `https://localhost:PORT/db`.
pub fn start_nginx(bin: &Path, db: &Path, workers: usize) -> Result<Nginx> {
    Nginx::start_as(bin, db, "db", workers).context("cannot start nginx")
}

/// nginx's pids (master and workers).
fn nginx_pids(ng: &Nginx) -> Vec<u32> {
    process_tree(ng.pid())
}

pub(crate) fn https_client_config(
    cert_der: &[u8],
    alpn: &[u8],
) -> Result<Arc<rustls::ClientConfig>> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut roots = rustls::RootCertStore::empty();
    roots.add(rustls::pki_types::CertificateDer::from(cert_der.to_vec()))?;
    let mut cfg = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .with_root_certificates(roots)
        .with_no_client_auth();
    cfg.alpn_protocols = vec![alpn.to_vec()];
    Ok(Arc::new(cfg))
}

pub(crate) type TlsStream = tokio_rustls::client::TlsStream<tokio::net::TcpStream>;

pub(crate) async fn tls_connect(
    addr: SocketAddr,
    tls: &tokio_rustls::TlsConnector,
) -> Result<TlsStream> {
    let tcp = tokio::net::TcpStream::connect(addr).await?;
    tcp.set_nodelay(true)?;
    let name = rustls::pki_types::ServerName::try_from("localhost")?;
    Ok(tls.connect(name, tcp).await?)
}

pub(crate) fn range_request(
    uri: &str,
    r: Req,
) -> Result<hyper::Request<http_body_util::Empty<bytes::Bytes>>> {
    // HTTP/2 takes the authority from the absolute URI (a Host header as
    // well makes nginx answer 400); HTTP/1.1 needs the Host header.
    let mut b = hyper::Request::get(uri);
    if uri.starts_with('/') {
        b = b.header(hyper::header::HOST, "localhost");
    }
    Ok(b.header(
        hyper::header::RANGE,
        format!("bytes={}-{}", r.offset, r.offset + r.size as u64 - 1),
    )
    .body(http_body_util::Empty::new())?)
}

pub(crate) async fn check_response(
    resp: hyper::Response<hyper::body::Incoming>,
    r: Req,
) -> Result<u64, String> {
    use http_body_util::BodyExt;
    let status = resp.status();
    let body = resp
        .into_body()
        .collect()
        .await
        .map_err(|e| e.to_string())?
        .to_bytes();
    if status != hyper::StatusCode::PARTIAL_CONTENT {
        return Err(format!("HTTP {status}"));
    }
    if body.len() != r.size as usize {
        return Err(format!("body {} bytes, expected {}", body.len(), r.size));
    }
    Ok(body.len() as u64)
}

pub(crate) async fn run_nginx(
    ng: &Nginx,
    list: &Arc<Vec<Req>>,
    args: &ServerArgs,
    h2: bool,
    scheds: &Schedules,
) -> Result<Vec<RunResult>> {
    let alpn: &[u8] = if h2 { b"h2" } else { b"http/1.1" };
    let tls = tokio_rustls::TlsConnector::from(https_client_config(&ng.cert_der, alpn)?);
    let conc = args.concurrency.max(1);
    let n_conns = if h2 {
        args.clients
    } else {
        args.clients * conc
    };
    let sem = Arc::new(tokio::sync::Semaphore::new(64));
    // Connect phase (not timed).
    let mut set = tokio::task::JoinSet::new();
    for _ in 0..n_conns {
        let tls = tls.clone();
        let addr = ng.addr;
        let sem = sem.clone();
        set.spawn(async move {
            let _p = sem.acquire_owned().await;
            let io = hyper_util::rt::TokioIo::new(tls_connect(addr, &tls).await?);
            if h2 {
                let (send, conn) =
                    hyper::client::conn::http2::handshake(hyper_util::rt::TokioExecutor::new(), io)
                        .await?;
                tokio::spawn(conn);
                Ok::<_, anyhow::Error>(Sender::H2(send))
            } else {
                let (send, conn) = hyper::client::conn::http1::handshake(io).await?;
                tokio::spawn(conn);
                Ok(Sender::H1(send))
            }
        });
    }
    let mut senders = vec![];
    while let Some(r) = set.join_next().await {
        senders.push(r??);
    }
    let pids = nginx_pids(ng);
    let label = if h2 { "nginx h2" } else { "nginx h1" };
    if !scheds.is_empty() {
        let uri: Arc<str> = if h2 {
            format!("https://localhost:{}/db", ng.addr.port()).into()
        } else {
            "/db".into()
        };
        let mut slots = vec![];
        let mut senders = senders.into_iter();
        for _ in 0..args.clients {
            let slot = if h2 {
                match senders.next() {
                    Some(Sender::H2(h)) => Slot::H2(h),
                    _ => bail!("missing HTTP/2 connection"),
                }
            } else {
                let mut pool = vec![];
                for _ in 0..conc {
                    match senders.next() {
                        Some(Sender::H1(h)) => pool.push(h),
                        _ => bail!("missing HTTP/1.1 connection"),
                    }
                }
                Slot::H1(tokio::sync::Mutex::new(pool))
            };
            slots.push(ClientSlot {
                sem: tokio::sync::Semaphore::new(conc),
                slot,
            });
        }
        let slots = Arc::new(slots);
        let mut out = vec![];
        out.extend(warm_up(label, &slots, list, scheds, &uri, &pids, n_conns).await?);
        for (rate, sched) in &scheds.runs {
            out.push(
                open_loop(
                    label,
                    slots.clone(),
                    list,
                    sched.clone(),
                    *rate,
                    uri.clone(),
                    &pids,
                    n_conns,
                )
                .await?,
            );
        }
        return Ok(out);
    }
    let uri: Arc<str> = if h2 {
        format!("https://localhost:{}/db", ng.addr.port()).into()
    } else {
        "/db".into()
    };
    let mut loops: Vec<Sender> = vec![];
    for s in senders {
        match s {
            Sender::H2(h) => loops.extend((0..conc).map(|_| Sender::H2(h.clone()))),
            other => loops.push(other),
        }
    }
    Ok(vec![
        closed_loop(label, loops, uri, list, args, &pids, n_conns).await?,
    ])
}
