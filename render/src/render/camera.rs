//! The f64 camera, its projection (reversed-Z, finite or infinite far
//! plane) and pixel rays.

use super::*;

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
