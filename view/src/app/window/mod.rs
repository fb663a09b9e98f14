//! The interactive viewer: a winit 0.30 window with a wgpu surface.
//!
//! Each redraw: apply the input to the camera, run the streaming client's
//! frame (deliver what arrived, select, request), turn its draw list into
//! the renderer's ([`SceneBuilder`], meshes built on worker threads), draw
//! the planet into an offscreen `Rgba8UnormSrgb` target with the shared
//! [`planet_render::Renderer`], then compose it with the text readout onto the surface
//! (whatever its format) in one full-screen pass.
//!
//! Controls: WASD / arrows move (speed ∝ altitude, Shift ×5), mouse drag
//! looks (fly) or orbits, scroll changes altitude / range, Q/E down / up,
//! Tab toggles orbit / fly, G goes to `--goto`, C toggles crack fixing,
//! H toggles the readout, Esc quits.

use crate::app::camera::{Controller, Input, Mode};
use crate::app::connect::{self, Endpoint, Source};
use crate::app::hud;
use crate::app::render_cmd::fit_planes;
use crate::app::scene::{BuildMode, SceneBuilder};
use anyhow::{Context, Result};
use planet_client::quality::QualityConfig;
use planet_client::ClientConfig;
use planet_core::format::Header;
use planet_render::{FrameTarget, RenderSettings};
use planet_session::streaming::StreamingClient;
use std::collections::HashSet;
use std::path::PathBuf;
use std::time::Instant;
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::KeyCode;

mod events;
mod gpu;

use gpu::{read_texture, save_png, Gfx};

/// No display to open a window on (the message says what to do instead).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct NoDisplay(pub String);

/// Options of the window.
#[derive(Debug, Clone)]
pub struct WindowOptions {
    /// Data source.
    pub source: Source,
    /// Simulated link.
    pub link: Option<planet_linksim::LinkConfig>,
    /// Target frame rate of the quality controller.
    /// Target frame rate; `None` picks one from the adapter (see [`default_target_fps`]).
    pub target_fps: Option<f64>,
    /// The --goto point.
    pub goto: Option<[f64; 3]>,
    /// Window size.
    pub width: u32,
    /// Window size.
    pub height: u32,
    /// Screenshot path (testing).
    pub screenshot: Option<PathBuf>,
    /// Exit after this many frames (testing).
    pub exit_after_frames: Option<u64>,
    /// Largest screen-space error in pixels the client aims at.
    pub max_sse: f64,
    /// Budget of resident samples in MB.
    pub memory_mb: Option<f64>,
    /// Append a JSON object per frame here (camera and counters).
    pub state: Option<PathBuf>,
}

fn no_display_message(detail: &str) -> String {
    format!(
        "planet-view: cannot open a window: {detail}.\n\
         Without a display, either render offscreen:\n\
         \x20   planet-view render --trajectory rainier --local --out frames/\n\
         or run the window under a virtual X server:\n\
         \x20   xvfb-run -a -s '-screen 0 1280x720x24' planet-view --local"
    )
}

/// Open the window and run until it is closed.
pub fn run(opts: WindowOptions) -> Result<()> {
    let has = |k: &str| std::env::var_os(k).is_some_and(|v| !v.is_empty());
    if !has("DISPLAY") && !has("WAYLAND_DISPLAY") {
        return Err(NoDisplay(no_display_message(
            "neither DISPLAY nor WAYLAND_DISPLAY is set",
        ))
        .into());
    }
    let event_loop = EventLoop::new()
        .map_err(|e| NoDisplay(no_display_message(&format!("the event loop failed: {e}"))))?;
    let rt = connect::runtime()?;
    let endpoint = connect::start(&rt, &opts.source, opts.link.as_ref())?;
    let cfg = ClientConfig {
        quality: QualityConfig::target_fps(opts.target_fps.unwrap_or(default_target_fps(false))),
        memory_budget: opts.memory_mb.map(|mb| (mb.max(0.0) * 1e6) as u64),
        ..ClientConfig::for_policy(planet_client::Policy::Ours, opts.max_sse)
    };
    let client = connect::connect(&rt, &endpoint.session, cfg)?;
    let header = client.header().clone();
    let datum = header.datum;
    // The views `G` cycles through: orbit, `--goto`, and the built-in
    // planet's named places; the window starts in the first.
    let mut views = Vec::new();
    if let Some([lat, lon, alt]) = opts.goto {
        views.push(("--goto".to_string(), Controller::fly(lat, lon, alt)));
    }
    let (olat, olon) = match opts.source {
        Source::Local => (
            planet_preprocess::builtin::PLACES[0].lat,
            planet_preprocess::builtin::PLACES[0].lon,
        ),
        _ => (20.0, 10.0),
    };
    views.push((
        "orbit".to_string(),
        Controller::orbit(olat, olon, 1.5 * datum.equatorial_radius()),
    ));
    if matches!(opts.source, Source::Local) {
        for p in planet_preprocess::builtin::PLACES {
            views.push((p.name.to_string(), Controller::place(p.lat, p.lon)));
        }
    }
    let start_cam = views[0].1;
    let state = match &opts.state {
        Some(p) => Some(std::io::BufWriter::new(
            std::fs::File::create(p).with_context(|| format!("--state {}", p.display()))?,
        )),
        None => None,
    };
    let mut app = App {
        opts,
        scene: SceneBuilder::new(&header),
        header,
        client: Some(client),
        gfx: None,
        error: None,
        ctl: start_cam,
        views,
        view: 0,
        cursor_point: None,
        state,
        started: Instant::now(),
        bytes_window: (Instant::now(), 0),
        byte_rate: 0.0,
        keys: HashSet::new(),
        dragging: false,
        last_cursor: None,
        input: Input::default(),
        last_frame: Instant::now(),
        last_cost: None,
        refresh_s: 1.0 / 60.0,
        frames: 0,
        fps: 0.0,
        fps_window: (Instant::now(), 0),
        last_title: Instant::now(),
        crack_fixing: true,
        show_hud: true,
        header_changes: 0,
        last_stats: None,
    };
    event_loop.set_control_flow(ControlFlow::Poll);
    let r = event_loop.run_app(&mut app);
    if let Some(c) = app.client.take() {
        c.close();
    }
    drop(app.gfx.take());
    shutdown(endpoint, rt);
    r.context("event loop")?;
    match app.error.take() {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

fn shutdown(endpoint: Endpoint, rt: tokio::runtime::Runtime) {
    endpoint.shutdown(&rt);
    rt.shutdown_timeout(std::time::Duration::from_secs(2));
}

struct App {
    opts: WindowOptions,
    header: Header,
    scene: SceneBuilder,
    client: Option<StreamingClient>,
    gfx: Option<Gfx>,
    error: Option<anyhow::Error>,
    ctl: Controller,
    /// Named views `G` cycles through, and the one shown last.
    views: Vec<(String, Controller)>,
    view: usize,
    /// The point under the cursor: lat, lon, elevation, whether the
    /// elevation is known (resident data).
    cursor_point: Option<(f64, f64, f64, bool)>,
    /// The `--state` file.
    state: Option<std::io::BufWriter<std::fs::File>>,
    started: Instant,
    /// Bytes received at the start of the rate window, and the rate (B/s).
    bytes_window: (Instant, u64),
    byte_rate: f64,
    keys: HashSet<KeyCode>,
    dragging: bool,
    last_cursor: Option<(f64, f64)>,
    input: Input,
    last_frame: Instant,
    /// The last frame's cost for the frame-rate controller ([`frame_cost`]).
    last_cost: Option<f64>,
    /// The display's refresh period in seconds (1/60 where unknown).
    refresh_s: f64,
    frames: u64,
    fps: f64,
    fps_window: (Instant, u64),
    last_title: Instant,
    crack_fixing: bool,
    show_hud: bool,
    header_changes: u64,
    last_stats: Option<planet_client::stats::FrameStats>,
}

impl App {
    fn fail(&mut self, event_loop: &ActiveEventLoop, e: anyhow::Error) {
        self.error = Some(e);
        event_loop.exit();
    }

    fn redraw(&mut self, event_loop: &ActiveEventLoop) -> Result<()> {
        let now = Instant::now();
        let dt = (now - self.last_frame).as_secs_f64().max(1e-4);
        self.last_frame = now;
        let datum = self.header.datum;
        let mut input = self.held();
        self.input = Input::default();
        // The point under the cursor (the wheel zooms towards it; the HUD
        // shows it): the cursor ray against the sphere through the ground
        // below the eye, then again at the elevation found there.
        self.cursor_point = None;
        if let (Some(gfx), Some(client), Some((cx, cy))) =
            (self.gfx.as_ref(), self.client.as_ref(), self.last_cursor)
        {
            let (w, h) = (gfx.config.width, gfx.config.height);
            let cam = self.ctl.camera(&datum, w, h);
            let tree = client.client.tree();
            let mut ground = 0.0;
            for _ in 0..2 {
                let Some(p) = crate::app::camera::pick(&datum, &cam, cx, cy, w, h, ground) else {
                    self.cursor_point = None;
                    break;
                };
                let (lat, lon, _) = crate::app::camera::position_to_geodetic(&datum, p);
                let elev = crate::app::camera::ground_elevation(tree, &self.header, lat, lon);
                ground = elev.unwrap_or(0.0);
                self.cursor_point = Some((lat, lon, ground, elev.is_some()));
            }
        }
        input.zoom_at = self.cursor_point.map(|(lat, lon, e, _)| (lat, lon, e));
        self.ctl.update(&datum, &input, dt);
        let (Some(gfx), Some(client)) = (self.gfx.as_mut(), self.client.as_mut()) else {
            return Ok(());
        };
        let (w, h) = (gfx.config.width, gfx.config.height);
        let cam = self.ctl.camera(&datum, w, h);
        if let Some(cost) = self.last_cost.take() {
            client.client.observe_frame_cost(cost);
        }
        let out = client.frame(&cam, dt);
        if client.counters().header_changes != self.header_changes {
            self.header_changes = client.counters().header_changes;
            self.header = client.header().clone();
            self.scene = SceneBuilder::new(&self.header);
        }
        let blocks = self
            .scene
            .prepare(client.client.tree(), &out.draw, BuildMode::Async);
        let base = RenderSettings::for_planet(
            &self.header.datum,
            self.header.min_elevation as f64,
            self.header.max_elevation as f64,
        );
        let mut settings = fit_planes(&base, &self.scene, &blocks);
        settings.crack_fixing = self.crack_fixing;
        gfx.renderer.settings = settings;

        // Readout.
        self.frames += 1;
        let (t0, n0) = self.fps_window;
        if (now - t0).as_secs_f64() >= 0.5 {
            self.fps = (self.frames - n0) as f64 / (now - t0).as_secs_f64();
            self.fps_window = (now, self.frames);
        }
        let s = &out.stats;
        let alt = self.ctl.altitude(&datum);
        let (eye, _, _) = self.ctl.pose(&datum);
        let (lat, lon, _) = crate::app::camera::position_to_geodetic(&datum, eye);
        let received = client.bytes_received();
        let (b_t0, b_n0) = self.bytes_window;
        if (now - b_t0).as_secs_f64() >= 1.0 {
            self.byte_rate = received.saturating_sub(b_n0) as f64 / (now - b_t0).as_secs_f64();
            self.bytes_window = (now, received);
        }
        let mode = match self.ctl.mode {
            Mode::Fly => "fly",
            Mode::Orbit => "orbit",
        };
        let tris = gfx.renderer.stats.triangles;
        let lines = vec![
            format!(
                "{:5.1} fps  {} tris  {} blocks  SSE max {:.1} px (tol {:.2})",
                self.fps,
                tris,
                blocks.len(),
                s.max_screen_error,
                client.client.tolerance()
            ),
            format!(
                "{} received  {}/s  {} in flight  {} nodes  {}",
                hud::bytes(received),
                hud::bytes(self.byte_rate as u64),
                s.in_flight,
                s.nodes,
                if client.is_connected() {
                    "connected"
                } else {
                    "RECONNECTING"
                }
            ),
            format!(
                "{}  alt {}  {}  view {}",
                hud::lat_lon(lat, lon),
                hud::metres(alt),
                mode,
                self.views[self.view].0,
            ),
            match self.cursor_point {
                Some((clat, clon, e, known)) => format!(
                    "cursor {}  elev {}",
                    hud::lat_lon(clat, clon),
                    if known {
                        hud::metres(e)
                    } else {
                        "?".to_string()
                    }
                ),
                None => "cursor: sky".to_string(),
            },
            format!(
                "cracks {}  mesh jobs {}",
                if self.crack_fixing { "fixed" } else { "OFF" },
                self.scene.stats.pending
            ),
            "WASD/arrows move  drag look  wheel alt  Q/E down/up".to_string(),
            "Tab orbit/fly  G next place  C cracks  H hud  Esc quit".to_string(),
        ];
        if (now - self.last_title).as_secs_f64() >= 0.5 || self.frames == 1 {
            self.last_title = now;
            gfx.window.set_title(&format!(
                "planet-view — {:.1} fps, {} tris, {} received, {} in flight, SSE max {:.1} px, alt {}",
                self.fps,
                tris,
                hud::bytes(client.bytes_received()),
                s.in_flight,
                s.max_screen_error,
                hud::metres(alt)
            ));
        }
        if let Some(out_state) = self.state.as_mut() {
            use std::io::Write;
            let c = &self.ctl;
            let line = serde_json::json!({
                "frame": self.frames,
                "time_s": (now - self.started).as_secs_f64(),
                "view": self.views[self.view].0,
                "mode": mode,
                "lat": lat,
                "lon": lon,
                "alt": alt,
                "heading": c.heading,
                "pitch": c.pitch,
                "target_lat": c.target_lat,
                "target_lon": c.target_lon,
                "range": c.range,
                "azimuth": c.azimuth,
                "tilt": c.tilt,
                "width": w,
                "height": h,
                "hud": self.show_hud,
                "bytes_received": received,
                "in_flight": s.in_flight,
                "max_sse_px": s.max_screen_error,
                "tolerance_px": client.client.tolerance(),
                "cursor": self.cursor_point.map(|(a, b, e, _)| [a, b, e]),
            });
            writeln!(out_state, "{line}")
                .and_then(|()| out_state.flush())
                .context("--state")?;
        }
        let scale = if w >= 1600 { 2 } else { 1 };
        let panel = self.show_hud.then(|| hud::rasterise(&lines, scale));
        gfx.set_hud(panel.as_ref());
        self.last_stats = Some(out.stats);
        client.client.recycle(out.draw);

        // Draw.
        let acquire = Instant::now();
        let frame = match gfx.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(f)
            | wgpu::CurrentSurfaceTexture::Suboptimal(f) => f,
            wgpu::CurrentSurfaceTexture::Outdated | wgpu::CurrentSurfaceTexture::Lost => {
                let size = gfx.window.inner_size();
                gfx.config.width = 0;
                gfx.resize(size.width, size.height);
                return Ok(());
            }
            _ => return Ok(()),
        };
        let mut waited = acquire.elapsed();
        let device = gfx.renderer.device().clone();
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("window frame"),
        });
        let cview = gfx.color.create_view(&Default::default());
        let dview = gfx.depth.create_view(&Default::default());
        gfx.renderer.encode(
            &mut enc,
            FrameTarget {
                color: &cview,
                depth: &dview,
                width: w,
                height: h,
            },
            &cam,
            &blocks,
        );
        let sview = frame.texture.create_view(&Default::default());
        {
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("compose"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &sview,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color::BLACK),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&gfx.pipeline);
            pass.set_bind_group(0, &gfx.bind_group, &[]);
            pass.draw(0..3, 0..1);
        }
        gfx.renderer.queue().submit([enc.finish()]);
        let done = self
            .opts
            .exit_after_frames
            .is_some_and(|n| self.frames >= n);
        if done {
            if let Some(path) = self.opts.screenshot.clone() {
                let queue = gfx.renderer.queue().clone();
                let (sw, sh, rgba) = if gfx.copy_src {
                    let bgra = matches!(
                        gfx.config.format.remove_srgb_suffix(),
                        wgpu::TextureFormat::Bgra8Unorm
                    );
                    read_texture(&device, &queue, &frame.texture, bgra)?
                } else {
                    read_texture(&device, &queue, &gfx.color, false)?
                };
                save_png(&path, sw, sh, &rgba)?;
                eprintln!(
                    "planet-view: screenshot {} ({}x{}, from the {}, adapter {}) after {} frames; last frame {} blocks, {} triangles, {} received",
                    path.display(),
                    sw,
                    sh,
                    if gfx.copy_src { "window surface" } else { "offscreen target" },
                    gfx.adapter_name,
                    self.frames,
                    blocks.len(),
                    tris,
                    hud::bytes(client.bytes_received())
                );
            }
        }
        gfx.window.pre_present_notify();
        let present = Instant::now();
        gfx.renderer.queue().present(frame);
        waited += present.elapsed();
        // On a CPU renderer the drawing runs on other CPU threads after
        // submit, in neither the work nor (at its low rates) a capped
        // interval: the controller keeps the interval there.
        self.last_cost = (!gfx.cpu_adapter).then(|| {
            frame_cost(
                now.elapsed().saturating_sub(waited).as_secs_f64(),
                dt,
                self.refresh_s,
            )
        });
        if done {
            event_loop.exit();
        }
        Ok(())
    }
}

/// A frame's cost for the frame-rate controller
/// ([`planet_client::Client::observe_frame_cost`]): its CPU work (`work_s`,
/// the frame without the waits for a surface texture and for presenting,
/// which vsync fills), or the interval `dt` since the frame before where that
/// missed a refresh of the display (`refresh_s`): the GPU's work shows only
/// there, since the window does not time the GPU. A GPU-bound scene may so
/// alternate between a coarser tolerance (missed refreshes) and a finer one
/// (cheap CPU work) within the controller's band.
fn frame_cost(work_s: f64, dt: f64, refresh_s: f64) -> f64 {
    if dt > 1.5 * refresh_s {
        work_s.max(dt)
    } else {
        work_s
    }
}

/// The frame rate aimed at when `--target-fps` is not given: 60 on a GPU; 15
/// on a CPU renderer, where 60 fps would drive the quality factor down to the
/// root blocks.
pub fn default_target_fps(cpu_adapter: bool) -> f64 {
    if cpu_adapter {
        15.0
    } else {
        60.0
    }
}

#[cfg(test)]
mod tests {
    use super::frame_cost;

    #[test]
    fn cost_is_the_work_unless_a_refresh_was_missed() {
        let r = 1.0 / 60.0;
        // On time: the CPU work, however long vsync made the interval.
        assert_eq!(frame_cost(0.004, r, r), 0.004);
        // Two refreshes for one frame: the interval shows the GPU's work.
        assert_eq!(frame_cost(0.004, 2.0 * r, r), 2.0 * r);
        // CPU work beyond the interval (the first frame) stays the cost.
        assert_eq!(frame_cost(0.1, 2.0 * r, r), 0.1);
    }
}
