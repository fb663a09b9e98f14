//! `planet-view`: the interactive viewer (window) and the headless renderer.
//!
//! ```text
//! planet-view --local                          # window, embedded procedural planet
//! planet-view --server ADDR --token T --database NAME --fingerprint HEX
//! planet-view --url https://host/path/earth.planetdb   # any HTTPS server, HTTP/2 ranges
//! planet-view render --trajectory rainier --local --out frames/ --reference
//! planet-view snapshot --db earth.planetdb --eye LAT,LON,ALT --target LAT,LON,ALT --out a.png
//! ```
#![forbid(unsafe_code)]

mod app;

use anyhow::{bail, Context, Result};
use app::connect::Source;
use clap::{Args, Parser, Subcommand};
use std::net::SocketAddr;
use std::path::PathBuf;

/// mimalloc, like `planet-server` and `planet-bench`: the network client
/// (quinn) and the record decoder allocate per request, and the client
/// figures in docs/BENCHMARKS.md are measured with this allocator.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Where the planet comes from.
#[derive(Debug, Clone, Args)]
struct SourceArgs {
    /// Stream the embedded procedural planet (built on first use into the
    /// cache directory) from an in-process server over real QUIC.
    #[arg(long)]
    local: bool,
    /// Serve this database file in-process and stream it over real QUIC.
    #[arg(long, value_name = "PATH", conflicts_with = "local")]
    db: Option<PathBuf>,
    /// A remote planet-server (UDP address).
    #[arg(long, value_name = "ADDR", conflicts_with_all = ["local", "db"])]
    server: Option<SocketAddr>,
    /// A database file on any HTTPS server that serves byte ranges over
    /// HTTP/2 (nginx, an object store, a CDN): no planet-server needed. The
    /// system's root certificates are trusted, or --fingerprint pins a
    /// self-signed one.
    #[arg(long, value_name = "URL", conflicts_with_all = ["local", "db", "server"])]
    url: Option<String>,
    /// Tenant token for --server.
    #[arg(long, default_value = "")]
    token: String,
    /// Tenant name for --server.
    #[arg(long, default_value = "public")]
    tenant: String,
    /// Database name for --server.
    #[arg(long)]
    database: Option<String>,
    /// SHA-256 fingerprint (hex) of the server certificate for --server (or
    /// for --url, pinning a self-signed certificate).
    #[arg(long)]
    fingerprint: Option<String>,
    /// Simulated link between client and server, e.g. `10mbit,50ms,1%loss`.
    #[arg(long, value_name = "SPEC")]
    link: Option<String>,
}

impl SourceArgs {
    fn source(&self) -> Result<Source> {
        if let Some(url) = &self.url {
            return Ok(Source::Url {
                url: url.clone(),
                fingerprint: self.fingerprint.clone(),
            });
        }
        if let Some(addr) = self.server {
            let database = self
                .database
                .clone()
                .context("--server needs --database NAME")?;
            let fingerprint = self
                .fingerprint
                .clone()
                .context("--server needs --fingerprint HEX (printed by planet-server)")?;
            return Ok(Source::Remote {
                addr,
                token: self.token.clone(),
                database,
                fingerprint,
                tenant: self.tenant.clone(),
            });
        }
        if let Some(p) = &self.db {
            return Ok(Source::Db(p.clone()));
        }
        Ok(Source::Local)
    }

    fn link(&self) -> Result<Option<planet_linksim::LinkConfig>> {
        match &self.link {
            None => Ok(None),
            Some(s) => Ok(Some(
                s.parse()
                    .map_err(|e| anyhow::anyhow!("--link {s:?}: {e}"))?,
            )),
        }
    }
}

/// Stream and render whole planets.
#[derive(Debug, Parser)]
#[command(
    name = "planet-view",
    version,
    about,
    args_conflicts_with_subcommands = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    window: WindowArgs,
}

#[derive(Debug, Clone, Args)]
struct WindowArgs {
    #[command(flatten)]
    source: SourceArgs,
    /// Frame rate the quality controller aims at [default: 60, or 15 when
    /// wgpu renders on the CPU (lavapipe), where 60 fps leaves only the roots].
    #[arg(long)]
    target_fps: Option<f64>,
    /// Largest screen-space error in pixels the client aims at (the frame-rate
    /// controller coarsens it when the frame rate falls short).
    #[arg(long, default_value_t = planet_client::refinement::DEFAULT_MAX_SSE_PX)]
    max_sse: f64,
    /// Budget of resident samples in MB: over it the least important
    /// blocks are merged away (default: none).
    #[arg(long)]
    memory: Option<f64>,
    /// Start at (and return with G to) LAT,LON,ALT (degrees, metres).
    #[arg(long, value_name = "LAT,LON,ALT", allow_hyphen_values = true)]
    goto: Option<String>,
    /// Window width.
    #[arg(long, default_value_t = 1280)]
    width: u32,
    /// Window height.
    #[arg(long, default_value_t = 720)]
    height: u32,
    /// (Testing) write the window's content to this PNG and exit after
    /// --exit-after-frames frames.
    #[arg(long, value_name = "PATH")]
    screenshot: Option<PathBuf>,
    /// (Testing) exit after this many frames.
    #[arg(long, value_name = "N")]
    exit_after_frames: Option<u64>,
    /// (Testing, scripting) append one JSON object per frame to this file:
    /// the camera (view, mode, lat, lon, alt, heading, pitch, target, range,
    /// azimuth, tilt), the window size and the streaming counters.
    #[arg(long, value_name = "PATH")]
    state: Option<PathBuf>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Fly a trajectory offscreen: PNG frames, a per-frame CSV and (with
    /// --reference) the image error against the complete database.
    Render(RenderArgs),
    /// Render one converged still image from the complete database.
    Snapshot(SnapshotArgs),
}

#[derive(Debug, Args)]
struct RenderArgs {
    #[arg(long, help = planet_client::trajectory::TRAJECTORY_HELP)]
    trajectory: String,
    #[command(flatten)]
    source: SourceArgs,
    /// Output directory (frames, frames.csv).
    #[arg(long)]
    out: PathBuf,
    /// Frames per second of trajectory time.
    #[arg(long, default_value_t = 30.0)]
    fps: f64,
    /// Image width.
    #[arg(long, default_value_t = 640)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 480)]
    height: u32,
    /// Write every Nth frame (and the last).
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Also render each written frame from the complete database and add
    /// the image error (depth RMSE, coverage, PSNR) to the CSV.
    #[arg(long)]
    reference: bool,
    /// Reference resolution: samples at most this many pixels apart.
    #[arg(long, default_value_t = 1.0)]
    reference_px: f64,
    /// Render the reference from this database instead of the streamed one
    /// (e.g. the lossless build of a database streamed with a lossy codec:
    /// the image error then includes the codec's). Implies --reference.
    #[arg(long, value_name = "PATH")]
    reference_db: Option<PathBuf>,
    /// Do not pace frames to real time (the stream then gets less time).
    #[arg(long)]
    no_pace: bool,
    /// Stop after this many seconds of trajectory time.
    #[arg(long)]
    duration: Option<f64>,
    /// Largest screen-space error in pixels the streaming client aims at.
    #[arg(long, default_value_t = planet_client::refinement::DEFAULT_MAX_SSE_PX)]
    max_sse: f64,
    /// (Benchmark) build and draw every frame as the window does, waiting
    /// for the device, and record the client's, the scene builder's and
    /// the renderer's milliseconds per frame (CSV columns, a table, a JSON
    /// line and timing.json). Without --target-fps the quality controller
    /// stays off: every frame aims at --max-sse.
    #[arg(long)]
    time: bool,
    /// Run the window's frame-rate controller aiming at this many frames per
    /// second (the window's default is 60): it coarsens the tolerance above
    /// --max-sse while frames cost more than 1/RATE and refines back while
    /// they cost less. Fed with each frame's measured cost (client, scene
    /// builder, drawing waited for), as the window feeds it; needs --time.
    #[arg(long)]
    target_fps: Option<f64>,
}

#[derive(Debug, Args)]
struct SnapshotArgs {
    /// The database file.
    #[arg(long)]
    db: PathBuf,
    /// Eye position LAT,LON,ALT.
    #[arg(long, allow_hyphen_values = true)]
    eye: String,
    /// Look at LAT,LON,ALT (default: the planet centre).
    #[arg(long, allow_hyphen_values = true)]
    target: Option<String>,
    /// Output PNG.
    #[arg(long)]
    out: PathBuf,
    /// Image width.
    #[arg(long, default_value_t = 640)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 480)]
    height: u32,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 57.3)]
    fov: f64,
    /// Samples at most this many pixels apart.
    #[arg(long, default_value_t = 1.0)]
    px: f64,
    /// Sun direction as LAT,LON (default: the renderer's).
    #[arg(long, allow_hyphen_values = true)]
    sun: Option<String>,
    /// Shade by altitude (blue, green, brown, white) instead of colour.
    #[arg(long)]
    altitude_colours: bool,
    /// (Benchmark) then render the converged scene N more times without
    /// read-back and print the frame times (median, p95, max; a table row
    /// and a JSON line).
    #[arg(long, value_name = "N", default_value_t = 0)]
    time_frames: usize,
}

/// Parse `a,b[,c]` numbers.
fn parse_numbers(s: &str, n: usize, what: &str) -> Result<Vec<f64>> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("{what} {s:?}: expected {n} comma-separated numbers"))?;
    if v.len() != n || v.iter().any(|x| !x.is_finite()) {
        bail!("{what} {s:?}: expected {n} comma-separated numbers");
    }
    Ok(v)
}

fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

fn main() {
    planet_core::pages::no_transparent_huge_pages();
    planet_core::pipe::exit_quietly_on_broken_pipe();
    init_logging();
    let cli = Cli::parse();
    let r = match cli.command {
        Some(Command::Render(a)) => render(a),
        Some(Command::Snapshot(a)) => snapshot(a),
        None => window(cli.window),
    };
    if let Err(e) = r {
        if let Some(app::window::NoDisplay(msg)) = e.downcast_ref::<app::window::NoDisplay>() {
            eprintln!("{msg}");
            std::process::exit(3);
        }
        eprintln!("planet-view: error: {e:#}");
        std::process::exit(1);
    }
}

fn render(a: RenderArgs) -> Result<()> {
    let opts = app::render_cmd::RenderOptions {
        trajectory: a.trajectory,
        source: a.source.source()?,
        link: a.source.link()?,
        out: a.out,
        fps: a.fps,
        width: a.width,
        height: a.height,
        every: a.every,
        reference: a.reference || a.reference_db.is_some(),
        reference_db: a.reference_db,
        reference_px: a.reference_px,
        pace: !a.no_pace,
        duration: a.duration,
        max_sse: a.max_sse,
        time: a.time,
        target_fps: a.target_fps,
    };
    app::render_cmd::run(&opts)
}

fn snapshot(a: SnapshotArgs) -> Result<()> {
    let eye = parse_numbers(&a.eye, 3, "--eye")?;
    let target = match &a.target {
        Some(t) => Some(parse_numbers(t, 3, "--target")?),
        None => None,
    };
    let sun = match &a.sun {
        Some(s) => Some(parse_numbers(s, 2, "--sun")?),
        None => None,
    };
    app::snapshot::run(&app::snapshot::SnapshotOptions {
        db: a.db,
        eye: [eye[0], eye[1], eye[2]],
        target: target.map(|t| [t[0], t[1], t[2]]),
        out: a.out,
        width: a.width,
        height: a.height,
        fov_y: a.fov.to_radians(),
        px: a.px,
        sun: sun.map(|s| [s[0], s[1]]),
        altitude_colours: a.altitude_colours,
        time_frames: a.time_frames,
    })
}

fn window(a: WindowArgs) -> Result<()> {
    let goto = match &a.goto {
        Some(g) => {
            let v = parse_numbers(g, 3, "--goto")?;
            Some([v[0], v[1], v[2]])
        }
        None => None,
    };
    app::window::run(app::window::WindowOptions {
        source: a.source.source()?,
        link: a.source.link()?,
        target_fps: a.target_fps,
        goto,
        width: a.width.max(16),
        height: a.height.max(16),
        max_sse: a.max_sse,
        memory_mb: a.memory,
        screenshot: a.screenshot,
        exit_after_frames: a.exit_after_frames,
        state: a.state,
    })
}
