//! The link for kernel TCP (ISSUE #19): a network namespace joined to this
//! one by two TUN devices, whose IP packets this process moves from one to
//! the other through the same shaper (`shaper.rs`) as the UDP relay, so that TCP's
//! own loss recovery, congestion control and head-of-line blocking are what
//! a benchmark measures.
//!
//! ```text
//!   this namespace                         namespace `planet-…` (servers)
//!   client ── 10.200.a.b+1 ─ tun "plc…" ─┐   ┌─ tun "pls…" ─ 10.200.a.b+2 ── nginx
//!                                        └─ this process: up/down shapers ┘
//! ```
//!
//! A server is started inside the namespace ([`TcpLink::command`], i.e.
//! `ip netns exec NS …`) listening on [`TcpLink::server_ip`]; clients here
//! connect to that address and their packets cross the link. Only addresses
//! inside the namespace this link created, and the point-to-point pair, are
//! used. Needs root (or `CAP_NET_ADMIN` and `CAP_SYS_ADMIN`), `/dev/net/tun`
//! and iproute2's `ip`. Dropping the link deletes the namespace and both
//! devices.
//!
//! Bytes on the wire: the shaper adds [`crate::config::PER_PACKET_OVERHEAD`]
//! (IPv4 + UDP headers) to a UDP payload; here the packets are whole IP
//! packets, so that much is subtracted first and every packet counts its
//! real size, headers included, against the bandwidth.

use std::io;
use std::net::Ipv4Addr;
use std::process::Command;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use tokio::sync::mpsc;
use tokio::task::AbortHandle;
use tokio_tun::Tun;

use crate::config::{LinkConfig, PER_PACKET_OVERHEAD};
use crate::delivery::delivery_loop;
use crate::shaper::{Shaper, Timed, Verdict};

/// Largest IP packet read from a TUN device (its MTU is 1 500).
const MAX_PACKET: usize = 65_536;

/// Links made by this process (for unique names and subnets).
static NEXT: AtomicU64 = AtomicU64::new(0);

/// Counters of a [`TcpLink`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TcpLinkStats {
    /// IP packets that entered the link towards the servers.
    pub packets_up: u64,
    /// IP packets that entered the link towards the clients.
    pub packets_down: u64,
    /// Bytes (whole IP packets) delivered towards the clients.
    pub bytes_down: u64,
    /// Packets lost at random (both directions).
    pub dropped_loss: u64,
    /// Packets dropped at a full bottleneck queue (both directions).
    pub dropped_queue: u64,
}

#[derive(Default)]
struct Counters {
    packets_up: AtomicU64,
    packets_down: AtomicU64,
    bytes_down: AtomicU64,
    dropped_loss: AtomicU64,
    dropped_queue: AtomicU64,
}

/// A shaped link between this namespace and a new one ([module docs](self)).
pub struct TcpLink {
    ns: String,
    /// The namespace's TUN device.
    far_dev: String,
    client_ip: Ipv4Addr,
    server_ip: Ipv4Addr,
    counters: Arc<Counters>,
    tasks: Vec<AbortHandle>,
}

fn ip(args: &[&str]) -> io::Result<()> {
    let out = Command::new("ip").args(args).output()?;
    if out.status.success() {
        Ok(())
    } else {
        Err(io::Error::other(format!(
            "ip {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        )))
    }
}

impl TcpLink {
    /// Creates the namespace and the two devices and starts moving packets
    /// through `up` (towards the namespace) and `down`. Must be called
    /// inside a tokio runtime.
    pub async fn start(up: LinkConfig, down: LinkConfig) -> io::Result<TcpLink> {
        let k = (u64::from(std::process::id()) << 8) + NEXT.fetch_add(1, Ordering::Relaxed);
        // 10.200.0.0/16 in /30s: 16 384 links.
        let slot = (k % 16_384) as u32;
        let base = u32::from(Ipv4Addr::new(10, 200, 0, 0)) + slot * 4;
        let client_ip = Ipv4Addr::from(base + 1);
        let server_ip = Ipv4Addr::from(base + 2);
        let ns = format!("planet-{slot}-{}", std::process::id());
        ip(&["netns", "add", &ns])?;
        let mut link = TcpLink {
            far_dev: format!("pls{slot}"),
            ns,
            client_ip,
            server_ip,
            counters: Arc::new(Counters::default()),
            tasks: Vec::new(),
        };
        // From here on, Drop deletes the namespace on any error.
        ip(&["netns", "exec", &link.ns, "ip", "link", "set", "lo", "up"])?;
        let near = point_to_point(&format!("plc{slot}"), client_ip, server_ip)?;
        let far = in_namespace(&link.ns, || {
            point_to_point(&link.far_dev, server_ip, client_ip)
        })?;
        let (near, far) = (Arc::new(near), Arc::new(far));
        let (up_tx, up_rx) = mpsc::unbounded_channel();
        let (down_tx, down_rx) = mpsc::unbounded_channel();
        let up_shaper = Arc::new(Mutex::new(Shaper::new(up, 0x7570)));
        let down_shaper = Arc::new(Mutex::new(Shaper::new(down, 0x646f)));
        let c = &link.counters;
        link.tasks = vec![
            tokio::spawn(read_loop(
                Arc::clone(&near),
                up_shaper,
                up_tx,
                Arc::clone(c),
                true,
            ))
            .abort_handle(),
            tokio::spawn(read_loop(
                Arc::clone(&far),
                down_shaper,
                down_tx,
                Arc::clone(c),
                false,
            ))
            .abort_handle(),
            tokio::spawn(delivery_loop(up_rx, move |p| write(Arc::clone(&far), p))).abort_handle(),
            tokio::spawn(delivery_loop(down_rx, {
                let c = Arc::clone(c);
                move |p: Vec<u8>| {
                    c.bytes_down.fetch_add(p.len() as u64, Ordering::Relaxed);
                    write(Arc::clone(&near), p)
                }
            }))
            .abort_handle(),
        ];
        Ok(link)
    }

    /// The namespace's name (`ip netns exec NAME …`).
    pub fn namespace(&self) -> &str {
        &self.ns
    }

    /// The servers' address, inside the namespace.
    pub fn server_ip(&self) -> Ipv4Addr {
        self.server_ip
    }

    /// This side's address of the point-to-point pair.
    pub fn client_ip(&self) -> Ipv4Addr {
        self.client_ip
    }

    /// A command that runs `program` inside the namespace.
    pub fn command(&self, program: impl AsRef<std::ffi::OsStr>) -> Command {
        let mut c = Command::new("ip");
        c.args(["netns", "exec", &self.ns]).arg(program);
        c
    }

    /// The TCP congestion control of the namespace's connections to this
    /// side from now on (the servers' sending side): e.g. `cubic`, Linux's
    /// default, or `bbr`. Set on the namespace's route back
    /// (`ip route … congctl`): a namespace other than the host's may not
    /// change its default to an algorithm the host restricts, and starts
    /// with the host's default. Fails on a name the kernel does not offer
    /// (`net.ipv4.tcp_available_congestion_control`).
    pub fn set_tcp_congestion(&self, algorithm: &str) -> io::Result<()> {
        let (client, server) = (self.client_ip.to_string(), self.server_ip.to_string());
        ip(&[
            "-n",
            &self.ns,
            "route",
            "replace",
            &format!("{client}/32"),
            "dev",
            &self.far_dev,
            "src",
            &server,
            "congctl",
            algorithm,
        ])
        .map_err(|e| {
            io::Error::new(
                e.kind(),
                format!("TCP congestion control {algorithm:?} on the link's route: {e}"),
            )
        })
    }

    /// The TCP congestion control the namespace's connections to this side
    /// get: the route's (`congctl`), else the namespace's default.
    pub fn tcp_congestion(&self) -> io::Result<String> {
        let client = self.client_ip.to_string();
        let out = Command::new("ip")
            .args(["-n", &self.ns, "route", "show", &format!("{client}/32")])
            .output()?;
        let route = String::from_utf8_lossy(&out.stdout);
        let mut words = route.split_whitespace();
        if words.any(|w| w == "congctl") {
            if let Some(a) = words.next() {
                return Ok(a.to_string());
            }
        }
        in_namespace(&self.ns, || {
            Ok(std::fs::read_to_string(TCP_CONGESTION)?.trim().to_string())
        })
    }

    /// The counters so far.
    pub fn stats(&self) -> TcpLinkStats {
        let c = &self.counters;
        TcpLinkStats {
            packets_up: c.packets_up.load(Ordering::Relaxed),
            packets_down: c.packets_down.load(Ordering::Relaxed),
            bytes_down: c.bytes_down.load(Ordering::Relaxed),
            dropped_loss: c.dropped_loss.load(Ordering::Relaxed),
            dropped_queue: c.dropped_queue.load(Ordering::Relaxed),
        }
    }
}

impl Drop for TcpLink {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
        if let Err(e) = ip(&["netns", "del", &self.ns]) {
            tracing::warn!(error = %e, ns = %self.ns, "linksim: cannot delete the namespace");
        }
    }
}

/// Runs `f` on a thread that joined namespace `ns` (network settings under
/// `/proc/sys/net` and devices created there belong to that namespace),
/// inside the current tokio runtime's context.
fn in_namespace<T: Send>(ns: &str, f: impl FnOnce() -> io::Result<T> + Send) -> io::Result<T> {
    let path = format!("/run/netns/{ns}");
    let handle = tokio::runtime::Handle::try_current().ok();
    std::thread::scope(|s| {
        s.spawn(|| {
            let file = std::fs::File::open(&path)?;
            rustix::thread::move_into_link_name_space(
                std::os::fd::AsFd::as_fd(&file),
                Some(rustix::thread::LinkNameSpaceType::Network),
            )?;
            let _rt = handle.as_ref().map(tokio::runtime::Handle::enter);
            f()
        })
        .join()
        .map_err(|_| io::Error::other("namespace thread panicked"))?
    })
}

/// A TUN device `name` of address `addr` with a point-to-point route to
/// `peer`, in the calling thread's namespace (the namespace's device is
/// made by a thread that joined it, [`in_namespace`]: a device belongs to
/// the namespace it was created in, and its fd keeps working after the
/// thread is gone).
fn point_to_point(name: &str, addr: Ipv4Addr, peer: Ipv4Addr) -> io::Result<Tun> {
    Tun::builder()
        .name(name)
        .address(addr)
        .destination(peer)
        .netmask(Ipv4Addr::new(255, 255, 255, 255))
        .up()
        .build()
        .map_err(io::Error::other)?
        .pop()
        .ok_or_else(|| io::Error::other("no TUN queue"))
}

/// The TCP congestion control setting of a namespace.
const TCP_CONGESTION: &str = "/proc/sys/net/ipv4/tcp_congestion_control";

/// An IP packet and when it leaves the link.
type Scheduled = Timed<Vec<u8>>;

async fn read_loop(
    from: Arc<Tun>,
    shaper: Arc<Mutex<Shaper>>,
    tx: mpsc::UnboundedSender<Scheduled>,
    c: Arc<Counters>,
    up: bool,
) {
    let mut buf = vec![0u8; MAX_PACKET];
    let mut seq = 0u64;
    loop {
        let n = match from.recv(&mut buf).await {
            Ok(n) => n,
            Err(e) => {
                tracing::debug!(error = %e, "linksim: TUN read failed");
                return;
            }
        };
        if up {
            c.packets_up.fetch_add(1, Ordering::Relaxed);
        } else {
            c.packets_down.fetch_add(1, Ordering::Relaxed);
        }
        let verdict = {
            let mut s = shaper.lock().unwrap_or_else(|e| e.into_inner());
            s.decide(Instant::now(), n.saturating_sub(PER_PACKET_OVERHEAD), false)
        };
        match verdict {
            Verdict::Deliver(at) => {
                seq += 1;
                let item = buf[..n].to_vec();
                if tx.send(Scheduled { at, seq, item }).is_err() {
                    return;
                }
            }
            Verdict::DropLoss => {
                c.dropped_loss.fetch_add(1, Ordering::Relaxed);
            }
            Verdict::DropQueue | Verdict::DropBlackhole => {
                c.dropped_queue.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
}

/// Write one packet out of a TUN device; a failed write is a lost packet.
async fn write(to: Arc<Tun>, packet: Vec<u8>) {
    if let Err(e) = to.send(&packet).await {
        tracing::debug!(error = %e, "linksim: TUN write failed");
    }
}
