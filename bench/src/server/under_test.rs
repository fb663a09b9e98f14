//! The planet-server under test (a subprocess or in process) and the
//! benchmark clients' connections to it.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use planet_protocol::Hello;
use planet_session::net::{ConnectOptions, Connection};

use super::*;

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
                let mut cmd = Command::new(&bin);
                cmd.arg("--database")
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
                    );
                let s = spawn_server(cmd, &bin, "warn", false)?;
                Ok(ServerUnderTest {
                    addr: s.addr,
                    fingerprint: s.fingerprint,
                    database,
                    child: Some(s.child),
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
            signal(&c, Signal::TERM);
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
            crate::children::unregister(c.id());
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

/// A planet-server subprocess and the addresses it printed on stdout.
pub struct Spawned {
    /// The process.
    pub child: Child,
    /// QUIC address (`listening ADDR`).
    pub addr: SocketAddr,
    /// Certificate fingerprint (`cert-sha256 HEX`).
    pub fingerprint: String,
    /// Metrics address (`metrics ADDR`), when asked for.
    pub metrics: Option<SocketAddr>,
}

/// Starts `cmd` (the planet-server binary `bin` with its arguments) with
/// `RUST_LOG` from `PLANET_BENCH_SERVER_LOG` (default `log`), and waits up
/// to 30 s for the address and fingerprint lines on its stdout, and for
/// the metrics address too when `with_metrics`. Its stdout is drained
/// afterwards, so the server never blocks on it.
pub fn spawn_server(
    mut cmd: Command,
    bin: &Path,
    log: &str,
    with_metrics: bool,
) -> Result<Spawned> {
    let mut child = cmd
        .env(
            "RUST_LOG",
            std::env::var("PLANET_BENCH_SERVER_LOG").unwrap_or_else(|_| log.into()),
        )
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .with_context(|| format!("cannot start {}", bin.display()))?;
    crate::children::register(child.id());
    let stdout = child.stdout.take().context("no stdout")?;
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            // Keep draining after the receiver is gone.
            let _ = tx.send(line);
        }
    });
    let read = || -> Result<(SocketAddr, String, Option<SocketAddr>)> {
        let (mut addr, mut metrics, mut fingerprint) = (None, None, None);
        let deadline = Instant::now() + Duration::from_secs(30);
        while addr.is_none() || fingerprint.is_none() || (with_metrics && metrics.is_none()) {
            let left = deadline.saturating_duration_since(Instant::now());
            let Ok(line) = rx.recv_timeout(left) else {
                bail!("{} did not print its addresses", bin.display());
            };
            if let Some(f) = line.strip_prefix("cert-sha256 ") {
                fingerprint = Some(f.trim().to_string());
            } else if let Some(a) = line.strip_prefix("listening ") {
                addr = Some(a.trim().parse::<SocketAddr>()?);
            } else if let Some(a) = line.strip_prefix("metrics ") {
                metrics = Some(a.trim().parse::<SocketAddr>()?);
            }
        }
        Ok((
            addr.context("address")?,
            fingerprint.context("fingerprint")?,
            metrics,
        ))
    };
    match read() {
        Ok((addr, fingerprint, metrics)) => Ok(Spawned {
            child,
            addr,
            fingerprint,
            metrics,
        }),
        Err(e) => {
            let _ = child.kill();
            let _ = child.wait();
            crate::children::unregister(child.id());
            Err(e)
        }
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
        "planet-server binary not found next to {}: run `cargo build --release -p planet-server-bin` \
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
pub(crate) fn bench_endpoint(
    peer: SocketAddr,
    max_udp_payload: Option<u16>,
) -> Result<quinn::Endpoint> {
    Ok(planet_session::net::new_endpoint_with(
        peer,
        max_udp_payload,
    )?)
}
