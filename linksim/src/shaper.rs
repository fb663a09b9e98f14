//! The per-direction decision logic, free of I/O: given the arrival time and
//! size of a datagram, decide whether it is dropped and when it is delivered.

use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::config::{LinkConfig, PER_PACKET_OVERHEAD};

/// Longest delay the shaper will schedule for any one component (delay,
/// jitter, reorder delay); keeps `Instant` arithmetic far from overflow.
const MAX_COMPONENT: Duration = Duration::from_secs(3600);

/// What happens to one datagram.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Verdict {
    /// Deliver at this instant.
    Deliver(Instant),
    /// Lost on the wire (random loss).
    DropLoss,
    /// Dropped at the tail of a full bottleneck queue.
    DropQueue,
    /// Dropped because the link is down.
    DropBlackhole,
}

/// A packet (any kind: a datagram and its destination, an IP packet) and
/// the time it leaves the link; ordered by that time, then by `seq` (the
/// order the times were decided), for the delivery heaps.
#[derive(Debug)]
pub(crate) struct Timed<T> {
    pub(crate) at: Instant,
    pub(crate) seq: u64,
    pub(crate) item: T,
}

impl<T> PartialEq for Timed<T> {
    fn eq(&self, other: &Self) -> bool {
        (self.at, self.seq) == (other.at, other.seq)
    }
}
impl<T> Eq for Timed<T> {}
impl<T> PartialOrd for Timed<T> {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl<T> Ord for Timed<T> {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (self.at, self.seq).cmp(&(other.at, other.seq))
    }
}

/// One direction's state: configuration, RNG, and the bottleneck's virtual
/// clock.
#[derive(Debug)]
pub(crate) struct Shaper {
    cfg: LinkConfig,
    rng: ChaCha8Rng,
    stream: u64,
    /// When the bottleneck finishes serialising everything admitted so far.
    busy_until: Option<Instant>,
    /// Latest delivery time given to an in-order packet: later in-order
    /// packets are never delivered before it (jitter does not reorder).
    fifo_floor: Option<Instant>,
}

fn rng_for(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

impl Shaper {
    /// `stream` separates the two directions' random sequences even when
    /// both use the same seed.
    pub(crate) fn new(cfg: LinkConfig, stream: u64) -> Self {
        Self {
            rng: rng_for(cfg.seed, stream),
            stream,
            cfg,
            busy_until: None,
            fifo_floor: None,
        }
    }

    pub(crate) fn config(&self) -> &LinkConfig {
        &self.cfg
    }

    /// Replaces the configuration. The RNG is re-seeded only when the seed
    /// changes; otherwise its sequence continues. Packets already queued or
    /// in flight keep their schedule.
    pub(crate) fn set_config(&mut self, cfg: LinkConfig) {
        if cfg.seed != self.cfg.seed {
            self.rng = rng_for(cfg.seed, self.stream);
        }
        self.cfg = cfg;
    }

    /// Decides the fate of a datagram of `len` payload bytes arriving at
    /// `now`. Exactly four random numbers are drawn per call, whatever the
    /// outcome, so the n-th datagram of a direction always sees the same
    /// draws for a given seed.
    pub(crate) fn decide(&mut self, now: Instant, len: usize, blackhole: bool) -> Verdict {
        let u_loss: f64 = self.rng.random();
        let u_jitter: f64 = self.rng.random();
        let u_reorder: f64 = self.rng.random();
        let u_reorder_amount: f64 = self.rng.random();

        if blackhole {
            return Verdict::DropBlackhole;
        }

        // Bottleneck: drop-tail queue drained at the link rate.
        let departure = match self.cfg.bandwidth_bps {
            None => now,
            Some(0) => return Verdict::DropQueue,
            Some(bps) => {
                let start = self.busy_until.map_or(now, |b| b.max(now));
                let backlog_ns = (start - now).as_nanos();
                let backlog_bytes = backlog_ns.saturating_mul(bps as u128) / 8_000_000_000;
                let wire = (len + PER_PACKET_OVERHEAD) as u128;
                if backlog_bytes > 0 && backlog_bytes + wire > self.cfg.queue_limit_bytes as u128 {
                    return Verdict::DropQueue;
                }
                let ser_ns = wire.saturating_mul(8_000_000_000) / bps as u128;
                let ser = Duration::from_nanos(u64::try_from(ser_ns).unwrap_or(u64::MAX))
                    .min(MAX_COMPONENT);
                let dep = start + ser;
                self.busy_until = Some(dep);
                dep
            }
        };

        // Random loss on the wire, after the bottleneck (the packet used its
        // share of the capacity).
        if u_loss < self.cfg.loss {
            return Verdict::DropLoss;
        }

        // Propagation delay ± jitter, never before the departure.
        let delay = self.cfg.delay.min(MAX_COMPONENT);
        let jitter = self.cfg.jitter.min(MAX_COMPONENT);
        let offset = (2.0 * u_jitter - 1.0) * jitter.as_secs_f64();
        let mut at = if offset >= 0.0 {
            departure + delay + Duration::from_secs_f64(offset)
        } else {
            departure + delay.saturating_sub(Duration::from_secs_f64(-offset))
        };
        if let Some(floor) = self.fifo_floor {
            at = at.max(floor);
        }

        if u_reorder < self.cfg.reorder {
            // Held back; later packets overtake it. The FIFO floor is not
            // moved, so they are not held back with it.
            let extra = self
                .cfg
                .reorder_delay
                .min(MAX_COMPONENT)
                .mul_f64(0.5 + u_reorder_amount);
            return Verdict::Deliver(at + extra);
        }
        self.fifo_floor = Some(at);
        Verdict::Deliver(at)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_decisions() {
        let cfg = LinkConfig::loopback()
            .with_loss(0.3)
            .with_reorder(0.2)
            .with_jitter(Duration::from_millis(5))
            .with_seed(1234);
        let t0 = Instant::now();
        let run = |seed: u64| {
            let mut s = Shaper::new(cfg.clone().with_seed(seed), 0);
            (0..2000)
                .map(
                    |i| match s.decide(t0 + Duration::from_micros(i * 100), 1000, false) {
                        Verdict::Deliver(at) => Some(at - t0),
                        _ => None,
                    },
                )
                .collect::<Vec<_>>()
        };
        assert_eq!(run(1234), run(1234));
        assert_ne!(run(1234), run(1235));
    }

    #[test]
    fn directions_use_distinct_streams() {
        let cfg = LinkConfig::loopback().with_loss(0.5).with_seed(7);
        let t0 = Instant::now();
        let mut a = Shaper::new(cfg.clone(), 0);
        let mut b = Shaper::new(cfg, 1);
        let pa: Vec<_> = (0..200).map(|_| a.decide(t0, 100, false)).collect();
        let pb: Vec<_> = (0..200).map(|_| b.decide(t0, 100, false)).collect();
        assert_ne!(pa, pb);
    }

    #[test]
    fn blackhole_consumes_draws() {
        let cfg = LinkConfig::loopback().with_loss(0.5).with_seed(3);
        let t0 = Instant::now();
        let mut a = Shaper::new(cfg.clone(), 0);
        let mut b = Shaper::new(cfg, 0);
        assert_eq!(a.decide(t0, 100, true), Verdict::DropBlackhole);
        b.decide(t0, 100, false);
        for _ in 0..100 {
            assert_eq!(a.decide(t0, 100, false), b.decide(t0, 100, false));
        }
    }

    #[test]
    fn serialisation_and_queue_limit() {
        // 8 Mbit/s: a 972 + 28 = 1000-byte packet takes 1 ms.
        let cfg =
            LinkConfig::new(Some(8_000_000), Duration::from_millis(10)).with_queue_limit(5_000);
        let mut s = Shaper::new(cfg, 0);
        let t0 = Instant::now();
        let mut delivered = Vec::new();
        let mut queue_drops = 0;
        for _ in 0..20 {
            match s.decide(t0, 972, false) {
                Verdict::Deliver(at) => delivered.push(at - t0),
                Verdict::DropQueue => queue_drops += 1,
                v => panic!("unexpected {v:?}"),
            }
        }
        // Backlog after k packets is k kB; a packet is admitted while
        // backlog + 1 kB <= 5 kB, i.e. 5 packets in a burst.
        assert_eq!(delivered.len(), 5);
        assert_eq!(queue_drops, 15);
        for (k, d) in delivered.iter().enumerate() {
            assert_eq!(*d, Duration::from_millis(10 + k as u64 + 1));
        }
        // Once the queue drains, packets are admitted again.
        let later = t0 + Duration::from_millis(5);
        assert_eq!(
            s.decide(later, 972, false),
            Verdict::Deliver(later + Duration::from_millis(11))
        );
    }

    #[test]
    fn jitter_alone_keeps_order_and_reorder_breaks_it() {
        let t0 = Instant::now();
        let order = |cfg: LinkConfig| {
            let mut s = Shaper::new(cfg, 0);
            let mut times = Vec::new();
            for i in 0..1000u64 {
                if let Verdict::Deliver(at) =
                    s.decide(t0 + Duration::from_micros(i * 200), 100, false)
                {
                    times.push(at);
                }
            }
            times.windows(2).filter(|w| w[1] < w[0]).count()
        };
        let base = LinkConfig::new(None, Duration::from_millis(20));
        assert_eq!(
            order(base.clone().with_jitter(Duration::from_millis(10))),
            0
        );
        assert_eq!(order(base.clone()), 0);
        assert!(order(base.with_reorder(0.1)) > 20);
    }

    #[test]
    fn jitter_spread() {
        let t0 = Instant::now();
        let cfg =
            LinkConfig::new(None, Duration::from_millis(50)).with_jitter(Duration::from_millis(10));
        let mut s = Shaper::new(cfg, 0);
        let mut min = Duration::MAX;
        let mut max = Duration::ZERO;
        // Sparse packets so the FIFO floor never binds.
        for i in 0..2000u64 {
            let now = t0 + Duration::from_millis(i * 100);
            if let Verdict::Deliver(at) = s.decide(now, 100, false) {
                let d = at - now;
                min = min.min(d);
                max = max.max(d);
            }
        }
        assert!(
            min >= Duration::from_millis(40) && min < Duration::from_millis(41),
            "{min:?}"
        );
        assert!(
            max <= Duration::from_millis(60) && max > Duration::from_millis(59),
            "{max:?}"
        );
    }
}
