//! Per-tenant bandwidth limit: a token bucket shared by all the tenant's
//! connections.
//!
//! A request reserves its size from the bucket (the balance may go negative:
//! later requests queue behind it, which makes the pacing FIFO-fair across
//! the tenant's connections). The caller then sleeps until the reservation is
//! covered. If that wait would exceed the configured maximum, the
//! reservation is refunded and the request is refused with `rate_limited`.

use std::sync::Mutex;
use std::time::{Duration, Instant};

/// A token bucket of `rate` bytes per second with a burst of one second.
#[derive(Debug)]
pub struct TokenBucket {
    rate: f64,
    state: Mutex<(f64, Instant)>,
}

impl TokenBucket {
    /// A full bucket of `rate` bytes per second (`rate > 0`).
    pub fn new(rate: u64) -> TokenBucket {
        let rate = rate.max(1) as f64;
        TokenBucket {
            rate,
            state: Mutex::new((rate, Instant::now())),
        }
    }

    /// Reserves `bytes`: `Ok(wait)` (possibly zero) or `Err(wait)` if the
    /// wait would exceed `max_wait` (nothing reserved then).
    pub fn reserve(&self, bytes: u64, max_wait: Duration) -> Result<Duration, Duration> {
        let mut guard = match self.state.lock() {
            Ok(g) => g,
            Err(p) => p.into_inner(),
        };
        let now = Instant::now();
        let (tokens, last) = *guard;
        let refilled = (tokens + now.duration_since(last).as_secs_f64() * self.rate).min(self.rate);
        let after = refilled - bytes as f64;
        let wait = if after >= 0.0 {
            Duration::ZERO
        } else {
            Duration::from_secs_f64(-after / self.rate)
        };
        if wait > max_wait {
            *guard = (refilled, now);
            return Err(wait);
        }
        *guard = (after, now);
        Ok(wait)
    }

    /// Returns an unused reservation (e.g. the request was cancelled).
    pub fn refund(&self, bytes: u64) {
        let mut guard = match self.state.lock() {
            Ok(g) => g,
            Err(p) => p.into_inner(),
        };
        guard.0 = (guard.0 + bytes as f64).min(self.rate);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paces_then_refuses() {
        let b = TokenBucket::new(1000);
        let max = Duration::from_secs(2);
        assert_eq!(b.reserve(600, max), Ok(Duration::ZERO));
        let w = b.reserve(600, max).unwrap();
        assert!(w > Duration::from_millis(150) && w < Duration::from_millis(250));
        // 1.2 s more queued: still within 2 s.
        assert!(b.reserve(1000, max).is_ok());
        // Now the queue is ~1.2 s deep; 1000 more would need ~2.2 s.
        assert!(b.reserve(1000, max).is_err());
        b.refund(1000);
        assert!(b.reserve(500, max).is_ok());
    }
}
