//! The UDP relay: sockets, per-client sessions, delivery scheduling.

use std::collections::HashMap;
use std::io;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::net::UdpSocket;
use tokio::sync::mpsc;
use tokio::task::AbortHandle;

use crate::config::LinkConfig;
use crate::delivery::delivery_loop;
use crate::shaper::{Shaper, Timed, Verdict};

/// A client that sent nothing and received nothing for this long loses its
/// upstream socket (like a NAT mapping timing out); if it sends again it gets
/// a new one, which the server sees as a new source port.
pub const SESSION_IDLE_TIMEOUT: Duration = Duration::from_secs(120);

/// Upper bound on the payload bytes scheduled but not yet delivered in one
/// direction (packets "on the wire"); beyond it packets are counted as queue
/// drops. Only a guard against unbounded memory on unlimited links.
pub const MAX_IN_FLIGHT_BYTES: usize = 64 * 1024 * 1024;

const MAX_DATAGRAM: usize = 65_536;

/// Socket buffer size requested for the relay's sockets (the kernel caps it
/// at `net.core.rmem_max` / `wmem_max`), so that bursts (e.g. GSO batches)
/// are not dropped by the relay itself before the simulated link sees them.
const SOCKET_BUFFER: usize = 4 * 1024 * 1024;

/// Binds a non-blocking UDP socket with enlarged buffers.
fn bind_udp(addr: SocketAddr) -> io::Result<UdpSocket> {
    use socket2::{Domain, Protocol, Socket, Type};
    let socket = Socket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
    socket.set_nonblocking(true)?;
    // Best effort: a smaller buffer is not an error.
    if let Err(e) = socket.set_recv_buffer_size(SOCKET_BUFFER) {
        tracing::debug!(error = %e, "linksim: cannot enlarge receive buffer");
    }
    if let Err(e) = socket.set_send_buffer_size(SOCKET_BUFFER) {
        tracing::debug!(error = %e, "linksim: cannot enlarge send buffer");
    }
    socket.bind(&addr.into())?;
    UdpSocket::from_std(socket.into())
}

/// Counters of a [`Link`], both directions together unless named.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Datagrams delivered (both directions).
    pub packets_forwarded: u64,
    /// Datagrams delivered client → server.
    pub packets_up: u64,
    /// Datagrams delivered server → client.
    pub packets_down: u64,
    /// Datagrams dropped by random loss.
    pub packets_dropped_loss: u64,
    /// Datagrams dropped at a full bottleneck queue (or past
    /// [`MAX_IN_FLIGHT_BYTES`]).
    pub packets_dropped_queue: u64,
    /// Datagrams dropped because the link was blackholed, on entry or while
    /// in flight.
    pub packets_dropped_blackhole: u64,
    /// Payload bytes delivered client → server.
    pub bytes_up: u64,
    /// Payload bytes delivered server → client.
    pub bytes_down: u64,
}

#[derive(Debug, Default)]
struct Counters {
    up_packets: AtomicU64,
    down_packets: AtomicU64,
    loss: AtomicU64,
    queue: AtomicU64,
    blackhole: AtomicU64,
    up_bytes: AtomicU64,
    down_bytes: AtomicU64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Dir {
    Up,
    Down,
}

/// A datagram and where it goes.
#[derive(Debug)]
struct Datagram {
    data: Vec<u8>,
    socket: Arc<UdpSocket>,
    dest: SocketAddr,
}

/// A datagram waiting for its delivery time.
type Scheduled = Timed<Datagram>;

struct ShaperState {
    shaper: Shaper,
    seq: u64,
}

struct Direction {
    dir: Dir,
    state: Mutex<ShaperState>,
    tx: mpsc::UnboundedSender<Scheduled>,
    in_flight: AtomicUsize,
}

struct Session {
    socket: Arc<UdpSocket>,
    /// Milliseconds since `Inner::epoch` of the last datagram either way.
    last_active: Arc<AtomicU64>,
    task: AbortHandle,
}

struct Inner {
    server_addr: SocketAddr,
    epoch: Instant,
    up: Direction,
    down: Direction,
    blackhole: AtomicBool,
    counters: Counters,
    sessions: Mutex<HashMap<SocketAddr, Session>>,
    shut_down: AtomicBool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// An in-process UDP relay that simulates a network link between clients
/// and one server. See the [crate documentation](crate) for the model.
///
/// Dropping the `Link` (or calling [`Link::shutdown`]) stops its tasks and
/// closes its sockets.
pub struct Link {
    inner: Arc<Inner>,
    local_addr: SocketAddr,
    tasks: Mutex<Vec<AbortHandle>>,
}

impl std::fmt::Debug for Link {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Link")
            .field("local_addr", &self.local_addr)
            .field("server_addr", &self.inner.server_addr)
            .field("up", &self.config_up().to_string())
            .field("down", &self.config_down().to_string())
            .field("blackhole", &self.blackhole())
            .finish()
    }
}

impl Link {
    /// Binds a UDP socket on `127.0.0.1:0` and starts relaying: datagrams
    /// that clients send to [`Link::local_addr`] go to `server_addr`
    /// through the `config_up` direction, the server's replies come back
    /// through `config_down`. Must be called inside a tokio runtime.
    pub async fn start(
        server_addr: SocketAddr,
        config_up: LinkConfig,
        config_down: LinkConfig,
    ) -> io::Result<Link> {
        let front = Arc::new(bind_udp(SocketAddr::from((Ipv4Addr::LOCALHOST, 0)))?);
        let local_addr = front.local_addr()?;
        let (up_tx, up_rx) = mpsc::unbounded_channel();
        let (down_tx, down_rx) = mpsc::unbounded_channel();
        let inner = Arc::new(Inner {
            server_addr,
            epoch: Instant::now(),
            up: Direction::new(Dir::Up, config_up, up_tx),
            down: Direction::new(Dir::Down, config_down, down_tx),
            blackhole: AtomicBool::new(false),
            counters: Counters::default(),
            sessions: Mutex::new(HashMap::new()),
            shut_down: AtomicBool::new(false),
        });
        let tasks = vec![
            tokio::spawn(delivery_loop(up_rx, deliver_to(&inner, Dir::Up))).abort_handle(),
            tokio::spawn(delivery_loop(down_rx, deliver_to(&inner, Dir::Down))).abort_handle(),
            tokio::spawn(front_loop(inner.clone(), front)).abort_handle(),
            tokio::spawn(reaper_loop(inner.clone())).abort_handle(),
        ];
        tracing::debug!(%local_addr, %server_addr, "link started");
        Ok(Link {
            inner,
            local_addr,
            tasks: Mutex::new(tasks),
        })
    }

    /// [`Link::start`] with the same configuration in both directions (the
    /// directions still draw from different random streams).
    pub async fn start_symmetric(server_addr: SocketAddr, config: LinkConfig) -> io::Result<Link> {
        Self::start(server_addr, config.clone(), config).await
    }

    /// The address clients send to (on 127.0.0.1).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The server this link forwards to.
    pub fn server_addr(&self) -> SocketAddr {
        self.inner.server_addr
    }

    /// Replaces the client → server configuration. Packets already queued or
    /// in flight keep their schedule; the RNG is re-seeded only if the seed
    /// changes.
    pub fn set_up(&self, config: LinkConfig) {
        lock(&self.inner.up.state).shaper.set_config(config);
    }

    /// Replaces the server → client configuration (see [`Link::set_up`]).
    pub fn set_down(&self, config: LinkConfig) {
        lock(&self.inner.down.state).shaper.set_config(config);
    }

    /// The current client → server configuration.
    pub fn config_up(&self) -> LinkConfig {
        lock(&self.inner.up.state).shaper.config().clone()
    }

    /// The current server → client configuration.
    pub fn config_down(&self) -> LinkConfig {
        lock(&self.inner.down.state).shaper.config().clone()
    }

    /// While `true`, every datagram in either direction is dropped, both
    /// those arriving and those already in flight: the link is down.
    pub fn set_blackhole(&self, on: bool) {
        self.inner.blackhole.store(on, Ordering::SeqCst);
    }

    /// Whether the link is blackholed.
    pub fn blackhole(&self) -> bool {
        self.inner.blackhole.load(Ordering::SeqCst)
    }

    /// A snapshot of the counters.
    pub fn stats(&self) -> LinkStats {
        let c = &self.inner.counters;
        let up = c.up_packets.load(Ordering::Relaxed);
        let down = c.down_packets.load(Ordering::Relaxed);
        LinkStats {
            packets_forwarded: up + down,
            packets_up: up,
            packets_down: down,
            packets_dropped_loss: c.loss.load(Ordering::Relaxed),
            packets_dropped_queue: c.queue.load(Ordering::Relaxed),
            packets_dropped_blackhole: c.blackhole.load(Ordering::Relaxed),
            bytes_up: c.up_bytes.load(Ordering::Relaxed),
            bytes_down: c.down_bytes.load(Ordering::Relaxed),
        }
    }

    /// Number of client addresses that currently have an upstream socket.
    pub fn clients(&self) -> usize {
        lock(&self.inner.sessions).len()
    }

    /// Stops all tasks and closes the sockets; datagrams in flight are
    /// discarded. Idempotent; also done on drop.
    pub fn shutdown(&self) {
        for t in lock(&self.tasks).drain(..) {
            t.abort();
        }
        let mut sessions = lock(&self.inner.sessions);
        self.inner.shut_down.store(true, Ordering::SeqCst);
        for (_, s) in sessions.drain() {
            s.task.abort();
        }
    }
}

impl Drop for Link {
    fn drop(&mut self) {
        self.shutdown();
    }
}

impl Direction {
    fn new(dir: Dir, cfg: LinkConfig, tx: mpsc::UnboundedSender<Scheduled>) -> Self {
        let stream = match dir {
            Dir::Up => 0,
            Dir::Down => 1,
        };
        Self {
            dir,
            state: Mutex::new(ShaperState {
                shaper: Shaper::new(cfg, stream),
                seq: 0,
            }),
            tx,
            in_flight: AtomicUsize::new(0),
        }
    }
}

impl Inner {
    fn direction(&self, dir: Dir) -> &Direction {
        match dir {
            Dir::Up => &self.up,
            Dir::Down => &self.down,
        }
    }

    fn now_ms(&self) -> u64 {
        u64::try_from(self.epoch.elapsed().as_millis()).unwrap_or(u64::MAX)
    }

    fn is_from_server(&self, src: SocketAddr) -> bool {
        src == self.server_addr
            || (self.server_addr.ip().is_unspecified() && src.port() == self.server_addr.port())
    }

    /// Runs the shaper on one datagram and schedules it if it survives.
    fn submit(&self, dir: Dir, data: &[u8], socket: &Arc<UdpSocket>, dest: SocketAddr) {
        let d = self.direction(dir);
        let blackhole = self.blackhole.load(Ordering::Relaxed);
        let mut st = lock(&d.state);
        let verdict = st.shaper.decide(Instant::now(), data.len(), blackhole);
        match verdict {
            Verdict::Deliver(at) => {
                if d.in_flight.load(Ordering::Relaxed) + data.len() > MAX_IN_FLIGHT_BYTES {
                    self.counters.queue.fetch_add(1, Ordering::Relaxed);
                    return;
                }
                d.in_flight.fetch_add(data.len(), Ordering::Relaxed);
                let seq = st.seq;
                st.seq += 1;
                // Sent while holding the lock, so that the delivery task
                // sees packets in the order their times were decided.
                let _ = d.tx.send(Scheduled {
                    at,
                    seq,
                    item: Datagram {
                        data: data.to_vec(),
                        socket: socket.clone(),
                        dest,
                    },
                });
            }
            Verdict::DropLoss => {
                self.counters.loss.fetch_add(1, Ordering::Relaxed);
            }
            Verdict::DropQueue => {
                self.counters.queue.fetch_add(1, Ordering::Relaxed);
            }
            Verdict::DropBlackhole => {
                self.counters.blackhole.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    async fn deliver(&self, dir: Dir, p: Datagram) {
        let d = self.direction(dir);
        d.in_flight.fetch_sub(p.data.len(), Ordering::Relaxed);
        if self.blackhole.load(Ordering::Relaxed) {
            self.counters.blackhole.fetch_add(1, Ordering::Relaxed);
            return;
        }
        match p.socket.send_to(&p.data, p.dest).await {
            Ok(_) => {
                let (packets, bytes) = match d.dir {
                    Dir::Up => (&self.counters.up_packets, &self.counters.up_bytes),
                    Dir::Down => (&self.counters.down_packets, &self.counters.down_bytes),
                };
                packets.fetch_add(1, Ordering::Relaxed);
                bytes.fetch_add(p.data.len() as u64, Ordering::Relaxed);
            }
            Err(e) => tracing::debug!(dest = %p.dest, error = %e, "linksim: send failed"),
        }
    }

    /// The upstream socket for `client`, creating the session if needed.
    async fn session_for(
        self: &Arc<Self>,
        client: SocketAddr,
        front: &Arc<UdpSocket>,
    ) -> Option<Arc<UdpSocket>> {
        let now = self.now_ms();
        if let Some(s) = lock(&self.sessions).get(&client) {
            s.last_active.store(now, Ordering::Relaxed);
            return Some(s.socket.clone());
        }
        let bind_ip: IpAddr = match self.server_addr.ip() {
            IpAddr::V4(ip) if ip.is_loopback() => Ipv4Addr::LOCALHOST.into(),
            IpAddr::V4(_) => Ipv4Addr::UNSPECIFIED.into(),
            IpAddr::V6(ip) if ip.is_loopback() => Ipv6Addr::LOCALHOST.into(),
            IpAddr::V6(_) => Ipv6Addr::UNSPECIFIED.into(),
        };
        let socket = match bind_udp(SocketAddr::new(bind_ip, 0)) {
            Ok(s) => Arc::new(s),
            Err(e) => {
                tracing::warn!(%client, error = %e, "linksim: cannot bind upstream socket; dropping datagram");
                return None;
            }
        };
        let last_active = Arc::new(AtomicU64::new(now));
        let task = tokio::spawn(upstream_loop(
            self.clone(),
            socket.clone(),
            front.clone(),
            client,
            last_active.clone(),
        ))
        .abort_handle();
        let mut sessions = lock(&self.sessions);
        if self.shut_down.load(Ordering::SeqCst) {
            task.abort();
            return None;
        }
        tracing::debug!(%client, upstream = ?socket.local_addr().ok(), "linksim: new client");
        sessions.insert(
            client,
            Session {
                socket: socket.clone(),
                last_active,
                task,
            },
        );
        Some(socket)
    }
}

/// Client → link: receives on the front socket, submits upstream.
async fn front_loop(inner: Arc<Inner>, front: Arc<UdpSocket>) {
    let mut buf = vec![0u8; MAX_DATAGRAM];
    loop {
        let (n, from) = match front.recv_from(&mut buf).await {
            Ok(x) => x,
            Err(e) => {
                // E.g. an ICMP error surfaced on the socket; keep serving.
                tracing::debug!(error = %e, "linksim: front recv error");
                tokio::task::yield_now().await;
                continue;
            }
        };
        let Some(upstream) = inner.session_for(from, &front).await else {
            continue;
        };
        inner.submit(Dir::Up, &buf[..n], &upstream, inner.server_addr);
    }
}

/// Server → link for one client: receives on that client's upstream socket,
/// submits downstream to the client via the front socket.
async fn upstream_loop(
    inner: Arc<Inner>,
    upstream: Arc<UdpSocket>,
    front: Arc<UdpSocket>,
    client: SocketAddr,
    last_active: Arc<AtomicU64>,
) {
    let mut buf = vec![0u8; MAX_DATAGRAM];
    loop {
        let (n, from) = match upstream.recv_from(&mut buf).await {
            Ok(x) => x,
            Err(e) => {
                tracing::debug!(%client, error = %e, "linksim: upstream recv error");
                tokio::task::yield_now().await;
                continue;
            }
        };
        if !inner.is_from_server(from) {
            tracing::debug!(%from, "linksim: ignoring datagram not from the server");
            continue;
        }
        last_active.store(inner.now_ms(), Ordering::Relaxed);
        inner.submit(Dir::Down, &buf[..n], &front, client);
    }
}

/// Delivers one direction's datagrams in order of their delivery time.
/// The delivery of one direction: each datagram through [`Inner::deliver`].
fn deliver_to(inner: &Arc<Inner>, dir: Dir) -> impl FnMut(Datagram) -> BoxedDelivery {
    let inner = Arc::clone(inner);
    move |p| {
        let inner = Arc::clone(&inner);
        Box::pin(async move { inner.deliver(dir, p).await })
    }
}

type BoxedDelivery = std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send>>;

/// Drops sessions idle for longer than [`SESSION_IDLE_TIMEOUT`].
async fn reaper_loop(inner: Arc<Inner>) {
    let period = SESSION_IDLE_TIMEOUT / 4;
    let timeout_ms = u64::try_from(SESSION_IDLE_TIMEOUT.as_millis()).unwrap_or(u64::MAX);
    loop {
        tokio::time::sleep(period).await;
        let now = inner.now_ms();
        lock(&inner.sessions).retain(|client, s| {
            let idle = now.saturating_sub(s.last_active.load(Ordering::Relaxed));
            let keep = idle <= timeout_ms;
            if !keep {
                tracing::debug!(%client, "linksim: idle client expired");
                s.task.abort();
            }
            keep
        });
    }
}
