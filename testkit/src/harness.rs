//! Harness for end-to-end tests and benchmarks: an in-process
//! `planet-server` on loopback with a persisted development certificate (so
//! a restarted server keeps its fingerprint and port), the matching pinned
//! [`SessionConfig`], small procedural databases, an independent horizon
//! test, and the client's surface elevation interpolated from its leaves.

use glam::DVec3;
use planet_client::tree::{PartialTree, Samples};
use planet_core::camera::Basis;
use planet_core::cube::{direction_from_lat_lon, FaceCoord};
use planet_core::format::Header;
use planet_core::{BlockId, Datum};
use planet_protocol::Hello;
use planet_server::{Congestion, Server, ServerConfig, ServerHandle, TlsSource};
use planet_session::SessionConfig;
use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

/// Why the harness failed.
#[derive(Debug, thiserror::Error)]
pub enum HarnessError {
    /// Filesystem.
    #[error("i/o")]
    Io(#[from] std::io::Error),
    /// Certificate generation.
    #[error("certificate")]
    Cert(#[from] rcgen::Error),
    /// Server configuration.
    #[error("server configuration")]
    Config(#[from] planet_server::ConfigError),
    /// Server start.
    #[error("server")]
    Server(#[from] planet_server::ServerError),
    /// Client TLS configuration.
    #[error("client tls")]
    Tls(#[from] planet_session::tls::TlsError),
    /// Database build.
    #[error("database build")]
    Build(#[from] planet_preprocess::BuildError),
}

/// A self-signed certificate for `localhost`/`127.0.0.1`, written as PEM
/// files, and its SHA-256 fingerprint.
pub struct DevCert {
    _dir: tempfile::TempDir,
    /// Certificate PEM path.
    pub cert: PathBuf,
    /// Key PEM path.
    pub key: PathBuf,
    /// Lower-case hex SHA-256 of the certificate DER.
    pub fingerprint: String,
}

impl DevCert {
    /// Generates a certificate into a fresh temporary directory.
    pub fn generate() -> Result<DevCert, HarnessError> {
        let ck = rcgen::generate_simple_self_signed(vec![
            "localhost".to_string(),
            "127.0.0.1".to_string(),
        ])?;
        let dir = tempfile::tempdir()?;
        let cert = dir.path().join("cert.pem");
        let key = dir.path().join("key.pem");
        std::fs::write(&cert, ck.cert.pem())?;
        std::fs::write(&key, ck.signing_key.serialize_pem())?;
        let fingerprint = planet_session::tls::sha256_hex(ck.cert.der());
        Ok(DevCert {
            _dir: dir,
            cert,
            key,
            fingerprint,
        })
    }
}

/// An in-process server on one database, restartable on the same port.
pub struct LocalServer {
    handle: Option<ServerHandle>,
    addr: SocketAddr,
    db: PathBuf,
    cert: Arc<DevCert>,
    runtime: tokio::runtime::Handle,
    congestion: Option<Congestion>,
}

/// Name of the database a [`LocalServer`] serves (the file stem).
pub fn database_name(db: &Path) -> String {
    db.file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("planet")
        .to_string()
}

fn server_config(
    db: &Path,
    listen: SocketAddr,
    cert: &DevCert,
    congestion: Option<Congestion>,
) -> Result<ServerConfig, HarnessError> {
    let mut cfg = ServerConfig::single_database(db, listen, "")?;
    cfg.tls = TlsSource::Pem {
        cert: cert.cert.clone(),
        key: cert.key.clone(),
    };
    cfg.shutdown_grace = Duration::from_millis(200);
    if let Some(c) = congestion {
        cfg.congestion = c;
    }
    for t in &mut cfg.tenants {
        t.max_in_flight = 256;
    }
    Ok(cfg)
}

impl LocalServer {
    /// Starts a server for `db` on `127.0.0.1:0` with a new certificate.
    /// Call from outside the runtime's worker threads (it blocks on it).
    pub fn start(runtime: &tokio::runtime::Handle, db: &Path) -> Result<LocalServer, HarnessError> {
        Self::start_with(runtime, db, None)
    }

    /// [`LocalServer::start`] with another congestion controller than the
    /// server's default (`None`: the default).
    pub fn start_with(
        runtime: &tokio::runtime::Handle,
        db: &Path,
        congestion: Option<Congestion>,
    ) -> Result<LocalServer, HarnessError> {
        let cert = Arc::new(DevCert::generate()?);
        let listen = SocketAddr::from(([127, 0, 0, 1], 0));
        Self::start_inner(runtime, db, listen, cert, congestion)
    }

    /// Starts a server for `db` on `listen` with `cert`.
    pub fn start_on(
        runtime: &tokio::runtime::Handle,
        db: &Path,
        listen: SocketAddr,
        cert: Arc<DevCert>,
    ) -> Result<LocalServer, HarnessError> {
        Self::start_inner(runtime, db, listen, cert, None)
    }

    fn start_inner(
        runtime: &tokio::runtime::Handle,
        db: &Path,
        listen: SocketAddr,
        cert: Arc<DevCert>,
        congestion: Option<Congestion>,
    ) -> Result<LocalServer, HarnessError> {
        let cfg = server_config(db, listen, &cert, congestion)?;
        let handle = runtime.block_on(Server::start(cfg))?;
        Ok(LocalServer {
            addr: handle.local_addr(),
            handle: Some(handle),
            db: db.to_path_buf(),
            cert,
            runtime: runtime.clone(),
            congestion,
        })
    }

    /// The server's UDP address.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The certificate fingerprint clients pin.
    pub fn fingerprint(&self) -> &str {
        &self.cert.fingerprint
    }

    /// The running server, if any.
    pub fn handle(&self) -> Option<&ServerHandle> {
        self.handle.as_ref()
    }

    /// A session configuration pinning this server's certificate, for a
    /// client that connects to `addr` (the server itself or a link in front
    /// of it). Reconnect backoff is capped at 1 s.
    pub fn session_config(&self, addr: SocketAddr) -> Result<SessionConfig, HarnessError> {
        let tls = planet_session::tls::pinned(&self.cert.fingerprint)?;
        let hello = Hello::new("public", "", database_name(&self.db));
        let mut cfg = SessionConfig::new(addr, "localhost", tls, hello);
        cfg.backoff_max = Duration::from_secs(1);
        Ok(cfg)
    }

    /// Graceful shutdown (the port is free afterwards).
    pub fn stop(&mut self) {
        if let Some(h) = self.handle.take() {
            self.runtime.block_on(h.shutdown());
        }
    }

    /// Starts the server again on the same port with the same certificate.
    pub fn restart(&mut self) -> Result<(), HarnessError> {
        self.stop();
        // The port may take a moment to be free: 50 tries, 50 ms apart.
        let mut tries = 1;
        loop {
            let cfg = server_config(&self.db, self.addr, &self.cert, self.congestion)?;
            match self.runtime.block_on(Server::start(cfg)) {
                Ok(h) => {
                    self.handle = Some(h);
                    return Ok(());
                }
                Err(e) if tries >= 50 => return Err(e.into()),
                Err(_) => tries += 1,
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for LocalServer {
    fn drop(&mut self) {
        if let Some(h) = self.handle.take() {
            if tokio::runtime::Handle::try_current().is_err() {
                self.runtime.block_on(h.shutdown());
            }
        }
    }
}

/// Builds a procedural database (`levels` uniform levels, with colour).
pub fn build_procedural_db(out: &Path, levels: u8, seed: u64) -> Result<(), HarnessError> {
    build_procedural_db_with_detail(out, levels, seed, &[])
}

/// Builds a procedural database with colour: `levels` uniform levels,
/// deepened in the detail regions (the deep benchmark planets; an empty
/// slice gives [`build_procedural_db`]'s uniform planet).
pub fn build_procedural_db_with_detail(
    out: &Path,
    levels: u8,
    seed: u64,
    detail: &[planet_preprocess::DetailRegion],
) -> Result<(), HarnessError> {
    let mut opts = planet_preprocess::default_procedural_options();
    opts.levels = levels;
    opts.seed = seed;
    opts.quiet = true;
    opts.detail = detail.to_vec();
    planet_preprocess::build_procedural(&opts, out)
        .map(|_| ())
        .map_err(HarnessError::from)
}

/// A multi-threaded tokio runtime for servers, links and sessions.
pub fn runtime(threads: usize) -> std::io::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(threads.max(1))
        .enable_all()
        .build()
}

/// Independent horizon test: whether every point of a `n × n` grid over
/// `block`, at each of three heights in `[h_min, h_max]`, is hidden from
/// `eye` by the ball of radius `r_occluder` (the segment from the eye to the
/// point passes inside it). Used to check that the client never requests a
/// block behind the horizon.
pub fn block_behind_horizon(
    datum: &Datum,
    eye: DVec3,
    block: BlockId,
    h_min: f64,
    h_max: f64,
    r_occluder: f64,
    n: usize,
) -> bool {
    let (s0, t0, s1, t1) = block.extent();
    let n = n.max(2);
    for j in 0..n {
        for i in 0..n {
            let fc = FaceCoord {
                face: block.face,
                s: s0 + (s1 - s0) * i as f64 / (n - 1) as f64,
                t: t0 + (t1 - t0) * j as f64 / (n - 1) as f64,
            };
            let d = fc.direction();
            for h in [h_min, 0.5 * (h_min + h_max), h_max] {
                let p = DVec3::from_array(datum.position(d, h));
                if !segment_inside_ball(eye, p, r_occluder) {
                    return false;
                }
            }
        }
    }
    true
}

fn segment_inside_ball(a: DVec3, b: DVec3, r: f64) -> bool {
    let d = b - a;
    let dd = d.length_squared();
    let t = if dd > 0.0 {
        (-a.dot(d) / dd).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (a + d * t).length() < r
}

/// Elevation in metres of the surface a leaf is drawn with, at grid
/// position `(gx, gy)` in `[0, w]²` (sample units of the full grid):
/// bilinear interpolation over the samples of the drawn LOD (every sample at
/// LOD 0, every other one at LOD 1).
pub fn leaf_surface_elevation(
    header: &Header,
    grid: &[i16],
    w: usize,
    lod: u8,
    gx: f64,
    gy: f64,
) -> f64 {
    let side = w + 1;
    let step = if lod == 0 { 1usize } else { 2 };
    let cells = w / step;
    let (cx, cy) = (
        (gx / step as f64).clamp(0.0, cells as f64),
        (gy / step as f64).clamp(0.0, cells as f64),
    );
    let (x0, y0) = (
        (cx.floor() as usize).min(cells - 1),
        (cy.floor() as usize).min(cells - 1),
    );
    let (fx, fy) = (cx - x0 as f64, cy - y0 as f64);
    let at = |i: usize, j: usize| header.metres(grid[(j * step) * side + i * step]);
    let top = at(x0, y0) + (at(x0 + 1, y0) - at(x0, y0)) * fx;
    let bot = at(x0, y0 + 1) + (at(x0 + 1, y0 + 1) - at(x0, y0 + 1)) * fx;
    top + (bot - top) * fy
}

/// The client's drawn surface elevation at `(lat, lon)` in degrees: the
/// elevation leaf covering the point, at its drawn LOD (from `drawn`), or
/// `None` when that leaf is not drawn this frame.
pub fn client_surface_elevation(
    tree: &PartialTree,
    drawn: &HashMap<BlockId, u8>,
    lat_deg: f64,
    lon_deg: f64,
) -> Option<f64> {
    let fc = FaceCoord::from_lat_lon(lat_deg.to_radians(), lon_deg.to_radians());
    let et = tree.elevation();
    let w = et.width;
    let mut id = BlockId::root(fc.face);
    loop {
        let node = et.get(&id)?;
        let n = (1u64 << id.level) as f64;
        let gx = (fc.s * n - id.x as f64) * w as f64;
        let gy = (fc.t * n - id.y as f64) * w as f64;
        if node.split {
            let kx = usize::from(gx >= w as f64 / 2.0);
            let ky = usize::from(gy >= w as f64 / 2.0);
            id = id.child(kx | (ky << 1));
            continue;
        }
        let lod = *drawn.get(&id)?;
        let Some(Samples::Elevation(grid)) = &node.samples else {
            return None;
        };
        return Some(leaf_surface_elevation(
            tree.header(),
            grid,
            w,
            lod,
            gx.clamp(0.0, w as f64),
            gy.clamp(0.0, w as f64),
        ));
    }
}

/// Ground points (lat, lon in degrees) seen through an `nx × ny` grid of
/// screen positions of `camera`, on the sphere of radius `radius` (rays that
/// miss it are skipped).
/// Latitudes are geodetic for `datum` (the normal of the ellipsoid through
/// the hit point), as everywhere else in the project.
pub fn probe_points(
    camera: &planet_client::Camera,
    datum: &Datum,
    radius: f64,
    nx: usize,
    ny: usize,
) -> Vec<(f64, f64)> {
    let Basis {
        forward: f,
        right: r,
        up: u,
    } = camera.basis();
    let ty = (camera.fov_y * 0.5).tan();
    let tx = ty * camera.aspect;
    let mut out = Vec::new();
    for j in 0..ny {
        for i in 0..nx {
            let sx = (i as f64 + 0.5) / nx as f64 * 2.0 - 1.0;
            let sy = (j as f64 + 0.5) / ny as f64 * 2.0 - 1.0;
            let d = (f + r * (sx * tx) + u * (sy * ty)).normalize();
            // |e + s d|² = R²
            let e = camera.eye;
            let b = e.dot(d);
            let c = e.length_squared() - radius * radius;
            let disc = b * b - c;
            if disc < 0.0 {
                continue;
            }
            let s = -b - disc.sqrt();
            if s <= 0.0 {
                continue;
            }
            let p = e + d * s;
            let n = DVec3::new(p.x, p.y, p.z / (1.0 - datum.e2())).normalize();
            let (lat, lon) = planet_core::cube::lat_lon_from_direction(n.to_array());
            out.push((lat.to_degrees(), lon.to_degrees()));
        }
    }
    out
}

/// Unit direction of (lat, lon) in degrees.
pub fn direction_deg(lat: f64, lon: f64) -> DVec3 {
    DVec3::from_array(direction_from_lat_lon(lat.to_radians(), lon.to_radians()))
}
