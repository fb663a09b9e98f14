//! The wgpu renderer: camera-relative, reversed-Z, horizon-fitted planes.
//!
//! Per block the CPU computes `centre − eye` in f64 and casts it to f32; the
//! vertex shader adds it to the block's f32 vertex offsets and applies the
//! rotation-only view and the projection. Depth is reversed (Depth32Float,
//! cleared to 0, compare `Greater`): depth 1 at the near plane, 0 at the far
//! plane (or at infinity with [`DepthMode::Infinite`]).
//!
//! The renderer draws exactly the blocks it is given (the caller culls). A
//! GPU mesh cache keyed by `(BlockId, mesh version)` uploads each mesh once
//! and evicts entries not drawn for [`RenderSettings::cache_frames`] frames;
//! textures are cached the same way.

use crate::clip_planes::{horizon_planes, ClipPlanes};
use crate::masks::{IndexRange, Masks};
use crate::mesh::{BlockMesh, Vertex};
use planet_core::lod::Rgb;
use planet_core::BlockId;
use std::collections::HashMap;
use std::num::NonZeroU64;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use wgpu::util::DeviceExt;

/// Colour target format.
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;
/// Depth buffer format.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// A perspective camera in planet-frame f64.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraF64 {
    /// Eye position, metres, planet frame.
    pub position: [f64; 3],
    /// View direction (need not be normalised).
    pub forward: [f64; 3],
    /// Approximate up direction.
    pub up: [f64; 3],
    /// Vertical field of view, radians.
    pub fov_y: f64,
}

impl CameraF64 {
    /// A camera at `eye` looking at `target`.
    pub fn look_at(eye: [f64; 3], target: [f64; 3], up: [f64; 3], fov_y: f64) -> CameraF64 {
        CameraF64 {
            position: eye,
            forward: [target[0] - eye[0], target[1] - eye[1], target[2] - eye[2]],
            up,
            fov_y,
        }
    }

    /// Orthonormal basis `(right, up, forward)`.
    pub fn basis(&self) -> [[f64; 3]; 3] {
        let f = unit(self.forward);
        let mut r = cross(f, self.up);
        if norm(r) < 1e-9 * norm(self.up).max(1e-300) {
            // Up parallel to forward: pick any perpendicular.
            let alt = if f[0].abs() < 0.9 {
                [1.0, 0.0, 0.0]
            } else {
                [0.0, 1.0, 0.0]
            };
            r = cross(f, alt);
        }
        let r = unit(r);
        let u = cross(r, f);
        [r, u, f]
    }

    /// Half the angle between opposite screen corners for this aspect ratio.
    pub fn half_diagonal_fov(&self, aspect: f64) -> f64 {
        let ty = (self.fov_y * 0.5).tan();
        (ty * (1.0 + aspect * aspect).sqrt()).atan()
    }

    /// Unit planet-frame direction of the ray through the centre of pixel
    /// `(px, py)` (row 0 at the top) of a `width × height` image.
    pub fn pixel_ray(&self, px: f64, py: f64, width: u32, height: u32) -> [f64; 3] {
        let [r, u, f] = self.basis();
        let (x, y) = ndc(px, py, width, height);
        let ty = (self.fov_y * 0.5).tan();
        let tx = ty * width as f64 / height as f64;
        unit([
            f[0] + x * tx * r[0] + y * ty * u[0],
            f[1] + x * tx * r[1] + y * ty * u[1],
            f[2] + x * tx * r[2] + y * ty * u[2],
        ])
    }
}

/// Normalised device coordinates of a pixel centre (y up).
pub fn ndc(px: f64, py: f64, width: u32, height: u32) -> (f64, f64) {
    (
        (px + 0.5) / width as f64 * 2.0 - 1.0,
        1.0 - (py + 0.5) / height as f64 * 2.0,
    )
}

/// How near and far planes are chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DepthMode {
    /// Thesis Eq. 4.3, see [`crate::clip_planes`].
    Horizon,
    /// The horizon-fitted near plane and a far plane at infinity.
    Infinite,
}

/// The projection of one frame: enough to turn depth back into distance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Projection {
    /// Near plane distance.
    pub near: f64,
    /// Far plane distance (`f64::INFINITY` for an infinite projection).
    pub far: f64,
    /// Vertical field of view (radians).
    pub fov_y: f64,
    /// Width / height.
    pub aspect: f64,
}

impl Projection {
    /// `(A, B)` with clip `z = A·z_view + B`, `w = −z_view`: reversed-Z,
    /// depth `B/dist − A`, 1 at near, 0 at far.
    fn z_coeffs(&self) -> (f64, f64) {
        if self.far.is_finite() {
            let a = self.near / (self.far - self.near);
            (a, a * self.far)
        } else {
            (0.0, self.near)
        }
    }

    /// The projection matrix (column-major), f64.
    pub fn matrix(&self) -> [[f64; 4]; 4] {
        let ty = 1.0 / (self.fov_y * 0.5).tan();
        let tx = ty / self.aspect;
        let (a, b) = self.z_coeffs();
        [
            [tx, 0.0, 0.0, 0.0],
            [0.0, ty, 0.0, 0.0],
            [0.0, 0.0, a, -1.0],
            [0.0, 0.0, b, 0.0],
        ]
    }

    /// Distance along the view axis of a depth-buffer value (None for the
    /// cleared background, depth 0).
    pub fn view_depth(&self, depth: f32) -> Option<f64> {
        if depth <= 0.0 {
            return None;
        }
        let (a, b) = self.z_coeffs();
        Some(b / (depth as f64 + a))
    }

    /// Distance in metres along the view ray through pixel `(px, py)` of a
    /// `width × height` image whose depth value is `depth`.
    pub fn ray_distance(
        &self,
        depth: f32,
        px: u32,
        py: u32,
        width: u32,
        height: u32,
    ) -> Option<f64> {
        let z = self.view_depth(depth)?;
        let (x, y) = ndc(px as f64, py as f64, width, height);
        let ty = (self.fov_y * 0.5).tan();
        let tx = ty * self.aspect;
        Some(z * (1.0 + (x * tx).powi(2) + (y * ty).powi(2)).sqrt())
    }
}

/// Renderer settings.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderSettings {
    /// Use the edge strips (false: every edge at level difference 0, which
    /// shows cracks; for tests and demonstrations).
    pub crack_fixing: bool,
    /// Near/far plane choice.
    pub depth_mode: DepthMode,
    /// Minimum planet radius (datum polar radius + minimum elevation).
    ///
    /// The far plane assumes nothing drawn lies below this radius. Coarse
    /// blocks' flat triangles dip below their vertices (chord sag, about
    /// `R·θ²/8` for a triangle spanning the angle `θ`: 4 km for a level-2
    /// block at LOD 1 with `W = 16`), so subtract the sag of the coarsest
    /// drawn blocks or distant coarse terrain may be cut at the horizon.
    pub r_min: f64,
    /// Maximum planet radius (datum equatorial radius + maximum elevation).
    pub r_max: f64,
    /// Direction towards the sun (planet frame).
    pub sun_dir: [f32; 3],
    /// Ambient light fraction.
    pub ambient: f32,
    /// Background colour (linear RGBA) of space; with an [`Atmosphere`],
    /// the sky's colour inside the air ([`Atmosphere::sky`]).
    pub clear: [f64; 4],
    /// The datum's semi-axes (equatorial, polar) in metres: the eye's
    /// altitude for the sky's colour.
    pub radii: [f64; 2],
    /// Aerial perspective ([`Atmosphere`]); `None`: none.
    pub atmosphere: Option<Atmosphere>,
    /// Evict cached GPU meshes and textures not drawn for this many frames.
    pub cache_frames: u64,
}

impl RenderSettings {
    /// Settings for a planet with `datum` and elevations in `[min, max]` m.
    pub fn for_planet(datum: &planet_core::Datum, min_elev: f64, max_elev: f64) -> RenderSettings {
        RenderSettings {
            crack_fixing: true,
            depth_mode: DepthMode::Horizon,
            r_min: datum.polar_radius() + min_elev,
            r_max: datum.equatorial_radius() + max_elev,
            radii: [datum.equatorial_radius(), datum.polar_radius()],
            sun_dir: [0.6, 0.5, 0.62],
            ambient: 0.25,
            clear: [0.0, 0.0, 0.02, 1.0],
            atmosphere: Some(Atmosphere::EARTH),
            cache_frames: 8,
        }
    }
}

/// Aerial perspective: terrain fades towards a sunlit sky colour with the
/// air between it and the eye. The optical depth is that of an exponential
/// atmosphere near the seen point, `ρ(h)·L / V` with `ρ(h) = exp(−h/H)`
/// and the path `L` the distance to the point, at most the air column
/// seen at the point's zenith angle (`H / cos z`): so the ground is hazy
/// near the horizon from anywhere, barely from orbit straight down, and
/// the planet's limb glows. Computed in the fragment shader (shader.wgsl),
/// finite at every distance and inside the planet (heights below 0 count
/// as 0, a zero distance as no haze).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Atmosphere {
    /// Scale height `H` in metres.
    pub scale_height: f32,
    /// Visibility `V` at sea level in metres (optical depth 1).
    pub visibility: f32,
}

impl Atmosphere {
    /// The Earth's: 8 km scale height, 120 km visibility at sea level (clear air).
    pub const EARTH: Atmosphere = Atmosphere {
        scale_height: 8_000.0,
        visibility: 120_000.0,
    };

    /// The sky's colour at full density: the colour the aerial
    /// perspective fades terrain to (shader.wgsl `aerial`), lit by the
    /// sun's height `sun_up` (cosine of its zenith angle, clamped to 0..1).
    pub fn sky_colour(sun_up: f64) -> [f64; 3] {
        let k = 0.2 + 0.8 * sun_up.clamp(0.0, 1.0);
        [0.50 * k, 0.66 * k, 0.90 * k]
    }

    /// The background seen from `eye` (planet frame, metres): `space`
    /// above the air, the sky's colour ([`Atmosphere::sky_colour`] at the
    /// sun's height there) within it, mixed by the air's density at the
    /// eye's altitude above the ellipsoid of semi-axes `radii` (equatorial,
    /// polar; `exp(−h/H)`, 1 at and below the surface). `sun` is a unit
    /// vector. Finite for every eye: at the centre, or not finite, `space`.
    pub fn sky(&self, eye: [f64; 3], sun: [f64; 3], radii: [f64; 2], space: [f64; 4]) -> [f64; 4] {
        let len = (eye[0] * eye[0] + eye[1] * eye[1] + eye[2] * eye[2]).sqrt();
        if !(len.is_finite() && len > 0.0) {
            return space;
        }
        let d = eye.map(|v| v / len);
        let (a, b) = (radii[0].max(1.0), radii[1].max(1.0));
        let r = 1.0 / ((d[0] * d[0] + d[1] * d[1]) / (a * a) + d[2] * d[2] / (b * b)).sqrt();
        let h = (len - r).max(0.0);
        let density = (-h / f64::from(self.scale_height.max(1.0))).exp();
        let sun_up = d[0] * sun[0] + d[1] * sun[1] + d[2] * sun[2];
        let sky = Self::sky_colour(if sun_up.is_finite() { sun_up } else { 0.0 });
        [
            space[0] + (sky[0] - space[0]) * density,
            space[1] + (sky[1] - space[1]) * density,
            space[2] + (sky[2] - space[2]) * density,
            space[3],
        ]
    }
}

static NEXT_TEXTURE_VERSION: AtomicU64 = AtomicU64::new(1);

/// A block's colour texture, with its LODs as mip levels (finest first).
#[derive(Debug, Clone)]
pub struct BlockTexture {
    /// The colour block.
    pub id: BlockId,
    /// Mip levels, finest first, each `side >> k` wide, RGB8 row-major (`j`
    /// along `v`). Levels below the streamed ones are box-filtered here
    /// ("virtual" LODs, thesis §4.4.3).
    pub levels: Vec<(usize, Vec<Rgb>)>,
    /// Unique per built texture (cache key).
    pub version: u64,
}

impl BlockTexture {
    /// From the filtered LOD 1 `(W/2)²` grid and, when loaded, the full LOD 0
    /// `W²` grid of a colour block of width `w`.
    pub fn new(id: BlockId, w: usize, full: Option<&[Rgb]>, lod1: &[Rgb]) -> BlockTexture {
        let mut levels = Vec::new();
        if let Some(full) = full {
            assert_eq!(full.len(), w * w);
            levels.push((w, full.to_vec()));
        }
        assert_eq!(lod1.len(), (w / 2) * (w / 2));
        levels.push((w / 2, lod1.to_vec()));
        while let Some((side, last)) = levels.last() {
            let side = *side;
            if side < 2 || side % 2 != 0 {
                break;
            }
            let next = planet_core::lod::colour_filter(last, side);
            levels.push((side / 2, next));
        }
        BlockTexture {
            id,
            levels,
            version: NEXT_TEXTURE_VERSION.fetch_add(1, Ordering::Relaxed),
        }
    }
}

/// A block's colour source: its own texture or an ancestor's, with the 2×3
/// texture transform (here scale + offset) from the block's `(i/W, j/W)`
/// coordinates to the texture's (thesis §4.4.3).
#[derive(Debug, Clone)]
pub struct ColourRef {
    /// The texture.
    pub texture: Arc<BlockTexture>,
    /// Scale of the transform.
    pub scale: [f32; 2],
    /// Offset of the transform.
    pub offset: [f32; 2],
}

impl ColourRef {
    /// The transform for drawing `block` with `texture`, which must belong to
    /// `block` or one of its ancestors.
    pub fn for_block(texture: Arc<BlockTexture>, block: BlockId) -> Option<ColourRef> {
        let t = texture.id;
        if !t.contains(&block) {
            return None;
        }
        let dl = block.level - t.level;
        let k = (1u64 << dl) as f64;
        let scale = 1.0 / k;
        let ox = (block.x as u64 - ((t.x as u64) << dl)) as f64 / k;
        let oy = (block.y as u64 - ((t.y as u64) << dl)) as f64 / k;
        Some(ColourRef {
            texture,
            scale: [scale as f32, scale as f32],
            offset: [ox as f32, oy as f32],
        })
    }
}

/// One block to draw this frame.
#[derive(Debug, Clone)]
pub struct DrawBlock {
    /// The block.
    pub id: BlockId,
    /// The selected LOD: 0 the full grid, 1 the first (step 2).
    pub lod: u8,
    /// Per edge (Left, Top, Right, Bottom): how many definition levels
    /// coarser the neighbour on that edge is (0: same or finer).
    pub neighbour_lod_diff: [u8; 4],
    /// The vertex data.
    pub mesh: Arc<BlockMesh>,
    /// Colour, or `None` to shade by altitude.
    pub colour: Option<ColourRef>,
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Globals {
    view_proj: [[f32; 4]; 4],
    sun: [f32; 4],
    params: [f32; 4],
    /// Eye position (planet frame, f32: only directions are taken from it).
    eye: [f32; 4],
    /// Atmosphere: scale height (m), visibility at sea level (m), on (1/0).
    atmos: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct BlockUniform {
    /// `centre − eye`, high part ([`crate::camera_relative::SplitOffset`]).
    offset: [f32; 4],
    /// `centre − eye`, low part.
    offset_lo: [f32; 4],
    tex: [f32; 4],
    flags: [f32; 4],
}

const BLOCK_UNIFORM_STRIDE: u64 = 256;

struct GpuMesh {
    vbuf: wgpu::Buffer,
    last_used: u64,
}

struct GpuTexture {
    bind_group: wgpu::BindGroup,
    last_used: u64,
}

struct GpuMasks {
    masks: Masks,
    ibuf: wgpu::Buffer,
}

/// Statistics of the last frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FrameStats {
    /// Blocks drawn.
    pub blocks: usize,
    /// Triangles drawn.
    pub triangles: u64,
    /// Meshes uploaded this frame.
    pub uploads: usize,
    /// Cached meshes after eviction.
    pub cached_meshes: usize,
}

/// Where a frame is drawn: colour ([`COLOR_FORMAT`]) and depth
/// ([`DEPTH_FORMAT`]) views of `width × height`.
#[derive(Debug, Clone, Copy)]
pub struct FrameTarget<'a> {
    /// Colour view.
    pub color: &'a wgpu::TextureView,
    /// Depth view.
    pub depth: &'a wgpu::TextureView,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

/// The device-side renderer, usable with any colour/depth target.
pub struct Renderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline: wgpu::RenderPipeline,
    globals_buf: wgpu::Buffer,
    globals_bg: wgpu::BindGroup,
    block_bgl: wgpu::BindGroupLayout,
    block_buf: wgpu::Buffer,
    block_bg: wgpu::BindGroup,
    block_capacity: u64,
    tex_bgl: wgpu::BindGroupLayout,
    sampler: wgpu::Sampler,
    dummy_tex: wgpu::BindGroup,
    masks: HashMap<usize, GpuMasks>,
    meshes: HashMap<(BlockId, u64), GpuMesh>,
    textures: HashMap<(BlockId, u64), GpuTexture>,
    frame: u64,
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
                    include_str!("shader.wgsl")
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

    fn block_buffer(
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

    fn upload_texture(
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

    /// The projection the next frame will use for `camera` on a target of
    /// aspect `aspect`.
    pub fn projection(&self, camera: &CameraF64, aspect: f64) -> Projection {
        let ClipPlanes { near, far } = horizon_planes(
            camera.position,
            camera.forward,
            self.settings.r_min,
            self.settings.r_max,
            camera.half_diagonal_fov(aspect),
        );
        Projection {
            near,
            far: match self.settings.depth_mode {
                DepthMode::Horizon => far,
                DepthMode::Infinite => f64::INFINITY,
            },
            fov_y: camera.fov_y,
            aspect,
        }
    }

    /// Record the frame into `encoder`: clear and draw `blocks` into the
    /// colour and depth views (`width × height`). Returns the projection.
    pub fn encode(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        target: FrameTarget<'_>,
        camera: &CameraF64,
        blocks: &[DrawBlock],
    ) -> Projection {
        let FrameTarget {
            color,
            depth,
            width,
            height,
        } = target;
        self.frame += 1;
        let frame = self.frame;
        let aspect = width as f64 / height.max(1) as f64;
        let proj = self.projection(camera, aspect);

        // View-projection without translation, composed in f64.
        let [r, u, f] = camera.basis();
        let view = [
            [r[0], u[0], -f[0], 0.0],
            [r[1], u[1], -f[1], 0.0],
            [r[2], u[2], -f[2], 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let vp = mat_mul(proj.matrix(), view);
        let sun = unit(self.settings.sun_dir.map(|v| v as f64));
        let globals = Globals {
            view_proj: vp.map(|c| c.map(|v| v as f32)),
            sun: [sun[0] as f32, sun[1] as f32, sun[2] as f32, 0.0],
            params: [self.settings.ambient, 0.0, 0.0, 0.0],
            eye: [
                camera.position[0] as f32,
                camera.position[1] as f32,
                camera.position[2] as f32,
                0.0,
            ],
            atmos: match self.settings.atmosphere {
                Some(a) => [a.scale_height.max(1.0), a.visibility.max(1.0), 1.0, 0.0],
                None => [1.0, 1.0, 0.0, 0.0],
            },
        };
        self.queue
            .write_buffer(&self.globals_buf, 0, bytemuck::bytes_of(&globals));

        // Uploads (meshes, masks, textures) and per-block uniforms.
        let mut uploads = 0;
        if blocks.len() as u64 > self.block_capacity {
            self.block_capacity = (blocks.len() as u64).next_power_of_two();
            let (b, g) = Self::block_buffer(&self.device, &self.block_bgl, self.block_capacity);
            self.block_buf = b;
            self.block_bg = g;
        }
        let mut uniforms = vec![0u8; blocks.len() * BLOCK_UNIFORM_STRIDE as usize];
        for (k, b) in blocks.iter().enumerate() {
            let m = &b.mesh;
            let key = (m.id, m.version);
            if let Some(g) = self.meshes.get_mut(&key) {
                g.last_used = frame;
            } else {
                let vbuf = self
                    .device
                    .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some("block vertices"),
                        contents: bytemuck::cast_slice(&m.vertices),
                        usage: wgpu::BufferUsages::VERTEX,
                    });
                self.meshes.insert(
                    key,
                    GpuMesh {
                        vbuf,
                        last_used: frame,
                    },
                );
                uploads += 1;
            }
            if !self.masks.contains_key(&m.w) {
                let masks = Masks::new(m.w);
                let ibuf = self
                    .device
                    .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                        label: Some("masks"),
                        contents: bytemuck::cast_slice(&masks.indices),
                        usage: wgpu::BufferUsages::INDEX,
                    });
                self.masks.insert(m.w, GpuMasks { masks, ibuf });
            }
            let mut tex = [1.0f32, 1.0, 0.0, 0.0];
            let mut has_tex = 0.0;
            let mut coarse = 0.0f32;
            if let Some(c) = &b.colour {
                let tkey = (c.texture.id, c.texture.version);
                if let Some(t) = self.textures.get_mut(&tkey) {
                    t.last_used = frame;
                } else {
                    let bind_group = Self::upload_texture(
                        &self.device,
                        &self.queue,
                        &self.tex_bgl,
                        &self.sampler,
                        &c.texture,
                    );
                    self.textures.insert(
                        tkey,
                        GpuTexture {
                            bind_group,
                            last_used: frame,
                        },
                    );
                }
                tex = [c.scale[0], c.scale[1], c.offset[0], c.offset[1]];
                has_tex = 1.0;
                // How many octaves the texture is coarser than the mesh:
                // mesh samples per texel across the block.
                let texels = c.texture.levels.first().map_or(1, |l| l.0) as f32 * c.scale[0];
                coarse = (m.w as f32 / texels.max(1e-6)).log2().max(0.0);
            }
            let rel = [
                m.centre[0] - camera.position[0],
                m.centre[1] - camera.position[1],
                m.centre[2] - camera.position[2],
            ];
            let off = crate::camera_relative::SplitOffset::new(rel);
            let bu = BlockUniform {
                offset: [off.hi[0], off.hi[1], off.hi[2], 0.0],
                offset_lo: [off.lo[0], off.lo[1], off.lo[2], 0.0],
                tex,
                flags: [has_tex, coarse, 0.0, 0.0],
            };
            let o = k * BLOCK_UNIFORM_STRIDE as usize;
            uniforms[o..o + std::mem::size_of::<BlockUniform>()]
                .copy_from_slice(bytemuck::bytes_of(&bu));
        }
        if !uniforms.is_empty() {
            self.queue.write_buffer(&self.block_buf, 0, &uniforms);
        }

        let c = match self.settings.atmosphere {
            Some(a) => a.sky(
                camera.position,
                sun,
                self.settings.radii,
                self.settings.clear,
            ),
            None => self.settings.clear,
        };
        let mut triangles = 0u64;
        {
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("planet pass"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: color,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color {
                            r: c[0],
                            g: c[1],
                            b: c[2],
                            a: c[3],
                        }),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: depth,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(0.0),
                        store: wgpu::StoreOp::Store,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &self.globals_bg, &[]);
            for (k, b) in blocks.iter().enumerate() {
                let m = &b.mesh;
                let gm = &self.meshes[&(m.id, m.version)];
                let gmask = &self.masks[&m.w];
                let tbg = match &b.colour {
                    Some(c) => &self.textures[&(c.texture.id, c.texture.version)].bind_group,
                    None => &self.dummy_tex,
                };
                pass.set_bind_group(
                    1,
                    &self.block_bg,
                    &[(k as u64 * BLOCK_UNIFORM_STRIDE) as u32],
                );
                pass.set_bind_group(2, tbg, &[]);
                pass.set_vertex_buffer(0, gm.vbuf.slice(..));
                pass.set_index_buffer(gmask.ibuf.slice(..), wgpu::IndexFormat::Uint32);
                let ranges: [IndexRange; 5] =
                    gmask
                        .masks
                        .ranges(b.lod, b.neighbour_lod_diff, self.settings.crack_fixing);
                for r in ranges {
                    if r.count > 0 {
                        pass.draw_indexed(r.range(), 0, 0..1);
                        triangles += r.count as u64 / 3;
                    }
                }
            }
        }

        // Evict what was not drawn recently.
        let keep = self.settings.cache_frames;
        self.meshes.retain(|_, g| frame - g.last_used <= keep);
        self.textures.retain(|_, t| frame - t.last_used <= keep);
        self.stats = FrameStats {
            blocks: blocks.len(),
            triangles,
            uploads,
            cached_meshes: self.meshes.len(),
        };
        proj
    }
}

fn mat_mul(a: [[f64; 4]; 4], b: [[f64; 4]; 4]) -> [[f64; 4]; 4] {
    // Column-major: (a·b)[col][row] = Σ_k a[k][row]·b[col][k].
    let mut out = [[0.0; 4]; 4];
    for col in 0..4 {
        for row in 0..4 {
            out[col][row] = (0..4).map(|k| a[k][row] * b[col][k]).sum();
        }
    }
    out
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    let l = norm(v);
    if l > 0.0 {
        [v[0] / l, v[1] / l, v[2] / l]
    } else {
        [0.0, 0.0, -1.0]
    }
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The background is the sky's colour at and under the surface (at the
    /// poles on the polar radius, at the equator on the equatorial one),
    /// fades with altitude, is space from 1000 Earth radii, and is finite
    /// for every eye (the centre, non-finite positions).
    #[test]
    fn sky_fades_from_the_ground_to_space() {
        let a = Atmosphere::EARTH;
        let radii = [6_378_137.0, 6_356_752.3];
        let space = [0.0, 0.0, 0.02, 1.0];
        let sun = [1.0, 0.0, 0.0];
        let sky = Atmosphere::sky_colour(1.0);
        let at = |p: [f64; 3]| a.sky(p, sun, radii, space);
        let close = |c: [f64; 4], e: [f64; 3]| (0..3).all(|k| (c[k] - e[k]).abs() < 1e-3);
        // Equator, sun overhead, 1 m up and inside the planet.
        assert!(close(at([radii[0] + 1.0, 0.0, 0.0]), sky));
        assert!(close(at([1000.0, 0.0, 0.0]), sky));
        // North pole: altitude above the polar radius (the equatorial one
        // would put an eye 20 km up still 1.4 km under the ground, in full
        // sky).
        let pole = at([0.0, 0.0, radii[1] + 10.0]);
        assert!(close(pole, Atmosphere::sky_colour(0.0)), "{pole:?}");
        let high = at([0.0, 0.0, radii[1] + 20_000.0]);
        assert!(high[2] < 0.5 * Atmosphere::sky_colour(0.0)[2], "{high:?}");
        // Monotone with altitude, space far out.
        let mut last = f64::INFINITY;
        for h in [0.0, 1e3, 1e4, 1e5, 1e6, 6.4e9] {
            let c = at([radii[0] + h, 0.0, 0.0]);
            assert!(c.iter().all(|v| v.is_finite()));
            assert!(c[2] <= last + 1e-12, "not monotone at {h}");
            last = c[2];
        }
        assert!(close(at([6.4e9, 0.0, 0.0]), [space[0], space[1], space[2]]));
        assert_eq!(at([0.0, 0.0, 0.0]), space);
        assert_eq!(at([f64::NAN, 0.0, 0.0]), space);
        assert_eq!(at([f64::INFINITY, 0.0, 0.0]), space);
    }

    #[test]
    fn projection_round_trips_depth() {
        for far in [1000.0, f64::INFINITY] {
            let p = Projection {
                near: 0.5,
                far,
                fov_y: 1.0,
                aspect: 1.5,
            };
            let m = p.matrix();
            for dist in [0.5, 1.0, 10.0, 999.0] {
                // View-space point on the axis at z = −dist.
                let zc = m[2][2] * -dist + m[3][2];
                let wc = dist;
                let depth = (zc / wc) as f32;
                assert!((0.0..=1.0).contains(&depth));
                let back = p.view_depth(depth).unwrap();
                assert!((back - dist).abs() < 1e-4 * dist, "{far} {dist} {back}");
            }
        }
    }

    #[test]
    fn colour_ref_transform() {
        let face = planet_core::Face::new(2).unwrap();
        let anc = BlockId::new(face, 1, 1, 0).unwrap();
        let t = Arc::new(BlockTexture::new(anc, 4, None, &[[1, 2, 3]; 4]));
        assert_eq!(t.levels.iter().map(|l| l.0).collect::<Vec<_>>(), vec![2, 1]);
        let b = BlockId::new(face, 3, 5, 2).unwrap();
        let c = ColourRef::for_block(t.clone(), b).unwrap();
        assert_eq!(c.scale, [0.25, 0.25]);
        assert_eq!(c.offset, [0.25, 0.5]);
        assert!(ColourRef::for_block(t, BlockId::new(face, 3, 0, 0).unwrap()).is_none());
    }

    #[test]
    fn pixel_rays_match_the_basis() {
        let cam = CameraF64::look_at([0.0, 0.0, 10.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 1.0);
        let r = cam.pixel_ray(49.5, 49.5, 100, 100);
        assert!((r[2] + 1.0).abs() < 1e-12);
        let top = cam.pixel_ray(49.5, 0.0, 100, 100);
        assert!(top[1] > 0.0);
        let right = cam.pixel_ray(99.0, 49.5, 100, 100);
        // right = forward × up = (0,0,-1)×(0,1,0) = (1,0,0)
        assert!(right[0] > 0.0);
    }
}
