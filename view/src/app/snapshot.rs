//! `planet-view snapshot`: one still image from the complete database (the
//! reference client converged for the camera), e.g. for documentation.

use crate::app::camera::{geodetic_to_position, local_frame};
use crate::app::reference::{reference_qf, Reference};
use crate::app::render_cmd::fit_planes;
use anyhow::{Context, Result};
use glam::DVec3;
use planet_client::Camera;
use planet_core::format::DbFile;
use planet_render::{HeadlessRenderer, RenderSettings};
use std::path::PathBuf;
use std::time::Duration;

/// Options of a snapshot.
#[derive(Debug, Clone)]
pub struct SnapshotOptions {
    /// Database file.
    pub db: PathBuf,
    /// Eye (lat°, lon°, alt m).
    pub eye: [f64; 3],
    /// Target (lat°, lon°, alt m); `None`: the planet centre.
    pub target: Option<[f64; 3]>,
    /// Output PNG.
    pub out: PathBuf,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Vertical field of view (radians).
    pub fov_y: f64,
    /// Sample spacing in pixels.
    pub px: f64,
    /// Sun direction (lat°, lon°).
    pub sun: Option<[f64; 2]>,
    /// Shade by altitude instead of the colour tree.
    pub altitude_colours: bool,
    /// After the image, render the same converged scene this many more
    /// times without read-back and print the frame times (0: none).
    pub time_frames: usize,
}

/// Render the snapshot.
pub fn run(o: &SnapshotOptions) -> Result<()> {
    let db = DbFile::open(&o.db).with_context(|| format!("opening {}", o.db.display()))?;
    let header = db.header.clone();
    let datum = header.datum;
    let eye = geodetic_to_position(&datum, o.eye[0], o.eye[1], o.eye[2]);
    let target = match o.target {
        Some(t) => geodetic_to_position(&datum, t[0], t[1], t[2]),
        None => DVec3::ZERO,
    };
    let (up, _, _) = local_frame(o.eye[0], o.eye[1]);
    let cam = Camera {
        eye,
        forward: target - eye,
        up,
        fov_y: o.fov_y,
        aspect: o.width as f64 / o.height as f64,
        viewport_height_px: o.height as f64,
    };
    let qf = reference_qf(o.px, o.fov_y, o.height);
    let mut reference = Reference::from_file(db, qf)?;
    let mut blocks = reference.converge(&cam, 20_000, Duration::from_secs(600));
    if o.altitude_colours {
        for b in &mut blocks {
            b.colour = None;
        }
    }
    let mut base = RenderSettings::for_planet(
        &datum,
        header.min_elevation as f64,
        header.max_elevation as f64,
    );
    if let Some([lat, lon]) = o.sun {
        let (s, _, _) = local_frame(lat, lon);
        base.sun_dir = [s.x as f32, s.y as f32, s.z as f32];
    }
    let mut r = HeadlessRenderer::with_settings(o.width, o.height, base.clone())
        .context("headless renderer (install mesa-vulkan-drivers for lavapipe)")?;
    r.renderer.settings = fit_planes(&base, reference.scene(), &blocks);
    let img = r.render(&cam, &blocks)?;
    img.save_png(&o.out)?;
    let covered = img.depth.iter().filter(|&&d| d > 0.0).count();
    println!(
        "planet-view snapshot: {} ({} blocks, {} triangles, converged {} in {} frames, QF {qf:.3e}, {:.0}% of pixels covered, adapter {})",
        o.out.display(),
        blocks.len(),
        r.renderer.stats.triangles,
        reference.last_converged,
        reference.last_frames,
        100.0 * covered as f64 / img.depth.len() as f64,
        r.adapter_name
    );
    if o.time_frames > 0 {
        time_frames(&mut r, &cam, &blocks, o.time_frames)?;
    }
    Ok(())
}

/// Frames rendered before the timed ones (uploads, pipeline warm-up).
const WARM_UP_FRAMES: usize = 3;

/// The value at quantile `q` (0..=1) of `v`, sorted in place.
pub(crate) fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// Render the converged scene `n` times (after a few warm-up frames) and
/// print the frame and encode times: a table row and one JSON line.
fn time_frames(
    r: &mut HeadlessRenderer,
    cam: &Camera,
    blocks: &[planet_render::DrawBlock],
    n: usize,
) -> Result<()> {
    let mut frame = Vec::with_capacity(n);
    let mut encode = Vec::with_capacity(n);
    for k in 0..WARM_UP_FRAMES + n {
        let t = r.time_frame(cam, blocks)?;
        if k >= WARM_UP_FRAMES {
            frame.push(t.frame_s * 1e3);
            encode.push(t.encode_s * 1e3);
        }
    }
    let triangles = r.renderer.stats.triangles;
    let (w, h) = r.size();
    let f = [0.5, 0.95, 1.0].map(|q| quantile(&mut frame, q));
    let e = [0.5, 0.95, 1.0].map(|q| quantile(&mut encode, q));
    println!("| adapter | size | blocks | triangles | frame ms median / p95 / max | encode ms median / p95 / max | fps at the median | triangles/s |");
    println!("|---|---|---|---|---|---|---|---|");
    println!(
        "| {} | {w}×{h} | {} | {triangles} | {:.3} / {:.3} / {:.3} | {:.3} / {:.3} / {:.3} | {:.1} | {:.1} M |",
        r.adapter_name,
        blocks.len(),
        f[0],
        f[1],
        f[2],
        e[0],
        e[1],
        e[2],
        1e3 / f[0],
        triangles as f64 / f[0] / 1e3
    );
    let json = serde_json::json!({
        "adapter": r.adapter_name,
        "width": w,
        "height": h,
        "blocks": blocks.len(),
        "triangles": triangles,
        "frames": n,
        "frame_ms": {"median": f[0], "p95": f[1], "max": f[2]},
        "encode_ms": {"median": e[0], "p95": e[1], "max": e[2]},
    });
    println!("{json}");
    Ok(())
}
