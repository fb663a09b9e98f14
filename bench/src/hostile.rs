//! `planet-bench hostile`: hostile clients of one kind at a time against one
//! planet-server (subprocess, loopback) while a good client streams
//! (ISSUE #17, "Must show"; the limits are in docs/SECURITY.md).
//!
//! Kinds, each `--clients` concurrent loops that start again as soon as the
//! server closes them (a refused connection waits 200 ms first, so that the
//! loops do not spin on the CPU the server and the good client share):
//! - `zero-window`: QUIC with a zero receive window, then a valid `Hello`;
//!   the server can never write the Welcome;
//! - `half-open`: QUIC handshake, then nothing (no control stream);
//! - `bad-token`: a `Hello` with a wrong token, its `Error` read.
//!
//! QUIC datagram stuffing is not a kind: the server does not offer
//! datagrams, so a client cannot send any (checked at start).
//!
//! Hostile loops bind 127.0.0.2, 127.0.0.3, ... (`--addresses`) so that the
//! per-address cap does not stop them alone; the good client is 127.0.0.1.
//! The good client reaches the server through a simulated link (`--link`,
//! default 50 Mbit/s and 20 ms each way; `none` for raw loopback) with 64
//! requests in flight; the hostile loops' threads run 10 nice levels below
//! it and the server (`--attacker-nice`), standing for other hosts.
//! Per kind: the good client's throughput (MB/s) alone and under attack,
//! fresh good connections' connect times (Welcome received, through the
//! link) under attack, the server's CPU (cores) alone and under attack, the server's RSS (VmRSS, sampled every
//! 200 ms) before and at its peak, the hostile connections the server held
//! at once (peak of `planet_connections_active` − 1, scraped; it includes
//! pending connections), and the pre-auth outcome counters. Memory per hostile
//! connection = (peak RSS − RSS before) / peak connections held.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, Command};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use planet_protocol::Hello;
use planet_session::net::Connection;

use crate::server::{
    bench_connect_options, default_server_bin, proc_cpu_seconds, proc_rss, raise_nofile_limit,
    request_list, resolve_db, spawn_server, Req,
};

/// `planet-bench hostile` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct HostileArgs {
    /// Database file (default: the default procedural planet).
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// planet-server binary (default: next to planet-bench).
    #[arg(long)]
    pub server_bin: Option<PathBuf>,
    /// Concurrent hostile loops per kind.
    #[arg(long, default_value_t = 1000)]
    pub clients: usize,
    /// Kinds to run, comma-separated: zero-window, half-open, bad-token.
    #[arg(long, default_value = "zero-window,half-open,bad-token")]
    pub kinds: String,
    /// The server's `max_connections`.
    #[arg(long, default_value_t = 200)]
    pub max_connections: usize,
    /// Seconds of each measurement (alone, then under attack).
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Hostile source addresses (127.0.0.2 onwards).
    #[arg(long, default_value_t = 32)]
    pub addresses: u8,
    /// Pause of each hostile loop between two attempts, ms (0: start again
    /// as soon as the server closed the previous connection).
    #[arg(long, default_value_t = 0)]
    pub pace_ms: u64,
    /// Added to the nice value of the hostile loops' threads (0–19). The
    /// attackers stand for other hosts: at 10 the server and the good client
    /// get the CPU they share with them first, so that the attackers' own
    /// TLS work is not counted against the server (the table shows the
    /// attack rate they still reach). 0 runs them at the same priority.
    #[arg(long, default_value_t = 10)]
    pub attacker_nice: i32,
    /// The good client's link to the server (planet-linksim spec, both
    /// directions), or `none` for raw loopback. A good client is a viewer
    /// on a network, not a process beside the server: through a link its
    /// throughput measures what the server still gives it, where on raw
    /// loopback 0.2 ms requests measure the scheduling noise of the 2 cores
    /// that the server, the good client and the attackers share.
    #[arg(long, default_value = "50mbit,20ms")]
    pub link: String,
    /// The good client's requests in flight (default: the server's default
    /// per-session limit, `max_in_flight`).
    #[arg(long, default_value_t = 64)]
    pub in_flight: usize,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// The server subprocess with its QUIC and metrics addresses.
struct Srv {
    child: Child,
    addr: SocketAddr,
    metrics: SocketAddr,
    fingerprint: String,
    database: String,
    _dir: tempfile::TempDir,
}

impl Drop for Srv {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        crate::children::unregister(self.child.id());
    }
}

fn start_server(args: &HostileArgs, db: &std::path::Path) -> Result<Srv> {
    let bin = match &args.server_bin {
        Some(b) => b.clone(),
        None => default_server_bin()?,
    };
    let database = crate::server::db_name(db)?;
    let dir = tempfile::tempdir()?;
    let cfg = dir.path().join("server.toml");
    // No cert/key: a generated certificate, development mode (empty token).
    std::fs::write(
        &cfg,
        format!(
            "listen = \"127.0.0.1:0\"\nmetrics = \"127.0.0.1:0\"\nmax_connections = {}\n\
             [[database]]\nname = \"{database}\"\npath = \"{}\"\n\
             [[tenant]]\nname = \"public\"\ntoken = \"\"\ndatabases = [\"{database}\"]\n",
            args.max_connections,
            db.display()
        ),
    )?;
    let mut cmd = Command::new(&bin);
    cmd.arg("--config").arg(&cfg);
    let s = spawn_server(cmd, &bin, "error", true)?;
    Ok(Srv {
        child: s.child,
        addr: s.addr,
        metrics: s.metrics.context("metrics address")?,
        fingerprint: s.fingerprint,
        database,
        _dir: dir,
    })
}

/// GET /metrics (HTTP/1.0, std TCP).
fn scrape(addr: SocketAddr) -> Result<String> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect_timeout(&addr, Duration::from_secs(5))?;
    s.set_read_timeout(Some(Duration::from_secs(5)))?;
    write!(s, "GET /metrics HTTP/1.0\r\nHost: x\r\n\r\n")?;
    let mut buf = String::new();
    s.read_to_string(&mut buf)?;
    Ok(buf)
}

/// Sum of the samples of `name` whose labels contain `label` (or all).
fn metric(text: &str, name: &str, label: Option<&str>) -> f64 {
    text.lines()
        .filter(|l| !l.starts_with('#'))
        .filter(|l| {
            l.starts_with(name) && matches!(l.as_bytes().get(name.len()), Some(b'{') | Some(b' '))
        })
        .filter(|l| label.is_none_or(|x| l.contains(x)))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    ZeroWindow,
    HalfOpen,
    BadToken,
}

impl Kind {
    fn parse(s: &str) -> Result<Kind> {
        Ok(match s.trim() {
            "zero-window" => Kind::ZeroWindow,
            "half-open" => Kind::HalfOpen,
            "bad-token" => Kind::BadToken,
            other => bail!("unknown kind {other:?}"),
        })
    }

    fn name(self) -> &'static str {
        match self {
            Kind::ZeroWindow => "zero-window",
            Kind::HalfOpen => "half-open",
            Kind::BadToken => "bad-token",
        }
    }
}

fn hostile_endpoint(ip: &str, fingerprint: &str, zero_window: bool) -> Result<quinn::Endpoint> {
    let mut ep = quinn::Endpoint::client(format!("{ip}:0").parse()?)?;
    let tls = planet_session::tls::pinned(fingerprint)?;
    let crypto = quinn::crypto::rustls::QuicClientConfig::try_from(tls)
        .map_err(|e| anyhow!("client crypto: {e}"))?;
    let mut cfg = quinn::ClientConfig::new(Arc::new(crypto));
    let mut t = quinn::TransportConfig::default();
    if zero_window {
        t.stream_receive_window(quinn::VarInt::from_u32(0));
        t.receive_window(quinn::VarInt::from_u32(0));
    }
    cfg.transport_config(Arc::new(t));
    ep.set_default_client_config(cfg);
    Ok(ep)
}

/// One hostile loop until `stop`.
async fn hostile_loop(
    kind: Kind,
    ep: quinn::Endpoint,
    addr: SocketAddr,
    hello: Vec<u8>,
    stop: Arc<AtomicBool>,
    attempts: Arc<AtomicU64>,
    pace: Duration,
) {
    let mut first = true;
    while !stop.load(Ordering::Relaxed) {
        if !first && !pace.is_zero() {
            tokio::time::sleep(pace).await;
        }
        first = false;
        attempts.fetch_add(1, Ordering::Relaxed);
        let Ok(connecting) = ep.connect(addr, "localhost") else {
            tokio::time::sleep(Duration::from_millis(200)).await;
            continue;
        };
        let conn = match connecting.await {
            Ok(c) => c,
            Err(_) => {
                tokio::time::sleep(Duration::from_millis(200)).await;
                continue;
            }
        };
        // Held until the connection ends (dropping the send side would
        // finish the control stream).
        let mut _held = None;
        if kind != Kind::HalfOpen {
            if let Ok((mut s, mut r)) = conn.open_bi().await {
                let _ = s.write_all(&hello).await;
                if kind == Kind::BadToken {
                    let _ = r.read_to_end(1 << 16).await;
                }
                _held = Some((s, r));
            }
        }
        tokio::select! {
            _ = conn.closed() => {}
            _ = async { while !stop.load(Ordering::Relaxed) { tokio::time::sleep(Duration::from_millis(50)).await } } => {
                conn.close(0u32.into(), b"");
            }
        }
    }
}

/// Fetches `reqs` cyclically with `in_flight` requests in flight for
/// `secs`: (records/s, MB/s).
async fn good_run(
    conn: &Connection,
    reqs: &Arc<Vec<Req>>,
    secs: f64,
    in_flight: usize,
) -> Result<(f64, f64)> {
    let next = Arc::new(AtomicU64::new(0));
    let done = Arc::new(AtomicU64::new(0));
    let bytes = Arc::new(AtomicU64::new(0));
    let until = Instant::now() + Duration::from_secs_f64(secs);
    let start = Instant::now();
    let mut workers = Vec::new();
    for _ in 0..in_flight.max(1) {
        let (conn, reqs, next, done, bytes) = (
            conn.clone(),
            reqs.clone(),
            next.clone(),
            done.clone(),
            bytes.clone(),
        );
        workers.push(tokio::spawn(async move {
            while Instant::now() < until {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let r = reqs[i as usize % reqs.len()];
                let got = conn
                    .fetch(i + 1, r.offset, r.size)
                    .await
                    .map_err(|e| anyhow!("good client: {e}"))?;
                done.fetch_add(1, Ordering::Relaxed);
                bytes.fetch_add(got.len() as u64, Ordering::Relaxed);
            }
            Ok::<(), anyhow::Error>(())
        }));
    }
    for w in workers {
        w.await??;
    }
    let secs = start.elapsed().as_secs_f64();
    Ok((
        done.load(Ordering::Relaxed) as f64 / secs,
        bytes.load(Ordering::Relaxed) as f64 / 1e6 / secs,
    ))
}

/// Results of one kind.
#[derive(Debug, Clone, serde::Serialize)]
struct KindResult {
    kind: String,
    clients: usize,
    hostile_attempts: u64,
    hostile_attempts_per_s: f64,
    peak_hostile_connections: f64,
    server_cores_alone: f64,
    server_cores_under_attack: f64,
    connect_ms_median: f64,
    connect_ms_max: f64,
    connect_failures: usize,
    link: String,
    baseline_records_per_s: f64,
    attack_records_per_s: f64,
    baseline_mb_per_s: f64,
    attack_mb_per_s: f64,
    ratio: f64,
    rss_before_mb: f64,
    rss_peak_mb: f64,
    rss_after_mb: f64,
    kb_per_hostile_connection: f64,
    handshakes_timeout: f64,
    handshakes_unauthorized: f64,
    handshakes_rate_limited: f64,
    connections_refused: f64,
    connections_retry: f64,
    connections_rejected: f64,
}

/// Runs the benchmark.
pub fn run(args: HostileArgs) -> Result<()> {
    raise_nofile_limit();
    let kinds = args
        .kinds
        .split(',')
        .map(Kind::parse)
        .collect::<Result<Vec<_>>>()?;
    let db = resolve_db(&args.db)?;
    let srv = start_server(&args, &db)?;
    let pid = srv.child.id();
    let reqs = Arc::new(request_list(&db, 10_000, 17, 0.5)?.reqs);
    let good_rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let nice = args.attacker_nice.clamp(0, 19);
    let bad_rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        // Linux nice values are per thread.
        .on_thread_start(move || {
            let _ = rustix::process::nice(nice);
        })
        .enable_all()
        .build()?;
    // The good client's way to the server.
    let link = match args.link.trim() {
        "none" => None,
        spec => {
            let cfg: planet_linksim::LinkConfig =
                spec.parse().map_err(|e| anyhow!("--link {spec:?}: {e}"))?;
            Some(good_rt.block_on(planet_linksim::Link::start_symmetric(srv.addr, cfg))?)
        }
    };
    let good_addr = link.as_ref().map_or(srv.addr, |l| l.local_addr());
    println!(
        "good client: {} in flight, link {}",
        args.in_flight,
        link.as_ref()
            .map_or("none (loopback)".to_string(), |_| args.link.clone())
    );
    let hello = Hello::new("public", "", srv.database.clone());
    let tls = planet_session::tls::pinned(&srv.fingerprint)?;
    let opts = bench_connect_options();
    // Datagrams: the server must not offer them.
    let datagrams = good_rt.block_on(async {
        let ep = hostile_endpoint("127.0.0.1", &srv.fingerprint, false)?;
        let c = ep.connect(srv.addr, "localhost")?.await?;
        let offered = c.max_datagram_size();
        c.close(0u32.into(), b"");
        Ok::<_, anyhow::Error>(offered)
    })?;
    println!(
        "QUIC datagrams offered by the server: {}",
        datagrams.map_or("no".to_string(), |n| format!("yes, up to {n} bytes"))
    );
    let mut results = Vec::new();
    for kind in kinds {
        let (good, _) = good_rt.block_on(Connection::connect_with(
            good_addr,
            "localhost",
            tls.clone(),
            hello.clone(),
            &opts,
        ))?;
        std::thread::sleep(Duration::from_millis(500));
        let before = scrape(srv.metrics)?;
        let rss_before = proc_rss(pid).map_or(0, |r| r.0);
        let cpu0 = proc_cpu_seconds(pid).unwrap_or(0.0);
        let t0 = Instant::now();
        let baseline = good_rt.block_on(good_run(&good, &reqs, args.seconds, args.in_flight))?;
        let cores_alone =
            (proc_cpu_seconds(pid).unwrap_or(0.0) - cpu0) / t0.elapsed().as_secs_f64();

        // The attack.
        let stop = Arc::new(AtomicBool::new(false));
        let attempts = Arc::new(AtomicU64::new(0));
        let hostile_hello = match kind {
            Kind::BadToken => Hello::new("public", "wrong", srv.database.clone()),
            _ => hello.clone(),
        }
        .encode_frame()?;
        let entered = bad_rt.enter();
        let endpoints = (0..args.addresses.max(1))
            .map(|i| {
                hostile_endpoint(
                    &format!("127.0.0.{}", 2 + u16::from(i)),
                    &srv.fingerprint,
                    kind == Kind::ZeroWindow,
                )
            })
            .collect::<Result<Vec<_>>>()?;
        drop(entered);
        let mut loops = Vec::new();
        for i in 0..args.clients {
            loops.push(bad_rt.spawn(hostile_loop(
                kind,
                endpoints[i % endpoints.len()].clone(),
                srv.addr,
                hostile_hello.clone(),
                stop.clone(),
                attempts.clone(),
                Duration::from_millis(args.pace_ms),
            )));
        }
        // Sample RSS and the connections held while the attack runs.
        let sampling = Arc::new(AtomicBool::new(true));
        let sampler = {
            let (sampling, metrics) = (sampling.clone(), srv.metrics);
            std::thread::spawn(move || {
                let (mut rss, mut held) = (0u64, 0f64);
                while sampling.load(Ordering::Relaxed) {
                    rss = rss.max(proc_rss(pid).map_or(0, |r| r.0));
                    if let Ok(t) = scrape(metrics) {
                        // Pending connections are counted in the active
                        // gauge too; the good client is the one left.
                        let h = metric(&t, "planet_connections_active", None) - 1.0;
                        held = held.max(h);
                    }
                    std::thread::sleep(Duration::from_millis(200));
                }
                (rss, held)
            })
        };
        std::thread::sleep(Duration::from_secs(2));
        let (cpu1, t1, attempts1) = (
            proc_cpu_seconds(pid).unwrap_or(0.0),
            Instant::now(),
            attempts.load(Ordering::Relaxed),
        );
        let under = good_rt.block_on(async {
            let run = good_run(&good, &reqs, args.seconds, args.in_flight);
            let connects = async {
                let mut times = Vec::new();
                let mut failures = 0;
                let until = Instant::now() + Duration::from_secs_f64(args.seconds);
                while Instant::now() < until {
                    let t0 = Instant::now();
                    match Connection::connect_with(
                        good_addr,
                        "localhost",
                        tls.clone(),
                        hello.clone(),
                        &opts,
                    )
                    .await
                    {
                        Ok((c, _)) => {
                            times.push(t0.elapsed().as_secs_f64() * 1e3);
                            c.close();
                        }
                        Err(_) => failures += 1,
                    }
                    tokio::time::sleep(Duration::from_millis(500)).await;
                }
                (times, failures)
            };
            let (r, c) = tokio::join!(run, connects);
            r.map(|r| (r, c))
        })?;
        let (attack_rate, (mut times, connect_failures)) = under;
        let attack_secs = t1.elapsed().as_secs_f64();
        let cores_attack = (proc_cpu_seconds(pid).unwrap_or(0.0) - cpu1) / attack_secs;
        let attempts_per_s = (attempts.load(Ordering::Relaxed) - attempts1) as f64 / attack_secs;
        stop.store(true, Ordering::Relaxed);
        sampling.store(false, Ordering::Relaxed);
        let (rss_peak, held) = sampler.join().map_err(|_| anyhow!("sampler panicked"))?;
        bad_rt.block_on(async {
            for l in loops {
                let _ = l.await;
            }
        });
        good.close();
        // Let the server drain what is left (handshake deadline 5 s).
        std::thread::sleep(Duration::from_secs(6));
        let rss_after = proc_rss(pid).map_or(0, |r| r.0);
        let after = scrape(srv.metrics)?;
        let delta = |name: &str, label: &str| {
            metric(&after, name, Some(label)) - metric(&before, name, Some(label))
        };
        times.sort_by(f64::total_cmp);
        let median = times.get(times.len() / 2).copied().unwrap_or(f64::NAN);
        let max = times.last().copied().unwrap_or(f64::NAN);
        let mb = |b: u64| b as f64 / 1e6;
        let r = KindResult {
            kind: kind.name().into(),
            clients: args.clients,
            hostile_attempts: attempts.load(Ordering::Relaxed),
            hostile_attempts_per_s: attempts_per_s,
            peak_hostile_connections: held,
            server_cores_alone: cores_alone,
            server_cores_under_attack: cores_attack,
            connect_ms_median: median,
            connect_ms_max: max,
            connect_failures,
            link: link
                .as_ref()
                .map_or("none".to_string(), |_| args.link.clone()),
            baseline_records_per_s: baseline.0,
            attack_records_per_s: attack_rate.0,
            baseline_mb_per_s: baseline.1,
            attack_mb_per_s: attack_rate.1,
            ratio: attack_rate.1 / baseline.1,
            rss_before_mb: mb(rss_before),
            rss_peak_mb: mb(rss_peak),
            rss_after_mb: mb(rss_after),
            kb_per_hostile_connection: (rss_peak.saturating_sub(rss_before)) as f64
                / 1e3
                / held.max(1.0),
            handshakes_timeout: delta("planet_handshakes_total", "outcome=\"timeout\""),
            handshakes_unauthorized: delta("planet_handshakes_total", "outcome=\"unauthorized\""),
            handshakes_rate_limited: delta("planet_handshakes_total", "outcome=\"rate_limited\""),
            connections_refused: delta("planet_connections_total", "outcome=\"refused\""),
            connections_retry: delta("planet_connections_total", "outcome=\"retry\""),
            connections_rejected: delta("planet_connections_total", "outcome=\"rejected\""),
        };
        eprintln!("{r:?}");
        results.push(r);
    }
    println!();
    println!(
        "| kind | hostile loops | attempts/s | held at once | good connect p50 / max (ms) | connect failures | alone (MB/s) | under attack (MB/s) | ratio | server cores alone / attacked | server RSS before / peak / after (MB) | kB per held connection | timeout | unauthorized | rate_limited | refused | retry | rejected |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for r in &results {
        println!(
            "| {} | {} | {:.0} | {:.0} | {:.1} / {:.1} | {} | {:.1} | {:.1} | {:.2} | {:.2} / {:.2} | {:.1} / {:.1} / {:.1} | {:.1} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} |",
            r.kind,
            r.clients,
            r.hostile_attempts_per_s,
            r.peak_hostile_connections,
            r.connect_ms_median,
            r.connect_ms_max,
            r.connect_failures,
            r.baseline_mb_per_s,
            r.attack_mb_per_s,
            r.ratio,
            r.server_cores_alone,
            r.server_cores_under_attack,
            r.rss_before_mb,
            r.rss_peak_mb,
            r.rss_after_mb,
            r.kb_per_hostile_connection,
            r.handshakes_timeout,
            r.handshakes_unauthorized,
            r.handshakes_rate_limited,
            r.connections_refused,
            r.connections_retry,
            r.connections_rejected,
        );
    }
    if let Some(p) = &args.json {
        std::fs::write(p, serde_json::to_string_pretty(&results)?)?;
    }
    Ok(())
}
