//! Offscreen rendering with read-back of colour and depth (tests, image
//! metrics, screenshots).

use crate::render::{
    Camera, DrawBlock, FrameTarget, Projection, RenderSettings, Renderer, COLOR_FORMAT,
    DEPTH_FORMAT,
};
use std::path::Path;
use std::time::Instant;

/// Errors of the headless renderer.
#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    /// No wgpu adapter (no GPU and no lavapipe/llvmpipe).
    #[error("no graphics adapter: {0}")]
    NoAdapter(String),
    /// The device could not be created.
    #[error("device request failed: {0}")]
    Device(String),
    /// Reading the image back failed.
    #[error("read-back failed: {0}")]
    Readback(String),
    /// Writing a PNG failed.
    #[error("png: {0}")]
    Png(String),
    /// Waiting for the device to finish a frame failed.
    #[error("waiting for the device failed: {0}")]
    Wait(String),
}

/// What one frame cost, measured without read-back.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameTiming {
    /// Seconds spent encoding the frame's commands on the CPU (the
    /// renderer's own per-frame CPU work: culling, uniforms, draw calls).
    pub encode_s: f64,
    /// Seconds from the start of encoding until the device has finished the
    /// frame: on a GPU, the GPU's time plus the driver's; on lavapipe, the
    /// rasterisation on the CPU too.
    pub frame_s: f64,
}

/// A rendered image.
#[derive(Debug, Clone)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// RGBA8 (sRGB), row-major, row 0 at the top.
    pub rgba: Vec<u8>,
    /// Reversed-Z depth (1 near, 0 far or background), row-major.
    pub depth: Vec<f32>,
    /// The projection used (to turn depth into distance).
    pub projection: Projection,
}

impl Image {
    /// Whether pixel `(x, y)` shows the background (nothing drawn).
    pub fn is_background(&self, x: u32, y: u32) -> bool {
        self.depth[(y * self.width + x) as usize] <= 0.0
    }

    /// Distance in metres along the view ray of pixel `(x, y)`, or `None`
    /// for background.
    pub fn distance(&self, x: u32, y: u32) -> Option<f64> {
        let d = self.depth[(y * self.width + x) as usize];
        self.projection
            .ray_distance(d, x, y, self.width, self.height)
    }

    /// The distance image (`NaN` for background), row-major.
    pub fn distances(&self) -> Vec<f64> {
        (0..self.height)
            .flat_map(|y| (0..self.width).map(move |x| (x, y)))
            .map(|(x, y)| self.distance(x, y).unwrap_or(f64::NAN))
            .collect()
    }

    /// Write the colour image as a PNG.
    pub fn save_png(&self, path: impl AsRef<Path>) -> Result<(), ViewError> {
        let file = std::fs::File::create(path).map_err(|e| ViewError::Png(e.to_string()))?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), self.width, self.height);
        enc.set_color(png::ColorType::Rgba);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc
            .write_header()
            .map_err(|e| ViewError::Png(e.to_string()))?;
        w.write_image_data(&self.rgba)
            .map_err(|e| ViewError::Png(e.to_string()))?;
        w.finish().map_err(|e| ViewError::Png(e.to_string()))
    }
}

/// A renderer with its own offscreen colour and depth targets.
pub struct HeadlessRenderer {
    /// The renderer (settings, caches, statistics).
    pub renderer: Renderer,
    width: u32,
    height: u32,
    color: wgpu::Texture,
    depth: wgpu::Texture,
    readback: wgpu::Buffer,
    padded_row: u32,
    /// The adapter's description, e.g. "llvmpipe (LLVM 15.0.6, 256 bits)".
    pub adapter_name: String,
}

impl HeadlessRenderer {
    /// Create a `width × height` renderer on the adapter chosen from the
    /// environment (`WGPU_BACKEND`, ...), with Earth-like default settings
    /// (change `renderer.settings`).
    pub fn new(width: u32, height: u32) -> Result<HeadlessRenderer, ViewError> {
        let settings = RenderSettings::for_planet(&planet_core::Datum::WGS84, -11_000.0, 9_000.0);
        Self::with_settings(width, height, settings)
    }

    /// As [`HeadlessRenderer::new`] with the given settings.
    pub fn with_settings(
        width: u32,
        height: u32,
        settings: RenderSettings,
    ) -> Result<HeadlessRenderer, ViewError> {
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            apply_limit_buckets: false,
        }))
        .map_err(|e| ViewError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        // The read-back copies the depth texture, which some adapters
        // (OpenGL ones: llvmpipe's GL when no Vulkan driver is installed)
        // cannot do; say so rather than fail in the first frame.
        if !adapter
            .get_downlevel_capabilities()
            .flags
            .contains(wgpu::DownlevelFlags::DEPTH_TEXTURE_AND_BUFFER_COPIES)
        {
            return Err(ViewError::NoAdapter(format!(
                "{} ({:?}) cannot copy depth textures, which the headless renderer reads back; \
                 install a Vulkan driver (Debian: mesa-vulkan-drivers for lavapipe) or set \
                 WGPU_BACKEND to a backend that can",
                info.name, info.backend
            )));
        }
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("planet-view headless"),
            required_features: wgpu::Features::empty(),
            required_limits: wgpu::Limits::downlevel_defaults().using_resolution(adapter.limits()),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| ViewError::Device(e.to_string()))?;
        let renderer = Renderer::new(device, queue, settings);
        let dev = renderer.device();
        let size = wgpu::Extent3d {
            width,
            height,
            depth_or_array_layers: 1,
        };
        let target = |format, label| {
            dev.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size,
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            })
        };
        let color = target(COLOR_FORMAT, "colour target");
        let depth = target(DEPTH_FORMAT, "depth target");
        let padded_row = (width * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
            * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let readback = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("read-back"),
            size: 2 * padded_row as u64 * height as u64,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        Ok(HeadlessRenderer {
            renderer,
            width,
            height,
            color,
            depth,
            readback,
            padded_row,
            adapter_name: format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type),
        })
    }

    /// Image size.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// A command encoder with the frame of `blocks` from `camera` drawn
    /// into the offscreen targets, and the projection it used.
    fn encode_frame(
        &mut self,
        label: &str,
        camera: &Camera,
        blocks: &[DrawBlock],
    ) -> (wgpu::CommandEncoder, Projection) {
        let cview = self
            .color
            .create_view(&wgpu::TextureViewDescriptor::default());
        let dview = self
            .depth
            .create_view(&wgpu::TextureViewDescriptor::default());
        let mut enc = self
            .renderer
            .device()
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) });
        let projection = self.renderer.encode(
            &mut enc,
            FrameTarget {
                color: &cview,
                depth: &dview,
                width: self.width,
                height: self.height,
            },
            camera,
            blocks,
        );
        (enc, projection)
    }

    /// Render `blocks` from `camera` into the offscreen targets and wait
    /// until the device has finished, without reading anything back: the
    /// frame's cost as a window would pay it (less the present). The first
    /// frames of a block set include its uploads; time the later ones.
    pub fn time_frame(
        &mut self,
        camera: &Camera,
        blocks: &[DrawBlock],
    ) -> Result<FrameTiming, ViewError> {
        let t0 = Instant::now();
        let (enc, _) = self.encode_frame("timed frame", camera, blocks);
        let t1 = Instant::now();
        self.renderer.queue().submit([enc.finish()]);
        self.renderer
            .device()
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| ViewError::Wait(e.to_string()))?;
        Ok(FrameTiming {
            encode_s: (t1 - t0).as_secs_f64(),
            frame_s: t0.elapsed().as_secs_f64(),
        })
    }

    /// Render `blocks` from `camera` and read back colour and depth.
    pub fn render(&mut self, camera: &Camera, blocks: &[DrawBlock]) -> Result<Image, ViewError> {
        let (w, h) = (self.width, self.height);
        let (mut enc, projection) = self.encode_frame("headless frame", camera, blocks);
        let half = self.padded_row as u64 * h as u64;
        for (tex, aspect, offset) in [
            (&self.color, wgpu::TextureAspect::All, 0),
            (&self.depth, wgpu::TextureAspect::DepthOnly, half),
        ] {
            enc.copy_texture_to_buffer(
                wgpu::TexelCopyTextureInfo {
                    texture: tex,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect,
                },
                wgpu::TexelCopyBufferInfo {
                    buffer: &self.readback,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset,
                        bytes_per_row: Some(self.padded_row),
                        rows_per_image: Some(h),
                    },
                },
                wgpu::Extent3d {
                    width: w,
                    height: h,
                    depth_or_array_layers: 1,
                },
            );
        }
        self.renderer.queue().submit([enc.finish()]);
        let slice = self.readback.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.renderer
            .device()
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| ViewError::Readback(e.to_string()))?;
        rx.recv()
            .map_err(|e| ViewError::Readback(e.to_string()))?
            .map_err(|e| ViewError::Readback(e.to_string()))?;
        let mut rgba = Vec::with_capacity((w * h * 4) as usize);
        let mut depth = Vec::with_capacity((w * h) as usize);
        {
            let data = slice
                .get_mapped_range()
                .map_err(|e| ViewError::Readback(format!("{e:?}")))?;
            let row = self.padded_row as usize;
            for y in 0..h as usize {
                rgba.extend_from_slice(&data[y * row..y * row + 4 * w as usize]);
                let d = &data[half as usize + y * row..half as usize + y * row + 4 * w as usize];
                depth.extend(
                    d.chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                );
            }
        }
        self.readback.unmap();
        Ok(Image {
            width: w,
            height: h,
            rgba,
            depth,
            projection,
        })
    }
}
