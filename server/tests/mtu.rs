//! Path-MTU discovery on loopback: with `max_udp_payload` 16 384 and the
//! client's loopback default, a 12 kB record arrives in one or two datagrams
//! once discovery has finished; with the default 1452 it takes nine or more. Before `planet_server::udp::GsoLimit`, batches of 16 kB datagrams
//! above 64 kB were dropped by the kernel (EMSGSIZE) and never arrived.

mod common;

use std::time::{Duration, Instant};

use common::*;
use planet_server::{Server, ServerConfig};
use planet_session::net::Connection;

/// Datagrams the client received for one fetch of `(off, size)`.
async fn datagrams_for_fetch(conn: &Connection, id: u64, off: u64, size: u32) -> u64 {
    let before = conn.quinn().stats().udp_rx.datagrams;
    let body = conn.fetch(id, off, size).await.expect("fetch");
    assert_eq!(body.len(), size as usize);
    conn.quinn().stats().udp_rx.datagrams - before
}

/// Fetches the largest record until it arrives in at most `want` datagrams
/// or `limit` passes; returns the fewest datagrams seen.
async fn fewest_datagrams(
    cfg: ServerConfig,
    recs: &[(u64, u32)],
    want: u64,
    limit: Duration,
) -> u64 {
    let h = Server::start(cfg).await.expect("server");
    let (conn, _) = connect(&h, acme()).await.expect("connect");
    let (off, size) = recs.iter().copied().max_by_key(|r| r.1).expect("records");
    assert!(size > 12_000, "largest record is {size} bytes");
    let deadline = Instant::now() + limit;
    let mut fewest = u64::MAX;
    let mut id = 1;
    while Instant::now() < deadline {
        fewest = fewest.min(datagrams_for_fetch(&conn, id, off, size).await);
        id += 1;
        if fewest <= want {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    conn.close();
    h.shutdown().await;
    fewest
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn loopback_responses_use_large_datagrams_up_to_the_ceiling() {
    let dir = tempfile::tempdir().unwrap();
    let (mut cfg, _) = two_tenant_config(dir.path());
    let recs = build_db_with(&dir.path().join("earth.planetdb"), 1, 11_000);
    cfg.max_udp_payload = 16_384;
    let n = fewest_datagrams(cfg, &recs, 2, Duration::from_secs(5)).await;
    assert!(n <= 2, "a 12 kB record took {n} datagrams");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn default_ceiling_keeps_datagrams_ethernet_sized() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, _) = two_tenant_config(dir.path());
    let recs = build_db_with(&dir.path().join("earth.planetdb"), 1, 11_000);
    assert_eq!(cfg.max_udp_payload, 1452);
    let n = fewest_datagrams(cfg, &recs, 0, Duration::from_secs(1)).await;
    assert!(
        n >= 9,
        "a 12 kB record took only {n} datagrams at 1452 bytes"
    );
}
