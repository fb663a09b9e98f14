//! Token buckets: a tenant's bandwidth (`max_bytes_per_second`) and
//! requests (`max_requests_per_second`), each shared by all the tenant's
//! connections, and failed hellos and new connections per client address
//! ([`KeyedBuckets`]).
//!
//! A request reserves its size from the bucket (the balance may go negative:
//! later requests queue behind it, which makes the pacing FIFO-fair across
//! the tenant's connections). The caller then sleeps until the reservation is
//! covered. If that wait would exceed the configured maximum, the
//! reservation is refunded and the request is refused with `rate_limited`.

use std::collections::HashMap;
use std::net::IpAddr;
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

/// What [`RecordAlerts::note`] says about one failure of a record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Alert {
    /// The first failure of this record seen by this process (count it).
    pub first: bool,
    /// Log it now (at most once per [`RecordAlerts::LOG_EVERY`] per record).
    pub log: bool,
}

/// Rate limit of the server's log lines and corruption alerts per record:
/// a record that keeps failing (corrupt, or unreadable storage) is counted
/// once and logged at most once a minute, however often clients ask for it.
#[derive(Debug, Default)]
pub struct RecordAlerts {
    seen: Mutex<HashMap<(String, u64), Instant>>,
}

impl RecordAlerts {
    /// Shortest interval between two log lines about one record.
    pub const LOG_EVERY: Duration = Duration::from_secs(60);

    /// Notes a failure of the record at `offset` of `db`.
    pub fn note(&self, db: &str, offset: u64) -> Alert {
        let mut map = match self.seen.lock() {
            Ok(g) => g,
            Err(p) => p.into_inner(),
        };
        let now = Instant::now();
        let key = (db.to_string(), offset);
        match map.get_mut(&key) {
            Some(last) if now.duration_since(*last) < Self::LOG_EVERY => Alert {
                first: false,
                log: false,
            },
            Some(last) => {
                *last = now;
                Alert {
                    first: false,
                    log: true,
                }
            }
            None => {
                if map.len() >= MAX_KEYS {
                    map.retain(|_, t| now.duration_since(*t) < Self::LOG_EVERY);
                }
                let first = map.len() < MAX_KEYS;
                if first {
                    map.insert(key, now);
                }
                Alert { first, log: first }
            }
        }
    }
}

/// Addresses remembered by [`KeyedBuckets`] before refilled ones are dropped.
const MAX_KEYS: usize = 16_384;

/// One small bucket per client IP: `capacity` events per minute, with a
/// burst of `capacity` (failed hellos, `max_failed_hellos_per_minute`).
/// Memory is bounded: past `MAX_KEYS` addresses, full buckets are
/// forgotten, and if none is full the oldest half is.
#[derive(Debug)]
pub struct KeyedBuckets {
    /// Events per second.
    rate: f64,
    /// Burst (bucket size); 0 = unlimited.
    capacity: f64,
    state: Mutex<HashMap<IpAddr, (f64, Instant)>>,
}

impl KeyedBuckets {
    /// `per_minute` events per minute per address, with a burst of the
    /// same size; 0 = unlimited.
    pub fn per_minute(per_minute: u32) -> KeyedBuckets {
        KeyedBuckets::new(f64::from(per_minute) / 60.0, f64::from(per_minute))
    }

    /// `per_second` events per second per address with a burst of `burst`
    /// (at least one); `per_second` 0 = unlimited.
    pub fn per_second(per_second: u32, burst: usize) -> KeyedBuckets {
        if per_second == 0 {
            return KeyedBuckets::new(0.0, 0.0);
        }
        KeyedBuckets::new(f64::from(per_second), burst.max(1) as f64)
    }

    fn new(rate: f64, capacity: f64) -> KeyedBuckets {
        KeyedBuckets {
            rate,
            capacity,
            state: Mutex::new(HashMap::new()),
        }
    }

    fn refilled(&self, (tokens, last): (f64, Instant), now: Instant) -> f64 {
        (tokens + now.duration_since(last).as_secs_f64() * self.rate).min(self.capacity)
    }

    /// Spends one event of `ip`'s budget if it has one left.
    pub fn try_spend(&self, ip: IpAddr) -> bool {
        if !self.allows(ip) {
            return false;
        }
        self.spend(ip);
        true
    }

    /// Whether `ip` still has budget (at least one event left).
    pub fn allows(&self, ip: IpAddr) -> bool {
        if self.capacity == 0.0 {
            return true;
        }
        let map = match self.state.lock() {
            Ok(g) => g,
            Err(p) => p.into_inner(),
        };
        map.get(&ip)
            .is_none_or(|&b| self.refilled(b, Instant::now()) >= 1.0)
    }

    /// Spends one event of `ip`'s budget.
    pub fn spend(&self, ip: IpAddr) {
        if self.capacity == 0.0 {
            return;
        }
        let mut map = match self.state.lock() {
            Ok(g) => g,
            Err(p) => p.into_inner(),
        };
        let now = Instant::now();
        if map.len() >= MAX_KEYS && !map.contains_key(&ip) {
            let cap = self.capacity;
            map.retain(|_, b| self.refilled(*b, now) < cap);
            if map.len() >= MAX_KEYS {
                let mut ages: Vec<Instant> = map.values().map(|b| b.1).collect();
                ages.sort_unstable();
                let cut = ages[ages.len() / 2];
                map.retain(|_, b| b.1 > cut);
            }
        }
        let b = map.entry(ip).or_insert((self.capacity, now));
        *b = ((self.refilled(*b, now) - 1.0).max(0.0), now);
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
        // 0.2 s less the time between the two calls (a busy machine may
        // stall a few tens of milliseconds there).
        assert!(w > Duration::from_millis(100) && w <= Duration::from_millis(200));
        // 1.2 s more queued: still within 2 s.
        assert!(b.reserve(1000, max).is_ok());
        // Now the queue is ~1.2 s deep; 1000 more would need ~2.2 s.
        assert!(b.reserve(1000, max).is_err());
        b.refund(1000);
        assert!(b.reserve(500, max).is_ok());
    }

    #[test]
    fn a_failing_record_is_counted_once_and_logged_once_a_minute() {
        let a = RecordAlerts::default();
        assert_eq!(
            a.note("earth", 64),
            Alert {
                first: true,
                log: true
            }
        );
        for _ in 0..1000 {
            assert_eq!(
                a.note("earth", 64),
                Alert {
                    first: false,
                    log: false
                }
            );
        }
        assert_eq!(
            a.note("earth", 128),
            Alert {
                first: true,
                log: true
            }
        );
        assert_eq!(
            a.note("mars", 64),
            Alert {
                first: true,
                log: true
            }
        );
    }

    #[test]
    fn keyed_buckets_limit_each_address_on_its_own() {
        let k = KeyedBuckets::per_minute(3);
        let a: IpAddr = "192.0.2.1".parse().unwrap();
        let b: IpAddr = "192.0.2.2".parse().unwrap();
        for _ in 0..3 {
            assert!(k.allows(a));
            k.spend(a);
        }
        assert!(!k.allows(a));
        assert!(k.allows(b));
        let unlimited = KeyedBuckets::per_minute(0);
        for _ in 0..100 {
            unlimited.spend(a);
        }
        assert!(unlimited.allows(a));
    }

    #[test]
    fn per_second_buckets_have_their_own_burst() {
        let k = KeyedBuckets::per_second(1000, 5);
        let a: IpAddr = "192.0.2.1".parse().unwrap();
        let spent = (0..20).filter(|_| k.try_spend(a)).count();
        // The burst, and at most a few refilled at 1000/s meanwhile.
        assert!((5..=8).contains(&spent), "{spent}");
        std::thread::sleep(Duration::from_millis(20));
        assert!(k.try_spend(a), "refilled at 1000 per second");
        let unlimited = KeyedBuckets::per_second(0, 5);
        assert!((0..100).all(|_| unlimited.try_spend(a)));
    }
}
