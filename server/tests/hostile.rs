//! Hostile clients against an in-process server, each run next to a
//! well-behaved client.
//!
//! Every case asserts (1) the error code the hostile client gets, (2) that the
//! server stays healthy (a fresh handshake works, `/healthz` answers 200) and
//! (3) that a concurrent good client keeps at least 90 % of its throughput:
//! the good client fetches a fixed request list (every record of the test
//! database, [`LIST_ROUNDS`] times, [`GOOD_PARALLEL`] requests in flight),
//! once alone (baseline) and once while the hostile client runs; records/s
//! are compared. Every byte the good client receives is compared with the
//! file (bytes lost or corrupted must be zero).
//!
//! The hostile client shares the test process, and so the CPU, with the
//! server and the good client; a hostile client on its own machine costs the
//! server less. Hostile loops are therefore paced while the good client
//! measures: request-level attacks at about 200 requests per second,
//! handshake-level attacks (wrong tokens, control-stream violations, stream
//! floods on fresh connections, connection churn) at one handshake per
//! [`HANDSHAKE_PACE`]; the bulk counts (300 wrong tokens, 2000 connections)
//! are then run back to back. Unpaced handshake floods are a CPU DoS the
//! server does not prevent (docs/SECURITY.md). The measurement alternates
//! [`PAIRS`] pairs of slices with the attack paused and running, so both see
//! the same background load, and is retried up to [`ATTEMPTS`] times to
//! absorb scheduler noise on a shared 2-core machine; the best ratio must
//! reach 0.9. Ratios are printed (`--nocapture`).
//!
//! The cases run one at a time (a process-wide lock) so that baselines are
//! not measured against each other.

mod common;

use std::future::Future;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use common::*;
use planet_protocol::{
    decode_request_stream, ErrorCode, FrameDecoder, Hello, LodRequest, Message, Status,
};
use planet_server::{Server, ServerConfig, ServerHandle};
use planet_session::net::{ConnectOptions, Connection, NetError};

/// Rounds of the record list the good client fetches per measurement.
const LIST_ROUNDS: usize = 40;
/// Pairs of (paused, running) measurement slices per attempt.
const PAIRS: usize = 4;
/// Requests the good client keeps in flight.
const GOOD_PARALLEL: usize = 4;
/// Measurements per case before the 90 % assertion fails.
const ATTEMPTS: usize = 8;
/// Required fraction of the baseline throughput.
const MIN_RATIO: f64 = 0.9;

/// Pause between the handshakes of a hostile client while the good client
/// measures: every handshake costs a TLS 1.3 key exchange on both sides, in
/// this process (see "not protected" in docs/SECURITY.md).
const HANDSHAKE_PACE: Duration = Duration::from_millis(100);
/// Rejected hellos the wrong-token case sends in a row.
const WRONG_HELLOS: u64 = 300;

/// Ids of the good client's requests, never reused (see resources.rs).
static GOOD_IDS: AtomicU64 = AtomicU64::new(1_000_000);

/// Bytes the good clients received and verified against the file.
static GOOD_BYTES: AtomicU64 = AtomicU64::new(0);

static SERIAL: Mutex<()> = Mutex::new(());

fn serial() -> MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// The tests' runtime: 2 workers.
fn runtime() -> tokio::runtime::Runtime {
    planet_testkit::runtime(2).expect("tokio runtime")
}

struct Fx {
    _dir: tempfile::TempDir,
    h: ServerHandle,
    recs: Vec<(u64, u32)>,
    mars_recs: Vec<(u64, u32)>,
    file: Arc<Vec<u8>>,
    mars_file: Arc<Vec<u8>>,
    good: Connection,
}

async fn fixture(tweak: impl FnOnce(&mut ServerConfig)) -> Fx {
    let dir = tempfile::tempdir().unwrap();
    let (mut cfg, recs) = two_tenant_config(dir.path());
    cfg.tenants[0].max_in_flight = 8;
    tweak(&mut cfg);
    let file = Arc::new(file_bytes(&dir.path().join("earth.planetdb")));
    let mars_file = Arc::new(file_bytes(&dir.path().join("mars.planetdb")));
    let mars_recs = record_list(&mars_file);
    let h = Server::start(cfg).await.unwrap();
    let (good, _) = connect(&h, acme()).await.unwrap();
    Fx {
        _dir: dir,
        h,
        recs,
        mars_recs,
        file,
        mars_file,
        good,
    }
}

/// Every record (offset, size) of a database file, walking `[64, header)`.
fn record_list(file: &[u8]) -> Vec<(u64, u32)> {
    let header_offset = u64::from_le_bytes(file[16..24].try_into().unwrap());
    let mut out = Vec::new();
    let mut off = 64u64;
    while off < header_offset {
        let len = planet_core::format::peek_record_len(&file[off as usize..]).unwrap();
        out.push((off, len));
        off += u64::from(len);
    }
    out
}

/// The good client: fetches the fixed list, checks every byte, returns
/// records/s.
async fn good_run(fx: &Fx) -> f64 {
    let list: Arc<Vec<(u64, u32)>> = Arc::new(
        (0..LIST_ROUNDS)
            .flat_map(|_| fx.recs.iter().copied())
            .collect(),
    );
    let next = Arc::new(AtomicUsize::new(0));
    let started = Instant::now();
    let workers: Vec<_> = (0..GOOD_PARALLEL)
        .map(|_| {
            let (list, next, conn, file) = (
                Arc::clone(&list),
                Arc::clone(&next),
                fx.good.clone(),
                Arc::clone(&fx.file),
            );
            tokio::spawn(async move {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&(off, size)) = list.get(i) else {
                        break;
                    };
                    let bytes = conn
                        .fetch(GOOD_IDS.fetch_add(1, Ordering::Relaxed), off, size)
                        .await
                        .expect("good client fetch");
                    assert_eq!(
                        &bytes[..],
                        &file[off as usize..off as usize + size as usize],
                        "good client got wrong bytes"
                    );
                    GOOD_BYTES.fetch_add(bytes.len() as u64, Ordering::Relaxed);
                }
            })
        })
        .collect();
    for w in workers {
        w.await.unwrap();
    }
    list.len() as f64 / started.elapsed().as_secs_f64()
}

/// Start/stop control of a hostile loop: the good client's measurements
/// alternate between slices with the attack paused and slices with it
/// running, so that both see the same background load.
#[derive(Clone, Default)]
struct Ctl {
    stop: Arc<AtomicBool>,
    active: Arc<AtomicBool>,
}

impl Ctl {
    /// Waits while the attack is paused; false once it is stopped.
    async fn go(&self) -> bool {
        loop {
            if self.stop.load(Ordering::Acquire) {
                return false;
            }
            if self.active.load(Ordering::Acquire) {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }

    fn stopped(&self) -> bool {
        self.stop.load(Ordering::Acquire)
    }
}

/// Runs `attack` while the good client measures; asserts the good client's
/// throughput ratio. Each attempt measures [`PAIRS`] pairs of slices (attack
/// paused, attack running) and compares the summed times. Returns the
/// attack's output of the last attempt.
async fn under_attack<F, Fut, T>(fx: &Fx, name: &str, attack: F) -> T
where
    F: Fn(Ctl) -> Fut,
    Fut: Future<Output = T> + Send + 'static,
    T: Send + 'static,
{
    let mut best = 0.0f64;
    let mut last = None;
    let bytes_before = GOOD_BYTES.load(Ordering::Relaxed);
    for attempt in 1..=ATTEMPTS {
        let ctl = Ctl::default();
        let task = tokio::spawn(attack(ctl.clone()));
        let per_slice = (LIST_ROUNDS * fx.recs.len()) as f64;
        let (mut t_base, mut t_attack) = (0.0, 0.0);
        for _ in 0..PAIRS {
            ctl.active.store(false, Ordering::Release);
            tokio::time::sleep(Duration::from_millis(10)).await;
            t_base += per_slice / good_run(fx).await;
            ctl.active.store(true, Ordering::Release);
            tokio::time::sleep(Duration::from_millis(20)).await;
            t_attack += per_slice / good_run(fx).await;
        }
        ctl.active.store(false, Ordering::Release);
        ctl.stop.store(true, Ordering::Release);
        let out = task.await.expect("attack task panicked");
        let n = PAIRS as f64 * per_slice;
        let (base, under) = (n / t_base, n / t_attack);
        let ratio = t_base / t_attack;
        eprintln!(
            "hostile[{name}] attempt {attempt}: baseline {base:.0} rec/s, under attack {under:.0} rec/s, ratio {ratio:.2}"
        );
        best = best.max(ratio);
        last = Some(out);
        if ratio >= MIN_RATIO {
            break;
        }
    }
    eprintln!(
        "hostile[{name}]: good client verified {} bytes, 0 lost or wrong",
        GOOD_BYTES.load(Ordering::Relaxed) - bytes_before
    );
    assert!(
        best >= MIN_RATIO,
        "hostile[{name}]: the good client kept only {:.0} % of its throughput",
        best * 100.0
    );
    last.unwrap()
}

/// The server is still healthy: `/healthz` 200 and a fresh session fetches.
async fn assert_healthy(fx: &Fx) {
    let (status, _) = http_get(fx.h.metrics_addr().unwrap(), "/healthz").await;
    assert_eq!(status, 200);
    let (conn, _) = connect(&fx.h, acme()).await.expect("fresh handshake");
    let (off, size) = fx.recs[0];
    assert_eq!(conn.fetch(1, off, size).await.unwrap().len(), size as usize);
    conn.close();
}

/// Waits until the server has exactly `n` open connections (the good
/// client's), or panics.
async fn wait_active(h: &ServerHandle, n: usize, within: Duration) {
    let deadline = Instant::now() + within;
    while h.active_connections() != n {
        assert!(
            Instant::now() < deadline,
            "active connections {} != {n} after {within:?}",
            h.active_connections()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let text = scrape(h).await;
    assert_eq!(metric(&text, "planet_connections_active", &[]), n as f64);
}

/// Sends `bytes` on a new request stream; returns the error code of the
/// response head (None for a record).
async fn raw_request(conn: &quinn::Connection, bytes: &[u8]) -> Option<ErrorCode> {
    let (mut send, mut recv) = conn.open_bi().await.expect("open_bi");
    // The server may stop reading a stream that is too long.
    let _ = send.write_all(bytes).await;
    let _ = send.finish();
    let reply = recv.read_to_end(1 << 20).await.expect("response");
    let mut dec = FrameDecoder::new();
    dec.push(&reply);
    match dec.next_frame() {
        Ok(Some(Message::ResponseHead(h))) => match h.status {
            Status::Ok => None,
            Status::Error(e) => Some(e.code),
        },
        other => panic!("expected a response head, got {other:?}"),
    }
}

/// A raw connection that completed the hello.
async fn raw_session(h: &ServerHandle, hello: Hello) -> (quinn::Endpoint, quinn::Connection) {
    let (ep, conn) = raw_connect(h).await;
    let (mut send, mut recv) = conn.open_bi().await.unwrap();
    send.write_all(&hello.encode_frame().unwrap())
        .await
        .unwrap();
    let mut dec = FrameDecoder::with_max_frame_len(planet_protocol::MAX_WELCOME_FRAME_LEN);
    loop {
        let chunk = recv.read_chunk(1 << 16, true).await.unwrap().unwrap();
        dec.push(&chunk.bytes);
        if let Some(m) = dec.next_frame().unwrap() {
            assert!(matches!(m, Message::Welcome(_)), "{m:?}");
            break;
        }
    }
    // Keep the control stream open: dropping `send` would finish it and end
    // the session.
    std::mem::forget(send);
    std::mem::forget(recv);
    (ep, conn)
}

fn paced(_i: u64) -> Duration {
    // About 200 hostile requests per second.
    Duration::from_millis(5)
}

#[test]
fn malformed_oversized_and_unknown_frames_on_request_streams() {
    let _g = serial();
    runtime().block_on(async {
        let fx = fixture(|_| {}).await;
        let (off, size) = fx.recs[0];
        let good_req = LodRequest {
            id: 5,
            offset: off,
            size,
        }
        .encode_frame()
        .unwrap();
        let mut long = good_req.clone();
        long.extend_from_slice(&good_req);
        let cases: Vec<Vec<u8>> = vec![
            vec![],                                          // empty stream
            good_req[..10].to_vec(),                         // truncated frame
            vec![0xff, 0xff, 0xff, 0x7f, 0x10],              // frame too large
            vec![2, 0, 0, 0, 0x7f, 0],                       // unknown message type
            vec![2, 0, 0, 0, 0x01, 0],                       // hello on a request stream
            vec![20, 0, 0, 0, 0x10, 1, 2, 3],                // lod_request with a short body
            long,                                            // two requests on one stream
            vec![0u8; 4096],                                 // zeros beyond the frame length
            (0..25u8).map(|b| b.wrapping_mul(37)).collect(), // garbage of a request's length
        ];
        // The expected code is what the protocol decoder says, except for
        // streams longer than one request (cut short by the server).
        let expected: Vec<ErrorCode> = cases
            .iter()
            .map(|c| {
                if c.len() > planet_protocol::LOD_REQUEST_FRAME_LEN {
                    ErrorCode::Malformed
                } else {
                    decode_request_stream(c).unwrap_err().code()
                }
            })
            .collect();
        let (ep, conn) = raw_session(&fx.h, acme()).await;
        let conn2 = conn.clone();
        let cases2 = cases.clone();
        let expected2 = expected.clone();
        let n = under_attack(&fx, "malformed frames", move |ctl| {
            let (conn, cases, expected) = (conn2.clone(), cases2.clone(), expected2.clone());
            async move {
                let mut n = 0u64;
                while ctl.go().await {
                    for (c, e) in cases.iter().zip(&expected) {
                        assert_eq!(raw_request(&conn, c).await, Some(*e), "{c:?}");
                        n += 1;
                        tokio::time::sleep(paced(n)).await;
                    }
                }
                n
            }
        })
        .await;
        eprintln!("hostile[malformed frames]: {n} malformed request streams");
        // The hostile connection itself stays usable.
        let req = LodRequest {
            id: 77,
            offset: off,
            size,
        };
        assert_eq!(raw_request(&conn, &req.encode_frame().unwrap()).await, None);
        let text = scrape(&fx.h).await;
        assert!(metric(&text, "planet_requests_total", &[("outcome", "invalid")]) >= n as f64);
        drop(conn);
        drop(ep);
        assert_healthy(&fx).await;
        fx.h.shutdown().await;
    });
}

#[test]
fn control_stream_violations_and_requests_before_hello() {
    let _g = serial();
    runtime().block_on(async {
        let fx = fixture(|_| {}).await;
        let (off, size) = fx.recs[0];
        let req = LodRequest {
            id: 3,
            offset: off,
            size,
        }
        .encode_frame()
        .unwrap();
        let fp = fx.h.cert_fingerprint().to_string();
        let addr = fx.h.local_addr();
        let n = under_attack(&fx, "control stream + before hello", move |ctl| {
            let (fp, req) = (fp.clone(), req.clone());
            async move {
                let tls = planet_session::tls::pinned(&fp).unwrap();
                let mut ep = quinn::Endpoint::client("127.0.0.1:0".parse().unwrap()).unwrap();
                let crypto = quinn::crypto::rustls::QuicClientConfig::try_from(tls).unwrap();
                ep.set_default_client_config(quinn::ClientConfig::new(Arc::new(crypto)));
                let bad_ctrl: Vec<(Vec<u8>, ErrorCode)> = vec![
                    (vec![2, 0, 0, 0, 0x7f, 0], ErrorCode::UnknownMessage),
                    (vec![0xff, 0xff, 0xff, 0x7f, 0x01], ErrorCode::FrameTooLarge),
                    (vec![3, 0, 0, 0, 0x01, 1, 2], ErrorCode::Malformed),
                    (req.clone(), ErrorCode::HelloRequired),
                    (
                        planet_protocol::Cancel { id: 1 }.encode_frame().unwrap(),
                        ErrorCode::HelloRequired,
                    ),
                ];
                let hello = acme().encode_frame().unwrap();
                let mut n = 0u64;
                while ctl.go().await {
                    // Before the hello is complete a client has the stream
                    // budget of the hello only: no request stream opens, the
                    // connection is kept, and completing the hello grants
                    // the tenant's streams.
                    let conn = ep.connect(addr, "localhost").unwrap().await.unwrap();
                    let (mut ctrl, _ctrl_recv) = conn.open_bi().await.unwrap();
                    ctrl.write_all(&hello[..3]).await.unwrap();
                    tokio::time::sleep(Duration::from_millis(20)).await;
                    let early =
                        tokio::time::timeout(Duration::from_millis(50), conn.open_bi()).await;
                    assert!(early.is_err(), "a request stream opened before the hello");
                    n += 1;
                    ctrl.write_all(&hello[3..]).await.unwrap();
                    let mut ok = false;
                    for _ in 0..50 {
                        if raw_request(&conn, &req).await.is_none() {
                            ok = true;
                            break;
                        }
                        tokio::time::sleep(Duration::from_millis(5)).await;
                    }
                    assert!(ok, "requests still refused after the hello");
                    conn.close(0u32.into(), b"");

                    // A fatal control-stream violation on a fresh connection.
                    let conn = ep.connect(addr, "localhost").unwrap().await.unwrap();
                    let (bytes, code) = &bad_ctrl[n as usize % bad_ctrl.len()];
                    let (mut send, mut recv) = conn.open_bi().await.unwrap();
                    send.write_all(bytes).await.unwrap();
                    let reply = recv.read_to_end(1 << 16).await.unwrap_or_default();
                    let mut dec = FrameDecoder::new();
                    dec.push(&reply);
                    match dec.next_frame() {
                        Ok(Some(Message::Error(e))) => assert_eq!(e.code, *code),
                        other => panic!("{bytes:?}: {other:?}"),
                    }
                    match conn.closed().await {
                        quinn::ConnectionError::ApplicationClosed(c) => {
                            assert_eq!(c.error_code.into_inner(), u64::from(code.to_quic()))
                        }
                        other => panic!("{other:?}"),
                    }
                    n += 1;
                    tokio::time::sleep(HANDSHAKE_PACE).await;
                }
                ep.wait_idle().await;
                n
            }
        })
        .await;
        eprintln!("hostile[control stream + before hello]: {n} hostile frames");
        assert_healthy(&fx).await;
        wait_active(&fx.h, 1, Duration::from_secs(5)).await;
        fx.h.shutdown().await;
    });
}

#[test]
fn wrong_tokens_in_a_row_and_other_tenants_database() {
    let _g = serial();
    runtime().block_on(async {
        // Every client here shares 127.0.0.1: the per-address limit of
        // failed hellos is off (resources.rs
        // failed_hellos_are_limited_per_address tests it).
        let fx = fixture(|c| c.max_failed_hellos_per_minute = 0).await;
        let fp = fx.h.cert_fingerprint().to_string();
        let addr = fx.h.local_addr();
        let (n, codes) = under_attack(&fx, "wrong tokens", move |ctl| {
            let fp = fp.clone();
            async move {
                let tls = planet_session::tls::pinned(&fp).unwrap();
                let cases = [
                    (
                        Hello::new("acme", "s3creT", "earth"),
                        ErrorCode::Unauthorized,
                    ),
                    (Hello::new("acme", "", "earth"), ErrorCode::Unauthorized),
                    (
                        Hello::new("acme", "t0ken", "earth"),
                        ErrorCode::Unauthorized,
                    ),
                    (
                        Hello::new("other", "s3cret", "mars"),
                        ErrorCode::Unauthorized,
                    ),
                    (Hello::new("acme", "s3cret", "mars"), ErrorCode::Forbidden),
                    (Hello::new("other", "t0ken", "earth"), ErrorCode::Forbidden),
                    (
                        Hello::new("acme", "x".repeat(256), "earth"),
                        ErrorCode::Unauthorized,
                    ),
                ];
                let mut n = 0u64;
                let mut codes = std::collections::BTreeMap::new();
                // Paced while the good client measures, then back to back
                // up to WRONG_HELLOS rejections.
                while !ctl.stopped() || n < WRONG_HELLOS {
                    if !ctl.stopped() && !ctl.go().await {
                        continue;
                    }
                    let (hello, code) = &cases[n as usize % cases.len()];
                    match Connection::connect(addr, "localhost", tls.clone(), hello.clone()).await {
                        Err(NetError::Rejected(e)) => assert_eq!(e.code, *code, "{hello:?}"),
                        other => panic!("{hello:?}: expected rejection, got {:?}", other.err()),
                    }
                    *codes.entry(code.as_str()).or_insert(0u64) += 1;
                    n += 1;
                    if !ctl.stopped() {
                        tokio::time::sleep(HANDSHAKE_PACE).await;
                    }
                }
                (n, codes)
            }
        })
        .await;
        eprintln!("hostile[wrong tokens]: {n} rejected hellos {codes:?}");
        assert!(n >= WRONG_HELLOS);
        // Without the per-address limit, the right token works right after
        // the failures.
        let (conn, _) = connect(&fx.h, acme()).await.unwrap();
        // Offsets of the other tenant's database, asked in our session, are
        // validated against our database: never a byte of the other file.
        for (i, (off, size)) in fx.mars_recs.iter().enumerate() {
            match conn.fetch(i as u64, *off, *size).await {
                Ok(bytes) => {
                    let ours = &fx.file[*off as usize..*off as usize + *size as usize];
                    assert_eq!(&bytes[..], ours);
                    assert_ne!(
                        &bytes[..],
                        &fx.mars_file[*off as usize..*off as usize + *size as usize]
                    );
                }
                Err(NetError::Server(e)) => assert!(
                    matches!(
                        e.code,
                        ErrorCode::OutOfRange | ErrorCode::NotARecord | ErrorCode::WrongSize
                    ),
                    "{e:?}"
                ),
                Err(e) => panic!("{e:?}"),
            }
        }
        let text = scrape(&fx.h).await;
        assert!(
            metric(
                &text,
                "planet_handshakes_total",
                &[("outcome", "unauthorized")]
            ) >= 1.0
        );
        assert!(
            metric(
                &text,
                "planet_handshakes_total",
                &[("outcome", "forbidden")]
            ) >= 1.0
        );
        conn.close();
        assert_healthy(&fx).await;
        wait_active(&fx.h, 1, Duration::from_secs(5)).await;
        fx.h.shutdown().await;
    });
}

#[test]
fn replayed_token_is_accepted_by_design_and_0rtt_cannot_be_replayed() {
    let _g = serial();
    runtime().block_on(async {
        let fx = fixture(|_| {}).await;
        // Bearer-token model: the same token on several connections at once
        // is fine (one tenant, many clients).
        let mut conns = Vec::new();
        for _ in 0..5 {
            conns.push(connect(&fx.h, acme()).await.unwrap().0);
        }
        let (off, size) = fx.recs[1];
        for (i, c) in conns.iter().enumerate() {
            assert_eq!(
                c.fetch(i as u64, off, size).await.unwrap().len(),
                size as usize
            );
        }
        for c in conns {
            c.close();
        }

        // 0-RTT: a client resuming its session (one rustls config, so one
        // ticket store) sends its Hello as early data and the server takes it.
        let tls = tls_for(&fx.h);
        let opts = ConnectOptions::default();
        let relay = Replayer::start(fx.h.local_addr()).await;
        let c1 = connect_as(fx.h.local_addr(), &tls, acme(), &opts)
            .await
            .unwrap();
        assert!(!c1.used_zero_rtt(), "a first connection cannot resume");
        assert_eq!(c1.fetch(1, off, size).await.unwrap().len(), size as usize);
        // Session tickets arrive after the handshake.
        tokio::time::sleep(Duration::from_millis(200)).await;
        c1.close();
        let hellos = handshakes_ok(&fx.h).await;
        let c2 = connect_as(relay.addr, &tls, acme(), &opts).await.unwrap();
        assert!(c2.used_zero_rtt(), "the resumed session did not use 0-RTT");
        assert_eq!(c2.fetch(2, off, size).await.unwrap().len(), size as usize);
        c2.close();
        assert_eq!(handshakes_ok(&fx.h).await, hellos + 1.0);
        // A wrong token in 0-RTT is refused with its code like any other.
        let bad = Hello::new("acme", "s3creT", "earth");
        match connect_as(relay.addr, &tls, bad, &opts).await {
            Err(NetError::Rejected(e)) => assert_eq!(e.code, ErrorCode::Unauthorized),
            other => panic!("expected unauthorized, got {:?}", other.err()),
        }

        // Replay: an on-path attacker resends the client's captured first
        // flight (the ClientHello with the ticket and the 0-RTT Hello) from
        // another port. The ticket was single-use, so the early data is
        // refused and the Hello never reaches a session.
        tokio::time::sleep(Duration::from_millis(500)).await;
        let _attacker = relay.replay(fx.h.local_addr()).await;
        tokio::time::sleep(Duration::from_millis(700)).await;
        assert_eq!(
            handshakes_ok(&fx.h).await,
            hellos + 1.0,
            "a replayed 0-RTT Hello was accepted"
        );

        // Control: the same replay against a server whose tickets can be
        // redeemed twice does deliver the early data a second time, so the
        // check above is not vacuous.
        assert_eq!(replay_against_reusable_tickets().await, 2);

        // With `zero_rtt = false` the server's tickets do not allow early
        // data: a resuming client does not even try 0-RTT.
        let dir = tempfile::tempdir().unwrap();
        let (mut cfg, recs) = two_tenant_config(dir.path());
        cfg.zero_rtt = false;
        let (off, size) = recs[1];
        let strict = Server::start(cfg).await.unwrap();
        let tls = tls_for(&strict);
        let opts = ConnectOptions::default();
        for round in 0..2 {
            let c = connect_as(strict.local_addr(), &tls, acme(), &opts)
                .await
                .unwrap();
            assert!(!c.used_zero_rtt(), "0-RTT with zero_rtt = false");
            assert!(
                !c.zero_rtt_refused(),
                "early data tried with zero_rtt = false"
            );
            assert_eq!(c.fetch(3, off, size).await.unwrap().len(), size as usize);
            if round == 0 {
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            c.close();
        }
        strict.shutdown().await;
        assert_healthy(&fx).await;
        fx.h.shutdown().await;
    });
}

async fn connect_as(
    addr: std::net::SocketAddr,
    tls: &Arc<rustls::ClientConfig>,
    hello: Hello,
    opts: &ConnectOptions,
) -> Result<Connection, NetError> {
    Connection::connect_with(addr, "localhost", Arc::clone(tls), hello, opts)
        .await
        .map(|(c, _)| c)
}

async fn handshakes_ok(h: &ServerHandle) -> f64 {
    metric(
        &scrape(h).await,
        "planet_handshakes_total",
        &[("outcome", "ok")],
    )
}

/// A UDP relay in front of a server (20 ms from server to client) that
/// records the client's first flight
/// (its datagrams that start with an Initial or a 0-RTT packet: the
/// ClientHello and the early data) so it can be replayed.
struct Replayer {
    addr: std::net::SocketAddr,
    first_flight: Arc<Mutex<Vec<Vec<u8>>>>,
    task: tokio::task::JoinHandle<()>,
}

impl Replayer {
    async fn start(server: std::net::SocketAddr) -> Replayer {
        let down = Arc::new(tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap());
        let up = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let addr = down.local_addr().unwrap();
        let first_flight = Arc::new(Mutex::new(Vec::new()));
        let flight = Arc::clone(&first_flight);
        let task = tokio::spawn(async move {
            let (mut a, mut b) = (vec![0u8; 65536], vec![0u8; 65536]);
            let mut client = None;
            loop {
                tokio::select! {
                    r = down.recv_from(&mut a) => {
                        let Ok((n, from)) = r else { return };
                        client = Some(from);
                        if is_initial_or_0rtt(&a[..n]) {
                            flight.lock().unwrap().push(a[..n].to_vec());
                        }
                        let _ = up.send_to(&a[..n], server).await;
                    }
                    r = up.recv_from(&mut b) => {
                        let Ok((n, _)) = r else { return };
                        if let Some(c) = client {
                            // 20 ms on the way back: the client's Hello
                            // leaves as 0-RTT before any answer can arrive,
                            // however the threads are scheduled.
                            let (down, d) = (Arc::clone(&down), b[..n].to_vec());
                            tokio::spawn(async move {
                                tokio::time::sleep(Duration::from_millis(20)).await;
                                let _ = down.send_to(&d, c).await;
                            });
                        }
                    }
                }
            }
        });
        Replayer {
            addr,
            first_flight,
            task,
        }
    }

    /// Sends the recorded first flight to `server` from a new socket, which
    /// is returned (kept open, never answering).
    async fn replay(&self, server: std::net::SocketAddr) -> tokio::net::UdpSocket {
        let flight = self.first_flight.lock().unwrap().clone();
        assert!(
            flight.iter().any(|d| long_header_types(d).contains(&1)),
            "no 0-RTT packet recorded"
        );
        let s = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        for d in flight {
            s.send_to(&d, server).await.unwrap();
        }
        s
    }
}

/// A datagram whose first packet has a long header of type Initial or 0-RTT.
fn is_initial_or_0rtt(d: &[u8]) -> bool {
    long_header_types(d).first().is_some_and(|&t| t <= 1)
}

/// The types (0 Initial, 1 0-RTT, 2 Handshake, 3 Retry) of the coalesced
/// long-header packets at the start of a datagram (RFC 9000 §17.2, §12.2).
fn long_header_types(d: &[u8]) -> Vec<u8> {
    fn varint(d: &[u8], i: &mut usize) -> Option<usize> {
        let first = *d.get(*i)?;
        let len = 1usize << (first >> 6);
        let mut v = u64::from(first & 0x3f);
        for k in 1..len {
            v = (v << 8) | u64::from(*d.get(*i + k)?);
        }
        *i += len;
        usize::try_from(v).ok()
    }
    let mut types = Vec::new();
    let mut i = 0;
    while let Some(&flags) = d.get(i) {
        if flags & 0x80 == 0 {
            break;
        }
        let ty = (flags & 0x30) >> 4;
        types.push(ty);
        if ty == 3 {
            break;
        }
        let mut j = i + 5;
        for _ in 0..2 {
            let Some(&n) = d.get(j) else { return types };
            j += 1 + usize::from(n);
        }
        if ty == 0 {
            let Some(t) = varint(d, &mut j) else {
                return types;
            };
            j += t;
        }
        let Some(len) = varint(d, &mut j) else {
            return types;
        };
        i = j + len;
    }
    types
}

impl Drop for Replayer {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// A session store whose tickets can be redeemed any number of times (`take`
/// keeps the session): what planet-server must not do.
#[derive(Debug, Default)]
struct ReusableSessions(Mutex<std::collections::HashMap<Vec<u8>, Vec<u8>>>);

impl rustls::server::StoresServerSessions for ReusableSessions {
    fn put(&self, key: Vec<u8>, value: Vec<u8>) -> bool {
        self.0.lock().unwrap().insert(key, value);
        true
    }
    fn get(&self, key: &[u8]) -> Option<Vec<u8>> {
        self.0.lock().unwrap().get(key).cloned()
    }
    fn take(&self, key: &[u8]) -> Option<Vec<u8>> {
        self.get(key)
    }
    fn can_cache(&self) -> bool {
        true
    }
}

/// A bare quinn server with reusable session tickets
/// ([`ReusableSessions`]) and 0-RTT. A client connects once
/// for a ticket, then again through a [`Replayer`] sending a stream in 0-RTT;
/// the recorded flight is replayed. Returns how many times the server read
/// that stream's early data.
async fn replay_against_reusable_tickets() -> usize {
    let ck = planet_server::tls::CertKey::dev_cert().unwrap();
    let mut scfg = planet_server::tls::rustls_server_config(&ck, true).unwrap();
    scfg.session_storage = Arc::new(ReusableSessions::default());
    let qcfg = quinn::crypto::rustls::QuicServerConfig::try_from(scfg).unwrap();
    let sep = quinn::Endpoint::server(
        quinn::ServerConfig::with_crypto(Arc::new(qcfg)),
        "127.0.0.1:0".parse().unwrap(),
    )
    .unwrap();
    let saddr = sep.local_addr().unwrap();
    let seen = Arc::new(AtomicUsize::new(0));
    let acceptor = tokio::spawn({
        let (sep, seen) = (sep.clone(), Arc::clone(&seen));
        async move {
            while let Some(inc) = sep.accept().await {
                let seen = Arc::clone(&seen);
                tokio::spawn(async move {
                    let Ok(c) = inc.accept() else { return };
                    let Ok((conn, _)) = c.into_0rtt() else { return };
                    while let Ok((_send, mut recv)) = conn.accept_bi().await {
                        if recv.read_to_end(64).await.as_deref() == Ok(b"early".as_slice()) {
                            seen.fetch_add(1, Ordering::SeqCst);
                        }
                    }
                });
            }
        }
    });
    let fp = planet_server::tls::sha256_hex(ck.leaf_der());
    let mut tls = (*planet_session::tls::pinned(&fp).unwrap()).clone();
    tls.enable_early_data = true;
    let crypto = quinn::crypto::rustls::QuicClientConfig::try_from(Arc::new(tls)).unwrap();
    let mut ep = quinn::Endpoint::client("127.0.0.1:0".parse().unwrap()).unwrap();
    ep.set_default_client_config(quinn::ClientConfig::new(Arc::new(crypto)));
    let first = ep.connect(saddr, "localhost").unwrap().await.unwrap();
    tokio::time::sleep(Duration::from_millis(200)).await;
    first.close(0u32.into(), b"");
    let relay = Replayer::start(saddr).await;
    let (conn, accepted) = ep
        .connect(relay.addr, "localhost")
        .unwrap()
        .into_0rtt()
        .unwrap_or_else(|_| panic!("control: no 0-RTT"));
    let (mut send, _recv) = conn.open_bi().await.unwrap();
    send.write_all(b"early").await.unwrap();
    send.finish().unwrap();
    assert!(accepted.await, "control: 0-RTT refused");
    tokio::time::sleep(Duration::from_millis(200)).await;
    conn.close(0u32.into(), b"");
    tokio::time::sleep(Duration::from_millis(500)).await;
    let _attacker = relay.replay(saddr).await;
    tokio::time::sleep(Duration::from_millis(700)).await;
    sep.close(0u32.into(), b"");
    acceptor.abort();
    seen.load(Ordering::SeqCst)
}

#[test]
fn offsets_inside_records_and_past_the_end() {
    let _g = serial();
    runtime().block_on(async {
        let fx = fixture(|_| {}).await;
        let (conn, welcome) = connect(&fx.h, acme()).await.unwrap();
        let file_size = welcome.file_size;
        let starts: std::collections::HashMap<u64, u32> = fx.recs.iter().copied().collect();
        let conn2 = conn.clone();
        let file = Arc::clone(&fx.file);
        let (n, codes) = under_attack(&fx, "offsets inside/past records", move |ctl| {
            let (conn, file, starts) = (conn2.clone(), Arc::clone(&file), starts.clone());
            async move {
                let mut x = 0x2545_f491_4f6c_dd1du64;
                let mut rnd = move || {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    x
                };
                let mut n = 0u64;
                let mut codes = std::collections::BTreeMap::new();
                while ctl.go().await {
                    let r = rnd();
                    let offset = match r % 4 {
                        0 => rnd() % (file_size + 1000),
                        1 => file_size - 1 + rnd() % 3,
                        2 => u64::MAX - rnd() % 100,
                        _ => 64 + rnd() % 64,
                    };
                    let size = match (r >> 8) % 3 {
                        0 => (rnd() % 4000) as u32,
                        1 => u32::MAX - (rnd() % 3) as u32,
                        _ => starts.get(&offset).copied().unwrap_or(1500),
                    };
                    let outcome = match conn.fetch(n, offset, size).await {
                        Ok(bytes) => {
                            assert_eq!(starts.get(&offset), Some(&size));
                            assert_eq!(
                                &bytes[..],
                                &file[offset as usize..offset as usize + size as usize]
                            );
                            "ok"
                        }
                        Err(NetError::Server(e)) => {
                            assert!(
                                matches!(
                                    e.code,
                                    ErrorCode::OutOfRange
                                        | ErrorCode::NotARecord
                                        | ErrorCode::WrongSize
                                        | ErrorCode::RecordTooLarge
                                ),
                                "{offset}+{size}: {e:?}"
                            );
                            e.code.as_str()
                        }
                        Err(e) => panic!("{offset}+{size}: {e:?}"),
                    };
                    *codes.entry(outcome).or_insert(0u64) += 1;
                    n += 1;
                    tokio::time::sleep(paced(n)).await;
                }
                (n, codes)
            }
        })
        .await;
        eprintln!("hostile[offsets]: {n} requests {codes:?}");
        assert!(codes.contains_key("out_of_range"), "{codes:?}");
        conn.close();
        assert_healthy(&fx).await;
        fx.h.shutdown().await;
    });
}

#[test]
fn stream_floods_beyond_the_in_flight_limit() {
    let _g = serial();
    runtime().block_on(async {
        let fx = fixture(|_| {}).await;
        let max_in_flight = 8usize;
        let fp = fx.h.cert_fingerprint().to_string();
        let addr = fx.h.local_addr();
        let recs = fx.recs.clone();
        let peak = Arc::new(AtomicU64::new(0));
        let peak2 = Arc::clone(&peak);
        let metrics_addr = fx.h.metrics_addr().unwrap();
        let (n, refused, blocked) = under_attack(&fx, "stream flood", move |ctl| {
            let (fp, recs, peak) = (fp.clone(), recs.clone(), Arc::clone(&peak2));
            async move {
                // Tiny receive windows: responses cannot complete, so every
                // request the server accepts stays in flight.
                let mut t = quinn::TransportConfig::default();
                t.stream_receive_window(quinn::VarInt::from_u32(256));
                let opts = ConnectOptions {
                    transport: Some(Arc::new(t)),
                    ..ConnectOptions::default()
                };
                let tls = planet_session::tls::pinned(&fp).unwrap();
                let (mut n, mut refused, mut blocked) = (0u64, 0u64, 0u64);
                while ctl.go().await {
                    let (conn, _) =
                        Connection::connect_with(addr, "localhost", tls.clone(), acme(), &opts)
                            .await
                            .expect("flooding client's handshake");
                    let q = conn.quinn().clone();
                    let mut held = Vec::new();
                    // Open as many streams as the server lets us, quickly.
                    for i in 0..64u64 {
                        let open = tokio::time::timeout(Duration::from_millis(100), q.open_bi());
                        let Ok(Ok((mut send, recv))) = open.await else {
                            blocked += 1;
                            break;
                        };
                        let (off, size) = recs[i as usize % recs.len()];
                        let req = LodRequest {
                            id: i,
                            offset: off,
                            size,
                        };
                        send.write_all(&req.encode_frame().expect("encode"))
                            .await
                            .expect("write a request");
                        send.finish().expect("finish a request stream");
                        held.push(recv);
                        n += 1;
                    }
                    // The streams beyond max_in_flight were refused.
                    let mut ok_heads = 0;
                    // Keep every stream open while reading the heads: dropping
                    // one would stop it and free its slot.
                    for recv in held.iter_mut() {
                        let chunk = recv
                            .read_chunk(64, true)
                            .await
                            .expect("read a response head")
                            .expect("a response head before the end of the stream");
                        let mut dec = FrameDecoder::new();
                        dec.push(&chunk.bytes);
                        // The head may be split: read a little more if needed.
                        let mut head = dec.next_frame();
                        while matches!(head, Ok(None)) {
                            let c = recv
                                .read_chunk(64, true)
                                .await
                                .expect("read the rest of a head")
                                .expect("the rest of a head before the end of the stream");
                            dec.push(&c.bytes);
                            head = dec.next_frame();
                        }
                        match head {
                            Ok(Some(Message::ResponseHead(h))) => match h.status {
                                Status::Ok => ok_heads += 1,
                                Status::Error(e) => {
                                    assert_eq!(e.code, ErrorCode::TooManyInFlight);
                                    refused += 1;
                                }
                            },
                            other => panic!("{other:?}"),
                        }
                    }
                    assert!(ok_heads <= max_in_flight, "{ok_heads} > {max_in_flight}");
                    let text = scrape_addr(metrics_addr).await;
                    let g = metric(&text, "planet_requests_in_flight", &[]) as u64;
                    peak.fetch_max(g, Ordering::Relaxed);
                    conn.close();
                    // Closing the connection frees its slots: wait for that
                    // before the next flood, so that the peak bound below
                    // does not depend on how fast this machine tears down.
                    let deadline = Instant::now() + Duration::from_secs(10);
                    loop {
                        let text = scrape_addr(metrics_addr).await;
                        let g = metric(&text, "planet_requests_in_flight", &[]) as u64;
                        if g <= GOOD_PARALLEL as u64 {
                            break;
                        }
                        assert!(
                            Instant::now() < deadline,
                            "{g} requests still in flight 10 s after the flooding connection closed"
                        );
                        tokio::time::sleep(Duration::from_millis(10)).await;
                    }
                    tokio::time::sleep(HANDSHAKE_PACE).await;
                }
                (n, refused, blocked)
            }
        })
        .await;
        let peak = peak.load(Ordering::Relaxed);
        eprintln!(
            "hostile[stream flood]: {n} requests opened, {refused} too_many_in_flight, \
             {blocked} times blocked by the stream limit, peak in-flight gauge {peak}"
        );
        assert!(
            refused > 0,
            "no request was refused with too_many_in_flight"
        );
        // One flooding connection at a time (the previous one has drained)
        // plus the good client's requests.
        assert!(
            peak <= (max_in_flight + GOOD_PARALLEL) as u64,
            "peak in-flight gauge {peak} > {max_in_flight} + {GOOD_PARALLEL}"
        );
        assert_healthy(&fx).await;
        wait_active(&fx.h, 1, Duration::from_secs(5)).await;
        fx.h.shutdown().await;
    });
}

async fn scrape_addr(addr: std::net::SocketAddr) -> String {
    http_get(addr, "/metrics").await.1
}

#[test]
fn clients_that_never_read_their_responses() {
    let _g = serial();
    runtime().block_on(async {
        let fx = fixture(|_| {}).await;
        let max_in_flight = 8usize;
        let fp = fx.h.cert_fingerprint().to_string();
        let addr = fx.h.local_addr();
        let recs = fx.recs.clone();
        let metrics_addr = fx.h.metrics_addr().unwrap();
        let (conns, opened, in_flight) = under_attack(&fx, "never reads", move |ctl| {
            let (fp, recs) = (fp.clone(), recs.clone());
            async move {
                let mut t = quinn::TransportConfig::default();
                t.stream_receive_window(quinn::VarInt::from_u32(128));
                t.receive_window(quinn::VarInt::from_u32(1024));
                let opts = ConnectOptions {
                    transport: Some(Arc::new(t)),
                    ..ConnectOptions::default()
                };
                let tls = planet_session::tls::pinned(&fp).unwrap();
                let mut conns = Vec::new();
                let mut streams = Vec::new();
                let mut opened = 0u64;
                // 16 connections, each filling every stream it may open,
                // none of them ever read.
                while ctl.go().await && conns.len() < 16 {
                    let (conn, _) =
                        Connection::connect_with(addr, "localhost", tls.clone(), acme(), &opts)
                            .await
                            .expect("flooding client's handshake");
                    let q = conn.quinn().clone();
                    for i in 0..64u64 {
                        let open = tokio::time::timeout(Duration::from_millis(50), q.open_bi());
                        let Ok(Ok((mut send, recv))) = open.await else {
                            break;
                        };
                        let (off, size) = recs[i as usize % recs.len()];
                        let req = LodRequest {
                            id: i,
                            offset: off,
                            size,
                        };
                        send.write_all(&req.encode_frame().unwrap()).await.unwrap();
                        send.finish().unwrap();
                        streams.push((send, recv));
                        opened += 1;
                    }
                    conns.push(conn);
                    tokio::time::sleep(HANDSHAKE_PACE).await;
                }
                while ctl.go().await {
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
                let text = scrape_addr(metrics_addr).await;
                let in_flight = metric(&text, "planet_requests_in_flight", &[]) as usize;
                let n = conns.len();
                for c in &conns {
                    c.close();
                }
                drop(streams);
                (n, opened, in_flight)
            }
        })
        .await;
        eprintln!(
            "hostile[never reads]: {conns} connections, {opened} unread requests, \
             {in_flight} in flight on the server at the end"
        );
        assert!(
            in_flight <= conns * max_in_flight + GOOD_PARALLEL,
            "{in_flight}"
        );
        wait_active(&fx.h, 1, Duration::from_secs(5)).await;
        let text = wait_metrics(&fx.h, |t| {
            metric(t, "planet_requests_in_flight", &[]) == 0.0
        })
        .await;
        assert_eq!(metric(&text, "planet_requests_in_flight", &[]), 0.0);
        assert_healthy(&fx).await;
        fx.h.shutdown().await;
    });
}

#[test]
fn thousands_of_connections_opened_and_dropped() {
    let _g = serial();
    runtime().block_on(async {
        let fx = fixture(|c| c.idle_timeout_ms = 1500).await;
        const TOTAL: u64 = 2000;
        let fp = fx.h.cert_fingerprint().to_string();
        let addr = fx.h.local_addr();
        let done = Arc::new(AtomicU64::new(0));
        let done2 = Arc::clone(&done);
        let started = Instant::now();
        let n = under_attack(&fx, "connection churn", move |ctl| {
            let (fp, done) = (fp.clone(), Arc::clone(&done2));
            async move {
                let tls = planet_session::tls::pinned(&fp).unwrap();
                let crypto =
                    quinn::crypto::rustls::QuicClientConfig::try_from(tls.clone()).unwrap();
                let client_cfg = quinn::ClientConfig::new(Arc::new(crypto));
                let mut ep = quinn::Endpoint::client("127.0.0.1:0".parse().unwrap()).unwrap();
                ep.set_default_client_config(client_cfg);
                // Keep churning during the measurement, then until TOTAL.
                let mut set = tokio::task::JoinSet::new();
                let mut i = 0u64;
                while !ctl.stopped() || done.load(Ordering::Relaxed) < TOTAL {
                    if !ctl.stopped() && !ctl.go().await {
                        continue;
                    }
                    // While the good client measures: paced churn (HANDSHAKE_PACE,
                    // one at a time); then as fast as 16 at a
                    // time allow, up to TOTAL.
                    let measuring = !ctl.stopped();
                    while set.len() >= if measuring { 1 } else { 16 } {
                        set.join_next().await.unwrap().unwrap();
                    }
                    let ep = ep.clone();
                    let tls = tls.clone();
                    let done = Arc::clone(&done);
                    let kind = i % 4;
                    set.spawn(async move {
                        match kind {
                            // Handshake, no hello, then drop (quinn sends
                            // an implicit close).
                            0 | 1 => {
                                let c = ep.connect(addr, "localhost").unwrap().await.unwrap();
                                drop(c);
                            }
                            // A full session, then close.
                            2 => {
                                let (c, _) = Connection::connect(addr, "localhost", tls, acme())
                                    .await
                                    .unwrap();
                                c.close();
                            }
                            // Hello sent, then the connection is dropped.
                            _ => {
                                let c = ep.connect(addr, "localhost").unwrap().await.unwrap();
                                let (mut s, _r) = c.open_bi().await.unwrap();
                                s.write_all(&acme().encode_frame().unwrap()).await.unwrap();
                                drop(c);
                            }
                        }
                        done.fetch_add(1, Ordering::Relaxed);
                    });
                    i += 1;
                    let pause = if measuring {
                        HANDSHAKE_PACE
                    } else {
                        Duration::from_millis(1)
                    };
                    tokio::time::sleep(pause).await;
                }
                while let Some(r) = set.join_next().await {
                    r.unwrap();
                }
                ep.wait_idle().await;
                done.load(Ordering::Relaxed)
            }
        })
        .await;
        let secs = started.elapsed().as_secs_f64();
        eprintln!("hostile[connection churn]: {n} connections opened and dropped in {secs:.1} s");
        assert!(n >= TOTAL);
        // Every connection is accounted for: only the good client remains.
        wait_active(&fx.h, 1, Duration::from_secs(10)).await;
        assert_healthy(&fx).await;
        fx.h.shutdown().await;
    });
}

#[test]
fn a_flooding_tenant_is_held_to_its_connection_and_request_limits() {
    // Tenant `other` floods: 4 clients, each with its whole in-flight
    // budget busy, unpaced; refused clients retry after 1 s (a client's
    // reconnect backoff: unpaced handshakes are a CPU DoS of their own,
    // docs/SECURITY.md). Its limits (2 sessions, 200 requests/s) keep it
    // from taking the server from `acme`, whose good client must keep 90 %
    // of its throughput.
    let _g = serial();
    runtime().block_on(async {
        let fx = fixture(|c| {
            c.tenants[1].max_connections = 2;
            c.tenants[1].max_requests_per_second = 200;
        })
        .await;
        let fp = fx.h.cert_fingerprint().to_string();
        let addr = fx.h.local_addr();
        let mars = Arc::new(fx.mars_recs.clone());
        let started = Instant::now();
        let (served, refused) = under_attack(&fx, "tenant flood", move |ctl| {
            let (fp, mars) = (fp.clone(), Arc::clone(&mars));
            async move {
                let tls = planet_session::tls::pinned(&fp).unwrap();
                let served = Arc::new(AtomicU64::new(0));
                let refused = Arc::new(AtomicU64::new(0));
                let mut clients = Vec::new();
                for c in 0..4u64 {
                    let (tls, mars, ctl) = (tls.clone(), Arc::clone(&mars), ctl.clone());
                    let (served, refused) = (Arc::clone(&served), Arc::clone(&refused));
                    clients.push(tokio::spawn(async move {
                        while ctl.go().await {
                            let hello = Hello::new("other", "t0ken", "mars");
                            let conn = match Connection::connect(addr, "localhost", tls.clone(), hello).await {
                                Ok((conn, _)) => conn,
                                Err(NetError::Rejected(e)) => {
                                    assert_eq!(e.code, ErrorCode::ServerBusy);
                                    refused.fetch_add(1, Ordering::Relaxed);
                                    tokio::time::sleep(Duration::from_secs(1)).await;
                                    continue;
                                }
                                Err(e) => panic!("{e:?}"),
                            };
                            let mut id = c << 40;
                            while ctl.go().await {
                                let mut batch = Vec::new();
                                for _ in 0..4 {
                                    let (off, size) = mars[id as usize % mars.len()];
                                    batch.push(conn.spawn_fetch(id, off, size));
                                    id += 1;
                                }
                                for f in batch {
                                    match f.join().await {
                                        Ok(_) => {
                                            served.fetch_add(1, Ordering::Relaxed);
                                        }
                                        Err(NetError::Server(e)) => {
                                            assert_eq!(e.code, ErrorCode::RateLimited)
                                        }
                                        Err(e) => panic!("{e:?}"),
                                    }
                                }
                            }
                            conn.close();
                        }
                    }));
                }
                for c in clients {
                    c.await.unwrap();
                }
                (served.load(Ordering::Relaxed), refused.load(Ordering::Relaxed))
            }
        })
        .await;
        let elapsed = started.elapsed().as_secs_f64();
        eprintln!(
            "hostile[tenant flood]: {served} records served to the flooder in {elapsed:.1} s (limit 200/s), {refused} sessions refused"
        );
        assert!(refused > 0, "the tenant connection cap never applied");
        // The last attempt's flood ran for at most `elapsed`; one second of
        // burst is allowed.
        assert!((served as f64) <= 200.0 * (elapsed + 1.0), "{served} in {elapsed:.1} s");
        let text = scrape(&fx.h).await;
        assert!(metric(&text, "planet_handshakes_total", &[("outcome", "busy")]) >= 1.0);
        assert_healthy(&fx).await;
        fx.h.shutdown().await;
    });
}
