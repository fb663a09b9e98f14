//! Server configuration: the TOML file format (`deploy/server.toml`) and the
//! checked, in-memory [`ServerConfig`] the library runs from.
//!
//! ```toml
//! listen = "0.0.0.0:4433"          # QUIC (UDP)
//! metrics = "0.0.0.0:9100"         # HTTP /metrics /healthz /readyz (optional)
//! cert = "/etc/planet/tls/cert.pem"
//! key = "/etc/planet/tls/key.pem"
//! max_connections = 2000
//! idle_timeout_ms = 30000
//! max_udp_payload = 1452            # path-MTU discovery ceiling (bytes)
//! initial_window = 65536            # congestion window of a new connection (bytes)
//! zero_rtt = true                   # accept 0-RTT Hello on resumed sessions
//! initial_rtt_ms = 100              # RTT assumed before the first sample
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
    /// Bearer token (compared in constant time).
    pub token: String,
    /// Databases this tenant may open.
    pub databases: Vec<String>,
    /// Requests one connection may have outstanding.
    pub max_in_flight: u32,
    /// Send budget in bytes per second shared by all the tenant's
    /// connections (token bucket); 0 = unlimited.
    pub max_bytes_per_second: u64,
}

impl std::fmt::Debug for TenantConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TenantConfig")
            .field("name", &self.name)
            .field("token", &"<redacted>")
            .field("databases", &self.databases)
            .field("max_in_flight", &self.max_in_flight)
            .field("max_bytes_per_second", &self.max_bytes_per_second)
            .finish()
    }
}

/// Default `max_in_flight` of a tenant.
pub const DEFAULT_MAX_IN_FLIGHT: u32 = 64;
/// Default connection limit.
pub const DEFAULT_MAX_CONNECTIONS: usize = 2000;
/// Default idle timeout.
pub const DEFAULT_IDLE_TIMEOUT_MS: u32 = 30_000;

/// Checked configuration of a server.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// QUIC listen address (UDP). Port 0 picks a free port.
    pub listen: SocketAddr,
    /// HTTP address for `/metrics`, `/healthz`, `/readyz`; `None` disables it.
    pub metrics: Option<SocketAddr>,
    /// Certificate source.
    pub tls: TlsSource,
    /// Connections beyond this are closed with `CONNECTION_CLOSED_BUSY`.
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
    /// Accept 0-RTT data from clients resuming a TLS session and answer in
    /// 0.5-RTT, so a returning client's Welcome arrives one round trip
    /// after its first packet. Replay-safe here: session tickets are
    /// stateful and single-use (rustls `ServerSessionMemoryCache::take`),
    /// and every request is an idempotent read (docs/SECURITY.md).
    pub zero_rtt: bool,
    /// Round-trip time assumed before the first sample, ms (RFC 9002's
    /// 333 ms by default in quinn; Chromium uses 100 ms). It sets the
    /// pacing rate of the first flight: a 0-RTT Welcome goes out before any
    /// sample, and at 333 ms the pacer spreads a 64 KiB window over 266 ms.
    /// It also sets the handshake's first retransmission timeout (3x this).
    pub initial_rtt_ms: u32,
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
    zero_rtt: Option<bool>,
    initial_rtt_ms: Option<u32>,
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
}

fn parse_addr(what: &str, s: &str) -> Result<SocketAddr, ConfigError> {
    s.parse()
        .map_err(|e| ConfigError::Invalid(format!("{what} address {s:?}: {e}")))
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
    /// sends an empty token).
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
            tenants: vec![TenantConfig {
                name: "public".into(),
                token: token.into(),
                databases: vec![name],
                max_in_flight: DEFAULT_MAX_IN_FLIGHT,
                max_bytes_per_second: 0,
            }],
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
            zero_rtt: true,
            initial_rtt_ms: DEFAULT_INITIAL_RTT_MS,
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
        if let Some(z) = file.zero_rtt {
            cfg.zero_rtt = z;
        }
        if let Some(r) = file.initial_rtt_ms {
            cfg.initial_rtt_ms = r;
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
                    let s = std::fs::read_to_string(&f).map_err(|e| {
                        ConfigError::Invalid(format!(
                            "tenant {:?}: cannot read token_file {}: {e}",
                            t.name,
                            f.display()
                        ))
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
            cfg.tenants.push(TenantConfig {
                name: t.name,
                token,
                databases: t.databases,
                max_in_flight: t.max_in_flight.unwrap_or(DEFAULT_MAX_IN_FLIGHT),
                max_bytes_per_second: t.max_bytes_per_second.unwrap_or(0),
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
            if t.token.len() > planet_protocol::MAX_NAME_LEN {
                return bad(format!("tenant {:?}: token longer than 256 bytes", t.name));
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
