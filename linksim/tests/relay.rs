//! End-to-end tests of the relay with real UDP sockets on loopback.

use std::collections::HashSet;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use planet_linksim::{Link, LinkConfig, PER_PACKET_OVERHEAD};
use tokio::net::UdpSocket;
use tokio::task::JoinHandle;
use tokio::time::{sleep, timeout};

async fn bind() -> UdpSocket {
    UdpSocket::bind("127.0.0.1:0").await.expect("bind")
}

/// Echoes every datagram back to its sender; records the senders.
async fn echo_server() -> (SocketAddr, Arc<Mutex<HashSet<SocketAddr>>>, JoinHandle<()>) {
    let sock = bind().await;
    let addr = sock.local_addr().expect("addr");
    let peers = Arc::new(Mutex::new(HashSet::new()));
    let p = peers.clone();
    let task = tokio::spawn(async move {
        let mut buf = vec![0u8; 65_536];
        while let Ok((n, from)) = sock.recv_from(&mut buf).await {
            p.lock().expect("lock").insert(from);
            let _ = sock.send_to(&buf[..n], from).await;
        }
    });
    (addr, peers, task)
}

#[derive(Debug, Clone, Copy)]
struct Arrival {
    at: Instant,
    seq: u32,
    len: usize,
}

/// Records every datagram (first 4 bytes = big-endian sequence number).
async fn sink_server() -> (SocketAddr, Arc<Mutex<Vec<Arrival>>>, JoinHandle<()>) {
    let sock = bind().await;
    let addr = sock.local_addr().expect("addr");
    let log = Arc::new(Mutex::new(Vec::new()));
    let l = log.clone();
    let task = tokio::spawn(async move {
        let mut buf = vec![0u8; 65_536];
        while let Ok((n, _)) = sock.recv_from(&mut buf).await {
            let seq = buf
                .get(..4)
                .and_then(|b| b.try_into().ok())
                .map_or(u32::MAX, u32::from_be_bytes);
            l.lock().expect("lock").push(Arrival {
                at: Instant::now(),
                seq,
                len: n,
            });
        }
    });
    (addr, log, task)
}

fn packet(seq: u32, len: usize) -> Vec<u8> {
    let mut p = vec![0xAB; len.max(4)];
    p[..4].copy_from_slice(&seq.to_be_bytes());
    p
}

/// Sends `count` numbered packets of `len` bytes to `to`, `per_ms` at a time
/// with a 1 ms sleep in between (no catch-up bursts after a late wake-up), so
/// no socket buffer on loopback overflows.
async fn send_numbered(sock: &UdpSocket, to: SocketAddr, count: u32, len: usize, per_ms: u32) {
    let mut sent = 0u32;
    while sent < count {
        for _ in 0..per_ms.min(count - sent) {
            sock.send_to(&packet(sent, len), to).await.expect("send");
            sent += 1;
        }
        sleep(Duration::from_millis(1)).await;
    }
}

/// Round trip of one datagram, or None on timeout.
async fn ping(
    sock: &UdpSocket,
    to: SocketAddr,
    payload: &[u8],
    wait: Duration,
) -> Option<Duration> {
    let t0 = Instant::now();
    sock.send_to(payload, to).await.expect("send");
    let mut buf = [0u8; 2048];
    loop {
        let (n, _) = timeout(wait.saturating_sub(t0.elapsed()), sock.recv_from(&mut buf))
            .await
            .ok()?
            .expect("recv");
        if &buf[..n] == payload {
            return Some(t0.elapsed());
        }
    }
}

fn seqs(log: &Arc<Mutex<Vec<Arrival>>>) -> Vec<u32> {
    log.lock().expect("lock").iter().map(|a| a.seq).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn throughput_matches_8_mbit() {
    let (server, log, _srv) = sink_server().await;
    let link = Link::start(server, LinkConfig::mbit(8.0, 0), LinkConfig::loopback())
        .await
        .expect("start");
    let client = bind().await;
    // Offer 12 Mbit/s of 1200-byte datagrams for 1.5 s (1250 packets/s).
    let len = 1200usize;
    let offered_bps = 12e6;
    let pkts_per_s = offered_bps / (len as f64 * 8.0);
    let start = Instant::now();
    let mut sent = 0u32;
    while start.elapsed() < Duration::from_millis(1500) {
        let due = (start.elapsed().as_secs_f64() * pkts_per_s) as u32 + 1;
        while sent < due {
            client
                .send_to(&packet(sent, len), link.local_addr())
                .await
                .expect("send");
            sent += 1;
        }
        sleep(Duration::from_millis(1)).await;
    }
    sleep(Duration::from_millis(200)).await;

    let arrivals = log.lock().expect("lock").clone();
    assert!(arrivals.len() > 500, "only {} arrivals", arrivals.len());
    // Rate over the arrivals after the first (which starts the clock).
    let first = arrivals[0].at;
    let last = arrivals[arrivals.len() - 1].at;
    let wire_bytes: usize = arrivals[1..]
        .iter()
        .map(|a| a.len + PER_PACKET_OVERHEAD)
        .sum();
    let rate = wire_bytes as f64 * 8.0 / (last - first).as_secs_f64();
    assert!(
        (rate - 8e6).abs() < 0.15 * 8e6,
        "measured {:.2} Mbit/s through an 8 Mbit/s link",
        rate / 1e6
    );
    let stats = link.stats();
    assert!(
        stats.packets_dropped_queue > 0,
        "overdriven link must drop: {stats:?}"
    );
    assert_eq!(stats.packets_up as usize, arrivals.len());
    assert_eq!(stats.packets_dropped_loss, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_share_the_bottleneck() {
    let (server, log, _srv) = sink_server().await;
    let link = Link::start(server, LinkConfig::mbit(4.0, 0), LinkConfig::loopback())
        .await
        .expect("start");
    let to = link.local_addr();
    // Two clients each offering up to ~19 Mbit/s (2 x 1200 B per ms) for ~0.5 s.
    let run = || async move {
        let c = bind().await;
        send_numbered(&c, to, 1000, 1200, 2).await;
    };
    tokio::join!(run(), run());
    sleep(Duration::from_millis(200)).await;
    let arrivals = log.lock().expect("lock").clone();
    let first = arrivals[0].at;
    let last = arrivals[arrivals.len() - 1].at;
    let wire_bytes: usize = arrivals[1..]
        .iter()
        .map(|a| a.len + PER_PACKET_OVERHEAD)
        .sum();
    let rate = wire_bytes as f64 * 8.0 / (last - first).as_secs_f64();
    assert!(
        (rate - 4e6).abs() < 0.15 * 4e6,
        "two clients together got {:.2} Mbit/s through a shared 4 Mbit/s link",
        rate / 1e6
    );
    assert!(link.stats().packets_dropped_queue > 0);
    assert_eq!(link.clients(), 2);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delay_gives_round_trip_time() {
    let (server, _, _srv) = echo_server().await;
    let cfg = LinkConfig::new(None, Duration::from_millis(50));
    let link = Link::start(server, cfg.clone(), cfg).await.expect("start");
    let client = bind().await;
    let mut rtts = Vec::new();
    for i in 0..8u8 {
        let rtt = ping(&client, link.local_addr(), &[i; 32], Duration::from_secs(1))
            .await
            .expect("reply");
        rtts.push(rtt);
    }
    rtts.sort();
    assert!(rtts[0] >= Duration::from_millis(100), "{rtts:?}");
    assert!(
        rtts[rtts.len() / 2] <= Duration::from_millis(115),
        "{rtts:?}"
    );

    // Changing the configuration at run time takes effect.
    link.set_up(LinkConfig::loopback());
    link.set_down(LinkConfig::new(None, Duration::from_millis(10)));
    let mut best = Duration::MAX;
    for _ in 0..3 {
        let rtt = ping(&client, link.local_addr(), b"after", Duration::from_secs(1))
            .await
            .expect("reply");
        assert!(rtt >= Duration::from_millis(10), "{rtt:?}");
        best = best.min(rtt);
    }
    assert!(best < Duration::from_millis(40), "{best:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn loss_drops_expected_fraction() {
    let (server, log, _srv) = sink_server().await;
    let up = LinkConfig::loopback().with_loss(0.1).with_seed(1);
    let link = Link::start(server, up, LinkConfig::loopback())
        .await
        .expect("start");
    let client = bind().await;
    let n = 5000u32;
    send_numbered(&client, link.local_addr(), n, 100, 50).await;
    sleep(Duration::from_millis(200)).await;
    let stats = link.stats();
    let received = log.lock().expect("lock").len() as u64;
    // Binomial(5000, 0.1): mean 500, sd 21.2; allow about 4.7 sd.
    assert!(
        (400..=600).contains(&stats.packets_dropped_loss),
        "dropped {} of {n}",
        stats.packets_dropped_loss
    );
    assert_eq!(
        stats.packets_dropped_loss + stats.packets_up,
        u64::from(n),
        "{stats:?}"
    );
    assert_eq!(received, stats.packets_up);
    assert_eq!(stats.bytes_up, stats.packets_up * 100);
    assert_eq!(stats.packets_dropped_queue, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn same_seed_same_drop_pattern() {
    async fn pattern(seed: u64) -> Vec<u32> {
        let (server, log, _srv) = sink_server().await;
        let up = LinkConfig::loopback().with_loss(0.3).with_seed(seed);
        let link = Link::start(server, up, LinkConfig::loopback())
            .await
            .expect("start");
        let client = bind().await;
        send_numbered(&client, link.local_addr(), 1000, 64, 50).await;
        sleep(Duration::from_millis(100)).await;
        assert_eq!(
            link.stats().packets_forwarded + link.stats().packets_dropped_loss,
            1000
        );
        let mut s = seqs(&log);
        s.sort();
        s
    }
    let a = pattern(42).await;
    let b = pattern(42).await;
    let c = pattern(43).await;
    assert!(a.len() > 600 && a.len() < 800, "{}", a.len());
    assert_eq!(a, b, "same seed must drop the same packets");
    assert_ne!(a, c, "different seeds should differ");
}

fn inversions(s: &[u32]) -> usize {
    let mut max = None;
    let mut n = 0;
    for &x in s {
        match max {
            Some(m) if x < m => n += 1,
            _ => max = Some(x),
        }
    }
    n
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reorder_produces_out_of_order_arrivals() {
    for (p, expect_reorder) in [(0.1, true), (0.0, false)] {
        let (server, log, _srv) = sink_server().await;
        let up = LinkConfig::loopback().with_reorder(p).with_seed(5);
        let link = Link::start(server, up, LinkConfig::loopback())
            .await
            .expect("start");
        let client = bind().await;
        send_numbered(&client, link.local_addr(), 2000, 200, 20).await;
        sleep(Duration::from_millis(100)).await;
        let s = seqs(&log);
        assert_eq!(s.len(), 2000, "nothing may be lost");
        let inv = inversions(&s);
        if expect_reorder {
            assert!(inv > 50, "reorder={p}: only {inv} out-of-order arrivals");
        } else {
            assert_eq!(inv, 0, "reorder=0 must keep order");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jitter_without_reorder_keeps_order() {
    let (server, log, _srv) = sink_server().await;
    let up =
        LinkConfig::new(None, Duration::from_millis(20)).with_jitter(Duration::from_millis(10));
    let link = Link::start(server, up, LinkConfig::loopback())
        .await
        .expect("start");
    let client = bind().await;
    send_numbered(&client, link.local_addr(), 1000, 100, 10).await;
    sleep(Duration::from_millis(150)).await;
    let s = seqs(&log);
    assert_eq!(s.len(), 1000);
    assert_eq!(inversions(&s), 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn blackhole_drops_everything_then_recovers() {
    let (server, _, _srv) = echo_server().await;
    let cfg = LinkConfig::new(None, Duration::from_millis(20));
    let link = Link::start(server, cfg.clone(), cfg).await.expect("start");
    let client = bind().await;
    let to = link.local_addr();
    assert!(ping(&client, to, b"before", Duration::from_secs(1))
        .await
        .is_some());

    // In flight when the link goes down: lost too.
    client.send_to(b"in-flight", to).await.expect("send");
    sleep(Duration::from_millis(5)).await;
    link.set_blackhole(true);
    assert!(link.blackhole());
    for i in 0..20u8 {
        client.send_to(&[i; 10], to).await.expect("send");
    }
    let mut buf = [0u8; 64];
    let got = timeout(Duration::from_millis(300), client.recv_from(&mut buf)).await;
    assert!(
        got.is_err(),
        "nothing may come back through a blackholed link"
    );
    let stats = link.stats();
    assert_eq!(stats.packets_dropped_blackhole, 21, "{stats:?}");

    link.set_blackhole(false);
    let rtt = ping(&client, to, b"after", Duration::from_secs(1)).await;
    assert!(rtt.is_some(), "link must recover");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn multiple_clients_get_their_own_replies() {
    let (server, peers, _srv) = echo_server().await;
    let cfg = LinkConfig::new(None, Duration::from_millis(10));
    let link = Link::start(server, cfg.clone(), cfg).await.expect("start");
    let a = bind().await;
    let b = bind().await;
    let to = link.local_addr();
    let (ra, rb) = tokio::join!(
        ping(&a, to, b"from a", Duration::from_secs(1)),
        ping(&b, to, b"from b", Duration::from_secs(1)),
    );
    assert!(ra.is_some() && rb.is_some());
    // And no cross-talk: each socket only ever sees its own echo.
    for _ in 0..5 {
        assert!(ping(&a, to, b"a again", Duration::from_secs(1))
            .await
            .is_some());
        assert!(ping(&b, to, b"b again", Duration::from_secs(1))
            .await
            .is_some());
    }
    let mut buf = [0u8; 64];
    assert!(timeout(Duration::from_millis(50), a.recv_from(&mut buf))
        .await
        .is_err());
    assert_eq!(link.clients(), 2);
    assert_eq!(
        peers.lock().expect("lock").len(),
        2,
        "server sees two upstream addresses"
    );
    let stats = link.stats();
    assert_eq!(stats.packets_up, 12);
    assert_eq!(stats.packets_down, 12);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ignores_strangers_and_stops_on_shutdown() {
    let (server, peers, _srv) = echo_server().await;
    let link = Link::start(server, LinkConfig::loopback(), LinkConfig::loopback())
        .await
        .expect("start");
    let client = bind().await;
    let to = link.local_addr();
    assert!(ping(&client, to, b"hello", Duration::from_secs(1))
        .await
        .is_some());

    // A third party writing to the client's upstream socket is not relayed.
    let upstream = *peers.lock().expect("lock").iter().next().expect("one peer");
    let stranger = bind().await;
    stranger.send_to(b"spoof", upstream).await.expect("send");
    let mut buf = [0u8; 64];
    assert!(
        timeout(Duration::from_millis(100), client.recv_from(&mut buf))
            .await
            .is_err()
    );
    assert_eq!(link.stats().packets_down, 1);

    link.shutdown();
    sleep(Duration::from_millis(20)).await;
    assert!(ping(&client, to, b"gone", Duration::from_millis(200))
        .await
        .is_none());
    drop(link);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn parsed_config_drives_a_link() {
    let (server, _, _srv) = echo_server().await;
    let cfg: LinkConfig = "1mbit,30ms,0%loss".parse().expect("parse");
    let link = Link::start_symmetric(server, cfg).await.expect("start");
    let client = bind().await;
    // 1000-byte datagram: 8.2 ms serialisation each way + 60 ms propagation.
    // The least of three pings: the link never delivers early, while a busy
    // machine may deliver any one of them late.
    let payload = vec![7u8; 1000];
    let mut best = Duration::MAX;
    for _ in 0..3 {
        let rtt = ping(&client, link.local_addr(), &payload, Duration::from_secs(1))
            .await
            .expect("reply");
        assert!(rtt >= Duration::from_millis(76), "{rtt:?} < 76 ms");
        best = best.min(rtt);
    }
    assert!(best < Duration::from_millis(130), "{best:?}");
}

#[test]
fn link_is_send_and_sync() {
    fn check<T: Send + Sync + 'static>() {}
    check::<Link>();
    check::<LinkConfig>();
    check::<planet_linksim::LinkStats>();
    check::<planet_linksim::ParseLinkConfigError>();
}
