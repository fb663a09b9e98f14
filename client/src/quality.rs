//! The quality-factor controller.
//!
//! Thesis §4.2.4 and §3.7 (see docs/REFERENCES.md): the quality factor `QF` is
//! proportional to the number of rendered triangles; it changes "in
//! proportion" only when the frame rate leaves a tolerance band around the
//! target. The law, band and rate are not given in the thesis; ours:
//!
//! ```text
//! ratio = target / measured           (triangle budget)
//!       = measured_fps / target_fps   (frame rate: fps ∝ 1 / triangles)
//! if |ln ratio| > ln(1 + tolerance):
//!     QF ← clamp(QF · clamp(ratio^k, 1/max_step, max_step), QF_MIN, QF_MAX)
//! ```
//!
//! With the plant `triangles ∝ QF`, one step moves `ln QF` by `k·ln ratio`,
//! so with `0 < k < 1` the error shrinks geometrically by `(1 − k)` and never
//! changes sign (no overshoot), and inside the band nothing moves, so
//! measurement noise smaller than the band causes no oscillation. The frame
//! rate is smoothed with an exponential moving average first. Defaults:
//! `k = 0.5`, tolerance 10 %, `max_step = 1.25` per frame.

/// Smallest quality factor.
pub const QF_MIN: f64 = 1.0;
/// Largest quality factor.
pub const QF_MAX: f64 = 1e10;

/// What the controller regulates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum QualityMode {
    /// QF stays where it is.
    Fixed,
    /// Reach this many frames per second.
    TargetFps(f64),
    /// Render about this many triangles per frame.
    TriangleBudget(f64),
}

/// Controller parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QualityConfig {
    /// The regulated quantity.
    pub mode: QualityMode,
    /// Initial QF.
    pub initial: f64,
    /// Relative half-width of the dead band (0.1 = ±10 %).
    pub tolerance: f64,
    /// Exponent `k` of the multiplicative law, in `(0, 1]`.
    pub gain: f64,
    /// Largest factor QF may change by in one frame.
    pub max_step: f64,
    /// Smoothing of the measurement (weight of the newest sample).
    pub smoothing: f64,
}

impl Default for QualityConfig {
    fn default() -> Self {
        QualityConfig {
            mode: QualityMode::Fixed,
            initial: 1e4,
            tolerance: 0.1,
            gain: 0.5,
            max_step: 1.25,
            smoothing: 0.5,
        }
    }
}

/// The QF controller.
#[derive(Debug, Clone, PartialEq)]
pub struct QualityController {
    config: QualityConfig,
    qf: f64,
    smoothed: Option<f64>,
}

impl QualityController {
    /// A controller starting at `config.initial`.
    pub fn new(config: QualityConfig) -> QualityController {
        QualityController {
            qf: sanitize(config.initial),
            config,
            smoothed: None,
        }
    }

    /// The current quality factor.
    pub fn qf(&self) -> f64 {
        self.qf
    }

    /// Change the mode (e.g. from a UI).
    pub fn set_mode(&mut self, mode: QualityMode) {
        self.config.mode = mode;
        self.smoothed = None;
    }

    /// Feed one frame's measurement: its duration in seconds and the number of
    /// triangles it rendered. Returns the new QF.
    pub fn update(&mut self, frame_seconds: f64, triangles: f64) -> f64 {
        let (target, measured, inverse) = match self.config.mode {
            QualityMode::Fixed => return self.qf,
            QualityMode::TargetFps(t) => (t, 1.0 / frame_seconds, false),
            QualityMode::TriangleBudget(t) => (t, triangles, true),
        };
        if !(measured.is_finite() && measured > 0.0 && target.is_finite() && target > 0.0) {
            return self.qf;
        }
        let a = self.config.smoothing.clamp(0.0, 1.0);
        let m = match self.smoothed {
            Some(s) => s + a * (measured - s),
            None => measured,
        };
        self.smoothed = Some(m);
        let ratio = if inverse { target / m } else { m / target };
        let band = (1.0 + self.config.tolerance.max(0.0)).ln();
        if ratio.ln().abs() <= band {
            return self.qf;
        }
        let step = self.config.max_step.max(1.0);
        let factor = ratio
            .powf(self.config.gain.clamp(0.0, 1.0))
            .clamp(1.0 / step, step);
        self.qf = sanitize(self.qf * factor);
        self.qf
    }
}

fn sanitize(qf: f64) -> f64 {
    if qf.is_nan() {
        QF_MIN
    } else {
        qf.clamp(QF_MIN, QF_MAX)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic noise in [−amp, amp].
    fn noise(k: u64, amp: f64) -> f64 {
        let x = k
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((x >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0) * amp
    }

    fn run(mode: QualityMode, plant: impl Fn(f64, u64) -> (f64, f64)) -> Vec<f64> {
        let mut c = QualityController::new(QualityConfig {
            mode,
            initial: 10.0,
            ..QualityConfig::default()
        });
        let mut qfs = vec![];
        for k in 0..400 {
            let (secs, tris) = plant(c.qf(), k);
            qfs.push(c.update(secs, tris));
        }
        qfs
    }

    fn check_converged(qfs: &[f64], ideal: f64) {
        let tail = &qfs[qfs.len() - 200..];
        for q in tail {
            assert!((q / ideal - 1.0).abs() < 0.2, "qf {q} ideal {ideal}");
        }
        // No oscillation: the direction of change flips at most a few times.
        let mut flips = 0;
        let mut last = 0.0f64;
        for w in tail.windows(2) {
            let d = (w[1] - w[0]).signum() * ((w[1] - w[0]).abs() > 0.0) as i32 as f64;
            if d != 0.0 {
                if last != 0.0 && d != last {
                    flips += 1;
                }
                last = d;
            }
        }
        assert!(flips <= 4, "{flips} direction changes");
    }

    #[test]
    fn converges_to_triangle_budget() {
        // triangles = 300·QF ± 3 %.
        let qfs = run(QualityMode::TriangleBudget(1.2e6), |qf, k| {
            (0.01, 300.0 * qf * (1.0 + noise(k, 0.03)))
        });
        check_converged(&qfs, 4000.0);
    }

    #[test]
    fn converges_to_frame_rate() {
        // frame time = 1 ms + QF·2 µs ± 3 %; 120 fps ⇒ QF ≈ 3666.
        let qfs = run(QualityMode::TargetFps(120.0), |qf, k| {
            ((1e-3 + qf * 2e-6) * (1.0 + noise(k, 0.03)), 0.0)
        });
        check_converged(&qfs, (1.0 / 120.0 - 1e-3) / 2e-6);
    }

    #[test]
    fn hostile_measurements() {
        let mut c = QualityController::new(QualityConfig {
            mode: QualityMode::TargetFps(60.0),
            ..QualityConfig::default()
        });
        for s in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e-300] {
            assert!(c.update(s, 0.0).is_finite());
        }
        assert!(c.qf() >= QF_MIN && c.qf() <= QF_MAX);
    }
}
