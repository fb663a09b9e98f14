//! What to refine, and in which order: the client's policy.
//!
//! The thesis (§3.6.2–3.6.4, §4.2.4; docs/REFERENCES.md) refines by
//! *importance*, the projected sample spacing scaled by a quality factor
//! (Eq. 3.2–3.4, [`crate::importance`]), and ranks requests by the same
//! number. It ignores the geometric error that every child reference of the
//! database already carries (docs/FORMAT.md: the largest vertical deviation
//! of a block drawn at its first LOD from the full-resolution data under
//! it), so a flat ocean block is refined as eagerly as a cliff, and the QF
//! that reaches a given screen-space error differs from one database and
//! camera to the next.
//!
//! The default policy, [`Policy::Ours`], refines by **screen-space error**
//! against a pixel tolerance (`--max-sse`, default 1 px), as the field does
//! (Cesium's `maximumScreenSpaceError`, docs/REFERENCES.md), with our per-record
//! errors:
//!
//! ```text
//! ρ(ε, d) = ε·H / (2·d·tan(fov_y/2))       d = max(distance to the block, near)
//! s1 = ρ(error of the block at LOD 1)       (its own record's error)
//! s0 = ρ(error of the block at LOD 0)       (largest error of its children's records)
//! leaf with LOD 1:   load LOD 0  when s1 > tol              (priority s1)
//! leaf with LOD 0:   split       when s0 > tol              (priority s0)
//!                    keep drawing LOD 0 while s1 > tol/2    (hysteresis)
//! split block:       merge       when s1 ≤ tol/4            (two halvings of hysteresis)
//! ```
//!
//! The distance to the block is a lower bound of the distance from the eye
//! to any point of its surface ([`Footprint::distance`]): the largest of
//! the distance to its bounding ball, the eye's height above the highest
//! point of its bounds, the distance to the cone of directions that the
//! block covers, and the distance beyond the planes of its four edges
//! (a coarse block's cone is far wider than the block itself), so a block
//! seen from above or from the side is not taken for one that surrounds
//! the eye.
//!
//! A block whose error is below the tolerance is never refined, whatever
//! its size or distance; one above always is. Colour refines by projected
//! texel size, as mip selection does: LOD 0 when the first LOD's texels
//! would cover more than `tol` pixels and the record adds a colour
//! difference (its error is at least one 8-bit step).
//!
//! The priority of a request is the screen-space error it removes per byte
//! it costs, `(s1 − s0) / (size + 256)`: ordering jobs by weight over
//! duration minimises the weighted sum of their completion times (Smith's
//! rule, 1956), and here the weights are the pixels of error that each
//! record removes and the durations its bytes on the link, so this order
//! minimises the error integrated over the flight when the link is the
//! bottleneck. Splits cost no bytes and go by `s0`.
//!
//! The two trees' errors are weighed in one unit, the displacement on
//! screen: a geometric error of `s` pixels moves the surface by up to `s`
//! pixels, while texels of `t` pixels place a colour edge within half a
//! texel of where it is ([`COLOUR_DISPLACEMENT`]). So a colour record's
//! gain in the priority is half its texels' shrinkage; its refinement test
//! stays one texel per pixel, as mip selection has it.
//!
//! The other policies are baselines measured in the same run
//! (`planet-bench flight --policy`), each with the same refinement test and
//! tolerance where its source has one, so that the comparison is of
//! scheduling:
//!
//! - [`Policy::Thesis`]: Eq. 3.2–3.4 as the thesis gives them, with its
//!   fixed queue and QF law ([`crate::quality`]).
//! - [`Policy::Cesium`]: CesiumJS terrain streaming with its defaults
//!   (docs/REFERENCES.md): SSE refinement at `maximumScreenSpaceError` (set to our
//!   tolerance), load priority `(1 − cos θ)·distance` where θ is the angle
//!   between the view direction and the tile's centre and `distance` the
//!   distance to its bounds (`GlobeSurfaceTileProvider.computeTileLoadPriority`;
//!   smaller first), 18 requests in flight (`RequestScheduler`:
//!   `maximumRequests = 50`, `maximumRequestsPerServer = 18`, one server),
//!   at most 20 new requests a frame (`priorityHeapLength = 20`; those that
//!   do not fit are refused and asked again next frame), in-flight requests
//!   kept until their tile is gone, no view prediction. Parents stay drawn
//!   until their children are loaded and ancestors are always loaded first,
//!   as in every policy here (a child's first LOD is its parent's data).
//! - [`Policy::Breadth`]: the naive baseline: the same SSE test, requests
//!   in level order, nearest first, a fixed queue of 16.

use crate::importance::{
    refine_importance, selected_lod, split_importance, wants_merge, wants_split, Importance,
    ScreenError,
};
use crate::visibility::{BlockBounds, View};
use glam::{DVec3, DVec4};
use std::fmt;
use std::str::FromStr;

/// Default pixel tolerance of the screen-space error.
pub const DEFAULT_MAX_SSE_PX: f64 = 1.0;

/// Drawing keeps LOD 0 while `s1` stays above `tol` times this.
pub const KEEP_LOD0: f64 = 0.5;
/// A split block merges when its own first LOD is within `tol` times this.
pub const MERGE_AT: f64 = 0.25;
/// Bytes a request costs besides its record (request, stream and response
/// framing, packet headers; docs/PROTOCOL.md), in the priority per byte.
pub const REQUEST_OVERHEAD: f64 = 256.0;
/// Screen displacement of a colour edge per texel of projected size: a
/// texel `t` pixels wide puts the colour it holds within `t/2` pixels of
/// where it is, so a colour record that shrinks the texels from `s1` to
/// `s0` pixels removes `(s1 − s0)/2` pixels of displacement, the unit of
/// an elevation record's gain (its geometric error projected).
pub const COLOUR_DISPLACEMENT: f64 = 0.5;

/// A client policy: refinement test and request order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Policy {
    /// Screen-space error against a pixel tolerance, worst error first,
    /// window sized by the link (the default).
    #[default]
    Ours,
    /// The thesis: importance (Eq. 3.2–3.4), QF, fixed queue.
    Thesis,
    /// CesiumJS terrain streaming with its defaults.
    Cesium,
    /// Level order, nearest first.
    Breadth,
}

impl Policy {
    /// Every policy, in the order benchmarks list them.
    pub const ALL: [Policy; 4] = [
        Policy::Ours,
        Policy::Thesis,
        Policy::Cesium,
        Policy::Breadth,
    ];

    /// The policy's name (`ours`, `thesis`, `cesium`, `breadth`).
    pub fn name(self) -> &'static str {
        match self {
            Policy::Ours => "ours",
            Policy::Thesis => "thesis",
            Policy::Cesium => "cesium",
            Policy::Breadth => "breadth",
        }
    }
}

impl fmt::Display for Policy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// An unknown policy name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown policy {0:?} (ours, thesis, cesium or breadth)")]
pub struct UnknownPolicy(pub String);

impl FromStr for Policy {
    type Err = UnknownPolicy;
    fn from_str(s: &str) -> Result<Policy, UnknownPolicy> {
        Policy::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| UnknownPolicy(s.to_string()))
    }
}

/// Where a block is, for its distance from the eye: the centre and
/// footprint radius of thesis §4.2.4 (the thesis's distance) and the cone of
/// directions and the largest radius its bounds cover (the tighter distance
/// of the screen-space error).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Footprint {
    /// Centre of the bounding box.
    pub centre: DVec3,
    /// Footprint radius (thesis `blockRadius`).
    pub radius: f64,
    /// Radius of the ball about `centre` holding every bounding point.
    pub sphere_radius: f64,
    /// Axis of the cone of directions of the bounding points (unit).
    pub axis: DVec3,
    /// Half-angle of that cone in radians (π: no cone).
    pub half_angle: f64,
    /// Cosine of `half_angle`.
    pub cos_half: f64,
    /// Sine of `half_angle`.
    pub sin_half: f64,
    /// Largest distance of a bounding point from the planet's centre.
    pub r_top: f64,
    /// Half-spaces `n·p ≤ w` along the block's four edges (`xyz`: the
    /// unit normal of [`BlockBounds::edge_normals`], `w`: the largest
    /// `n·p` over the bounding points), each holding the bounding points'
    /// hull and so the surface; [`NO_HALF_SPACE`] where an edge is
    /// degenerate.
    pub edges: [DVec4; 4],
}

/// A half-space of [`Footprint::edges`] that bounds nothing (`n·p − w`
/// is −∞ everywhere).
pub const NO_HALF_SPACE: DVec4 = DVec4::new(0.0, 0.0, 1.0, f64::INFINITY);

impl Footprint {
    /// The footprint of `b` (its bounding points' hull contains the
    /// block's surface, so every surface direction lies in the cone of the
    /// points' directions when that cone is narrower than a hemisphere, and
    /// no surface point is farther from the centre than the farthest point).
    pub fn of(b: &BlockBounds) -> Footprint {
        let axis = if b.centre.length_squared() > 0.0 && b.centre.is_finite() {
            b.centre.normalize()
        } else {
            DVec3::Z
        };
        let mut cos_min: f64 = 1.0;
        let mut r_top: f64 = 0.0;
        // Each edge plane moved out to the farthest bounding point.
        let mut w = [f64::NEG_INFINITY; 4];
        for p in &b.points {
            for (w, n) in w.iter_mut().zip(&b.edge_normals) {
                *w = w.max(n.dot(*p));
            }
            let l = p.length();
            r_top = r_top.max(l);
            if l > 0.0 {
                cos_min = cos_min.min(axis.dot(*p) / l);
            } else {
                cos_min = -1.0;
            }
        }
        // Half-angles from 90° on give no bound (the cone is not convex).
        let half_angle = if cos_min > 1e-3 {
            cos_min.clamp(-1.0, 1.0).acos() * (1.0 + 1e-9) + 1e-12
        } else {
            std::f64::consts::PI
        };
        Footprint {
            centre: b.centre,
            radius: b.radius,
            sphere_radius: b.sphere_radius,
            axis,
            half_angle,
            cos_half: half_angle.cos(),
            sin_half: half_angle.sin(),
            r_top: if r_top.is_finite() { r_top } else { f64::MAX },
            edges: std::array::from_fn(|k| {
                let n = b.edge_normals[k];
                if n != DVec3::ZERO && w[k].is_finite() {
                    n.extend(w[k])
                } else {
                    NO_HALF_SPACE
                }
            }),
        }
    }

    /// The footprint of `b` with its bounding ball only (no cone, no top):
    /// a looser distance, without reading the bounding points.
    pub fn ball(b: &BlockBounds) -> Footprint {
        Footprint {
            centre: b.centre,
            radius: b.radius,
            sphere_radius: b.sphere_radius,
            axis: DVec3::Z,
            half_angle: std::f64::consts::PI,
            cos_half: -1.0,
            sin_half: 0.0,
            r_top: f64::MAX,
            edges: [NO_HALF_SPACE; 4],
        }
    }

    /// A lower bound of the distance from `eye` to the block's surface
    /// (may be negative or zero when the eye may be inside its bounds):
    /// the largest of
    ///
    /// - `|eye − centre| − sphere_radius` (the bounding ball),
    /// - `|eye| − r_top` (the eye above the highest bounding point),
    /// - the distance from `eye` to the set of points at angle at least
    ///   `θ − half_angle` from its direction and at most `r_top` from the
    ///   centre, where `θ` is the angle between the eye and the axis: the
    ///   block seen from the side,
    /// - `n·eye − w` for each of the edges' half-spaces `n·p ≤ w`
    ///   ([`Footprint::edges`]), each holding the bounding points' hull
    ///   and so the surface: the eye beside the block but inside its
    ///   cone, which is far wider than the block (a level-1 block's cone
    ///   reaches 32° from its axis, and holds eyes 660 km beside it).
    pub fn distance(&self, eye: DVec3) -> f64 {
        self.distance_from(eye, eye.length())
    }

    /// `|eye − centre| − sphere_radius`: the distance to the ball holding
    /// every bounding point, a lower bound of [`Footprint::distance`] (its
    /// first term) that moves by at most as much as the eye.
    #[inline]
    pub fn ball_distance(&self, eye: DVec3) -> f64 {
        (eye - self.centre).length() - self.sphere_radius
    }

    /// `|eye − centre| + sphere_radius`: an upper bound of
    /// [`Footprint::distance`] (each of its terms is at most the distance
    /// to a bounding point, and those lie in the ball), which moves by at
    /// most as much as the eye.
    #[inline]
    pub fn upper_distance(&self, eye: DVec3) -> f64 {
        (eye - self.centre).length() + self.sphere_radius
    }

    /// [`Footprint::distance`] with `|eye|` given (the same for every
    /// block of a frame). The angle between the eye and the nearest
    /// direction of the cone, `φ = θ − half_angle`, is handled through its
    /// sine and cosine (no inverse trigonometry), and the distance in forms
    /// without cancellation.
    pub fn distance_from(&self, eye: DVec3, e: f64) -> f64 {
        let ball = self.ball_distance(eye);
        let above = e - self.r_top;
        let mut side = f64::NEG_INFINITY;
        if self.half_angle < std::f64::consts::FRAC_PI_2 && e > 0.0 {
            let c = (self.axis.dot(eye) / e).clamp(-1.0, 1.0);
            let s = ((1.0 - c) * (1.0 + c)).max(0.0).sqrt();
            // sin φ and cos φ of φ = θ − half_angle.
            let sin_p = s * self.cos_half - c * self.sin_half;
            if sin_p > 0.0 {
                let cos_p = c * self.cos_half + s * self.sin_half;
                // Nearest point at angle φ from the eye's direction and at
                // most r_top from the centre: at radius e·cos φ (clamped
                // to [0, r_top]).
                side = if cos_p <= 0.0 {
                    e
                } else if e * cos_p <= self.r_top {
                    e * sin_p
                } else {
                    // |eye − p|² = (e − r)² + 2·e·r·(1 − cos φ), with
                    // 1 − cos φ = sin²φ / (1 + cos φ).
                    let r = self.r_top;
                    let one_minus_cos = sin_p * sin_p / (1.0 + cos_p);
                    ((e - r) * (e - r) + 2.0 * e * r * one_minus_cos).sqrt()
                };
            }
        }
        // Beside the block: beyond one of its edges' half-spaces.
        let edge = self
            .edges
            .iter()
            .map(|h| h.truncate().dot(eye) - h.w)
            .fold(f64::NEG_INFINITY, f64::max);
        let d = ball.max(above).max(side).max(edge);
        if d.is_nan() {
            f64::NEG_INFINITY
        } else {
            d
        }
    }
}

/// What a node's decisions depend on besides the policy and tolerance,
/// computed once per node while the eye stays put (memoisable: it does not
/// depend on the view direction).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Measure {
    /// Thesis: importance. Screen-error policies: `s1`, the screen-space
    /// error of the block drawn at LOD 1, in pixels.
    pub a: f64,
    /// Screen-error policies: `s0`, at LOD 0 (unused by the thesis).
    pub b: f64,
    /// Distance from the eye to the block (`|eye − centre| − radius`).
    pub dist: f64,
    /// Pixels per metre at that distance (at least the near distance):
    /// [`crate::importance::ScreenError::scale`], for the drawn block's
    /// error and area ([`Refiner::drawn_error`], [`Refiner::drawn_area`]).
    pub scale: f64,
}

/// A leaf's decisions for one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LeafDecision {
    /// The LOD the selection wants (0 full resolution, 1 first LOD).
    pub lod: u8,
    /// Load LOD 0 (the block has LOD 1 only and wants LOD 0).
    pub load: bool,
    /// Split (the block has LOD 0 and wants its children).
    pub split: bool,
    /// The value reported as [`crate::DrawBlock::importance`]: the
    /// thesis's importance, or for the other policies the screen-space
    /// error of the first LOD in pixels.
    pub importance: f64,
}

/// Which tree a node belongs to: elevation errors are metres, colour
/// errors are 8-bit steps and refine by texel size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Elevation.
    Elevation,
    /// Colour.
    Colour,
}

/// The per-frame refinement test and request order of a policy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refiner {
    policy: Policy,
    tol: f64,
    qf: f64,
    imp: Importance,
    sse: ScreenError,
    near: f64,
    height: f64,
    max_area: f64,
    eye: DVec3,
    eye_len: f64,
    forward: DVec3,
}

impl Refiner {
    /// For `policy` in `view`, with quality factor `qf` (thesis) and pixel
    /// tolerance `max_sse` (the others; non-finite or non-positive values
    /// fall back to [`DEFAULT_MAX_SSE_PX`]).
    pub fn new(policy: Policy, view: &View, qf: f64, max_sse: f64) -> Refiner {
        let f = view.camera.forward;
        let forward = if f.length_squared() > 0.0 && f.is_finite() {
            f.normalize()
        } else {
            DVec3::ZERO
        };
        Refiner {
            policy,
            tol: sanitize_tolerance(max_sse),
            qf,
            imp: Importance::new(qf),
            sse: ScreenError::new(view.camera.viewport_height_px, view.camera.fov_y),
            near: if view.near.is_finite() {
                view.near.max(0.0)
            } else {
                0.0
            },
            height: if view.camera.viewport_height_px > 0.0 {
                view.camera.viewport_height_px
            } else {
                f64::INFINITY
            },
            max_area: {
                let c = &view.camera;
                let a = c.viewport_height_px * c.viewport_height_px * c.aspect;
                if a > 0.0 && a.is_finite() {
                    a
                } else {
                    f64::INFINITY
                }
            },
            eye: view.camera.eye,
            eye_len: view.camera.eye.length(),
            forward,
        }
    }

    /// The policy.
    pub fn policy(&self) -> Policy {
        self.policy
    }

    /// The eye this refiner measures from.
    pub fn eye(&self) -> DVec3 {
        self.eye
    }

    /// The pixel tolerance.
    pub fn tolerance(&self) -> f64 {
        self.tol
    }

    /// Bit patterns of everything besides the node that [`Refiner::measure`]
    /// depends on (for memoisation).
    pub fn memo_key(&self) -> [u64; 4] {
        [
            self.tol.to_bits(),
            self.near.to_bits(),
            self.policy as u64,
            self.qf.to_bits(),
        ]
    }

    /// The node's memoisable measure. `width` is the tree's block width,
    /// `err1` / `err0` the block's errors at LOD 1 and LOD 0.
    pub fn measure(&self, kind: Kind, fp: &Footprint, width: f64, err1: f64, err0: f64) -> Measure {
        let radius = fp.radius;
        match self.policy {
            Policy::Thesis => {
                let dist = (self.eye - fp.centre).length() - radius;
                Measure {
                    a: self.imp.of(dist, radius, width),
                    b: 0.0,
                    dist,
                    scale: self.sse.scale(dist.max(self.near)),
                }
            }
            _ => {
                let dist = fp.distance_from(self.eye, self.eye_len);
                let k = self.sse.scale(dist.max(self.near));
                let (s1, s0) = match kind {
                    Kind::Elevation => (self.sse.apply(err1, k), self.sse.apply(err0, k)),
                    Kind::Colour => {
                        // Where the LOD adds any colour.
                        let (texel1, texel0) = texel_sizes(radius, width);
                        (
                            if err1 > 0.0 {
                                self.sse.apply(texel1, k)
                            } else {
                                0.0
                            },
                            if err0 > 0.0 {
                                self.sse.apply(texel0, k)
                            } else {
                                0.0
                            },
                        )
                    }
                };
                Measure {
                    a: s1,
                    b: s0,
                    dist,
                    scale: k,
                }
            }
        }
    }

    /// The near distance, below which distances count as it
    /// ([`ScreenError::scale`] of `max(d, near)`).
    pub fn near(&self) -> f64 {
        self.near
    }

    /// The distance at which `error` metres project to `px` pixels
    /// ([`ScreenError::distance_for`], the error's formula solved for the
    /// distance), where it is finite and above the millimetre below which
    /// [`ScreenError::scale`] clamps. `None` for the thesis's importance,
    /// which is no error.
    fn threshold_distance(&self, error: f64, px: f64) -> Option<f64> {
        if self.policy == Policy::Thesis {
            return None;
        }
        let d = self.sse.distance_for(error, px);
        (d.is_finite() && d > 1e-3).then_some(d)
    }

    /// Whether the block of footprint `fp` is surely closer than the
    /// threshold distance `d` ([`Footprint::upper_distance`] below it, and
    /// the near distance too): `Some((within, slack))`, where `within` is
    /// `d` shrunk by 10⁻⁹ of itself (far more than the rounding of the
    /// error's forward formula) and `slack = within − upper` is how far
    /// the eye may move before that can change, while the near distance
    /// stays below `within`.
    fn stays_closer(&self, fp: &Footprint, d: f64) -> Option<(f64, f64)> {
        let within = d * (1.0 - 1e-9);
        let upper = fp.upper_distance(self.eye);
        // NaN compares false: measured.
        (upper < within && self.near < within).then_some((within, within - upper))
    }

    /// Whether the block of footprint `fp` is surely farther than the
    /// threshold distance `d` ([`Footprint::ball_distance`] above it, grown
    /// by 10⁻⁹; the near distance only raises the distance that counts):
    /// `Some((∞, slack))` as for [`Refiner::stays_closer`].
    fn stays_farther(&self, fp: &Footprint, d: f64) -> Option<(f64, f64)> {
        let beyond = d * (1.0 + 1e-9);
        let ball = fp.ball_distance(self.eye);
        // NaN compares false: measured.
        (ball > beyond).then_some((f64::INFINITY, ball - beyond))
    }

    /// Whether a split block of footprint `fp` surely keeps its children,
    /// decided without its full measure: `Some((within, slack))` while it
    /// is closer than the distance at which its first LOD's error falls to
    /// [`MERGE_AT`] of the tolerance, so that [`Refiner::merge`] declines
    /// (`stays_closer`). Its first LOD's error is `err1` metres
    /// (elevation) or, for colour (`err1 > 0`: finer colour exists), its
    /// texels at its first LOD (`texel_sizes`). `None` means "measure it"
    /// (no error, the thesis's importance, or no finite distance).
    pub fn keep_slack(
        &self,
        kind: Kind,
        fp: &Footprint,
        width: f64,
        err1: f64,
    ) -> Option<(f64, f64)> {
        let error = match kind {
            Kind::Elevation => err1,
            Kind::Colour if err1 > 0.0 => texel_sizes(fp.radius, width).0,
            Kind::Colour => return None,
        };
        self.stays_closer(fp, self.threshold_distance(error, self.tol * MERGE_AT)?)
    }

    /// For a colour leaf at its finest (LOD 0 loaded, no children to split
    /// into), drawn at `lod` now: the only thing [`Refiner::leaf`] decides
    /// for it is that LOD, by one threshold on its distance (LOD 0 while
    /// its first LOD's texels project above [`KEEP_LOD0`] of the
    /// tolerance). `Some((within, slack))` when that LOD surely stays
    /// while the eye moves less than `slack` and the near distance stays
    /// below `within`: drawn at LOD 1, `stays_farther`; at LOD
    /// 0, `stays_closer`. `None`: measure it.
    pub fn finest_colour_slack(
        &self,
        fp: &Footprint,
        width: f64,
        err1: f64,
        lod: u8,
    ) -> Option<(f64, f64)> {
        if self.policy == Policy::Thesis {
            return None;
        }
        if err1 <= 0.0 {
            // No finer colour: no error at its first LOD, drawn there.
            return (lod == 1).then_some((f64::INFINITY, f64::INFINITY));
        }
        let texel1 = texel_sizes(fp.radius, width).0;
        let d = self.threshold_distance(texel1, self.tol * KEEP_LOD0.min(1.0))?;
        if lod == 1 {
            self.stays_farther(fp, d)
        } else {
            self.stays_closer(fp, d)
        }
    }

    /// Whether a split block whose measure is `m` should merge, and the
    /// operation's priority.
    pub fn merge(&self, m: &Measure) -> Option<f64> {
        match self.policy {
            Policy::Thesis => wants_merge(m.a).then_some(m.a),
            _ => (m.a <= self.tol * MERGE_AT).then_some(-m.a),
        }
    }

    /// A leaf's decisions; `lod` is the best LOD it has (0 or 1).
    pub fn leaf(&self, m: &Measure, lod: u8) -> LeafDecision {
        match self.policy {
            Policy::Thesis => {
                let sel = selected_lod(m.a);
                LeafDecision {
                    lod: sel,
                    load: sel < lod,
                    split: sel >= lod && wants_split(m.a),
                    importance: m.a,
                }
            }
            _ => {
                let (s1, s0) = (m.a, m.b);
                let want0 = s1 > self.tol || (lod == 0 && s1 > self.tol * KEEP_LOD0);
                let sel = u8::from(!want0);
                LeafDecision {
                    lod: sel,
                    load: lod == 1 && s1 > self.tol,
                    split: lod == 0 && s0 > self.tol,
                    importance: s1,
                }
            }
        }
    }

    /// Whether a leaf with LOD `lod` whose measure here is `m` may want its
    /// LOD 0 or its children in the view of `ahead`, whose eye is `moved`
    /// metres from this one's: a cheap test, never false where
    /// [`Refiner::leaf`] at `ahead` would load or split. The footprint's
    /// distance is 1-Lipschitz in the eye ([`Footprint::distance`]), so
    /// there it is at least `m.dist − moved`, and the error that decides
    /// (`s1` to load, `s0` to split) grows at most by the ratio of the
    /// scales. Only for the screen-space policies (`true` for the
    /// thesis's, whose measure is no error).
    pub fn may_want_ahead(&self, ahead: &Refiner, moved: f64, m: &Measure, lod: u8) -> bool {
        if self.policy == Policy::Thesis || ahead.policy == Policy::Thesis {
            return true;
        }
        let now = if lod == 0 { m.b } else { m.a };
        // A margin for rounding, and for the eye's own rounding.
        let nearer = m.dist - moved - 1e-9 * (m.dist.abs() + moved) - 1e-6;
        // now · (scale there / scale here) > tol there, without dividing;
        // NaN (an unusable measure) counts as "may".
        let bound = now * ahead.sse.scale(nearer.max(ahead.near)) * (1.0 + 1e-9);
        let against = ahead.tol * m.scale;
        bound.is_nan() || against.is_nan() || bound > against
    }

    /// Whether a leaf with LOD `lod` and bounds `b` still needs its LOD 0
    /// by this refiner (the view predicted for the answer's arrival), at
    /// the distance of its ball, a lower bound of its footprint's: a request
    /// is dropped only when even that says it is not needed.
    pub fn loads_at_arrival(
        &self,
        kind: Kind,
        b: &BlockBounds,
        width: f64,
        err1: f64,
        lod: u8,
    ) -> bool {
        let m = self.measure(kind, &Footprint::ball(b), width, err1, 0.0);
        self.leaf(&m, lod).load
    }

    /// Priority (higher first) of loading LOD 0 of a leaf of tree `kind`
    /// with LOD `lod`, at `level`, centred at `centre`, whose record is
    /// `size` bytes.
    pub fn load_priority(
        &self,
        kind: Kind,
        m: &Measure,
        lod: u8,
        level: u8,
        centre: DVec3,
        size: u32,
    ) -> f64 {
        match self.policy {
            Policy::Thesis => refine_importance(lod, m.a),
            Policy::Ours => {
                let weight = match kind {
                    Kind::Elevation => 1.0,
                    Kind::Colour => COLOUR_DISPLACEMENT,
                };
                let gain = weight * (m.a - m.b).max(m.a * 1e-3);
                let p = gain / (size as f64 + REQUEST_OVERHEAD);
                if p.is_finite() {
                    p
                } else {
                    f64::MAX
                }
            }
            Policy::Cesium => self.cesium(m, centre),
            Policy::Breadth => breadth(m, level),
        }
    }

    /// Priority (higher first) of splitting a leaf (also given to the loads
    /// a split forces on its neighbours, §4.3.3).
    pub fn split_priority(&self, m: &Measure, level: u8, centre: DVec3) -> f64 {
        match self.policy {
            Policy::Thesis => split_importance(m.a),
            Policy::Ours => m.b,
            Policy::Cesium => self.cesium(m, centre),
            Policy::Breadth => breadth(m, level),
        }
    }

    /// CesiumJS `computeTileLoadPriority`: `(1 − dir·forward)·distance`,
    /// smaller sooner, negated here (higher first).
    fn cesium(&self, m: &Measure, centre: DVec3) -> f64 {
        let to = centre - self.eye;
        let len = to.length();
        if len.is_nan() || len <= 1e-5 || !len.is_finite() {
            return 0.0;
        }
        let cos = (to / len).dot(self.forward);
        let p = (1.0 - cos) * m.dist.max(0.0);
        if p.is_finite() {
            -p
        } else {
            f64::MIN
        }
    }

    /// Approximate screen area in pixels of a block of footprint radius
    /// `radius` at distance `dist`: `(√2·radius·H / (2·d·tan(fov/2)))²`, at
    /// most the viewport's area.
    pub fn screen_area(&self, radius: f64, dist: f64) -> f64 {
        self.area_at(radius, self.sse.scale(dist.max(self.near)))
    }

    /// [`Refiner::screen_area`] of a block of footprint radius `radius`
    /// at the measure's distance.
    pub fn drawn_area(&self, m: &Measure, radius: f64) -> f64 {
        self.area_at(radius, m.scale)
    }

    fn area_at(&self, radius: f64, scale: f64) -> f64 {
        let side = self.sse.apply(radius * std::f64::consts::SQRT_2, scale);
        (side * side).min(self.max_area)
    }

    /// The screen-space error in pixels of `error` metres at the measure's
    /// distance, capped at the viewport height: the figure reported for
    /// drawn blocks (an error larger than the screen is the whole screen
    /// wrong; uncapped, the first frames of a cold start near the ground,
    /// with the eye inside the bounds of the roots, report millions of
    /// pixels and would outweigh the rest of any flight in an integral).
    pub fn screen_error(&self, error: f64, dist: f64) -> f64 {
        self.sse.of(error, dist.max(self.near)).min(self.height)
    }

    /// [`Refiner::screen_error`] of `error` metres at the measure's
    /// distance.
    pub fn drawn_error(&self, m: &Measure, error: f64) -> f64 {
        self.sse.apply(error, m.scale).min(self.height)
    }

    /// The projected texel size in pixels of a colour block drawn at
    /// `lod`, from its [`Kind::Colour`] measure: its first LOD's texels
    /// (`m.a`) or its own (`m.b`), 0 where no finer colour exists to load
    /// (the measure's convention), capped at the viewport height as
    /// [`Refiner::drawn_error`] is. The colour half of the rendered error,
    /// which the colour refinement test holds to the tolerance. Meaningful
    /// for the screen-space policies (not [`Policy::Thesis`], whose measure
    /// is an importance).
    pub fn drawn_texel(&self, m: &Measure, lod: u8) -> f64 {
        let t = if lod == 0 { m.b } else { m.a };
        t.min(self.height)
    }
}

/// The size in metres of a colour block's texels at its first LOD and at
/// LOD 0: the footprint's side (`radius·√2`) over the texels across it
/// (`width / 2`, `width`).
fn texel_sizes(radius: f64, width: f64) -> (f64, f64) {
    let side = radius.max(0.0) * std::f64::consts::SQRT_2;
    (side / (width * 0.5).max(1.0), side / width.max(1.0))
}

/// Level first, then nearest: `−(level·10¹³ + distance)`.
fn breadth(m: &Measure, level: u8) -> f64 {
    let d = if m.dist.is_finite() {
        m.dist.clamp(0.0, 1e12)
    } else {
        1e12
    };
    -(level as f64 * 1e13 + d)
}

/// The priority of a load or split that only the view predicted for its
/// answer's arrival wants (a prefetch, [`crate::ClientConfig::prefetch`])
/// from its priority `p` there: below every load and split the present view
/// wants (theirs are positive in the screen-space policies), in the order
/// of `p`.
pub fn ahead_priority(p: f64) -> f64 {
    -1.0 / (1.0 + p.max(0.0))
}

/// A usable pixel tolerance.
pub fn sanitize_tolerance(max_sse: f64) -> f64 {
    if max_sse.is_finite() && max_sse > 0.0 {
        max_sse
    } else {
        DEFAULT_MAX_SSE_PX
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::visibility::Camera;
    use proptest::prelude::*;

    /// A footprint with only its ball (no cone, no top).
    fn ball(centre: DVec3, radius: f64) -> Footprint {
        Footprint {
            centre,
            radius,
            sphere_radius: radius,
            axis: DVec3::Z,
            half_angle: std::f64::consts::PI,
            cos_half: -1.0,
            sin_half: 0.0,
            r_top: f64::MAX,
            edges: [NO_HALF_SPACE; 4],
        }
    }

    fn view(eye: DVec3, fov_deg: f64) -> View {
        let mut c = Camera::look_at(eye, DVec3::ZERO, DVec3::Z);
        c.fov_y = fov_deg.to_radians();
        View::new(&c, 6.3e6, 6.4e6)
    }

    #[test]
    fn names_round_trip() {
        for p in Policy::ALL {
            assert_eq!(p.name().parse::<Policy>(), Ok(p));
        }
        assert!("cesiumjs".parse::<Policy>().is_err());
    }

    #[test]
    fn flat_block_never_refined_cliff_always() {
        let v = view(DVec3::new(6.4e6, 0.0, 0.0), 60.0);
        let r = Refiner::new(Policy::Ours, &v, 1e4, 1.0);
        let c = DVec3::new(6.37e6, 0.0, 0.0);
        // Flat: no error at either LOD, a metre away.
        let flat = r.measure(Kind::Elevation, &ball(c, 1000.0), 64.0, 0.0, 0.0);
        let d = r.leaf(&flat, 1);
        assert!(!d.load && d.lod == 1);
        assert!(!r.leaf(&flat, 0).split);
        // A cliff: 100 m of error 30 km away is ~3 px at 1080 px, 60°.
        let cliff = r.measure(Kind::Elevation, &ball(c, 1000.0), 64.0, 100.0, 50.0);
        assert!(r.leaf(&cliff, 1).load);
        assert!(r.leaf(&cliff, 0).split);
        assert!(r.merge(&cliff).is_none());
    }

    proptest! {
        /// Below tolerance: no load and no split; above: always, at every
        /// distance, FOV and tolerance, the eye inside the planet included.
        #[test]
        fn threshold_is_the_tolerance(
            x in -1e10f64..1e10, fov in 1.0f64..170.0, tol in 0.1f64..16.0,
            e1 in 0.0f64..1e4, e0 in 0.0f64..1e4, radius in 1.0f64..5e6,
        ) {
            let v = view(DVec3::new(x.abs().max(1.0), 1.0, 0.0), fov);
            let r = Refiner::new(Policy::Ours, &v, 1e4, tol);
            let c = DVec3::new(6.37e6, 0.0, 0.0);
            let m = r.measure(Kind::Elevation, &ball(c, radius), 64.0, e1, e0);
            prop_assert!(m.a.is_finite() && m.b.is_finite() && m.a >= 0.0 && m.b >= 0.0);
            let d1 = r.leaf(&m, 1);
            prop_assert_eq!(d1.load, m.a > tol);
            prop_assert!(!d1.split);
            let d0 = r.leaf(&m, 0);
            prop_assert_eq!(d0.split, m.b > tol);
            prop_assert!(!d0.load);
            if e1 * 1e-9 > 0.0 && m.a > 0.0 {
                prop_assert!(d1.importance.is_finite());
            }
            for p in Policy::ALL {
                let r = Refiner::new(p, &v, 1e4, tol);
                let m = r.measure(Kind::Elevation, &ball(c, radius), 64.0, e1, e0);
                prop_assert!(r.load_priority(Kind::Elevation, &m, 1, 10, c, 3000).is_finite());
                prop_assert!(r.split_priority(&m, 10, c).is_finite());
            }
        }

        /// The drawn block's error and area from the measure's scale are
        /// those of the distance (one formula), finite and capped, for every
        /// policy, from inside the planet to 1000 Earth radii, 1° to 170°.
        #[test]
        fn drawn_error_is_the_distance_error(
            x in -6.4e9f64..6.4e9, fov in 1.0f64..170.0, e in 0.0f64..1e4,
            radius in 1.0f64..5e6,
        ) {
            let v = view(DVec3::new(x, 1.0, 0.0), fov);
            let c = DVec3::new(6.37e6, 0.0, 0.0);
            for p in Policy::ALL {
                let r = Refiner::new(p, &v, 1e4, 1.0);
                let m = r.measure(Kind::Elevation, &ball(c, radius), 64.0, e, e);
                let (a, b) = (r.drawn_error(&m, e), r.screen_error(e, m.dist));
                prop_assert!((0.0..=1080.0).contains(&a));
                prop_assert!((a - b).abs() <= 1e-12 * b.max(1.0), "{a} {b}");
                let (a, b) = (r.drawn_area(&m, radius), r.screen_area(radius, m.dist));
                prop_assert!(a.is_finite() && a >= 0.0);
                prop_assert!((a - b).abs() <= 1e-12 * b.max(1.0), "{a} {b}");
            }
        }

        /// The screen-space error falls with distance (monotone) and rises
        /// with error, from 1 m to 1000 Earth radii.
        #[test]
        fn sse_monotone(a in 1.0f64..6.4e9, b in 1.0f64..6.4e9, e in 0.0f64..1e4) {
            let v = view(DVec3::new(6.4e9, 0.0, 0.0), 60.0);
            let r = Refiner::new(Policy::Ours, &v, 1e4, 1.0);
            let (near, far) = if a <= b { (a, b) } else { (b, a) };
            prop_assert!(r.screen_error(e, near) >= r.screen_error(e, far));
            prop_assert!(r.screen_error(e + 1.0, near) >= r.screen_error(e, near));
        }
    }

    /// The distance from `eye` to a `(k + 1)²` grid of the block's surface
    /// points at each of `heights` (brute force, for the bound's tests).
    fn surface_distance(
        datum: &planet_core::Datum,
        id: planet_core::BlockId,
        heights: &[f64],
        k: usize,
        eye: DVec3,
    ) -> f64 {
        let (s0, t0, s1, t1) = id.extent();
        let mut min = f64::INFINITY;
        for j in 0..=k {
            for i in 0..=k {
                let fc = planet_core::cube::FaceCoord {
                    face: id.face,
                    s: s0 + (s1 - s0) * i as f64 / k as f64,
                    t: t0 + (t1 - t0) * j as f64 / k as f64,
                };
                let u = fc.direction();
                for &h in heights {
                    min = min.min((eye - DVec3::from_array(datum.position(u, h))).length());
                }
            }
        }
        min
    }

    proptest! {
        /// The footprint distance is a lower bound of the distance to the
        /// block's surface (a dense grid of its points at random heights in
        /// its range), and not looser than the bounding ball, for blocks at
        /// every level, on cube edges and corners and at the poles, and eyes
        /// from inside the planet to 1000 Earth radii.
        #[test]
        fn footprint_distance_is_a_lower_bound(
            face in 0u8..6, level in 0u8..16, fx in 0.0f64..1.0, fy in 0.0f64..1.0,
            h0 in -11_000.0f64..9_000.0, dh in 0.0f64..9_000.0,
            dir in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
            alt_log in -1.0f64..9.8, below in proptest::bool::ANY,
            near_block in proptest::bool::ANY,
        ) {
            use planet_core::cube::FaceCoord;
            use planet_core::{BlockId, Datum, Face};
            let datum = Datum::WGS84;
            let n = 1u32 << level;
            let (x, y) = (((fx * n as f64) as u32).min(n - 1), ((fy * n as f64) as u32).min(n - 1));
            let id = BlockId::new(Face::new(face).expect("face"), level, x, y).expect("id");
            let b = BlockBounds::new(&datum, id, h0, h0 + dh);
            let fp = Footprint::of(&b);
            // The eye: near the block (above, beside or below it) or anywhere.
            let d = if near_block {
                let (s0, t0, s1, t1) = id.extent();
                let fc = FaceCoord { face: id.face, s: s0 + (s1 - s0) * fx, t: t0 + (t1 - t0) * fy };
                DVec3::from_array(fc.direction()) + DVec3::new(dir.0, dir.1, dir.2) * ((s1 - s0) * 2.0)
            } else {
                DVec3::new(dir.0, dir.1, dir.2)
            };
            let d = if d.length() < 1e-6 { DVec3::X } else { d.normalize() };
            let r = datum.equatorial_radius();
            let alt = 10f64.powf(alt_log);
            let eye = d * if below { (r - alt).max(0.0) } else { r + alt };
            let dist = fp.distance(eye);
            prop_assert!(!dist.is_nan());
            prop_assert!(dist >= (eye - b.centre).length() - b.sphere_radius - 1e-6);
            // The upper bound Refiner::keep_slack relies on.
            let upper = fp.upper_distance(eye);
            prop_assert!(dist <= upper * (1.0 + 1e-12), "{dist} > {upper}");
            let min = surface_distance(&datum, id, &[h0, h0 + dh * 0.5, h0 + dh], 24, eye);
            // A millimetre of slack per 10 000 km for rounding.
            prop_assert!(dist <= min + 1e-3 + min * 1e-10, "{} > {} at {:?}", dist, min, id);
        }
    }

    /// A block's footprint (heights −400 to 2000 m) and an eye above it,
    /// with the screen-space policy's refiner at any eye (looking at the
    /// planet's centre): the cases of the keeping tests.
    #[derive(Debug, Clone)]
    struct KeepCase {
        fp: Footprint,
        eye: DVec3,
        fov_deg: f64,
        tol: f64,
    }

    impl KeepCase {
        /// The block at `(fx, fy)` of a face at `level`; the eye in
        /// direction `dir`, `10^alt_log` m above the equatorial radius; the
        /// tolerance `10^tol_log` px.
        fn new(
            face: u8,
            level: u8,
            (fx, fy): (f64, f64),
            dir: (f64, f64, f64),
            alt_log: f64,
            fov_deg: f64,
            tol_log: f64,
        ) -> KeepCase {
            use planet_core::{BlockId, Datum, Face};
            let datum = Datum::WGS84;
            let n = 1u32 << level;
            let (x, y) = (
                ((fx * n as f64) as u32).min(n - 1),
                ((fy * n as f64) as u32).min(n - 1),
            );
            let id = BlockId::new(Face::new(face).expect("face"), level, x, y).expect("id");
            let d = DVec3::new(dir.0, dir.1, dir.2);
            let d = if d.length() < 1e-6 {
                DVec3::X
            } else {
                d.normalize()
            };
            KeepCase {
                fp: Footprint::of(&BlockBounds::new(&datum, id, -400.0, 2000.0)),
                eye: d * (datum.equatorial_radius() + 10f64.powf(alt_log)),
                fov_deg,
                tol: 10f64.powf(tol_log),
            }
        }

        fn refiner(&self, eye: DVec3) -> Refiner {
            let mut c = Camera::look_at(eye, DVec3::ZERO, DVec3::Z);
            c.fov_y = self.fov_deg.to_radians();
            Refiner::new(Policy::Ours, &View::new(&c, 6.35e6, 6.38e6), 1e4, self.tol)
        }

        /// The eye moved along `(x, y, z)` by the fraction `f` of `slack`
        /// (less 10⁻⁶ of it).
        fn moved(&self, (x, y, z, f): (f64, f64, f64, f64), slack: f64) -> DVec3 {
            let s = DVec3::new(x, y, z);
            let s = if s.length() < 1e-6 {
                DVec3::X
            } else {
                s.normalize()
            };
            self.eye + s * (slack * f * (1.0 - 1e-6))
        }
    }

    prop_compose! {
        /// A [`KeepCase`]: blocks at every level, on cube edges and corners
        /// and at the poles; eyes from 1 m to 1000 Earth radii from the
        /// surface; tolerances from 0.01 to 100 px; fields of view from 1°
        /// to 170°.
        fn keep_case()(
            face in 0u8..6, level in 0u8..16, fx in 0.0f64..1.0, fy in 0.0f64..1.0,
            dir in (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0),
            alt_log in 0.0f64..10.0, tol_log in -2.0f64..2.0, fov in 1.0f64..170.0,
        ) -> KeepCase {
            KeepCase::new(face, level, (fx, fy), dir, alt_log, fov, tol_log)
        }
    }

    /// A direction and a fraction for [`KeepCase::moved`].
    fn eye_step() -> impl Strategy<Value = (f64, f64, f64, f64)> {
        (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0, 0.0f64..1.0)
    }

    proptest! {
        /// A split block that [`Refiner::keep_slack`] keeps is not
        /// merged by its measure, at the eye it was asked at and at any eye
        /// within the slack `within − upper` of it (what the selector's
        /// odometer relies on), for both kinds, blocks at every level,
        /// tolerances from 0.01 to 100 px, fields of view from 1° to 170°
        /// and eyes from 1 m to 1000 Earth radii from the surface.
        #[test]
        fn surely_kept_splits_do_not_merge(
            k in keep_case(), step in eye_step(),
            err_log in -3.0f64..4.0, colour in proptest::bool::ANY,
        ) {
            let fp = &k.fp;
            let (kind, width) = if colour { (Kind::Colour, 256.0) } else { (Kind::Elevation, 64.0) };
            let err1 = 10f64.powf(err_log);
            let r = k.refiner(k.eye);
            if let Some((within, slack)) = r.keep_slack(kind, fp, width, err1) {
                prop_assert_eq!(r.merge(&r.measure(kind, fp, width, err1, 0.0)), None);
                // An eye moved by less than the slack.
                let moved = k.refiner(k.moved(step, slack));
                if moved.near() < within {
                    prop_assert_eq!(moved.merge(&moved.measure(kind, fp, width, err1, 0.0)), None);
                }
            }
        }

        /// A colour leaf at its finest keeps the LOD it is drawn at now
        /// ([`Refiner::leaf`]) at any eye within the slack of
        /// [`Refiner::finest_colour_slack`] (with the near distance below
        /// its bound), at LOD 0 and at LOD 1, for blocks at every level,
        /// tolerances from 0.01 to 100 px, fields of view from 1° to 170°
        /// and eyes from 1 m to 1000 Earth radii from the surface.
        #[test]
        fn finest_colour_leaves_keep_their_lod_within_the_slack(
            k in keep_case(), step in eye_step(),
            width_log in 2u32..9, no_finer in proptest::bool::weighted(0.1),
        ) {
            let width = f64::from(1u32 << width_log);
            let err1 = if no_finer { 0.0 } else { 1.0 };
            let lod_at = |r: &Refiner| r.leaf(&r.measure(Kind::Colour, &k.fp, width, err1, 0.0), 0).lod;
            let r = k.refiner(k.eye);
            let lod = lod_at(&r);
            if let Some((within, slack)) = r.finest_colour_slack(&k.fp, width, err1, lod) {
                let moved = k.refiner(k.moved(step, slack.min(1e12)));
                if moved.near() < within {
                    prop_assert_eq!(lod_at(&moved), lod, "slack {}", slack);
                }
            }
        }
    }

    /// A level-1 block seen from beside it, inside its cone of directions
    /// (25° from its axis against the cone's 32°; the eye of circle-rainier
    /// 3 km above the ground): the cone alone says the eye is inside
    /// (distance ≤ 0, the error capped at the screen's height over the
    /// whole screen); its edges' half-spaces give 663 km, within 1 % of
    /// the distance to its surface and below it.
    #[test]
    fn footprint_sees_a_coarse_block_beside_the_eye() {
        use planet_core::{BlockId, Datum, Face};
        let datum = Datum::WGS84;
        let id = BlockId::new(Face::new(1).expect("face"), 1, 0, 1).expect("id");
        let b = BlockBounds::new(&datum, id, -500.0, 4400.0);
        let fp = Footprint::of(&b);
        let eye = DVec3::new(-2_309_007.9, -3_717_774.2, 4_631_327.1);
        let theta = fp.axis.dot(eye.normalize()).acos();
        let cone_only = Footprint {
            edges: [NO_HALF_SPACE; 4],
            ..fp
        };
        assert!(theta < fp.half_angle);
        assert!(
            cone_only.distance(eye) <= 0.0,
            "{}",
            cone_only.distance(eye)
        );
        let d = fp.distance(eye);
        let min = surface_distance(&datum, id, &[-500.0, 4400.0], 400, eye);
        assert!(d > 0.99 * min && d <= min, "{d} against {min}");
    }

    #[test]
    fn footprint_sees_blocks_from_above_and_aside() {
        use planet_core::{BlockId, Datum, Face};
        let datum = Datum::WGS84;
        // A 10 km block, the eye 500 m above its top: the ball says "inside".
        let id = BlockId::new(Face::new(0).expect("face"), 10, 300, 700).expect("id");
        let b = BlockBounds::new(&datum, id, 0.0, 1000.0);
        let fp = Footprint::of(&b);
        let top = b.points.iter().map(|p| p.length()).fold(0.0, f64::max);
        let eye = b.centre.normalize() * (top + 500.0);
        assert!((eye - b.centre).length() - b.sphere_radius < 0.0);
        let d = fp.distance(eye);
        assert!((d - 500.0).abs() < 1.0, "{d}");
        // 50 km aside at ground level: tens of kilometres, not zero.
        let (s0, t0, s1, t1) = id.extent();
        let fc = planet_core::cube::FaceCoord {
            face: id.face,
            s: s1 + (s1 - s0) * 5.0,
            t: (t0 + t1) * 0.5,
        };
        let eye = DVec3::from_array(datum.position(fc.direction(), 500.0));
        let d = fp.distance(eye);
        assert!(d > 30_000.0 && d < 50_000.0, "{d}");
    }

    #[test]
    fn hysteresis_keeps_lod0_and_delays_merge() {
        let v = view(DVec3::new(6.4e6, 0.0, 0.0), 60.0);
        let r = Refiner::new(Policy::Ours, &v, 1e4, 1.0);
        let m = Measure {
            a: 0.7,
            b: 0.2,
            dist: 1e3,
            scale: 1.0,
        };
        assert_eq!(r.leaf(&m, 1).lod, 1);
        assert_eq!(r.leaf(&m, 0).lod, 0);
        assert!(r.merge(&m).is_none());
        let far = Measure { a: 0.2, ..m };
        assert!(r.merge(&far).is_some());
    }

    #[test]
    fn colour_refines_by_texel_size_only_where_it_adds_colour() {
        let v = view(DVec3::new(6.4e6, 0.0, 0.0), 60.0);
        let r = Refiner::new(Policy::Ours, &v, 1e4, 1.0);
        let c = DVec3::new(6.37e6, 0.0, 0.0);
        // 100 km block, 128 texels, 30 km away: texels of ~1.1 km, many px.
        let m = r.measure(Kind::Colour, &ball(c, 7.07e4), 128.0, 5.0, 5.0);
        assert!(r.leaf(&m, 1).load);
        let uniform = r.measure(Kind::Colour, &ball(c, 7.07e4), 128.0, 0.0, 0.0);
        assert!(!r.leaf(&uniform, 1).load);
    }

    #[test]
    fn colour_gain_counts_as_half_a_texel_of_displacement() {
        let v = view(DVec3::new(6.4e6, 0.0, 0.0), 60.0);
        let r = Refiner::new(Policy::Ours, &v, 1e4, 1.0);
        let c = DVec3::new(6.37e6, 0.0, 0.0);
        let m = Measure {
            a: 4.0,
            b: 2.0,
            dist: 3e4,
            scale: 1.0,
        };
        let e = r.load_priority(Kind::Elevation, &m, 1, 5, c, 4000);
        let col = r.load_priority(Kind::Colour, &m, 1, 5, c, 4000);
        // The same pixels and bytes: the elevation record first, the colour
        // one at half its priority, and ahead of it again once its texels
        // shrink by more than twice the elevation's error.
        assert!(e > col, "{e} {col}");
        assert!((col / e - COLOUR_DISPLACEMENT).abs() < 1e-12);
        let blurry = Measure {
            a: 10.0,
            b: 5.0,
            ..m
        };
        assert!(r.load_priority(Kind::Colour, &blurry, 1, 5, c, 4000) > e);
        // The other policies do not tell the trees apart.
        let ces = Refiner::new(Policy::Cesium, &v, 1e4, 1.0);
        assert_eq!(
            ces.load_priority(Kind::Elevation, &m, 1, 5, c, 4000),
            ces.load_priority(Kind::Colour, &m, 1, 5, c, 4000)
        );
    }

    #[test]
    fn cesium_prefers_tiles_ahead_and_near() {
        let v = view(DVec3::new(7e6, 0.0, 0.0), 60.0);
        let r = Refiner::new(Policy::Cesium, &v, 1e4, 2.0);
        let ahead = DVec3::new(6.4e6, 0.0, 0.0);
        let aside = DVec3::new(6.4e6, 3e5, 0.0);
        let ma = r.measure(Kind::Elevation, &ball(ahead, 1e3), 64.0, 10.0, 5.0);
        let ms = r.measure(Kind::Elevation, &ball(aside, 1e3), 64.0, 10.0, 5.0);
        assert!(
            r.load_priority(Kind::Elevation, &ma, 1, 5, ahead, 100)
                > r.load_priority(Kind::Elevation, &ms, 1, 5, aside, 100)
        );
        let b = Refiner::new(Policy::Breadth, &v, 1e4, 2.0);
        assert!(
            b.load_priority(Kind::Elevation, &ma, 1, 9, ahead, 100)
                < b.load_priority(Kind::Elevation, &ms, 1, 5, aside, 100)
        );
    }
}
