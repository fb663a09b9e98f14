//! The request window sized by the link: bandwidth × delay, measured.
//!
//! Beyond the thesis, which fixes the number of pending requests (§3.5.1:
//! "we fix the number of pending server requests to a maximum", size
//! not given, see docs/REFERENCES.md), and beyond every peer (all fixed:
//! 50/18/20/6/5). Too few requests in flight leave the link idle between
//! round trips; too many queue in the network, where they can no longer be
//! re-ranked or dropped when the view moves, and each answer arrives later.
//! The window that keeps the link busy and no more is its bandwidth-delay
//! product (BDP), so the client bounds the *bytes* in flight (records
//! have known sizes) by
//!
//! ```text
//! window = GAIN · delivery_rate · min_rtt      (at least MIN_WINDOW bytes)
//! ```
//!
//! as BBR sizes its congestion window (Cardwell et al., 2016: a max filter
//! of the delivery rate, a min filter of the round-trip time, gain 2):
//!
//! - **min RTT**: the smallest of the QUIC path's smoothed RTT (given by
//!   the transport, [`LinkEstimator::observe_rtt`]) and of the request
//!   latencies (send to delivery), so queueing in the link does not inflate
//!   it;
//! - **delivery rate**: bytes delivered per second over intervals of at
//!   least one min RTT (and [`MIN_INTERVAL`] s) during which requests were in
//!   flight the whole time, the largest of the last [`RATE_SAMPLES`]
//!   intervals. A window-limited sample is at most `window / rtt = GAIN ·
//!   rate`, so the estimate grows by up to `GAIN` per interval until the
//!   link, not the window, limits it (BBR's start-up).
//!
//! Before the first sample the window is [`INITIAL_WINDOW`].

/// Window gain over the bandwidth-delay product.
pub const GAIN: f64 = 2.0;
/// Smallest window, bytes: records are 2–12 kB, and on a lossy link a
/// stream waits a round trip or more for each retransmission, so at least
/// five to thirty requests stay in flight however low the measured product
/// (with 16 kB, a 1 Mbit/s, 200 ms, 2 %-loss link carried 15 % fewer bytes
/// than Cesium's 18 requests; docs/BENCHMARKS.md).
pub const MIN_WINDOW: u64 = 64 * 1024;
/// Window before any measurement, bytes.
pub const INITIAL_WINDOW: u64 = 64 * 1024;
/// Largest window, bytes.
pub const MAX_WINDOW: u64 = 16 * 1024 * 1024;
/// Shortest rate-sampling interval, seconds.
pub const MIN_INTERVAL: f64 = 0.1;
/// Rate samples kept for the max filter.
pub const RATE_SAMPLES: usize = 8;

/// Delivery rate and minimum RTT of the link, from the client's own
/// deliveries and the transport's RTT.
#[derive(Debug, Clone, Default)]
pub struct LinkEstimator {
    min_rtt: Option<f64>,
    /// Rate samples, bytes per second (newest last).
    rates: Vec<f64>,
    /// The interval being measured: elapsed seconds and bytes.
    elapsed: f64,
    bytes: u64,
    /// Whether requests were in flight during the whole interval.
    busy: bool,
}

impl LinkEstimator {
    /// No measurement yet.
    pub fn new() -> LinkEstimator {
        LinkEstimator {
            busy: true,
            ..LinkEstimator::default()
        }
    }

    /// A round-trip time measured by the transport, or a request's latency
    /// from send to delivery, in seconds (non-finite or non-positive values
    /// are ignored).
    pub fn observe_rtt(&mut self, seconds: f64) {
        if seconds.is_finite() && seconds > 0.0 {
            self.min_rtt = Some(self.min_rtt.map_or(seconds, |m| m.min(seconds)));
        }
    }

    /// One frame of `dt` seconds, in which `bytes` were delivered, and
    /// whether requests were in flight from its start (an idle link says
    /// nothing about its rate).
    pub fn on_frame(&mut self, dt: f64, bytes: u64, in_flight: bool) {
        if !(dt.is_finite() && dt > 0.0) {
            return;
        }
        if !in_flight {
            // Restart the interval: its rate would count idle time.
            self.elapsed = 0.0;
            self.bytes = 0;
            self.busy = true;
            return;
        }
        self.elapsed += dt;
        self.bytes += bytes;
        let interval = self.min_rtt.unwrap_or(0.0).max(MIN_INTERVAL);
        if self.elapsed >= interval {
            if self.busy && self.bytes > 0 {
                if self.rates.len() == RATE_SAMPLES {
                    self.rates.remove(0);
                }
                self.rates.push(self.bytes as f64 / self.elapsed);
            }
            self.elapsed = 0.0;
            self.bytes = 0;
            self.busy = true;
        }
    }

    /// The delivery rate estimate, bytes per second.
    pub fn rate(&self) -> Option<f64> {
        self.rates.iter().copied().reduce(f64::max)
    }

    /// The minimum RTT, seconds.
    pub fn min_rtt(&self) -> Option<f64> {
        self.min_rtt
    }

    /// The window in bytes: `GAIN · rate · min_rtt`, within
    /// [`MIN_WINDOW`, `MAX_WINDOW`]; [`INITIAL_WINDOW`] until both are known.
    pub fn window_bytes(&self) -> u64 {
        match (self.rate(), self.min_rtt) {
            (Some(r), Some(t)) => {
                let w = GAIN * r * t;
                if w.is_finite() {
                    (w as u64).clamp(MIN_WINDOW, MAX_WINDOW)
                } else {
                    MAX_WINDOW
                }
            }
            _ => INITIAL_WINDOW,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn window_is_twice_the_bdp() {
        let mut e = LinkEstimator::new();
        assert_eq!(e.window_bytes(), INITIAL_WINDOW);
        e.observe_rtt(0.25);
        e.observe_rtt(0.2);
        e.observe_rtt(0.3);
        // 2 Mbit/s: 250 000 B/s for 2 s of 1/30 s frames.
        for _ in 0..60 {
            e.on_frame(1.0 / 30.0, 250_000 / 30, true);
        }
        let r = e.rate().expect("rate");
        assert!((r - 250_000.0).abs() < 4_000.0, "{r}");
        let w = e.window_bytes() as f64;
        assert!((w - 2.0 * 250_000.0 * 0.2).abs() < 2_000.0, "{w}");
    }

    #[test]
    fn idle_time_is_not_counted() {
        let mut e = LinkEstimator::new();
        e.observe_rtt(0.05);
        for k in 0..120 {
            // Busy two thirds of the time at 1 MB/s.
            let busy = k % 30 < 20;
            e.on_frame(0.01, if busy { 10_000 } else { 0 }, busy);
        }
        let r = e.rate().expect("rate");
        assert!((r - 1e6).abs() < 1e4, "{r}");
    }

    proptest! {
        #[test]
        fn window_bounded(rtt in -1.0f64..100.0, bytes in 0u64..1_000_000_000, dt in -1.0f64..10.0) {
            let mut e = LinkEstimator::new();
            e.observe_rtt(rtt);
            for _ in 0..20 {
                e.on_frame(dt, bytes, true);
            }
            let w = e.window_bytes();
            prop_assert!((MIN_WINDOW..=MAX_WINDOW).contains(&w) || w == INITIAL_WINDOW);
        }
    }
}
