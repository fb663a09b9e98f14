//! Where the viewer's data come from: the embedded procedural database in a
//! cache directory, a database file served in-process, or a remote server;
//! optionally through a simulated link.

use planet_client::ClientConfig;
use planet_linksim::{Link, LinkConfig};
use planet_protocol::message::Hello;
use planet_server::{Server, ServerConfig, ServerHandle};
use planet_session::http::HttpSessionConfig;
use planet_session::net::SessionConfig;
use planet_session::streaming::{StreamingClient, StreamingError};
use planet_session::tls;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Why the data source could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum SetupError {
    /// No cache directory could be determined or created.
    #[error("cache directory {path}: {source}")]
    Cache {
        /// The directory.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// No cache directory is known (no $PLANET_CACHE, $XDG_CACHE_HOME, $HOME).
    #[error("no cache directory: set PLANET_CACHE, XDG_CACHE_HOME or HOME")]
    NoCacheDir,
    /// Building the procedural database failed.
    #[error("building the default database at {path}: {source}")]
    Build {
        /// The path.
        path: PathBuf,
        /// The error.
        source: planet_preprocess::BuildError,
    },
    /// The database file cannot be opened.
    #[error("database {path}: {reason}")]
    Database {
        /// The path.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// The in-process server did not start.
    #[error("in-process server: {0}")]
    Server(String),
    /// TLS configuration (fingerprint) is invalid.
    #[error("TLS: {0}")]
    Tls(#[from] tls::TlsError),
    /// The link simulator did not start.
    #[error("link simulator: {0}")]
    Link(std::io::Error),
    /// Connecting failed.
    #[error("connecting to {addr}: {source}")]
    Connect {
        /// The address (or URL).
        addr: String,
        /// The error.
        source: StreamingError,
    },
    /// The tokio runtime could not start.
    #[error("tokio runtime: {0}")]
    Runtime(std::io::Error),
}

/// Where to stream from.
#[derive(Debug, Clone)]
pub enum Source {
    /// The embedded procedural database, served in-process.
    Local,
    /// A database file, served in-process.
    Db(PathBuf),
    /// A database file on any HTTPS server (HTTP/2 byte ranges).
    Url {
        /// `https://host/path/file.planetdb`.
        url: String,
        /// Pinned SHA-256 fingerprint of its certificate (hex), for a
        /// self-signed one; otherwise the system's roots.
        fingerprint: Option<String>,
    },
    /// A remote server.
    Remote {
        /// Address.
        addr: SocketAddr,
        /// Tenant token.
        token: String,
        /// Database name.
        database: String,
        /// Pinned SHA-256 fingerprint of its certificate (hex).
        fingerprint: String,
        /// Tenant name.
        tenant: String,
    },
}

/// The cache directory: `$PLANET_CACHE`, `$XDG_CACHE_HOME/planet` or
/// `~/.cache/planet`.
pub fn cache_dir() -> Result<PathBuf, SetupError> {
    let non_empty = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty());
    if let Some(p) = non_empty("PLANET_CACHE") {
        return Ok(PathBuf::from(p));
    }
    if let Some(p) = non_empty("XDG_CACHE_HOME") {
        return Ok(PathBuf::from(p).join("planet"));
    }
    if let Some(p) = non_empty("HOME") {
        return Ok(PathBuf::from(p).join(".cache").join("planet"));
    }
    Err(SetupError::NoCacheDir)
}

fn opens(path: &Path) -> Result<(), String> {
    planet_core::format::DbFile::open(path)
        .map(|_| ())
        .map_err(|e| e.to_string())
}

/// Why a cached built-in database is not used: it does not open (another
/// format version, a torn file) or another generator made it.
fn stale_reason(path: &Path) -> Option<String> {
    match planet_core::format::DbFile::open(path) {
        Err(e) => Some(format!("does not open ({e})")),
        Ok(db) => {
            let want = planet_preprocess::builtin::builtin_description();
            (db.header.description != want).then(|| {
                format!(
                    "was made by another generator or with other options ('{}', want '{want}')",
                    db.header.description
                )
            })
        }
    }
}

/// The built-in planet ([`planet_preprocess::builtin`]) in the cache
/// directory: built on first use with a progress bar, and rebuilt only when
/// it is missing, does not open, or its description (generator version and
/// options) differs from this build's.
pub fn default_database() -> Result<PathBuf, SetupError> {
    let dir = cache_dir()?;
    std::fs::create_dir_all(&dir).map_err(|source| SetupError::Cache {
        path: dir.clone(),
        source,
    })?;
    let path = dir.join("default.planetdb");
    if path.exists() {
        match stale_reason(&path) {
            None => return Ok(path),
            Some(why) => eprintln!(
                "planet-view: cached database {} {why}; rebuilding",
                path.display()
            ),
        }
    }
    eprintln!(
        "planet-view: building the built-in planet into {} (first use) ...",
        path.display()
    );
    let t0 = std::time::Instant::now();
    // A name of its own per build: two viewers starting at once do not
    // write into one file; the rename is atomic.
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    let tmp = dir.join(format!(
        "default.planetdb.tmp-{}-{nanos}",
        std::process::id()
    ));
    let opts = planet_preprocess::builtin::builtin_options();
    if let Err(source) = planet_preprocess::build_procedural(&opts, &tmp) {
        let _ = std::fs::remove_file(&tmp);
        return Err(SetupError::Build {
            path: tmp.clone(),
            source,
        });
    }
    std::fs::rename(&tmp, &path).map_err(|source| SetupError::Cache {
        path: path.clone(),
        source,
    })?;
    eprintln!("planet-view: built in {:.1} s", t0.elapsed().as_secs_f64());
    if let Some(reason) = stale_reason(&path) {
        return Err(SetupError::Database {
            path: path.clone(),
            reason,
        });
    }
    Ok(path)
}

/// A tokio runtime for the network (and the in-process server).
pub fn runtime() -> Result<tokio::runtime::Runtime, SetupError> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("planet-net")
        .enable_all()
        .build()
        .map_err(SetupError::Runtime)
}

/// A running data source: the in-process server and link (if any) and the
/// session configuration to reach it.
pub struct Endpoint {
    /// The in-process server.
    pub server: Option<ServerHandle>,
    /// The link simulator.
    pub link: Option<Link>,
    /// The database file, when it is local.
    pub db_path: Option<PathBuf>,
    /// How to reach the data (the server or link address, or the URL).
    pub session: Target,
    /// The same bypassing the link (for a reference client).
    pub direct: Target,
}

/// A session's transport and where it goes.
#[derive(Debug, Clone)]
pub enum Target {
    /// planet-server over QUIC.
    Quic(SessionConfig),
    /// A file over HTTP/2 byte ranges.
    Http(HttpSessionConfig),
}

/// Start the source (server, link) on `rt`.
pub fn start(
    rt: &tokio::runtime::Runtime,
    source: &Source,
    link: Option<&LinkConfig>,
) -> Result<Endpoint, SetupError> {
    tls::install_crypto_provider();
    if let Source::Url { url, fingerprint } = source {
        if link.is_some() {
            return Err(SetupError::Server(
                "--link shapes QUIC (UDP) only; for a URL use planet-bench flight --transport http2"
                    .into(),
            ));
        }
        let trust = match fingerprint {
            Some(fp) => tls::ServerTrust::Fingerprint(tls::parse_fingerprint(fp)?),
            None => tls::ServerTrust::System,
        };
        let tls_cfg = tls::https_config(&trust)?;
        let cfg = HttpSessionConfig::from_url(url, tls_cfg)
            .map_err(|e| SetupError::Server(e.to_string()))?;
        return Ok(Endpoint {
            server: None,
            link: None,
            db_path: None,
            session: Target::Http(cfg.clone()),
            direct: Target::Http(cfg),
        });
    }
    let (server, db_path, addr, fingerprint, hello) = match source {
        Source::Local | Source::Db(_) => {
            let path = match source {
                Source::Db(p) => {
                    opens(p).map_err(|reason| SetupError::Database {
                        path: p.clone(),
                        reason,
                    })?;
                    p.clone()
                }
                _ => default_database()?,
            };
            let listen: SocketAddr = ([127, 0, 0, 1], 0).into();
            let cfg = ServerConfig::single_database(&path, listen, "")
                .map_err(|e| SetupError::Server(e.to_string()))?;
            let name = cfg.databases[0].name.clone();
            let server = rt
                .block_on(Server::start(cfg))
                .map_err(|e| SetupError::Server(e.to_string()))?;
            let addr = server.local_addr();
            let fp = server.cert_fingerprint().to_string();
            (
                Some(server),
                Some(path),
                addr,
                fp,
                Hello::new("public", "", name),
            )
        }
        Source::Url { .. } => unreachable!("handled above"),
        Source::Remote {
            addr,
            token,
            database,
            fingerprint,
            tenant,
        } => (
            None,
            None,
            *addr,
            fingerprint.clone(),
            Hello::new(tenant.clone(), token.clone(), database.clone()),
        ),
    };
    let tls_cfg = tls::pinned(&fingerprint)?;
    let direct = SessionConfig::new(addr, "localhost", tls_cfg, hello);
    let link = match link {
        Some(cfg) => Some(
            rt.block_on(Link::start(addr, cfg.clone(), cfg.clone().with_seed(2)))
                .map_err(SetupError::Link)?,
        ),
        None => None,
    };
    let mut session = direct.clone();
    if let Some(l) = &link {
        session.addr = l.local_addr();
    }
    Ok(Endpoint {
        server,
        link,
        db_path,
        session: Target::Quic(session),
        direct: Target::Quic(direct),
    })
}

/// Connect a streaming client.
pub fn connect(
    rt: &tokio::runtime::Runtime,
    target: &Target,
    cfg: ClientConfig,
) -> Result<StreamingClient, SetupError> {
    let timeout = Duration::from_secs(10);
    match target {
        Target::Quic(session) => {
            StreamingClient::connect(rt.handle(), session.clone(), cfg, timeout).map_err(|source| {
                SetupError::Connect {
                    addr: session.addr.to_string(),
                    source,
                }
            })
        }
        Target::Http(session) => {
            StreamingClient::connect_http(rt.handle(), session.clone(), cfg, timeout).map_err(
                |source| SetupError::Connect {
                    addr: session.url.to_string(),
                    source,
                },
            )
        }
    }
}

impl Endpoint {
    /// Stop the server and the link.
    pub fn shutdown(self, rt: &tokio::runtime::Runtime) {
        if let Some(l) = &self.link {
            l.shutdown();
        }
        if let Some(s) = self.server {
            let _ = rt.block_on(async {
                tokio::time::timeout(Duration::from_secs(3), s.shutdown()).await
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cached_planet_of_another_generator_is_stale() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("default.planetdb");
        assert!(stale_reason(&path).is_some_and(|r| r.contains("does not open")));
        let mut o = planet_preprocess::default_procedural_options();
        o.levels = 1;
        planet_preprocess::build_procedural(&o, &path).unwrap();
        let why = stale_reason(&path).expect("a uniform 1-level planet is not the built-in one");
        assert!(
            why.contains("another generator or with other options"),
            "{why}"
        );
        std::fs::write(&path, b"PLANETDB torn").unwrap();
        assert!(stale_reason(&path).is_some_and(|r| r.contains("does not open")));
    }
}
