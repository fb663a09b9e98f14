//! End-to-end over the second transport (ISSUE #19): the streaming client
//! fetches the database as HTTP/2 byte ranges from a real nginx over TLS,
//! with no planet-server.

mod common;

use common::*;
use planet_client::tree::Samples;
use planet_linksim::{LinkConfig, TcpLink};
use planet_session::http::HttpSessionConfig;
use planet_session::streaming::StreamingClient;
use planet_testkit::harness::{build_procedural_db, runtime};
use planet_testkit::nginx::{Nginx, NGINX_BIN};
use std::path::Path;
use std::time::{Duration, Instant};

/// nginx serving `file`, or `None` (skipped, failing in CI) without nginx.
fn nginx(file: &Path) -> Option<Nginx> {
    if !Path::new(NGINX_BIN).exists() {
        planet_testkit::skip_or_fail(&format!("{NGINX_BIN} not installed"));
        return None;
    }
    Some(Nginx::start(Path::new(NGINX_BIN), file, 1).expect("nginx"))
}

fn connect_http(rt: &tokio::runtime::Runtime, ng: &Nginx) -> StreamingClient {
    let trust = planet_session::tls::ServerTrust::Certificates(vec![ng.cert_der.clone()]);
    let tls = planet_session::tls::https_config(&trust).expect("tls");
    let cfg = HttpSessionConfig::from_url(&ng.url(), tls).expect("url");
    StreamingClient::connect_http(rt.handle(), cfg, client_cfg(), Duration::from_secs(10))
        .expect("welcome over HTTP/2")
}

#[test]
fn static_camera_converges_to_exact_samples_over_http2() {
    let rt = runtime(2).expect("runtime");
    let Some(ng) = nginx(small_db()) else { return };
    let mut sc = connect_http(&rt, &ng);
    let camera = static_camera();
    let out = converge(&mut sc, &camera, Duration::from_secs(30), |_, _| {});
    assert_exact(&sc, &out);
    assert!(sc.bytes_received() > 0);
    sc.close();
}

#[test]
fn a_replaced_file_restarts_the_session_with_the_new_header() {
    let rt = runtime(2).expect("runtime");
    let dir = tempfile::tempdir().expect("tempdir");
    let first = dir.path().join("first.planetdb");
    let second = dir.path().join("second.planetdb");
    build_procedural_db(&first, 2, 1).expect("first");
    build_procedural_db(&second, 2, 2).expect("second");
    let Some(ng) = nginx(&first) else { return };
    let mut sc = connect_http(&rt, &ng);
    let before = sc.header().clone();
    let camera = static_camera();
    let _ = converge(&mut sc, &camera, Duration::from_secs(30), |_, _| {});
    let connects = sc.counters().connects;
    // Publish the second file under the same URL, as a deploy would
    // (rename over the served name).
    let tmp = ng.served_path().with_extension("new");
    std::os::unix::fs::symlink(&second, &tmp).expect("link");
    std::fs::rename(&tmp, ng.served_path()).expect("rename");
    // A new view needs new records: their requests carry the old ETag and
    // get 412, the session reconnects and welcomes the new header.
    let moved = cam(27.95, 86.93, 60_000.0, 0.0, -25.0);
    let start = Instant::now();
    while sc.header() == &before {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "still on the old header: counters {:?}",
            sc.counters()
        );
        std::thread::sleep(Duration::from_millis(10));
        let _ = sc.frame(&moved, 0.01);
    }
    assert!(sc.counters().connects > connects);
    let out = converge(&mut sc, &moved, Duration::from_secs(30), |_, _| {});
    assert!(!out.draw.is_empty());
    sc.client.tree().validate().expect("tree invariants");
    sc.close();
}

#[test]
fn a_corrupt_record_is_detected_and_never_drawn() {
    let rt = runtime(2).expect("runtime");
    let Some(ng) = nginx(small_db()) else { return };
    // The record of the parent of the finest block the static view draws:
    // a block's record holds its LOD 0 and its children's LOD 1.
    let mut sc = connect_http(&rt, &ng);
    let camera = static_camera();
    let out = converge(&mut sc, &camera, Duration::from_secs(30), |_, _| {});
    let et = sc.client.tree().elevation();
    let victim = out
        .draw
        .iter()
        .map(|d| d.block)
        .filter(|b| b.level >= 2)
        .max_by_key(|b| b.level)
        .and_then(|b| b.parent())
        .expect("a block drawn two levels below the roots");
    let parent = victim.parent().expect("parent");
    let refs = et
        .get(&parent)
        .and_then(|n| n.child_refs.clone())
        .expect("parent's child references");
    let i = parent
        .children()
        .iter()
        .position(|c| *c == victim)
        .expect("a child of its parent");
    let r = refs[i];
    sc.close();
    drop(ng);

    // The same file with one byte of that record flipped, behind nginx:
    // it serves the bytes as they are, so only the client's checks stand
    // between them and the screen.
    let dir = tempfile::tempdir().expect("tempdir");
    let bad = dir.path().join("corrupt.planetdb");
    let mut bytes = std::fs::read(small_db()).expect("read");
    let at = (r.offset + u64::from(r.size) / 2) as usize;
    bytes[at] ^= 0x5a;
    std::fs::write(&bad, &bytes).expect("write");
    let Some(ng) = nginx(&bad) else { return };
    let mut sc = connect_http(&rt, &ng);
    let truth = truth();
    let side = sc.client.tree().elevation().width + 1;
    let start = Instant::now();
    let mut frames = 0;
    while start.elapsed() < Duration::from_secs(4) {
        std::thread::sleep(Duration::from_millis(10));
        let out = sc.frame(&camera, 0.01);
        frames += 1;
        let et = sc.client.tree().elevation();
        for d in &out.draw {
            assert!(
                !(d.block == victim && d.lod == 0) && d.block.parent() != Some(victim),
                "{:?} at LOD {} drawn from the corrupt record of {victim:?}",
                d.block,
                d.lod
            );
            let Some(Samples::Elevation(grid)) = et.get(&d.block).and_then(|n| n.samples.as_ref())
            else {
                continue;
            };
            assert_drawn_samples_exact(d, grid, truth, side);
        }
    }
    let err = sc.client.last_error().unwrap_or_default().to_string();
    eprintln!(
        "{frames} frames; last rejection: {err}; counters {:?}",
        sc.counters()
    );
    assert!(
        err.contains("checksum"),
        "the corrupt record was not rejected: {err:?}"
    );
    sc.close();
}

#[test]
fn converges_from_nginx_through_a_lossy_shaped_tcp_link() {
    // Kernel TCP through the TUN link: nginx in its own network namespace,
    // every IP packet between it and the client through the same shaper
    // as the QUIC relay (10 Mbit/s, 20 ms each way, 2 % loss).
    let rt = runtime(2).expect("runtime");
    if !Path::new(NGINX_BIN).exists() {
        planet_testkit::skip_or_fail(&format!("{NGINX_BIN} not installed"));
        return;
    }
    let cfg: LinkConfig = "10mbit,20ms,2%loss".parse().expect("link");
    let link = match rt.block_on(TcpLink::start(cfg.clone().with_seed(1), cfg.with_seed(2))) {
        Ok(l) => l,
        Err(e) => {
            planet_testkit::skip_or_fail(&format!(
                "no TUN link (needs root, /dev/net/tun, ip netns): {e}"
            ));
            return;
        }
    };
    // The namespace's TCP congestion control is its own: CUBIC (Linux's
    // default) for nginx here, whatever the host runs, which stays as it
    // was; a name the kernel does not offer is an error.
    let host_cc = "/proc/sys/net/ipv4/tcp_congestion_control";
    let host = std::fs::read_to_string(host_cc).expect("host congestion control");
    link.set_tcp_congestion("cubic")
        .expect("cubic in the namespace");
    assert_eq!(link.tcp_congestion().expect("read back"), "cubic");
    assert!(link.set_tcp_congestion("no-such-control").is_err());
    assert_eq!(std::fs::read_to_string(host_cc).expect("host"), host);
    let ng = Nginx::start_in_namespace(
        Path::new(NGINX_BIN),
        small_db(),
        1,
        link.namespace(),
        link.server_ip(),
    )
    .expect("nginx in the namespace");
    let start = Instant::now();
    let mut sc = connect_http(&rt, &ng);
    let camera = static_camera();
    let out = converge(&mut sc, &camera, Duration::from_secs(60), |_, _| {});
    assert_exact(&sc, &out);
    // nginx's connection to the client runs CUBIC (`ss` inside the
    // namespace, while the HTTP/2 connection is still open).
    let ss = link
        .command("ss")
        .args(["-tin", "state", "established"])
        .output()
        .expect("ss");
    let ss = String::from_utf8_lossy(&ss.stdout);
    assert!(
        ss.contains(" cubic ") && !ss.contains(" bbr "),
        "nginx's connections: {ss}"
    );
    let stats = link.stats();
    eprintln!(
        "converged in {:?} through the TCP link: {stats:?}, counters {:?}",
        start.elapsed(),
        sc.counters()
    );
    assert!(stats.packets_down > 0 && stats.packets_up > 0);
    assert!(
        stats.bytes_down >= sc.bytes_received(),
        "the records crossed the link"
    );
    assert!(
        stats.dropped_loss > 0,
        "2 % loss dropped nothing: {stats:?}"
    );
    sc.close();
    drop(ng);
}

#[test]
fn converges_from_a_server_without_http2() {
    // ALPN offers http/1.1 only: the session falls back to a pool of
    // HTTP/1.1 connections and still converges to the exact samples.
    let rt = runtime(2).expect("runtime");
    if !Path::new(NGINX_BIN).exists() {
        planet_testkit::skip_or_fail(&format!("{NGINX_BIN} not installed"));
        return;
    }
    let ng = Nginx::start_http1_only(Path::new(NGINX_BIN), small_db()).expect("nginx");
    let mut sc = connect_http(&rt, &ng);
    let out = converge(
        &mut sc,
        &static_camera(),
        Duration::from_secs(30),
        |_, _| {},
    );
    assert_exact(&sc, &out);
    sc.close();
}
