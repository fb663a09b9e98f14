//! GPU plumbing of the window: the surface, the offscreen planet target,
//! the readout texture and the full-screen pass that composes them
//! (`blit.wgsl`); texture read-back and PNG screenshots.

use crate::app::hud;
use anyhow::{Context, Result};
use planet_render::render::{COLOR_FORMAT, DEPTH_FORMAT};
use planet_render::{RenderSettings, Renderer};
use std::sync::Arc;
use winit::dpi::PhysicalSize;
use winit::event_loop::ActiveEventLoop;
use winit::window::Window;

pub(super) struct Gfx {
    pub(super) window: Arc<Window>,
    pub(super) surface: wgpu::Surface<'static>,
    pub(super) config: wgpu::SurfaceConfiguration,
    pub(super) renderer: Renderer,
    pub(super) color: wgpu::Texture,
    pub(super) depth: wgpu::Texture,
    pub(super) hud_tex: wgpu::Texture,
    pub(super) hud_size: (u32, u32),
    pub(super) bind_group: wgpu::BindGroup,
    pub(super) bgl: wgpu::BindGroupLayout,
    pub(super) pipeline: wgpu::RenderPipeline,
    pub(super) copy_src: bool,
    pub(super) adapter_name: String,
    /// The adapter renders on the CPU (lavapipe, llvmpipe).
    pub(super) cpu_adapter: bool,
}

const BLIT_WGSL: &str = include_str!("blit.wgsl");

impl Gfx {
    pub(super) fn new(event_loop: &ActiveEventLoop, width: u32, height: u32) -> Result<Gfx> {
        let attrs = Window::default_attributes()
            .with_title("planet-view")
            .with_inner_size(PhysicalSize::new(width, height));
        let window = Arc::new(
            event_loop
                .create_window(attrs)
                .context("creating the window")?,
        );
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_with_display_handle_from_env(
                Box::new(event_loop.owned_display_handle()),
            ));
        let surface = instance
            .create_surface(window.clone())
            .context("creating the surface")?;
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: Some(&surface),
            apply_limit_buckets: false,
        }))
        .context("no graphics adapter for the window (install mesa-vulkan-drivers)")?;
        let info = adapter.get_info();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("planet-view window"),
            required_features: wgpu::Features::empty(),
            required_limits: wgpu::Limits::downlevel_defaults().using_resolution(adapter.limits()),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .context("requesting the device")?;
        let size = window.inner_size();
        let (w, h) = (size.width.max(1), size.height.max(1));
        let caps = surface.get_capabilities(&adapter);
        let mut config = surface
            .get_default_config(&adapter, w, h)
            .context("the surface is not supported by the adapter")?;
        if let Some(f) = caps.formats.iter().find(|f| f.is_srgb()) {
            config.format = *f;
        }
        let copy_src = caps.usages.contains(wgpu::TextureUsages::COPY_SRC)
            && matches!(
                config.format.remove_srgb_suffix(),
                wgpu::TextureFormat::Bgra8Unorm | wgpu::TextureFormat::Rgba8Unorm
            );
        if copy_src {
            config.usage |= wgpu::TextureUsages::COPY_SRC;
        }
        config.present_mode = if caps.present_modes.contains(&wgpu::PresentMode::Fifo) {
            wgpu::PresentMode::Fifo
        } else {
            caps.present_modes[0]
        };
        surface.configure(&device, &config);
        let shader_src = BLIT_WGSL.replace(
            "ENCODE",
            if config.format.is_srgb() {
                "false"
            } else {
                "true"
            },
        );
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("blit"),
            source: wgpu::ShaderSource::Wgsl(shader_src.into()),
        });
        let tex_entry = |binding| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::FRAGMENT,
            ty: wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: false },
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false,
            },
            count: None,
        };
        let bgl = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("blit"),
            entries: &[tex_entry(0), tex_entry(1)],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("blit"),
            bind_group_layouts: &[Some(&bgl)],
            immediate_size: 0,
        });
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("blit"),
            layout: Some(&layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs"),
                compilation_options: Default::default(),
                buffers: &[],
            },
            primitive: wgpu::PrimitiveState::default(),
            depth_stencil: None,
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: config.format,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let renderer = Renderer::new(
            device,
            queue,
            RenderSettings::for_planet(&planet_core::Datum::WGS84, -11_000.0, 9_000.0),
        );
        let (color, depth) = Self::targets(renderer.device(), w, h);
        let hud_tex = Self::hud_texture(renderer.device(), 1, 1);
        let bind_group = Self::bind(renderer.device(), &bgl, &color, &hud_tex);
        Ok(Gfx {
            window,
            surface,
            config,
            renderer,
            color,
            depth,
            hud_tex,
            hud_size: (1, 1),
            bind_group,
            bgl,
            pipeline,
            copy_src,
            adapter_name: format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type),
            cpu_adapter: info.device_type == wgpu::DeviceType::Cpu,
        })
    }

    pub(super) fn targets(device: &wgpu::Device, w: u32, h: u32) -> (wgpu::Texture, wgpu::Texture) {
        let size = wgpu::Extent3d {
            width: w,
            height: h,
            depth_or_array_layers: 1,
        };
        let make = |format, usage, label| {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size,
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage,
                view_formats: &[],
            })
        };
        (
            make(
                COLOR_FORMAT,
                wgpu::TextureUsages::RENDER_ATTACHMENT
                    | wgpu::TextureUsages::TEXTURE_BINDING
                    | wgpu::TextureUsages::COPY_SRC,
                "scene colour",
            ),
            make(
                DEPTH_FORMAT,
                wgpu::TextureUsages::RENDER_ATTACHMENT,
                "scene depth",
            ),
        )
    }

    pub(super) fn hud_texture(device: &wgpu::Device, w: u32, h: u32) -> wgpu::Texture {
        device.create_texture(&wgpu::TextureDescriptor {
            label: Some("hud"),
            size: wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8UnormSrgb,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        })
    }

    pub(super) fn bind(
        device: &wgpu::Device,
        bgl: &wgpu::BindGroupLayout,
        color: &wgpu::Texture,
        hud: &wgpu::Texture,
    ) -> wgpu::BindGroup {
        let cv = color.create_view(&Default::default());
        let hv = hud.create_view(&Default::default());
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("blit"),
            layout: bgl,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&cv),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&hv),
                },
            ],
        })
    }

    pub(super) fn resize(&mut self, w: u32, h: u32) {
        let (w, h) = (w.max(1), h.max(1));
        if (w, h) == (self.config.width, self.config.height) {
            return;
        }
        self.config.width = w;
        self.config.height = h;
        self.surface.configure(self.renderer.device(), &self.config);
        let (c, d) = Self::targets(self.renderer.device(), w, h);
        self.color = c;
        self.depth = d;
        self.bind_group = Self::bind(
            self.renderer.device(),
            &self.bgl,
            &self.color,
            &self.hud_tex,
        );
    }

    pub(super) fn set_hud(&mut self, panel: Option<&hud::Panel>) {
        let (w, h, data) = match panel {
            Some(p) => (p.width, p.height, p.rgba.clone()),
            None => (1, 1, vec![0, 0, 0, 0]),
        };
        if (w, h) != self.hud_size {
            self.hud_tex = Self::hud_texture(self.renderer.device(), w, h);
            self.hud_size = (w, h);
            self.bind_group = Self::bind(
                self.renderer.device(),
                &self.bgl,
                &self.color,
                &self.hud_tex,
            );
        }
        self.renderer.queue().write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &self.hud_tex,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            &data,
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(4 * w),
                rows_per_image: Some(h),
            },
            wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
        );
    }
}

/// Copy a texture (RGBA8 or BGRA8, `w × h`) to RGBA8 bytes.
pub(super) fn read_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
    bgra: bool,
) -> Result<(u32, u32, Vec<u8>)> {
    let (w, h) = (texture.width(), texture.height());
    let row =
        (w * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buf = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("screenshot"),
        size: row as u64 * h as u64,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut enc = device.create_command_encoder(&Default::default());
    enc.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::TexelCopyBufferInfo {
            buffer: &buf,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(h),
            },
        },
        wgpu::Extent3d {
            width: w,
            height: h,
            depth_or_array_layers: 1,
        },
    );
    queue.submit([enc.finish()]);
    let slice = buf.slice(..);
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| anyhow::anyhow!("poll: {e}"))?;
    rx.recv()?.map_err(|e| anyhow::anyhow!("map: {e}"))?;
    let data = slice
        .get_mapped_range()
        .map_err(|e| anyhow::anyhow!("mapped range: {e:?}"))?;
    let mut out = Vec::with_capacity((w * h * 4) as usize);
    for y in 0..h as usize {
        let r = &data[y * row as usize..y * row as usize + 4 * w as usize];
        if bgra {
            for px in r.chunks_exact(4) {
                out.extend_from_slice(&[px[2], px[1], px[0], 255]);
            }
        } else {
            for px in r.chunks_exact(4) {
                out.extend_from_slice(&[px[0], px[1], px[2], 255]);
            }
        }
    }
    drop(data);
    buf.unmap();
    Ok((w, h, out))
}

pub(super) fn save_png(path: &std::path::Path, w: u32, h: u32, rgba: &[u8]) -> Result<()> {
    let file = std::fs::File::create(path).with_context(|| format!("{}", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let mut wr = enc.write_header()?;
    wr.write_image_data(rgba)?;
    wr.finish()?;
    Ok(())
}
