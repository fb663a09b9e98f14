//! `planet-bench server`: request throughput and latency of planet-server
//! against Debian's nginx serving the same file over HTTPS byte ranges.
//!
//! 1. Enumerate every record of the database (`planet_preprocess::db::scan`)
//!    and draw a seeded request list with a flight-like size mix: mostly
//!    elevation records, some colour (`--elevation-share`), levels drawn
//!    uniformly (a flight refines every level around the camera, so shallow
//!    levels are requested about as often as deep ones).
//! 2. QUIC: start planet-server (a subprocess by default, so its CPU time is
//!    its own), open `--clients` connections, each running `--concurrency`
//!    sequential request loops over the shared list (request `i` of the run
//!    is `list[i % len]`); per-request latency from opening the stream to
//!    the last body byte.
//! 3. nginx (`--nginx`): write a config under a temporary prefix (TLS 1.3,
//!    self-signed certificate, `sendfile on`, keep-alive), start
//!    `/usr/sbin/nginx`, and replay **the same list** as
//!    `Range: bytes=off-(off+size-1)` GETs: HTTP/1.1 with `--concurrency`
//!    keep-alive connections per client (as browsers do), and HTTP/2 with one
//!    connection per client and `--concurrency` streams (the same shape as
//!    QUIC). Prints the QUIC/nginx ratios, then stops nginx.
//!
//! Connections are set up before the timed window; the figures are the
//! steady-state request loop only. Client and server share the machine.

use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use planet_core::format::Tree;
use planet_protocol::Hello;
use planet_session::net::{ConnectOptions, Connection};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Where the server under test runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ServerMode {
    /// `planet-server` as a child process (its CPU and memory are measured).
    Subprocess,
    /// `planet_server::Server` on its own runtime in this process (no
    /// separate CPU accounting; used by the smoke tests).
    InProcess,
}

/// Which nginx protocol(s) to replay against.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum HttpMode {
    /// HTTP/1.1, `--concurrency` keep-alive connections per client.
    H1,
    /// HTTP/2, one connection per client, `--concurrency` streams.
    H2,
    /// Both, one after the other.
    Both,
}

/// `planet-bench server` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct ServerArgs {
    /// Database file (default: build the default procedural planet to
    /// /tmp/planet-bench-default.planetdb if missing).
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// Concurrent client connections.
    #[arg(long, default_value_t = 200)]
    pub clients: usize,
    /// Concurrent requests per client.
    #[arg(long, default_value_t = 4)]
    pub concurrency: usize,
    /// Length of each timed run in seconds (ignored with --requests).
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// Run exactly this many requests per side instead of a timed run.
    #[arg(long)]
    pub requests: Option<usize>,
    /// Also replay the requests against nginx over HTTPS.
    #[arg(long)]
    pub nginx: bool,
    /// nginx protocol(s).
    #[arg(long, value_enum, default_value = "both")]
    pub http: HttpMode,
    /// nginx binary.
    #[arg(long, default_value = "/usr/sbin/nginx")]
    pub nginx_bin: PathBuf,
    /// nginx worker processes (default: the number of CPUs, like the
    /// server's runtime).
    #[arg(long)]
    pub nginx_workers: Option<usize>,
    /// Seed of the request list.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Share of elevation records in the request mix (the rest colour).
    #[arg(long, default_value_t = 0.75)]
    pub elevation_share: f64,
    /// Length of the request list (replayed cyclically).
    #[arg(long, default_value_t = 100_000)]
    pub list_len: usize,
    /// How the server runs.
    #[arg(long, value_enum, default_value = "subprocess")]
    pub server: ServerMode,
    /// planet-server binary (default: next to this executable).
    #[arg(long)]
    pub server_bin: Option<PathBuf>,
    /// Worker threads of the client runtime (default: the number of CPUs).
    #[arg(long)]
    pub client_threads: Option<usize>,
    /// `planet-server --worker-threads` (default: its own, one per CPU).
    #[arg(long)]
    pub server_threads: Option<usize>,
    /// Client QUIC endpoints (UDP sockets) shared by the connections,
    /// round-robin; 0 = one endpoint per connection (the pre-2026-11-22
    /// behaviour, and what independent clients on separate hosts do).
    /// Default 4 (since 2026-11-22 15:00): with one socket for 200
    /// connections, the closed loop's opening burst (800 responses at once,
    /// in 16 kB datagrams with `--client-max-udp-payload 16384`) overflowed
    /// its receive buffer (capped at 2 × `net.core.rmem_max`), and the
    /// losses cost up to 1.5 s of probe timeouts.
    #[arg(long, default_value_t = 4)]
    pub client_endpoints: usize,
    /// Largest UDP payload the client endpoints accept (quinn's
    /// `max_udp_payload_size` transport parameter; default: the client's
    /// own, 16384 for a loopback server), also passed to the server as
    /// `--max-udp-payload` (its path-MTU discovery ceiling, default 1452).
    /// 16384 gives 16 kB datagrams on loopback (MTU 65536), the counterpart
    /// of kernel TCP's 64 kB loopback segments.
    #[arg(long)]
    pub client_max_udp_payload: Option<u16>,
    /// Open-loop mode: offered load in requests/s over all clients
    /// (comma-separated list: one run per rate, each side). Requests are
    /// issued on a precomputed schedule whatever the responses do, and
    /// latency counts from the *scheduled* send time, so a stalled server is
    /// not hidden by fewer requests (no coordinated omission). Without
    /// `--rate` the run is closed-loop (throughput).
    #[arg(long, value_delimiter = ',')]
    pub rate: Vec<f64>,
    /// Arrival process of the open-loop schedule.
    #[arg(long, value_enum, default_value = "poisson")]
    pub arrivals: Arrivals,
    /// Open-loop mode: seconds of untimed warm-up at the first `--rate`
    /// before the timed runs, on each side (0: none). Opening all the
    /// connections at once inflates their RTT estimates (hundreds of
    /// handshakes queue on two cores: 20–50 ms, up to 200 ms), and quinn
    /// paces each connection's first responses at that RTT until enough
    /// acknowledgements have corrected it (docs/BENCHMARKS.md, "The
    /// open-loop tail was the connection storm"). The warm-up is printed,
    /// not counted.
    #[arg(long, default_value_t = 5.0)]
    pub warmup: f64,
}

/// Arrival process of an open-loop run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Arrivals {
    /// Seeded Poisson process (exponential gaps), each request to a
    /// uniformly drawn client: the superposition of independent clients.
    Poisson,
    /// Evenly spaced arrivals, clients in turn.
    Uniform,
}

impl Default for ServerArgs {
    fn default() -> Self {
        ServerArgs {
            db: None,
            clients: 200,
            concurrency: 4,
            seconds: 20.0,
            requests: None,
            nginx: false,
            http: HttpMode::Both,
            nginx_bin: "/usr/sbin/nginx".into(),
            nginx_workers: None,
            seed: 1,
            elevation_share: 0.75,
            list_len: 100_000,
            server: ServerMode::Subprocess,
            server_bin: None,
            client_threads: None,
            server_threads: None,
            client_endpoints: 4,
            client_max_udp_payload: None,
            rate: vec![],
            arrivals: Arrivals::Poisson,
            warmup: 5.0,
        }
    }
}

// ---------------------------------------------------------------- shared helpers

/// The default database: the default procedural planet, built once.
pub fn default_db() -> Result<PathBuf> {
    let path = std::env::temp_dir().join("planet-bench-default.planetdb");
    if path.is_file() {
        return Ok(path);
    }
    eprintln!(
        "building the default procedural planet to {}",
        path.display()
    );
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    planet_preprocess::build_procedural(&planet_preprocess::default_procedural_options(), &tmp)
        .map_err(|e| anyhow!("building the default database: {e}"))?;
    std::fs::rename(&tmp, &path)?;
    Ok(path)
}

/// Resolve `--db` or build the default database.
pub fn resolve_db(db: &Option<PathBuf>) -> Result<PathBuf> {
    match db {
        Some(p) => {
            if !p.is_file() {
                bail!("database {} not found", p.display());
            }
            Ok(p.clone())
        }
        None => default_db(),
    }
}

/// Database name the single-database server derives from the path.
pub fn db_name(path: &Path) -> Result<String> {
    path.file_stem()
        .and_then(|s| s.to_str())
        .map(str::to_string)
        .context("database path has no file stem")
}

/// Latency figures in microseconds.
#[derive(Debug, Clone, Copy, Default)]
pub struct Latency {
    /// Median.
    pub p50: u32,
    /// 90th percentile.
    pub p90: u32,
    /// 99th percentile.
    pub p99: u32,
    /// Maximum.
    pub max: u32,
    /// Mean.
    pub mean: f64,
}

/// Percentiles of `v` (sorted in place).
pub fn latency(v: &mut [u32]) -> Latency {
    if v.is_empty() {
        return Latency::default();
    }
    v.sort_unstable();
    let at = |q: f64| v[((q * v.len() as f64) as usize).min(v.len() - 1)];
    Latency {
        p50: at(0.50),
        p90: at(0.90),
        p99: at(0.99),
        max: v[v.len() - 1],
        mean: v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64,
    }
}

/// Formats microseconds as milliseconds.
pub fn ms(us: u32) -> String {
    format!("{:.2} ms", us as f64 / 1000.0)
}

fn clk_tck() -> f64 {
    // SAFETY: sysconf has no preconditions.
    let t = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    if t > 0 {
        t as f64
    } else {
        100.0
    }
}

/// CPU seconds (user + system) used so far by process `pid`.
pub fn proc_cpu_seconds(pid: u32) -> Option<f64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name, which is in parentheses.
    let rest = &s[s.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    // rest starts at field 3 (state): utime is field 14, stime field 15.
    let utime: f64 = f.get(11)?.parse().ok()?;
    let stime: f64 = f.get(12)?.parse().ok()?;
    Some((utime + stime) / clk_tck())
}

fn proc_ppid(pid: u32) -> Option<u32> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let rest = &s[s.rfind(')')? + 2..];
    rest.split_whitespace().nth(1)?.parse().ok()
}

/// Resident memory of `pid`: (VmRSS, RssAnon) in bytes.
pub fn proc_rss(pid: u32) -> Option<(u64, u64)> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| -> Option<u64> {
        let line = s.lines().find(|l| l.starts_with(name))?;
        let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
        Some(kb * 1024)
    };
    Some((field("VmRSS:")?, field("RssAnon:").unwrap_or(0)))
}

/// `pid` and its direct children (e.g. an nginx master and its workers).
pub fn process_tree(pid: u32) -> Vec<u32> {
    let mut out = vec![pid];
    if let Ok(rd) = std::fs::read_dir("/proc") {
        for e in rd.flatten() {
            if let Some(p) = e.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) {
                if proc_ppid(p) == Some(pid) {
                    out.push(p);
                }
            }
        }
    }
    out
}

/// Sum of CPU seconds of `pids`.
pub fn cpu_seconds_of(pids: &[u32]) -> f64 {
    pids.iter().filter_map(|&p| proc_cpu_seconds(p)).sum()
}

/// Load average line (`/proc/loadavg`), recorded next to every figure.
pub fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "?".into())
}

/// Raise the soft open-file limit to the hard limit.
pub fn raise_nofile_limit() -> u64 {
    // SAFETY: plain getrlimit/setrlimit on a local struct.
    unsafe {
        let mut r = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut r) != 0 {
            return 0;
        }
        if r.rlim_cur < r.rlim_max {
            let want = libc::rlimit {
                rlim_cur: r.rlim_max,
                rlim_max: r.rlim_max,
            };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &want) == 0 {
                return want.rlim_cur;
            }
        }
        r.rlim_cur
    }
}

/// The planet-server under test.
pub struct ServerUnderTest {
    /// QUIC address.
    pub addr: SocketAddr,
    /// Certificate fingerprint (hex SHA-256) to pin.
    pub fingerprint: String,
    /// Database name.
    pub database: String,
    child: Option<Child>,
    in_process: Option<(tokio::runtime::Runtime, planet_server::ServerHandle)>,
}

impl ServerUnderTest {
    /// Start the server on `db` (127.0.0.1, ephemeral port).
    pub fn start(mode: ServerMode, db: &Path, server_bin: Option<&Path>) -> Result<Self> {
        Self::start_with(mode, db, server_bin, None, None)
    }

    /// [`ServerUnderTest::start`] with a path-MTU discovery ceiling
    /// (`--max-udp-payload`) and worker threads (`--worker-threads`, for a
    /// subprocess only); the server's defaults when `None`.
    pub fn start_with(
        mode: ServerMode,
        db: &Path,
        server_bin: Option<&Path>,
        max_udp_payload: Option<u16>,
        server_threads: Option<usize>,
    ) -> Result<Self> {
        let database = db_name(db)?;
        match mode {
            ServerMode::Subprocess => {
                let bin = match server_bin {
                    Some(b) => b.to_path_buf(),
                    None => default_server_bin()?,
                };
                let mut child = Command::new(&bin)
                    .arg("--database")
                    .arg(db)
                    .args(["--listen", "127.0.0.1:0", "--dev-cert"])
                    // Every benchmark client comes from 127.0.0.1.
                    .args(["--max-connections-per-address", "1000000"])
                    .args(
                        max_udp_payload
                            .map(|m| vec!["--max-udp-payload".to_string(), m.to_string()])
                            .unwrap_or_default(),
                    )
                    .args(
                        server_threads
                            .map(|n| vec!["--worker-threads".to_string(), n.to_string()])
                            .unwrap_or_default(),
                    )
                    .env(
                        "RUST_LOG",
                        std::env::var("PLANET_BENCH_SERVER_LOG").unwrap_or_else(|_| "warn".into()),
                    )
                    .stdin(Stdio::null())
                    .stdout(Stdio::piped())
                    .stderr(Stdio::inherit())
                    .spawn()
                    .with_context(|| format!("cannot start {}", bin.display()))?;
                let stdout = child.stdout.take().context("no stdout")?;
                let (tx, rx) = std::sync::mpsc::channel();
                std::thread::spawn(move || {
                    use std::io::BufRead;
                    for line in std::io::BufReader::new(stdout).lines() {
                        let Ok(line) = line else { break };
                        if tx.send(line).is_err() {
                            // Keep draining so the server never blocks on stdout.
                        }
                    }
                });
                let mut fingerprint = None;
                let mut addr = None;
                let deadline = Instant::now() + Duration::from_secs(30);
                while addr.is_none() || fingerprint.is_none() {
                    let left = deadline.saturating_duration_since(Instant::now());
                    let line = match rx.recv_timeout(left) {
                        Ok(l) => l,
                        Err(_) => {
                            let _ = child.kill();
                            bail!(
                                "{} did not print its address and fingerprint",
                                bin.display()
                            );
                        }
                    };
                    if let Some(f) = line.strip_prefix("cert-sha256 ") {
                        fingerprint = Some(f.trim().to_string());
                    } else if let Some(a) = line.strip_prefix("listening ") {
                        addr = Some(a.trim().parse::<SocketAddr>()?);
                    }
                }
                Ok(ServerUnderTest {
                    addr: addr.unwrap_or_else(|| unreachable!()),
                    fingerprint: fingerprint.unwrap_or_default(),
                    database,
                    child: Some(child),
                    in_process: None,
                })
            }
            ServerMode::InProcess => {
                let rt = tokio::runtime::Builder::new_multi_thread()
                    .worker_threads(2)
                    .thread_name("bench-server")
                    .enable_all()
                    .build()?;
                let mut cfg =
                    planet_server::ServerConfig::single_database(db, "127.0.0.1:0".parse()?, "")?;
                if let Some(m) = max_udp_payload {
                    cfg.max_udp_payload = m;
                }
                // Every benchmark client comes from 127.0.0.1.
                cfg.max_connections_per_address = 1_000_000;
                let handle = rt.block_on(planet_server::Server::start(cfg))?;
                Ok(ServerUnderTest {
                    addr: handle.local_addr(),
                    fingerprint: handle.cert_fingerprint().to_string(),
                    database,
                    child: None,
                    in_process: Some((rt, handle)),
                })
            }
        }
    }

    /// The server's pid when it is a subprocess.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(|c| c.id())
    }

    /// The hello for this server's database.
    pub fn hello(&self) -> Hello {
        Hello::new("public", "", self.database.clone())
    }

    /// Stop the server (SIGTERM, then kill after 5 s).
    pub fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            // SAFETY: signalling our own child by pid.
            unsafe {
                libc::kill(c.id() as libc::pid_t, libc::SIGTERM);
            }
            let deadline = Instant::now() + Duration::from_secs(5);
            loop {
                match c.try_wait() {
                    Ok(Some(_)) => break,
                    Ok(None) if Instant::now() < deadline => {
                        std::thread::sleep(Duration::from_millis(20))
                    }
                    _ => {
                        let _ = c.kill();
                        let _ = c.wait();
                        break;
                    }
                }
            }
        }
        if let Some((rt, h)) = self.in_process.take() {
            rt.block_on(h.shutdown());
        }
    }
}

impl Drop for ServerUnderTest {
    fn drop(&mut self) {
        self.stop();
    }
}

/// `planet-server` next to the current executable (target/release when run
/// from target/release/planet-bench).
pub fn default_server_bin() -> Result<PathBuf> {
    let exe = std::env::current_exe()?;
    let mut dirs = vec![];
    if let Some(d) = exe.parent() {
        dirs.push(d.to_path_buf());
        if let Some(p) = d.parent() {
            dirs.push(p.to_path_buf()); // target/debug/deps -> target/debug
        }
    }
    for d in dirs {
        let c = d.join("planet-server");
        if c.is_file() {
            return Ok(c);
        }
    }
    bail!(
        "planet-server binary not found next to {}: run `cargo build --release -p planet-server` \
         or pass --server-bin (or --server in-process)",
        exe.display()
    )
}

/// QUIC connection options for benchmarks: the client's defaults with a
/// longer connect timeout (hundreds of handshakes at once on 2 cores).
pub fn bench_connect_options() -> ConnectOptions {
    ConnectOptions {
        connect_timeout: Duration::from_secs(30),
        ..ConnectOptions::default()
    }
}

/// Open `n` connections, at most `parallel` handshakes at a time, each on
/// its own client endpoint (UDP socket).
pub async fn connect_many(
    srv_addr: SocketAddr,
    fingerprint: &str,
    hello: &Hello,
    n: usize,
    parallel: usize,
) -> Result<Vec<Connection>> {
    connect_many_on(srv_addr, fingerprint, hello, n, parallel, 0).await
}

/// Open `n` connections, at most `parallel` handshakes at a time, spread
/// round-robin over `endpoints` shared client endpoints (0: one endpoint per
/// connection).
pub async fn connect_many_on(
    srv_addr: SocketAddr,
    fingerprint: &str,
    hello: &Hello,
    n: usize,
    parallel: usize,
    endpoints: usize,
) -> Result<Vec<Connection>> {
    connect_many_on_with(srv_addr, fingerprint, hello, n, parallel, endpoints, None).await
}

/// [`connect_many_on`] with endpoints that accept UDP payloads up to
/// `max_udp_payload` (the client's default when `None`).
pub async fn connect_many_on_with(
    srv_addr: SocketAddr,
    fingerprint: &str,
    hello: &Hello,
    n: usize,
    parallel: usize,
    endpoints: usize,
    max_udp_payload: Option<u16>,
) -> Result<Vec<Connection>> {
    let tls = planet_session::tls::pinned(fingerprint)?;
    let eps = (0..endpoints.min(n))
        .map(|_| bench_endpoint(srv_addr, max_udp_payload))
        .collect::<Result<Vec<_>>>()?;
    let sem = Arc::new(tokio::sync::Semaphore::new(parallel.max(1)));
    let mut set = tokio::task::JoinSet::new();
    for i in 0..n {
        let tls = tls.clone();
        let hello = hello.clone();
        let sem = sem.clone();
        let ep = (!eps.is_empty()).then(|| eps[i % eps.len()].clone());
        set.spawn(async move {
            let _permit = sem.acquire_owned().await;
            let opts = ConnectOptions {
                max_udp_payload,
                ..bench_connect_options()
            };
            let r = match ep {
                Some(ep) => {
                    Connection::connect_on(&ep, srv_addr, "localhost", tls, hello, &opts).await
                }
                None => Connection::connect_with(srv_addr, "localhost", tls, hello, &opts).await,
            }
            .map(|(c, _)| c);
            (i, r)
        });
    }
    let mut out: Vec<Option<Connection>> = (0..n).map(|_| None).collect();
    while let Some(r) = set.join_next().await {
        let (i, r) = r?;
        out[i] = Some(r.map_err(|e| anyhow!("connection {i}: {e}"))?);
    }
    Ok(out.into_iter().flatten().collect())
}

/// A client endpoint for the bench: `planet_session::net::new_endpoint_with`.
fn bench_endpoint(peer: SocketAddr, max_udp_payload: Option<u16>) -> Result<quinn::Endpoint> {
    Ok(planet_session::net::new_endpoint_with(
        peer,
        max_udp_payload,
    )?)
}

// ---------------------------------------------------------------- request list

/// One request: a record's file range.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Req {
    /// File offset.
    pub offset: u64,
    /// Size in bytes.
    pub size: u32,
}

/// What the request list holds.
#[derive(Debug, Clone)]
pub struct RequestList {
    /// The requests, replayed cyclically.
    pub reqs: Vec<Req>,
    /// Records in the database (elevation, colour).
    pub records: (usize, usize),
    /// Mean request size.
    pub mean_size: f64,
    /// Elevation share actually drawn.
    pub elevation_share: f64,
}

/// Every record of `db` and a seeded request list of `len` entries:
/// `elevation_share` elevation records, the rest colour, each tree's level
/// drawn uniformly and the record uniformly within its level.
pub fn request_list(db: &Path, len: usize, seed: u64, elevation_share: f64) -> Result<RequestList> {
    let (_, recs) =
        planet_preprocess::db::scan(db).map_err(|e| anyhow!("scan {}: {e}", db.display()))?;
    // by_level[tree][level] = records
    let mut by_level: [Vec<Vec<Req>>; 2] = [vec![], vec![]];
    for r in &recs {
        let t = match r.tree {
            Tree::Elevation => 0,
            Tree::Colour => 1,
        };
        let l = r.block.level as usize;
        if by_level[t].len() <= l {
            by_level[t].resize(l + 1, vec![]);
        }
        by_level[t][l].push(Req {
            offset: r.offset,
            size: r.size,
        });
    }
    for t in &mut by_level {
        t.retain(|l| !l.is_empty());
    }
    let counts = (
        by_level[0].iter().map(Vec::len).sum::<usize>(),
        by_level[1].iter().map(Vec::len).sum::<usize>(),
    );
    if counts.0 + counts.1 == 0 {
        bail!("{} has no records", db.display());
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut reqs = Vec::with_capacity(len);
    let mut elev = 0usize;
    for _ in 0..len.max(1) {
        let mut t = if rng.random::<f64>() < elevation_share {
            0
        } else {
            1
        };
        if by_level[t].is_empty() {
            t = 1 - t;
        }
        if t == 0 {
            elev += 1;
        }
        let levels = &by_level[t];
        let level = &levels[rng.random_range(0..levels.len())];
        reqs.push(level[rng.random_range(0..level.len())]);
    }
    let mean_size = reqs.iter().map(|r| r.size as f64).sum::<f64>() / reqs.len() as f64;
    let n = reqs.len();
    Ok(RequestList {
        reqs,
        records: counts,
        mean_size,
        elevation_share: elev as f64 / n as f64,
    })
}

// ---------------------------------------------------------------- runs

/// Results of one side.
#[derive(Debug, Clone, Default)]
pub struct RunResult {
    /// Label.
    pub label: String,
    /// Completed requests.
    pub requests: u64,
    /// Body bytes received.
    pub bytes: u64,
    /// Failed requests.
    pub errors: u64,
    /// First error seen.
    pub first_error: Option<String>,
    /// Timed window (first request to last response).
    pub wall: Duration,
    /// Latency.
    pub latency: Latency,
    /// Server CPU seconds in the window (None when not measurable).
    pub server_cpu: Option<f64>,
    /// Connections used.
    pub connections: usize,
    /// CPU seconds of the bench process (the clients) in the window.
    pub client_cpu: f64,
    /// Open-loop runs: the offered load (requests/s).
    pub offered: Option<f64>,
    /// Open-loop runs: how late the client started requests against their
    /// schedule (client-side overhead, included in `latency`).
    pub lag: Option<Latency>,
    /// QUIC runs: datagrams of the window, from the client connections'
    /// quinn statistics.
    pub udp: Option<UdpCounts>,
    /// An open-loop warm-up (`--warmup`): printed, not compared.
    pub warmup: bool,
}

/// UDP datagram counts of the client's QUIC connections over a window.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UdpCounts {
    /// Datagrams received (server to client).
    pub rx_datagrams: u64,
    /// Bytes received in them (UDP payload).
    pub rx_bytes: u64,
    /// Datagrams sent (client to server).
    pub tx_datagrams: u64,
    /// Packets of the client's own that were declared lost (the server's
    /// losses are not visible client-side).
    pub client_lost_packets: u64,
}

impl UdpCounts {
    /// Sums the statistics of `conns` now.
    pub fn of(conns: &[Connection]) -> UdpCounts {
        conns.iter().fold(UdpCounts::default(), |acc, c| {
            let s = c.quinn().stats();
            UdpCounts {
                rx_datagrams: acc.rx_datagrams + s.udp_rx.datagrams,
                rx_bytes: acc.rx_bytes + s.udp_rx.bytes,
                tx_datagrams: acc.tx_datagrams + s.udp_tx.datagrams,
                client_lost_packets: acc.client_lost_packets + s.path.lost_packets,
            }
        })
    }

    /// `self - before`, saturating.
    pub fn since(&self, before: &UdpCounts) -> UdpCounts {
        UdpCounts {
            rx_datagrams: self.rx_datagrams.saturating_sub(before.rx_datagrams),
            rx_bytes: self.rx_bytes.saturating_sub(before.rx_bytes),
            tx_datagrams: self.tx_datagrams.saturating_sub(before.tx_datagrams),
            client_lost_packets: self
                .client_lost_packets
                .saturating_sub(before.client_lost_packets),
        }
    }
}

impl RunResult {
    /// Requests per second.
    pub fn rps(&self) -> f64 {
        self.requests as f64 / self.wall.as_secs_f64().max(1e-9)
    }
    /// Megabytes (10^6) per second.
    pub fn mbps(&self) -> f64 {
        self.bytes as f64 / 1e6 / self.wall.as_secs_f64().max(1e-9)
    }
    fn print(&self) {
        let cpu = match self.server_cpu {
            Some(c) => format!(
                "{:.0} % of one core ({:.1} µs CPU/request)",
                100.0 * c / self.wall.as_secs_f64().max(1e-9),
                1e6 * c / self.requests.max(1) as f64
            ),
            None => "n/a (in-process)".into(),
        };
        let cpu = format!(
            "{cpu}, client CPU {:.1} µs/request",
            1e6 * self.client_cpu / self.requests.max(1) as f64
        );
        let offered = match self.offered {
            Some(r) => format!(" (offered {r:.0})"),
            None => String::new(),
        };
        println!(
            "{:<8} {:>5} conns  {:>9.0} req/s{}  {:>8.1} MB/s  p50 {}  p90 {}  p99 {}  max {}  errors {}  server CPU {}",
            self.label,
            self.connections,
            self.rps(),
            offered,
            self.mbps(),
            ms(self.latency.p50),
            ms(self.latency.p90),
            ms(self.latency.p99),
            ms(self.latency.max),
            self.errors,
            cpu
        );
        if let Some(l) = &self.lag {
            println!(
                "         client start lag vs schedule: p50 {}  p99 {}  max {}",
                ms(l.p50),
                ms(l.p99),
                ms(l.max)
            );
        }
        if let Some(u) = &self.udp {
            let n = self.requests.max(1) as f64;
            println!(
                "         UDP datagrams per request: {:.2} server->client (mean {:.0} B), {:.2} client->server; client packets lost {}",
                u.rx_datagrams as f64 / n,
                u.rx_bytes as f64 / u.rx_datagrams.max(1) as f64,
                u.tx_datagrams as f64 / n,
                u.client_lost_packets
            );
        }
        if let Some(e) = &self.first_error {
            println!("         first error: {e}");
        }
    }
}

#[derive(Default)]
struct LoopStats {
    lat_us: Vec<u32>,
    bytes: u64,
    errors: u64,
    first_error: Option<String>,
}

impl LoopStats {
    fn merge(&mut self, o: LoopStats) {
        self.lat_us.extend(o.lat_us);
        self.bytes += o.bytes;
        self.errors += o.errors;
        if self.first_error.is_none() {
            self.first_error = o.first_error;
        }
    }
    fn error(&mut self, e: String) {
        self.errors += 1;
        if self.first_error.is_none() {
            self.first_error = Some(e);
        }
    }
}

/// Shared request cursor: request `i` is `list[i % len]`; stops at `limit`
/// or at the deadline.
struct Cursor {
    list: Arc<Vec<Req>>,
    next: AtomicUsize,
    limit: usize,
    deadline: Instant,
}

impl Cursor {
    fn take(&self) -> Option<(usize, Req)> {
        if Instant::now() >= self.deadline {
            return None;
        }
        let i = self.next.fetch_add(1, Ordering::Relaxed);
        if i >= self.limit {
            return None;
        }
        Some((i, self.list[i % self.list.len()]))
    }
}

fn new_cursor(list: &Arc<Vec<Req>>, args: &ServerArgs, start: Instant) -> Arc<Cursor> {
    let (limit, deadline) = match args.requests {
        Some(n) => (n, start + Duration::from_secs(24 * 3600)),
        None => (usize::MAX, start + Duration::from_secs_f64(args.seconds)),
    };
    Arc::new(Cursor {
        list: list.clone(),
        next: AtomicUsize::new(0),
        limit,
        deadline,
    })
}

// ---------------------------------------------------------------- open loop

/// One scheduled request of an open-loop run: request `k` of the schedule
/// is `list[k % len]`, sent at `at` after the start by client `client`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arrival {
    /// Send time after the start of the run.
    pub at: Duration,
    /// Client (connection group) index.
    pub client: usize,
}

/// A seeded schedule of `n` arrivals at `rate` requests/s over `clients`.
pub fn schedule(
    rate: f64,
    n: usize,
    clients: usize,
    seed: u64,
    arrivals: Arrivals,
) -> Vec<Arrival> {
    let clients = clients.max(1);
    let rate = rate.max(1e-3);
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x005e_ed0f_a771_7a15);
    let mut t = 0.0f64;
    (0..n)
        .map(|k| match arrivals {
            Arrivals::Poisson => {
                // Exponential gap; 1 - u is in (0, 1] so ln is finite.
                let u: f64 = rng.random();
                t += -(1.0 - u).ln() / rate;
                Arrival {
                    at: Duration::from_secs_f64(t),
                    client: rng.random_range(0..clients),
                }
            }
            Arrivals::Uniform => Arrival {
                at: Duration::from_secs_f64(k as f64 / rate),
                client: k % clients,
            },
        })
        .collect()
}

type H1Send = hyper::client::conn::http1::SendRequest<http_body_util::Empty<bytes::Bytes>>;
type H2Send = hyper::client::conn::http2::SendRequest<http_body_util::Empty<bytes::Bytes>>;

/// How one client of an open-loop run sends.
enum Slot {
    /// One QUIC connection, one stream per request.
    Quic(Connection),
    /// A pool of HTTP/1.1 keep-alive connections, one request each at a time.
    H1(tokio::sync::Mutex<Vec<H1Send>>),
    /// One HTTP/2 connection, one stream per request.
    H2(H2Send),
}

/// One client: at most `--concurrency` requests outstanding (the same cap
/// for every protocol; a request that finds them all busy waits, and the
/// wait counts in its latency).
struct ClientSlot {
    sem: tokio::sync::Semaphore,
    slot: Slot,
}

async fn issue(c: &ClientSlot, k: usize, r: Req, uri: &str) -> Result<u64, String> {
    let _permit = c.sem.acquire().await.map_err(|e| e.to_string())?;
    let res = match &c.slot {
        Slot::Quic(conn) => Sender::Quic(conn.clone()).send(k, r, uri).await,
        Slot::H1(pool) => {
            let h = pool
                .lock()
                .await
                .pop()
                .ok_or_else(|| "no free HTTP/1.1 connection".to_string())?;
            let mut sender = Sender::H1(h);
            let res = sender.send(k, r, uri).await;
            if let Sender::H1(h) = sender {
                pool.lock().await.push(h);
            }
            res
        }
        Slot::H2(h) => Sender::H2(h.clone()).send(k, r, uri).await,
    };
    res.map_err(|e| e.msg)
}

fn us(d: Duration) -> u32 {
    d.as_micros().min(u32::MAX as u128) as u32
}

/// Replays `sched` on `slots`: a blocking thread sleeps until each send
/// time (`std::thread::sleep`, microsecond precision, unlike tokio's 1 ms
/// timer wheel) and spawns the request on the client runtime. Latency is
/// measured from the scheduled time.
#[allow(clippy::too_many_arguments)]
async fn open_loop(
    label: &str,
    slots: Arc<Vec<ClientSlot>>,
    list: &Arc<Vec<Req>>,
    sched: Arc<Vec<Arrival>>,
    rate: f64,
    uri: Arc<str>,
    pids: &[u32],
    connections: usize,
) -> Result<RunResult> {
    let handle = tokio::runtime::Handle::current();
    let cpu0 = cpu_seconds_of(pids);
    let self0 = proc_cpu_seconds(std::process::id()).unwrap_or(0.0);
    let start = Instant::now() + Duration::from_millis(50);
    let list = list.clone();
    let handles = tokio::task::spawn_blocking(move || {
        let mut hs = Vec::with_capacity(sched.len());
        for (k, a) in sched.iter().enumerate() {
            let due = start + a.at;
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
            let slots = slots.clone();
            let uri = uri.clone();
            let r = list[k % list.len()];
            let client = a.client % slots.len().max(1);
            hs.push(handle.spawn(async move {
                let lag = due.elapsed();
                let res = match slots.get(client) {
                    Some(c) => issue(c, k, r, &uri).await,
                    None => Err("no clients".to_string()),
                };
                (lag, due.elapsed(), res)
            }));
        }
        hs
    })
    .await?;
    let mut st = LoopStats::default();
    let mut lag = Vec::with_capacity(handles.len());
    for h in handles {
        let (l, t, res) = h.await?;
        lag.push(us(l));
        match res {
            Ok(n) => {
                st.lat_us.push(us(t));
                st.bytes += n;
            }
            Err(e) => st.error(e),
        }
    }
    let wall = start.elapsed();
    let cpu1 = cpu_seconds_of(pids);
    let client_cpu = proc_cpu_seconds(std::process::id()).unwrap_or(0.0) - self0;
    Ok(RunResult {
        label: label.into(),
        requests: st.lat_us.len() as u64,
        bytes: st.bytes,
        errors: st.errors,
        first_error: st.first_error,
        wall,
        latency: latency(&mut st.lat_us),
        server_cpu: (!pids.is_empty()).then_some(cpu1 - cpu0),
        connections,
        client_cpu,
        offered: Some(rate),
        lag: Some(latency(&mut lag)),
        udp: None,
        warmup: false,
    })
}

/// The open-loop schedules of a run: an optional untimed warm-up, then
/// one timed run per `--rate`.
#[derive(Default)]
pub struct Schedules {
    /// Replayed first, printed, not counted.
    pub warmup: Option<(f64, Arc<Vec<Arrival>>)>,
    /// The timed runs.
    pub runs: Vec<(f64, Arc<Vec<Arrival>>)>,
}

impl Schedules {
    fn is_empty(&self) -> bool {
        self.runs.is_empty()
    }
}

/// Replays the warm-up schedule of `scheds`, if any, on `slots`; prints
/// the result and returns it marked as a warm-up.
async fn warm_up(
    label: &str,
    slots: &Arc<Vec<ClientSlot>>,
    list: &Arc<Vec<Req>>,
    scheds: &Schedules,
    uri: &str,
    pids: &[u32],
    connections: usize,
) -> Result<Option<RunResult>> {
    let Some((rate, sched)) = &scheds.warmup else {
        return Ok(None);
    };
    let mut r = open_loop(
        label,
        slots.clone(),
        list,
        sched.clone(),
        *rate,
        uri.into(),
        pids,
        connections,
    )
    .await?;
    r.label = format!("{label} warm-up (not counted)");
    r.warmup = true;
    r.print();
    Ok(Some(r))
}

/// Smoothed RTT estimates of the client connections (quinn's, in ms):
/// p50, p90 and max.
fn rtt_estimates(conns: &[Connection]) -> String {
    let mut v: Vec<u32> = conns.iter().map(|c| us(c.quinn().rtt())).collect();
    if v.is_empty() {
        return "none".into();
    }
    let l = latency(&mut v);
    format!("p50 {} p90 {} max {}", ms(l.p50), ms(l.p90), ms(l.max))
}

async fn run_quic(
    srv: &ServerUnderTest,
    list: &Arc<Vec<Req>>,
    args: &ServerArgs,
    scheds: &Schedules,
) -> Result<Vec<RunResult>> {
    let conns = connect_many_on_with(
        srv.addr,
        &srv.fingerprint,
        &srv.hello(),
        args.clients,
        64,
        args.client_endpoints,
        args.client_max_udp_payload,
    )
    .await?;
    let pids: Vec<u32> = srv.pid().into_iter().collect();
    if !scheds.is_empty() {
        let conc = args.concurrency.max(1);
        let slots: Arc<Vec<ClientSlot>> = Arc::new(
            conns
                .iter()
                .map(|c| ClientSlot {
                    sem: tokio::sync::Semaphore::new(conc),
                    slot: Slot::Quic(c.clone()),
                })
                .collect(),
        );
        let mut out = vec![];
        println!(
            "QUIC client RTT estimates after connecting: {}",
            rtt_estimates(&conns)
        );
        if let Some(r) = warm_up("QUIC", &slots, list, scheds, "", &pids, conns.len()).await? {
            out.push(r);
            println!(
                "QUIC client RTT estimates after the warm-up: {}",
                rtt_estimates(&conns)
            );
        }
        for (rate, sched) in &scheds.runs {
            let udp0 = UdpCounts::of(&conns);
            let mut r = open_loop(
                "QUIC",
                slots.clone(),
                list,
                sched.clone(),
                *rate,
                "".into(),
                &pids,
                conns.len(),
            )
            .await?;
            if srv.pid().is_none() {
                r.server_cpu = None;
            }
            r.udp = Some(UdpCounts::of(&conns).since(&udp0));
            out.push(r);
        }
        for c in &conns {
            c.close();
        }
        return Ok(out);
    }
    let udp0 = UdpCounts::of(&conns);
    let loops = conns
        .iter()
        .flat_map(|c| (0..args.concurrency.max(1)).map(|_| Sender::Quic(c.clone())))
        .collect();
    let mut r = closed_loop("QUIC", loops, "".into(), list, args, &pids, conns.len()).await?;
    r.udp = Some(UdpCounts::of(&conns).since(&udp0));
    if srv.pid().is_none() {
        r.server_cpu = None;
    }
    for c in &conns {
        c.close();
    }
    Ok(vec![r])
}

// ---------------------------------------------------------------- nginx

/// A running nginx serving one file at `/db` over TLS.
pub struct Nginx {
    /// Its address.
    pub addr: SocketAddr,
    /// Certificate (DER) to trust.
    pub cert_der: Vec<u8>,
    child: Child,
    _prefix: tempfile::TempDir,
}

impl Nginx {
    /// Start `bin` serving `db` at `https://localhost:PORT/db`.
    pub fn start(bin: &Path, db: &Path, workers: usize) -> Result<Nginx> {
        let prefix = tempfile::Builder::new()
            .prefix("planet-bench-nginx")
            .tempdir()?;
        let p = prefix.path();
        std::fs::create_dir_all(p.join("www"))?;
        std::fs::create_dir_all(p.join("tmp"))?;
        let db = std::fs::canonicalize(db)?;
        std::os::unix::fs::symlink(&db, p.join("www/db"))?;
        let cert =
            rcgen::generate_simple_self_signed(vec!["localhost".into(), "127.0.0.1".into()])?;
        std::fs::write(p.join("cert.pem"), cert.cert.pem())?;
        std::fs::write(p.join("key.pem"), cert.signing_key.serialize_pem())?;
        let port = TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
        let addr: SocketAddr = ([127, 0, 0, 1], port).into();
        // Running as root, workers would switch to `nobody`; keep them as the
        // current user so they can read the file wherever it is.
        let user = if unsafe { libc::geteuid() } == 0 {
            "user root root;"
        } else {
            ""
        };
        let conf = format!(
            r#"# written by planet-bench server
{user}
daemon off;
master_process on;
worker_processes {workers};
worker_rlimit_nofile 65536;
error_log {p}/error.log warn;
pid {p}/nginx.pid;
events {{ worker_connections 16384; }}
http {{
    access_log off;
    default_type application/octet-stream;
    sendfile on;
    tcp_nopush on;
    tcp_nodelay on;
    keepalive_timeout 300s;
    keepalive_requests 100000000;
    http2_max_concurrent_streams 128;
    client_body_temp_path {p}/tmp/body;
    proxy_temp_path {p}/tmp/proxy;
    fastcgi_temp_path {p}/tmp/fastcgi;
    uwsgi_temp_path {p}/tmp/uwsgi;
    scgi_temp_path {p}/tmp/scgi;
    server {{
        listen 127.0.0.1:{port} ssl http2;
        server_name localhost;
        ssl_certificate {p}/cert.pem;
        ssl_certificate_key {p}/key.pem;
        ssl_protocols TLSv1.3;
        root {p}/www;
        disable_symlinks off;
        location / {{ }}
    }}
}}
"#,
            p = p.display()
        );
        std::fs::write(p.join("nginx.conf"), conf)?;
        let mut child = Command::new(bin)
            .arg("-p")
            .arg(p)
            .arg("-e")
            .arg(p.join("error.log"))
            .arg("-c")
            .arg(p.join("nginx.conf"))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .with_context(|| format!("cannot start {}", bin.display()))?;
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if std::net::TcpStream::connect(addr).is_ok() {
                break;
            }
            if let Ok(Some(st)) = child.try_wait() {
                let log = std::fs::read_to_string(p.join("error.log")).unwrap_or_default();
                bail!("nginx exited ({st}): {log}");
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                bail!("nginx did not listen on {addr}");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        Ok(Nginx {
            addr,
            cert_der: cert.cert.der().to_vec(),
            child,
            _prefix: prefix,
        })
    }

    /// nginx's pids (master and workers).
    pub fn pids(&self) -> Vec<u32> {
        process_tree(self.child.id())
    }
}

impl Drop for Nginx {
    fn drop(&mut self) {
        // SIGQUIT: graceful stop of master and workers.
        // SAFETY: signalling our own child by pid.
        unsafe {
            libc::kill(self.child.id() as libc::pid_t, libc::SIGQUIT);
        }
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        unsafe {
            libc::kill(self.child.id() as libc::pid_t, libc::SIGTERM);
        }
        let _ = self.child.wait();
    }
}

fn https_client_config(cert_der: &[u8], alpn: &[u8]) -> Result<Arc<rustls::ClientConfig>> {
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

type TlsStream = tokio_rustls::client::TlsStream<tokio::net::TcpStream>;

async fn tls_connect(addr: SocketAddr, tls: &tokio_rustls::TlsConnector) -> Result<TlsStream> {
    let tcp = tokio::net::TcpStream::connect(addr).await?;
    tcp.set_nodelay(true)?;
    let name = rustls::pki_types::ServerName::try_from("localhost")?;
    Ok(tls.connect(name, tcp).await?)
}

fn range_request(uri: &str, r: Req) -> Result<hyper::Request<http_body_util::Empty<bytes::Bytes>>> {
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

async fn check_response(
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

async fn run_nginx(
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
    let pids = ng.pids();
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

/// The closed loop (throughput): one task per entry of `loops`, each
/// sending its next request when the previous one has completed, until
/// the run's cursor runs out. Server CPU is that of `pids`, client CPU this
/// process's, both over the timed window.
async fn closed_loop(
    label: &str,
    loops: Vec<Sender>,
    uri: Arc<str>,
    list: &Arc<Vec<Req>>,
    args: &ServerArgs,
    pids: &[u32],
    connections: usize,
) -> Result<RunResult> {
    let cpu0 = cpu_seconds_of(pids);
    let self0 = proc_cpu_seconds(std::process::id()).unwrap_or(0.0);
    let start = Instant::now();
    let cursor = new_cursor(list, args, start);
    let mut set = tokio::task::JoinSet::new();
    for mut sender in loops {
        let cursor = cursor.clone();
        let uri = uri.clone();
        set.spawn(async move {
            let mut st = LoopStats::default();
            while let Some((i, r)) = cursor.take() {
                let t0 = Instant::now();
                match sender.send(i, r, &uri).await {
                    Ok(n) => {
                        st.lat_us.push(us(t0.elapsed()));
                        st.bytes += n;
                    }
                    Err(SendError { msg, fatal }) => {
                        st.error(msg);
                        if fatal {
                            break;
                        }
                    }
                }
            }
            st
        });
    }
    let mut all = LoopStats::default();
    while let Some(r) = set.join_next().await {
        all.merge(r?);
    }
    let wall = start.elapsed();
    let cpu1 = cpu_seconds_of(pids);
    let client_cpu = proc_cpu_seconds(std::process::id()).unwrap_or(0.0) - self0;
    Ok(RunResult {
        label: label.into(),
        requests: all.lat_us.len() as u64,
        bytes: all.bytes,
        errors: all.errors,
        first_error: all.first_error,
        wall,
        latency: latency(&mut all.lat_us),
        server_cpu: Some(cpu1 - cpu0),
        connections,
        client_cpu,
        offered: None,
        lag: None,
        udp: None,
        warmup: false,
    })
}

/// A failed request of a closed loop; `fatal` ends the loop (its
/// connection is unusable).
struct SendError {
    msg: String,
    fatal: bool,
}

impl SendError {
    fn of(e: impl ToString) -> SendError {
        SendError {
            msg: e.to_string(),
            fatal: false,
        }
    }
}

/// One closed-loop request sender: a QUIC connection (one stream per
/// request), an HTTP/1.1 keep-alive connection, or an HTTP/2 connection
/// (one stream per request).
enum Sender {
    Quic(Connection),
    H1(H1Send),
    H2(H2Send),
}

impl Sender {
    /// Sends request `i` (`r`) and returns the body length once the whole
    /// response has arrived and matched the request.
    async fn send(&mut self, i: usize, r: Req, uri: &str) -> Result<u64, SendError> {
        let resp = match self {
            Sender::Quic(c) => {
                let body = c
                    .fetch(i as u64, r.offset, r.size)
                    .await
                    .map_err(SendError::of)?;
                if body.len() != r.size as usize {
                    return Err(SendError::of(format!(
                        "short body {} of {}",
                        body.len(),
                        r.size
                    )));
                }
                return Ok(body.len() as u64);
            }
            Sender::H1(h) => {
                h.ready().await.map_err(|e| SendError {
                    msg: e.to_string(),
                    fatal: true,
                })?;
                h.send_request(range_request(uri, r).map_err(SendError::of)?)
                    .await
            }
            Sender::H2(h) => {
                h.send_request(range_request(uri, r).map_err(SendError::of)?)
                    .await
            }
        };
        check_response(resp.map_err(SendError::of)?, r)
            .await
            .map_err(SendError::of)
    }
}

/// What a `server` run measured.
#[derive(Debug, Clone)]
pub struct ServerReport {
    /// The QUIC side: one closed-loop run, or one run per `--rate`.
    pub quic: Vec<RunResult>,
    /// The nginx sides.
    pub nginx: Vec<RunResult>,
    /// The open-loop warm-ups of every side (already printed).
    pub warmups: Vec<RunResult>,
}

/// `planet-bench server`.
pub fn run(args: ServerArgs) -> Result<()> {
    let report = bench(&args)?;
    let mut failed = false;
    for n in report
        .quic
        .iter()
        .chain(&report.nginx)
        .chain(&report.warmups)
    {
        failed |= n.errors > 0;
    }
    if failed {
        bail!("requests failed (see the errors above)");
    }
    Ok(())
}

/// Runs the benchmark, prints and returns the figures.
pub fn bench(args: &ServerArgs) -> Result<ServerReport> {
    planet_session::tls::install_crypto_provider();
    let nofile = raise_nofile_limit();
    let db = resolve_db(&args.db)?;
    let list = request_list(&db, args.list_len, args.seed, args.elevation_share)?;
    let file_size = std::fs::metadata(&db)?.len();
    println!(
        "database {} ({:.1} MB, {} elevation + {} colour records); request list: {} entries, seed {}, \
         {:.0} % elevation, mean {:.1} kB",
        db.display(),
        file_size as f64 / 1e6,
        list.records.0,
        list.records.1,
        list.reqs.len(),
        args.seed,
        100.0 * list.elevation_share,
        list.mean_size / 1e3
    );
    let cpus = std::thread::available_parallelism().map_or(2, |n| n.get());
    println!(
        "{} clients x {} concurrent requests, {}; {} CPUs, load average {} (before), open files {}",
        args.clients,
        args.concurrency,
        match args.requests {
            Some(n) => format!("{n} requests per side"),
            None => format!("{} s per side", args.seconds),
        },
        cpus,
        loadavg(),
        nofile
    );
    let threads = args.client_threads.unwrap_or(cpus);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(threads.max(1))
        .thread_name("bench-client")
        .enable_all()
        .build()?;
    let reqs = Arc::new(list.reqs.clone());
    let runs = args
        .rate
        .iter()
        .map(|&rate| {
            let n = args
                .requests
                .unwrap_or((rate * args.seconds).round().max(1.0) as usize);
            let s = schedule(rate, n, args.clients, args.seed, args.arrivals);
            (rate, Arc::new(s))
        })
        .collect();
    let warmup = match args.rate.first() {
        Some(&rate) if args.warmup > 0.0 => {
            let n = (rate * args.warmup).round().max(1.0) as usize;
            // Other arrival times than the timed runs' (same request list).
            let s = schedule(rate, n, args.clients, !args.seed, args.arrivals);
            Some((rate, Arc::new(s)))
        }
        _ => None,
    };
    let scheds = Schedules { warmup, runs };
    if !scheds.is_empty() {
        println!(
            "open loop ({:?} arrivals, latency from the scheduled send time): rates {:?} req/s, \
             at most {} outstanding per client, {}",
            args.arrivals,
            args.rate,
            args.concurrency,
            match &scheds.warmup {
                Some((rate, _)) => format!("after {} s of warm-up at {rate} req/s", args.warmup),
                None => "no warm-up".into(),
            }
        );
    }
    println!(
        "client: {} runtime threads, QUIC connections on {}",
        threads.max(1),
        if args.client_endpoints == 0 {
            "one endpoint each".to_string()
        } else {
            format!("{} shared endpoint(s)", args.client_endpoints)
        }
    );

    let mut srv = ServerUnderTest::start_with(
        args.server,
        &db,
        args.server_bin.as_deref(),
        args.client_max_udp_payload,
        args.server_threads,
    )?;
    let mut warmups = vec![];
    let (warm, quic): (Vec<_>, Vec<_>) = rt
        .block_on(run_quic(&srv, &reqs, args, &scheds))?
        .into_iter()
        .partition(|r| r.warmup);
    warmups.extend(warm);
    srv.stop();
    for q in &quic {
        q.print();
    }

    let mut nginx = vec![];
    if args.nginx {
        let workers = args.nginx_workers.unwrap_or(cpus);
        let ng = Nginx::start(&args.nginx_bin, &db, workers)?;
        let modes: &[bool] = match args.http {
            HttpMode::H1 => &[false],
            HttpMode::H2 => &[true],
            HttpMode::Both => &[false, true],
        };
        for &h2 in modes {
            let rs = rt.block_on(run_nginx(&ng, &reqs, args, h2, &scheds))?;
            let (warm, rs): (Vec<_>, Vec<_>) = rs.into_iter().partition(|r| r.warmup);
            warmups.extend(warm);
            for r in rs {
                r.print();
                nginx.push(r);
            }
        }
        drop(ng);
        for n in &nginx {
            let Some(q) = quic.iter().find(|q| q.offered == n.offered) else {
                continue;
            };
            let at = match n.offered {
                Some(r) => format!(" at {r:.0} req/s offered"),
                None => String::new(),
            };
            println!(
                "QUIC / {}{at}: requests/s x{:.2}, MB/s x{:.2}, p50 x{:.2}, p99 x{:.2} (lower is better for latency)",
                n.label,
                q.rps() / n.rps().max(1e-9),
                q.mbps() / n.mbps().max(1e-9),
                q.latency.p50 as f64 / (n.latency.p50.max(1)) as f64,
                q.latency.p99 as f64 / (n.latency.p99.max(1)) as f64
            );
        }
    }
    println!("load average {} (after)", loadavg());
    rt.shutdown_timeout(Duration::from_secs(2));
    Ok(ServerReport {
        quic,
        nginx,
        warmups,
    })
}

#[cfg(test)]
pub(crate) mod tests_support {
    use std::path::PathBuf;

    /// A 3-level procedural database, built once per test binary.
    pub(crate) fn tiny_db() -> PathBuf {
        static DB: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
        DB.get_or_init(|| {
            let dir =
                std::env::temp_dir().join(format!("planet-bench-test-{}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            let path = dir.join("tiny.planetdb");
            let mut o = planet_preprocess::default_procedural_options();
            o.levels = 3;
            planet_preprocess::build_procedural(&o, &path).unwrap();
            path
        })
        .clone()
    }
}

#[cfg(test)]
mod tests {
    use super::tests_support::tiny_db;
    use super::*;

    #[test]
    fn request_list_is_seeded_and_valid() {
        let db = tiny_db();
        let a = request_list(&db, 1000, 7, 0.75).unwrap();
        let b = request_list(&db, 1000, 7, 0.75).unwrap();
        assert_eq!(a.reqs, b.reqs);
        assert!(a.records.0 > 0 && a.records.1 > 0);
        assert!((0.6..0.9).contains(&a.elevation_share));
        let bytes = std::fs::read(&db).unwrap();
        for r in a.reqs.iter().take(200) {
            let rec = &bytes[r.offset as usize..(r.offset + r.size as u64) as usize];
            planet_core::format::parse_record(rec, Some(bytes.len() as u64)).unwrap();
        }
    }

    #[test]
    fn percentiles() {
        let mut v: Vec<u32> = (1..=100).rev().collect();
        let l = latency(&mut v);
        assert_eq!((l.p50, l.p99, l.max), (51, 100, 100));
    }

    #[test]
    fn smoke_server_bench_tiny() {
        let args = ServerArgs {
            db: Some(tiny_db()),
            clients: 5,
            concurrency: 2,
            seconds: 2.0,
            list_len: 1000,
            server: ServerMode::InProcess,
            client_threads: Some(2),
            ..ServerArgs::default()
        };
        let r = bench(&args).unwrap();
        assert_eq!(r.quic.len(), 1);
        let q = &r.quic[0];
        assert_eq!(q.errors, 0, "{:?}", q.first_error);
        assert!(q.requests > 0 && q.bytes > 0);
        assert_eq!(q.connections, 5);
    }

    #[test]
    fn smoke_server_bench_open_loop() {
        let args = ServerArgs {
            db: Some(tiny_db()),
            clients: 4,
            concurrency: 2,
            seconds: 1.0,
            list_len: 500,
            server: ServerMode::InProcess,
            client_threads: Some(2),
            rate: vec![200.0, 400.0],
            warmup: 0.25,
            ..ServerArgs::default()
        };
        let r = bench(&args).unwrap();
        assert_eq!(r.quic.len(), 2);
        // 0.25 s of warm-up at the first rate, reported apart.
        assert_eq!(r.warmups.len(), 1);
        assert_eq!(
            (r.warmups[0].requests, r.warmups[0].offered),
            (50, Some(200.0))
        );
        for (q, want) in r.quic.iter().zip([200u64, 400]) {
            assert_eq!(q.errors, 0, "{:?}", q.first_error);
            assert_eq!(q.requests, want);
            assert!(q.lag.is_some());
        }
    }

    #[test]
    fn schedules_are_seeded_and_at_the_rate() {
        let a = schedule(1000.0, 20_000, 200, 3, Arrivals::Poisson);
        assert_eq!(a, schedule(1000.0, 20_000, 200, 3, Arrivals::Poisson));
        let span = a.last().unwrap().at.as_secs_f64();
        assert!((19.0..21.0).contains(&span), "{span}");
        assert!(a.windows(2).all(|w| w[0].at <= w[1].at));
        assert!(a.iter().all(|x| x.client < 200));
        let u = schedule(100.0, 300, 7, 3, Arrivals::Uniform);
        assert_eq!(u[150].at, Duration::from_secs_f64(1.5));
        assert_eq!(u[150].client, 150 % 7);
    }
}
