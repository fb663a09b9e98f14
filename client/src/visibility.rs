//! Visibility: view frustum, horizon-fitted near/far planes and horizon
//! occlusion of blocks.
//!
//! Implements thesis §3.6.1 / §4.2.1 (frustum against 3D bounding boxes) and
//! §4.5.4 Eq. 4.3 (Planetary paper §6.4 Eq. 1–2, docs/REFERENCES.md): the far plane is
//! fitted to the horizon of the planet, so blocks behind the horizon fail the
//! ordinary frustum test. Beyond the thesis:
//!
//! - **Numerical form.** `‖VO‖² − ‖OT‖²` is computed as
//!   `(‖VO‖ − ‖OT‖)(‖VO‖ + ‖OT‖)` (no cancellation near the surface), and a
//!   camera inside the min sphere (or at the planet centre) disables horizon
//!   fitting instead of producing NaN.
//! - **Erratum / gap in Eq. 4.3.** Eq. 4.3 gives the depth of the farthest
//!   point of the *horizon ring* of the max sphere. When the point of the max
//!   sphere farthest along the view direction is itself visible (looking away
//!   from the planet from low altitude), that point is farther than the ring;
//!   we take it when it is not occluded. The property test
//!   `far_plane_never_culls_visible_points` checks the result against brute
//!   force.
//! - **Near plane [VAGUE in the thesis].** `near = (‖VO‖ − ‖OM‖)·cos θc`,
//!   with `θc` the half-angle of the frustum's corner ray, so that a max-sphere
//!   point seen at the screen corner is never in front of the near plane;
//!   clamped to [`NEAR_MIN`].
//! - **Horizon occlusion per block.** Independently of the far plane, a block
//!   is hidden when all its bounding points lie in the *convex* part of the
//!   min sphere's shadow: inside the tangent cone from the eye and beyond the
//!   plane of the tangent circle. That set is convex, so if it holds every
//!   bounding point it holds their hull, and so the block: the test never
//!   culls a visible point.
//! - **Curved blocks.** A block's bounding points are an `n × n` grid of
//!   directions (cells of at most about 2.5°, `n ≥ 3`) at its minimum and
//!   maximum elevation; the outer points are pushed out by `1/cos θ`, with
//!   `θ` (plus 10 %) the largest angle from a grid cell's centre to its
//!   corners, so the planes through them stay outside the curved surface.
//! - **The pushed points' false positives.** Those pushed-out points rise up
//!   to about 2 km above a coarse block (3 × 3 cells of 1.9° at level 4),
//!   and each frustum plane may pass on a different one: a camera looking up
//!   from 300 m kept every block under it. A block is also hidden when the
//!   ball about the planet centre through its highest true surface point
//!   (`top_radius`: exact, from the patch's corners) misses the view cone.
//!
//! All tests run in eye-relative coordinates in `f64`.

use glam::{DMat4, DVec3, DVec4};
use planet_core::cube::FaceCoord;
use planet_core::{BlockId, Datum};

/// The segment/ball test of the horizon planes, shared with core.
pub use planet_core::horizon::segment_hits_ball;
/// Smallest near-plane distance in metres (the renderer's: one formula,
/// one clamp).
pub use planet_core::horizon::MIN_NEAR as NEAR_MIN;

/// The camera of the workspace ([`planet_core::camera`]).
pub use planet_core::camera::{Basis, Camera};

/// Horizon-fitted near and far distances (thesis Eq. 4.3), for min and max
/// planet radii `r_min` (‖OT‖) and `r_max` (‖OM‖): the formula of
/// [`planet_core::horizon`], with the corner half-angle of this camera.
pub fn near_far(camera: &Camera, r_min: f64, r_max: f64) -> (f64, f64) {
    let p = planet_core::horizon::horizon_planes(
        camera.eye,
        camera.basis().forward,
        r_min,
        r_max,
        camera.half_diagonal_fov(),
    );
    (p.near, p.far)
}

/// Conservative bounds of a block: bounding points, axis-aligned box, centre
/// and footprint radius (thesis §4.2.4 `blockRadius`).
#[derive(Debug, Clone, PartialEq)]
pub struct BlockBounds {
    /// Points whose convex hull contains the block's surface.
    pub points: Vec<DVec3>,
    /// Minimum corner of the axis-aligned box of `points`.
    pub min: DVec3,
    /// Maximum corner of the axis-aligned box of `points`.
    pub max: DVec3,
    /// Centre of the box.
    pub centre: DVec3,
    /// Footprint radius: the largest distance from the block's centre surface
    /// point to its corner surface points (at height 0).
    pub radius: f64,
    /// Radius of a sphere about `centre` holding every bounding point.
    pub sphere_radius: f64,
    /// An upper bound of the distance from the planet centre to the block's
    /// surface (not to the pushed-out bounding points): the block is hidden
    /// when a ball of this radius about the centre misses the view cone
    /// ([`View::top_in_view`]), as when the camera looks up from above it.
    pub top_radius: f64,
    /// For blocks coarser than [`PART_LEVEL`]: the bounds of their
    /// descendants at that level (same elevation range). The block is visible
    /// only if one part is, which removes the false positives of one loose
    /// hull spanning both the space behind the eye and behind the horizon.
    pub parts: Vec<BlockBounds>,
    /// Outward unit normals of the planes through the planet centre and
    /// each edge's two corners' directions (`DVec3::ZERO` where an edge is
    /// degenerate). Moved out to the farthest bounding point, each bounds
    /// a half-space holding the block's surface, whose distance from an
    /// eye beside the block is at least the eye's distance beyond it
    /// ([`crate::refinement::Footprint::of`]): a coarse block's cone of
    /// directions is far wider than the block, and holds eyes hundreds of
    /// kilometres from it.
    pub edge_normals: [DVec3; 4],
}

/// The outward unit normal of the plane through the planet centre and the
/// directions `a` and `b` (unit vectors) on the side away from `inside`
/// ([`BlockBounds::edge_normals`]); zero when `a` and `b` are parallel.
fn edge_normal(a: DVec3, b: DVec3, inside: DVec3) -> DVec3 {
    let n = a.cross(b).normalize_or_zero();
    if n.dot(inside) > 0.0 {
        -n
    } else {
        n
    }
}

/// Level of the parts that coarse blocks are tested by.
pub const PART_LEVEL: u8 = 4;

impl BlockBounds {
    /// Bounds of `id` with elevations in `[h_min, h_max]` metres, with
    /// parts at level [`PART_LEVEL`] when the block is coarser.
    pub fn new(datum: &Datum, id: BlockId, h_min: f64, h_max: f64) -> BlockBounds {
        let mut b = BlockBounds::single(datum, id, h_min, h_max);
        if id.level < PART_LEVEL {
            let mut ids = vec![id];
            while ids[0].level < PART_LEVEL {
                ids = ids.iter().flat_map(|i| i.children()).collect();
            }
            b.parts = ids
                .into_iter()
                .map(|i| BlockBounds::single(datum, i, h_min, h_max))
                .collect();
        }
        b
    }

    /// Bounds of `id` alone (no parts).
    pub fn single(datum: &Datum, id: BlockId, h_min: f64, h_max: f64) -> BlockBounds {
        let (h_min, h_max) = if h_min <= h_max {
            (h_min, h_max)
        } else {
            (h_max, h_min)
        };
        // Grid cells of at most ~2.5° keep the outward push under 5e-4 of
        // the radius (about 3 km on the Earth), so coarse blocks near the
        // horizon are not kept visible by a loose bound.
        let cells = (90.0 / 2.5 / f64::powi(2.0, id.level as i32)).ceil() as usize;
        let n = (cells + 1).clamp(3, 64);
        let (s0, t0, s1, t1) = id.extent();
        let dir = |a: f64, b: f64| {
            let fc = FaceCoord {
                face: id.face,
                s: s0 + (s1 - s0) * a,
                t: t0 + (t1 - t0) * b,
            };
            DVec3::from_array(fc.direction())
        };
        let step = 1.0 / (n - 1) as f64;
        let mut theta: f64 = 0.0;
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let (a, b) = (i as f64 * step, j as f64 * step);
                let c = dir(a + step / 2.0, b + step / 2.0);
                for (da, db) in [(0.0, 0.0), (step, 0.0), (0.0, step), (step, step)] {
                    let k = dir(a + da, b + db);
                    theta = theta.max(angle(c, k));
                }
            }
        }
        let push = 1.0 / (theta * 1.1).min(1.4).cos() * (1.0 + 1e-9);
        let mut points = Vec::with_capacity(2 * n * n);
        for j in 0..n {
            for i in 0..n {
                let d = dir(i as f64 * step, j as f64 * step).to_array();
                points.push(DVec3::from_array(datum.position(d, h_min)));
                points.push(DVec3::from_array(datum.position(d, h_max)) * push);
            }
        }
        let (mut min, mut max) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for p in &points {
            min = min.min(*p);
            max = max.max(*p);
        }
        let centre = (min + max) * 0.5;
        let mid = DVec3::from_array(datum.position(dir(0.5, 0.5).to_array(), 0.0));
        let radius = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)]
            .iter()
            .map(|&(a, b)| {
                (DVec3::from_array(datum.position(dir(a, b).to_array(), 0.0)) - mid).length()
            })
            .fold(0.0, f64::max);
        let sphere_radius = points
            .iter()
            .map(|p| (*p - centre).length())
            .fold(0.0, f64::max)
            * (1.0 + 1e-12);
        let corners = [dir(0.0, 0.0), dir(1.0, 0.0), dir(0.0, 1.0), dir(1.0, 1.0)];
        // Round the block: (0,0) → (1,0) → (1,1) → (0,1).
        let ring = [corners[0], corners[1], corners[3], corners[2]];
        let inside = dir(0.5, 0.5);
        let edge_normals = std::array::from_fn(|k| edge_normal(ring[k], ring[(k + 1) % 4], inside));
        BlockBounds {
            points,
            min,
            max,
            centre,
            radius,
            sphere_radius,
            top_radius: top_radius(datum, corners, h_max),
            parts: Vec::new(),
            edge_normals,
        }
    }
}

/// An upper bound of the distance from the planet centre to the points at
/// heights up to `h_max` over the cube-face patch with these corner
/// directions (geodetic normals). That distance depends on `|n_z|` only and
/// decreases as it grows (for heights small beside the radius; otherwise the
/// bound is infinite), and over a patch bounded by great circles `|n_z|` is
/// smallest at a corner, or 0 where the patch meets the equator.
fn top_radius(datum: &Datum, corners: [DVec3; 4], h_max: f64) -> f64 {
    if h_max.is_nan() || h_max.abs() > 0.01 * datum.equatorial_radius() {
        return f64::INFINITY;
    }
    let z = corners.map(|c| c.z);
    let w = if z.iter().any(|&v| v <= 0.0) && z.iter().any(|&v| v >= 0.0) {
        0.0
    } else {
        z.iter().map(|v| v.abs()).fold(1.0, f64::min)
    };
    let n = [(1.0 - w * w).max(0.0).sqrt(), 0.0, w];
    DVec3::from_array(datum.position(n, h_max)).length() * (1.0 + 1e-12) + 1e-6
}

fn angle(a: DVec3, b: DVec3) -> f64 {
    2.0 * ((a - b).length() / 2.0).min(1.0).asin()
}

/// A plane `n·p + d ≥ 0` (inside), in eye-relative coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Plane {
    n: DVec3,
    d: f64,
}

/// The per-frame view: frustum (eye-relative), near/far and horizon.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// The camera.
    pub camera: Camera,
    /// Near distance (metres along the view direction).
    pub near: f64,
    /// Horizon-fitted far distance.
    pub far: f64,
    /// Radius of the occluding min sphere.
    pub r_min: f64,
    planes: [Plane; 6],
    /// `|n|` of each plane (sphere pre-tests).
    plane_norms: [f64; 6],
    /// `cos` and `sin` of the cone half-angle (cone pre-test).
    cone_cos_sin: (f64, f64),
    forward: DVec3,
    eye_len: f64,
    cos_beta: f64,
    cone_half_angle: f64,
    /// The radius from which a ball about the planet centre meets the view
    /// cone ([`centre_reach`]).
    centre_reach: f64,
    planet_in_view: bool,
}

/// The smallest radius of a ball about the planet centre (the origin) that
/// meets the cone (apex, unit axis, half-angle): 0 when the centre is in the
/// cone, `‖apex‖·sin β` when the centre is `β < 90°` outside its edge, `‖apex‖`
/// beyond. [`cone_meets_sphere`] with the origin as centre is
/// `radius >= centre_reach(..)` (the same 1e-9 rad of slack).
fn centre_reach(apex: DVec3, axis: DVec3, half: f64) -> f64 {
    let dist = apex.length();
    if dist.is_nan() || dist <= 0.0 || dist.is_infinite() {
        return 0.0;
    }
    let cos_angle = (-apex.dot(axis) / dist).clamp(-1.0, 1.0);
    let beyond = cos_angle.acos() - half - 1e-9;
    if beyond.is_nan() || beyond <= 0.0 {
        0.0
    } else if beyond >= std::f64::consts::FRAC_PI_2 {
        dist
    } else {
        dist * beyond.sin()
    }
}

/// Whether the cone (apex, unit axis, half-angle) meets the sphere.
fn cone_meets_sphere(apex: DVec3, axis: DVec3, half: f64, centre: DVec3, radius: f64) -> bool {
    let d = centre - apex;
    let dist = d.length();
    if dist.partial_cmp(&radius) != Some(std::cmp::Ordering::Greater) {
        return true;
    }
    let spread = (radius / dist).min(1.0).asin();
    let cos_angle = (d.dot(axis) / dist).clamp(-1.0, 1.0);
    cos_angle.acos() <= half + spread + 1e-9
}

impl View {
    /// Build the view for `camera` over a planet whose surface lies between
    /// radii `r_min` and `r_max`.
    pub fn new(camera: &Camera, r_min: f64, r_max: f64) -> View {
        let (near, far) = near_far(camera, r_min, r_max);
        let Basis {
            forward: f,
            right: r,
            up: u,
        } = camera.basis();
        let ty = (camera.fov_y * 0.5).tan().abs();
        let tx = ty * camera.aspect.abs();
        let planes = [
            Plane {
                n: r + f * tx,
                d: 0.0,
            },
            Plane {
                n: -r + f * tx,
                d: 0.0,
            },
            Plane {
                n: u + f * ty,
                d: 0.0,
            },
            Plane {
                n: -u + f * ty,
                d: 0.0,
            },
            Plane { n: f, d: -near },
            Plane { n: -f, d: far },
        ];
        let eye_len = camera.eye.length();
        let cos_beta = if eye_len > r_min {
            ((eye_len - r_min) * (eye_len + r_min)).sqrt() / eye_len
        } else {
            1.0
        };
        let cone_half_angle = (tx.hypot(ty)).atan();
        let centre_reach = centre_reach(camera.eye, f, cone_half_angle);
        let r = r_max.max(r_min);
        let planet_in_view = r.is_nan() || r >= centre_reach;
        View {
            plane_norms: planes.map(|p| p.n.length()),
            cone_cos_sin: (cone_half_angle.cos(), cone_half_angle.sin()),
            cone_half_angle,
            centre_reach,
            planet_in_view,
            camera: *camera,
            near,
            far,
            r_min,
            planes,
            forward: f,
            eye_len,
            cos_beta,
        }
    }

    /// The eye-relative view-projection (depth 0..1, right-handed) matching
    /// the frustum, for a renderer that draws in eye-relative coordinates.
    pub fn view_projection(&self) -> DMat4 {
        let Basis {
            forward: f,
            right: r,
            up: u,
        } = self.camera.basis();
        let view = DMat4::from_cols(
            DVec4::new(r.x, u.x, -f.x, 0.0),
            DVec4::new(r.y, u.y, -f.y, 0.0),
            DVec4::new(r.z, u.z, -f.z, 0.0),
            DVec4::W,
        );
        let g = 1.0 / (self.camera.fov_y * 0.5).tan();
        let (n, fa) = (self.near, self.far);
        let proj = DMat4::from_cols(
            DVec4::new(g / self.camera.aspect, 0.0, 0.0, 0.0),
            DVec4::new(0.0, g, 0.0, 0.0),
            DVec4::new(0.0, 0.0, fa / (n - fa), -1.0),
            DVec4::new(0.0, 0.0, n * fa / (n - fa), 0.0),
        );
        proj * view
    }

    /// Whether the box (planet-centred) is at least partly inside the frustum.
    pub fn box_in_frustum(&self, min: DVec3, max: DVec3) -> bool {
        let (lo, hi) = (min - self.camera.eye, max - self.camera.eye);
        self.planes.iter().all(|p| {
            let v = DVec3::new(
                if p.n.x >= 0.0 { hi.x } else { lo.x },
                if p.n.y >= 0.0 { hi.y } else { lo.y },
                if p.n.z >= 0.0 { hi.z } else { lo.z },
            );
            p.n.dot(v) + p.d >= 0.0
        })
    }

    /// Whether the planet-centred point `p` is in the convex part of the min
    /// sphere's shadow (so certainly hidden).
    pub fn point_behind_horizon(&self, p: DVec3) -> bool {
        if self.eye_len.partial_cmp(&self.r_min) != Some(std::cmp::Ordering::Greater) {
            return false;
        }
        let v = self.camera.eye;
        let vhat = v / self.eye_len;
        // Beyond the plane of the tangent circle: p·V̂ < r²/|V|.
        let beyond = p.dot(vhat) < self.r_min * (self.r_min / self.eye_len) * (1.0 - 1e-12);
        if !beyond {
            return false;
        }
        let d = p - v;
        let along = d.dot(-vhat);
        along > 0.0 && along > d.length() * self.cos_beta * (1.0 + 1e-12)
    }

    /// Whether every bounding point of the block is behind the horizon.
    pub fn behind_horizon(&self, b: &BlockBounds) -> bool {
        if b.points.is_empty() {
            return false;
        }
        // Sphere pre-tests (every point lies in the sphere): same answer.
        match self.sphere_horizon(b.centre, b.sphere_radius) {
            Some(hidden) => hidden,
            None => b.points.iter().all(|p| self.point_behind_horizon(*p)),
        }
    }

    /// The horizon test (§4.5.4) for every point of the ball (`centre`,
    /// `radius`) at once: `Some(true)` when all of them are in the convex
    /// part of the min sphere's shadow, `Some(false)` when none is beyond
    /// the plane of the tangent circle (so none is hidden), `None` when the
    /// ball straddles. Margins of 1 mm keep it on the safe side of rounding,
    /// so it agrees with [`View::point_behind_horizon`] on every point.
    pub fn sphere_horizon(&self, centre: DVec3, radius: f64) -> Option<bool> {
        if self.eye_len.partial_cmp(&self.r_min) != Some(std::cmp::Ordering::Greater) {
            return Some(false);
        }
        if !(centre.is_finite() && radius.is_finite() && radius >= 0.0) {
            return None;
        }
        let v = self.camera.eye;
        let vhat = v / self.eye_len;
        let plane = self.r_min * (self.r_min / self.eye_len);
        let tol = 1e-3 + 1e-12 * self.eye_len;
        let c = centre.dot(vhat);
        if c - radius >= plane + tol {
            return Some(false);
        }
        if c + radius < plane * (1.0 - 1e-12) - tol {
            // Inside the shadow cone: angle to −V̂ plus the ball's angular
            // radius below β (cos form; a sum above π/2 fails the test).
            let d = centre - v;
            let dist = d.length();
            if dist > radius * (1.0 + 1e-9) + tol {
                let cos_phi = (d.dot(-vhat) / dist).clamp(-1.0, 1.0);
                let sin_phi = (1.0 - cos_phi * cos_phi).max(0.0).sqrt();
                let ss = radius / dist + 1e-12;
                let cs = (1.0 - ss * ss).max(0.0).sqrt();
                let cos_sum = cos_phi * cs - sin_phi * ss;
                if cos_phi > 0.0 && cos_sum > self.cos_beta * (1.0 + 1e-12) + 1e-9 {
                    return Some(true);
                }
            }
        }
        None
    }

    /// Visibility of every block whose bounding points (and parts' points)
    /// all lie in the ball (`centre`, `radius`), decided without the points
    /// (§3.6.1, §4.2.1, §4.5.4): `Some(true)` when the ball is inside the
    /// frustum and in front of the horizon (so [`View::is_visible`] is true
    /// for each such block), `Some(false)` when it is outside one plane or
    /// behind the horizon, `None` when undecided. Used to skip the tests of
    /// whole subtrees ([`crate::selection::Selector`]).
    pub fn classify_sphere(&self, centre: DVec3, radius: f64) -> Option<bool> {
        if !self.planet_in_view {
            return Some(false);
        }
        if !(centre.is_finite() && radius.is_finite() && radius >= 0.0) {
            return None;
        }
        let c = centre - self.camera.eye;
        let mut inside = true;
        for (p, len) in self.planes.iter().zip(self.plane_norms) {
            let s = p.n.dot(c) + p.d;
            let m = radius * len * (1.0 + 1e-9) + (1e-6 + 1e-3) * (1.0 + len);
            if s <= -m {
                return Some(false);
            }
            inside &= s >= m;
        }
        match self.sphere_horizon(centre, radius) {
            Some(true) => Some(false),
            Some(false) if inside => Some(true),
            _ => None,
        }
    }

    /// Whether the block may be visible (frustum with horizon-fitted planes,
    /// and horizon occlusion).
    pub fn is_visible(&self, b: &BlockBounds) -> bool {
        if !b.parts.is_empty() {
            return self.planet_in_view
                && self.sphere_in_cone(b.centre, b.sphere_radius)
                && b.parts.iter().any(|p| self.is_visible(p));
        }
        self.planet_in_view
            && self.top_in_view(b.top_radius)
            && self.sphere_in_cone(b.centre, b.sphere_radius)
            && self.box_in_frustum(b.min, b.max)
            && self.hull_in_frustum_sphere(&b.points, b.centre, b.sphere_radius)
            && !self.behind_horizon(b)
    }

    /// [`View::is_visible`] (the same answer) that tries the bounding point
    /// `*hint` first in the horizon test and leaves there the point that
    /// proved the block visible: from frame to frame it usually does again.
    pub fn is_visible_hinted(&self, b: &BlockBounds, hint: &mut u32) -> bool {
        if !b.parts.is_empty() {
            return self.is_visible(b);
        }
        self.planet_in_view
            && self.top_in_view(b.top_radius)
            && self.sphere_in_cone(b.centre, b.sphere_radius)
            && self.box_in_frustum(b.min, b.max)
            && self.hull_in_frustum_sphere(&b.points, b.centre, b.sphere_radius)
            && !self.behind_horizon_hinted(b, hint)
    }

    /// Whether the planet is in view at all (else nothing is visible).
    pub fn planet_in_view(&self) -> bool {
        self.planet_in_view
    }

    /// Whether a ball of radius `top_radius` about the planet centre meets
    /// the view cone ([`BlockBounds::top_radius`]): false when the camera
    /// looks away from everything that low, e.g. up from above the block,
    /// where the bounding points pushed out over a coarse grid can still
    /// pass every plane. Exact for the block's true surface, so it only
    /// removes false positives of the hull test.
    pub fn top_in_view(&self, top_radius: f64) -> bool {
        top_radius.is_nan() || top_radius >= self.centre_reach
    }

    /// Whether the bounding point `p` of a block proves the block visible:
    /// `p` is inside every frustum plane (each plane test of
    /// [`View::hull_in_frustum`] and, since the box holds `p`, of
    /// [`View::box_in_frustum`] passes; the same expressions) and not
    /// behind the horizon. With [`View::planet_in_view`],
    /// [`View::top_in_view`] of the block's top radius and
    /// [`View::sphere_in_cone`] of the block's ball this gives
    /// [`View::is_visible`] of a block without parts.
    pub fn point_witnesses_visible(&self, p: DVec3) -> bool {
        let q = p - self.camera.eye;
        self.planes.iter().all(|pl| pl.n.dot(q) + pl.d >= 0.0) && !self.point_behind_horizon(p)
    }

    fn behind_horizon_hinted(&self, b: &BlockBounds, hint: &mut u32) -> bool {
        let n = b.points.len();
        if n == 0 {
            return false;
        }
        if let Some(hidden) = self.sphere_horizon(b.centre, b.sphere_radius) {
            return hidden;
        }
        let start = *hint as usize % n;
        for k in 0..n {
            let i = if start + k < n {
                start + k
            } else {
                start + k - n
            };
            if !self.point_behind_horizon(b.points[i]) {
                *hint = i as u32;
                return false;
            }
        }
        true
    }

    /// Whether the sphere may meet the frustum's bounding cone (apex at the
    /// eye, axis forward, half-angle of the frustum's corner ray).
    pub fn sphere_in_cone(&self, centre: DVec3, radius: f64) -> bool {
        // Trig-free pre-test; only the uncertain band takes the exact form
        // below (so the answer is the same).
        let d = centre - self.camera.eye;
        let d2 = d.length_squared();
        if d2.is_finite() && radius >= 0.0 && d2 > radius * radius * (1.0 + 1e-6) {
            let dist = d2.sqrt();
            let (ch, sh) = self.cone_cos_sin;
            let ss = radius / dist;
            let cs = (1.0 - ss * ss).max(0.0).sqrt();
            let along = d.dot(self.forward) / dist;
            // cos(half + spread): half < π/2 (an atan) and spread ≤ π/2,
            // so the sum is in [0, π) where cos is decreasing.
            let sum_cos = ch * cs - sh * ss;
            if along > sum_cos + 1e-6 {
                return true;
            }
            if along < sum_cos - 1e-6 {
                return false;
            }
        }
        cone_meets_sphere(
            self.camera.eye,
            self.forward,
            self.cone_half_angle,
            centre,
            radius,
        )
    }

    /// Whether the convex hull of the planet-centred `points` may meet the
    /// frustum: false when all of them are outside one plane.
    pub fn hull_in_frustum(&self, points: &[DVec3]) -> bool {
        let eye = self.camera.eye;
        self.planes
            .iter()
            .all(|p| points.iter().any(|q| p.n.dot(*q - eye) + p.d >= 0.0))
    }

    /// [`View::hull_in_frustum`] for points inside the sphere
    /// (`centre`, `radius`): planes that the sphere lies clearly inside or
    /// outside of are decided without the points (same answer).
    fn hull_in_frustum_sphere(&self, points: &[DVec3], centre: DVec3, radius: f64) -> bool {
        if points.is_empty() {
            return self.hull_in_frustum(points);
        }
        let eye = self.camera.eye;
        let c = centre - eye;
        self.planes.iter().zip(self.plane_norms).all(|(p, len)| {
            let s = p.n.dot(c) + p.d;
            let m = radius * len * (1.0 + 1e-9) + 1e-6 * (1.0 + len);
            if s >= m {
                true
            } else if s <= -m {
                false
            } else {
                points.iter().any(|q| p.n.dot(*q - eye) + p.d >= 0.0)
            }
        })
    }

    /// Depth of a point along the view direction.
    pub fn depth(&self, p: DVec3) -> f64 {
        self.forward.dot(p - self.camera.eye)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use planet_core::Face;
    use proptest::prelude::*;

    const R: f64 = 6_371_000.0;

    fn unit(a: f64, b: f64) -> DVec3 {
        let (sa, ca) = a.sin_cos();
        let (sb, cb) = b.sin_cos();
        DVec3::new(ca * cb, ca * sb, sa)
    }

    proptest! {
        /// The horizon test never hides a point that brute force sees.
        #[test]
        fn horizon_test_is_conservative(
            alt in 0.0f64..1.0e7, ea in -1.5f64..1.5, eb in -3.2f64..3.2,
            pts in proptest::collection::vec((-1.5f64..1.5, -3.2f64..3.2, 0.0f64..1.0), 64),
        ) {
            let r_min = R - 1000.0;
            let eye = unit(ea, eb) * (R + alt);
            let view = View::new(&Camera::look_at(eye, DVec3::ZERO, DVec3::Z), r_min, R + 9000.0);
            for (a, b, h) in pts {
                let p = unit(a, b) * (r_min + 10_000.0 * h);
                if view.point_behind_horizon(p) {
                    prop_assert!(segment_hits_ball(eye, p, r_min));
                }
            }
        }
    }

    #[test]
    fn bounds_contain_surface() {
        let datum = Datum::WGS84;
        // Every face (the polar faces, faces across the equator) at coarse
        // and fine levels, blocks at corners and in the middle.
        for face in Face::ALL {
            for level in [0u8, 1, 2, 3, 6] {
                let last = (1u32 << level) - 1;
                for (x, y) in [(0, 0), (last, 0), (last / 2, (last / 2 + 1).min(last))] {
                    let id = BlockId::new(face, level, x, y).unwrap();
                    let b = BlockBounds::new(&datum, id, -100.0, 100.0);
                    let (s0, t0, s1, t1) = id.extent();
                    let mut top: f64 = 0.0;
                    for j in 0..=20 {
                        for i in 0..=20 {
                            let fc = FaceCoord {
                                face: id.face,
                                s: s0 + (s1 - s0) * i as f64 / 20.0,
                                t: t0 + (t1 - t0) * j as f64 / 20.0,
                            };
                            for h in [-100.0, 0.0, 100.0] {
                                let p = DVec3::from_array(datum.position(fc.direction(), h));
                                assert!(p.cmpge(b.min).all() && p.cmple(b.max).all(), "{level}");
                                assert!(p.length() <= b.top_radius, "{id:?} {}", p.length());
                                top = top.max(p.length());
                            }
                        }
                    }
                    // Tight: within 50 m of the sampled highest point (the
                    // grid may miss the equator by up to 2.25°).
                    assert!(
                        b.top_radius - top < 50.0,
                        "{id:?}: {} vs {top}",
                        b.top_radius
                    );
                    assert!(b.radius > 0.0);
                }
            }
        }
    }

    /// A ball about the centre meets the cone exactly when its radius
    /// reaches [`centre_reach`] (the formula [`View::top_in_view`] and
    /// [`View::planet_in_view`] use), against the general cone/sphere test.
    #[test]
    fn centre_reach_matches_cone_meets_sphere() {
        let mut rng = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..20_000 {
            let eye = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * R * 4.0;
            let axis = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5).normalize();
            let half = next() * 1.5;
            let reach = centre_reach(eye, axis, half);
            for r in [reach * 0.999, reach * 1.001, R, eye.length() * 1.001] {
                let meets = cone_meets_sphere(eye, axis, half, DVec3::ZERO, r);
                // Only a sliver of 1e-9 rad either way may differ.
                if (r - reach).abs() > 1e-6 * eye.length() {
                    assert_eq!(meets, r >= reach, "{eye} {axis} {half} r {r} reach {reach}");
                }
            }
        }
    }

    /// Looking up from 316 m above the datum: every block below the eye is
    /// hidden, although their pushed-out bounding points rise up to about
    /// 2 km and pass each frustum plane (the case a client property test
    /// found); looking down, the block under the eye is visible.
    #[test]
    fn blocks_below_an_eye_looking_up_are_hidden() {
        let datum = Datum::WGS84;
        let a = datum.equatorial_radius();
        let eye = DVec3::new(-(a + 316.0), 0.0, 0.0);
        let up = Camera::look_at(eye, eye * 2.0, DVec3::Z);
        let down = Camera::look_at(eye, DVec3::ZERO, DVec3::Z);
        let id = FaceCoord::from_direction([-1.0, 0.0, 0.0]);
        for level in 2..=6u8 {
            let n = 1u32 << level;
            let x = ((id.s * n as f64) as u32).min(n - 1);
            let y = ((id.t * n as f64) as u32).min(n - 1);
            let block = BlockId::new(id.face, level, x, y).unwrap();
            let b = BlockBounds::new(&datum, block, -1514.0, -167.0);
            let view = View::new(&up, a - 1600.0, a + 9000.0);
            assert!(!view.is_visible(&b), "{block:?} visible looking up");
            let view = View::new(&down, a - 1600.0, a + 9000.0);
            assert!(view.is_visible(&b), "{block:?} hidden looking down");
        }
    }

    #[test]
    fn view_projection_matches_planes() {
        let eye = DVec3::new(R + 1000.0, 0.0, 0.0);
        let cam = Camera::look_at(eye, eye + DVec3::Y, DVec3::X);
        let v = View::new(&cam, R - 100.0, R + 100.0);
        let m = v.view_projection();
        let f = cam.basis().forward;
        let clip = |d: f64| {
            let c = m * (f * d).extend(1.0);
            c.z / c.w
        };
        assert!(clip(v.near).abs() < 1e-9);
        assert!((clip(v.far) - 1.0).abs() < 1e-9);
    }

    #[test]
    fn degenerate_cameras_are_finite() {
        for eye in [DVec3::ZERO, DVec3::X * 1e12, DVec3::X * (R - 10.0)] {
            let cam = Camera::look_at(eye, DVec3::X, DVec3::Z);
            let (n, f) = near_far(&cam, R - 100.0, R + 100.0);
            assert!(
                n.is_finite() && f.is_finite() && n > 0.0 && f > n,
                "{eye} {n} {f}"
            );
        }
    }
}
