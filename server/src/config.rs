//! Server configuration: the TOML file format (`deploy/server.toml`) and the
//! checked, in-memory [`ServerConfig`] the library runs from.
//!
//! ```toml
//! listen = "0.0.0.0:4433"          # QUIC (UDP)
//! metrics = "127.0.0.1:9100"       # HTTP /metrics /healthz /readyz (optional; keep private)
//! cert = "/etc/planet/tls/cert.pem"
//! key = "/etc/planet/tls/key.pem"
//! max_connections = 2000
//! idle_timeout_ms = 30000
//! max_udp_payload = 1452            # path-MTU discovery ceiling (bytes)
//! initial_window = 65536            # congestion window of a new connection (bytes)
//! congestion = "bbr"                # "bbr" | "cubic" (congestion controller)
//! zero_rtt = true                   # accept 0-RTT Hello on resumed sessions
//! child_tables = true               # answer LodRefsRequest (0x12) with child tables
//! stream_priority = true            # answer higher Priority (0x14) requests first
//! initial_rtt_ms = 100              # RTT assumed before the first sample
//! handshake_timeout_ms = 5000       # whole pre-auth phase (QUIC, Hello, Welcome)
//! handshake_timeout_under_load_ms = 1000  # the same beyond retry_above_pending
//! write_timeout_ms = 30000          # any one write on behalf of a peer
//! max_pending_handshakes = 256      # pre-auth connections (own budget)
//! retry_above_pending = 64          # QUIC Retry beyond this many pending
//! max_connections_per_address = 64  # per client IP, pending + established
//! max_failed_hellos_per_minute = 30 # per client IP; then refused before TLS
//! max_handshakes_per_address_per_second = 10  # new connections per client IP
//!                                   # (burst: max_connections_per_address or more)
//! storage = "pread"                 # "pread" | "mmap" | "auto"
//!
//! [[database]]
//! name = "earth"
//! path = "/data/earth.planetdb"
//!
//! [[tenant]]
//! name = "public"
//! token_file = "/etc/planet/tokens/public"   # or token = "..."
//! databases = ["earth"]
//! max_in_flight = 64
//! max_bytes_per_second = 0                  # 0 = unlimited
//! max_connections = 0                       # sessions of this tenant; 0 = unlimited
//! max_requests_per_second = 0               # request budget; 0 = unlimited
//! ```
//!
//! Relative paths in the file are resolved against the file's directory.
//! Only database files are re-read on reload (SIGHUP); the configuration
//! itself (tenants, tokens, limits) is read once at start.

use std::collections::HashSet;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;

pub use crate::token::Token;

/// Why a configuration is invalid.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The configuration file could not be read.
    #[error("cannot read config file {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The TOML does not parse or has unknown/missing fields.
    #[error("invalid config file {path}: {message}")]
    Parse {
        /// The file (or `<string>`).
        path: PathBuf,
        /// The parser's message.
        message: String,
    },
    /// A semantic error (duplicate names, unknown database, missing file...).
    #[error("invalid configuration: {0}")]
    Invalid(String),
    /// An address does not parse.
    #[error("invalid configuration: {what} address {text:?}")]
    Address {
        /// Which address (`listen`, `metrics`...).
        what: String,
        /// The text given.
        text: String,
        /// The parser's error.
        source: std::net::AddrParseError,
    },
    /// A tenant's `token_file` cannot be read.
    #[error("invalid configuration: tenant {tenant:?}: cannot read token_file {}", path.display())]
    TokenFile {
        /// The tenant.
        tenant: String,
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// Where the TLS certificate comes from.
#[derive(Debug, Clone)]
pub enum TlsSource {
    /// PEM files: certificate chain and private key.
    Pem {
        /// Certificate chain (PEM).
        cert: PathBuf,
        /// Private key (PEM, PKCS#8, PKCS#1 or SEC1).
        key: PathBuf,
    },
    /// A self-signed certificate for `localhost` and `127.0.0.1`, generated
    /// at start (development only; clients pin its fingerprint).
    DevCert,
}

/// One served database file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DatabaseConfig {
    /// Name clients ask for in `Hello.database`.
    pub name: String,
    /// Path of the `.planetdb` file.
    pub path: PathBuf,
}

/// One tenant (client population).
#[derive(Clone, PartialEq, Eq)]
pub struct TenantConfig {
    /// Tenant name (`Hello.tenant`).
    pub name: String,
    /// Bearer token: only its SHA-256 is kept, compared in constant time.
    pub token: Token,
    /// Databases this tenant may open.
    pub databases: Vec<String>,
    /// Requests one connection may have outstanding.
    pub max_in_flight: u32,
    /// Send budget in bytes per second shared by all the tenant's
    /// connections (token bucket); 0 = unlimited.
    pub max_bytes_per_second: u64,
    /// Established sessions the tenant may hold at once; 0 = unlimited.
    /// Beyond it a `Hello` is refused with `server_busy`.
    pub max_connections: u32,
    /// Requests per second shared by all the tenant's connections (token
    /// bucket, one second of burst): excess requests are paced, and refused
    /// with `rate_limited` beyond `max_rate_wait`; 0 = unlimited.
    pub max_requests_per_second: u32,
}

impl TenantConfig {
    /// A tenant with the default limits.
    pub fn new(name: impl Into<String>, token: impl Into<Token>, databases: Vec<String>) -> Self {
        TenantConfig {
            name: name.into(),
            token: token.into(),
            databases,
            max_in_flight: DEFAULT_MAX_IN_FLIGHT,
            max_bytes_per_second: 0,
            max_connections: 0,
            max_requests_per_second: 0,
        }
    }
}

impl std::fmt::Debug for TenantConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TenantConfig")
            .field("name", &self.name)
            .field("token", &"<redacted>")
            .field("databases", &self.databases)
            .field("max_in_flight", &self.max_in_flight)
            .field("max_bytes_per_second", &self.max_bytes_per_second)
            .field("max_connections", &self.max_connections)
            .field("max_requests_per_second", &self.max_requests_per_second)
            .finish()
    }
}

/// Default `max_in_flight` of a tenant.
pub const DEFAULT_MAX_IN_FLIGHT: u32 = 64;
/// Default connection limit.
pub const DEFAULT_MAX_CONNECTIONS: usize = 2000;
/// Default idle timeout.
pub const DEFAULT_IDLE_TIMEOUT_MS: u32 = 30_000;
/// Default [`ServerConfig::handshake_timeout`].
pub const DEFAULT_HANDSHAKE_TIMEOUT_MS: u32 = 5_000;
/// Default [`ServerConfig::handshake_timeout_under_load`].
pub const DEFAULT_HANDSHAKE_TIMEOUT_UNDER_LOAD_MS: u32 = 1_000;
/// Default [`ServerConfig::write_timeout`].
pub const DEFAULT_WRITE_TIMEOUT_MS: u32 = 30_000;
/// Default [`ServerConfig::max_pending_handshakes`].
pub const DEFAULT_MAX_PENDING_HANDSHAKES: usize = 256;
/// Default [`ServerConfig::retry_above_pending`].
pub const DEFAULT_RETRY_ABOVE_PENDING: usize = 64;
/// Default [`ServerConfig::max_connections_per_address`].
pub const DEFAULT_MAX_CONNECTIONS_PER_ADDRESS: usize = 64;
/// Default [`ServerConfig::max_failed_hellos_per_minute`].
pub const DEFAULT_MAX_FAILED_HELLOS_PER_MINUTE: u32 = 30;
/// Default [`ServerConfig::max_handshakes_per_address_per_second`].
pub const DEFAULT_MAX_HANDSHAKES_PER_ADDRESS_PER_SECOND: u32 = 10;

/// How record bytes are read from database files (docs/SECURITY.md,
/// "Storage faults").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StorageMode {
    /// `pread` into a buffer per request: a truncated file or an I/O error
    /// is a per-request `storage` error (the default).
    Pread,
    /// Serve zero-copy from a memory map: fastest, but a file truncated in
    /// place or a failing device raises SIGBUS and kills the process.
    Mmap,
    /// `pread` on network and FUSE filesystems (detected with `statfs`),
    /// the memory map on local ones.
    Auto,
}

impl std::str::FromStr for StorageMode {
    type Err = ConfigError;
    fn from_str(s: &str) -> Result<Self, ConfigError> {
        match s {
            "pread" => Ok(StorageMode::Pread),
            "mmap" => Ok(StorageMode::Mmap),
            "auto" => Ok(StorageMode::Auto),
            other => Err(ConfigError::Invalid(format!(
                "storage {other:?}: expected \"pread\", \"mmap\" or \"auto\""
            ))),
        }
    }
}

/// The congestion controller of every connection (quinn's).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Congestion {
    /// CUBIC (RFC 9438), as TCP stacks use by default: backs off on every
    /// loss, so random (non-congestive) loss caps its rate.
    Cubic,
    /// BBR (draft-cardwell-iccrg-bbr): paces at the measured bottleneck
    /// bandwidth and does not treat isolated losses as congestion
    /// (quinn marks its implementation experimental).
    Bbr,
}

impl Default for Congestion {
    /// BBR: the server's default (docs/BENCHMARKS.md "Congestion control").
    fn default() -> Self {
        Congestion::Bbr
    }
}

impl Congestion {
    /// The name in the configuration file.
    pub fn name(&self) -> &'static str {
        match self {
            Congestion::Cubic => "cubic",
            Congestion::Bbr => "bbr",
        }
    }
}

impl std::str::FromStr for Congestion {
    type Err = ConfigError;
    fn from_str(s: &str) -> Result<Self, ConfigError> {
        match s {
            "cubic" => Ok(Congestion::Cubic),
            "bbr" => Ok(Congestion::Bbr),
            other => Err(ConfigError::Invalid(format!(
                "congestion {other:?}: expected \"cubic\" or \"bbr\""
            ))),
        }
    }
}

/// Checked configuration of a server.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// QUIC listen address (UDP). Port 0 picks a free port.
    pub listen: SocketAddr,
    /// HTTP address for `/metrics`, `/healthz`, `/readyz`; `None` disables it.
    pub metrics: Option<SocketAddr>,
    /// Certificate source.
    pub tls: TlsSource,
    /// Established sessions at once: a `Hello` beyond it is refused with
    /// `server_busy` (and the connection closed with that code).
    /// Unauthenticated connections count against `max_pending_handshakes`
    /// instead.
    pub max_connections: usize,
    /// QUIC idle timeout (also announced in `Limits.idle_timeout_ms`).
    pub idle_timeout_ms: u32,
    /// Served databases.
    pub databases: Vec<DatabaseConfig>,
    /// Tenants.
    pub tenants: Vec<TenantConfig>,
    /// Largest record a request may ask for (`Limits.max_record_size`).
    pub max_record_size: u32,
    /// How long a graceful shutdown lets in-flight responses finish.
    pub shutdown_grace: Duration,
    /// Longest a request may be paced by its tenant's bandwidth bucket
    /// before it is refused with `rate_limited`.
    pub max_rate_wait: Duration,
    /// Ceiling of QUIC path-MTU discovery: the largest UDP payload the
    /// server probes for and sends. The client's `max_udp_payload_size`
    /// transport parameter bounds it too, and planet clients announce
    /// 1 472 bytes (an Ethernet MTU) unless the server is on loopback or
    /// they are configured otherwise, so on the Internet the server never
    /// probes above what an Ethernet path carries. Default 1452, quinn's
    /// default. 16 384 on loopback (MTU 65 536) sends a 7 kB response in
    /// one datagram instead of five or six, as kernel TCP uses 64 kB
    /// loopback segments, and cuts the server's CPU per request by a
    /// quarter, but gave occasional 25–200 ms stalls (without packet loss)
    /// in open-loop runs on a loaded machine, not reproduced on a quiet one
    /// and not explained; see docs/BENCHMARKS.md.
    pub max_udp_payload: u16,
    /// Congestion window of a new connection, bytes (QUIC's default is
    /// 10 packets, about 14.7 kB). The Welcome carries the database header
    /// (47 kB for the real-data Earth, most of it the colour roots), so with
    /// the default it needs 2–3 slow-start round trips before the first
    /// frame; 64 KiB sends it in one flight.
    pub initial_window: u64,
    /// Congestion controller (see [`Congestion`]); BBR by default: at
    /// 1 Mbit/s, 100 ms and 2 % random loss a flight receives 7.8 MB with
    /// BBR against 3.5 MB with CUBIC, and as much on a clean link
    /// (docs/BENCHMARKS.md, "Congestion control").
    pub congestion: Congestion,
    /// Accept 0-RTT data from clients resuming a TLS session and answer in
    /// 0.5-RTT, so a returning client's Welcome arrives one round trip
    /// after its first packet. Replay-safe here: session tickets are
    /// stateful and single-use (rustls `ServerSessionMemoryCache::take`),
    /// and every request is an idempotent read (docs/SECURITY.md).
    pub zero_rtt: bool,
    /// Answer `LodRefsRequest` (0x12, docs/PROTOCOL.md §4.8): a record
    /// with its children's child tables, read from up to four more
    /// records. `false` (`child_tables = false` or `--no-child-tables`)
    /// answers it as a server that predates it does, an error head with
    /// id 0 and `unknown_message`, and clients fall back to `LodRequest`
    /// (one tree level per round trip) for the rest of the connection.
    pub child_tables: bool,
    /// Read a request stream's `Priority` frame (0x14, docs/PROTOCOL.md
    /// §4.10) and send its response before those of the connection's
    /// lower-priority requests still buffered. `false` (`stream_priority =
    /// false` or `--no-stream-priority`) answers such a stream as a server
    /// that predates the frame does, an error head with id 0 and
    /// `unknown_message`: clients ask again without it, and answers go in
    /// the order of the requests.
    pub stream_priority: bool,
    /// Round-trip time assumed before the first sample, ms (RFC 9002's
    /// 333 ms by default in quinn; Chromium uses 100 ms). It sets the
    /// pacing rate of the first flight: a 0-RTT Welcome goes out before any
    /// sample, and at 333 ms the pacer spreads a 64 KiB window over 266 ms.
    /// It also sets the handshake's first retransmission timeout (3x this).
    pub initial_rtt_ms: u32,
    /// Total time a connection may stay unauthenticated: from its first
    /// packet through the QUIC handshake, the control stream, the `Hello`
    /// and the whole `Welcome` (or error reply) written. Past it the
    /// connection is closed with `timeout` and counted as
    /// `planet_handshakes_total{outcome="timeout"}`.
    pub handshake_timeout: Duration,
    /// The handshake deadline of connections accepted while more than
    /// `retry_above_pending` are pending (under load): a client that is not
    /// flooding needs a few round trips, while every slot a flooder holds
    /// costs it a handshake per deadline. Never longer than
    /// `handshake_timeout`.
    pub handshake_timeout_under_load: Duration,
    /// Longest one write on behalf of a peer may block (a response head or
    /// body, an error reply): a client that stops reading, or advertises a
    /// zero receive window, loses the stream (`timeout`), not a slot forever.
    pub write_timeout: Duration,
    /// Unauthenticated connections allowed at once, a budget separate from
    /// `max_connections`: beyond it new connections are refused before any
    /// cryptography (`planet_connections_total{outcome="refused"}`).
    pub max_pending_handshakes: usize,
    /// With more pending handshakes than this, clients must prove their
    /// address first (QUIC Retry). 0 = always.
    pub retry_above_pending: usize,
    /// Connections (pending and established) one client IP may hold.
    pub max_connections_per_address: usize,
    /// Failed `Hello`s one client IP may send per minute (burst of the same
    /// size); beyond it every connection from that IP is refused before its
    /// TLS handshake (a `Hello` already under way, right or wrong, gets
    /// `rate_limited`) until the budget refills. 0 = unlimited.
    pub max_failed_hellos_per_minute: u32,
    /// New connections (TLS handshakes) one client IP may start per second,
    /// with a burst of `max_connections_per_address` or one second's worth,
    /// whichever is larger: an address may open its whole allowance at
    /// once, then this many more per second. Beyond
    /// it connections are refused before any cryptography, so a handshake
    /// flood from a few addresses costs the server stateless packets, not
    /// TLS work. 0 = unlimited.
    pub max_handshakes_per_address_per_second: u32,
    /// How record bytes are read (see [`StorageMode`]).
    pub storage: StorageMode,
    /// Development mode: empty, short, low-entropy or placeholder tokens
    /// are accepted. Set by [`ServerConfig::single_database`], by a file
    /// without `cert`/`key` (a generated certificate), and by the binary's
    /// `--dev` and `--dev-cert`; never otherwise.
    pub dev: bool,
}

/// Default [`ServerConfig::max_udp_payload`].
pub const DEFAULT_MAX_UDP_PAYLOAD: u16 = 1452;

/// Default [`ServerConfig::initial_rtt_ms`].
pub const DEFAULT_INITIAL_RTT_MS: u32 = 100;

/// Default [`ServerConfig::initial_window`].
pub const DEFAULT_INITIAL_WINDOW: u64 = 64 * 1024;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileConfig {
    listen: Option<String>,
    metrics: Option<String>,
    cert: Option<PathBuf>,
    key: Option<PathBuf>,
    max_connections: Option<usize>,
    idle_timeout_ms: Option<u32>,
    max_udp_payload: Option<u16>,
    initial_window: Option<u64>,
    congestion: Option<String>,
    zero_rtt: Option<bool>,
    child_tables: Option<bool>,
    stream_priority: Option<bool>,
    initial_rtt_ms: Option<u32>,
    handshake_timeout_ms: Option<u32>,
    handshake_timeout_under_load_ms: Option<u32>,
    write_timeout_ms: Option<u32>,
    max_pending_handshakes: Option<usize>,
    retry_above_pending: Option<usize>,
    max_connections_per_address: Option<usize>,
    max_failed_hellos_per_minute: Option<u32>,
    max_handshakes_per_address_per_second: Option<u32>,
    storage: Option<String>,
    #[serde(default)]
    database: Vec<FileDatabase>,
    #[serde(default)]
    tenant: Vec<FileTenant>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileDatabase {
    name: String,
    path: PathBuf,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileTenant {
    name: String,
    token: Option<String>,
    token_file: Option<PathBuf>,
    databases: Vec<String>,
    max_in_flight: Option<u32>,
    max_bytes_per_second: Option<u64>,
    max_connections: Option<u32>,
    max_requests_per_second: Option<u32>,
}

fn parse_addr(what: &str, s: &str) -> Result<SocketAddr, ConfigError> {
    s.parse().map_err(|source| ConfigError::Address {
        what: what.to_string(),
        text: s.to_string(),
        source,
    })
}

fn resolve(base: &Path, p: &Path) -> PathBuf {
    if p.is_absolute() {
        p.to_path_buf()
    } else {
        base.join(p)
    }
}

impl ServerConfig {
    /// A single-database configuration (no config file): database name =
    /// file stem, one tenant `public` with `token` (empty = any client that
    /// sends an empty token; weak tokens are accepted only with a
    /// development certificate, see [`ServerConfig::validate`]).
    pub fn single_database(
        path: impl Into<PathBuf>,
        listen: SocketAddr,
        token: impl Into<String>,
    ) -> Result<ServerConfig, ConfigError> {
        let path = path.into();
        let name = path
            .file_stem()
            .and_then(|s| s.to_str())
            .filter(|s| !s.is_empty())
            .ok_or_else(|| {
                ConfigError::Invalid(format!(
                    "cannot derive a database name from {}",
                    path.display()
                ))
            })?
            .to_string();
        let cfg = ServerConfig {
            listen,
            metrics: None,
            tls: TlsSource::DevCert,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            idle_timeout_ms: DEFAULT_IDLE_TIMEOUT_MS,
            databases: vec![DatabaseConfig {
                name: name.clone(),
                path,
            }],
            tenants: vec![TenantConfig::new(
                "public",
                Token::new(&token.into()),
                vec![name],
            )],
            dev: true,
            ..ServerConfig::base(listen)
        };
        cfg.validate()?;
        Ok(cfg)
    }

    fn base(listen: SocketAddr) -> ServerConfig {
        ServerConfig {
            listen,
            metrics: None,
            tls: TlsSource::DevCert,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            idle_timeout_ms: DEFAULT_IDLE_TIMEOUT_MS,
            databases: Vec::new(),
            tenants: Vec::new(),
            max_record_size: planet_core::format::MAX_RECORD_LEN as u32,
            shutdown_grace: Duration::from_secs(10),
            max_rate_wait: Duration::from_secs(2),
            max_udp_payload: DEFAULT_MAX_UDP_PAYLOAD,
            initial_window: DEFAULT_INITIAL_WINDOW,
            congestion: Congestion::default(),
            zero_rtt: true,
            child_tables: true,
            stream_priority: true,
            initial_rtt_ms: DEFAULT_INITIAL_RTT_MS,
            handshake_timeout: Duration::from_millis(u64::from(DEFAULT_HANDSHAKE_TIMEOUT_MS)),
            handshake_timeout_under_load: Duration::from_millis(u64::from(
                DEFAULT_HANDSHAKE_TIMEOUT_UNDER_LOAD_MS,
            )),
            write_timeout: Duration::from_millis(u64::from(DEFAULT_WRITE_TIMEOUT_MS)),
            max_pending_handshakes: DEFAULT_MAX_PENDING_HANDSHAKES,
            retry_above_pending: DEFAULT_RETRY_ABOVE_PENDING,
            max_connections_per_address: DEFAULT_MAX_CONNECTIONS_PER_ADDRESS,
            max_failed_hellos_per_minute: DEFAULT_MAX_FAILED_HELLOS_PER_MINUTE,
            max_handshakes_per_address_per_second: DEFAULT_MAX_HANDSHAKES_PER_ADDRESS_PER_SECOND,
            storage: StorageMode::Pread,
            dev: false,
        }
    }

    /// Reads and checks a TOML configuration file.
    pub fn load(path: &Path) -> Result<ServerConfig, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let base = path.parent().unwrap_or_else(|| Path::new("."));
        Self::from_toml_str(&text, base).map_err(|e| match e {
            ConfigError::Parse { message, .. } => ConfigError::Parse {
                path: path.to_path_buf(),
                message,
            },
            other => other,
        })
    }

    /// Parses and checks a TOML configuration; relative paths are resolved
    /// against `base_dir`.
    pub fn from_toml_str(text: &str, base_dir: &Path) -> Result<ServerConfig, ConfigError> {
        let file: FileConfig = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: PathBuf::from("<string>"),
            message: e.to_string(),
        })?;
        let listen = parse_addr("listen", file.listen.as_deref().unwrap_or("0.0.0.0:4433"))?;
        let mut cfg = ServerConfig::base(listen);
        cfg.metrics = file
            .metrics
            .as_deref()
            .map(|m| parse_addr("metrics", m))
            .transpose()?;
        cfg.tls = match (file.cert, file.key) {
            (Some(c), Some(k)) => TlsSource::Pem {
                cert: resolve(base_dir, &c),
                key: resolve(base_dir, &k),
            },
            (None, None) => TlsSource::DevCert,
            _ => {
                return Err(ConfigError::Invalid(
                    "`cert` and `key` must be given together".into(),
                ))
            }
        };
        cfg.dev = matches!(cfg.tls, TlsSource::DevCert);
        if let Some(m) = file.max_connections {
            cfg.max_connections = m;
        }
        if let Some(t) = file.idle_timeout_ms {
            cfg.idle_timeout_ms = t;
        }
        if let Some(m) = file.max_udp_payload {
            cfg.max_udp_payload = m;
        }
        if let Some(w) = file.initial_window {
            cfg.initial_window = w;
        }
        if let Some(c) = &file.congestion {
            cfg.congestion = c.parse()?;
        }
        if let Some(z) = file.zero_rtt {
            cfg.zero_rtt = z;
        }
        if let Some(c) = file.child_tables {
            cfg.child_tables = c;
        }
        if let Some(p) = file.stream_priority {
            cfg.stream_priority = p;
        }
        if let Some(r) = file.initial_rtt_ms {
            cfg.initial_rtt_ms = r;
        }
        if let Some(t) = file.handshake_timeout_ms {
            cfg.handshake_timeout = Duration::from_millis(u64::from(t));
        }
        if let Some(t) = file.handshake_timeout_under_load_ms {
            cfg.handshake_timeout_under_load = Duration::from_millis(u64::from(t));
        }
        if let Some(t) = file.write_timeout_ms {
            cfg.write_timeout = Duration::from_millis(u64::from(t));
        }
        if let Some(m) = file.max_pending_handshakes {
            cfg.max_pending_handshakes = m;
        }
        if let Some(m) = file.retry_above_pending {
            cfg.retry_above_pending = m;
        }
        if let Some(m) = file.max_connections_per_address {
            cfg.max_connections_per_address = m;
        }
        if let Some(m) = file.max_failed_hellos_per_minute {
            cfg.max_failed_hellos_per_minute = m;
        }
        if let Some(m) = file.max_handshakes_per_address_per_second {
            cfg.max_handshakes_per_address_per_second = m;
        }
        if let Some(s) = &file.storage {
            cfg.storage = s.parse()?;
        }
        cfg.databases = file
            .database
            .into_iter()
            .map(|d| DatabaseConfig {
                name: d.name,
                path: resolve(base_dir, &d.path),
            })
            .collect();
        for t in file.tenant {
            let token = match (t.token, t.token_file) {
                (Some(tok), None) => tok,
                (None, Some(f)) => {
                    let f = resolve(base_dir, &f);
                    let s =
                        std::fs::read_to_string(&f).map_err(|source| ConfigError::TokenFile {
                            tenant: t.name.clone(),
                            path: f.clone(),
                            source,
                        })?;
                    s.trim_end_matches(['\n', '\r']).to_string()
                }
                _ => {
                    return Err(ConfigError::Invalid(format!(
                        "tenant {:?}: exactly one of `token` and `token_file` is required",
                        t.name
                    )))
                }
            };
            if token.len() > planet_protocol::MAX_NAME_LEN {
                return Err(ConfigError::Invalid(format!(
                    "tenant {:?}: token longer than 256 bytes",
                    t.name
                )));
            }
            cfg.tenants.push(TenantConfig {
                name: t.name,
                token: Token::new(&token),
                databases: t.databases,
                max_in_flight: t.max_in_flight.unwrap_or(DEFAULT_MAX_IN_FLIGHT),
                max_bytes_per_second: t.max_bytes_per_second.unwrap_or(0),
                max_connections: t.max_connections.unwrap_or(0),
                max_requests_per_second: t.max_requests_per_second.unwrap_or(0),
            });
        }
        cfg.validate()?;
        Ok(cfg)
    }

    /// Semantic checks: names unique and non-empty, tenants reference known
    /// databases, database files exist, limits are sane.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |m: String| Err(ConfigError::Invalid(m));
        if self.databases.is_empty() {
            return bad("no [[database]] configured".into());
        }
        if self.tenants.is_empty() {
            return bad("no [[tenant]] configured".into());
        }
        if self.max_connections == 0 {
            return bad("max_connections must be at least 1".into());
        }
        if self.idle_timeout_ms == 0 {
            return bad("idle_timeout_ms must be at least 1".into());
        }
        if !(1200..=65_527).contains(&self.max_udp_payload) {
            return bad(format!(
                "max_udp_payload {} is outside 1200..=65527",
                self.max_udp_payload
            ));
        }
        if !(1..=10_000).contains(&self.initial_rtt_ms) {
            return bad(format!(
                "initial_rtt_ms {} is outside 1..=10000",
                self.initial_rtt_ms
            ));
        }
        if self.handshake_timeout.is_zero() || self.handshake_timeout > Duration::from_secs(120) {
            return bad("handshake_timeout_ms must be in 1..=120000".into());
        }
        if self.handshake_timeout_under_load.is_zero() {
            return bad("handshake_timeout_under_load_ms must be at least 1".into());
        }
        if self.write_timeout.is_zero() {
            return bad("write_timeout_ms must be at least 1".into());
        }
        if self.max_pending_handshakes == 0 || self.max_connections_per_address == 0 {
            return bad(
                "max_pending_handshakes and max_connections_per_address must be at least 1".into(),
            );
        }
        if !(2400..=16 * 1024 * 1024).contains(&self.initial_window) {
            return bad(format!(
                "initial_window {} is outside 2400..=16777216 bytes",
                self.initial_window
            ));
        }
        let mut names = HashSet::new();
        for d in &self.databases {
            if d.name.is_empty() || d.name.len() > planet_protocol::MAX_NAME_LEN {
                return bad(format!("database name {:?} is empty or too long", d.name));
            }
            if !names.insert(d.name.as_str()) {
                return bad(format!("duplicate database name {:?}", d.name));
            }
            if !d.path.is_file() {
                return bad(format!(
                    "database {:?}: file {} does not exist or is not a regular file",
                    d.name,
                    d.path.display()
                ));
            }
        }
        let mut tenants = HashSet::new();
        for t in &self.tenants {
            if t.name.is_empty() || t.name.len() > planet_protocol::MAX_NAME_LEN {
                return bad(format!("tenant name {:?} is empty or too long", t.name));
            }
            if let (Some(why), false) = (t.token.weakness(), self.is_dev()) {
                return bad(format!(
                    "tenant {:?}: {why} (weak tokens are accepted only in development mode, --dev)",
                    t.name
                ));
            }
            if !tenants.insert(t.name.as_str()) {
                return bad(format!("duplicate tenant name {:?}", t.name));
            }
            if t.max_in_flight == 0 || t.max_in_flight > 10_000 {
                return bad(format!(
                    "tenant {:?}: max_in_flight must be in 1..=10000",
                    t.name
                ));
            }
            for db in &t.databases {
                if !names.contains(db.as_str()) {
                    return bad(format!("tenant {:?} lists unknown database {db:?}", t.name));
                }
            }
        }
        if let TlsSource::Pem { cert, key } = &self.tls {
            for (what, p) in [("cert", cert), ("key", key)] {
                if !p.is_file() {
                    return bad(format!("{what} file {} does not exist", p.display()));
                }
            }
        }
        Ok(())
    }

    /// Development mode (see [`ServerConfig::dev`]): only then are empty,
    /// short, low-entropy or placeholder tokens accepted.
    pub fn is_dev(&self) -> bool {
        self.dev
    }

    /// The largest `max_in_flight` of any tenant (sizes the QUIC stream
    /// limit before the tenant is known).
    pub fn max_tenant_in_flight(&self) -> u32 {
        self.tenants
            .iter()
            .map(|t| t.max_in_flight)
            .max()
            .unwrap_or(DEFAULT_MAX_IN_FLIGHT)
    }
}
