//! What one run measured, and the state its request loops share.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use planet_session::net::Connection;

use super::*;

/// Results of one side.
#[derive(Debug, Clone, Default)]
pub struct RunResult {
    /// Label.
    pub label: String,
    /// Completed requests.
    pub requests: u64,
    /// Body bytes received.
    pub bytes: u64,
    /// Failed requests.
    pub errors: u64,
    /// First error seen.
    pub first_error: Option<String>,
    /// Timed window (first request to last response).
    pub wall: Duration,
    /// Latency.
    pub latency: Latency,
    /// Server CPU seconds in the window (None when not measurable).
    pub server_cpu: Option<f64>,
    /// Connections used.
    pub connections: usize,
    /// CPU seconds of the bench process (the clients) in the window.
    pub client_cpu: f64,
    /// Open-loop runs: the offered load (requests/s).
    pub offered: Option<f64>,
    /// Open-loop runs: how late the client started requests against their
    /// schedule (client-side overhead, included in `latency`).
    pub lag: Option<Latency>,
    /// QUIC runs: datagrams of the window, from the client connections'
    /// quinn statistics.
    pub udp: Option<UdpCounts>,
    /// An open-loop warm-up (`--warmup`): printed, not compared.
    pub warmup: bool,
}

/// UDP datagram counts of the client's QUIC connections over a window.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UdpCounts {
    /// Datagrams received (server to client).
    pub rx_datagrams: u64,
    /// Bytes received in them (UDP payload).
    pub rx_bytes: u64,
    /// Datagrams sent (client to server).
    pub tx_datagrams: u64,
    /// Packets of the client's own that were declared lost (the server's
    /// losses are not visible client-side).
    pub client_lost_packets: u64,
}

impl UdpCounts {
    /// Sums the statistics of `conns` now.
    pub fn of(conns: &[Connection]) -> UdpCounts {
        conns.iter().fold(UdpCounts::default(), |acc, c| {
            let s = c.quinn().stats();
            UdpCounts {
                rx_datagrams: acc.rx_datagrams + s.udp_rx.datagrams,
                rx_bytes: acc.rx_bytes + s.udp_rx.bytes,
                tx_datagrams: acc.tx_datagrams + s.udp_tx.datagrams,
                client_lost_packets: acc.client_lost_packets + s.path.lost_packets,
            }
        })
    }

    /// `self - before`, saturating.
    pub fn since(&self, before: &UdpCounts) -> UdpCounts {
        UdpCounts {
            rx_datagrams: self.rx_datagrams.saturating_sub(before.rx_datagrams),
            rx_bytes: self.rx_bytes.saturating_sub(before.rx_bytes),
            tx_datagrams: self.tx_datagrams.saturating_sub(before.tx_datagrams),
            client_lost_packets: self
                .client_lost_packets
                .saturating_sub(before.client_lost_packets),
        }
    }
}

impl RunResult {
    /// Requests per second.
    pub fn rps(&self) -> f64 {
        self.requests as f64 / self.wall.as_secs_f64().max(1e-9)
    }
    /// Megabytes (10^6) per second.
    pub fn mbps(&self) -> f64 {
        self.bytes as f64 / 1e6 / self.wall.as_secs_f64().max(1e-9)
    }
    pub(crate) fn print(&self) {
        let cpu = match self.server_cpu {
            Some(c) => format!(
                "{:.0} % of one core ({:.1} µs CPU/request)",
                100.0 * c / self.wall.as_secs_f64().max(1e-9),
                1e6 * c / self.requests.max(1) as f64
            ),
            None => "n/a (in-process)".into(),
        };
        let cpu = format!(
            "{cpu}, client CPU {:.1} µs/request",
            1e6 * self.client_cpu / self.requests.max(1) as f64
        );
        let offered = match self.offered {
            Some(r) => format!(" (offered {r:.0})"),
            None => String::new(),
        };
        println!(
            "{:<8} {:>5} conns  {:>9.0} req/s{}  {:>8.1} MB/s  p50 {}  p90 {}  p99 {}  max {}  errors {}  server CPU {}",
            self.label,
            self.connections,
            self.rps(),
            offered,
            self.mbps(),
            ms(self.latency.p50),
            ms(self.latency.p90),
            ms(self.latency.p99),
            ms(self.latency.max),
            self.errors,
            cpu
        );
        if let Some(l) = &self.lag {
            println!(
                "         client start lag vs schedule: p50 {}  p99 {}  max {}",
                ms(l.p50),
                ms(l.p99),
                ms(l.max)
            );
        }
        if let Some(u) = &self.udp {
            let n = self.requests.max(1) as f64;
            println!(
                "         UDP datagrams per request: {:.2} server->client (mean {:.0} B), {:.2} client->server; client packets lost {}",
                u.rx_datagrams as f64 / n,
                u.rx_bytes as f64 / u.rx_datagrams.max(1) as f64,
                u.tx_datagrams as f64 / n,
                u.client_lost_packets
            );
        }
        if let Some(e) = &self.first_error {
            println!("         first error: {e}");
        }
    }
}

#[derive(Default)]
pub(crate) struct LoopStats {
    pub(crate) lat_us: Vec<u32>,
    pub(crate) bytes: u64,
    pub(crate) errors: u64,
    pub(crate) first_error: Option<String>,
}

impl LoopStats {
    pub(crate) fn merge(&mut self, o: LoopStats) {
        self.lat_us.extend(o.lat_us);
        self.bytes += o.bytes;
        self.errors += o.errors;
        if self.first_error.is_none() {
            self.first_error = o.first_error;
        }
    }
    pub(crate) fn error(&mut self, e: String) {
        self.errors += 1;
        if self.first_error.is_none() {
            self.first_error = Some(e);
        }
    }
}

/// Shared request cursor: request `i` is `list[i % len]`; stops at `limit`
/// or at the deadline.
pub(crate) struct Cursor {
    pub(crate) list: Arc<Vec<Req>>,
    pub(crate) next: AtomicUsize,
    pub(crate) limit: usize,
    pub(crate) deadline: Instant,
}

impl Cursor {
    pub(crate) fn take(&self) -> Option<(usize, Req)> {
        if Instant::now() >= self.deadline {
            return None;
        }
        let i = self.next.fetch_add(1, Ordering::Relaxed);
        if i >= self.limit {
            return None;
        }
        Some((i, self.list[i % self.list.len()]))
    }
}

pub(crate) fn new_cursor(list: &Arc<Vec<Req>>, args: &ServerArgs, start: Instant) -> Arc<Cursor> {
    let (limit, deadline) = match args.requests {
        Some(n) => (n, start + Duration::from_secs(24 * 3600)),
        None => (usize::MAX, start + Duration::from_secs_f64(args.seconds)),
    };
    Arc::new(Cursor {
        list: list.clone(),
        next: AtomicUsize::new(0),
        limit,
        deadline,
    })
}
