//! The projection of the core camera (reversed-Z, finite or infinite far
//! plane), and depth turned back into distance.

/// The camera of the workspace: [`planet_core::camera::Camera`]. The
/// renderer takes its aspect ratio from the frame target, not the camera.
pub use planet_core::camera::{ndc, Basis, Camera};

/// How near and far planes are chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DepthMode {
    /// Thesis Eq. 4.3, see [`planet_core::horizon`].
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
