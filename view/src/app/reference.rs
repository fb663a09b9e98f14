//! The reference image: the same camera rendered from the complete database,
//! and the image error of a streamed frame against it.
//!
//! The reference is a second [`Client`] whose records come straight from the
//! database (a file read, or a second streaming client on a direct link),
//! with a fixed quality factor high enough that every drawn block's samples
//! are at most `reference_px` pixels apart on screen (or it is a leaf of the
//! database), run until it converges for the camera: no request sent, none
//! in flight, no split, merge or refine left. So it shows what the database
//! holds at (sub-)pixel resolution, independently of bandwidth and time.
//!
//! Sample spacing: a block drawn at LOD 0 has `quality = √QF·r/(W·d) ∈
//! [1, 2)` (it would split above 2), and its samples are `√2·r/W` apart,
//! i.e. at most `2√2/√QF` radians; so `QF = 8 / (reference_px · pixel)²`
//! with `pixel = fov_y / height`.

use crate::app::scene::{BuildMode, SceneBuilder};
use planet_client::quality::{QualityConfig, QualityMode};
use planet_client::tree::PartialTree;
use planet_client::{Camera, Client, ClientConfig, DrawBlock as ClientBlock};
use planet_core::format::DbFile;
use planet_render::{DrawBlock, Image};
use planet_session::streaming::StreamingClient;
use std::time::{Duration, Instant};

/// The quality factor giving samples at most `px` pixels apart.
pub fn reference_qf(px: f64, fov_y: f64, height: u32) -> f64 {
    let pixel = fov_y / height.max(1) as f64;
    8.0 / (px * pixel).powi(2)
}

/// A client config with a fixed quality factor and a large queue: the
/// thesis's spacing criterion (samples at most so many pixels apart), not a
/// streaming policy.
pub fn reference_config(qf: f64, decode_threads: usize) -> ClientConfig {
    let mut cfg = ClientConfig {
        decode_threads,
        tree_ops_per_frame: 4096,
        quality: QualityConfig {
            mode: QualityMode::Fixed,
            initial: qf,
            ..QualityConfig::default()
        },
        ..ClientConfig::for_policy(planet_client::Policy::Thesis, 1.0)
    };
    cfg.queue.max_in_flight = 256;
    cfg.queue.cancel_after_frames = 1_000_000;
    cfg.queue.preempt_margin = f64::INFINITY;
    cfg
}

enum Feed {
    File(Box<DbFile>),
    Stream(Box<StreamingClient>),
}

/// A converging reference client.
pub struct Reference {
    feed: Feed,
    client: Option<Client>,
    scene: SceneBuilder,
    /// Frames the last convergence took.
    pub last_frames: usize,
    /// Whether the last convergence finished (false: hit the frame limit).
    pub last_converged: bool,
}

/// Why a reference cannot be built.
#[derive(Debug, thiserror::Error)]
pub enum ReferenceError {
    /// The database file cannot be read.
    #[error("reference database: {0}")]
    Db(#[from] planet_core::format::FormatError),
    /// The client refuses the header.
    #[error("reference client: {0}")]
    Client(#[from] planet_client::ClientError),
}

impl Reference {
    /// A reference reading records from the database file.
    pub fn from_file(db: DbFile, qf: f64) -> Result<Reference, ReferenceError> {
        let client = Client::new(db.header.clone(), reference_config(qf, 0))?;
        let scene = SceneBuilder::new(&db.header);
        Ok(Reference {
            feed: Feed::File(Box::new(db)),
            client: Some(client),
            scene,
            last_frames: 0,
            last_converged: false,
        })
    }

    /// A reference fed by a streaming client (connected with
    /// [`reference_config`]) on a direct link to the server.
    pub fn from_stream(sc: StreamingClient) -> Reference {
        let scene = SceneBuilder::new(sc.header());
        Reference {
            feed: Feed::Stream(Box::new(sc)),
            client: None,
            scene,
            last_frames: 0,
            last_converged: false,
        }
    }

    /// Run frames for `camera` until converged (or `max_frames`, or
    /// `max_time`), and return the renderer's draw list.
    pub fn converge(
        &mut self,
        camera: &Camera,
        max_frames: usize,
        max_time: Duration,
    ) -> Vec<DrawBlock> {
        let t0 = Instant::now();
        let mut draw: Vec<ClientBlock> = vec![];
        let mut quiet = 0;
        let mut frames = 0;
        self.last_converged = false;
        while frames < max_frames && t0.elapsed() < max_time {
            frames += 1;
            let (out, busy) = match (&mut self.feed, &mut self.client) {
                (Feed::File(db), Some(client)) => {
                    let out = client.frame(camera, 1.0 / 30.0);
                    for s in &out.send {
                        let r = db
                            .read_record(&s.record)
                            .map_err(planet_client::TransportError::request);
                        client.deliver(s.id, r);
                    }
                    let busy = !out.send.is_empty()
                        || client.queue().in_flight() > 0
                        || !client.pending_ops().is_empty();
                    (out, busy)
                }
                (Feed::Stream(sc), _) => {
                    let out = sc.frame(camera, 1.0 / 30.0);
                    let busy = !out.send.is_empty()
                        || sc.client.queue().in_flight() > 0
                        || !sc.client.pending_ops().is_empty()
                        || sc.client.decoding() > 0;
                    if busy {
                        std::thread::sleep(Duration::from_millis(2));
                    }
                    (out, busy)
                }
                (Feed::File(_), None) => unreachable!(),
            };
            let changed =
                out.stats.refines_applied > 0 || out.stats.splits > 0 || out.stats.merges > 0;
            draw = out.draw;
            if busy || changed {
                quiet = 0;
            } else {
                quiet += 1;
                if quiet >= 2 {
                    self.last_converged = true;
                    break;
                }
            }
        }
        self.last_frames = frames;
        let tree = tree_of(&self.feed, &self.client);
        self.scene.prepare(tree, &draw, BuildMode::Sync)
    }

    /// Triangles of the last reference draw list (from the scene stats).
    pub fn scene(&self) -> &SceneBuilder {
        &self.scene
    }
}

fn tree_of<'a>(feed: &'a Feed, client: &'a Option<Client>) -> &'a PartialTree {
    match (feed, client) {
        (_, Some(c)) => c.tree(),
        (Feed::Stream(s), None) => s.client.tree(),
        (Feed::File(_), None) => unreachable!("file references own a client"),
    }
}

/// Image error of a frame against its reference.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageError {
    /// RMS difference of the depth-derived position (metres) over pixels
    /// covered in both images (0 when none).
    pub depth_rmse_m: f64,
    /// The same relative to the reference distance (RMS of `Δd / d`).
    pub depth_rel_rmse: f64,
    /// Pixels covered in both.
    pub covered_both: usize,
    /// Pixels covered in exactly one of the two (silhouette / hole mismatch).
    pub coverage_mismatch: usize,
    /// PSNR of the sRGB colour (dB) over all pixels, capped at 100 dB.
    pub psnr_db: f64,
}

/// Compare a frame with the reference rendered from the same camera.
pub fn image_error(frame: &Image, reference: &Image) -> ImageError {
    assert_eq!(
        (frame.width, frame.height),
        (reference.width, reference.height)
    );
    let (w, h) = (frame.width, frame.height);
    let (mut se, mut rel, mut both, mut mismatch) = (0.0f64, 0.0f64, 0usize, 0usize);
    for y in 0..h {
        for x in 0..w {
            // Same camera, same ray: the position difference is the
            // difference of the distances along it.
            match (frame.distance(x, y), reference.distance(x, y)) {
                (Some(a), Some(b)) => {
                    both += 1;
                    se += (a - b) * (a - b);
                    rel += ((a - b) / b.max(1e-6)).powi(2);
                }
                (None, None) => {}
                _ => mismatch += 1,
            }
        }
    }
    let mut cse = 0.0f64;
    for (a, b) in frame
        .rgba
        .chunks_exact(4)
        .zip(reference.rgba.chunks_exact(4))
    {
        for k in 0..3 {
            let d = a[k] as f64 - b[k] as f64;
            cse += d * d;
        }
    }
    let mse = cse / (3.0 * (w as f64) * (h as f64)).max(1.0);
    let psnr = if mse > 0.0 {
        (10.0 * (255.0f64 * 255.0 / mse).log10()).min(100.0)
    } else {
        100.0
    };
    ImageError {
        depth_rmse_m: if both > 0 {
            (se / both as f64).sqrt()
        } else {
            0.0
        },
        depth_rel_rmse: if both > 0 {
            (rel / both as f64).sqrt()
        } else {
            0.0
        },
        covered_both: both,
        coverage_mismatch: mismatch,
        psnr_db: psnr,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use planet_render::Projection;

    fn img(depth: Vec<f32>, rgb: u8) -> Image {
        let n = depth.len();
        Image {
            width: n as u32,
            height: 1,
            rgba: (0..n).flat_map(|_| [rgb, rgb, rgb, 255]).collect(),
            depth,
            projection: Projection {
                near: 1.0,
                far: f64::INFINITY,
                fov_y: 1.0,
                aspect: n as f64,
            },
        }
    }

    #[test]
    fn errors_are_zero_for_identical_images_and_grow_with_differences() {
        let a = img(vec![0.5, 0.25, 0.0, 0.1], 100);
        let e = image_error(&a, &a);
        assert_eq!(e.depth_rmse_m, 0.0);
        assert_eq!(e.psnr_db, 100.0);
        assert_eq!(e.covered_both, 3);
        assert_eq!(e.coverage_mismatch, 0);
        let b = img(vec![0.5, 0.2, 0.1, 0.0], 110);
        let e = image_error(&b, &a);
        assert_eq!(e.covered_both, 2);
        assert_eq!(e.coverage_mismatch, 2);
        assert!(e.depth_rmse_m > 0.0 && e.depth_rmse_m.is_finite());
        assert!((e.psnr_db - 10.0 * (255.0f64 * 255.0 / 100.0).log10()).abs() < 1e-9);
    }

    #[test]
    fn reference_qf_matches_the_sample_spacing() {
        let qf = reference_qf(1.0, 1.0, 500);
        // 2√2/√QF = one pixel.
        assert!((2.0 * 2f64.sqrt() / qf.sqrt() - 1.0 / 500.0).abs() < 1e-12);
    }
}
