//! The open loop (latency at a fixed arrival rate) and the QUIC side of a
//! run.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Result;
use planet_session::net::Connection;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;

/// One scheduled request of an open-loop run: request `k` of the schedule
/// is `list[k % len]`, sent at `at` after the start by client `client`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arrival {
    /// Send time after the start of the run.
    pub at: Duration,
    /// Client (connection group) index.
    pub client: usize,
}

/// A seeded schedule of `n` arrivals at `rate` requests/s over `clients`.
pub fn schedule(
    rate: f64,
    n: usize,
    clients: usize,
    seed: u64,
    arrivals: Arrivals,
) -> Vec<Arrival> {
    let clients = clients.max(1);
    let rate = rate.max(1e-3);
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x005e_ed0f_a771_7a15);
    let mut t = 0.0f64;
    (0..n)
        .map(|k| match arrivals {
            Arrivals::Poisson => {
                // Exponential gap; 1 - u is in (0, 1] so ln is finite.
                let u: f64 = rng.random();
                t += -(1.0 - u).ln() / rate;
                Arrival {
                    at: Duration::from_secs_f64(t),
                    client: rng.random_range(0..clients),
                }
            }
            Arrivals::Uniform => Arrival {
                at: Duration::from_secs_f64(k as f64 / rate),
                client: k % clients,
            },
        })
        .collect()
}

pub(crate) type H1Send =
    hyper::client::conn::http1::SendRequest<http_body_util::Empty<bytes::Bytes>>;
pub(crate) type H2Send =
    hyper::client::conn::http2::SendRequest<http_body_util::Empty<bytes::Bytes>>;

/// How one client of an open-loop run sends.
pub(crate) enum Slot {
    /// One QUIC connection, one stream per request.
    Quic(Connection),
    /// A pool of HTTP/1.1 keep-alive connections, one request each at a time.
    H1(tokio::sync::Mutex<Vec<H1Send>>),
    /// One HTTP/2 connection, one stream per request.
    H2(H2Send),
}

/// One client: at most `--concurrency` requests outstanding (the same cap
/// for every protocol; a request that finds them all busy waits, and the
/// wait counts in its latency).
pub(crate) struct ClientSlot {
    pub(crate) sem: tokio::sync::Semaphore,
    pub(crate) slot: Slot,
}

pub(crate) async fn issue(c: &ClientSlot, k: usize, r: Req, uri: &str) -> Result<u64, String> {
    let _permit = c.sem.acquire().await.map_err(|e| e.to_string())?;
    let res = match &c.slot {
        Slot::Quic(conn) => Sender::Quic(conn.clone()).send(k, r, uri).await,
        Slot::H1(pool) => {
            let h = pool
                .lock()
                .await
                .pop()
                .ok_or_else(|| "no free HTTP/1.1 connection".to_string())?;
            let mut sender = Sender::H1(h);
            let res = sender.send(k, r, uri).await;
            if let Sender::H1(h) = sender {
                pool.lock().await.push(h);
            }
            res
        }
        Slot::H2(h) => Sender::H2(h.clone()).send(k, r, uri).await,
    };
    res.map_err(|e| e.msg)
}

pub(crate) fn us(d: Duration) -> u32 {
    d.as_micros().min(u32::MAX as u128) as u32
}

/// Replays `sched` on `slots`: a blocking thread sleeps until each send
/// time (`std::thread::sleep`, microsecond precision, unlike tokio's 1 ms
/// timer wheel) and spawns the request on the client runtime. Latency is
/// measured from the scheduled time.
#[allow(clippy::too_many_arguments)]
pub(crate) async fn open_loop(
    label: &str,
    slots: Arc<Vec<ClientSlot>>,
    list: &Arc<Vec<Req>>,
    sched: Arc<Vec<Arrival>>,
    rate: f64,
    uri: Arc<str>,
    pids: &[u32],
    connections: usize,
) -> Result<RunResult> {
    let handle = tokio::runtime::Handle::current();
    let cpu0 = cpu_seconds_of(pids);
    let self0 = proc_cpu_seconds(std::process::id()).unwrap_or(0.0);
    let start = Instant::now() + Duration::from_millis(50);
    let list = list.clone();
    let handles = tokio::task::spawn_blocking(move || {
        let mut hs = Vec::with_capacity(sched.len());
        for (k, a) in sched.iter().enumerate() {
            let due = start + a.at;
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
            let slots = slots.clone();
            let uri = uri.clone();
            let r = list[k % list.len()];
            let client = a.client % slots.len().max(1);
            hs.push(handle.spawn(async move {
                let lag = due.elapsed();
                let res = match slots.get(client) {
                    Some(c) => issue(c, k, r, &uri).await,
                    None => Err("no clients".to_string()),
                };
                (lag, due.elapsed(), res)
            }));
        }
        hs
    })
    .await?;
    let mut st = LoopStats::default();
    let mut lag = Vec::with_capacity(handles.len());
    for h in handles {
        let (l, t, res) = h.await?;
        lag.push(us(l));
        match res {
            Ok(n) => {
                st.lat_us.push(us(t));
                st.bytes += n;
            }
            Err(e) => st.error(e),
        }
    }
    let wall = start.elapsed();
    let cpu1 = cpu_seconds_of(pids);
    let client_cpu = proc_cpu_seconds(std::process::id()).unwrap_or(0.0) - self0;
    Ok(RunResult {
        label: label.into(),
        requests: st.lat_us.len() as u64,
        bytes: st.bytes,
        errors: st.errors,
        first_error: st.first_error,
        wall,
        latency: latency(&mut st.lat_us),
        server_cpu: (!pids.is_empty()).then_some(cpu1 - cpu0),
        connections,
        client_cpu,
        offered: Some(rate),
        lag: Some(latency(&mut lag)),
        udp: None,
        warmup: false,
    })
}

/// The open-loop schedules of a run: an optional untimed warm-up, then
/// one timed run per `--rate`.
#[derive(Default)]
pub struct Schedules {
    /// Replayed first, printed, not counted.
    pub warmup: Option<(f64, Arc<Vec<Arrival>>)>,
    /// The timed runs.
    pub runs: Vec<(f64, Arc<Vec<Arrival>>)>,
}

impl Schedules {
    pub(crate) fn is_empty(&self) -> bool {
        self.runs.is_empty()
    }
}

/// Replays the warm-up schedule of `scheds`, if any, on `slots`; prints
/// the result and returns it marked as a warm-up.
pub(crate) async fn warm_up(
    label: &str,
    slots: &Arc<Vec<ClientSlot>>,
    list: &Arc<Vec<Req>>,
    scheds: &Schedules,
    uri: &str,
    pids: &[u32],
    connections: usize,
) -> Result<Option<RunResult>> {
    let Some((rate, sched)) = &scheds.warmup else {
        return Ok(None);
    };
    let mut r = open_loop(
        label,
        slots.clone(),
        list,
        sched.clone(),
        *rate,
        uri.into(),
        pids,
        connections,
    )
    .await?;
    r.label = format!("{label} warm-up (not counted)");
    r.warmup = true;
    r.print();
    Ok(Some(r))
}

/// Smoothed RTT estimates of the client connections (quinn's, in ms):
/// p50, p90 and max.
pub(crate) fn rtt_estimates(conns: &[Connection]) -> String {
    let mut v: Vec<u32> = conns.iter().map(|c| us(c.quinn().rtt())).collect();
    if v.is_empty() {
        return "none".into();
    }
    let l = latency(&mut v);
    format!("p50 {} p90 {} max {}", ms(l.p50), ms(l.p90), ms(l.max))
}

pub(crate) async fn run_quic(
    srv: &ServerUnderTest,
    list: &Arc<Vec<Req>>,
    args: &ServerArgs,
    scheds: &Schedules,
) -> Result<Vec<RunResult>> {
    let conns = connect_many_on_with(
        srv.addr,
        &srv.fingerprint,
        &srv.hello(),
        args.clients,
        64,
        args.client_endpoints,
        args.client_max_udp_payload,
    )
    .await?;
    let pids: Vec<u32> = srv.pid().into_iter().collect();
    if !scheds.is_empty() {
        let conc = args.concurrency.max(1);
        let slots: Arc<Vec<ClientSlot>> = Arc::new(
            conns
                .iter()
                .map(|c| ClientSlot {
                    sem: tokio::sync::Semaphore::new(conc),
                    slot: Slot::Quic(c.clone()),
                })
                .collect(),
        );
        let mut out = vec![];
        println!(
            "QUIC client RTT estimates after connecting: {}",
            rtt_estimates(&conns)
        );
        if let Some(r) = warm_up("QUIC", &slots, list, scheds, "", &pids, conns.len()).await? {
            out.push(r);
            println!(
                "QUIC client RTT estimates after the warm-up: {}",
                rtt_estimates(&conns)
            );
        }
        for (rate, sched) in &scheds.runs {
            let udp0 = UdpCounts::of(&conns);
            let mut r = open_loop(
                "QUIC",
                slots.clone(),
                list,
                sched.clone(),
                *rate,
                "".into(),
                &pids,
                conns.len(),
            )
            .await?;
            if srv.pid().is_none() {
                r.server_cpu = None;
            }
            r.udp = Some(UdpCounts::of(&conns).since(&udp0));
            out.push(r);
        }
        for c in &conns {
            c.close();
        }
        return Ok(out);
    }
    let udp0 = UdpCounts::of(&conns);
    let loops = conns
        .iter()
        .flat_map(|c| (0..args.concurrency.max(1)).map(|_| Sender::Quic(c.clone())))
        .collect();
    let mut r = closed_loop("QUIC", loops, "".into(), list, args, &pids, conns.len()).await?;
    r.udp = Some(UdpCounts::of(&conns).since(&udp0));
    if srv.pid().is_none() {
        r.server_cpu = None;
    }
    for c in &conns {
        c.close();
    }
    Ok(vec![r])
}
