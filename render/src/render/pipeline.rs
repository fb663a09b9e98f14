//! The device-side resources: the pipeline, bind groups, the per-block
//! uniform buffer and the GPU caches of meshes, masks and textures.

use super::*;
use crate::masks::Masks;
use crate::mesh::Vertex;
use planet_core::BlockId;
use std::collections::HashMap;
use std::num::NonZeroU64;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct Globals {
    pub(super) view_proj: [[f32; 4]; 4],
    pub(super) sun: [f32; 4],
    pub(super) params: [f32; 4],
    /// Eye position (planet frame, f32: only directions are taken from it).
    pub(super) eye: [f32; 4],
    /// Atmosphere: scale height (m), visibility at sea level (m), on (1/0).
    pub(super) atmos: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct BlockUniform {
    /// `centre − eye`, high part ([`crate::camera_relative::SplitOffset`]).
    pub(super) offset: [f32; 4],
    /// `centre − eye`, low part.
    pub(super) offset_lo: [f32; 4],
    pub(super) tex: [f32; 4],
    pub(super) flags: [f32; 4],
}

pub(super) const BLOCK_UNIFORM_STRIDE: u64 = 256;

pub(super) struct GpuMesh {
    pub(super) vbuf: wgpu::Buffer,
    pub(super) last_used: u64,
}

pub(super) struct GpuTexture {
    pub(super) bind_group: wgpu::BindGroup,
    pub(super) last_used: u64,
}

pub(super) struct GpuMasks {
    pub(super) masks: Masks,
    pub(super) ibuf: wgpu::Buffer,
}

/// The device-side renderer, usable with any colour/depth target.
pub struct Renderer {
    pub(super) device: wgpu::Device,
    pub(super) queue: wgpu::Queue,
    pub(super) pipeline: wgpu::RenderPipeline,
    pub(super) globals_buf: wgpu::Buffer,
    pub(super) globals_bg: wgpu::BindGroup,
    pub(super) block_bgl: wgpu::BindGroupLayout,
    pub(super) block_buf: wgpu::Buffer,
    pub(super) block_bg: wgpu::BindGroup,
    pub(super) block_capacity: u64,
    pub(super) tex_bgl: wgpu::BindGroupLayout,
    pub(super) sampler: wgpu::Sampler,
    pub(super) dummy_tex: wgpu::BindGroup,
    pub(super) masks: HashMap<usize, GpuMasks>,
    pub(super) meshes: HashMap<(BlockId, u64), GpuMesh>,
    pub(super) textures: HashMap<(BlockId, u64), GpuTexture>,
    pub(super) frame: u64,
    /// Settings used by the next frame.
    pub settings: RenderSettings,
    /// Statistics of the last frame.
    pub stats: FrameStats,
}

impl Renderer {
    /// Create the pipeline on `device` for [`COLOR_FORMAT`] and
    /// [`DEPTH_FORMAT`] targets.
    pub fn new(device: wgpu::Device, queue: wgpu::Queue, settings: RenderSettings) -> Renderer {
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("planet shader"),
            source: wgpu::ShaderSource::Wgsl(
                format!(
                    "{}\n{}",
                    crate::camera_relative::WGSL,
                    include_str!("../shader.wgsl")
                )
                .into(),
            ),
        });
        let uniform_entry = |dynamic: bool, size: u64| wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: dynamic,
                min_binding_size: NonZeroU64::new(size),
            },
            count: None,
        };
        let globals_bgl = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("globals"),
            entries: &[uniform_entry(false, std::mem::size_of::<Globals>() as u64)],
        });
        let block_bgl = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("block"),
            entries: &[uniform_entry(
                true,
                std::mem::size_of::<BlockUniform>() as u64,
            )],
        });
        let tex_bgl = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("texture"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: true },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("planet layout"),
            bind_group_layouts: &[Some(&globals_bgl), Some(&block_bgl), Some(&tex_bgl)],
            immediate_size: 0,
        });
        let attrs = wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x2, 3 => Float32, 4 => Float16x4];
        let pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("planet pipeline"),
            layout: Some(&layout),
            vertex: wgpu::VertexState {
                module: &shader,
                entry_point: Some("vs"),
                compilation_options: Default::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: std::mem::size_of::<Vertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &attrs,
                })],
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                front_face: wgpu::FrontFace::Ccw,
                cull_mode: Some(wgpu::Face::Back),
                ..Default::default()
            },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: DEPTH_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Greater),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module: &shader,
                entry_point: Some("fs"),
                compilation_options: Default::default(),
                targets: &[Some(wgpu::ColorTargetState {
                    format: COLOR_FORMAT,
                    blend: None,
                    write_mask: wgpu::ColorWrites::ALL,
                })],
            }),
            multiview_mask: None,
            cache: None,
        });
        let globals_buf = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("globals"),
            size: std::mem::size_of::<Globals>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let globals_bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("globals"),
            layout: &globals_bgl,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: globals_buf.as_entire_binding(),
            }],
        });
        let block_capacity = 64;
        let (block_buf, block_bg) = Self::block_buffer(&device, &block_bgl, block_capacity);
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("colour"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Linear,
            ..Default::default()
        });
        let dummy = BlockTexture {
            id: BlockId::root(planet_core::Face::NORTH),
            levels: vec![(1, vec![[255, 0, 255]])],
            version: 0,
        };
        let dummy_tex = Self::upload_texture(&device, &queue, &tex_bgl, &sampler, &dummy);
        Renderer {
            device,
            queue,
            pipeline,
            globals_buf,
            globals_bg,
            block_bgl,
            block_buf,
            block_bg,
            block_capacity,
            tex_bgl,
            sampler,
            dummy_tex,
            masks: HashMap::new(),
            meshes: HashMap::new(),
            textures: HashMap::new(),
            frame: 0,
            settings,
            stats: FrameStats::default(),
        }
    }

    /// The device.
    pub fn device(&self) -> &wgpu::Device {
        &self.device
    }

    /// The queue.
    pub fn queue(&self) -> &wgpu::Queue {
        &self.queue
    }

    pub(super) fn block_buffer(
        device: &wgpu::Device,
        bgl: &wgpu::BindGroupLayout,
        capacity: u64,
    ) -> (wgpu::Buffer, wgpu::BindGroup) {
        let buf = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("block uniforms"),
            size: capacity * BLOCK_UNIFORM_STRIDE,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("block uniforms"),
            layout: bgl,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &buf,
                    offset: 0,
                    size: NonZeroU64::new(std::mem::size_of::<BlockUniform>() as u64),
                }),
            }],
        });
        (buf, bg)
    }

    pub(super) fn upload_texture(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        bgl: &wgpu::BindGroupLayout,
        sampler: &wgpu::Sampler,
        t: &BlockTexture,
    ) -> wgpu::BindGroup {
        let side = t.levels[0].0 as u32;
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("block colour"),
            size: wgpu::Extent3d {
                width: side,
                height: side,
                depth_or_array_layers: 1,
            },
            mip_level_count: t.levels.len() as u32,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8UnormSrgb,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        for (level, (s, data)) in t.levels.iter().enumerate() {
            let rgba: Vec<u8> = data.iter().flat_map(|c| [c[0], c[1], c[2], 255]).collect();
            queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &texture,
                    mip_level: level as u32,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                &rgba,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * *s as u32),
                    rows_per_image: Some(*s as u32),
                },
                wgpu::Extent3d {
                    width: *s as u32,
                    height: *s as u32,
                    depth_or_array_layers: 1,
                },
            );
        }
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("block colour"),
            layout: bgl,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&view),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Sampler(sampler),
                },
            ],
        })
    }
}
