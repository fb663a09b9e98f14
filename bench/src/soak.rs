//! `planet-bench soak`: steady streaming load with connection churn against
//! one planet-server for hours, watching the server's memory, file
//! descriptors and errors.
//!
//! `--clients` slots each run, back to back until the end: connect (a real
//! QUIC connection and Hello), fly like a `planet-bench load` client (the
//! real [`planet_client::Client`] along a built-in trajectory moved to a
//! random place, heading and phase) for a random session length around
//! `--session` seconds (uniform in 0.5–1.5×), then close. The server runs
//! as a subprocess; every `--sample` seconds its VmRSS and anonymous RSS
//! (`/proc/PID/status`), open file descriptors (`/proc/PID/fd`) and CPU
//! time are recorded with the request and session counters.
//!
//! Memory is flat when the least-squares slope of the anonymous RSS over
//! the run after the warm-up (the first tenth, 1 to 10 minutes) stays
//! under `--max-growth` MiB per hour. The command fails (non-zero exit) on
//! any request or connect error, any session whose connection was lost,
//! growing memory, or growing descriptors; it prints a table and, with
//! `--json`, writes every sample.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use planet_client::request_queue::QueueConfig;
use planet_client::trajectory::Trajectory;
use planet_client::ClientConfig;
use planet_core::format::Header;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::load::{fly, ClientSpec, Live, Path};
use crate::server::{
    connect_many, load1, loadavg, proc_anon_huge, proc_cpu_seconds, proc_rss, proc_threads,
    raise_nofile_limit, resolve_db, ServerMode, ServerUnderTest,
};

/// `planet-bench soak` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct SoakArgs {
    /// Database file (default: build the default procedural planet to
    /// /tmp/planet-bench-default.planetdb if missing).
    #[arg(long)]
    pub db: Option<PathBuf>,
    /// Length of the soak in hours.
    #[arg(long, default_value_t = 2.0)]
    pub hours: f64,
    /// Client slots streaming at once.
    #[arg(long, default_value_t = 64)]
    pub clients: usize,
    /// Mean session length in seconds (each is 0.5–1.5 times this).
    #[arg(long, default_value_t = 60.0)]
    pub session: f64,
    /// Simulated frames per second of each client.
    #[arg(long, default_value_t = 5.0)]
    pub fps: f64,
    /// Viewport height in pixels (16:9, 60° vertical field of view).
    #[arg(long, default_value_t = 270.0)]
    pub viewport_height: f64,
    /// Built-in trajectory every client flies (moved, turned and phased at
    /// random): rainier, everest, orbit, static-low.
    #[arg(long, default_value = "rainier")]
    pub trajectory: String,
    /// Seed of the clients' places, phases and session lengths.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Seconds between samples of the server's memory and counters.
    #[arg(long, default_value_t = 10.0)]
    pub sample: f64,
    /// Largest anonymous-RSS growth after the warm-up, MiB per hour.
    #[arg(long, default_value_t = 4.0)]
    pub max_growth: f64,
    /// planet-server binary (default: next to this executable).
    #[arg(long)]
    pub server_bin: Option<PathBuf>,
    /// Write every sample and the verdict as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// One sample of the server and the counters.
#[derive(Debug, Clone, Copy, Default)]
struct Sample {
    t: f64,
    vm_rss: u64,
    anon: u64,
    /// Of `anon`, in transparent huge pages.
    huge: u64,
    fds: u64,
    threads: u64,
    load1: f64,
    cpu: f64,
    requests: u64,
    bytes: u64,
    errors: u64,
    sessions: u64,
}

/// Counters of the churning slots.
#[derive(Default)]
struct Churn {
    sessions: AtomicU64,
    lost: AtomicU64,
    connect_errors: AtomicU64,
    first_error: Mutex<Option<String>>,
}

impl Churn {
    fn error(&self, e: String) {
        let mut f = self.first_error.lock().unwrap_or_else(|p| p.into_inner());
        f.get_or_insert(e);
    }
}

fn open_fds(pid: u32) -> Option<u64> {
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .ok()
        .map(|d| d.count() as u64)
}

/// Least-squares slope of `y` against `x`.
fn slope(points: &[(f64, f64)]) -> f64 {
    let n = points.len() as f64;
    if points.len() < 2 {
        return 0.0;
    }
    let (mx, my) = points
        .iter()
        .fold((0.0, 0.0), |(a, b), &(x, y)| (a + x / n, b + y / n));
    let (num, den) = points.iter().fold((0.0, 0.0), |(a, b), &(x, y)| {
        (a + (x - mx) * (y - my), b + (x - mx) * (x - mx))
    });
    if den > 0.0 {
        num / den
    } else {
        0.0
    }
}

/// One slot: sessions back to back until `end`.
#[allow(clippy::too_many_arguments)]
async fn slot(
    k: u64,
    srv: (std::net::SocketAddr, String, planet_protocol::Hello),
    header: Header,
    base: Trajectory,
    args: SoakArgs,
    end: tokio::time::Instant,
    live: Arc<Live>,
    churn: Arc<Churn>,
) {
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed.wrapping_mul(1_000_003) ^ k);
    let period = Duration::from_secs_f64(1.0 / args.fps.max(0.1));
    let cfg = ClientConfig {
        queue: QueueConfig::default(),
        decode_threads: 0,
        ..ClientConfig::default()
    };
    // Spread the slots' first connections over one mean session.
    let first = Duration::from_secs_f64(args.session * rng.random::<f64>());
    tokio::time::sleep_until((tokio::time::Instant::now() + first).min(end)).await;
    while tokio::time::Instant::now() < end {
        let conn = match connect_many(srv.0, &srv.1, &srv.2, 1, 1).await {
            Ok(mut v) => match v.pop() {
                Some(c) => c,
                None => {
                    churn.connect_errors.fetch_add(1, Ordering::Relaxed);
                    churn.error("connect: no connection".into());
                    continue;
                }
            },
            Err(e) => {
                churn.connect_errors.fetch_add(1, Ordering::Relaxed);
                churn.error(format!("connect: {e:#}"));
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
        };
        let now = tokio::time::Instant::now();
        let stop =
            (now + Duration::from_secs_f64(args.session * rng.random_range(0.5..1.5))).min(end);
        let spec = ClientSpec {
            conn: conn.clone(),
            header: header.clone(),
            path: Path::new(&base, &mut rng),
            cfg,
            fov: 60f64.to_radians(),
            aspect: 16.0 / 9.0,
            viewport: args.viewport_height,
        };
        let r = fly(spec, now, stop, period, live.clone()).await;
        if let Some(e) = r.first_error {
            churn.error(e);
        }
        if !r.held {
            churn.lost.fetch_add(1, Ordering::Relaxed);
        }
        conn.close();
        churn.sessions.fetch_add(1, Ordering::Relaxed);
    }
}

/// `planet-bench soak`.
pub fn run(args: SoakArgs) -> Result<()> {
    planet_session::tls::install_crypto_provider();
    let nofile = raise_nofile_limit();
    let db = resolve_db(&args.db)?;
    let base = Trajectory::builtin(&args.trajectory)
        .ok_or_else(|| anyhow!("unknown trajectory {:?}", args.trajectory))?;
    let seconds = args.hours * 3600.0;
    if !(seconds > 0.0 && seconds.is_finite()) {
        bail!("--hours must be positive");
    }
    println!(
        "soak: database {} ({:.1} MB); {} client slots, sessions {:.0} s ± 50 %, {} fps, {:.2} h, \
         trajectory {} (seed {}); load average {} (before), open files {}",
        db.display(),
        std::fs::metadata(&db)?.len() as f64 / 1e6,
        args.clients,
        args.session,
        args.fps,
        args.hours,
        args.trajectory,
        args.seed,
        loadavg(),
        nofile
    );
    let rt = tokio::runtime::Builder::new_multi_thread()
        .thread_name("soak-client")
        .enable_all()
        .build()?;
    let srv = ServerUnderTest::start(ServerMode::Subprocess, &db, args.server_bin.as_deref())?;
    let pid = srv.pid().context("the server runs as a subprocess")?;
    let hello = srv.hello();
    // The header, from one Welcome.
    let header = rt.block_on(async {
        let c = connect_many(srv.addr, &srv.fingerprint, &hello, 1, 1).await?;
        let c = c.into_iter().next().context("no connection")?;
        let w = c.welcome();
        let h = Header::decode(&w.header, Some(w.file_size))?;
        c.close();
        anyhow::Ok(h)
    })?;

    let live = Arc::new(Live::default());
    let churn = Arc::new(Churn::default());
    let stop = Arc::new(AtomicBool::new(false));
    let samples = Arc::new(Mutex::new(Vec::<Sample>::new()));
    let t0 = Instant::now();
    let cpu0 = proc_cpu_seconds(pid).unwrap_or(0.0);
    println!(
        "{:>8} {:>10} {:>10} {:>9} {:>5} {:>7} {:>9} {:>6} {:>11} {:>9} {:>6} {:>8}",
        "t (s)",
        "VmRSS MiB",
        "anon MiB",
        "huge MiB",
        "fds",
        "threads",
        "CPU %",
        "load",
        "requests",
        "MB",
        "errors",
        "sessions"
    );
    let monitor = {
        let (live, churn, stop, samples) =
            (live.clone(), churn.clone(), stop.clone(), samples.clone());
        let every = Duration::from_secs_f64(args.sample.max(0.5));
        std::thread::spawn(move || {
            let mut next = Instant::now();
            let mut last_cpu = (0.0f64, cpu0);
            while !stop.load(Ordering::Relaxed) {
                next += every;
                while Instant::now() < next {
                    if stop.load(Ordering::Relaxed) {
                        return;
                    }
                    std::thread::sleep(Duration::from_millis(100));
                }
                let t = t0.elapsed().as_secs_f64();
                let (vm_rss, anon) = proc_rss(pid).unwrap_or((0, 0));
                let cpu = proc_cpu_seconds(pid).unwrap_or(last_cpu.1);
                let s = Sample {
                    t,
                    vm_rss,
                    anon,
                    huge: proc_anon_huge(pid).unwrap_or(0),
                    fds: open_fds(pid).unwrap_or(0),
                    threads: proc_threads(pid).unwrap_or(0),
                    load1: load1().unwrap_or(f64::NAN),
                    cpu: cpu - cpu0,
                    requests: live.requests.load(Ordering::Relaxed),
                    bytes: live.bytes.load(Ordering::Relaxed),
                    errors: live.errors.load(Ordering::Relaxed)
                        + churn.connect_errors.load(Ordering::Relaxed),
                    sessions: churn.sessions.load(Ordering::Relaxed),
                };
                let pct = 100.0 * (cpu - last_cpu.1) / (t - last_cpu.0).max(1e-9);
                last_cpu = (t, cpu);
                println!(
                    "{:>8.0} {:>10.1} {:>10.1} {:>9.1} {:>5} {:>7} {:>9.1} {:>6.2} {:>11} {:>9.1} {:>6} {:>8}",
                    s.t,
                    s.vm_rss as f64 / 1048576.0,
                    s.anon as f64 / 1048576.0,
                    s.huge as f64 / 1048576.0,
                    s.fds,
                    s.threads,
                    pct,
                    s.load1,
                    s.requests,
                    s.bytes as f64 / 1e6,
                    s.errors,
                    s.sessions
                );
                samples.lock().unwrap_or_else(|p| p.into_inner()).push(s);
            }
        })
    };

    rt.block_on(async {
        let end = tokio::time::Instant::now() + Duration::from_secs_f64(seconds);
        let mut set = tokio::task::JoinSet::new();
        for k in 0..args.clients as u64 {
            set.spawn(slot(
                k,
                (srv.addr, srv.fingerprint.clone(), hello.clone()),
                header.clone(),
                base.clone(),
                args.clone(),
                end,
                live.clone(),
                churn.clone(),
            ));
        }
        while let Some(r) = set.join_next().await {
            if let Err(e) = r {
                churn.error(format!("slot task: {e}"));
                churn.lost.fetch_add(1, Ordering::Relaxed);
            }
        }
    });
    stop.store(true, Ordering::Relaxed);
    let _ = monitor.join();
    let alive = proc_rss(pid).is_some();
    drop(srv);
    rt.shutdown_timeout(Duration::from_secs(2));

    let samples = samples.lock().unwrap_or_else(|p| p.into_inner()).clone();
    let warm = (seconds * 0.1).clamp(60.0, 600.0);
    let after: Vec<&Sample> = samples.iter().filter(|s| s.t >= warm).collect();
    let anon_mib_h = slope(
        &after
            .iter()
            .map(|s| (s.t / 3600.0, s.anon as f64 / 1048576.0))
            .collect::<Vec<_>>(),
    );
    let fds_h = slope(
        &after
            .iter()
            .map(|s| (s.t / 3600.0, s.fds as f64))
            .collect::<Vec<_>>(),
    );
    let (fd_min, fd_max) = after
        .iter()
        .fold((u64::MAX, 0), |(a, b), s| (a.min(s.fds), b.max(s.fds)));
    let (anon_min, anon_max) = after
        .iter()
        .fold((u64::MAX, 0), |(a, b), s| (a.min(s.anon), b.max(s.anon)));
    let requests = live.requests.load(Ordering::Relaxed);
    let errors = live.errors.load(Ordering::Relaxed);
    let connect_errors = churn.connect_errors.load(Ordering::Relaxed);
    let sessions = churn.sessions.load(Ordering::Relaxed);
    let lost = churn.lost.load(Ordering::Relaxed);
    let first_error = churn
        .first_error
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .clone();
    let wall = t0.elapsed().as_secs_f64();
    println!(
        "soak over {:.2} h: {sessions} sessions, {requests} requests ({:.0}/s), {:.1} MB, \
         {errors} request errors, {connect_errors} connect errors, {lost} sessions lost",
        wall / 3600.0,
        requests as f64 / wall.max(1e-9),
        live.bytes.load(Ordering::Relaxed) as f64 / 1e6,
    );
    println!(
        "after the warm-up ({warm:.0} s): anon RSS {:.1}–{:.1} MiB, slope {anon_mib_h:+.2} MiB/h \
         (limit {:.1}); fds {fd_min}–{fd_max}, slope {fds_h:+.2}/h; server alive at the end: {alive}",
        anon_min as f64 / 1048576.0,
        anon_max as f64 / 1048576.0,
        args.max_growth,
    );
    if let Some(e) = &first_error {
        println!("first error: {e}");
    }
    let mut faults = Vec::new();
    if errors + connect_errors > 0 {
        faults.push(format!(
            "{errors} request errors, {connect_errors} connect errors"
        ));
    }
    if lost > 0 {
        faults.push(format!("{lost} sessions lost their connection"));
    }
    if !alive {
        faults.push("the server was not running at the end".into());
    }
    if after.len() < 10 {
        faults.push("fewer than 10 samples after the warm-up: too short to judge memory".into());
    }
    if anon_mib_h > args.max_growth {
        faults.push(format!(
            "anonymous RSS grows {anon_mib_h:.2} MiB/h (limit {:.1})",
            args.max_growth
        ));
    }
    // A descriptor leak grows with sessions; a few come and go with the
    // server's own work.
    if fd_max > fd_min + 16 && fds_h > 8.0 {
        faults.push(format!("open descriptors grow {fds_h:.1}/h"));
    }
    if let Some(path) = &args.json {
        let json = serde_json::json!({
            "hours": args.hours,
            "clients": args.clients,
            "session_s": args.session,
            "fps": args.fps,
            "trajectory": args.trajectory,
            "seed": args.seed,
            "db": db.display().to_string(),
            "wall_s": wall,
            "sessions": sessions,
            "requests": requests,
            "request_errors": errors,
            "connect_errors": connect_errors,
            "sessions_lost": lost,
            "warm_up_s": warm,
            "anon_rss_slope_mib_per_h": anon_mib_h,
            "fds_slope_per_h": fds_h,
            "faults": faults,
            "samples": samples.iter().map(|s| serde_json::json!({
                "t": s.t, "vm_rss": s.vm_rss, "anon": s.anon, "anon_huge": s.huge, "fds": s.fds,
                "threads": s.threads, "load1": s.load1,
                "cpu_s": s.cpu, "requests": s.requests, "bytes": s.bytes,
                "errors": s.errors, "sessions": s.sessions,
            })).collect::<Vec<_>>(),
        });
        std::fs::write(path, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    if !faults.is_empty() {
        bail!("soak failed: {}", faults.join("; "));
    }
    println!("soak passed: memory and descriptors flat, no error");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slope_of_a_line_and_of_noise() {
        let line: Vec<(f64, f64)> = (0..50).map(|i| (i as f64, 3.0 * i as f64 + 7.0)).collect();
        assert!((slope(&line) - 3.0).abs() < 1e-9);
        let flat: Vec<(f64, f64)> = (0..50)
            .map(|i| (i as f64, if i % 2 == 0 { 10.0 } else { 12.0 }))
            .collect();
        assert!(slope(&flat).abs() < 0.01);
        assert_eq!(slope(&[(1.0, 2.0)]), 0.0);
        assert_eq!(slope(&[(1.0, 2.0), (1.0, 5.0)]), 0.0);
    }
}
