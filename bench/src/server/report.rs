//! A `server` run end to end and its report.

use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Result};

use super::*;

#[derive(Debug, Clone)]
pub struct ServerReport {
    /// The QUIC side: one closed-loop run, or one run per `--rate`.
    pub quic: Vec<RunResult>,
    /// The nginx sides.
    pub nginx: Vec<RunResult>,
    /// The open-loop warm-ups of every side (already printed).
    pub warmups: Vec<RunResult>,
}

/// `planet-bench server`.
pub fn run(args: ServerArgs) -> Result<()> {
    let report = bench(&args)?;
    let mut failed = false;
    for n in report
        .quic
        .iter()
        .chain(&report.nginx)
        .chain(&report.warmups)
    {
        failed |= n.errors > 0;
    }
    if failed {
        bail!("requests failed (see the errors above)");
    }
    Ok(())
}

/// Runs the benchmark, prints and returns the figures.
pub fn bench(args: &ServerArgs) -> Result<ServerReport> {
    planet_session::tls::install_crypto_provider();
    let nofile = raise_nofile_limit();
    let db = resolve_db(&args.db)?;
    let list = request_list(&db, args.list_len, args.seed, args.elevation_share)?;
    let file_size = std::fs::metadata(&db)?.len();
    println!(
        "database {} ({:.1} MB, {} elevation + {} colour records); request list: {} entries, seed {}, \
         {:.0} % elevation, mean {:.1} kB",
        db.display(),
        file_size as f64 / 1e6,
        list.records.0,
        list.records.1,
        list.reqs.len(),
        args.seed,
        100.0 * list.elevation_share,
        list.mean_size / 1e3
    );
    let cpus = std::thread::available_parallelism().map_or(2, |n| n.get());
    println!(
        "{} clients x {} concurrent requests, {}; {} CPUs, load average {} (before), open files {}",
        args.clients,
        args.concurrency,
        match args.requests {
            Some(n) => format!("{n} requests per side"),
            None => format!("{} s per side", args.seconds),
        },
        cpus,
        loadavg(),
        nofile
    );
    let threads = args.client_threads.unwrap_or(cpus);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(threads.max(1))
        .thread_name("bench-client")
        .enable_all()
        .build()?;
    let reqs = Arc::new(list.reqs.clone());
    let runs = args
        .rate
        .iter()
        .map(|&rate| {
            let n = args
                .requests
                .unwrap_or((rate * args.seconds).round().max(1.0) as usize);
            let s = schedule(rate, n, args.clients, args.seed, args.arrivals);
            (rate, Arc::new(s))
        })
        .collect();
    let warmup = match args.rate.first() {
        Some(&rate) if args.warmup > 0.0 => {
            let n = (rate * args.warmup).round().max(1.0) as usize;
            // Other arrival times than the timed runs' (same request list).
            let s = schedule(rate, n, args.clients, !args.seed, args.arrivals);
            Some((rate, Arc::new(s)))
        }
        _ => None,
    };
    let scheds = Schedules { warmup, runs };
    if !scheds.is_empty() {
        println!(
            "open loop ({:?} arrivals, latency from the scheduled send time): rates {:?} req/s, \
             at most {} outstanding per client, {}",
            args.arrivals,
            args.rate,
            args.concurrency,
            match &scheds.warmup {
                Some((rate, _)) => format!("after {} s of warm-up at {rate} req/s", args.warmup),
                None => "no warm-up".into(),
            }
        );
    }
    println!(
        "client: {} runtime threads, QUIC connections on {}",
        threads.max(1),
        if args.client_endpoints == 0 {
            "one endpoint each".to_string()
        } else {
            format!("{} shared endpoint(s)", args.client_endpoints)
        }
    );

    let mut srv = ServerUnderTest::start_with(
        args.server,
        &db,
        args.server_bin.as_deref(),
        args.client_max_udp_payload,
        args.server_threads,
    )?;
    let mut warmups = vec![];
    let (warm, quic): (Vec<_>, Vec<_>) = rt
        .block_on(run_quic(&srv, &reqs, args, &scheds))?
        .into_iter()
        .partition(|r| r.warmup);
    warmups.extend(warm);
    srv.stop();
    for q in &quic {
        q.print();
    }

    let mut nginx = vec![];
    if args.nginx {
        let workers = args.nginx_workers.unwrap_or(cpus);
        let ng = start_nginx(&args.nginx_bin, &db, workers)?;
        let modes: &[bool] = match args.http {
            HttpMode::H1 => &[false],
            HttpMode::H2 => &[true],
            HttpMode::Both => &[false, true],
        };
        for &h2 in modes {
            let rs = rt.block_on(run_nginx(&ng, &reqs, args, h2, &scheds))?;
            let (warm, rs): (Vec<_>, Vec<_>) = rs.into_iter().partition(|r| r.warmup);
            warmups.extend(warm);
            for r in rs {
                r.print();
                nginx.push(r);
            }
        }
        drop(ng);
        for n in &nginx {
            let Some(q) = quic.iter().find(|q| q.offered == n.offered) else {
                continue;
            };
            let at = match n.offered {
                Some(r) => format!(" at {r:.0} req/s offered"),
                None => String::new(),
            };
            println!(
                "QUIC / {}{at}: requests/s x{:.2}, MB/s x{:.2}, p50 x{:.2}, p99 x{:.2} (lower is better for latency)",
                n.label,
                q.rps() / n.rps().max(1e-9),
                q.mbps() / n.mbps().max(1e-9),
                q.latency.p50 as f64 / (n.latency.p50.max(1)) as f64,
                q.latency.p99 as f64 / (n.latency.p99.max(1)) as f64
            );
        }
    }
    println!("load average {} (after)", loadavg());
    rt.shutdown_timeout(Duration::from_secs(2));
    Ok(ServerReport {
        quic,
        nginx,
        warmups,
    })
}
