//! `planet-bench flight`: error against run time and bytes, per link.

use crate::plot;
use crate::thread_cpu;
use anyhow::{bail, Context, Result};
use clap::Args;
use planet_client::net::{Connection, SessionConfig};
use planet_client::quality::{QualityConfig, QualityMode};
use planet_client::request_queue::QueueConfig;
use planet_client::streaming::StreamingClient;
use planet_client::trajectory::Trajectory;
use planet_client::ClientConfig;
use planet_linksim::{Link, LinkConfig};
use planet_preprocess::db::Sampler;
use planet_tests::{client_surface_elevation, probe_points, runtime, LocalServer};
use std::collections::HashMap;
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Args, Debug, Clone)]
pub struct FlightArgs {
    /// Database file (built there first with --procedural if missing).
    #[arg(long)]
    pub db: PathBuf,
    /// Build a procedural database at --db if it does not exist.
    #[arg(long)]
    pub procedural: bool,
    /// Levels of the procedural database.
    #[arg(long, default_value_t = 6)]
    pub levels: u8,
    /// Built-in trajectory name (rainier, everest, orbit, static-low) or file.
    #[arg(long, default_value = "rainier")]
    pub trajectory: String,
    /// Link specification (linksim syntax, e.g. "1mbit,100ms,2%loss" or
    /// "loopback"); repeat for several runs.
    #[arg(long = "link", required = true)]
    pub links: Vec<String>,
    /// Simulated frame rate (frames paced in real time).
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Output directory (CSV, PNG, summary).
    #[arg(long)]
    pub out: PathBuf,
    /// Quality-factor controller: regulate to this many triangles per frame
    /// (default: fixed QF).
    #[arg(long)]
    pub budget_triangles: Option<f64>,
    /// Initial (and, without --budget-triangles, fixed) quality factor
    /// (default: the client's default).
    #[arg(long)]
    pub qf: Option<f64>,
    /// Request queue size (requests in flight at most).
    #[arg(long)]
    pub queue: Option<usize>,
    /// Do not filter requests by the view predicted for their arrival
    /// (client/src/view_prediction.rs), for A/B comparisons.
    #[arg(long)]
    pub no_predict: bool,
    /// A returning client: connect once through the same link first (same
    /// TLS configuration and options), keep the session ticket and the
    /// address-validation token, close; the measured connection then
    /// resumes and sends its Hello as 0-RTT early data. The warm-up's link
    /// bytes are not counted.
    #[arg(long)]
    pub warm: bool,
    /// Stop after this many seconds of the trajectory.
    #[arg(long)]
    pub duration: Option<f64>,
    /// Probe grid (columns × rows of screen rays from the last camera).
    #[arg(long, default_value_t = 20)]
    pub probe_cols: usize,
    #[arg(long, default_value_t = 10)]
    pub probe_rows: usize,
    /// Viewport height in pixels (the width follows a 16:9 aspect).
    #[arg(long, default_value_t = 1080.0)]
    pub viewport_height: f64,
    /// Label of this run in the summary (default: the link spec).
    #[arg(long)]
    pub label: Option<String>,
}

/// One frame's measurements.
#[derive(Debug, Clone, Default)]
pub struct Row {
    pub frame: u64,
    pub t: f64,
    pub bytes_total: u64,
    pub bytes_frame: u64,
    pub in_flight: usize,
    pub sent: usize,
    pub cancelled: usize,
    pub cancelled_total: u64,
    pub blocks: usize,
    pub triangles: u64,
    pub qf: f64,
    pub sse_max: f64,
    pub sse_mean: f64,
    pub err_max: f64,
    pub err_mean: f64,
    pub probes: usize,
    pub relevant: f64,
    pub cpu_ms: f64,
    pub nodes: usize,
    pub connected: bool,
}

/// What the summary table shows for one link.
#[derive(Debug, Clone)]
pub struct Summary {
    pub label: String,
    pub first_frame_ms: f64,
    /// The measured connection resumed a session and its Hello went as
    /// 0-RTT early data (`--warm`).
    pub zero_rtt: bool,
    pub connect_ms: f64,
    pub sse_start_s: Option<f64>,
    pub sse_stop_s: Option<f64>,
    pub sse_final_stop_s: Option<f64>,
    pub bytes: u64,
    pub link_bytes_down: u64,
    pub relevant_pct: f64,
    /// Forced neighbour refines not drawn on arrival (part of the rest).
    pub forced_pct: f64,
    pub after_cancel_pct: f64,
    pub dropped_pct: f64,
    pub cancels: u64,
    pub requests: u64,
    pub cpu_mean_ms: f64,
    pub cpu_max_ms: f64,
    pub cpu_p99_ms: f64,
    pub final_sse_max: f64,
    pub final_err_max: f64,
    pub frames_late: u64,
    pub frames: u64,
}

/// Static segments of a trajectory: consecutive keyframes with equal poses.
fn static_segments(t: &Trajectory) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    for w in t.keyframes.windows(2) {
        let (a, b) = (w[0], w[1]);
        let same = a.lat_deg == b.lat_deg
            && a.lon_deg == b.lon_deg
            && a.alt_m == b.alt_m
            && a.heading_deg == b.heading_deg
            && a.pitch_deg == b.pitch_deg;
        if same {
            out.push((a.t, b.t));
        }
    }
    out
}

/// Seconds from `start` until max SSE ≤ 1 px (within `[start, end]`).
fn time_to_sse(rows: &[Row], start: f64, end: f64) -> Option<f64> {
    rows.iter()
        .filter(|r| r.t >= start - 1e-9 && r.t <= end + 1e-9)
        .find(|r| r.sse_max <= 1.0)
        .map(|r| r.t - start)
}

fn link_name(spec: &str) -> String {
    spec.chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect()
}

pub fn run(a: FlightArgs) -> Result<()> {
    if !a.db.exists() {
        if !a.procedural {
            bail!(
                "{} does not exist (use --procedural to build one)",
                a.db.display()
            );
        }
        eprintln!(
            "building a procedural database ({} levels) at {}",
            a.levels,
            a.db.display()
        );
        planet_tests::build_procedural_db(&a.db, a.levels, 1)?;
    }
    let traj = match Trajectory::builtin(&a.trajectory) {
        Some(t) => t,
        None => Trajectory::load(Path::new(&a.trajectory))
            .with_context(|| format!("trajectory {}", a.trajectory))?,
    };
    std::fs::create_dir_all(&a.out)?;
    let mut summaries = Vec::new();
    for spec in &a.links {
        let s = run_link(&a, &traj, spec)?;
        print_summary(std::slice::from_ref(&s));
        summaries.push(s);
    }
    let table = summary_table(&summaries);
    println!("\n{table}");
    let mut f = std::fs::File::create(a.out.join("summary.md"))?;
    writeln!(f, "{table}")?;
    Ok(())
}

fn run_link(a: &FlightArgs, traj: &Trajectory, spec: &str) -> Result<Summary> {
    let cfg: LinkConfig = spec.parse().with_context(|| format!("link {spec:?}"))?;
    let label = a.label.clone().unwrap_or_else(|| spec.to_string());
    eprintln!("== {label}: {}", a.db.display());
    let rt = runtime(2)?;
    let server = LocalServer::start(rt.handle(), &a.db)?;
    let link = rt.block_on(Link::start(
        server.addr(),
        cfg.clone().with_seed(1),
        cfg.with_seed(2),
    ))?;
    let mut client_cfg = ClientConfig {
        predict_view: !a.no_predict,
        ..ClientConfig::default()
    };
    if let Some(q) = a.queue {
        client_cfg.queue = QueueConfig {
            max_in_flight: q,
            ..client_cfg.queue
        };
    }
    if let Some(qf) = a.qf {
        client_cfg.quality.initial = qf;
    }
    if let Some(b) = a.budget_triangles {
        client_cfg.quality = QualityConfig {
            mode: QualityMode::TriangleBudget(b),
            ..client_cfg.quality
        };
    }
    let sampler = Sampler::open(&a.db)?;
    let datum = sampler.header().datum;
    let aspect = 16.0 / 9.0;
    let fov = 60f64.to_radians();
    let vh = a.viewport_height;
    let duration = a.duration.unwrap_or(traj.duration()).min(traj.duration());
    // Fixed probes: ground points seen by the last camera, with the
    // full-resolution elevation from the database.
    let last = traj.camera_at(duration, &datum, fov, aspect, vh);
    let lat0 = planet_core::cube::lat_lon_from_direction(last.eye.normalize().to_array()).0;
    let r_ground = datum.surface_radius(planet_core::cube::direction_from_lat_lon(lat0, 0.0));
    let mut cache = HashMap::new();
    let probes: Vec<(f64, f64, f64)> =
        probe_points(&last, &datum, r_ground, a.probe_cols, a.probe_rows)
            .into_iter()
            .filter_map(|(lat, lon)| {
                sampler
                    .sample_cached(lat, lon, &mut cache)
                    .ok()
                    .map(|s| (lat, lon, s.metres))
            })
            .collect();
    drop(cache);
    let session = server.session_config(link.local_addr())?;
    let warm_up_bytes = if a.warm {
        rt.block_on(warm_up(&session))?;
        link.stats().bytes_down
    } else {
        0
    };
    let t_connect = Instant::now();
    let mut sc =
        StreamingClient::connect(rt.handle(), session, client_cfg, Duration::from_secs(20))?;
    let connect_ms = t_connect.elapsed().as_secs_f64() * 1e3;

    let zero_rtt = sc.session().used_zero_rtt();
    eprintln!(
        "{} probes; connected in {connect_ms:.1} ms (0-RTT: {zero_rtt})",
        probes.len()
    );

    let mut rows: Vec<Row> = Vec::new();
    let mut first_frame_ms = f64::NAN;
    let start = Instant::now();
    let frames = (duration * a.fps).floor() as u64 + 1;
    let mut frames_late = 0;
    let mut prev_bytes = 0u64;
    for n in 0..frames {
        let t = n as f64 / a.fps;
        let due = start + Duration::from_secs_f64(t);
        let now = Instant::now();
        if due > now {
            std::thread::sleep(due - now);
        } else if now - due > Duration::from_secs_f64(1.0 / a.fps) {
            frames_late += 1;
        }
        let camera = traj.camera_at(t, &datum, fov, aspect, vh);
        let c0 = thread_cpu();
        let out = sc.frame(&camera, 1.0 / a.fps);
        let cpu = thread_cpu().saturating_sub(c0);
        if first_frame_ms.is_nan() && !out.draw.is_empty() {
            first_frame_ms = t_connect.elapsed().as_secs_f64() * 1e3;
        }
        let drawn: HashMap<_, _> = out.draw.iter().map(|d| (d.block, d.lod)).collect();
        let (mut emax, mut esum, mut np) = (0.0f64, 0.0, 0usize);
        for &(lat, lon, truth) in &probes {
            if let Some(h) = client_surface_elevation(sc.client.tree(), &drawn, lat, lon) {
                let e = (h - truth).abs();
                emax = emax.max(e);
                esum += e;
                np += 1;
            }
        }
        let bytes = sc.bytes_received();
        let st = &out.stats;
        rows.push(Row {
            frame: n,
            t,
            bytes_total: bytes,
            bytes_frame: bytes - prev_bytes,
            in_flight: st.in_flight,
            sent: st.sent,
            cancelled: st.cancelled,
            cancelled_total: st.totals.cancelled,
            blocks: st.blocks_drawn,
            triangles: st.triangles,
            qf: st.quality_factor,
            sse_max: st.max_screen_error,
            sse_mean: st.mean_screen_error,
            err_max: emax,
            err_mean: if np > 0 { esum / np as f64 } else { f64::NAN },
            probes: np,
            relevant: st.totals.relevant_ratio(),
            cpu_ms: cpu.as_secs_f64() * 1e3,
            nodes: st.nodes,
            connected: sc.is_connected(),
        });
        prev_bytes = bytes;
    }
    if std::env::var_os("PLANET_BENCH_DEBUG").is_some() {
        let camera = traj.camera_at(duration, &datum, fov, aspect, vh);
        let out = sc.frame(&camera, 1.0 / a.fps);
        let drawn: HashMap<_, _> = out.draw.iter().map(|d| (d.block, d.lod)).collect();
        for &(lat, lon, _) in probes.iter().take(200) {
            let fc = planet_core::cube::FaceCoord::from_lat_lon(lat.to_radians(), lon.to_radians());
            let mut id = planet_core::BlockId::root(fc.face);
            let et = sc.client.tree().elevation();
            while et.get(&id).is_some_and(|n| n.split) {
                let n = (1u64 << id.level) as f64;
                let kx = usize::from((fc.s * n - id.x as f64) >= 0.5);
                let ky = usize::from((fc.t * n - id.y as f64) >= 0.5);
                id = id.child(kx | (ky << 1));
            }
            let p = glam::DVec3::from_array(datum.position(
                planet_core::cube::direction_from_lat_lon(lat.to_radians(), lon.to_radians()),
                0.0,
            ));
            eprintln!(
                "probe {lat:.3} {lon:.3} leaf {id:?} drawn {:?} dist {:.0} km",
                drawn.get(&id),
                (p - camera.eye).length() / 1e3
            );
        }
    }
    let counters = sc.counters();
    let totals = sc.client.totals();
    let link_stats = link.stats();
    sc.close();
    drop(link);
    drop(server);

    let name = link_name(&label);
    write_csv(&a.out.join(format!("flight-{name}.csv")), &rows)?;
    plot::flight_plot(
        &a.out.join(format!("flight-{name}.png")),
        &format!("{} — {label}", a.trajectory),
        &rows,
    )?;

    let segs = static_segments(traj);
    let seg_start = segs.first().copied();
    // The first stop after the trajectory moved, and the last stop.
    let moved: Vec<(f64, f64)> = segs
        .iter()
        .copied()
        .filter(|s| seg_start.is_none_or(|f| s.0 > f.0) && s.1 - s.0 >= 5.0)
        .collect();
    let mut cpu: Vec<f64> = rows.iter().map(|r| r.cpu_ms).collect();
    cpu.sort_by(f64::total_cmp);
    let p99 = cpu[((cpu.len() as f64 * 0.99) as usize).min(cpu.len() - 1)];
    let b = counters.bytes_received.max(1) as f64;
    let lastrow = rows.last().cloned().unwrap_or_default();
    Ok(Summary {
        label,
        first_frame_ms,
        connect_ms,
        sse_start_s: seg_start.and_then(|s| time_to_sse(&rows, s.0, s.1.min(duration))),
        sse_stop_s: moved
            .first()
            .and_then(|s| time_to_sse(&rows, s.0, s.1.min(duration))),
        sse_final_stop_s: moved
            .last()
            .filter(|_| moved.len() > 1)
            .and_then(|s| time_to_sse(&rows, s.0, s.1.min(duration))),
        bytes: counters.bytes_received,
        link_bytes_down: link_stats.bytes_down - warm_up_bytes,
        zero_rtt,
        relevant_pct: 100.0 * totals.relevant_ratio(),
        forced_pct: 100.0 * totals.forced_ratio(),
        after_cancel_pct: 100.0 * counters.bytes_after_cancel as f64 / b,
        dropped_pct: 100.0 * totals.bytes_dropped as f64 / b,
        cancels: counters.cancels,
        requests: counters.requests,
        cpu_mean_ms: cpu.iter().sum::<f64>() / cpu.len() as f64,
        cpu_max_ms: cpu.last().copied().unwrap_or(0.0),
        cpu_p99_ms: p99,
        final_sse_max: lastrow.sse_max,
        final_err_max: lastrow.err_max,
        frames_late,
        frames,
    })
}

/// One connection through the link that is closed again once the server's
/// session tickets and address-validation tokens (sent after the handshake)
/// have had time to arrive: what a returning client has kept.
async fn warm_up(session: &SessionConfig) -> Result<()> {
    let (conn, _) = Connection::connect_with(
        session.addr,
        &session.server_name,
        Arc::clone(&session.tls),
        session.hello.clone(),
        &session.options,
    )
    .await
    .context("warm-up connection")?;
    // Tickets and tokens follow the handshake by about one round trip;
    // one second covers every link of the benchmark, losses included.
    tokio::time::sleep(Duration::from_secs(1)).await;
    conn.close();
    Ok(())
}

fn write_csv(path: &Path, rows: &[Row]) -> Result<()> {
    let mut s = String::from(
        "frame,t_s,bytes_total,bytes_frame,in_flight,sent,cancelled,cancelled_total,blocks,triangles,quality_factor,sse_max_px,sse_mean_px,true_err_max_m,true_err_mean_m,probes,relevant_ratio,cpu_ms,nodes,connected\n",
    );
    for r in rows {
        let _ = writeln!(
            s,
            "{},{:.4},{},{},{},{},{},{},{},{},{:.1},{:.4},{:.4},{:.3},{:.3},{},{:.5},{:.4},{},{}",
            r.frame,
            r.t,
            r.bytes_total,
            r.bytes_frame,
            r.in_flight,
            r.sent,
            r.cancelled,
            r.cancelled_total,
            r.blocks,
            r.triangles,
            r.qf,
            r.sse_max,
            r.sse_mean,
            r.err_max,
            r.err_mean,
            r.probes,
            r.relevant,
            r.cpu_ms,
            r.nodes,
            u8::from(r.connected)
        );
    }
    std::fs::write(path, s)?;
    Ok(())
}

fn fmt_s(v: Option<f64>) -> String {
    v.map_or("not reached".into(), |s| format!("{s:.2} s"))
}

pub fn summary_table(ss: &[Summary]) -> String {
    let mut t = String::new();
    let _ = writeln!(
        t,
        "| link | first frame (connect) | SSE ≤ 1 px after start | after 1st stop | after last stop | bytes | link bytes down | relevant (forced neighbours) | after cancel | dropped | requests / cancels | CPU/frame mean / p99 / max | final max SSE / true err | late frames |"
    );
    let _ = writeln!(
        t,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for s in ss {
        let _ = writeln!(
            t,
            "| {}{} | {:.0} ms ({:.0} ms) | {} | {} | {} | {:.2} MB | {:.2} MB | {:.2} % ({:.2} %) | {:.2} % | {:.2} % | {} / {} | {:.3} / {:.3} / {:.3} ms | {:.2} px / {:.1} m | {} / {} |",
            s.label,
            if s.zero_rtt { " (0-RTT)" } else { "" },
            s.first_frame_ms,
            s.connect_ms,
            fmt_s(s.sse_start_s),
            fmt_s(s.sse_stop_s),
            fmt_s(s.sse_final_stop_s),
            s.bytes as f64 / 1e6,
            s.link_bytes_down as f64 / 1e6,
            s.relevant_pct,
            s.forced_pct,
            s.after_cancel_pct,
            s.dropped_pct,
            s.requests,
            s.cancels,
            s.cpu_mean_ms,
            s.cpu_p99_ms,
            s.cpu_max_ms,
            s.final_sse_max,
            s.final_err_max,
            s.frames_late,
            s.frames
        );
    }
    t
}

fn print_summary(ss: &[Summary]) {
    eprintln!("{}", summary_table(ss));
}
