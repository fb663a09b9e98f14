//! The QUIC endpoint's UDP socket: buffers large enough for bursts, and GSO
//! batches that never exceed the largest UDP datagram.
//!
//! **Buffers.** With the kernel's default receive buffer (about 208 KiB) a
//! loaded server on loopback dropped tens of thousands of datagrams per
//! minute (`RcvbufErrors` in /proc/net/snmp); QUIC then recovers only after
//! probe timeouts, which showed up as p99 latencies of seconds in
//! `planet-bench server`. We ask for 4 MiB each way; the kernel caps the
//! request at `net.core.rmem_max` / `wmem_max`, which is not an error.
//!
//! **GSO batches.** quinn hands the socket up to 10 datagrams of the
//! connection's current path MTU as one segmentation-offload (`UDP_SEGMENT`)
//! send, without checking the batch's total size. The kernel refuses a
//! `sendmsg` whose payload exceeds one UDP datagram (65 507 bytes over IPv4)
//! with `EMSGSIZE`, and quinn-udp swallows `EMSGSIZE` silently (it expects it
//! only for MTU probes), so once path-MTU discovery goes above 6 550 bytes
//! (`max_udp_payload`), any batch of more than 65 507 bytes was lost whole:
//! four 16 kB datagrams, or two 64 kB ones. QUIC recovered by loss detection
//! or probe timeout, which is what the 0.6–0.9 s stalls of the 16 kB
//! loopback runs were (together with receive-buffer overflow at the
//! benchmark's single client socket, see docs/BENCHMARKS.md). [`GsoLimit`]
//! splits such batches into sends of at most [`MAX_GSO_BYTES`].

use std::fmt;
use std::io::{self, IoSliceMut};
use std::net::{SocketAddr, UdpSocket};
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use quinn::udp::{RecvMeta, Transmit};
use quinn::{AsyncUdpSocket, UdpPoller};

/// Socket buffer size requested for QUIC endpoints.
pub const SOCKET_BUFFER: usize = 4 * 1024 * 1024;

/// Largest payload of one `sendmsg` with segmentation offload: the largest
/// UDP payload over IPv4 (65 535 − 20 − 8). IPv6 allows 20 bytes more; the
/// IPv4 figure is used for both.
pub const MAX_GSO_BYTES: usize = 65_507;

/// Binds a UDP socket with enlarged send and receive buffers.
pub fn bind(addr: SocketAddr) -> io::Result<UdpSocket> {
    use socket2::{Domain, Protocol, Socket, Type};
    let socket = Socket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
    if let Err(e) = socket.set_recv_buffer_size(SOCKET_BUFFER) {
        tracing::debug!(error = %e, "cannot enlarge the UDP receive buffer");
    }
    if let Err(e) = socket.set_send_buffer_size(SOCKET_BUFFER) {
        tracing::debug!(error = %e, "cannot enlarge the UDP send buffer");
    }
    socket.bind(&addr.into())?;
    Ok(socket.into())
}

/// A quinn socket that splits segmentation-offload batches larger than
/// [`MAX_GSO_BYTES`] into several sends, at segment boundaries (see the
/// module documentation). Everything else is passed through.
pub struct GsoLimit {
    inner: Arc<dyn AsyncUdpSocket>,
}

impl GsoLimit {
    /// Wraps a runtime socket (`Runtime::wrap_udp_socket`).
    pub fn new(inner: Arc<dyn AsyncUdpSocket>) -> GsoLimit {
        GsoLimit { inner }
    }
}

impl fmt::Debug for GsoLimit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GsoLimit")
            .field("inner", &self.inner)
            .finish()
    }
}

impl AsyncUdpSocket for GsoLimit {
    fn create_io_poller(self: Arc<Self>) -> Pin<Box<dyn UdpPoller>> {
        Arc::clone(&self.inner).create_io_poller()
    }

    /// Sends `transmit`, in pieces of at most [`MAX_GSO_BYTES`] if it is a
    /// larger segmentation-offload batch. `WouldBlock` on a later piece is
    /// returned as is: quinn then retries the whole transmit, and the
    /// pieces already sent arrive twice (the peer drops duplicate packet
    /// numbers), which is cheaper than losing the rest to a probe timeout.
    fn try_send(&self, transmit: &Transmit) -> io::Result<()> {
        let segment = match transmit.segment_size {
            Some(s) if s > 0 && transmit.contents.len() > MAX_GSO_BYTES => s,
            _ => return self.inner.try_send(transmit),
        };
        let per_send = (MAX_GSO_BYTES / segment).max(1) * segment;
        for piece in transmit.contents.chunks(per_send) {
            self.inner.try_send(&Transmit {
                destination: transmit.destination,
                ecn: transmit.ecn,
                contents: piece,
                segment_size: (piece.len() > segment).then_some(segment),
                src_ip: transmit.src_ip,
            })?;
        }
        Ok(())
    }

    fn poll_recv(
        &self,
        cx: &mut Context,
        bufs: &mut [IoSliceMut<'_>],
        meta: &mut [RecvMeta],
    ) -> Poll<io::Result<usize>> {
        self.inner.poll_recv(cx, bufs, meta)
    }

    fn local_addr(&self) -> io::Result<SocketAddr> {
        self.inner.local_addr()
    }

    fn max_transmit_segments(&self) -> usize {
        self.inner.max_transmit_segments()
    }

    fn max_receive_segments(&self) -> usize {
        self.inner.max_receive_segments()
    }

    fn may_fragment(&self) -> bool {
        self.inner.may_fragment()
    }
}

/// A quinn server endpoint on a socket from [`bind`], wrapped in
/// [`GsoLimit`].
pub fn server_endpoint(
    config: quinn::ServerConfig,
    addr: SocketAddr,
) -> io::Result<quinn::Endpoint> {
    let runtime = quinn::default_runtime()
        .ok_or_else(|| io::Error::other("no async runtime for the QUIC endpoint"))?;
    let socket = runtime.wrap_udp_socket(bind(addr)?)?;
    quinn::Endpoint::new_with_abstract_socket(
        quinn::EndpointConfig::default(),
        Some(config),
        Arc::new(GsoLimit::new(socket)),
        runtime,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    /// Records the transmits it is given; `block_at` makes the n-th send
    /// (0-based) fail with `WouldBlock`.
    #[derive(Debug, Default)]
    struct Recorder {
        sent: Mutex<Vec<(usize, Option<usize>)>>,
        block_at: Option<usize>,
    }

    #[derive(Debug)]
    struct NeverPoller;

    impl UdpPoller for NeverPoller {
        fn poll_writable(self: Pin<&mut Self>, _cx: &mut Context) -> Poll<io::Result<()>> {
            Poll::Ready(Ok(()))
        }
    }

    impl AsyncUdpSocket for Recorder {
        fn create_io_poller(self: Arc<Self>) -> Pin<Box<dyn UdpPoller>> {
            Box::pin(NeverPoller)
        }
        fn try_send(&self, t: &Transmit) -> io::Result<()> {
            let mut sent = self.sent.lock().map_err(|_| io::Error::other("poisoned"))?;
            if Some(sent.len()) == self.block_at {
                return Err(io::ErrorKind::WouldBlock.into());
            }
            sent.push((t.contents.len(), t.segment_size));
            Ok(())
        }
        fn poll_recv(
            &self,
            _cx: &mut Context,
            _bufs: &mut [IoSliceMut<'_>],
            _meta: &mut [RecvMeta],
        ) -> Poll<io::Result<usize>> {
            Poll::Pending
        }
        fn local_addr(&self) -> io::Result<SocketAddr> {
            Ok(([127, 0, 0, 1], 1).into())
        }
    }

    fn send(rec: &Arc<Recorder>, len: usize, segment: Option<usize>) -> io::Result<()> {
        let sock = GsoLimit::new(Arc::clone(rec) as Arc<dyn AsyncUdpSocket>);
        let contents = vec![0u8; len];
        sock.try_send(&Transmit {
            destination: ([127, 0, 0, 1], 2).into(),
            ecn: None,
            contents: &contents,
            segment_size: segment,
            src_ip: None,
        })
    }

    fn sent(rec: &Recorder) -> Vec<(usize, Option<usize>)> {
        rec.sent.lock().map(|s| s.clone()).unwrap_or_default()
    }

    #[test]
    fn small_batches_pass_through() {
        let rec = Arc::new(Recorder::default());
        send(&rec, 10 * 1452, Some(1452)).unwrap();
        send(&rec, 900, None).unwrap();
        assert_eq!(sent(&rec), vec![(14_520, Some(1452)), (900, None)]);
    }

    #[test]
    fn large_batches_are_split_at_segment_boundaries() {
        let rec = Arc::new(Recorder::default());
        // Ten 16 kB datagrams, the last one short: 3 + 3 + 3 + 1 segments.
        let len = 9 * 16_384 + 100;
        send(&rec, len, Some(16_384)).unwrap();
        assert_eq!(
            sent(&rec),
            vec![
                (3 * 16_384, Some(16_384)),
                (3 * 16_384, Some(16_384)),
                (3 * 16_384, Some(16_384)),
                (100, None),
            ]
        );
        assert!(sent(&rec).iter().all(|(l, _)| *l <= MAX_GSO_BYTES));
        assert_eq!(sent(&rec).iter().map(|(l, _)| l).sum::<usize>(), len);
    }

    #[test]
    fn maximal_datagrams_go_one_per_send() {
        let rec = Arc::new(Recorder::default());
        send(&rec, 2 * 65_000 + 10, Some(65_000)).unwrap();
        assert_eq!(sent(&rec), vec![(65_000, None), (65_000, None), (10, None)]);
    }

    #[test]
    fn would_block_is_reported() {
        let rec = Arc::new(Recorder {
            block_at: Some(1),
            ..Recorder::default()
        });
        let e = send(&rec, 8 * 16_384, Some(16_384)).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::WouldBlock);
        assert_eq!(sent(&rec), vec![(3 * 16_384, Some(16_384))]);
    }
}
