//! nginx serving one file over HTTPS (TLS 1.3, HTTP/2 and HTTP/1.1) with
//! byte ranges and ETags, as any static host would: the HTTP transport's
//! tests and the benchmarks' peer.

use std::io;
use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Where Debian installs nginx (`.ci/run` installs it).
pub const NGINX_BIN: &str = "/usr/sbin/nginx";

/// Why nginx could not be started.
#[derive(Debug, thiserror::Error)]
pub enum NginxError {
    /// Files, sockets or the process.
    #[error("nginx: {0}")]
    Io(#[from] io::Error),
    /// The self-signed certificate.
    #[error("nginx certificate")]
    Cert(#[from] rcgen::Error),
    /// nginx exited at start; its error log.
    #[error("nginx exited ({status}): {log}")]
    Exited {
        /// Exit status.
        status: std::process::ExitStatus,
        /// `error.log`.
        log: String,
    },
    /// nginx did not listen within 10 s.
    #[error("nginx did not listen on {0}")]
    NoListen(SocketAddr),
}

/// A running nginx serving one file at `https://localhost:PORT/NAME`.
pub struct Nginx {
    /// Its address (127.0.0.1, an ephemeral port).
    pub addr: SocketAddr,
    /// Its self-signed certificate (DER), for `localhost` and 127.0.0.1.
    pub cert_der: Vec<u8>,
    /// The file's name in the URL path.
    pub name: String,
    child: Child,
    www: PathBuf,
    _prefix: tempfile::TempDir,
}

impl Nginx {
    /// Starts `bin` with `workers` worker processes, serving `file` at
    /// `/NAME` (the file's own name).
    pub fn start(bin: &Path, file: &Path, workers: usize) -> Result<Nginx, NginxError> {
        let name = file
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("db")
            .to_string();
        Nginx::start_as(bin, file, &name, workers)
    }

    /// [`Nginx::start`], serving `file` at `/name`.
    pub fn start_as(
        bin: &Path,
        file: &Path,
        name: &str,
        workers: usize,
    ) -> Result<Nginx, NginxError> {
        let port = TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
        let addr = ([127, 0, 0, 1], port).into();
        Nginx::launch(bin, file, name, workers, addr, None, true)
    }

    /// [`Nginx::start`] without HTTP/2: ALPN offers `http/1.1` only, as an
    /// old or minimal static host would.
    pub fn start_http1_only(bin: &Path, file: &Path) -> Result<Nginx, NginxError> {
        let name = file
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("db")
            .to_string();
        let port = TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
        let addr = ([127, 0, 0, 1], port).into();
        Nginx::launch(bin, file, &name, 1, addr, None, false)
    }

    /// [`Nginx::start`] inside the network namespace `ns` (e.g. a
    /// `planet_linksim::TcpLink`'s), listening on `ip:8443`; its
    /// certificate also names `ip`, and [`Nginx::url`] uses it.
    pub fn start_in_namespace(
        bin: &Path,
        file: &Path,
        workers: usize,
        ns: &str,
        ip: std::net::Ipv4Addr,
    ) -> Result<Nginx, NginxError> {
        let name = file
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("db")
            .to_string();
        Nginx::launch(bin, file, &name, workers, (ip, 8443).into(), Some(ns), true)
    }

    fn launch(
        bin: &Path,
        file: &Path,
        name: &str,
        workers: usize,
        addr: SocketAddr,
        ns: Option<&str>,
        http2: bool,
    ) -> Result<Nginx, NginxError> {
        let http2 = if http2 { " http2" } else { "" };
        let prefix = tempfile::Builder::new().prefix("planet-nginx").tempdir()?;
        let p = prefix.path();
        let www = p.join("www");
        std::fs::create_dir_all(&www)?;
        std::fs::create_dir_all(p.join("tmp"))?;
        let file = std::fs::canonicalize(file)?;
        std::os::unix::fs::symlink(&file, www.join(name))?;
        let cert = rcgen::generate_simple_self_signed(vec![
            "localhost".into(),
            "127.0.0.1".into(),
            addr.ip().to_string(),
        ])?;
        std::fs::write(p.join("cert.pem"), cert.cert.pem())?;
        std::fs::write(p.join("key.pem"), cert.signing_key.serialize_pem())?;
        // Running as root, workers would switch to `nobody`; keep them as the
        // current user so they can read the file wherever it is.
        let user = if rustix::process::geteuid().is_root() {
            "user root root;"
        } else {
            ""
        };
        let conf = format!(
            r#"# written by planet-testkit
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
        listen {addr} ssl{http2};
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
            workers = workers.max(1),
            p = p.display()
        );
        std::fs::write(p.join("nginx.conf"), conf)?;
        let mut cmd = match ns {
            Some(ns) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", ns]).arg(bin);
                c
            }
            None => Command::new(bin),
        };
        let mut child = cmd
            .arg("-p")
            .arg(p)
            .arg("-e")
            .arg(p.join("error.log"))
            .arg("-c")
            .arg(p.join("nginx.conf"))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()?;
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if std::net::TcpStream::connect_timeout(&addr, Duration::from_secs(1)).is_ok() {
                break;
            }
            if let Ok(Some(status)) = child.try_wait() {
                let log = std::fs::read_to_string(p.join("error.log")).unwrap_or_default();
                return Err(NginxError::Exited { status, log });
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                let _ = child.wait();
                return Err(NginxError::NoListen(addr));
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        Ok(Nginx {
            addr,
            cert_der: cert.cert.der().to_vec(),
            name: name.to_string(),
            child,
            www,
            _prefix: prefix,
        })
    }

    /// `https://localhost:PORT/NAME` on loopback, `https://IP:8443/NAME` in
    /// a namespace.
    pub fn url(&self) -> String {
        if self.addr.ip().is_loopback() {
            format!("https://localhost:{}/{}", self.addr.port(), self.name)
        } else {
            format!("https://{}/{}", self.addr, self.name)
        }
    }

    /// The path nginx serves the file from (a symbolic link to it): replace
    /// it (e.g. by rename) to publish a new version.
    pub fn served_path(&self) -> PathBuf {
        self.www.join(&self.name)
    }

    /// The master process's pid.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }
}

impl Drop for Nginx {
    fn drop(&mut self) {
        use rustix::process::{kill_process, Pid, Signal};
        // SIGQUIT: graceful stop of master and workers.
        let pid = Pid::from_child(&self.child);
        let _ = kill_process(pid, Signal::QUIT);
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = kill_process(pid, Signal::TERM);
        let _ = self.child.wait();
    }
}
