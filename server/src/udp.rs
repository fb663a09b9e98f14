//! The QUIC endpoint's UDP socket, with buffers large enough for bursts.
//!
//! With the kernel's default receive buffer (about 208 KiB) a loaded server
//! on loopback dropped tens of thousands of datagrams per minute
//! (`RcvbufErrors` in /proc/net/snmp); QUIC then recovers only after probe
//! timeouts, which showed up as p99 latencies of seconds in
//! `planet-bench server`. We ask for 4 MiB each way; the kernel caps the
//! request at `net.core.rmem_max` / `wmem_max`, which is not an error.

use std::io;
use std::net::{SocketAddr, UdpSocket};

/// Socket buffer size requested for QUIC endpoints.
pub const SOCKET_BUFFER: usize = 4 * 1024 * 1024;

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

/// A quinn server endpoint on a socket from [`bind`].
pub fn server_endpoint(
    config: quinn::ServerConfig,
    addr: SocketAddr,
) -> io::Result<quinn::Endpoint> {
    let runtime = quinn::default_runtime()
        .ok_or_else(|| io::Error::other("no async runtime for the QUIC endpoint"))?;
    quinn::Endpoint::new(
        quinn::EndpointConfig::default(),
        Some(config),
        bind(addr)?,
        runtime,
    )
}
