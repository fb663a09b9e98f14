//! The perspective camera, in planet-centred metres and `f64`: the one camera
//! type of the workspace. The client's visibility and importance (thesis
//! §4.2.1 frustum culling, §4.5.4 horizon planes) and the renderer (§4.5,
//! camera-relative rendering) take it; see `docs/REFERENCES.md`.
//!
//! Conventions: the planet frame is right-handed with its origin at the
//! planet centre; `forward` is the view direction, `up` an approximate up
//! that [`Camera::basis`] re-orthogonalises. The basis is returned as a named
//! [`Basis`], never as a tuple, so that callers cannot mix up the axes.

use glam::DVec3;

/// A perspective camera in planet-centred metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Eye position, planet-centred, metres.
    pub eye: DVec3,
    /// View direction (need not be normalised).
    pub forward: DVec3,
    /// Approximate up vector (re-orthogonalised against `forward`).
    pub up: DVec3,
    /// Vertical field of view in radians.
    pub fov_y: f64,
    /// Width / height of the viewport.
    pub aspect: f64,
    /// Viewport height in pixels (for screen-space errors).
    pub viewport_height_px: f64,
}

/// An orthonormal, right-handed camera basis: `right × up = −forward`
/// (the camera looks down its −z axis, as in OpenGL and wgpu view space).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Basis {
    /// Unit view direction.
    pub forward: DVec3,
    /// Unit right vector (screen +x).
    pub right: DVec3,
    /// Unit up vector (screen +y).
    pub up: DVec3,
}

impl Camera {
    /// A camera at `eye` looking at `target`, with `up` as the approximate
    /// up: 60° vertical field of view, 16:9, 1080 pixels high.
    pub fn look_at(eye: DVec3, target: DVec3, up: DVec3) -> Camera {
        Camera {
            eye,
            forward: target - eye,
            up,
            fov_y: 60f64.to_radians(),
            aspect: 16.0 / 9.0,
            viewport_height_px: 1080.0,
        }
    }

    /// This camera with another viewport (`width × height` pixels).
    pub fn with_viewport(mut self, width: u32, height: u32) -> Camera {
        let h = height.max(1) as f64;
        self.aspect = width.max(1) as f64 / h;
        self.viewport_height_px = h;
        self
    }

    /// The orthonormal basis. A degenerate `forward` (zero or not finite)
    /// falls back to −z; an `up` parallel to `forward` (within a relative
    /// 1e-6) to any perpendicular axis.
    pub fn basis(&self) -> Basis {
        let f = self
            .forward
            .try_normalize()
            .filter(|f| f.is_finite())
            .unwrap_or(DVec3::NEG_Z);
        let mut r = f.cross(self.up);
        let scale = self.up.length();
        let usable = r.is_finite() && scale.is_finite() && r.length() >= 1e-6 * scale.max(1e-300);
        if !usable {
            let alt = if f.x.abs() < 0.9 { DVec3::X } else { DVec3::Y };
            r = f.cross(alt);
        }
        // One Gram–Schmidt step: a nearly parallel `up` leaves rounding
        // along `f` that normalising would magnify.
        let r = (r - f * f.dot(r)).normalize();
        Basis {
            forward: f,
            right: r,
            up: r.cross(f),
        }
    }

    /// Half the angle between opposite screen corners.
    pub fn half_diagonal_fov(&self) -> f64 {
        let ty = (self.fov_y * 0.5).tan().abs();
        (ty * (1.0 + self.aspect * self.aspect).sqrt()).atan()
    }

    /// Unit planet-frame direction of the ray through the centre of pixel
    /// `(px, py)` (row 0 at the top) of a `width × height` image; the aspect
    /// ratio is the image's.
    pub fn pixel_ray(&self, px: f64, py: f64, width: u32, height: u32) -> DVec3 {
        let b = self.basis();
        let (x, y) = ndc(px, py, width, height);
        let ty = (self.fov_y * 0.5).tan();
        let tx = ty * width as f64 / height.max(1) as f64;
        (b.forward + x * tx * b.right + y * ty * b.up).normalize()
    }
}

/// Normalised device coordinates of a pixel centre (y up).
pub fn ndc(px: f64, py: f64, width: u32, height: u32) -> (f64, f64) {
    (
        (px + 0.5) / width.max(1) as f64 * 2.0 - 1.0,
        1.0 - (py + 0.5) / height.max(1) as f64 * 2.0,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const R: f64 = 6_371_000.0;

    fn assert_orthonormal(b: Basis) {
        for v in [b.forward, b.right, b.up] {
            assert!((v.length() - 1.0).abs() < 1e-12, "{b:?}");
        }
        assert!(b.forward.dot(b.right).abs() < 1e-12, "{b:?}");
        assert!(b.forward.dot(b.up).abs() < 1e-12, "{b:?}");
        assert!(b.right.dot(b.up).abs() < 1e-12, "{b:?}");
        // Right-handed, looking down −z.
        assert!((b.right.cross(b.up) + b.forward).length() < 1e-12, "{b:?}");
    }

    #[test]
    fn basis_is_orthonormal_at_planet_scale() {
        // Poles, a cube corner direction, the antimeridian, 1 m and 1000
        // radii up, and inside the planet.
        let dirs = [
            DVec3::Z,
            DVec3::NEG_Z,
            DVec3::new(1.0, 1.0, 1.0).normalize(),
            DVec3::new(-1.0, 1e-12, 0.0).normalize(),
            DVec3::new(0.3, -0.2, 0.9).normalize(),
        ];
        for d in dirs {
            for h in [1.0, 1000.0 * R, -0.5 * R] {
                let eye = d * (R + h);
                for target in [DVec3::ZERO, eye + DVec3::X, eye + d] {
                    for up in [DVec3::Z, d, DVec3::ZERO, DVec3::splat(f64::NAN)] {
                        let c = Camera::look_at(eye, target, up);
                        assert_orthonormal(c.basis());
                    }
                }
            }
        }
        // Degenerate forward.
        let c = Camera::look_at(DVec3::X, DVec3::X, DVec3::Z);
        assert_eq!(c.basis().forward, DVec3::NEG_Z);
        assert_orthonormal(c.basis());
    }

    #[test]
    fn up_is_kept_when_it_is_not_parallel() {
        let c = Camera::look_at(DVec3::ZERO, DVec3::X, DVec3::new(0.1, 0.0, 1.0));
        let b = c.basis();
        assert!((b.up - DVec3::Z).length() < 1e-12, "{b:?}");
        assert!((b.right - DVec3::NEG_Y).length() < 1e-12, "{b:?}");
    }

    #[test]
    fn pixel_rays_span_the_field_of_view() {
        for fov in [1f64.to_radians(), 60f64.to_radians(), 170f64.to_radians()] {
            let mut c = Camera::look_at(DVec3::ZERO, DVec3::NEG_Z, DVec3::Y);
            c.fov_y = fov;
            let (w, h) = (640u32, 480u32);
            // The centre of the top and bottom rows are ±fov/2 from the axis
            // (up to half a pixel).
            let top = c.pixel_ray(319.5, -0.5, w, h);
            let bottom = c.pixel_ray(319.5, h as f64 - 0.5, w, h);
            let a_top = top.angle_between(DVec3::NEG_Z);
            let a_bottom = bottom.angle_between(DVec3::NEG_Z);
            assert!((a_top - fov / 2.0).abs() < 1e-9, "{fov} {a_top}");
            assert!((a_bottom - fov / 2.0).abs() < 1e-9, "{fov} {a_bottom}");
            assert!(top.y > 0.0 && bottom.y < 0.0);
            // The corners are at the half-diagonal angle.
            let c = c.with_viewport(w, h);
            let corner = c.pixel_ray(-0.5, -0.5, w, h);
            let diag = corner.angle_between(DVec3::NEG_Z);
            assert!((diag - c.half_diagonal_fov()).abs() < 1e-9, "{fov}");
        }
    }
}
