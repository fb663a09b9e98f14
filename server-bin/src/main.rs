//! `planet-server` binary: CLI, logging, signals.
//!
//! ```text
//! planet-server --config /etc/planet/server.toml [--log-format json]
//! planet-server --database DB --listen ADDR --dev-cert [--metrics ADDR] [--token T] [--dev]
//! planet-server healthcheck --url http://127.0.0.1:9100/healthz
//! ```
//! SIGHUP re-opens the database files; SIGTERM / SIGINT drain and exit.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use planet_server::{Server, ServerConfig, TlsSource};

/// mimalloc instead of glibc's malloc: every request allocates a few small
/// buffers (quinn's stream state, frames, the response head), and glibc's
/// malloc/free took about 9 % of the server's CPU in the closed-loop
/// benchmark (docs/BENCHMARKS.md, "Where the server's CPU goes now").
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Debug, Parser)]
#[command(
    name = "planet-server",
    version,
    about = "Multi-tenant QUIC server of planet databases"
)]
#[command(args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// GET a URL (HTTP/1.0 over plain TCP): exit 0 on 200, 1 otherwise.
    Healthcheck {
        /// e.g. http://127.0.0.1:9100/healthz
        #[arg(long)]
        url: String,
        /// Timeout in milliseconds.
        #[arg(long, default_value_t = 3000)]
        timeout_ms: u64,
    },
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

#[derive(Debug, clap::Args)]
struct RunArgs {
    /// TOML configuration file.
    #[arg(long, conflicts_with = "database")]
    config: Option<PathBuf>,
    /// Serve this one database (no config file); name = file stem, tenant
    /// "public".
    #[arg(long)]
    database: Option<PathBuf>,
    /// Token of the "public" tenant in --database mode (default: empty).
    #[arg(long, requires = "database", default_value = "")]
    token: String,
    /// QUIC (UDP) listen address (overrides the config file).
    #[arg(long)]
    listen: Option<SocketAddr>,
    /// HTTP address for /metrics, /healthz, /readyz (overrides the config).
    #[arg(long)]
    metrics: Option<SocketAddr>,
    /// PEM certificate chain.
    #[arg(long, requires = "key")]
    cert: Option<PathBuf>,
    /// PEM private key.
    #[arg(long, requires = "cert")]
    key: Option<PathBuf>,
    /// Generate a self-signed certificate (localhost, 127.0.0.1) and print
    /// its SHA-256 fingerprint on stdout.
    #[arg(long, conflicts_with_all = ["cert", "key"])]
    dev_cert: bool,
    /// Development mode: accept empty, short or placeholder tokens (implied
    /// by --dev-cert and by a config file without cert/key).
    #[arg(long)]
    dev: bool,
    /// Ceiling of QUIC path-MTU discovery in bytes (overrides the config;
    /// default 1452). Clients bound it by their own `max_udp_payload_size`
    /// (planet clients: 1472, or 16384 to a loopback server); 16384 helps
    /// on loopback and jumbo-frame networks.
    #[arg(long)]
    max_udp_payload: Option<u16>,
    /// Congestion window of a new connection in bytes (overrides the
    /// config; default 65536, QUIC's own default is about 14 720).
    #[arg(long)]
    initial_window: Option<u64>,
    /// Congestion controller: bbr (default) or cubic (config `congestion`).
    #[arg(long)]
    congestion: Option<String>,
    /// Connections one client IP may hold (overrides the config; default
    /// 64). Benchmarks that simulate many clients from one address raise it.
    #[arg(long)]
    max_connections_per_address: Option<usize>,
    /// Refuse 0-RTT data (resuming clients then wait one more round trip
    /// for their Welcome). Overrides `zero_rtt` in the config.
    #[arg(long)]
    no_zero_rtt: bool,
    /// Answer `LodRefsRequest` (0x12) as a server that predates it does
    /// (`unknown_message`, id 0): no child reads on behalf of clients,
    /// which then ask one tree level per round trip. Overrides
    /// `child_tables` in the config.
    #[arg(long)]
    no_child_tables: bool,
    /// Answer a request stream that begins with a `Priority` frame (0x14)
    /// as a server that predates it does (`unknown_message`, id 0):
    /// answers go in the order of the requests. Overrides
    /// `stream_priority` in the config.
    #[arg(long)]
    no_stream_priority: bool,
    /// Tokio worker threads (default: one per CPU). 1 runs everything on
    /// a single-threaded runtime: no cross-thread wake-ups, one core at most.
    #[arg(long)]
    worker_threads: Option<usize>,
    /// Log format.
    #[arg(long, value_enum, default_value = "text")]
    log_format: LogFormat,
}

fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    match format {
        LogFormat::Json => builder.json().init(),
        LogFormat::Text => builder.init(),
    }
}

/// Minimal HTTP/1.0 GET over std TCP; returns the status code.
fn http_status(url: &str, timeout: Duration) -> Result<u16> {
    let rest = url
        .strip_prefix("http://")
        .context("only http:// URLs are supported")?;
    let (hostport, path) = match rest.find('/') {
        Some(i) => (&rest[..i], &rest[i..]),
        None => (rest, "/"),
    };
    let with_port = if hostport.contains(':') {
        hostport.to_string()
    } else {
        format!("{hostport}:80")
    };
    let addr = with_port
        .to_socket_addrs()
        .with_context(|| format!("cannot resolve {hostport}"))?
        .next()
        .with_context(|| format!("no address for {hostport}"))?;
    let mut s = TcpStream::connect_timeout(&addr, timeout)?;
    s.set_read_timeout(Some(timeout))?;
    s.set_write_timeout(Some(timeout))?;
    write!(s, "GET {path} HTTP/1.0\r\nHost: {hostport}\r\n\r\n")?;
    let mut buf = Vec::new();
    s.take(64 * 1024).read_to_end(&mut buf)?;
    let text = String::from_utf8_lossy(&buf);
    let status_line = text.lines().next().unwrap_or_default();
    let code = status_line
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse::<u16>().ok())
        .with_context(|| format!("bad status line {status_line:?}"))?;
    Ok(code)
}

fn build_config(args: &RunArgs) -> Result<ServerConfig> {
    let mut cfg = if let Some(path) = &args.config {
        ServerConfig::load(path)?
    } else if let Some(db) = &args.database {
        let listen = args
            .listen
            .context("--database needs --listen ADDR (e.g. 0.0.0.0:4433)")?;
        ServerConfig::single_database(db, listen, args.token.clone())?
    } else {
        bail!("give --config FILE, or --database DB --listen ADDR --dev-cert");
    };
    if let Some(l) = args.listen {
        cfg.listen = l;
    }
    if let Some(m) = args.metrics {
        cfg.metrics = Some(m);
    }
    if let Some(m) = args.max_udp_payload {
        cfg.max_udp_payload = m;
    }
    if let Some(w) = args.initial_window {
        cfg.initial_window = w;
    }
    if let Some(c) = &args.congestion {
        cfg.congestion = c.parse()?;
    }
    if let Some(m) = args.max_connections_per_address {
        cfg.max_connections_per_address = m;
    }
    if args.no_zero_rtt {
        cfg.zero_rtt = false;
    }
    if args.no_child_tables {
        cfg.child_tables = false;
    }
    if args.no_stream_priority {
        cfg.stream_priority = false;
    }
    if let (Some(c), Some(k)) = (&args.cert, &args.key) {
        cfg.tls = TlsSource::Pem {
            cert: c.clone(),
            key: k.clone(),
        };
    } else if args.dev_cert {
        cfg.tls = TlsSource::DevCert;
    } else if args.database.is_some() {
        bail!("--database mode needs --dev-cert or --cert/--key");
    }
    cfg.dev = args.dev || matches!(cfg.tls, TlsSource::DevCert);
    cfg.validate()?;
    Ok(cfg)
}

fn main() -> std::process::ExitCode {
    planet_core::pages::no_transparent_huge_pages();
    planet_core::pipe::exit_quietly_on_broken_pipe();
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("planet-server: error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run() -> Result<()> {
    let cli = Cli::parse();
    if let Some(Command::Healthcheck { url, timeout_ms }) = cli.command {
        let code = match http_status(&url, Duration::from_millis(timeout_ms)) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("healthcheck {url}: {e:#}");
                std::process::exit(1);
            }
        };
        if code == 200 {
            return Ok(());
        }
        eprintln!("healthcheck {url}: HTTP {code}");
        std::process::exit(1);
    }
    init_logging(cli.run.log_format);
    let cfg = build_config(&cli.run)?;
    let dev = matches!(cfg.tls, TlsSource::DevCert);
    let mut builder = match cli.run.worker_threads {
        Some(0) => bail!("--worker-threads must be at least 1"),
        Some(1) => tokio::runtime::Builder::new_current_thread(),
        Some(n) => {
            let mut b = tokio::runtime::Builder::new_multi_thread();
            b.worker_threads(n);
            b
        }
        None => tokio::runtime::Builder::new_multi_thread(),
    };
    let rt = builder
        .enable_all()
        .build()
        .context("cannot start the tokio runtime")?;
    rt.block_on(async move {
        let handle = Server::start(cfg).await?;
        if dev {
            // On stdout so scripts and clients can pin it.
            println!("cert-sha256 {}", handle.cert_fingerprint());
        }
        println!("listening {}", handle.local_addr());
        if let Some(m) = handle.metrics_addr() {
            println!("metrics {m}");
        }
        use tokio::signal::unix::{signal, SignalKind};
        let mut hup = signal(SignalKind::hangup())?;
        let mut term = signal(SignalKind::terminate())?;
        let mut int = signal(SignalKind::interrupt())?;
        loop {
            tokio::select! {
                _ = hup.recv() => {
                    tracing::info!("SIGHUP: reloading databases");
                    handle.reload();
                }
                _ = term.recv() => break,
                _ = int.recv() => break,
            }
        }
        tracing::info!("shutting down: draining connections");
        handle.shutdown().await;
        Ok::<(), anyhow::Error>(())
    })
}
