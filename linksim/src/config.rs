//! [`LinkConfig`]: the parameters of one direction of a simulated link, its
//! presets, builders and its textual form (`"10mbit,50ms,2%loss"`).

use std::fmt;
use std::str::FromStr;
use std::time::Duration;

use thiserror::Error;

/// Bytes of IPv4 + UDP header counted on the wire for every datagram, on top
/// of its payload, when the bandwidth limit is applied.
pub const PER_PACKET_OVERHEAD: usize = 28;

/// Queue limit used when the link has no bandwidth limit (the queue never
/// builds up then, so the value hardly matters) and as the textual default.
pub const DEFAULT_QUEUE_LIMIT: usize = 256 * 1024;

/// Smallest default queue limit of a rate-limited link (about 43 full-size
/// packets), so that links with tiny delays still absorb a burst.
pub const MIN_DEFAULT_QUEUE_LIMIT: usize = 64 * 1024;

/// Extra delay given to a reordered packet by default (see
/// [`LinkConfig::reorder_delay`]).
pub const DEFAULT_REORDER_DELAY: Duration = Duration::from_millis(10);

/// Parameters of one direction of a simulated link.
///
/// A datagram entering the link first waits in a drop-tail bottleneck queue
/// of `queue_limit_bytes` that drains at `bandwidth_bps`; then, with
/// probability `loss`, it is lost on the wire; otherwise it arrives after
/// `delay` ± `jitter` (uniform). With probability `reorder` it is held back
/// a further `reorder_delay` × U(0.5, 1.5), so that packets sent after it
/// overtake it. Jitter alone never reorders packets (see the crate docs).
///
/// The default is [`LinkConfig::loopback`].
#[derive(Debug, Clone, PartialEq)]
pub struct LinkConfig {
    /// Bottleneck rate in bits per second, counting payload plus
    /// [`PER_PACKET_OVERHEAD`] bytes per datagram. `None` = unlimited.
    /// `Some(0)` drops every packet (at the queue).
    pub bandwidth_bps: Option<u64>,
    /// One-way propagation delay.
    pub delay: Duration,
    /// Maximum deviation from `delay`, drawn uniformly from ±`jitter`.
    pub jitter: Duration,
    /// Probability (0..=1) that a packet is lost (Bernoulli, independent).
    pub loss: f64,
    /// Probability (0..=1) that a packet is delayed by an extra
    /// `reorder_delay` × U(0.5, 1.5), letting later packets overtake it.
    pub reorder: f64,
    /// Mean extra delay of a reordered packet.
    pub reorder_delay: Duration,
    /// Drop-tail limit of the bottleneck queue in bytes (like a router
    /// buffer). Only meaningful when `bandwidth_bps` is set.
    pub queue_limit_bytes: usize,
    /// Seed of the ChaCha RNG that draws loss, jitter and reordering.
    pub seed: u64,
}

impl Default for LinkConfig {
    fn default() -> Self {
        Self::loopback()
    }
}

impl LinkConfig {
    /// No limits, no delay, no loss: a plain relay.
    pub fn loopback() -> Self {
        Self {
            bandwidth_bps: None,
            delay: Duration::ZERO,
            jitter: Duration::ZERO,
            loss: 0.0,
            reorder: 0.0,
            reorder_delay: DEFAULT_REORDER_DELAY,
            queue_limit_bytes: DEFAULT_QUEUE_LIMIT,
            seed: 0,
        }
    }

    /// A link of the given rate and one-way delay, with the default queue
    /// limit for them ([`LinkConfig::default_queue_limit`]) and nothing else.
    pub fn new(bandwidth_bps: Option<u64>, delay: Duration) -> Self {
        Self {
            bandwidth_bps,
            delay,
            queue_limit_bytes: Self::default_queue_limit(bandwidth_bps, delay),
            ..Self::loopback()
        }
    }

    /// A link of `mbit` Mbit/s (10^6 bit/s) and `delay_ms` one-way delay.
    ///
    /// # Panics
    /// If `mbit` is not a finite positive number.
    pub fn mbit(mbit: f64, delay_ms: u64) -> Self {
        assert!(
            mbit.is_finite() && mbit > 0.0,
            "LinkConfig::mbit: rate must be finite and positive, got {mbit}"
        );
        let bps = (mbit * 1e6).round().max(1.0) as u64;
        Self::new(Some(bps), Duration::from_millis(delay_ms))
    }

    /// Default bottleneck buffer: the bandwidth-delay product over the round
    /// trip (2 × `delay`), at least [`MIN_DEFAULT_QUEUE_LIMIT`];
    /// [`DEFAULT_QUEUE_LIMIT`] without a rate limit.
    pub fn default_queue_limit(bandwidth_bps: Option<u64>, delay: Duration) -> usize {
        match bandwidth_bps {
            None => DEFAULT_QUEUE_LIMIT,
            Some(bps) => {
                let rtt = delay.saturating_mul(2).as_nanos();
                let bdp = (bps as u128).saturating_mul(rtt) / 8_000_000_000;
                usize::try_from(bdp)
                    .unwrap_or(usize::MAX)
                    .max(MIN_DEFAULT_QUEUE_LIMIT)
            }
        }
    }

    /// Sets the loss probability (clamped to 0..=1; NaN counts as 0).
    pub fn with_loss(mut self, p: f64) -> Self {
        self.loss = clamp_probability(p);
        self
    }

    /// Sets the reordering probability (clamped to 0..=1; NaN counts as 0).
    pub fn with_reorder(mut self, p: f64) -> Self {
        self.reorder = clamp_probability(p);
        self
    }

    /// Sets the mean extra delay of a reordered packet.
    pub fn with_reorder_delay(mut self, d: Duration) -> Self {
        self.reorder_delay = d;
        self
    }

    /// Sets the jitter (uniform ± `d` around the delay).
    pub fn with_jitter(mut self, d: Duration) -> Self {
        self.jitter = d;
        self
    }

    /// Sets the bottleneck queue limit in bytes.
    pub fn with_queue_limit(mut self, bytes: usize) -> Self {
        self.queue_limit_bytes = bytes;
        self
    }

    /// Sets the RNG seed.
    pub fn with_seed(mut self, seed: u64) -> Self {
        self.seed = seed;
        self
    }
}

fn clamp_probability(p: f64) -> f64 {
    if p.is_nan() {
        0.0
    } else {
        p.clamp(0.0, 1.0)
    }
}

/// Why a link description such as `"10mbit,50ms,2%loss"` could not be parsed.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum ParseLinkConfigError {
    /// The description is empty.
    #[error("empty link description (try `loopback` or `10mbit,50ms`)")]
    Empty,
    /// A token is neither a rate, a duration, a `N%loss`/`N%reorder` nor a
    /// known `key=value`.
    #[error(
        "unrecognised link token `{0}` (expected e.g. `10mbit`, `50ms`, `2%loss`, `1%reorder`, \
         `jitter=5ms`, `queue=64kb`, `seed=7`, `loopback`)"
    )]
    UnknownToken(String),
    /// A number or unit in a token is malformed.
    #[error("invalid value in link token `{0}`")]
    InvalidValue(String),
    /// A probability is outside 0..=100 %.
    #[error("probability out of range in link token `{0}` (must be 0..=100%)")]
    OutOfRange(String),
    /// The same parameter is given twice (or `loopback` together with a rate).
    #[error("link parameter `{0}` given more than once")]
    Duplicate(&'static str),
}

impl FromStr for LinkConfig {
    type Err = ParseLinkConfigError;

    /// Parses a comma-separated description. Tokens (case-insensitive):
    /// `loopback` (no rate limit), a rate (`10mbit`, `1.5mbps`, `500kbit`,
    /// `1gbit`, `64000bit`), a bare duration (the one-way delay: `50ms`,
    /// `1s`, `500us`), `2%loss`, `1%reorder`, and `key=value` with keys
    /// `rate`, `delay`, `jitter`, `loss`, `reorder`, `reorder_delay`,
    /// `queue` (`64kb`, `64kib`, `1mb`, `65536`) and `seed`. `loss` and
    /// `reorder` values are probabilities (`0.02`) or percentages (`2%`).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let mut rate: Option<Option<u64>> = None;
        let mut delay: Option<Duration> = None;
        let mut jitter: Option<Duration> = None;
        let mut loss: Option<f64> = None;
        let mut reorder: Option<f64> = None;
        let mut reorder_delay: Option<Duration> = None;
        let mut queue: Option<usize> = None;
        let mut seed: Option<u64> = None;

        fn set<T>(
            slot: &mut Option<T>,
            v: T,
            name: &'static str,
        ) -> Result<(), ParseLinkConfigError> {
            if slot.is_some() {
                return Err(ParseLinkConfigError::Duplicate(name));
            }
            *slot = Some(v);
            Ok(())
        }

        let mut any = false;
        for raw in s.split(',') {
            let tok = raw.trim().to_ascii_lowercase();
            if tok.is_empty() {
                continue;
            }
            any = true;
            let bad = || ParseLinkConfigError::InvalidValue(raw.trim().to_string());
            if tok == "loopback" || tok == "lo" || tok == "unlimited" {
                set(&mut rate, None, "rate")?;
            } else if let Some((key, value)) = tok.split_once('=') {
                let value = value.trim();
                match key.trim() {
                    "rate" | "bw" | "bandwidth" => {
                        set(&mut rate, Some(parse_rate(value).ok_or_else(bad)?), "rate")?
                    }
                    "delay" => set(&mut delay, parse_duration(value).ok_or_else(bad)?, "delay")?,
                    "jitter" => set(
                        &mut jitter,
                        parse_duration(value).ok_or_else(bad)?,
                        "jitter",
                    )?,
                    "reorder_delay" | "reorder-delay" => set(
                        &mut reorder_delay,
                        parse_duration(value).ok_or_else(bad)?,
                        "reorder_delay",
                    )?,
                    "loss" => set(&mut loss, parse_probability(value, raw)?, "loss")?,
                    "reorder" => set(&mut reorder, parse_probability(value, raw)?, "reorder")?,
                    "queue" | "limit" => {
                        set(&mut queue, parse_bytes(value).ok_or_else(bad)?, "queue")?
                    }
                    "seed" => set(&mut seed, value.parse::<u64>().map_err(|_| bad())?, "seed")?,
                    _ => return Err(ParseLinkConfigError::UnknownToken(raw.trim().to_string())),
                }
            } else if let Some(p) = tok.strip_suffix("loss") {
                set(&mut loss, parse_probability(p.trim(), raw)?, "loss")?;
            } else if let Some(p) = tok.strip_suffix("reorder") {
                set(&mut reorder, parse_probability(p.trim(), raw)?, "reorder")?;
            } else if let Some(bps) = parse_rate(&tok) {
                set(&mut rate, Some(bps), "rate")?;
            } else if let Some(d) = parse_duration(&tok) {
                set(&mut delay, d, "delay")?;
            } else if starts_numeric(&tok) {
                return Err(bad());
            } else {
                return Err(ParseLinkConfigError::UnknownToken(raw.trim().to_string()));
            }
        }
        if !any {
            return Err(ParseLinkConfigError::Empty);
        }

        let mut cfg = LinkConfig::new(rate.flatten(), delay.unwrap_or(Duration::ZERO));
        if let Some(j) = jitter {
            cfg.jitter = j;
        }
        if let Some(p) = loss {
            cfg.loss = p;
        }
        if let Some(p) = reorder {
            cfg.reorder = p;
        }
        if let Some(d) = reorder_delay {
            cfg.reorder_delay = d;
        }
        if let Some(q) = queue {
            cfg.queue_limit_bytes = q;
        }
        if let Some(s) = seed {
            cfg.seed = s;
        }
        Ok(cfg)
    }
}

fn starts_numeric(s: &str) -> bool {
    s.starts_with(|c: char| c.is_ascii_digit() || c == '.' || c == '-' || c == '+')
}

/// Splits `"12.5mbit"` into `(12.5, "mbit")`; the number must be finite and
/// non-negative.
fn split_number(s: &str) -> Option<(f64, &str)> {
    let end = s
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(s.len());
    if end == 0 {
        return None;
    }
    let n: f64 = s[..end].parse().ok()?;
    if !n.is_finite() || n < 0.0 {
        return None;
    }
    Some((n, s[end..].trim()))
}

fn parse_rate(s: &str) -> Option<u64> {
    let (n, unit) = split_number(s)?;
    let mult = match unit {
        "bit" | "bps" => 1.0,
        "kbit" | "kbps" => 1e3,
        "mbit" | "mbps" => 1e6,
        "gbit" | "gbps" => 1e9,
        _ => return None,
    };
    let bps = (n * mult).round();
    if bps > u64::MAX as f64 {
        return None;
    }
    Some(bps as u64)
}

fn parse_duration(s: &str) -> Option<Duration> {
    let (n, unit) = split_number(s)?;
    let secs = match unit {
        "s" => n,
        "ms" => n / 1e3,
        "us" | "µs" => n / 1e6,
        "ns" => n / 1e9,
        _ => return None,
    };
    Duration::try_from_secs_f64(secs).ok()
}

fn parse_bytes(s: &str) -> Option<usize> {
    let (n, unit) = split_number(s)?;
    let mult = match unit {
        "" | "b" => 1.0,
        "kb" | "k" => 1e3,
        "kib" => 1024.0,
        "mb" | "m" => 1e6,
        "mib" => 1024.0 * 1024.0,
        _ => return None,
    };
    let b = (n * mult).round();
    if b > usize::MAX as f64 {
        return None;
    }
    Some(b as usize)
}

fn parse_probability(value: &str, raw: &str) -> Result<f64, ParseLinkConfigError> {
    let bad = || ParseLinkConfigError::InvalidValue(raw.trim().to_string());
    let (p, is_percent) = match value.strip_suffix('%') {
        Some(v) => (v.trim(), true),
        None => (value, false),
    };
    let (n, rest) = split_number(p).ok_or_else(bad)?;
    if !rest.is_empty() {
        return Err(bad());
    }
    let n = if is_percent { n / 100.0 } else { n };
    if !(0.0..=1.0).contains(&n) {
        return Err(ParseLinkConfigError::OutOfRange(raw.trim().to_string()));
    }
    Ok(n)
}

fn fmt_duration(d: Duration) -> String {
    let ns = d.as_nanos();
    if ns.is_multiple_of(1_000_000_000) && ns != 0 {
        format!("{}s", ns / 1_000_000_000)
    } else if ns.is_multiple_of(1_000_000) {
        format!("{}ms", ns / 1_000_000)
    } else if ns.is_multiple_of(1_000) {
        format!("{}us", ns / 1_000)
    } else {
        format!("{ns}ns")
    }
}

/// Writes the textual form accepted by [`FromStr`]; `parse(to_string())`
/// gives back an equal config. Parameters at their defaults are left out.
impl fmt::Display for LinkConfig {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut parts: Vec<String> = Vec::new();
        match self.bandwidth_bps {
            None => parts.push("loopback".into()),
            Some(b) if b.is_multiple_of(1_000_000_000) && b != 0 => {
                parts.push(format!("{}gbit", b / 1_000_000_000))
            }
            Some(b) if b.is_multiple_of(1_000_000) && b != 0 => {
                parts.push(format!("{}mbit", b / 1_000_000))
            }
            Some(b) if b.is_multiple_of(1_000) && b != 0 => {
                parts.push(format!("{}kbit", b / 1_000))
            }
            Some(b) => parts.push(format!("{b}bit")),
        }
        if !self.delay.is_zero() {
            parts.push(fmt_duration(self.delay));
        }
        if !self.jitter.is_zero() {
            parts.push(format!("jitter={}", fmt_duration(self.jitter)));
        }
        if self.loss != 0.0 {
            parts.push(format!("loss={}", self.loss));
        }
        if self.reorder != 0.0 {
            parts.push(format!("reorder={}", self.reorder));
        }
        if self.reorder_delay != DEFAULT_REORDER_DELAY {
            parts.push(format!(
                "reorder_delay={}",
                fmt_duration(self.reorder_delay)
            ));
        }
        if self.queue_limit_bytes != Self::default_queue_limit(self.bandwidth_bps, self.delay) {
            parts.push(format!("queue={}", self.queue_limit_bytes));
        }
        if self.seed != 0 {
            parts.push(format!("seed={}", self.seed));
        }
        f.write_str(&parts.join(","))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_examples() {
        let c: LinkConfig = "10mbit,50ms".parse().expect("parse");
        assert_eq!(c, LinkConfig::mbit(10.0, 50));
        assert_eq!(c.bandwidth_bps, Some(10_000_000));
        assert_eq!(c.delay, Duration::from_millis(50));
        // BDP over 100 ms RTT at 10 Mbit/s = 125 kB.
        assert_eq!(c.queue_limit_bytes, 125_000);

        let c: LinkConfig = "1mbit,100ms,2%loss".parse().expect("parse");
        assert_eq!(c.bandwidth_bps, Some(1_000_000));
        assert_eq!(c.delay, Duration::from_millis(100));
        assert!((c.loss - 0.02).abs() < 1e-12);
        assert_eq!(c.queue_limit_bytes, MIN_DEFAULT_QUEUE_LIMIT);

        let c: LinkConfig = "loopback".parse().expect("parse");
        assert_eq!(c, LinkConfig::loopback());

        let c: LinkConfig =
            " 1.5Mbps , 20ms, jitter=5ms, 1%reorder, queue=32kib, seed=9, loss=0.1 "
                .parse()
                .expect("parse");
        assert_eq!(c.bandwidth_bps, Some(1_500_000));
        assert_eq!(c.jitter, Duration::from_millis(5));
        assert!((c.reorder - 0.01).abs() < 1e-12);
        assert_eq!(c.queue_limit_bytes, 32 * 1024);
        assert_eq!(c.seed, 9);
        assert!((c.loss - 0.1).abs() < 1e-12);

        let c: LinkConfig = "loopback,25ms,reorder=5%,reorder_delay=3ms"
            .parse()
            .expect("parse");
        assert_eq!(c.bandwidth_bps, None);
        assert_eq!(c.delay, Duration::from_millis(25));
        assert_eq!(c.reorder_delay, Duration::from_millis(3));
    }

    #[test]
    fn rejects_garbage() {
        use ParseLinkConfigError as E;
        assert_eq!("".parse::<LinkConfig>(), Err(E::Empty));
        assert_eq!(" , ".parse::<LinkConfig>(), Err(E::Empty));
        assert!(matches!(
            "fast".parse::<LinkConfig>(),
            Err(E::UnknownToken(_))
        ));
        assert!(matches!(
            "10furlongs".parse::<LinkConfig>(),
            Err(E::InvalidValue(_))
        ));
        assert!(matches!(
            "1mbit,150%loss".parse::<LinkConfig>(),
            Err(E::OutOfRange(_))
        ));
        assert!(matches!(
            "1mbit,x%loss".parse::<LinkConfig>(),
            Err(E::InvalidValue(_))
        ));
        assert!(matches!(
            "1mbit,-5ms".parse::<LinkConfig>(),
            Err(E::InvalidValue(_))
        ));
        assert!(matches!(
            "1mbit,colour=red".parse::<LinkConfig>(),
            Err(E::UnknownToken(_))
        ));
        assert_eq!(
            "1mbit,2mbit".parse::<LinkConfig>(),
            Err(E::Duplicate("rate"))
        );
        assert_eq!(
            "loopback,2mbit".parse::<LinkConfig>(),
            Err(E::Duplicate("rate"))
        );
        assert_eq!(
            "10ms,20ms".parse::<LinkConfig>(),
            Err(E::Duplicate("delay"))
        );
        assert!(matches!(
            "seed=-1".parse::<LinkConfig>(),
            Err(E::InvalidValue(_))
        ));
    }

    #[test]
    fn display_round_trips() {
        let configs = [
            LinkConfig::loopback(),
            LinkConfig::mbit(10.0, 50),
            LinkConfig::mbit(1.5, 0),
            LinkConfig::mbit(0.064, 250)
                .with_loss(0.02)
                .with_reorder(0.015)
                .with_reorder_delay(Duration::from_micros(2500))
                .with_jitter(Duration::from_millis(7))
                .with_queue_limit(12_345)
                .with_seed(42),
            LinkConfig::new(Some(1_234_567), Duration::from_secs(1)),
        ];
        for c in configs {
            let s = c.to_string();
            let back: LinkConfig = s.parse().unwrap_or_else(|e| panic!("{s}: {e}"));
            assert_eq!(back, c, "{s}");
        }
        assert_eq!(LinkConfig::mbit(10.0, 50).to_string(), "10mbit,50ms");
    }

    #[test]
    fn builders_clamp_probabilities() {
        let c = LinkConfig::loopback().with_loss(2.0).with_reorder(f64::NAN);
        assert_eq!(c.loss, 1.0);
        assert_eq!(c.reorder, 0.0);
    }
}
