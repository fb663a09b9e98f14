//! One frame: the projection, the per-block uniforms, the draw calls and
//! the cache eviction.

use super::*;
use crate::masks::{IndexRange, Masks};
use glam::DVec3;
use planet_core::horizon::ClipPlanes;
use wgpu::util::DeviceExt;

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

impl Renderer {
    /// The projection the next frame will use for `camera` on a target of
    /// aspect `aspect`.
    pub fn projection(&self, camera: &Camera, aspect: f64) -> Projection {
        let ClipPlanes { near, far } =
            Camera { aspect, ..*camera }.clip_planes(self.settings.r_min, self.settings.r_max);
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
        camera: &Camera,
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
        let Basis {
            right: r,
            up: u,
            forward: f,
        } = camera.basis();
        let view = [
            [r[0], u[0], -f[0], 0.0],
            [r[1], u[1], -f[1], 0.0],
            [r[2], u[2], -f[2], 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let vp = mat_mul(proj.matrix(), view);
        let sun = DVec3::from(self.settings.sun_dir.map(f64::from))
            .try_normalize()
            .unwrap_or(DVec3::NEG_Z);
        let globals = Globals {
            view_proj: vp.map(|c| c.map(|v| v as f32)),
            sun: sun.as_vec3().extend(0.0).to_array(),
            params: [self.settings.ambient, 0.0, 0.0, 0.0],
            eye: camera.eye.as_vec3().extend(0.0).to_array(),
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
            let rel = DVec3::from(m.centre) - camera.eye;
            let off = crate::camera_relative::SplitOffset::new(rel.to_array());
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
                camera.eye.to_array(),
                sun.to_array(),
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
