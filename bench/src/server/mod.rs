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

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
mod closed_loop;
mod nginx;
mod open_loop;
mod proc_stats;
mod report;
mod requests;
mod runs;
mod under_test;

pub(crate) use closed_loop::*;
pub use nginx::*;
pub use open_loop::*;
pub use proc_stats::*;
pub use report::*;
pub use requests::*;
pub use runs::*;
pub use under_test::*;

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

/// The default database: the default procedural planet, built once, and
/// again when the file there does not open (another format version).
pub fn default_db() -> Result<PathBuf> {
    let path = std::env::temp_dir().join("planet-bench-default.planetdb");
    match planet_core::format::DbFile::open(&path) {
        Ok(_) => return Ok(path),
        Err(e) if path.exists() => eprintln!(
            "{} does not open ({e}): rebuilding the default procedural planet",
            path.display()
        ),
        Err(_) => eprintln!(
            "building the default procedural planet to {}",
            path.display()
        ),
    }
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
    use std::time::Duration;

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
