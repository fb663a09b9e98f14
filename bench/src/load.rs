//! `planet-bench load`: many lightweight streaming clients in one process
//! against one planet-server on loopback.
//!
//! Each client is the real [`planet_client::Client`] (partial tree,
//! importance, fixed-size request queue with cancellation) with inline
//! decoding (0 decode threads) and a small viewport, driven at `--fps`
//! simulated frames per second along its own camera path: a built-in
//! trajectory (default `rainier`: orbit, descent, hover, fast flights)
//! moved to a random place of the planet, turned by a random heading and
//! started at a random phase, so the clients do not request the same records
//! at the same time. All clients share one tokio runtime; each has its own
//! [`planet_session::net::Connection`] (one QUIC connection, and, as
//! `Connection` is built, its own UDP socket), its requests are one stream
//! each and cancellations stop the streams.
//!
//! The server runs as a subprocess so that its CPU time
//! (`/proc/PID/stat` utime + stime) and memory (`/proc/PID/status` VmRSS and
//! RssAnon, sampled every second) are its own. Memory per connection is
//! (RSS with N connections − RSS idle) / N, measured after the connections
//! are set up and again at the end of the run. The command fails (non-zero
//! exit) on any request error or any connection not held for the whole run.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use planet_client::request_queue::QueueConfig;
use planet_client::trajectory::{Keyframe, Trajectory};
use planet_client::{Client, ClientConfig, TransportError};
use planet_core::format::Header;
use planet_session::net::Connection;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::server::{
    connect_many, cpu_seconds_of, latency, loadavg, ms, proc_rss, raise_nofile_limit, resolve_db,
    ServerMode, ServerUnderTest,
};

/// `planet-bench load` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct LoadArgs {
    /// Database file (default: build the default procedural planet to
    /// /tmp/planet-bench-default.planetdb if missing).
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// Concurrent clients (one QUIC connection each).
    #[arg(long, default_value_t = 1000)]
    pub clients: usize,
    /// Length of the flight in seconds.
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    /// Simulated frames per second of each client.
    #[arg(long, default_value_t = 10.0)]
    pub fps: f64,
    /// Viewport height in pixels (16:9, 60° vertical field of view).
    #[arg(long, default_value_t = 270.0)]
    pub viewport_height: f64,
    /// Request queue size of each client (requests in flight at most).
    #[arg(long, default_value_t = QueueConfig::default().max_in_flight)]
    pub queue: usize,
    /// Built-in trajectory every client flies (moved, turned and phased at
    /// random): rainier, everest, orbit, static-low.
    #[arg(long, default_value = "rainier")]
    pub trajectory: String,
    /// Seed of the clients' places and phases.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// How the server runs (in-process gives no server CPU/memory figures).
    #[arg(long, value_enum, default_value = "subprocess")]
    pub server: ServerMode,
    /// planet-server binary (default: next to this executable).
    #[arg(long)]
    pub server_bin: Option<PathBuf>,
    /// Worker threads of the client runtime (default: the number of CPUs).
    #[arg(long)]
    pub client_threads: Option<usize>,
    /// Handshakes in progress at once while connecting.
    #[arg(long, default_value_t = 64)]
    pub connect_parallel: usize,
}

impl Default for LoadArgs {
    fn default() -> Self {
        LoadArgs {
            db: None,
            clients: 1000,
            seconds: 60.0,
            fps: 10.0,
            viewport_height: 270.0,
            queue: QueueConfig::default().max_in_flight,
            trajectory: "rainier".into(),
            seed: 1,
            server: ServerMode::Subprocess,
            server_bin: None,
            client_threads: None,
            connect_parallel: 64,
        }
    }
}

/// One client's path: a built-in trajectory moved to `(lat, lon)`, turned by
/// `heading`, played from `phase` seconds, cyclically.
#[derive(Debug, Clone)]
pub(crate) struct Path {
    traj: Trajectory,
    phase: f64,
}

impl Path {
    pub(crate) fn new(base: &Trajectory, rng: &mut ChaCha8Rng) -> Path {
        let k0 = base.keyframes[0];
        let lat: f64 = rng.random_range(-60.0..60.0);
        let lon: f64 = rng.random_range(-180.0..180.0);
        let turn: f64 = rng.random_range(0.0..360.0);
        let keyframes = base
            .keyframes
            .iter()
            .map(|k| {
                // Offsets from the first keyframe, turned by `turn` (small
                // offsets: a local flat approximation is enough).
                let (dn, de) = (k.lat_deg - k0.lat_deg, k.lon_deg - k0.lon_deg);
                let (s, c) = turn.to_radians().sin_cos();
                let (n2, e2) = (dn * c - de * s, dn * s + de * c);
                Keyframe {
                    t: k.t,
                    lat_deg: (lat + n2).clamp(-89.0, 89.0),
                    lon_deg: wrap180(lon + e2),
                    alt_m: k.alt_m,
                    heading_deg: wrap180(k.heading_deg + turn),
                    pitch_deg: k.pitch_deg,
                }
            })
            .collect();
        let traj = Trajectory { keyframes };
        let phase = rng.random_range(0.0..traj.duration().max(1.0));
        Path { traj, phase }
    }

    fn time(&self, t: f64) -> f64 {
        let d = self.traj.duration();
        if d > 0.0 {
            (self.phase + t) % d
        } else {
            0.0
        }
    }
}

fn wrap180(d: f64) -> f64 {
    (d + 180.0).rem_euclid(360.0) - 180.0
}

/// Live counters shared by the clients and the monitor.
#[derive(Default)]
pub(crate) struct Live {
    pub(crate) requests: AtomicU64,
    pub(crate) bytes: AtomicU64,
    pub(crate) errors: AtomicU64,
    pub(crate) in_flight: AtomicU64,
}

#[derive(Default)]
pub(crate) struct ClientResult {
    pub(crate) lat_us: Vec<u32>,
    pub(crate) bytes: u64,
    pub(crate) errors: u64,
    pub(crate) first_error: Option<String>,
    pub(crate) frames: u64,
    pub(crate) sent: u64,
    pub(crate) cancelled: u64,
    pub(crate) refines: u64,
    pub(crate) held: bool,
    pub(crate) max_frame_us: u64,
    pub(crate) frame_us_total: u64,
}

pub(crate) struct ClientSpec {
    pub(crate) conn: Connection,
    pub(crate) header: Header,
    pub(crate) path: Path,
    pub(crate) cfg: ClientConfig,
    pub(crate) fov: f64,
    pub(crate) aspect: f64,
    pub(crate) viewport: f64,
}

/// One client's flight on `spec.conn` from `start` to `end` (shared by
/// `load` and `soak`).
pub(crate) async fn fly(
    spec: ClientSpec,
    start: tokio::time::Instant,
    end: tokio::time::Instant,
    period: Duration,
    live: Arc<Live>,
) -> ClientResult {
    let mut res = ClientResult::default();
    let datum = spec.header.datum;
    let mut client = match Client::new(spec.header, spec.cfg) {
        Ok(c) => c,
        Err(e) => {
            res.errors += 1;
            res.first_error = Some(format!("client: {e}"));
            return res;
        }
    };
    let conn = spec.conn;
    let mut tick = tokio::time::interval_at(start, period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    type Fetch = (u64, Instant, Result<Vec<u8>, planet_session::net::NetError>);
    let mut fetches: tokio::task::JoinSet<Fetch> = tokio::task::JoinSet::new();
    let mut handles: HashMap<u64, tokio::task::AbortHandle> = HashMap::new();
    let mut last = start;
    loop {
        tokio::select! {
            biased;
            Some(j) = fetches.join_next(), if !fetches.is_empty() => {
                let (id, t0, r) = match j {
                    Ok(x) => x,
                    Err(e) if e.is_cancelled() => continue,
                    Err(e) => {
                        res.errors += 1;
                        res.first_error.get_or_insert_with(|| format!("fetch task: {e}"));
                        continue;
                    }
                };
                if handles.remove(&id).is_none() {
                    continue; // cancelled by the queue after it finished
                }
                live.in_flight.fetch_sub(1, Ordering::Relaxed);
                match r {
                    Ok(bytes) => {
                        res.lat_us.push(t0.elapsed().as_micros().min(u32::MAX as u128) as u32);
                        res.bytes += bytes.len() as u64;
                        live.requests.fetch_add(1, Ordering::Relaxed);
                        live.bytes.fetch_add(bytes.len() as u64, Ordering::Relaxed);
                        client.deliver(id, Ok(bytes));
                    }
                    Err(e) => {
                        res.errors += 1;
                        live.errors.fetch_add(1, Ordering::Relaxed);
                        res.first_error.get_or_insert_with(|| e.to_string());
                        client.deliver(id, Err(TransportError::request(e)));
                    }
                }
            }
            now = tick.tick() => {
                if now >= end {
                    break;
                }
                let f0 = Instant::now();
                let t = (now - start).as_secs_f64();
                let dt = (now - last).as_secs_f64().max(1e-3);
                last = now;
                let cam = spec.path.traj.camera_at(spec.path.time(t), &datum, spec.fov, spec.aspect, spec.viewport);
                let out = client.frame(&cam, dt);
                res.frames += 1;
                for s in &out.send {
                    let c = conn.clone();
                    let (id, off, size) = (s.id, s.record.offset, s.record.size);
                    let t0 = Instant::now();
                    let h = fetches.spawn(async move { (id, t0, c.fetch(id, off, size).await) });
                    handles.insert(id, h);
                }
                live.in_flight.fetch_add(out.send.len() as u64, Ordering::Relaxed);
                res.sent += out.send.len() as u64;
                for id in &out.cancel {
                    if let Some(h) = handles.remove(id) {
                        h.abort();
                        res.cancelled += 1;
                        live.in_flight.fetch_sub(1, Ordering::Relaxed);
                    }
                }
                let us = f0.elapsed().as_micros() as u64;
                res.frame_us_total += us;
                res.max_frame_us = res.max_frame_us.max(us);
                // One frame per poll: a late client must not keep the worker
                // (and the QUIC drivers queued behind it) for a whole coop
                // budget of frames.
                tokio::task::yield_now().await;
            }
        }
    }
    live.in_flight
        .fetch_sub(handles.len() as u64, Ordering::Relaxed);
    fetches.abort_all();
    res.held = conn.quinn().close_reason().is_none() && conn.goodbye().is_none();
    res.refines = client.totals().refines_applied;
    res
}

/// What a load run measured.
#[derive(Debug, Clone, Default)]
pub struct LoadReport {
    /// Clients connected.
    pub clients: usize,
    /// Connections still open at the end of the flight.
    pub held: usize,
    /// Completed requests.
    pub requests: u64,
    /// Failed requests.
    pub errors: u64,
    /// Body bytes.
    pub bytes: u64,
    /// Flight length.
    pub wall: Duration,
    /// Request latency.
    pub latency: crate::server::Latency,
    /// Server CPU seconds during the flight.
    pub server_cpu: Option<f64>,
    /// Server (VmRSS, RssAnon) idle, after connecting, peak during the flight.
    pub rss: Option<[(u64, u64); 3]>,
    /// Frames run by all clients.
    pub frames: u64,
}

impl LoadReport {
    /// Requests per second.
    pub fn rps(&self) -> f64 {
        self.requests as f64 / self.wall.as_secs_f64().max(1e-9)
    }
}

/// `planet-bench load`.
pub fn run(args: LoadArgs) -> Result<()> {
    let r = bench(&args)?;
    if r.errors > 0 {
        bail!("{} requests failed", r.errors);
    }
    if r.held < r.clients {
        bail!(
            "{} of {} connections were lost during the run",
            r.clients - r.held,
            r.clients
        );
    }
    if r.requests == 0 {
        bail!("no request completed");
    }
    Ok(())
}

fn mb(b: u64) -> f64 {
    b as f64 / 1048576.0
}

/// Runs the load test, prints and returns the figures.
pub fn bench(args: &LoadArgs) -> Result<LoadReport> {
    planet_session::tls::install_crypto_provider();
    let nofile = raise_nofile_limit();
    let db = resolve_db(&args.db)?;
    let base = Trajectory::builtin(&args.trajectory)
        .ok_or_else(|| anyhow!("unknown trajectory {:?}", args.trajectory))?;
    let cpus = std::thread::available_parallelism().map_or(2, |n| n.get());
    println!(
        "database {} ({:.1} MB); {} clients, {} s, {} fps, viewport {}p, queue {}, trajectory {} \
         (random place/heading/phase, seed {}); {} CPUs, load average {} (before), open files {}",
        db.display(),
        std::fs::metadata(&db)?.len() as f64 / 1e6,
        args.clients,
        args.seconds,
        args.fps,
        args.viewport_height,
        args.queue,
        args.trajectory,
        args.seed,
        cpus,
        loadavg(),
        nofile
    );
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(args.client_threads.unwrap_or(cpus).max(1))
        .thread_name("load-client")
        .enable_all()
        .build()?;
    let srv = ServerUnderTest::start(args.server, &db, args.server_bin.as_deref())?;
    let pid = srv.pid();
    std::thread::sleep(Duration::from_millis(500));
    let rss_idle = pid.and_then(proc_rss);

    let t_connect = Instant::now();
    let conns = rt.block_on(connect_many(
        srv.addr,
        &srv.fingerprint,
        &srv.hello(),
        args.clients,
        args.connect_parallel,
    ))?;
    let connect_time = t_connect.elapsed();
    let w = conns[0].welcome();
    let header = Header::decode(&w.header, Some(w.file_size))?;
    std::thread::sleep(Duration::from_millis(1000));
    let rss_connected = pid.and_then(proc_rss);
    println!(
        "connected {} clients in {:.2} s; server RSS idle {} → {} with the connections",
        conns.len(),
        connect_time.as_secs_f64(),
        fmt_rss(rss_idle),
        fmt_rss(rss_connected)
    );

    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    let cfg = ClientConfig {
        queue: QueueConfig {
            max_in_flight: args.queue.max(1),
            ..QueueConfig::default()
        },
        decode_threads: 0,
        ..ClientConfig::default()
    };
    let live = Arc::new(Live::default());
    let period = Duration::from_secs_f64(1.0 / args.fps.max(0.1));
    let stop = Arc::new(AtomicBool::new(false));
    let peak = Arc::new(Mutex::new((0u64, 0u64)));
    let cpu0 = pid.map(|p| cpu_seconds_of(&[p]));
    let self0 = crate::server::proc_cpu_seconds(std::process::id());
    let wall0 = Instant::now();

    // Monitor: server RSS every second, progress every 10 s.
    let monitor = {
        let live = live.clone();
        let stop = stop.clone();
        let peak = peak.clone();
        std::thread::spawn(move || {
            let t0 = Instant::now();
            let mut last = (0u64, 0u64, Instant::now());
            let mut n = 0u64;
            while !stop.load(Ordering::Relaxed) {
                std::thread::sleep(Duration::from_millis(250));
                n += 1;
                if n.is_multiple_of(4) {
                    if let Some((v, a)) = pid.and_then(proc_rss) {
                        let mut p = peak.lock().unwrap_or_else(|e| e.into_inner());
                        p.0 = p.0.max(v);
                        p.1 = p.1.max(a);
                    }
                }
                if n.is_multiple_of(40) {
                    let r = live.requests.load(Ordering::Relaxed);
                    let b = live.bytes.load(Ordering::Relaxed);
                    let dt = last.2.elapsed().as_secs_f64();
                    println!(
                        "  t={:>4.0} s  {:>7.0} req/s  {:>6.1} MB/s  in flight {:>5}  errors {}  server CPU {}  load {}",
                        t0.elapsed().as_secs_f64(),
                        (r - last.0) as f64 / dt,
                        (b - last.1) as f64 / 1e6 / dt,
                        live.in_flight.load(Ordering::Relaxed),
                        live.errors.load(Ordering::Relaxed),
                        pid.and_then(crate::server::proc_cpu_seconds)
                            .map(|c| format!("{c:.1} s total"))
                            .unwrap_or_else(|| "n/a".into()),
                        loadavg()
                    );
                    last = (r, b, Instant::now());
                }
            }
        })
    };

    let results: Vec<ClientResult> = rt.block_on(async {
        let start = tokio::time::Instant::now() + Duration::from_millis(200);
        let end = start + Duration::from_secs_f64(args.seconds);
        let mut set = tokio::task::JoinSet::new();
        for conn in &conns {
            let spec = ClientSpec {
                conn: conn.clone(),
                header: header.clone(),
                path: Path::new(&base, &mut rng),
                cfg,
                fov: 60f64.to_radians(),
                aspect: 16.0 / 9.0,
                viewport: args.viewport_height,
            };
            // Spread the clients' frames over the frame period.
            let offset = period.mul_f64(rng.random::<f64>());
            set.spawn(fly(spec, start + offset, end, period, live.clone()));
        }
        let mut out = vec![];
        while let Some(r) = set.join_next().await {
            match r {
                Ok(r) => out.push(r),
                Err(e) => out.push(ClientResult {
                    errors: 1,
                    first_error: Some(e.to_string()),
                    ..ClientResult::default()
                }),
            }
        }
        out
    });
    let wall = wall0.elapsed().saturating_sub(Duration::from_millis(200));
    let cpu1 = pid.map(|p| cpu_seconds_of(&[p]));
    let self1 = crate::server::proc_cpu_seconds(std::process::id());
    let rss_end = pid.and_then(proc_rss);
    stop.store(true, Ordering::Relaxed);
    let _ = monitor.join();
    for c in &conns {
        c.close();
    }
    drop(conns);
    drop(srv);
    rt.shutdown_timeout(Duration::from_secs(2));

    let mut lat = vec![];
    let mut r = LoadReport {
        clients: results.len(),
        wall,
        ..LoadReport::default()
    };
    let mut first_error = None;
    let (mut sent, mut cancelled, mut refines, mut frame_us, mut max_frame_us) = (0, 0, 0, 0, 0);
    for c in results {
        lat.extend(c.lat_us);
        r.bytes += c.bytes;
        r.errors += c.errors;
        r.frames += c.frames;
        r.held += c.held as usize;
        sent += c.sent;
        cancelled += c.cancelled;
        refines += c.refines;
        frame_us += c.frame_us_total;
        max_frame_us = max_frame_us.max(c.max_frame_us);
        if first_error.is_none() {
            first_error = c.first_error;
        }
    }
    r.requests = lat.len() as u64;
    r.latency = latency(&mut lat);
    r.server_cpu = match (cpu0, cpu1) {
        (Some(a), Some(b)) => Some(b - a),
        _ => None,
    };
    let peak = *peak.lock().unwrap_or_else(|e| e.into_inner());
    let peak = (
        peak.0.max(rss_end.map_or(0, |x| x.0)),
        peak.1.max(rss_end.map_or(0, |x| x.1)),
    );
    if let (Some(i), Some(c)) = (rss_idle, rss_connected) {
        r.rss = Some([i, c, peak]);
    }
    let secs = wall.as_secs_f64();
    println!(
        "results over {secs:.1} s (load average {} after):",
        loadavg()
    );
    println!(
        "  clients {}  connections held for the whole run {}  frames {:.1}/s per client (target {})  \
         mean frame {:.0} µs, max {:.1} ms",
        r.clients,
        r.held,
        r.frames as f64 / r.clients.max(1) as f64 / secs,
        args.fps,
        frame_us as f64 / r.frames.max(1) as f64,
        max_frame_us as f64 / 1000.0
    );
    println!(
        "  requests {} ({:.0}/s)  sent {}  cancelled {}  refines applied {}  {:.2} MB/s  errors {}",
        r.requests,
        r.rps(),
        sent,
        cancelled,
        refines,
        r.bytes as f64 / 1e6 / secs,
        r.errors
    );
    println!(
        "  latency p50 {}  p90 {}  p99 {}  max {}  mean {:.2} ms",
        ms(r.latency.p50),
        ms(r.latency.p90),
        ms(r.latency.p99),
        ms(r.latency.max),
        r.latency.mean / 1000.0
    );
    if let Some(c) = r.server_cpu {
        println!(
            "  server CPU {:.1} s = {:.0} % of one core ({:.0} µs per request)",
            c,
            100.0 * c / secs,
            1e6 * c / r.requests.max(1) as f64
        );
    }
    if let (Some(a), Some(b)) = (self0, self1) {
        println!(
            "  client process CPU {:.0} % of one core",
            100.0 * (b - a) / secs
        );
    }
    if let Some([i, c, p]) = r.rss {
        let n = r.clients.max(1) as f64;
        println!(
            "  server RSS idle {} / connected {} / peak {}; per connection: {:.1} KiB anon ({:.1} KiB VmRSS) \
             connected, {:.1} KiB anon ({:.1} KiB VmRSS) at peak",
            fmt_rss(Some(i)),
            fmt_rss(Some(c)),
            fmt_rss(Some(p)),
            (c.1 as f64 - i.1 as f64) / n / 1024.0,
            (c.0 as f64 - i.0 as f64) / n / 1024.0,
            (p.1 as f64 - i.1 as f64) / n / 1024.0,
            (p.0 as f64 - i.0 as f64) / n / 1024.0,
        );
    }
    if let Some(e) = first_error {
        println!("  first error: {e}");
    }
    Ok(r)
}

fn fmt_rss(r: Option<(u64, u64)>) -> String {
    match r {
        Some((v, a)) => format!("{:.1} MiB (anon {:.1} MiB)", mb(v), mb(a)),
        None => "n/a".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_differ_and_stay_valid() {
        let base = Trajectory::builtin("rainier").unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let a = Path::new(&base, &mut rng);
        let b = Path::new(&base, &mut rng);
        assert_ne!(a.traj.keyframes[0].lat_deg, b.traj.keyframes[0].lat_deg);
        for p in [&a, &b] {
            for k in &p.traj.keyframes {
                assert!(k.lat_deg.abs() <= 89.0 && k.lon_deg.abs() <= 180.0);
            }
            assert!(p.time(1000.0) <= p.traj.duration());
        }
    }

    #[test]
    fn smoke_load_tiny() {
        let args = LoadArgs {
            db: Some(crate::server::tests_support::tiny_db()),
            clients: 5,
            seconds: 2.0,
            server: ServerMode::InProcess,
            client_threads: Some(2),
            ..LoadArgs::default()
        };
        let r = bench(&args).unwrap();
        assert_eq!(r.errors, 0);
        assert_eq!(r.held, 5);
        assert!(r.requests > 0 && r.bytes > 0, "{r:?}");
    }
}
