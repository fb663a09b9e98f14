//! `planet-view render`: fly a trajectory offscreen, write PNG frames, a
//! per-frame CSV of streaming statistics and, with `--reference`, the image
//! error of every written frame against the complete database.

use crate::app::camera::FOV_Y;
use crate::app::connect::{self, Source};
use crate::app::reference::{image_error, reference_config, reference_qf, Reference};
use crate::app::scene::{BuildMode, SceneBuilder};
use anyhow::{Context, Result};
use planet_client::quality::QualityConfig;
use planet_client::trajectory::Trajectory;
use planet_client::ClientConfig;
use planet_linksim::LinkConfig;
use planet_render::{DrawBlock, HeadlessRenderer, RenderSettings};
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

/// Options of the render command.
#[derive(Debug, Clone)]
pub struct RenderOptions {
    /// Built-in trajectory name or file.
    pub trajectory: String,
    /// Data source.
    pub source: Source,
    /// Optional simulated link.
    pub link: Option<LinkConfig>,
    /// Output directory.
    pub out: PathBuf,
    /// Frames per second of trajectory time.
    pub fps: f64,
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// Write every Nth frame.
    pub every: usize,
    /// Compute the image error against the complete database.
    pub reference: bool,
    /// Render the reference from this database (default: the streamed one).
    pub reference_db: Option<PathBuf>,
    /// Reference sample spacing in pixels.
    pub reference_px: f64,
    /// Pace frames to real time (the network runs in real time).
    pub pace: bool,
    /// Stop after this many seconds of trajectory time.
    pub duration: Option<f64>,
    /// Largest screen-space error in pixels of the streaming client.
    pub max_sse: f64,
    /// Build and draw every frame (as the window does) and record the
    /// client's, the scene builder's and the renderer's time per frame.
    pub time: bool,
    /// Run the window's frame-rate controller aiming at this rate, fed with
    /// each frame's measured cost (none: the tolerance stays at `max_sse`).
    /// Needs `time`.
    pub target_fps: Option<f64>,
}

/// Set `r_min` for the drawn blocks' chord sag.
pub fn fit_planes(
    base: &RenderSettings,
    scene: &SceneBuilder,
    blocks: &[DrawBlock],
) -> RenderSettings {
    let mut s = base.clone();
    s.r_min = base.r_min - scene.max_sag(blocks) * 1.05 - 1.0;
    s
}

fn fmt(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.6}")
    } else {
        String::new()
    }
}

/// Run the command; prints a summary.
pub fn run(opts: &RenderOptions) -> Result<()> {
    let traj = Trajectory::from_spec(&opts.trajectory)?;
    let duration = opts.duration.unwrap_or_else(|| traj.duration()).max(0.0);
    let fps = opts.fps.max(0.1);
    let every = opts.every.max(1);
    if opts.target_fps.is_some() && !opts.time {
        anyhow::bail!("--target-fps needs --time: the controller is fed the measured frame times");
    }
    std::fs::create_dir_all(&opts.out)
        .with_context(|| format!("creating {}", opts.out.display()))?;
    let rt = connect::runtime()?;
    let endpoint = connect::start(&rt, &opts.source, opts.link.as_ref())?;
    let mut cfg = ClientConfig::for_policy(planet_client::Policy::Ours, opts.max_sse);
    if let Some(t) = opts.target_fps {
        cfg.quality = QualityConfig::target_fps(t);
    }
    let mut sc = connect::connect(&rt, &endpoint.session, cfg)?;
    let header = sc.header().clone();
    let datum = header.datum;
    let base = RenderSettings::for_planet(
        &datum,
        header.min_elevation as f64,
        header.max_elevation as f64,
    );
    let mut renderer = HeadlessRenderer::with_settings(opts.width, opts.height, base.clone())
        .context("headless renderer (install mesa-vulkan-drivers for lavapipe)")?;
    eprintln!("planet-view render: adapter {}", renderer.adapter_name);
    let mut reference = if opts.reference {
        let qf = reference_qf(opts.reference_px, FOV_Y, opts.height);
        Some(
            match opts.reference_db.as_ref().or(endpoint.db_path.as_ref()) {
                Some(p) => {
                    let db = planet_core::format::DbFile::open(p)
                        .with_context(|| format!("opening {} for the reference", p.display()))?;
                    Reference::from_file(db, qf)?
                }
                None => Reference::from_stream(connect::connect(
                    &rt,
                    &endpoint.direct,
                    reference_config(qf, 2),
                )?),
            },
        )
    } else {
        None
    };
    let mut scene = SceneBuilder::new(&header);
    let csv_path = opts.out.join("frames.csv");
    let mut csv = std::io::BufWriter::new(
        std::fs::File::create(&csv_path).with_context(|| format!("{}", csv_path.display()))?,
    );
    writeln!(
        csv,
        "frame,time_s,bytes_received,in_flight,cancelled,cancelled_total,blocks,triangles,quality_factor,max_sse_px,mean_sse_px,written,depth_rmse_m,depth_rel_rmse,coverage_mismatch_px,covered_px,psnr_db,ref_blocks,ref_triangles,ref_frames,ref_converged,client_ms,scene_ms,encode_ms,draw_ms"
    )?;
    let mut timing = FrameTimes::default();
    let aspect = opts.width as f64 / opts.height as f64;
    let n = (duration * fps).floor() as usize + 1;
    let start = Instant::now();
    let mut paused = Duration::ZERO;
    let mut written = 0usize;
    let mut errors = vec![];
    let mut header_changes = sc.counters().header_changes;
    let mut last_cost_s = None;
    for i in 0..n {
        let t = i as f64 / fps;
        if opts.pace {
            let due = start + paused + Duration::from_secs_f64(t);
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
        let cam = traj.camera_at(t, &datum, FOV_Y, aspect, opts.height as f64);
        // The frame-rate controller gets the last frame's measured cost,
        // as the window gives it.
        if let Some(cost) = last_cost_s {
            sc.client.observe_frame_cost(cost);
        }
        let t_client = Instant::now();
        let out = sc.frame(&cam, 1.0 / fps);
        let client_s = t_client.elapsed().as_secs_f64();
        if sc.counters().header_changes != header_changes {
            header_changes = sc.counters().header_changes;
            scene = SceneBuilder::new(sc.header());
        }
        // The window's per-frame work: the client's frame, the scene
        // builder (meshes built on worker threads, the old ones drawn
        // meanwhile) and a frame drawn and waited for.
        let timed = if opts.time {
            let t_scene = Instant::now();
            let blocks = scene.prepare(sc.client.tree(), &out.draw, BuildMode::Async);
            let scene_s = t_scene.elapsed().as_secs_f64();
            renderer.renderer.settings = fit_planes(&base, &scene, &blocks);
            let f = renderer.time_frame(&cam, &blocks)?;
            last_cost_s = Some(client_s + scene_s + f.frame_s);
            Some(timing.push([client_s, scene_s, f.encode_s, f.frame_s]))
        } else {
            None
        };
        let s = &out.stats;
        let write = i % every == 0 || i + 1 == n;
        let mut row = format!(
            "{i},{t:.4},{},{},{},{},{},{},{:.3},{:.4},{:.4},{}",
            sc.bytes_received(),
            s.in_flight,
            s.cancelled,
            s.totals.cancelled,
            s.blocks_drawn,
            s.triangles,
            s.quality_factor,
            s.max_screen_error,
            s.mean_screen_error,
            u8::from(write)
        );
        if write {
            let blocks = scene.prepare(sc.client.tree(), &out.draw, BuildMode::Sync);
            let own = fit_planes(&base, &scene, &blocks);
            renderer.renderer.settings = own.clone();
            let img = renderer.render(&cam, &blocks)?;
            let png = opts.out.join(format!("frame_{i:05}.png"));
            img.save_png(&png)?;
            written += 1;
            if let Some(r) = reference.as_mut() {
                let t0 = Instant::now();
                let rblocks = r.converge(&cam, 5000, Duration::from_secs(120));
                // One projection for both images (the lower sag-fitted
                // radius of the two block sets), so that the depth error
                // measures the geometry, not two far planes' rounding.
                let mut shared = fit_planes(&base, r.scene(), &rblocks);
                shared.r_min = shared.r_min.min(own.r_min);
                renderer.renderer.settings = shared;
                let img = if renderer.renderer.settings.r_min == own.r_min {
                    img
                } else {
                    renderer.render(&cam, &blocks)?
                };
                let rimg = renderer.render(&cam, &rblocks)?;
                let e = image_error(&img, &rimg);
                let rtris = renderer.renderer.stats.triangles;
                row += &format!(
                    ",{},{},{},{},{},{},{},{},{}",
                    fmt(e.depth_rmse_m),
                    fmt(e.depth_rel_rmse),
                    e.coverage_mismatch,
                    e.covered_both,
                    fmt(e.psnr_db),
                    rblocks.len(),
                    rtris,
                    r.last_frames,
                    u8::from(r.last_converged)
                );
                if i == 0 {
                    rimg.save_png(opts.out.join("reference_00000.png"))?;
                }
                errors.push((t, e));
                paused += t0.elapsed();
            } else {
                row += ",,,,,,,,,";
            }
        } else {
            row += ",,,,,,,,,";
        }
        match timed {
            Some(ms) => ms.iter().for_each(|v| row += &format!(",{v:.4}")),
            None => row += ",,,,",
        }
        writeln!(csv, "{row}")?;
    }
    csv.flush()?;
    let wall = start.elapsed().as_secs_f64();
    let totals = sc.client.totals();
    println!(
        "planet-view render: {n} frames ({written} written) of {duration:.1} s at {fps} fps in {wall:.1} s wall; {} bytes received, {} requests, {} cancelled; CSV {}",
        sc.bytes_received(),
        totals.sent,
        totals.cancelled,
        csv_path.display()
    );
    if let (Some(first), Some(last)) = (errors.first(), errors.last()) {
        let mean = |f: &dyn Fn(&crate::app::reference::ImageError) -> f64| {
            errors.iter().map(|(_, e)| f(e)).sum::<f64>() / errors.len() as f64
        };
        println!(
            "image error vs the complete database: PSNR {:.2} dB -> {:.2} dB (mean {:.2}); depth RMSE {:.2} m -> {:.2} m (mean {:.2}); coverage mismatch {} -> {} px",
            first.1.psnr_db,
            last.1.psnr_db,
            mean(&|e| e.psnr_db),
            first.1.depth_rmse_m,
            last.1.depth_rmse_m,
            mean(&|e| e.depth_rmse_m),
            first.1.coverage_mismatch,
            last.1.coverage_mismatch
        );
    }
    if opts.time {
        let json = timing.report(&renderer.adapter_name, opts.width, opts.height, fps);
        let path = opts.out.join("timing.json");
        std::fs::write(&path, format!("{json}\n"))
            .with_context(|| format!("{}", path.display()))?;
    }
    sc.close();
    drop(reference);
    endpoint.shutdown(&rt);
    Ok(())
}

/// Per-frame times of `--time`, in milliseconds.
#[derive(Debug, Default)]
struct FrameTimes {
    client: Vec<f64>,
    scene: Vec<f64>,
    encode: Vec<f64>,
    draw: Vec<f64>,
    total: Vec<f64>,
}

impl FrameTimes {
    /// Record one frame's client, scene, encode and draw seconds (the draw
    /// includes the encode); returns them in milliseconds.
    fn push(&mut self, seconds: [f64; 4]) -> [f64; 4] {
        let ms = seconds.map(|s| s * 1e3);
        let [client, scene, encode, draw] = ms;
        self.client.push(client);
        self.scene.push(scene);
        self.encode.push(encode);
        self.draw.push(draw);
        self.total.push(client + scene + draw);
        ms
    }

    /// Print a table (median, p95, p99, max of each part and of the whole
    /// frame; frames over the `fps` budget) and return it as JSON.
    fn report(&mut self, adapter: &str, width: u32, height: u32, fps: f64) -> serde_json::Value {
        let budget_ms = 1e3 / fps;
        let n = self.total.len();
        let over = self.total.iter().filter(|&&t| t > budget_ms).count();
        let qs = [0.5, 0.95, 0.99, 1.0];
        let mut parts = serde_json::Map::new();
        println!("| {adapter}, {width}×{height}, {n} frames | median ms | p95 | p99 | max |");
        println!("|---|---|---|---|---|");
        for (name, key, v) in [
            (
                "client frame (selection, scheduling, arrivals)",
                "client_ms",
                &mut self.client,
            ),
            (
                "scene (mesh builds queued, uploads)",
                "scene_ms",
                &mut self.scene,
            ),
            ("renderer encode (CPU)", "encode_ms", &mut self.encode),
            ("encode + draw, waited for", "draw_ms", &mut self.draw),
            ("whole frame", "frame_ms", &mut self.total),
        ] {
            if v.is_empty() {
                continue;
            }
            let q = qs.map(|q| crate::app::snapshot::quantile(v, q));
            println!(
                "| {name} | {:.3} | {:.3} | {:.3} | {:.3} |",
                q[0], q[1], q[2], q[3]
            );
            parts.insert(
                key.to_owned(),
                serde_json::json!({"median": q[0], "p95": q[1], "p99": q[2], "max": q[3]}),
            );
        }
        println!("{over} of {n} frames over the {budget_ms:.2} ms budget of {fps} fps");
        let mut json = serde_json::json!({
            "adapter": adapter,
            "width": width,
            "height": height,
            "fps": fps,
            "frames": n,
            "frames_over_budget": over,
        });
        if let Some(o) = json.as_object_mut() {
            o.extend(parts);
        }
        println!("{json}");
        json
    }
}
