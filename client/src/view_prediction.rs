//! Where the camera will be when a request's answer is applied.
//!
//! Beyond the thesis (§3.5.2 ranks requests by the *current* view; the
//! papers' "relevant data" is the share of received bytes used for rendering
//! on arrival, docs/REFERENCES.md). A response is applied a round trip, its
//! transfer time and one decode after the request: at 1 Mbit/s with a queue
//! of 16 that is half a second, in which a descending or flying camera leaves
//! behind the blocks at the border of its view. Those answers arrive for
//! blocks no longer drawn and are irrelevant bytes.
//!
//! The predictor extrapolates the camera linearly (eye and view direction,
//! per frame) over the measured request latency in frames: an exponential
//! moving average of the frames from send to the frame that applies the
//! answer (after its decode), plus two moving mean deviations of it (RFC
//! 6298's RTTVAR), so that most answers land before the predicted view. The
//! client requests a visible block only if it is visible in the predicted
//! view as well (a colour block: one of the elevation leaves it textures,
//! [`crate::tree::LinkedTree::leaves_in_view`]), and in the view half a
//! horizon further ([`ViewPredictor::predict_stay`]): a block at the border
//! of a view the camera is leaving is in view at the arrival by a few
//! metres or not at all. A request in flight whose block is in neither the
//! present view nor the predicted one is cancelled. A static camera predicts
//! itself, so nothing changes for it; the displacement is capped at half the
//! height above the planet's minimum sphere and the turn at 30°, so a
//! prediction never puts the eye inside the planet or flips the view.
//!
//! The same extrapolation over a shorter horizon, the latency less two
//! deviations ([`ViewPredictor::early_frames`]), drives the prefetch
//! ([`crate::ClientConfig::prefetch`]): what that view needs and the present
//! one does not yet is asked now, after everything the present view needs.
//! Most answers come after that horizon, when the camera has got there, so
//! they are drawn on arrival as the others are, about one latency sooner
//! than if they were asked when needed; the full horizon would bring blocks
//! a few frames before the view draws them (0.7 % of the bytes on the deep
//! planet's `rainier` at 10 Mbit/s, docs/BENCHMARKS.md).

use crate::visibility::Camera;
use glam::DVec3;

/// Largest predicted turn of the view direction, radians.
const MAX_TURN: f64 = std::f64::consts::PI / 6.0;
/// Weight of a new latency sample in the moving average.
const LATENCY_SMOOTHING: f64 = 0.2;
/// Weight of a new sample in the latency's mean deviation (RFC 6298's β).
const DEV_SMOOTHING: f64 = 0.25;
/// Deviations added to the mean latency: most answers arrive before it.
const DEV_MARGIN: f64 = 2.0;

/// Linear camera extrapolation over the measured request latency.
#[derive(Debug, Clone, Default)]
pub struct ViewPredictor {
    prev: Option<Camera>,
    latency_frames: Option<f64>,
    /// Moving mean deviation of the latency (RFC 6298's RTTVAR), frames.
    latency_dev: f64,
    /// The eye's displacement over the last frame, metres.
    step: f64,
    /// The camera at [`ViewPredictor::early_frames`], from the last
    /// [`ViewPredictor::predict_stay`].
    early: Option<Camera>,
}

impl ViewPredictor {
    /// A predictor with no history.
    pub fn new() -> ViewPredictor {
        ViewPredictor::default()
    }

    /// A response was applied (decoded and in the tree, first seen by the
    /// selection) `frames` frames after its request was sent.
    pub fn observe_latency(&mut self, frames: u32) {
        let f = frames as f64;
        self.latency_frames = Some(match self.latency_frames {
            None => f,
            Some(l) => {
                self.latency_dev += DEV_SMOOTHING * ((f - l).abs() - self.latency_dev);
                l + LATENCY_SMOOTHING * (f - l)
            }
        });
    }

    /// How far the eye moved over the last frame seen by
    /// [`ViewPredictor::predict_stay`], metres (0 before two frames).
    pub fn step(&self) -> f64 {
        self.step
    }

    /// The horizon of the prediction in frames: the measured latency from
    /// request to applied answer plus `DEV_MARGIN` (two) of its deviations, if
    /// any response was applied yet.
    pub fn horizon_frames(&self) -> Option<f64> {
        self.latency_frames
            .map(|l| l + DEV_MARGIN * self.latency_dev)
    }

    /// The prefetch's horizon in frames ([`crate::ClientConfig::prefetch`]):
    /// the measured latency less `DEV_MARGIN` of its deviations, so that
    /// most answers asked now are applied after it. A block that the view
    /// needs by then and is asked now is drawn when its answer comes (its
    /// bytes relevant on arrival), sooner than if it were asked when
    /// needed. `None` where that is not ahead of now.
    pub fn early_frames(&self) -> Option<f64> {
        self.latency_frames
            .map(|l| l - DEV_MARGIN * self.latency_dev)
            .filter(|t| *t > 0.0)
    }

    /// The camera predicted [`ViewPredictor::early_frames`] ahead by the
    /// last [`ViewPredictor::predict_stay`] (`None` where it predicted
    /// nothing, or that horizon is not ahead).
    pub fn early(&self) -> Option<Camera> {
        self.early
    }

    /// Record this frame's camera and return the camera predicted when a
    /// request sent now is applied; `None` when there is nothing to predict
    /// (first frame, no latency measured yet, or the camera did not move).
    /// `r_min` is the radius of the planet's minimum sphere.
    pub fn predict(&mut self, camera: &Camera, r_min: f64) -> Option<Camera> {
        self.predict_stay(camera, r_min).map(|[arrival, _]| arrival)
    }

    /// As [`ViewPredictor::predict`], with a second camera: the one
    /// [`STAY_HORIZONS`] horizons ahead, where a block must still be in
    /// view for its answer to be worth asking. A block at the border of the
    /// view that the camera is leaving is in view at the predicted arrival
    /// by a few metres or not at all (on a low, fast flight, the blocks
    /// passing out at the side of the screen: docs/BENCHMARKS.md,
    /// "edge-pass"); its answer would be drawn a frame or two at best.
    pub fn predict_stay(&mut self, camera: &Camera, r_min: f64) -> Option<[Camera; 2]> {
        self.early = None;
        let prev = self.prev.replace(*camera)?;
        let step = (camera.eye - prev.eye).length();
        self.step = if step.is_finite() { step } else { 0.0 };
        let tau = self.horizon_frames()?;
        let out = [
            extrapolate(&prev, camera, tau, r_min)?,
            extrapolate(&prev, camera, tau * STAY_HORIZONS, r_min)?,
        ];
        self.early = self
            .early_frames()
            .and_then(|t| extrapolate(&prev, camera, t, r_min));
        Some(out)
    }
}

/// How far ahead, in prediction horizons, a requested block must still be
/// in view ([`ViewPredictor::predict_stay`]): half a horizon after the
/// arrival, a margin against the knife edge of a block leaving the view
/// just then. A whole horizon (2) also dropped blocks that stay in view a
/// second or more: circling Mount Rainier at 1 Mbit/s, a coarse block
/// entering the view stayed unrefined twice as long, 36 frames against 19,
/// and the flight's error integral rose by 30 % (docs/BENCHMARKS.md,
/// "circle-rainier").
pub const STAY_HORIZONS: f64 = 1.5;

/// `camera` extrapolated `tau` frames ahead from its step since `prev`;
/// `None` when it did not move or turn.
fn extrapolate(prev: &Camera, camera: &Camera, tau: f64, r_min: f64) -> Option<Camera> {
    let step = camera.eye - prev.eye;
    let f0 = prev.forward.try_normalize()?;
    let f1 = camera.forward.try_normalize()?;
    if !(step.is_finite() && tau.is_finite()) {
        return None;
    }
    if step == DVec3::ZERO && f0 == f1 {
        return None;
    }
    // Eye: linear, at most half the height above the minimum sphere.
    let mut shift = step * tau;
    let height = camera.eye.length() - r_min;
    let cap = 0.5 * height.max(0.0);
    if shift.length() > cap {
        shift = shift.normalize_or_zero() * cap;
    }
    // View direction: the per-frame turn, repeated, at most MAX_TURN.
    let turn = (f0.angle_between(f1) * tau).min(MAX_TURN);
    let forward = match f0.cross(f1).try_normalize() {
        Some(axis) if turn > 0.0 && turn.is_finite() => {
            glam::DQuat::from_axis_angle(axis, turn).mul_vec3(f1)
        }
        _ => f1,
    };
    Some(Camera {
        eye: camera.eye + shift,
        forward,
        ..*camera
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const R: f64 = 6_371_000.0;

    fn cam(eye: DVec3, forward: DVec3) -> Camera {
        Camera {
            eye,
            forward,
            up: DVec3::Z,
            fov_y: 1.0,
            aspect: 1.0,
            viewport_height_px: 1000.0,
        }
    }

    #[test]
    fn static_camera_and_no_latency_predict_nothing() {
        let mut p = ViewPredictor::new();
        let c = cam(DVec3::new(R + 1000.0, 0.0, 0.0), DVec3::NEG_X);
        assert!(p.predict(&c, R).is_none());
        assert!(p.predict(&c, R).is_none(), "no latency yet");
        p.observe_latency(10);
        assert!(p.predict(&c, R).is_none(), "did not move");
    }

    #[test]
    fn moving_eye_is_extrapolated_over_the_latency() {
        let mut p = ViewPredictor::new();
        p.observe_latency(10);
        let a = cam(DVec3::new(R + 100_000.0, 0.0, 0.0), DVec3::NEG_X);
        let b = cam(DVec3::new(R + 99_000.0, 0.0, 0.0), DVec3::NEG_X);
        assert!(p.predict(&a, R).is_none());
        let q = p.predict(&b, R).expect("moving");
        assert!((q.eye.x - (R + 89_000.0)).abs() < 1e-6, "{}", q.eye.x - R);
        assert_eq!(q.forward, b.forward.normalize());
    }

    /// The second camera of `predict_stay` is `STAY_HORIZONS` horizons
    /// ahead (where a requested block must still be in view), beyond the
    /// first, the arrival's, as `predict`; both are capped alike.
    #[test]
    fn stay_camera_is_further_ahead() {
        let mut p = ViewPredictor::new();
        p.observe_latency(10);
        let a = cam(DVec3::new(R + 100_000.0, 0.0, 0.0), DVec3::NEG_X);
        let b = cam(DVec3::new(R + 99_000.0, 0.0, 0.0), DVec3::NEG_X);
        assert!(p.predict_stay(&a, R).is_none());
        let [arrival, stay] = p.predict_stay(&b, R).expect("moving");
        assert!((arrival.eye.x - (R + 89_000.0)).abs() < 1e-6);
        let ahead = 99_000.0 - 10_000.0 * STAY_HORIZONS;
        assert!(
            (stay.eye.x - (R + ahead)).abs() < 1e-6,
            "{}",
            stay.eye.x - R
        );
        // Close to the ground the cap (half the height) holds for both.
        let mut p = ViewPredictor::new();
        p.observe_latency(10);
        p.predict_stay(&cam(DVec3::new(R + 1_100.0, 0.0, 0.0), DVec3::NEG_X), R);
        let [arrival, stay] = p
            .predict_stay(&cam(DVec3::new(R + 1_000.0, 0.0, 0.0), DVec3::NEG_X), R)
            .expect("moving");
        assert!((arrival.eye.x - (R + 500.0)).abs() < 1e-6);
        assert!((stay.eye.x - (R + 500.0)).abs() < 1e-6);
    }

    /// The horizon is the mean latency plus two mean deviations: a steady
    /// latency predicts exactly that far, a jittery one further.
    #[test]
    fn horizon_adds_the_latency_deviation() {
        let mut p = ViewPredictor::new();
        assert_eq!(p.horizon_frames(), None);
        p.observe_latency(10);
        p.observe_latency(10);
        assert_eq!(p.horizon_frames(), Some(10.0));
        p.observe_latency(20);
        // Mean 10 + 0.2·10 = 12; deviation 0.25·10 = 2.5.
        let h = p.horizon_frames().expect("measured");
        assert!((h - 17.0).abs() < 1e-12, "{h}");
    }

    #[test]
    fn prediction_never_enters_the_planet() {
        let mut p = ViewPredictor::new();
        p.observe_latency(1000);
        let a = cam(DVec3::new(R + 2_000.0, 0.0, 0.0), DVec3::NEG_X);
        let b = cam(DVec3::new(R + 1_000.0, 0.0, 0.0), DVec3::NEG_X);
        p.predict(&a, R);
        let q = p.predict(&b, R).expect("moving");
        assert!((q.eye.x - (R + 500.0)).abs() < 1e-6, "{}", q.eye.x - R);
    }

    /// The prefetch's camera is the latency less two deviations ahead, and
    /// none where that is not ahead of now.
    #[test]
    fn early_camera_is_two_deviations_short_of_the_latency() {
        let mut p = ViewPredictor::new();
        p.observe_latency(10);
        p.observe_latency(6);
        // Latency 9.2 frames, deviation 1: 7.2 frames ahead.
        assert_eq!(p.early_frames(), Some(9.2 - 2.0));
        let a = cam(DVec3::new(R + 2_000.0, 0.0, 0.0), DVec3::NEG_X);
        let b = cam(DVec3::new(R + 1_990.0, 0.0, 0.0), DVec3::NEG_X);
        assert!(p.predict_stay(&a, R).is_none() && p.early().is_none());
        p.predict_stay(&b, R).expect("moving");
        let e = p.early().expect("early");
        assert!(
            (e.eye.x - (R + 1_990.0 - 72.0)).abs() < 1e-6,
            "{}",
            e.eye.x - R
        );
        // A still camera predicts nothing, early or not.
        p.predict_stay(&b, R);
        assert!(p.early().is_none());
        // Latency 1.6 frames, deviation 2: nothing ahead.
        let mut p = ViewPredictor::new();
        p.observe_latency(0);
        p.observe_latency(8);
        assert_eq!(p.early_frames(), None);
    }

    #[test]
    fn turning_view_is_extrapolated_and_capped() {
        let mut p = ViewPredictor::new();
        p.observe_latency(5);
        let eye = DVec3::new(R + 1e6, 0.0, 0.0);
        let deg = 1f64.to_radians();
        let a = cam(eye, DVec3::NEG_X);
        let b = cam(eye, DVec3::new(-deg.cos(), deg.sin(), 0.0));
        p.predict(&a, R);
        let q = p.predict(&b, R).expect("turning");
        let turned = DVec3::NEG_X.angle_between(q.forward).to_degrees();
        assert!((turned - 6.0).abs() < 1e-6, "{turned}");
        // 100 frames of latency: capped at 30° beyond the current direction.
        let mut p = ViewPredictor::new();
        p.observe_latency(100);
        p.predict(&a, R);
        let q = p.predict(&b, R).expect("turning");
        let turned = DVec3::NEG_X.angle_between(q.forward).to_degrees();
        assert!((turned - 31.0).abs() < 1e-6, "{turned}");
    }
}
