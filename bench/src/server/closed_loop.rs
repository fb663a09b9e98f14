//! The closed loop (throughput): each loop sends its next request when the
//! previous one has completed.

use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;
use planet_session::net::Connection;

use super::*;

/// The closed loop (throughput): one task per entry of `loops`, each
/// sending its next request when the previous one has completed, until
/// the run's cursor runs out. Server CPU is that of `pids`, client CPU this
/// process's, both over the timed window.
pub(crate) async fn closed_loop(
    label: &str,
    loops: Vec<Sender>,
    uri: Arc<str>,
    list: &Arc<Vec<Req>>,
    args: &ServerArgs,
    pids: &[u32],
    connections: usize,
) -> Result<RunResult> {
    let cpu0 = cpu_seconds_of(pids);
    let self0 = proc_cpu_seconds(std::process::id()).unwrap_or(0.0);
    let start = Instant::now();
    let cursor = new_cursor(list, args, start);
    let mut set = tokio::task::JoinSet::new();
    for mut sender in loops {
        let cursor = cursor.clone();
        let uri = uri.clone();
        set.spawn(async move {
            let mut st = LoopStats::default();
            while let Some((i, r)) = cursor.take() {
                let t0 = Instant::now();
                match sender.send(i, r, &uri).await {
                    Ok(n) => {
                        st.lat_us.push(us(t0.elapsed()));
                        st.bytes += n;
                    }
                    Err(SendError { msg, fatal }) => {
                        st.error(msg);
                        if fatal {
                            break;
                        }
                    }
                }
            }
            st
        });
    }
    let mut all = LoopStats::default();
    while let Some(r) = set.join_next().await {
        all.merge(r?);
    }
    let wall = start.elapsed();
    let cpu1 = cpu_seconds_of(pids);
    let client_cpu = proc_cpu_seconds(std::process::id()).unwrap_or(0.0) - self0;
    Ok(RunResult {
        label: label.into(),
        requests: all.lat_us.len() as u64,
        bytes: all.bytes,
        errors: all.errors,
        first_error: all.first_error,
        wall,
        latency: latency(&mut all.lat_us),
        server_cpu: Some(cpu1 - cpu0),
        connections,
        client_cpu,
        offered: None,
        lag: None,
        udp: None,
        warmup: false,
    })
}

/// A failed request of a closed loop; `fatal` ends the loop (its
/// connection is unusable).
pub(crate) struct SendError {
    pub(crate) msg: String,
    pub(crate) fatal: bool,
}

impl SendError {
    fn of(e: impl ToString) -> SendError {
        SendError {
            msg: e.to_string(),
            fatal: false,
        }
    }
}

/// One closed-loop request sender: a QUIC connection (one stream per
/// request), an HTTP/1.1 keep-alive connection, or an HTTP/2 connection
/// (one stream per request).
pub(crate) enum Sender {
    Quic(Connection),
    H1(H1Send),
    H2(H2Send),
}

impl Sender {
    /// Sends request `i` (`r`) and returns the body length once the whole
    /// response has arrived and matched the request.
    pub(crate) async fn send(&mut self, i: usize, r: Req, uri: &str) -> Result<u64, SendError> {
        let resp = match self {
            Sender::Quic(c) => {
                let body = c
                    .fetch(i as u64, r.offset, r.size)
                    .await
                    .map_err(SendError::of)?;
                if body.len() != r.size as usize {
                    return Err(SendError::of(format!(
                        "short body {} of {}",
                        body.len(),
                        r.size
                    )));
                }
                return Ok(body.len() as u64);
            }
            Sender::H1(h) => {
                h.ready().await.map_err(|e| SendError {
                    msg: e.to_string(),
                    fatal: true,
                })?;
                h.send_request(range_request(uri, r).map_err(SendError::of)?)
                    .await
            }
            Sender::H2(h) => {
                h.send_request(range_request(uri, r).map_err(SendError::of)?)
                    .await
            }
        };
        check_response(resp.map_err(SendError::of)?, r)
            .await
            .map_err(SendError::of)
    }
}
