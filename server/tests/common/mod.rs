//! Test helpers: a tiny database, servers on 127.0.0.1:0, raw QUIC clients,
//! metric scraping.
#![allow(dead_code)]

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use planet_core::format::{parse_record, ChildRef, Header};
use planet_protocol::{Hello, Welcome};
use planet_server::{DatabaseConfig, ServerConfig, ServerHandle, TenantConfig, TlsSource};
use planet_session::net::{ConnectOptions, Connection, NetError};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Deterministic, incompressible-ish bytes.
fn noise(seed: u64, n: usize) -> Vec<u8> {
    let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 24) as u8
        })
        .collect()
}

/// Writes a database: per face a root record with 4 leaf children; payload
/// sizes ~1-2 KB. Returns every record's (offset, size).
pub fn build_db(path: &Path, seed: u64) -> Vec<(u64, u32)> {
    build_db_with(path, seed, 0)
}

/// [`build_db`] with `extra` more payload bytes in every leaf record.
pub fn build_db_with(path: &Path, seed: u64, extra: usize) -> Vec<(u64, u32)> {
    planet_testkit::testdb::write_two_level_db(path, 8, &format!("test db seed {seed}"), |f, k| {
        match k {
            Some(k) => noise(
                seed * 1000 + (f * 10 + k) as u64,
                1000 + 97 * k + 13 * f + extra,
            ),
            None => noise(seed * 1000 + 900 + f as u64, 1500),
        }
    })
    .expect("write the test database")
}

/// A config with databases `earth` (and `mars`) and tenants `acme` (earth,
/// token "s3cret") and `other` (mars, token "t0ken").
pub fn two_tenant_config(dir: &Path) -> (ServerConfig, Vec<(u64, u32)>) {
    let earth = dir.join("earth.planetdb");
    let mars = dir.join("mars.planetdb");
    let recs = build_db(&earth, 1);
    build_db(&mars, 2);
    let mut cfg =
        ServerConfig::single_database(&earth, "127.0.0.1:0".parse().unwrap(), "").expect("config");
    cfg.metrics = Some("127.0.0.1:0".parse().unwrap());
    cfg.tls = TlsSource::DevCert;
    cfg.databases = vec![
        DatabaseConfig {
            name: "earth".into(),
            path: earth,
        },
        DatabaseConfig {
            name: "mars".into(),
            path: mars,
        },
    ];
    cfg.tenants = vec![
        TenantConfig {
            max_in_flight: 4,
            ..TenantConfig::new("acme", "s3cret", vec!["earth".into()])
        },
        TenantConfig {
            max_in_flight: 4,
            ..TenantConfig::new("other", "t0ken", vec!["mars".into()])
        },
    ];
    cfg.shutdown_grace = Duration::from_secs(2);
    // Every test client comes from 127.0.0.1: the per-address limits are
    // tested on their own (resources.rs), with clients on 127.0.0.2.
    cfg.max_connections_per_address = 100_000;
    cfg.max_failed_hellos_per_minute = 0;
    cfg.validate().expect("valid");
    (cfg, recs)
}

pub fn acme() -> Hello {
    Hello::new("acme", "s3cret", "earth")
}

pub fn tls_for(h: &ServerHandle) -> Arc<rustls::ClientConfig> {
    planet_session::tls::pinned(h.cert_fingerprint()).expect("pinned tls")
}

pub async fn connect(h: &ServerHandle, hello: Hello) -> Result<(Connection, Welcome), NetError> {
    Connection::connect(h.local_addr(), "localhost", tls_for(h), hello).await
}

pub async fn connect_opts(
    h: &ServerHandle,
    hello: Hello,
    opts: &ConnectOptions,
) -> Result<(Connection, Welcome), NetError> {
    Connection::connect_with(h.local_addr(), "localhost", tls_for(h), hello, opts).await
}

/// A quinn client endpoint bound to `ip` (e.g. 127.0.0.2: Linux routes the
/// whole 127/8 to loopback), trusting the server `h`, with `transport`.
pub fn endpoint_on(
    h: &ServerHandle,
    ip: &str,
    transport: Option<quinn::TransportConfig>,
) -> quinn::Endpoint {
    let mut ep = quinn::Endpoint::client(format!("{ip}:0").parse().unwrap()).unwrap();
    let crypto = quinn::crypto::rustls::QuicClientConfig::try_from(tls_for(h)).unwrap();
    let mut cfg = quinn::ClientConfig::new(Arc::new(crypto));
    if let Some(t) = transport {
        cfg.transport_config(Arc::new(t));
    }
    ep.set_default_client_config(cfg);
    ep
}

/// A raw quinn connection (no protocol handshake).
pub async fn raw_connect(h: &ServerHandle) -> (quinn::Endpoint, quinn::Connection) {
    let mut ep = quinn::Endpoint::client("127.0.0.1:0".parse().unwrap()).unwrap();
    let crypto = quinn::crypto::rustls::QuicClientConfig::try_from(tls_for(h)).unwrap();
    ep.set_default_client_config(quinn::ClientConfig::new(Arc::new(crypto)));
    let conn = ep
        .connect(h.local_addr(), "localhost")
        .unwrap()
        .await
        .expect("raw connect");
    (ep, conn)
}

/// GET over HTTP/1.0; returns (status, body).
pub async fn http_get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut s = tokio::net::TcpStream::connect(addr)
        .await
        .expect("http connect");
    s.write_all(format!("GET {path} HTTP/1.0\r\nHost: x\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).await.unwrap();
    let text = String::from_utf8_lossy(&buf).into_owned();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    (status, body)
}

/// Sum of the samples of `name` whose labels contain all `labels`.
pub fn metric(text: &str, name: &str, labels: &[(&str, &str)]) -> f64 {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .filter(|l| {
            l.starts_with(name) && matches!(l.as_bytes().get(name.len()), Some(b'{') | Some(b' '))
        })
        .filter(|l| {
            labels
                .iter()
                .all(|(k, v)| l.contains(&format!("{k}=\"{v}\"")))
        })
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

pub async fn scrape(h: &ServerHandle) -> String {
    let (status, body) = http_get(h.metrics_addr().expect("metrics"), "/metrics").await;
    assert_eq!(status, 200);
    body
}

/// Polls the metrics until `pred` holds (metrics of a response are counted
/// once the client acknowledged it), or panics after 5 s.
pub async fn wait_metrics(h: &ServerHandle, pred: impl Fn(&str) -> bool) -> String {
    for _ in 0..100 {
        let text = scrape(h).await;
        if pred(&text) {
            return text;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let text = scrape(h).await;
    panic!("metrics condition not met:\n{text}");
}

/// Follows the header's roots and the records' children; returns every
/// (offset, size, bytes) fetched.
pub async fn fetch_tree(conn: &Connection, welcome: &Welcome) -> Vec<(u64, u32, Vec<u8>)> {
    let header = Header::decode(&welcome.header, Some(welcome.file_size)).expect("header");
    let mut queue: Vec<ChildRef> = header.elevation.root_records.to_vec();
    let mut out = Vec::new();
    let mut id = 0;
    while let Some(r) = queue.pop() {
        id += 1;
        let bytes = conn.fetch(id, r.offset, r.size).await.expect("fetch");
        let rec = parse_record(&bytes, Some(welcome.file_size)).expect("valid record");
        queue.extend(rec.header.children.iter().copied());
        out.push((r.offset, r.size, bytes));
    }
    out
}

pub fn file_bytes(p: &PathBuf) -> Vec<u8> {
    std::fs::read(p).unwrap()
}
