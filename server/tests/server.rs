//! End-to-end tests of planet-server with the client transport
//! (`planet_session::net`) and raw QUIC streams.

mod common;

use std::time::Duration;

use common::*;
use planet_protocol::{
    ErrorCode, FrameDecoder, Hello, LodRequest, Message, Response, ResponseDecoder,
};
use planet_server::{ReloadOutcome, Server, ServerConfig};
use planet_session::net::{ConnectOptions, NetError, NetEvent, Session, SessionConfig};

fn server_code(r: Result<Vec<u8>, NetError>) -> ErrorCode {
    match r {
        Err(NetError::Server(e)) => e.code,
        other => panic!("expected a server error head, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fetches_whole_tree_and_counts_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, recs) = two_tenant_config(dir.path());
    let file = file_bytes(&dir.path().join("earth.planetdb"));
    let h = Server::start(cfg).await.unwrap();
    assert_eq!(h.cert_fingerprint().len(), 64);
    assert_eq!(
        planet_session::tls::sha256_hex(h.cert_der()),
        h.cert_fingerprint()
    );

    let (status, _) = http_get(h.metrics_addr().unwrap(), "/healthz").await;
    assert_eq!(status, 200);
    let (status, _) = http_get(h.metrics_addr().unwrap(), "/readyz").await;
    assert_eq!(status, 200);

    let (conn, welcome) = connect(&h, acme()).await.unwrap();
    assert_eq!(welcome.database, "earth");
    assert_eq!(welcome.file_size, file.len() as u64);
    assert_eq!(welcome.limits.max_in_flight, 4);
    let fetched = fetch_tree(&conn, &welcome).await;
    assert_eq!(fetched.len(), recs.len());
    let mut total = 0u64;
    for (off, size, bytes) in &fetched {
        assert_eq!(
            &file[*off as usize..*off as usize + *size as usize],
            &bytes[..]
        );
        total += u64::from(*size);
    }
    let n = fetched.len() as f64;
    let text = wait_metrics(&h, |t| {
        metric(t, "planet_requests_total", &[("outcome", "ok")]) >= n
    })
    .await;
    assert_eq!(
        metric(&text, "planet_requests_total", &[("outcome", "ok")]),
        n
    );
    assert_eq!(
        metric(
            &text,
            "planet_requests_total",
            &[("tenant", "acme"), ("database", "earth")]
        ),
        n
    );
    assert_eq!(metric(&text, "planet_bytes_sent_total", &[]), total as f64);
    assert_eq!(
        metric(&text, "planet_handshakes_total", &[("outcome", "ok")]),
        1.0
    );
    assert_eq!(
        metric(
            &text,
            "planet_connections_total",
            &[("outcome", "accepted")]
        ),
        1.0
    );
    assert_eq!(metric(&text, "planet_connections_active", &[]), 1.0);
    assert_eq!(metric(&text, "planet_record_size_bytes_count", &[]), n);
    assert_eq!(
        metric(&text, "planet_request_duration_seconds_count", &[]),
        n
    );
    assert_eq!(
        metric(
            &text,
            "planet_database_size_bytes",
            &[("database", "earth")]
        ),
        file.len() as f64
    );
    assert_eq!(metric(&text, "planet_build_info", &[]), 1.0);
    for name in [
        "planet_requests_in_flight",
        "planet_database_reloads_total",
        "process_cpu_seconds_total",
        "process_resident_memory_bytes",
        "process_open_fds",
    ] {
        assert!(text.contains(name), "{name} missing from /metrics");
    }
    conn.close();
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_can_share_one_client_endpoint() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, recs) = two_tenant_config(dir.path());
    let file = file_bytes(&dir.path().join("earth.planetdb"));
    let h = Server::start(cfg).await.unwrap();
    let ep = planet_session::net::new_endpoint(h.local_addr()).unwrap();
    let mut conns = vec![];
    for _ in 0..3 {
        let (c, w) = planet_session::net::Connection::connect_on(
            &ep,
            h.local_addr(),
            "localhost",
            tls_for(&h),
            acme(),
            &ConnectOptions::default(),
        )
        .await
        .unwrap();
        assert_eq!(w.database, "earth");
        conns.push(c);
    }
    assert_eq!(h.active_connections(), 3);
    for (i, c) in conns.iter().enumerate() {
        let (off, size) = recs[i % recs.len()];
        let body = c.fetch(1, off, size).await.unwrap();
        assert_eq!(&body[..], &file[off as usize..off as usize + size as usize]);
    }
    // Closing one connection leaves the others (and the endpoint) usable.
    conns.remove(0).close();
    let (off, size) = recs[0];
    assert_eq!(
        conns[1].fetch(2, off, size).await.unwrap().len(),
        size as usize
    );
    drop(ep);
    assert_eq!(
        conns[0].fetch(3, off, size).await.unwrap().len(),
        size as usize
    );
    for c in &conns {
        c.close();
    }
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_get_their_codes_and_the_connection_stays_usable() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, recs) = two_tenant_config(dir.path());
    let h = Server::start(cfg).await.unwrap();
    let (conn, welcome) = connect(&h, acme()).await.unwrap();
    let (good, good_welcome) = connect(&h, acme()).await.unwrap();
    let good_task = tokio::spawn(async move {
        let mut n = 0;
        for _ in 0..3 {
            n += fetch_tree(&good, &good_welcome).await.len();
        }
        good.close();
        n
    });
    let (off, size) = recs[0];
    let file_size = welcome.file_size;
    let cases: Vec<(u64, u32, ErrorCode)> = vec![
        (file_size + 10, 100, ErrorCode::OutOfRange),
        (file_size - 10, 100, ErrorCode::OutOfRange),
        (0, 64, ErrorCode::OutOfRange),
        // Inside the header: past the record area.
        (file_size - 200, 100, ErrorCode::OutOfRange),
        (off + 7, size, ErrorCode::NotARecord),
        (off + 100, 200, ErrorCode::NotARecord),
        (off, size - 1, ErrorCode::WrongSize),
        (off, size + 1, ErrorCode::WrongSize),
        (off, 0, ErrorCode::WrongSize),
        (off, 17 * 1024 * 1024, ErrorCode::RecordTooLarge),
    ];
    for (i, (o, s, code)) in cases.iter().enumerate() {
        let got = server_code(conn.fetch(100 + i as u64, *o, *s).await);
        assert_eq!(got, *code, "case {i}: offset {o} size {s}");
        // Still usable.
        let ok = conn.fetch(1, off, size).await.unwrap();
        assert_eq!(ok.len(), size as usize);
    }
    assert_eq!(good_task.await.unwrap(), 3 * recs.len());
    let text = wait_metrics(&h, |t| {
        metric(t, "planet_requests_total", &[("outcome", "invalid")]) >= cases.len() as f64
    })
    .await;
    assert_eq!(
        metric(&text, "planet_requests_total", &[("outcome", "invalid")]),
        cases.len() as f64
    );
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn handshake_rejections() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, _) = two_tenant_config(dir.path());
    let h = Server::start(cfg).await.unwrap();
    let cases = [
        (
            Hello::new("acme", "wrong", "earth"),
            ErrorCode::Unauthorized,
        ),
        (
            Hello::new("nobody", "s3cret", "earth"),
            ErrorCode::Unauthorized,
        ),
        (Hello::new("acme", "s3cret", "mars"), ErrorCode::Forbidden),
        (
            Hello::new("acme", "s3cret", "venus"),
            ErrorCode::UnknownDatabase,
        ),
        (
            Hello {
                version: 99,
                ..acme()
            },
            ErrorCode::UnsupportedVersion,
        ),
    ];
    for (hello, code) in cases {
        match connect(&h, hello.clone()).await {
            Err(NetError::Rejected(e)) => assert_eq!(e.code, code, "{hello:?}"),
            other => panic!("{hello:?}: expected rejection, got {other:?}"),
        }
    }
    // The other tenant reads its own database.
    let (conn, welcome) = connect(&h, Hello::new("other", "t0ken", "mars"))
        .await
        .unwrap();
    assert_eq!(fetch_tree(&conn, &welcome).await.len(), 30);
    let text = scrape(&h).await;
    assert_eq!(
        metric(
            &text,
            "planet_handshakes_total",
            &[("outcome", "unauthorized")]
        ),
        2.0
    );
    assert_eq!(
        metric(
            &text,
            "planet_handshakes_total",
            &[("outcome", "forbidden")]
        ),
        1.0
    );
    assert_eq!(
        metric(
            &text,
            "planet_handshakes_total",
            &[("outcome", "unknown_database")]
        ),
        1.0
    );
    assert_eq!(
        metric(
            &text,
            "planet_handshakes_total",
            &[("outcome", "unsupported_version")]
        ),
        1.0
    );
    h.shutdown().await;
}

async fn read_all(recv: &mut quinn::RecvStream) -> Vec<u8> {
    recv.read_to_end(1 << 20).await.expect("read response")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn request_before_hello_and_malformed_control_stream() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, recs) = two_tenant_config(dir.path());
    let h = Server::start(cfg).await.unwrap();
    let (good, good_welcome) = connect(&h, acme()).await.unwrap();
    let req = LodRequest {
        id: 9,
        offset: recs[0].0,
        size: recs[0].1,
    };

    // 1. Before the hello completes, a client has the stream budget of the
    //    hello only: a second stream cannot be opened (QUIC stream limit 1),
    //    so no request is read before authentication.
    {
        let (_ep, conn) = raw_connect(&h).await;
        let (mut ctrl_send, _ctrl_recv) = conn.open_bi().await.unwrap();
        let hello = acme().encode_frame().unwrap();
        ctrl_send.write_all(&hello[..3]).await.unwrap();
        tokio::time::sleep(Duration::from_millis(100)).await;
        let second = tokio::time::timeout(Duration::from_millis(300), conn.open_bi()).await;
        assert!(
            second.is_err(),
            "a request stream was granted before the hello"
        );
        // Completing the hello then grants the tenant's streams.
        ctrl_send.write_all(&hello[3..]).await.unwrap();
        tokio::time::sleep(Duration::from_millis(100)).await;
        let (mut send, mut recv) = conn.open_bi().await.unwrap();
        send.write_all(&req.encode_frame().unwrap()).await.unwrap();
        send.finish().unwrap();
        let mut dec = ResponseDecoder::new(req);
        dec.push(&read_all(&mut recv).await).unwrap();
        assert!(matches!(dec.finish().unwrap(), Response::Record { .. }));
    }

    // 2. Control-stream violations are fatal with their code.
    let bad_frames: Vec<(Vec<u8>, ErrorCode)> = vec![
        (req.encode_frame().unwrap(), ErrorCode::HelloRequired),
        (vec![2, 0, 0, 0, 0x7f, 0], ErrorCode::UnknownMessage),
        (vec![0xff, 0xff, 0xff, 0x7f, 0x01], ErrorCode::FrameTooLarge),
        (vec![3, 0, 0, 0, 0x01, 1, 2], ErrorCode::Malformed),
    ];
    for (bytes, code) in bad_frames {
        let (_ep, conn) = raw_connect(&h).await;
        let (mut send, mut recv) = conn.open_bi().await.unwrap();
        send.write_all(&bytes).await.unwrap();
        let reply = recv.read_to_end(1 << 16).await.unwrap_or_default();
        let mut dec = FrameDecoder::new();
        dec.push(&reply);
        match dec.next_frame() {
            Ok(Some(Message::Error(e))) => assert_eq!(e.code, code, "{bytes:?}"),
            other => panic!("{bytes:?}: expected an Error frame, got {other:?}"),
        }
        let closed = conn.closed().await;
        match closed {
            quinn::ConnectionError::ApplicationClosed(c) => {
                assert_eq!(c.error_code.into_inner(), u64::from(code.to_quic()))
            }
            other => panic!("{other:?}"),
        }
    }

    // 3. After the hello: an unknown message type on the control stream.
    {
        let (_ep, conn) = raw_connect(&h).await;
        let (mut send, mut recv) = conn.open_bi().await.unwrap();
        send.write_all(&acme().encode_frame().unwrap())
            .await
            .unwrap();
        send.write_all(&[2, 0, 0, 0, 0x42, 0]).await.unwrap();
        let reply = recv.read_to_end(1 << 20).await.unwrap_or_default();
        let mut dec = FrameDecoder::new();
        dec.push(&reply);
        assert!(matches!(dec.next_frame(), Ok(Some(Message::Welcome(_)))));
        match dec.next_frame() {
            Ok(Some(Message::Error(e))) => assert_eq!(e.code, ErrorCode::UnknownMessage),
            other => panic!("{other:?}"),
        }
    }

    // A well-behaved client was served throughout.
    assert_eq!(fetch_tree(&good, &good_welcome).await.len(), recs.len());
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn too_many_in_flight() {
    let dir = tempfile::tempdir().unwrap();
    let (mut cfg, recs) = two_tenant_config(dir.path());
    cfg.tenants[0].max_in_flight = 2;
    let h = Server::start(cfg).await.unwrap();
    // A tiny stream receive window: the server cannot finish a response
    // until we read it, so requests stay in flight.
    let mut t = quinn::TransportConfig::default();
    t.stream_receive_window(quinn::VarInt::from_u32(256));
    let opts = ConnectOptions {
        transport: Some(std::sync::Arc::new(t)),
        ..ConnectOptions::default()
    };
    let (conn, _) = connect_opts(&h, acme(), &opts).await.unwrap();
    let q = conn.quinn();
    let mut held = Vec::new();
    for (i, (off, size)) in recs.iter().take(2).enumerate() {
        let req = LodRequest {
            id: i as u64,
            offset: *off,
            size: *size,
        };
        let (mut send, mut recv) = q.open_bi().await.unwrap();
        send.write_all(&req.encode_frame().unwrap()).await.unwrap();
        send.finish().unwrap();
        // Wait for the first response bytes: the request is now in flight.
        let first = recv.read_chunk(16, true).await.unwrap().unwrap();
        let first: Vec<u8> = first.bytes.to_vec();
        held.push((req, recv, first));
    }
    let (off, size) = recs[2];
    let got = server_code(conn.fetch(7, off, size).await);
    assert_eq!(got, ErrorCode::TooManyInFlight);
    // Duplicate id of a request in flight.
    let got = server_code(conn.fetch(0, off, size).await);
    assert_eq!(got, ErrorCode::DuplicateRequest);
    // Drain the held responses: they complete, and the slot frees up.
    for (req, mut recv, first) in held {
        let mut dec = ResponseDecoder::new(req);
        dec.push(&first).unwrap();
        dec.push(&read_all(&mut recv).await).unwrap();
        assert!(matches!(dec.finish().unwrap(), Response::Record { .. }));
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(conn.fetch(8, off, size).await.unwrap().len(), size as usize);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn corrupt_record_is_refused_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let (mut cfg, recs) = two_tenant_config(dir.path());
    let path = dir.path().join("earth.planetdb");
    let mut bytes = file_bytes(&path);
    let (off, size) = recs[3];
    bytes[off as usize + size as usize / 2] ^= 0x40;
    let bad = dir.path().join("bad.planetdb");
    std::fs::write(&bad, &bytes).unwrap();
    cfg.databases[0].path = bad;
    let h = Server::start(cfg).await.unwrap();
    let (conn, _) = connect(&h, acme()).await.unwrap();
    assert_eq!(
        server_code(conn.fetch(1, off, size).await),
        ErrorCode::CorruptRecord
    );
    let (o2, s2) = recs[4];
    assert_eq!(conn.fetch(2, o2, s2).await.unwrap().len(), s2 as usize);
    let text = wait_metrics(&h, |t| {
        metric(t, "planet_requests_total", &[("outcome", "ok")]) >= 1.0
    })
    .await;
    assert_eq!(
        metric(&text, "planet_requests_total", &[("outcome", "corrupt")]),
        1.0
    );
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tenant_and_database_series_exist_at_zero_before_any_request() {
    use planet_server::metrics::RequestOutcome;
    let dir = tempfile::tempdir().unwrap();
    let (cfg, _) = two_tenant_config(dir.path());
    let h = Server::start(cfg).await.unwrap();
    let text = scrape(&h).await;
    let samples = |name: &str, labels: &[(&str, &str)]| -> Vec<String> {
        text.lines()
            .filter(|l| l.starts_with(&format!("{name}{{")))
            .filter(|l| {
                labels
                    .iter()
                    .all(|(k, v)| l.contains(&format!("{k}=\"{v}\"")))
            })
            .map(str::to_string)
            .collect()
    };
    for (tenant, db) in [("acme", "earth"), ("other", "mars")] {
        for o in RequestOutcome::ALL {
            let got = samples(
                "planet_requests_total",
                &[
                    ("tenant", tenant),
                    ("database", db),
                    ("outcome", o.as_str()),
                ],
            );
            assert_eq!(got.len(), 1, "{tenant}/{db}/{}: {got:?}", o.as_str());
            assert!(got[0].ends_with(" 0"), "{}", got[0]);
        }
        let got = samples(
            "planet_bytes_sent_total",
            &[("tenant", tenant), ("database", db)],
        );
        assert_eq!(got.len(), 1, "bytes sent {tenant}/{db}: {got:?}");
        for hist in [
            "planet_request_duration_seconds_count",
            "planet_record_size_bytes_count",
        ] {
            assert_eq!(samples(hist, &[("database", db)]).len(), 1, "{hist} {db}");
        }
    }
    // Only the databases a tenant may open.
    assert!(samples(
        "planet_requests_total",
        &[("tenant", "acme"), ("database", "mars")]
    )
    .is_empty());
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn max_connections_refuses_extra() {
    let dir = tempfile::tempdir().unwrap();
    let (mut cfg, _) = two_tenant_config(dir.path());
    cfg.max_connections = 1;
    let h = Server::start(cfg).await.unwrap();
    let (first, _) = connect(&h, acme()).await.unwrap();
    match connect(&h, acme()).await {
        Err(e) => assert_eq!(e.code(), Some(ErrorCode::ServerBusy), "{e:?}"),
        Ok(_) => panic!("second connection accepted"),
    }
    let text = scrape(&h).await;
    assert_eq!(
        metric(
            &text,
            "planet_connections_total",
            &[("outcome", "rejected")]
        ),
        1.0
    );
    // After the first leaves, a new one gets in.
    first.close();
    drop(first);
    let mut ok = false;
    for _ in 0..50 {
        tokio::time::sleep(Duration::from_millis(50)).await;
        if connect(&h, acme()).await.is_ok() {
            ok = true;
            break;
        }
    }
    assert!(ok, "slot not freed");
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reload_serves_new_file_to_new_sessions_only() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, old_recs) = two_tenant_config(dir.path());
    let path = dir.path().join("earth.planetdb");
    let old_file = file_bytes(&path);
    let h = Server::start(cfg).await.unwrap();
    let (old_conn, old_welcome) = connect(&h, acme()).await.unwrap();

    // Unchanged file: no reload.
    assert!(h
        .reload()
        .iter()
        .all(|(_, o)| *o == ReloadOutcome::Unchanged));
    // Publish a new version by rename (DbWriter writes .tmp then renames).
    let new_recs = build_db(&path, 7);
    let new_file = file_bytes(&path);
    assert_ne!(old_file, new_file);
    let outcome = h.reload();
    assert!(
        outcome.contains(&("earth".to_string(), ReloadOutcome::Reloaded)),
        "{outcome:?}"
    );

    // The old session still reads the old file.
    for (off, size, bytes) in fetch_tree(&old_conn, &old_welcome).await {
        assert_eq!(
            &old_file[off as usize..(off + u64::from(size)) as usize],
            &bytes[..]
        );
    }
    assert_eq!(old_recs.len(), new_recs.len());
    // A new session gets the new one.
    let (new_conn, new_welcome) = connect(&h, acme()).await.unwrap();
    assert_ne!(new_welcome.header, old_welcome.header);
    for (off, size, bytes) in fetch_tree(&new_conn, &new_welcome).await {
        assert_eq!(
            &new_file[off as usize..(off + u64::from(size)) as usize],
            &bytes[..]
        );
    }
    let text = scrape(&h).await;
    assert_eq!(
        metric(
            &text,
            "planet_database_reloads_total",
            &[("database", "earth")]
        ),
        1.0
    );
    // A broken replacement is refused; the previous file stays.
    std::fs::write(dir.path().join("tmp"), b"garbage").unwrap();
    std::fs::rename(dir.path().join("tmp"), &path).unwrap();
    assert!(matches!(h.reload()[0].1, ReloadOutcome::Failed(_)));
    let (c3, w3) = connect(&h, acme()).await.unwrap();
    assert_eq!(w3.header, new_welcome.header);
    drop(c3);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn graceful_shutdown_says_goodbye_and_closes() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, recs) = two_tenant_config(dir.path());
    let h = Server::start(cfg).await.unwrap();
    let (conn, _) = connect(&h, acme()).await.unwrap();
    let (off, size) = recs[0];
    conn.fetch(1, off, size).await.unwrap();
    let watcher = conn.clone();
    let closed = tokio::spawn(async move { watcher.closed().await });
    h.shutdown().await;
    let reason = tokio::time::timeout(Duration::from_secs(5), closed)
        .await
        .expect("closed in time")
        .unwrap();
    assert_eq!(reason.code(), Some(ErrorCode::ShuttingDown), "{reason:?}");
    assert_eq!(conn.goodbye(), Some(ErrorCode::ShuttingDown));
}

#[test]
fn session_reconnects_after_server_restart() {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (cfg, recs) = two_tenant_config(dir.path());
    // Both servers use the same certificate (PEM files), as a restarted
    // server would.
    let ck = planet_server::tls::CertKey::dev_cert().unwrap();
    let cert_pem = dir.path().join("cert.pem");
    let key_pem = dir.path().join("key.pem");
    write_pem(&cert_pem, "CERTIFICATE", ck.leaf_der());
    write_pem(&key_pem, "PRIVATE KEY", ck.key.secret_der());
    let mut cfg: ServerConfig = cfg;
    cfg.tls = planet_server::TlsSource::Pem {
        cert: cert_pem,
        key: key_pem,
    };
    let h = rt.block_on(Server::start(cfg.clone())).unwrap();
    let addr = h.local_addr();
    let tls = tls_for(&h);
    let mut scfg = SessionConfig::new(addr, "localhost", tls, acme());
    scfg.options.connect_timeout = Duration::from_millis(500);
    scfg.backoff_initial = Duration::from_millis(50);
    scfg.backoff_max = Duration::from_millis(400);
    let session = Session::spawn(rt.handle(), scfg);
    let wait_for = |pred: &dyn Fn(&NetEvent) -> bool| -> NetEvent {
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        while std::time::Instant::now() < deadline {
            if let Some(ev) = session.wait_event(Duration::from_millis(100)) {
                if pred(&ev) {
                    return ev;
                }
            }
        }
        panic!("event not received");
    };
    wait_for(&|e| matches!(e, NetEvent::Connected(_)));
    assert!(!session.used_zero_rtt() && !session.zero_rtt_refused());
    let (off, size) = recs[0];
    session.request(1, off, size);
    match wait_for(&|e| matches!(e, NetEvent::Record { .. } | NetEvent::Failed { .. })) {
        NetEvent::Record { id, bytes } => {
            assert_eq!(id, 1);
            assert_eq!(bytes.len(), size as usize);
        }
        other => panic!("{other:?}"),
    }
    // Cancel support: cancelling an id not in flight is a no-op.
    session.cancel(99);

    rt.block_on(h.shutdown());
    wait_for(&|e| matches!(e, NetEvent::Disconnected));
    // Restart on the same port.
    cfg.listen = addr;
    let mut h2 = None;
    for _ in 0..40 {
        match rt.block_on(Server::start(cfg.clone())) {
            Ok(h) => {
                h2 = Some(h);
                break;
            }
            Err(_) => std::thread::sleep(Duration::from_millis(50)),
        }
    }
    let h2 = h2.expect("restart on the same port");
    wait_for(&|e| matches!(e, NetEvent::Connected(_)));
    // The session kept its ticket from the first server and tried 0-RTT;
    // the restarted server does not know the ticket, refused the early data,
    // and the Hello went again after the handshake.
    assert!(
        session.zero_rtt_refused(),
        "0-RTT was not tried and refused"
    );
    assert!(!session.used_zero_rtt());
    session.request(2, off, size);
    match wait_for(&|e| matches!(e, NetEvent::Record { .. } | NetEvent::Failed { .. })) {
        NetEvent::Record { id, .. } => assert_eq!(id, 2),
        other => panic!("{other:?}"),
    }
    session.close();
    rt.block_on(h2.shutdown());
}

fn write_pem(path: &std::path::Path, label: &str, der: &[u8]) {
    // Minimal base64 (standard alphabet, padded).
    const A: &[u8] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut b64 = String::new();
    for chunk in der.chunks(3) {
        let n = (u32::from(chunk[0]) << 16)
            | (u32::from(*chunk.get(1).unwrap_or(&0)) << 8)
            | u32::from(*chunk.get(2).unwrap_or(&0));
        for i in 0..4 {
            if i <= chunk.len() {
                b64.push(A[((n >> (18 - 6 * i)) & 63) as usize] as char);
            } else {
                b64.push('=');
            }
        }
    }
    let mut pem = format!("-----BEGIN {label}-----\n");
    for line in b64.as_bytes().chunks(64) {
        pem.push_str(std::str::from_utf8(line).unwrap());
        pem.push('\n');
    }
    pem.push_str(&format!("-----END {label}-----\n"));
    std::fs::write(path, pem).unwrap();
}

/// A token from `openssl rand -hex 32`.
const STRONG: &str = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08";

#[test]
fn config_errors_are_clear() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("earth.planetdb");
    build_db(&db, 1);
    let base = format!(
        "listen = \"127.0.0.1:0\"\n[[database]]\nname = \"earth\"\npath = \"{}\"\n",
        db.display()
    );
    let ok = format!("{base}[[tenant]]\nname = \"p\"\ntoken = \"x\"\ndatabases = [\"earth\"]\n");
    ServerConfig::from_toml_str(&ok, dir.path()).expect("valid config");
    let unknown_db =
        format!("{base}[[tenant]]\nname = \"p\"\ntoken = \"x\"\ndatabases = [\"mars\"]\n");
    let e = ServerConfig::from_toml_str(&unknown_db, dir.path()).unwrap_err();
    assert!(e.to_string().contains("unknown database \"mars\""), "{e}");
    let dup = format!("{ok}[[tenant]]\nname = \"p\"\ntoken = \"y\"\ndatabases = []\n");
    let e = ServerConfig::from_toml_str(&dup, dir.path()).unwrap_err();
    assert!(e.to_string().contains("duplicate tenant"), "{e}");
    let missing = ok.replace("earth.planetdb", "nope.planetdb");
    let e = ServerConfig::from_toml_str(&missing, dir.path()).unwrap_err();
    assert!(e.to_string().contains("nope.planetdb"), "{e}");
    let typo = format!("{ok}max_conections = 3\n");
    assert!(ServerConfig::from_toml_str(&typo, dir.path()).is_err());
    assert_eq!(
        ServerConfig::from_toml_str(&ok, dir.path())
            .unwrap()
            .max_udp_payload,
        planet_server::config::DEFAULT_MAX_UDP_PAYLOAD
    );
    assert_eq!(planet_server::config::DEFAULT_MAX_UDP_PAYLOAD, 1452);
    let jumbo = format!("max_udp_payload = 8952\n{ok}");
    let c = ServerConfig::from_toml_str(&jumbo, dir.path()).unwrap();
    assert_eq!(c.max_udp_payload, 8952);
    // The congestion controller: BBR unless the file says otherwise.
    let c = ServerConfig::from_toml_str(&ok, dir.path()).unwrap();
    assert_eq!(c.congestion, planet_server::Congestion::Bbr);
    let cubic = format!("congestion = \"cubic\"\n{ok}");
    let c = ServerConfig::from_toml_str(&cubic, dir.path()).unwrap();
    assert_eq!(c.congestion, planet_server::Congestion::Cubic);
    let reno = format!("congestion = \"reno\"\n{ok}");
    let e = ServerConfig::from_toml_str(&reno, dir.path()).unwrap_err();
    assert!(e.to_string().contains("congestion \"reno\""), "{e}");
    let tiny = format!("max_udp_payload = 900\n{ok}");
    let e = ServerConfig::from_toml_str(&tiny, dir.path()).unwrap_err();
    assert!(e.to_string().contains("max_udp_payload 900"), "{e}");
    // The deploy example parses (paths do not exist here, so only syntax;
    // its token file is replaced by one that exists).
    let token_file = dir.path().join("public.token");
    std::fs::write(&token_file, format!("{STRONG}\n")).unwrap();
    let example = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/server.toml"),
    )
    .unwrap()
    .replace("/etc/planet/tokens/public", token_file.to_str().unwrap());
    let e = ServerConfig::from_toml_str(&example, dir.path()).unwrap_err();
    assert!(e.to_string().contains("/data/earth.planetdb"), "{e}");

    // Outside development mode (cert and key given), weak tokens are
    // refused at start; with a generated certificate they are accepted.
    let (cert, key) = (dir.path().join("c.pem"), dir.path().join("k.pem"));
    std::fs::write(&cert, "x").unwrap();
    std::fs::write(&key, "x").unwrap();
    let with_token = |token: &str| {
        format!(
            "cert = \"{}\"\nkey = \"{}\"\n{base}[[tenant]]\nname = \"p\"\ntoken = \"{token}\"\ndatabases = [\"earth\"]\n",
            cert.display(),
            key.display()
        )
    };
    for (token, why) in [
        ("", "empty"),
        ("change-me", "placeholder"),
        ("REPLACE_ME-public-tenant-token", "placeholder"),
        ("s3cret", "6 bytes"),
        ("aaaaaaaaaaaaaaaaaaaaaaaa", "entropy"),
    ] {
        let e = ServerConfig::from_toml_str(&with_token(token), dir.path()).unwrap_err();
        assert!(e.to_string().contains(why), "{token:?}: {e}");
        assert!(!e.to_string().contains(token) || token.is_empty() || why == "placeholder");
    }
    let cfg = ServerConfig::from_toml_str(&with_token(STRONG), dir.path()).unwrap();
    assert!(!cfg.dev);
    assert!(!format!("{cfg:?}").contains(STRONG));
    let mut dev = cfg.clone();
    dev.tenants[0].token = "".into();
    assert!(dev.validate().is_err());
    dev.dev = true;
    dev.validate()
        .expect("weak tokens are accepted in development mode");

    // A truncated database is refused naming the file.
    let trunc = dir.path().join("trunc.planetdb");
    let bytes = std::fs::read(&db).unwrap();
    std::fs::write(&trunc, &bytes[..bytes.len() - 5]).unwrap();
    let e = planet_server::db::MappedDb::open("t", &trunc).unwrap_err();
    assert!(e.to_string().contains("trunc.planetdb"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tenant_bandwidth_is_paced_then_rate_limited_and_cancel_is_counted() {
    let dir = tempfile::tempdir().unwrap();
    let (mut cfg, recs) = two_tenant_config(dir.path());
    cfg.tenants[0].max_in_flight = 64;
    cfg.tenants[0].max_bytes_per_second = 4000;
    let h = Server::start(cfg).await.unwrap();
    let (conn, welcome) = connect(&h, acme()).await.unwrap();
    assert_eq!(welcome.limits.max_bytes_per_second, 4000);
    let (off, size) = recs[0];
    let handles: Vec<_> = (0..20).map(|i| conn.spawn_fetch(i, off, size)).collect();
    let (mut ok, mut limited) = (0, 0);
    for hdl in handles {
        match hdl.join().await {
            Ok(b) => {
                assert_eq!(b.len(), size as usize);
                ok += 1
            }
            Err(NetError::Server(e)) if e.code == ErrorCode::RateLimited => limited += 1,
            Err(e) => panic!("{e:?}"),
        }
    }
    assert!(ok >= 3 && limited >= 1, "ok {ok} limited {limited}");
    // A paced request that the client cancels is counted as cancelled.
    tokio::time::sleep(Duration::from_millis(2600)).await;
    let filler: Vec<_> = (100..105).map(|i| conn.spawn_fetch(i, off, size)).collect();
    // Let the fillers reserve the bucket first, so the victim is paced.
    tokio::time::sleep(Duration::from_millis(50)).await;
    let victim = conn.spawn_fetch(200, off, size);
    tokio::time::sleep(Duration::from_millis(100)).await;
    if victim.is_finished() {
        panic!(
            "victim finished early: {:?} size {size}",
            victim.join().await
        );
    }
    victim.cancel();
    let r = victim.join().await;
    assert!(matches!(r, Err(NetError::Cancelled)), "{r:?}");
    for f in filler {
        let _ = f.join().await;
    }
    let text = wait_metrics(&h, |t| {
        metric(t, "planet_requests_total", &[("outcome", "cancelled")]) >= 1.0
    })
    .await;
    assert_eq!(
        metric(
            &text,
            "planet_requests_total",
            &[("outcome", "rate_limited")]
        ),
        f64::from(limited)
    );
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn quic_datagrams_are_not_offered() {
    // The protocol has no use for QUIC datagrams; when they were enabled
    // quinn advertised `max_datagram_frame_size` and buffered about 1.25 MB
    // of unread datagrams per connection, before authentication.
    let dir = tempfile::tempdir().unwrap();
    let (cfg, _) = two_tenant_config(dir.path());
    let h = Server::start(cfg).await.unwrap();
    let (_ep, conn) = raw_connect(&h).await;
    assert_eq!(conn.max_datagram_size(), None);
    let sent = conn.send_datagram(bytes::Bytes::from_static(&[0u8; 1000]));
    assert!(
        matches!(sent, Err(quinn::SendDatagramError::UnsupportedByPeer)),
        "{sent:?}"
    );
    conn.close(0u32.into(), b"");
    h.shutdown().await;
}

/// A metric's labels in the contract: (label, allowed values; empty = any).
type ContractLabels = Vec<(String, Vec<String>)>;

/// The contract lines of `deploy/metrics-contract.txt`: name -> (type,
/// labels).
fn contract() -> std::collections::BTreeMap<String, (String, ContractLabels)> {
    let text = include_str!("../../deploy/metrics-contract.txt");
    let mut out = std::collections::BTreeMap::new();
    for line in text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
    {
        let mut words = line.split_whitespace();
        let name = words.next().unwrap().to_string();
        let kind = words.next().unwrap().to_string();
        let labels = words
            .map(|w| match w.split_once('=') {
                Some((k, v)) => (k.to_string(), v.split('|').map(String::from).collect()),
                None => (w.to_string(), vec![]),
            })
            .collect();
        out.insert(name, (kind, labels));
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_match_the_contract_and_the_deploy_guide() {
    use planet_server::metrics::{HandshakeEnd, RequestOutcome, CONNECTION_OUTCOMES};
    let contract = contract();
    let deploy = include_str!("../../docs/DEPLOY.md");
    let values = |name: &str, label: &str| -> Vec<String> {
        contract[name]
            .1
            .iter()
            .find(|(k, _)| k == label)
            .map(|(_, v)| v.clone())
            .unwrap_or_else(|| panic!("{name} has no label {label} in the contract"))
    };
    // Every outcome the code can emit is in the contract, and the contract
    // lists no outcome the code cannot emit.
    let mut code: Vec<&str> = RequestOutcome::ALL.iter().map(|o| o.as_str()).collect();
    let mut listed = values("planet_requests_total", "outcome");
    code.sort_unstable();
    listed.sort_unstable();
    assert_eq!(code, listed, "planet_requests_total outcomes");
    let mut code = HandshakeEnd::LABELS.to_vec();
    let mut listed = values("planet_handshakes_total", "outcome");
    code.sort_unstable();
    listed.sort_unstable();
    assert_eq!(code, listed, "planet_handshakes_total outcomes");
    let mut code = CONNECTION_OUTCOMES.to_vec();
    let mut listed = values("planet_connections_total", "outcome");
    code.sort_unstable();
    listed.sort_unstable();
    assert_eq!(code, listed, "planet_connections_total outcomes");

    // A live scrape: every planet_ family is in the contract with its type,
    // every contract planet_ metric is exported, and each one (with every
    // outcome value) is documented in docs/DEPLOY.md's metrics section.
    let dir = tempfile::tempdir().unwrap();
    let (cfg, recs) = two_tenant_config(dir.path());
    let h = Server::start(cfg).await.unwrap();
    let (conn, _) = connect(&h, acme()).await.unwrap();
    conn.fetch(1, recs[0].0, recs[0].1).await.unwrap();
    let text = wait_metrics(&h, |t| {
        metric(t, "planet_requests_total", &[("outcome", "ok")]) >= 1.0
    })
    .await;
    let exported: std::collections::BTreeMap<&str, &str> = text
        .lines()
        .filter_map(|l| l.strip_prefix("# TYPE "))
        .filter_map(|l| l.split_once(' '))
        .filter(|(n, _)| n.starts_with("planet_"))
        .collect();
    for (name, kind) in &exported {
        let (ckind, _) = contract
            .get(*name)
            .unwrap_or_else(|| panic!("{name} is exported but not in metrics-contract.txt"));
        assert_eq!(ckind, kind, "{name}");
    }
    for (name, (_, labels)) in contract.iter().filter(|(n, _)| n.starts_with("planet_")) {
        assert!(
            exported.contains_key(name.as_str()),
            "{name} is in the contract but not exported"
        );
        assert!(
            deploy.contains(name.as_str()),
            "{name} is not documented in docs/DEPLOY.md"
        );
        for (label, vals) in labels {
            for v in vals {
                assert!(
                    deploy.contains(&format!("`{v}`")),
                    "{name}{{{label}=\"{v}\"}} is not documented in docs/DEPLOY.md"
                );
            }
        }
    }
    conn.close();
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn protocol_document_claims_hold() {
    // docs/PROTOCOL.md: records lie in [64, header_offset); the superblock
    // and the header are `out_of_range`; an undecodable request stream is
    // answered with an error head of id 0.
    let doc = include_str!("../../docs/PROTOCOL.md");
    assert!(doc.contains("`[64, header_offset)`"));
    assert!(doc.contains("**id 0**"));
    let dir = tempfile::tempdir().unwrap();
    let (cfg, _) = two_tenant_config(dir.path());
    let file = file_bytes(&dir.path().join("earth.planetdb"));
    let header_offset = u64::from_le_bytes(file[16..24].try_into().unwrap());
    let h = Server::start(cfg).await.unwrap();
    let (conn, welcome) = connect(&h, acme()).await.unwrap();
    assert_eq!(welcome.file_size, file.len() as u64);
    for (id, offset, size) in [(1, 0, 64), (2, 0, 8), (3, header_offset, 8)] {
        assert_eq!(
            server_code(conn.fetch(id, offset, size).await),
            ErrorCode::OutOfRange,
            "{offset}+{size}"
        );
    }
    let (mut send, mut recv) = conn.quinn().open_bi().await.unwrap();
    send.write_all(&[3, 0, 0, 0, 0x10, 1, 2]).await.unwrap();
    send.finish().unwrap();
    let reply = read_all(&mut recv).await;
    let mut dec = FrameDecoder::new();
    dec.push(&reply);
    match dec.next_frame() {
        Ok(Some(Message::ResponseHead(head))) => {
            assert_eq!(head.id, 0);
            match head.status {
                planet_protocol::Status::Error(e) => assert_eq!(e.code, ErrorCode::Malformed),
                other => panic!("{other:?}"),
            }
        }
        other => panic!("{other:?}"),
    }
    conn.close();
    h.shutdown().await;
}
