//! `planet-render`: the wgpu renderer of the planet-streaming system (the
//! `planet-view` binary draws with it).
//!
//! The streaming client decides *what* to draw; this crate draws a list of
//! [`DrawBlock`]s:
//!
//! - [`mesh`]: a block's vertices, built off the render thread from its
//!   elevation grid, as f32 + f16 offsets from an f64 block centre.
//! - [`camera_relative`]: the double-single `centre − eye + pos` that keeps
//!   camera-relative vertices to one f32 rounding.
//! - [`masks`]: the shared index masks per LOD, with the edge strips that
//!   stitch a block to a coarser neighbour (no cracks, no T-junctions).
//! - [`render`]: the wgpu 30 pipeline: camera-relative, reversed-Z with the
//!   horizon-fitted planes of [`planet_core::horizon`] (thesis Eq. 4.3) for
//!   the core [`Camera`], lighting,
//!   per-block colour textures (or an altitude ramp), GPU caches.
//! - [`headless`]: offscreen rendering with colour and depth read-back.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod camera_relative;
pub mod headless;
pub mod masks;
pub mod mesh;
pub mod render;

pub use headless::{FrameTiming, HeadlessRenderer, Image, ViewError};
pub use mesh::BlockMesh;
pub use render::{
    BlockTexture, Camera, ColourRef, DepthMode, DrawBlock, FrameTarget, Projection, RenderSettings,
    Renderer,
};
