//! `planet-bench flight`: error against run time and bytes, per link and
//! per client policy, in one invocation.
//!
//! Every (link, policy) run flies the same trajectory against a fresh
//! in-process server through a fresh simulated link with the same seeds, so
//! the policies (`--policy`: ours, thesis, cesium, breadth; see
//! `client/src/refinement.rs`) differ only in how they schedule. Outputs in
//! `--out`: a CSV per run, one PNG per link with every policy overlaid
//! (max and mean SSE and true error against time, max SSE against bytes),
//! `summary.md` and `summary.json` (one object per run).
//!
//! The error of a frame is the screen-space error (SSE) of each drawn
//! block, and its mean is taken over the screen's pixels: each drawn block
//! weighted by its approximate screen area (`error_integral_px_s` = ∫ that
//! mean dt, the error of the average pixel: the Speed Index's ∫ (1 − visual
//! completeness) dt, docs/REFERENCES.md "Measures", weighs pixels too). The
//! mean over drawn blocks (`block_error_integral_px_s`) is reported beside
//! it but is not a convergence measure: it weighs a block a
//! few pixels wide like one that fills half the screen, so it changes with
//! how a policy tiles the view, not only with the image, and it can rise
//! when every pixel gets better. Nine blocks at 0 px and one at 100 px
//! average 10 px; refining the last into four children at 65 px makes every
//! one of its pixels better and the block mean 20 px (the pixel mean goes
//! from the 100 px block's share of the screen × 100 to × 65).
//!
//! Before the runs, the flight is replayed over the database file with
//! every request answered at once ([`InstantReplay`]): the default policy
//! converged at the tolerance at each frame. It gives the bytes the path
//! needs (`needed_over_delivered`), the error the tolerance leaves whatever
//! the link (`floor_error_integral_px_s`; a run's
//! `excess_error_integral_px_s` is its integral less this floor: the error
//! of data not yet arrived, the part scheduling can change), and a lower
//! bound on the time to the tolerance at a stop at t = 0
//! (`start_lower_bound_s`: a record's place is in its parent, so the start
//! view's deepest record is a chain of round trips, two levels each at
//! most with the child tables of `LodRefsRequest`).
//!
//! Per link, the same replay with each record answered only at the round
//! trip that could first bring it ([`earliest_trip`]) gives a lower bound
//! on any client's integral over that link's round-trip time
//! (`round_trip_bound_error_integral_px_s`, [`round_trip_bound`]): the
//! floor, and the error of the levels that no round trip could have
//! brought yet. Where it is above half of a peer's integral, no scheduler
//! of this protocol can halve that peer's error.
//!
//! The stops' times (`time_to_1px_after_stops_s`) measure the geometry, as
//! the issue defines them. Colour is the other half of what is drawn, and
//! policies order the two trees differently (`ours` weighs a colour
//! record's texels as screen displacement and may load a coarse colour
//! before a near-tolerance elevation record): each frame also records the
//! largest projected texel of the drawn colour (`colour_texel_max_px`,
//! [`Client::colour_screen_error`], 0 where it is at its finest data), and
//! `time_to_1px_with_colour_after_stops_s` is the time until geometry and
//! colour are both within the tolerance.
//!
//! `--transport` (repeatable) adds the transport as a dimension: `quic`
//! (planet-server in process, through the UDP relay) and `http2` (the same
//! file served by nginx over HTTPS byte ranges, through the TCP link: kernel
//! TCP in a network namespace, shaped packet by packet by the same shaper
//! and seeds as the UDP relay; `planet_linksim::TcpLink`). Only the
//! transport differs: same client, policies, database, trajectory and link.
//! Each sender runs its own default congestion control: BBR in
//! planet-server (`--congestion`), CUBIC, the Linux kernel's default, for
//! nginx's TCP (`--tcp-congestion`, set on the namespace's route, so the
//! host's own default does not leak in); `summary.json` names it
//! (`congestion`).

use crate::plot;
use crate::thread_cpu;
use anyhow::{bail, Context, Result};
use clap::Args;
use planet_client::quality::{QualityConfig, QualityMode};
use planet_client::trajectory::Trajectory;
use planet_client::{Client, ClientConfig, Policy};
use planet_core::format::DbFile;
use planet_core::BlockId;
use planet_linksim::{Link, LinkConfig, TcpLink};
use planet_preprocess::db::Sampler;
use planet_session::http::HttpSessionConfig;
use planet_session::net::{Connection, SessionConfig};
use planet_session::streaming::StreamingClient;
use planet_testkit::harness::{client_surface_elevation, probe_points, runtime, LocalServer};
use serde::Serialize;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Args, Debug, Clone)]
pub struct FlightArgs {
    /// Database file (built there first with --procedural if missing);
    /// repeat to fly the same links and policies over several databases
    /// (e.g. one codec against another) in one invocation.
    #[arg(long = "db", required = true)]
    pub dbs: Vec<PathBuf>,
    /// The database of the run in progress (one of `dbs`).
    #[arg(skip)]
    pub db: PathBuf,
    /// Build a procedural database at --db if it does not exist.
    #[arg(long)]
    pub procedural: bool,
    /// Levels of the procedural database.
    #[arg(long, default_value_t = 6)]
    pub levels: u8,
    /// Detail regions of the procedural database built with --procedural
    /// (`LAT,LON,RADIUS_KM,LEVEL`, repeatable; see `planet-build build
    /// --detail`).
    #[arg(long = "detail")]
    pub detail: Vec<planet_preprocess::DetailRegion>,
    #[arg(long, default_value = "rainier", help = planet_client::trajectory::TRAJECTORY_HELP)]
    pub trajectory: String,
    /// Client policy (ours, thesis, cesium, breadth); repeat to run several
    /// on the same database, link and trajectory.
    #[arg(long = "policy", default_value = "ours")]
    pub policies: Vec<Policy>,
    /// Pixel tolerance of the screen-space error, for every policy that has
    /// one (Cesium's maximumScreenSpaceError is set to it too).
    #[arg(long, default_value_t = planet_client::refinement::DEFAULT_MAX_SSE_PX)]
    pub max_sse: f64,
    /// Budget of resident samples in MB (default: none).
    #[arg(long)]
    pub memory: Option<f64>,
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
    /// The thesis policy's triangle budget per frame (its QF law, thesis
    /// §4.6: 2 million triangles on the high-end client).
    #[arg(long, default_value_t = THESIS_TRIANGLES)]
    pub thesis_triangles: f64,
    /// Do not filter requests by the view predicted for their arrival
    /// (client/src/view_prediction.rs), for A/B comparisons.
    #[arg(long)]
    pub no_predict: bool,
    /// Skip the instant replay (the flight over the database file with
    /// every request answered at once), which gives the bytes needed, the
    /// error floor and the start's lower bound.
    #[arg(long)]
    pub no_needed: bool,
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
    /// The server's congestion controller (`cubic` or `bbr`; default: the
    /// server's default, `congestion` in docs/DEPLOY.md's server.toml).
    #[arg(long)]
    pub congestion: Option<String>,
    /// Transports to fly, each with every link and policy: `quic`
    /// (planet-server) and `http2` (nginx byte ranges through the TCP link;
    /// needs root, /dev/net/tun and iproute2).
    #[arg(long = "transport", value_enum, default_value = "quic")]
    pub transports: Vec<Transport>,
    /// nginx binary for `--transport http2`.
    #[arg(long, default_value = planet_testkit::nginx::NGINX_BIN)]
    pub nginx_bin: PathBuf,
    /// TCP congestion control of nginx's connections for `--transport
    /// http2`: `cubic`, the Linux kernel's default since 2.6.19
    /// (`CONFIG_DEFAULT_TCP_CONG`), which a stock nginx host runs; `bbr`,
    /// which some CDNs run; or `system`, whatever this host's default is
    /// (this project's VM defaults to BBR).
    #[arg(long, default_value = "cubic")]
    pub tcp_congestion: String,
}

/// How the client reaches the database.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Transport {
    /// planet-server over QUIC.
    Quic,
    /// nginx over HTTP/2 (TLS over kernel TCP) byte ranges.
    Http2,
}

impl std::fmt::Display for Transport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Transport::Quic => "quic",
            Transport::Http2 => "http2",
        })
    }
}

/// The thesis's triangle budget on its high-end client (§4.6, 2 M).
pub const THESIS_TRIANGLES: f64 = 2.0e6;

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
    /// Largest projected texel size of the drawn colour, px (0 where it is
    /// at its finest data; [`planet_client::Client::colour_screen_error`]).
    pub colour_max: f64,
    pub sse_mean: f64,
    pub sse_pixel_mean: f64,
    /// The instant replay's per-pixel mean SSE at this frame (NaN without
    /// it): the floor under `sse_pixel_mean`.
    pub sse_pixel_floor: f64,
    pub err_max: f64,
    pub err_mean: f64,
    pub probes: usize,
    pub relevant: f64,
    pub cpu_ms: f64,
    pub nodes: usize,
    pub connected: bool,
}

/// What the summary table shows for one run.
#[derive(Debug, Clone)]
pub struct Summary {
    pub label: String,
    pub transport: Transport,
    /// The sender's congestion control (server's for QUIC, TCP's for
    /// HTTP/2).
    pub congestion: String,
    /// The database's file stem.
    pub db: String,
    pub policy: Policy,
    /// ∫ per-pixel mean SSE dt (drawn blocks weighted by screen area) and
    /// ∫ max SSE dt over the flight (px·s).
    pub error_integral: f64,
    pub max_sse_integral: f64,
    /// ∫ mean SSE over drawn blocks dt (unweighted; see the module doc).
    pub block_error_integral: f64,
    /// Per stop (static segment): its start and the time to max SSE ≤ the
    /// tolerance from it (`None`: not reached during the stop).
    pub stops: Vec<(f64, Option<f64>)>,
    /// Per stop: the time until the colour meets the tolerance too (the
    /// largest drawn texel at most the tolerance in pixels, or at its
    /// finest data), `None` if not during the stop. At least the stop's
    /// geometric time.
    pub stops_with_colour: Vec<Option<f64>>,
    pub wasted_pct: f64,
    /// Of the wasted bytes, those dropped on arrival or rejected (the rest
    /// were applied and never drawn).
    pub dropped_pct: f64,
    /// Of the wasted bytes, child tables never used (`ours`' lookahead).
    pub unused_tables_pct: f64,
    pub needed_over_delivered: Option<f64>,
    /// ∫ dt of the per-pixel mean SSE that the instant replay draws
    /// ([`InstantReplay::floor`]): the error the tolerance leaves.
    pub floor_integral: Option<f64>,
    /// [`InstantReplay::start_bound_s`] for this link.
    pub start_bound_s: Option<f64>,
    /// [`round_trip_bound`] for this link's round trip: no client of the
    /// protocol has a smaller `error_integral`.
    pub round_trip_bound: Option<f64>,
    pub first_frame_ms: f64,
    /// The measured connection resumed a session and its Hello went as
    /// 0-RTT early data (`--warm`).
    pub zero_rtt: bool,
    pub connect_ms: f64,
    pub bytes: u64,
    pub link_bytes_down: u64,
    pub relevant_pct: f64,
    /// Forced neighbour refines not drawn on arrival (part of the rest).
    pub forced_pct: f64,
    pub cancels: u64,
    pub requests: u64,
    pub cpu_mean_ms: f64,
    pub cpu_p99_ms: f64,
    pub final_sse_max: f64,
    pub final_err_max: f64,
    pub frames_late: u64,
    pub frames: u64,
}

impl Summary {
    /// `error_integral` less the floor's: the error of data not yet
    /// arrived, the part a scheduler changes.
    pub fn excess_integral(&self) -> Option<f64> {
        self.floor_integral.map(|f| self.error_integral - f)
    }
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

/// Seconds from `start` to the first row within `[start, end]` that
/// `met` accepts (e.g. max SSE ≤ the tolerance).
fn time_to(rows: &[Row], start: f64, end: f64, met: impl Fn(&Row) -> bool) -> Option<f64> {
    rows.iter()
        .filter(|r| r.t >= start - 1e-9 && r.t <= end + 1e-9)
        .find(|r| met(r))
        .map(|r| r.t - start)
}

fn link_name(spec: &str) -> String {
    spec.chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect()
}

/// One line of `summary.json`.
#[derive(Debug, Serialize)]
struct JsonSummary<'a> {
    db: &'a str,
    link: &'a str,
    transport: Transport,
    /// The sender's congestion control: planet-server's for QUIC, nginx's
    /// TCP for HTTP/2.
    congestion: &'a str,
    policy: &'a str,
    trajectory: &'a str,
    max_sse_px: f64,
    /// ∫ per-pixel mean SSE dt.
    error_integral_px_s: f64,
    max_sse_integral_px_s: f64,
    /// ∫ mean SSE over drawn blocks dt.
    block_error_integral_px_s: f64,
    stops_s: Vec<f64>,
    time_to_1px_after_stops_s: Vec<Option<f64>>,
    /// Per stop: the time until the drawn colour's texels are within the
    /// tolerance as well (geometry and colour both converged).
    time_to_1px_with_colour_after_stops_s: Vec<Option<f64>>,
    bytes: u64,
    link_bytes: u64,
    relevant_ratio: f64,
    wasted_ratio: f64,
    /// Part of `wasted_ratio` dropped on arrival or rejected; the rest was
    /// applied and never drawn.
    dropped_ratio: f64,
    /// Part of `wasted_ratio` that is child tables never used.
    unused_tables_ratio: f64,
    requests: u64,
    cancels: u64,
    needed_over_delivered: Option<f64>,
    needed_bytes: Option<u64>,
    /// ∫ per-pixel mean SSE dt of the same flight with every request
    /// answered at once: the error the tolerance leaves, which no
    /// scheduling removes.
    floor_error_integral_px_s: Option<f64>,
    /// `error_integral_px_s` − `floor_error_integral_px_s`: the error of
    /// data not yet arrived.
    excess_error_integral_px_s: Option<f64>,
    /// A lower bound on `error_integral_px_s` for any client of the
    /// protocol over this link ([`round_trip_bound`]): the floor, and the
    /// error of the levels no round trip could have brought yet.
    round_trip_bound_error_integral_px_s: Option<f64>,
    /// A lower bound on `time_to_1px_after_stops_s` of a stop at t = 0
    /// ([`InstantReplay::start_bound_s`]: the start chain's round trips, or
    /// one round trip and the start view's elevation bytes at the link's
    /// rate).
    start_lower_bound_s: Option<f64>,
    first_frame_ms: f64,
    final_sse_max_px: f64,
    cpu_mean_ms: f64,
    cpu_p99_ms: f64,
    frames_late: u64,
}

pub fn run(args: FlightArgs) -> Result<()> {
    let traj = Trajectory::from_spec(&args.trajectory)?;
    std::fs::create_dir_all(&args.out)?;
    let several = args.dbs.len() > 1;
    let mut summaries = Vec::new();
    let mut needed_per_db = Vec::new();
    // Per database: its instant replay's floor (the plot's, with one).
    let mut floors: Vec<Option<Vec<f64>>> = Vec::new();
    // Per link: every (database, policy) run, for one overlaid plot.
    let mut per_link: Vec<Vec<(String, Vec<Row>)>> = vec![Vec::new(); args.links.len()];
    for db in &args.dbs {
        let a = FlightArgs {
            db: db.clone(),
            ..args.clone()
        };
        if !a.db.exists() {
            if !a.procedural {
                bail!(
                    "{} does not exist (use --procedural to build one)",
                    a.db.display()
                );
            }
            eprintln!(
                "building a procedural database ({} levels{}) at {}",
                a.levels,
                if a.detail.is_empty() {
                    String::new()
                } else {
                    format!(", {} detail regions", a.detail.len())
                },
                a.db.display()
            );
            planet_testkit::harness::build_procedural_db_with_detail(
                &a.db, a.levels, 1, &a.detail,
            )?;
        }
        let needed = if a.no_needed {
            None
        } else {
            let t0 = Instant::now();
            let r = instant_replay(&a, &traj)?;
            eprintln!(
                "{}: bytes needed for ≤ {} px along the path (instant delivery): {:.2} MB, \
                 {:.1} kB of elevation in a chain of {} at the start, floor ∫ {:.1} px·s \
                 ({:.1} s)",
                a.db.display(),
                a.max_sse,
                r.needed as f64 / 1e6,
                r.start_elevation as f64 / 1e3,
                r.start_chain,
                r.floor_integral(a.fps),
                t0.elapsed().as_secs_f64()
            );
            Some(r)
        };
        // The database file for the round-trip bounds, opened once.
        let file = match &needed {
            Some(_) => {
                Some(DbFile::open(&a.db).with_context(|| format!("opening {}", a.db.display()))?)
            }
            None => None,
        };
        let transports = a.transports.len() > 1;
        for (k, spec) in a.links.iter().enumerate() {
            let bound = match (&needed, &file) {
                (Some(r), Some(file)) => {
                    let cfg: LinkConfig = spec.parse().with_context(|| format!("link {spec:?}"))?;
                    let t0 = Instant::now();
                    let rtt = 2.0 * cfg.delay.as_secs_f64();
                    let b = round_trip_bound(file, &a, &traj, rtt, &r.floor)?;
                    eprintln!(
                        "{spec}: round-trip bound ∫ {b:.1} px·s ({:.1} s)",
                        t0.elapsed().as_secs_f64()
                    );
                    Some(b)
                }
                _ => None,
            };
            for (&transport, &policy) in a
                .transports
                .iter()
                .flat_map(|t| a.policies.iter().map(move |p| (t, p)))
            {
                let (mut s, rows) = run_link(&a, &traj, spec, transport, policy, needed.as_ref())?;
                s.round_trip_bound = bound;
                print_summary(std::slice::from_ref(&s));
                let mut name = policy.name().to_string();
                if transports {
                    name = format!("{name} / {transport}");
                }
                if several {
                    name = format!("{name} @ {}", s.db);
                }
                per_link[k].push((name, rows));
                needed_per_db.push(needed.as_ref().map(|r| r.needed));
                summaries.push(s);
            }
        }
        floors.push(needed.map(|r| r.floor));
    }
    // The floor in the plot when one database was flown.
    let floor: Option<Vec<(f64, f64)>> = match floors.as_slice() {
        [Some(f)] => Some(
            f.iter()
                .enumerate()
                .map(|(n, &y)| (n as f64 / args.fps, y))
                .collect(),
        ),
        _ => None,
    };
    for (spec, runs) in args.links.iter().zip(&per_link) {
        let label = args.label.clone().unwrap_or_else(|| spec.to_string());
        plot::policies_plot(
            &args.out.join(format!("flight-{}.png", link_name(&label))),
            &format!(
                "{} — {label} — max SSE {} px",
                args.trajectory, args.max_sse
            ),
            runs,
            args.max_sse,
            floor.as_deref(),
        )?;
    }
    let a = &args;
    let mut json = Vec::new();
    for (s, &needed) in summaries.iter().zip(&needed_per_db) {
        json.push(JsonSummary {
            db: &s.db,
            link: &s.label,
            transport: s.transport,
            congestion: &s.congestion,
            policy: s.policy.name(),
            trajectory: &a.trajectory,
            max_sse_px: a.max_sse,
            error_integral_px_s: s.error_integral,
            max_sse_integral_px_s: s.max_sse_integral,
            block_error_integral_px_s: s.block_error_integral,
            stops_s: s.stops.iter().map(|x| x.0).collect(),
            time_to_1px_after_stops_s: s.stops.iter().map(|x| x.1).collect(),
            time_to_1px_with_colour_after_stops_s: s.stops_with_colour.clone(),
            bytes: s.bytes,
            link_bytes: s.link_bytes_down,
            relevant_ratio: s.relevant_pct / 100.0,
            wasted_ratio: s.wasted_pct / 100.0,
            dropped_ratio: s.dropped_pct / 100.0,
            unused_tables_ratio: s.unused_tables_pct / 100.0,
            requests: s.requests,
            cancels: s.cancels,
            needed_over_delivered: s.needed_over_delivered,
            needed_bytes: needed,
            floor_error_integral_px_s: s.floor_integral,
            excess_error_integral_px_s: s.excess_integral(),
            round_trip_bound_error_integral_px_s: s.round_trip_bound,
            start_lower_bound_s: s.start_bound_s,
            first_frame_ms: s.first_frame_ms,
            final_sse_max_px: s.final_sse_max,
            cpu_mean_ms: s.cpu_mean_ms,
            cpu_p99_ms: s.cpu_p99_ms,
            frames_late: s.frames_late,
        });
    }
    let table = summary_table(&summaries);
    println!("\n{table}");
    let mut f = std::fs::File::create(a.out.join("summary.md"))?;
    writeln!(f, "{table}")?;
    std::fs::write(
        a.out.join("summary.json"),
        serde_json::to_string_pretty(&json)?,
    )?;
    Ok(())
}

/// The client configuration of `policy` for this benchmark: the policy's
/// own defaults (`ClientConfig::for_policy`), the thesis with its QF law
/// (a triangle budget).
fn client_config(a: &FlightArgs, policy: Policy) -> ClientConfig {
    let mut cfg = ClientConfig::for_policy(policy, a.max_sse);
    cfg.memory_budget = a.memory.map(|mb| (mb.max(0.0) * 1e6) as u64);
    if a.no_predict {
        cfg.predict_view = false;
    }
    if policy == Policy::Thesis {
        cfg.quality = QualityConfig {
            mode: QualityMode::TriangleBudget(a.thesis_triangles),
            ..cfg.quality
        };
    }
    cfg
}

/// The flight replayed with every request answered at once (the link no
/// limit): the same trajectory, frame by frame at `--fps`, over the
/// database file, the default policy converged at the tolerance at each
/// frame before the next.
#[derive(Debug, Clone, Default)]
pub struct InstantReplay {
    /// Bytes of every record it fetched along the path, each counted once:
    /// what the flight needs for the tolerance when the link is not the
    /// limit.
    pub needed: u64,
    /// Elevation bytes the first frame's view needs from nothing for the
    /// tolerance ([`start_needs`]): what any policy must receive before
    /// the view meets it at the start (a child's place and error are in
    /// its parent). 0 where the first frame met it before any record
    /// arrived.
    pub start_elevation: u64,
    /// The longest chain of those records: the deepest one's level + 1. A
    /// record's place in the file is in its parent (docs/FORMAT.md), and
    /// the child tables of a `LodRefsRequest` (docs/PROTOCOL.md §4.8) reach
    /// one level further: the root's round trip, then two levels per round
    /// trip at most.
    pub start_chain: u32,
    /// Per frame: the per-pixel mean SSE of its converged view, the error
    /// that remains at the tolerance whatever the link.
    pub floor: Vec<f64>,
}

impl InstantReplay {
    /// ∫ floor dt: the part of a run's `error_integral_px_s` that the
    /// tolerance leaves, which no scheduling removes.
    pub fn floor_integral(&self, fps: f64) -> f64 {
        self.floor.iter().sum::<f64>() / fps
    }

    /// A lower bound on the time to the tolerance at a stop that starts
    /// at t = 0 over `link` (0 where the first frame meets it before any
    /// record arrives): the larger of the round trips of
    /// [`InstantReplay::start_chain`] (one for the root, then one per two
    /// levels) and one round trip plus the start's
    /// elevation bytes at the link's rate (framing, the congestion
    /// controller's start-up and decoding left out). `None` for an
    /// unlimited link.
    pub fn start_bound_s(&self, link: &LinkConfig) -> Option<f64> {
        let rtt = 2.0 * link.delay.as_secs_f64();
        if self.start_chain == 0 {
            return Some(0.0);
        }
        link.bandwidth_bps.filter(|&b| b > 0).map(|b| {
            let deepest = u8::try_from(self.start_chain - 1).unwrap_or(u8::MAX);
            let trips = earliest_trip(deepest);
            (f64::from(trips) * rtt).max(rtt + self.start_elevation as f64 * 8.0 / b as f64)
        })
    }
}

/// The round trip, counted from a first request at t = 0 with only the
/// header known, before which no client of the protocol can hold a record
/// of `level`: a record's place is in its parent's record
/// (docs/FORMAT.md), the roots' in the header, and a `LodRefsRequest`
/// (docs/PROTOCOL.md §4.8) brings the references one level further. The
/// roots arrive after the first round trip with their grandchildren's
/// references, then two levels per round trip: level `L` after
/// `1 + ⌈L/2⌉`.
pub fn earliest_trip(level: u8) -> u32 {
    1 + u32::from(level).div_ceil(2)
}

/// A lower bound on any client's `error_integral_px_s` over a link of
/// round-trip time `rtt` (s): the flight replayed over the database as in
/// [`instant_replay`], but each record answered only once the link's
/// round trips could have brought it ([`earliest_trip`]), and at once from
/// then on (the link's rate, framing, the congestion controller's start-up
/// and decoding left out). Each frame is the default client converged at
/// the tolerance with the records due by its time; from the round trip
/// that can bring the deepest level on, that is the floor (`floor`, one
/// per frame, whose length sets the flight's). It is the floor's integral
/// plus the error of the levels no round trip could have brought yet: the
/// start from orbit, where each level costs a round trip whatever the
/// scheduler. Where it is above half of a policy's integral, no client of
/// this protocol can have half that policy's error.
pub fn round_trip_bound(
    db: &DbFile,
    a: &FlightArgs,
    traj: &Trajectory,
    rtt: f64,
    floor: &[f64],
) -> Result<f64> {
    let deepest = db
        .header
        .colour
        .as_ref()
        .map_or(0, |c| c.max_level)
        .max(db.header.elevation.max_level);
    let all_due = f64::from(earliest_trip(deepest)) * rtt;
    let mut client = Client::new(db.header.clone(), replay_config(a))?;
    // Requests not due yet: id → the round trip that can answer them.
    let mut parked: HashMap<u64, (u32, planet_core::format::ChildRef)> = HashMap::new();
    let mut sum = 0.0;
    for (n, &f) in floor.iter().enumerate() {
        let t = n as f64 / a.fps;
        if t >= all_due {
            sum += f;
            continue;
        }
        // (A nanosecond of slack: frame times and round trips are sums of
        // decimals, and the bound must not miss a due frame by a rounding.)
        let due = |trip: u32| f64::from(trip) * rtt <= t + 1e-9;
        let camera = flight_camera(traj, t, &db.header.datum, a);
        let ready: Vec<(u64, planet_core::format::ChildRef)> = parked
            .iter()
            .filter(|(_, (trip, _))| due(*trip))
            .map(|(&id, &(_, r))| (id, r))
            .collect();
        let mut delivered = !ready.is_empty();
        for (id, r) in ready {
            parked.remove(&id);
            client.deliver(id, Ok(read(db, &r)?));
        }
        // As `converge`, but holding what is not due, and one more frame
        // after every frame that answered something.
        let mut last = 0.0;
        for _ in 0..400 {
            let out = client.frame(&camera, 1.0 / a.fps);
            last = out.stats.pixel_mean_screen_error;
            for id in &out.cancel {
                parked.remove(id);
            }
            let before = delivered;
            delivered = false;
            for s in &out.send {
                let trip = earliest_trip(s.block.level);
                if due(trip) {
                    client.deliver(s.id, Ok(read(db, &s.record)?));
                    delivered = true;
                } else {
                    parked.insert(s.id, (trip, s.record));
                }
            }
            client.recycle(out.draw);
            if !before && !delivered && client.pending_ops().is_empty() {
                break;
            }
        }
        sum += last;
    }
    Ok(sum / a.fps)
}

/// The camera of the flight at `t`: 60° vertical field of view, 16:9, the
/// viewport's height of `--viewport-height`.
fn flight_camera(
    traj: &Trajectory,
    t: f64,
    datum: &planet_core::Datum,
    a: &FlightArgs,
) -> planet_client::Camera {
    traj.camera_at(t, datum, 60f64.to_radians(), 16.0 / 9.0, a.viewport_height)
}

/// A record's bytes from the database file, the error naming its place.
fn read(db: &DbFile, r: &planet_core::format::ChildRef) -> Result<Vec<u8>> {
    db.read_record(r)
        .with_context(|| format!("record at {} + {}", r.offset, r.size))
}

/// The default policy with every request answered in the same frame.
fn replay_config(a: &FlightArgs) -> ClientConfig {
    let mut cfg = ClientConfig {
        decode_threads: 0,
        tree_ops_per_frame: 4096,
        ..ClientConfig::for_policy(Policy::Ours, a.max_sse)
    };
    cfg.queue.max_in_flight = 100_000;
    cfg.link_window = false;
    cfg.predict_view = false;
    cfg
}

/// [`InstantReplay::start_elevation`] and [`InstantReplay::start_chain`]:
/// the first frame converged from nothing by a client that sees the
/// geometry only (colour refines elevation blocks too, §4.4.1, and the
/// stops measure geometry), counting the elevation records it asks for but
/// a neighbour's forced ones (crack-free splits, which Cesium's skirts do
/// not need). (0, 0) where the view meets the tolerance before any record
/// arrives.
fn start_needs(db: &DbFile, camera: &planet_client::Camera, a: &FlightArgs) -> Result<(u64, u32)> {
    let mut header = db.header.clone();
    header.colour = None;
    let mut client = Client::new(header, replay_config(a))?;
    let (mut bytes, mut chain, mut met) = (0u64, 0u32, false);
    converge(&mut client, db, camera, a.fps, |k, out| {
        if k == 0 && !out.draw.is_empty() && out.stats.max_screen_error <= a.max_sse {
            met = true;
            return false;
        }
        for s in out.send.iter().filter(|s| !s.forced) {
            bytes += u64::from(s.record.size);
            chain = chain.max(u32::from(s.block.level) + 1);
        }
        true
    })?;
    Ok(if met { (0, 0) } else { (bytes, chain) })
}

/// Runs `client`'s frames at `camera`, answering every request from
/// `db` in the same frame, until nothing is asked, pending or in flight
/// (at most 400 frames). `each` sees every frame's output (its index
/// first) before its requests are answered and stops the loop by returning
/// false. Returns the last frame's per-pixel mean SSE.
fn converge(
    client: &mut Client,
    db: &DbFile,
    camera: &planet_client::Camera,
    fps: f64,
    mut each: impl FnMut(usize, &planet_client::FrameOutput) -> bool,
) -> Result<f64> {
    let mut last = 0.0;
    for k in 0..400 {
        let out = client.frame(camera, 1.0 / fps);
        last = out.stats.pixel_mean_screen_error;
        if !each(k, &out) {
            break;
        }
        let busy = !out.send.is_empty() || !client.pending_ops().is_empty();
        for s in &out.send {
            client.deliver(s.id, Ok(read(db, &s.record)?));
        }
        client.recycle(out.draw);
        if !busy && client.queue().in_flight() == 0 {
            break;
        }
    }
    Ok(last)
}

fn instant_replay(a: &FlightArgs, traj: &Trajectory) -> Result<InstantReplay> {
    let db = DbFile::open(&a.db).with_context(|| format!("opening {}", a.db.display()))?;
    let datum = db.header.datum;
    let mut seen: std::collections::HashSet<(u64, u32)> = Default::default();
    let mut out0 = InstantReplay::default();
    let duration = a.duration.unwrap_or(traj.duration()).min(traj.duration());
    let frames = (duration * a.fps).floor() as u64 + 1;
    let camera = flight_camera(traj, 0.0, &datum, a);
    (out0.start_elevation, out0.start_chain) = start_needs(&db, &camera, a)?;
    let mut client = Client::new(db.header.clone(), replay_config(a))?;
    for n in 0..frames {
        let t = n as f64 / a.fps;
        let camera = flight_camera(traj, t, &datum, a);
        let floor = converge(&mut client, &db, &camera, a.fps, |_, out| {
            for s in &out.send {
                if seen.insert((s.record.offset, s.record.size)) {
                    out0.needed += u64::from(s.record.size);
                }
            }
            true
        })?;
        out0.floor.push(floor);
    }
    Ok(out0)
}

/// The server side of one run: planet-server through the UDP relay, or
/// nginx through the TCP link.
enum Route {
    Quic {
        server: LocalServer,
        link: Link,
    },
    Http2 {
        // Dropped before the link (its namespace).
        nginx: planet_testkit::nginx::Nginx,
        link: TcpLink,
    },
}

impl Route {
    fn bytes_down(&self) -> u64 {
        match self {
            Route::Quic { link, .. } => link.stats().bytes_down,
            Route::Http2 { link, .. } => link.stats().bytes_down,
        }
    }
}

fn run_link(
    a: &FlightArgs,
    traj: &Trajectory,
    spec: &str,
    transport: Transport,
    policy: Policy,
    instant: Option<&InstantReplay>,
) -> Result<(Summary, Vec<Row>)> {
    let cfg: LinkConfig = spec.parse().with_context(|| format!("link {spec:?}"))?;
    let link_cfg = cfg.clone();
    let label = a.label.clone().unwrap_or_else(|| spec.to_string());
    eprintln!("== {label} / {transport} / {policy}: {}", a.db.display());
    let rt = runtime(2)?;
    let bandwidth = cfg.bandwidth_bps;
    let sender_congestion: String;
    let path = match transport {
        Transport::Quic => {
            let congestion = a
                .congestion
                .as_deref()
                .map(str::parse::<planet_server::Congestion>)
                .transpose()?;
            let server = LocalServer::start_with(rt.handle(), &a.db, congestion)?;
            sender_congestion = congestion.unwrap_or_default().name().to_string();
            let link = rt.block_on(Link::start(
                server.addr(),
                cfg.clone().with_seed(1),
                cfg.with_seed(2),
            ))?;
            Route::Quic { server, link }
        }
        Transport::Http2 => {
            let link = rt
                .block_on(TcpLink::start(cfg.clone().with_seed(1), cfg.with_seed(2)))
                .context("the TCP link (needs root, /dev/net/tun and iproute2's ip)")?;
            if a.tcp_congestion != "system" {
                link.set_tcp_congestion(&a.tcp_congestion)?;
            }
            sender_congestion = link.tcp_congestion()?;
            let nginx = planet_testkit::nginx::Nginx::start_in_namespace(
                &a.nginx_bin,
                &a.db,
                1,
                link.namespace(),
                link.server_ip(),
            )
            .context("nginx in the link's namespace")?;
            Route::Http2 { nginx, link }
        }
    };
    let client_cfg = client_config(a, policy);
    let sampler = Sampler::open(&a.db)?;
    let datum = sampler.header().datum;
    let duration = a.duration.unwrap_or(traj.duration()).min(traj.duration());
    // Fixed probes: ground points seen by the last camera, with the
    // full-resolution elevation from the database.
    let last = flight_camera(traj, duration, &datum, a);
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
    let (mut sc, connect_ms, t_connect, warm_up_bytes) = match &path {
        Route::Quic { server, link } => {
            let session = server.session_config(link.local_addr())?;
            let warm_up_bytes = if a.warm {
                rt.block_on(warm_up(&session))?;
                link.stats().bytes_down
            } else {
                0
            };
            let t_connect = Instant::now();
            let sc = StreamingClient::connect(
                rt.handle(),
                session,
                client_cfg,
                Duration::from_secs(20),
            )?;
            (
                sc,
                t_connect.elapsed().as_secs_f64() * 1e3,
                t_connect,
                warm_up_bytes,
            )
        }
        Route::Http2 { nginx, .. } => {
            if a.warm {
                bail!("--warm applies to QUIC only (0-RTT resumption)");
            }
            let tls = planet_session::tls::https_config(
                &planet_session::tls::ServerTrust::Certificates(vec![nginx.cert_der.clone()]),
            )?;
            let session = HttpSessionConfig::from_url(&nginx.url(), tls)?;
            let t_connect = Instant::now();
            let sc = StreamingClient::connect_http(
                rt.handle(),
                session,
                client_cfg,
                Duration::from_secs(20),
            )?;
            (sc, t_connect.elapsed().as_secs_f64() * 1e3, t_connect, 0)
        }
    };

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
        let camera = flight_camera(traj, t, &datum, a);
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
        let colour_max = sc.client.colour_screen_error(&camera, &out.draw);
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
            colour_max,
            sse_mean: st.mean_screen_error,
            sse_pixel_mean: st.pixel_mean_screen_error,
            sse_pixel_floor: instant
                .and_then(|r| r.floor.get(n as usize).copied())
                .unwrap_or(f64::NAN),
            err_max: emax,
            err_mean: if np > 0 { esum / np as f64 } else { f64::NAN },
            probes: np,
            relevant: st.totals.relevant_ratio(),
            cpu_ms: cpu.as_secs_f64() * 1e3,
            nodes: st.nodes,
            connected: sc.is_connected(),
        });
        prev_bytes = bytes;
        sc.client.recycle(out.draw);
    }
    if std::env::var_os("PLANET_BENCH_DEBUG").is_some() {
        let camera = flight_camera(traj, duration, &datum, a);
        let out = sc.frame(&camera, 1.0 / a.fps);
        let drawn: HashMap<_, _> = out.draw.iter().map(|d| (d.block, d.lod)).collect();
        for &(lat, lon, _) in probes.iter().take(200) {
            let fc = planet_core::cube::FaceCoord::from_lat_lon(lat.to_radians(), lon.to_radians());
            let mut id = BlockId::root(fc.face);
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
    let link_bytes_down = path.bytes_down();
    sc.close();
    drop(path);

    let name = link_name(&label);
    let db_name =
        a.db.file_stem()
            .map(|x| x.to_string_lossy().to_string())
            .unwrap_or_default();
    let tr = if a.transports.len() > 1 {
        format!("-{transport}")
    } else {
        String::new()
    };
    let csv = if a.dbs.len() > 1 {
        format!("flight-{name}{tr}-{policy}-{}.csv", link_name(&db_name))
    } else {
        format!("flight-{name}{tr}-{policy}.csv")
    };
    write_csv(&a.out.join(csv), &rows)?;

    let segs = static_segments(traj);
    let tol = a.max_sse;
    let spans: Vec<(f64, f64)> = segs
        .iter()
        .filter(|s| s.0 < duration)
        .map(|s| (s.0, s.1.min(duration)))
        .collect();
    let stops: Vec<(f64, Option<f64>)> = spans
        .iter()
        .map(|&(a, b)| (a, time_to(&rows, a, b, |r| r.sse_max <= tol)))
        .collect();
    let stops_with_colour: Vec<Option<f64>> = spans
        .iter()
        .map(|&(a, b)| time_to(&rows, a, b, |r| r.sse_max.max(r.colour_max) <= tol))
        .collect();
    let dt = 1.0 / a.fps;
    let error_integral: f64 = rows.iter().map(|r| r.sse_pixel_mean * dt).sum();
    let max_sse_integral: f64 = rows.iter().map(|r| r.sse_max * dt).sum();
    let block_error_integral: f64 = rows.iter().map(|r| r.sse_mean * dt).sum();
    let needed_over_delivered = match (instant, bandwidth) {
        (Some(r), Some(bps)) if duration > 0.0 => {
            Some(r.needed as f64 / (bps as f64 / 8.0 * duration))
        }
        _ => None,
    };
    let floor_integral = instant.map(|r| r.floor_integral(a.fps));
    let start_bound_s = instant
        .filter(|_| stops.first().is_some_and(|s| s.0 == 0.0))
        .and_then(|r| r.start_bound_s(&link_cfg));
    let mut cpu: Vec<f64> = rows.iter().map(|r| r.cpu_ms).collect();
    cpu.sort_by(f64::total_cmp);
    let p99 = cpu[((cpu.len() as f64 * 0.99) as usize).min(cpu.len() - 1)];
    let lastrow = rows.last().cloned().unwrap_or_default();
    Ok((
        Summary {
            label,
            transport,
            congestion: sender_congestion,
            db: db_name,
            policy,
            error_integral,
            max_sse_integral,
            block_error_integral,
            stops,
            stops_with_colour,
            wasted_pct: 100.0 * totals.wasted_ratio(),
            dropped_pct: 100.0 * totals.dropped_ratio(),
            unused_tables_pct: 100.0 * totals.unused_tables_ratio(),
            needed_over_delivered,
            floor_integral,
            start_bound_s,
            round_trip_bound: None,
            first_frame_ms,
            connect_ms,
            bytes: counters.bytes_received,
            link_bytes_down: link_bytes_down - warm_up_bytes,
            zero_rtt,
            relevant_pct: 100.0 * totals.relevant_ratio(),
            forced_pct: 100.0 * totals.forced_ratio(),
            cancels: counters.cancels,
            requests: counters.requests,
            cpu_mean_ms: cpu.iter().sum::<f64>() / cpu.len() as f64,
            cpu_p99_ms: p99,
            final_sse_max: lastrow.sse_max,
            final_err_max: lastrow.err_max,
            frames_late,
            frames,
        },
        rows,
    ))
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
        "frame,t_s,bytes_total,bytes_frame,in_flight,sent,cancelled,cancelled_total,blocks,triangles,quality_factor,sse_max_px,colour_texel_max_px,sse_mean_px,sse_pixel_mean_px,sse_pixel_floor_px,true_err_max_m,true_err_mean_m,probes,relevant_ratio,cpu_ms,nodes,connected\n",
    );
    for r in rows {
        let _ = writeln!(
            s,
            "{},{:.4},{},{},{},{},{},{},{},{},{:.1},{:.4},{:.4},{:.4},{:.4},{:.4},{:.3},{:.3},{},{:.5},{:.4},{},{}",
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
            r.colour_max,
            r.sse_mean,
            r.sse_pixel_mean,
            r.sse_pixel_floor,
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

pub fn summary_table(ss: &[Summary]) -> String {
    let mut t = String::new();
    let _ = writeln!(
        t,
        "| database | link | transport | policy | ∫ mean SSE dt (per pixel) | ∫ max SSE dt | ∫ block-mean SSE dt | floor ∫ (excess) | round-trip bound ∫ | to tolerance after each stop (start's bound) | with colour | bytes | link bytes | needed / delivered | relevant (forced) | wasted (dropped, unused tables) | requests / cancels | first frame (connect) | CPU/frame mean / p99 | final max SSE / true err | late frames |"
    );
    let _ = writeln!(
        t,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for s in ss {
        let stops: Vec<String> = s
            .stops
            .iter()
            .map(|(at, x)| match x {
                Some(v) => format!("{at:.0}s: {v:.2}"),
                None => format!("{at:.0}s: —"),
            })
            .collect();
        let with_colour: Vec<String> = s
            .stops_with_colour
            .iter()
            .map(|x| x.map_or("—".into(), |v| format!("{v:.2}")))
            .collect();
        let _ = writeln!(
            t,
            "| {} | {}{} | {} | {} | {:.1} px·s | {:.1} px·s | {:.1} px·s | {} | {} | {}{} | {} | {:.2} MB | {:.2} MB | {} | {:.2} % ({:.2} %) | {:.2} % ({:.2} %, {:.2} %) | {} / {} | {:.0} ms ({:.0} ms) | {:.3} / {:.3} ms | {:.2} px / {:.1} m | {} / {} |",
            s.db,
            s.label,
            if s.zero_rtt { " (0-RTT)" } else { "" },
            format_args!("{} ({})", s.transport, s.congestion),
            s.policy,
            s.error_integral,
            s.max_sse_integral,
            s.block_error_integral,
            match (s.floor_integral, s.excess_integral()) {
                (Some(f), Some(x)) => format!("{f:.1} px·s ({x:.1})"),
                _ => "—".into(),
            },
            s.round_trip_bound
                .map_or("—".into(), |b| format!("{b:.1} px·s")),
            stops.join(", "),
            s.start_bound_s
                .map_or(String::new(), |b| format!(" (≥ {b:.2})")),
            with_colour.join(", "),
            s.bytes as f64 / 1e6,
            s.link_bytes_down as f64 / 1e6,
            s.needed_over_delivered
                .map_or("—".into(), |r| format!("{r:.1}×")),
            s.relevant_pct,
            s.forced_pct,
            s.wasted_pct,
            s.dropped_pct,
            s.unused_tables_pct,
            s.requests,
            s.cancels,
            s.first_frame_ms,
            s.connect_ms,
            s.cpu_mean_ms,
            s.cpu_p99_ms,
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

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        a: FlightArgs,
    }

    fn args(db: &Path, trajectory: &str, duration: f64) -> FlightArgs {
        let mut a = Cli::parse_from([
            "flight",
            "--db",
            db.to_str().unwrap(),
            "--link",
            "1mbit,100ms",
            "--out",
            "/nonexistent",
            "--trajectory",
            trajectory,
            "--duration",
            &duration.to_string(),
        ])
        .a;
        a.db = db.to_path_buf();
        a
    }

    #[test]
    fn start_bound_takes_the_chain_or_the_bytes() {
        let link: LinkConfig = "1mbit,100ms".parse().unwrap();
        let r = |bytes, chain| InstantReplay {
            start_elevation: bytes,
            start_chain: chain,
            ..InstantReplay::default()
        };
        // A chain of ten levels: the root, then two levels per round trip,
        // six round trips of 0.2 s, outweigh 10 kB at 125 kB/s.
        let b = r(10_000, 10).start_bound_s(&link).unwrap();
        assert!((b - 1.2).abs() < 1e-12, "{b}");
        let b = r(10_000, 11).start_bound_s(&link).unwrap();
        assert!((b - 1.2).abs() < 1e-12, "{b}");
        // 250 kB take 2 s after the first round trip.
        let b = r(250_000, 2).start_bound_s(&link).unwrap();
        assert!((b - 2.2).abs() < 1e-12, "{b}");
        // Met before anything arrives.
        assert_eq!(r(0, 0).start_bound_s(&link), Some(0.0));
        let unlimited: LinkConfig = "loopback".parse().unwrap();
        assert_eq!(r(10_000, 3).start_bound_s(&unlimited), None);
    }

    #[test]
    fn instant_replay_meets_the_tolerance_every_frame() {
        let db = crate::server::tests_support::tiny_db();
        // static-low starts near the ground: its first view needs records.
        let a = args(&db, "static-low", 2.0);
        let r = instant_replay(&a, &Trajectory::builtin("static-low").unwrap()).unwrap();
        assert_eq!(r.floor.len(), 61);
        assert!(r
            .floor
            .iter()
            .all(|&f| f.is_finite() && (0.0..=a.max_sse).contains(&f)));
        assert!(r.floor_integral(a.fps) > 0.0);
        assert!(
            r.start_elevation > 0 && r.start_elevation < r.needed,
            "{r:?}"
        );
        // The tiny planet has levels 0..=3: a chain of at most 4.
        assert!((1..=4).contains(&r.start_chain), "{r:?}");
        let bound = r.start_bound_s(&"1mbit,100ms".parse().unwrap()).unwrap();
        assert!(bound >= 0.1 * r.start_chain as f64, "{bound}");
    }

    #[test]
    fn a_level_can_arrive_two_per_round_trip_after_the_root() {
        let trips: Vec<u32> = [0u8, 1, 2, 3, 4, 5, 16, 30]
            .into_iter()
            .map(earliest_trip)
            .collect();
        assert_eq!(trips, [1, 2, 2, 3, 3, 4, 9, 16]);
    }

    /// The round-trip bound lies between the floor and what any client
    /// draws: the header alone until the first round trip, the floor once
    /// every level can have arrived, and it grows with the round trip.
    #[test]
    fn round_trip_bound_is_the_header_until_the_first_round_trip_then_the_floor() {
        let db = crate::server::tests_support::tiny_db();
        let a = args(&db, "static-low", 2.0);
        let traj = Trajectory::builtin("static-low").unwrap();
        let r = instant_replay(&a, &traj).unwrap();
        let floor = r.floor_integral(a.fps);
        // The view from the header alone, as every client draws at t = 0.
        let file = DbFile::open(&db).unwrap();
        let camera = flight_camera(&traj, 0.0, &file.header.datum, &a);
        let mut client = Client::new(file.header.clone(), replay_config(&a)).unwrap();
        let e0 = client
            .frame(&camera, 1.0 / a.fps)
            .stats
            .pixel_mean_screen_error;
        assert!(
            e0 > a.max_sse && r.floor[0] <= a.max_sse,
            "{e0} {:?}",
            r.floor[0]
        );
        let bounds: Vec<f64> = [0.0, 0.1, 0.2, 0.4]
            .into_iter()
            .map(|rtt| round_trip_bound(&file, &a, &traj, rtt, &r.floor).unwrap())
            .collect();
        // No round trip: the floor itself.
        assert!((bounds[0] - floor).abs() < 1e-9, "{bounds:?} {floor}");
        for (rtt, b) in [0.1, 0.2, 0.4].into_iter().zip(&bounds[1..]) {
            // The frames before the first round trip draw the header: the
            // rest at least the floor.
            let before = (rtt * a.fps).ceil() as usize;
            let at_least = (before as f64 * e0 + r.floor[before..].iter().sum::<f64>()) / a.fps;
            assert!(*b >= at_least - 1e-9, "rtt {rtt}: {b} < {at_least}");
        }
        assert!(
            bounds.windows(2).all(|w| w[0] < w[1]),
            "not growing with the round trip: {bounds:?}"
        );
    }

    /// Flights through the real server and link, `ours` and `cesium`, stay
    /// at or above the bound for their link's round trip.
    #[test]
    fn real_flights_stay_above_their_round_trip_bound() {
        let db = crate::server::tests_support::tiny_db();
        let mut a = args(&db, "static-low", 2.0);
        a.out = db.with_file_name("flight-bound");
        std::fs::create_dir_all(&a.out).unwrap();
        let traj = Trajectory::builtin("static-low").unwrap();
        let r = instant_replay(&a, &traj).unwrap();
        let file = DbFile::open(&db).unwrap();
        let bound = round_trip_bound(&file, &a, &traj, 0.2, &r.floor).unwrap();
        assert!(bound > r.floor_integral(a.fps), "{bound}");
        for policy in [Policy::Ours, Policy::Cesium] {
            let (s, rows) =
                run_link(&a, &traj, "1mbit,100ms", Transport::Quic, policy, Some(&r)).unwrap();
            assert_eq!(rows.len(), r.floor.len(), "{policy}");
            assert!(
                s.error_integral >= bound,
                "{policy}: {} under the bound {bound}",
                s.error_integral
            );
        }
    }

    /// Every built-in trajectory, whole, at two frames a second: the client
    /// with its defaults converges within the tolerance in every frame,
    /// across the cube corner of `corner-pass`, the turning climbs and the
    /// dives from orbit, and every path needs some record.
    #[test]
    fn every_builtin_trajectory_converges_every_frame() {
        let db = crate::server::tests_support::tiny_db();
        for name in planet_client::trajectory::BUILTIN_NAMES {
            let traj = Trajectory::builtin(name).unwrap();
            let mut a = args(&db, name, traj.duration());
            a.fps = 2.0;
            let r = instant_replay(&a, &traj).unwrap();
            assert_eq!(
                r.floor.len(),
                (traj.duration() * 2.0) as usize + 1,
                "{name}"
            );
            assert!(
                r.floor
                    .iter()
                    .all(|&f| f.is_finite() && (0.0..=a.max_sse).contains(&f)),
                "{name}: {:?}",
                r.floor
            );
            assert!(r.needed > 0, "{name}: {r:?}");
        }
    }
}
