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

mod blocks;
mod camera;
mod frame;
mod pipeline;
mod settings;

pub use blocks::*;
pub use camera::*;
pub use frame::*;
pub use pipeline::*;
pub use settings::*;

/// Colour target format.
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;
/// Depth buffer format.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

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

#[cfg(test)]
mod tests {
    use super::*;
    use planet_core::BlockId;
    use std::sync::Arc;

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
        let cam = Camera::look_at(
            glam::DVec3::new(0.0, 0.0, 10.0),
            glam::DVec3::ZERO,
            glam::DVec3::Y,
        );
        let r = cam.pixel_ray(49.5, 49.5, 100, 100);
        assert!((r[2] + 1.0).abs() < 1e-12);
        let top = cam.pixel_ray(49.5, 0.0, 100, 100);
        assert!(top[1] > 0.0);
        let right = cam.pixel_ray(99.0, 49.5, 100, 100);
        // right = forward × up = (0,0,-1)×(0,1,0) = (1,0,0)
        assert!(right[0] > 0.0);
    }
}
