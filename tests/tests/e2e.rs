//! End-to-end: real server, real QUIC, through the linksim relay.

mod common;

use common::*;
use planet_client::{Camera, DrawBlock, Outgoing};
use planet_linksim::{Link, LinkConfig};
use planet_testkit::harness::{block_behind_horizon, runtime, LocalServer};
use proptest::prelude::*;
use std::time::{Duration, Instant};

#[test]
fn static_camera_converges_to_exact_samples() {
    let rt = runtime(2).expect("runtime");
    let (server, link) = served_through(&rt, "50mbit,5ms");
    let mut sc = connect(&rt, &server, link.local_addr());
    let camera = static_camera();
    let out = converge(&mut sc, &camera, Duration::from_secs(30), |_, _| {});
    assert_exact(&sc, &out);
    assert!(sc.bytes_received() > 0);
    sc.close();
}

#[test]
fn no_request_behind_the_horizon() {
    let rt = runtime(2).expect("runtime");
    let (server, link) = served_through(&rt, "50mbit,5ms");
    let mut sc = connect(&rt, &server, link.local_addr());
    let h = sc.header().clone();
    let datum = h.datum;
    let r_occ = datum.polar_radius() + (h.min_elevation as f64).min(0.0);
    // Low cameras looking at the horizon in every direction, and one higher.
    let mut checked = 0usize;
    let mut drawn_checked = 0usize;
    let (h_min, h_max) = (h.min_elevation as f64, h.max_elevation as f64);
    let mut check = |camera: &Camera, sends: &[Outgoing], drawn: &[DrawBlock]| {
        // Nothing behind the horizon is drawn either (with the database's
        // whole elevation range, a block found hidden is certainly hidden).
        for d in drawn {
            let hidden = block_behind_horizon(&datum, camera.eye, d.block, h_min, h_max, r_occ, 17);
            assert!(
                !hidden,
                "{:?} drawn behind the horizon from {:?}",
                d.block, camera.eye
            );
            drawn_checked += 1;
        }
        for s in sends {
            let hidden = block_behind_horizon(
                &datum,
                camera.eye,
                s.block,
                s.record.min_elevation as f64,
                s.record.max_elevation as f64,
                r_occ,
                17,
            );
            assert!(
                !hidden,
                "request for {:?} ({:?}, forced {}) behind the horizon from {:?}",
                s.block, s.tree, s.forced, camera.eye
            );
            checked += 1;
        }
    };
    let start = Instant::now();
    let mut last = Instant::now();
    let mut t = 0.0;
    while start.elapsed() < Duration::from_secs(8) {
        std::thread::sleep(Duration::from_millis(10));
        let dt = last.elapsed().as_secs_f64();
        last = Instant::now();
        t += dt;
        let camera = if t < 6.0 {
            cam(46.85, -121.76, 3000.0, t * 60.0, 5.0)
        } else {
            cam(0.0, 179.9, 150_000.0, t * 90.0, -10.0)
        };
        let out = sc.frame(&camera, dt);
        check(&camera, &out.send, &out.draw);
    }
    assert!(checked > 20, "too few requests checked ({checked})");
    assert!(
        drawn_checked > 100,
        "too few drawn blocks checked ({drawn_checked})"
    );
    eprintln!("horizon: {checked} requests and {drawn_checked} drawn blocks checked");
    sc.close();
}

#[test]
fn server_restart_is_survived() {
    let rt = runtime(2).expect("runtime");
    let (mut server, link) = served_through(&rt, "20mbit,10ms");
    let mut sc = connect(&rt, &server, link.local_addr());
    let camera = static_camera();
    // Stream a little, then stop the server mid-stream.
    for _ in 0..15 {
        std::thread::sleep(Duration::from_millis(10));
        sc.frame(&camera, 0.01);
    }
    server.stop();
    let down = Instant::now();
    while down.elapsed() < Duration::from_millis(700) {
        std::thread::sleep(Duration::from_millis(10));
        let out = sc.frame(&camera, 0.01);
        sc.client
            .tree()
            .validate()
            .expect("tree while disconnected");
        assert!(!out.draw.is_empty(), "the tree is kept while disconnected");
    }
    server.restart().expect("restart on the same port");
    // The session reconnects by itself (with backoff), whether or not the
    // view still needs data.
    let up = Instant::now();
    while sc.counters().connects < 2 && up.elapsed() < Duration::from_secs(30) {
        std::thread::sleep(Duration::from_millis(10));
        sc.frame(&camera, 0.01);
    }
    let out = converge(&mut sc, &camera, Duration::from_secs(40), |_, _| {});
    assert!(
        sc.counters().connects >= 2,
        "reconnected: {:?}",
        sc.counters()
    );
    assert_exact(&sc, &out);
    sc.close();
}

#[test]
fn lossy_reordering_link_converges() {
    let rt = runtime(2).expect("runtime");
    let server = LocalServer::start(rt.handle(), small_db()).expect("server");
    let cfg: LinkConfig = "20mbit,10ms,5%loss,5%reorder".parse().expect("link");
    let link = rt
        .block_on(Link::start(
            server.addr(),
            cfg.clone().with_seed(3),
            cfg.with_seed(4),
        ))
        .expect("link");
    let mut sc = connect(&rt, &server, link.local_addr());
    let out = converge(
        &mut sc,
        &static_camera(),
        Duration::from_secs(40),
        |_, _| {},
    );
    assert_exact(&sc, &out);
    assert!(
        link.stats().packets_dropped_loss > 0,
        "the link lost packets"
    );
    sc.close();
}

#[test]
fn blackhole_then_recovery_converges() {
    let rt = runtime(2).expect("runtime");
    let (server, link) = served_through(&rt, "10mbit,20ms");
    let mut sc = connect(&rt, &server, link.local_addr());
    let camera = static_camera();
    for _ in 0..10 {
        std::thread::sleep(Duration::from_millis(10));
        sc.frame(&camera, 0.01);
    }
    link.set_blackhole(true);
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_secs(2) {
        std::thread::sleep(Duration::from_millis(10));
        sc.frame(&camera, 0.01);
        sc.client
            .tree()
            .validate()
            .expect("tree during the blackhole");
    }
    link.set_blackhole(false);
    let out = converge(&mut sc, &camera, Duration::from_secs(40), |_, _| {});
    assert_exact(&sc, &out);
    assert!(link.stats().packets_dropped_blackhole > 0);
    sc.close();
}

#[derive(Debug, Clone)]
struct Move {
    lat: f64,
    lon: f64,
    alt: f64,
    heading: f64,
    pitch: f64,
    frames: usize,
}

fn moves() -> impl Strategy<Value = Vec<Move>> {
    prop::collection::vec(
        (
            -89.0f64..89.0,
            -180.0f64..180.0,
            3.0f64..7.3,
            0.0f64..360.0,
            -90.0f64..10.0,
            1usize..12,
        )
            .prop_map(|(lat, lon, la, heading, pitch, frames)| Move {
                lat,
                lon,
                alt: 10f64.powf(la),
                heading,
                pitch,
                frames,
            }),
        1..8,
    )
}

#[test]
fn random_camera_moves_keep_the_tree_valid() {
    let rt = runtime(2).expect("runtime");
    let server = LocalServer::start(rt.handle(), small_db()).expect("server");
    let mut runner = proptest::test_runner::TestRunner::new(ProptestConfig {
        cases: 4,
        failure_persistence: None,
        ..ProptestConfig::default()
    });
    runner
        .run(&moves(), |ms| {
            let mut sc = connect(&rt, &server, server.addr());
            for m in &ms {
                let camera = cam(m.lat, m.lon, m.alt, m.heading, m.pitch);
                for _ in 0..m.frames {
                    std::thread::sleep(Duration::from_millis(5));
                    let out = sc.frame(&camera, 0.005);
                    prop_assert!(
                        sc.client.tree().validate().is_ok(),
                        "{:?}",
                        sc.client.tree().validate()
                    );
                    for d in &out.draw {
                        prop_assert!(sc
                            .client
                            .tree()
                            .elevation()
                            .get(&d.block)
                            .is_some_and(|n| n.is_leaf()));
                    }
                }
            }
            sc.close();
            Ok(())
        })
        .expect("property");
}

/// The small database's server behind a symmetric link of `spec`
/// (`LinkConfig`'s syntax); both run while they are held.
fn served_through(rt: &tokio::runtime::Runtime, spec: &str) -> (LocalServer, Link) {
    let server = LocalServer::start(rt.handle(), small_db()).expect("server");
    let link = rt
        .block_on(Link::start_symmetric(
            server.addr(),
            spec.parse::<LinkConfig>().expect("link"),
        ))
        .expect("link");
    (server, link)
}

/// The small database's server behind a 2 Mbit/s, 10 ms link, and the
/// session configuration that reaches it through the link.
fn behind_a_2mbit_link(
    rt: &tokio::runtime::Runtime,
) -> (LocalServer, Link, planet_session::net::SessionConfig) {
    let (server, link) = served_through(rt, "2mbit,10ms");
    let cfg = server.session_config(link.local_addr()).expect("config");
    (server, link, cfg)
}

/// A connection of the session library alone (no client) made with `cfg`.
async fn connect_session(
    cfg: planet_session::net::SessionConfig,
) -> planet_session::net::Connection {
    planet_session::net::Connection::connect(cfg.addr, &cfg.server_name, cfg.tls, cfg.hello)
        .await
        .map(|(c, _)| c)
        .expect("connect")
}

/// Requests made one after the other are answered in that order, whatever
/// order the tasks awaiting them run in (docs/PROTOCOL.md §5.2): the client
/// asks its most important record first, and it must not come last. Over a
/// 2 Mbit/s link each record takes milliseconds, so the order of arrival is
/// the order of completion.
#[test]
fn requests_are_answered_in_the_order_they_are_made() {
    use planet_core::format::{record_child_refs, ChildRef, DbFile};
    let rt = runtime(2).expect("runtime");
    let (_server, _link, cfg) = behind_a_2mbit_link(&rt);
    // The roots' records and their children's: the larger ones, largest
    // first (a round robin, or a race between tasks, would finish the small
    // ones first).
    let db = DbFile::open(small_db()).expect("open");
    let mut refs: Vec<ChildRef> = db.header.elevation.root_records.to_vec();
    for r in db.header.elevation.root_records {
        let bytes = db.read_record(&r).expect("record");
        refs.extend(record_child_refs(&bytes, None).expect("refs"));
    }
    refs.sort_by_key(|r| std::cmp::Reverse(r.size));
    refs.truncate(12);
    assert!(refs.iter().all(|r| r.size >= 500), "{refs:?}");
    let done = rt.block_on(async move {
        let conn = connect_session(cfg).await;
        let futs: Vec<_> = refs
            .iter()
            .enumerate()
            .map(|(i, r)| conn.fetch(i as u64 + 1, r.offset, r.size))
            .collect();
        // Spawned last first: tokio runs the task spawned last first.
        let mut tasks = Vec::new();
        for (i, f) in futs.into_iter().enumerate().rev() {
            tasks.push(tokio::spawn(async move {
                f.await.expect("record");
                (Instant::now(), i)
            }));
        }
        let mut done = Vec::new();
        for t in tasks {
            done.push(t.await.expect("task"));
        }
        conn.close();
        done
    });
    let mut by_time = done.clone();
    by_time.sort();
    let order: Vec<usize> = by_time.iter().map(|(_, i)| *i).collect();
    assert_eq!(order, (0..order.len()).collect::<Vec<_>>(), "{done:?}");
}

/// A request made after others with a higher priority (a `Priority` frame,
/// docs/PROTOCOL.md §4.10) overtakes the answers still waiting in the
/// server's send buffer; with the same priority it comes after them, or
/// nearly. Over a 2 Mbit/s link, 60 copies of the largest record take about
/// half a second; the last request is made once 10 answers are in, so
/// that every earlier request has long reached the server (a request
/// arriving with others is written in the order its task runs, not in
/// stream order), and returns the number of earlier answers that came
/// after it.
#[test]
fn a_higher_priority_overtakes_answers_still_buffered() {
    use planet_core::format::DbFile;
    use planet_protocol::{RequestKind, StreamPriority};
    let rt = runtime(2).expect("runtime");
    let (_server, _link, cfg) = behind_a_2mbit_link(&rt);
    let db = DbFile::open(small_db()).expect("open");
    let r = db
        .header
        .elevation
        .root_records
        .iter()
        .max_by_key(|r| r.size)
        .copied()
        .expect("a root");
    // Within the server's default in-flight limit (64).
    const LOW: u64 = 60;
    let overtaken = |last: i32| {
        let cfg = cfg.clone();
        rt.block_on(async move {
            let conn = connect_session(cfg).await;
            let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
            let low = Some(StreamPriority { priority: -1 });
            for id in 1..=LOW {
                let f = conn.fetch_as(id, r.offset, r.size, RequestKind::Record, low);
                let tx = tx.clone();
                tokio::spawn(async move {
                    f.await.expect("record");
                    let _ = tx.send(id);
                });
            }
            let mut order = Vec::new();
            while order.len() < 10 {
                order.push(rx.recv().await.expect("an answer"));
            }
            let last = Some(StreamPriority { priority: last });
            let f = conn.fetch_as(100, r.offset, r.size, RequestKind::Record, last);
            tokio::spawn(async move {
                f.await.expect("record");
                let _ = tx.send(100);
            });
            while let Some(id) = rx.recv().await {
                order.push(id);
                if order.len() as u64 == LOW + 1 {
                    break;
                }
            }
            assert!(!conn.priority_refused());
            conn.close();
            let at = order.iter().position(|&id| id == 100).expect("answered");
            order.len() - 1 - at
        })
    };
    // At equal priority the last request is usually answered last (0 after
    // it on a quiet machine). On a loaded one the server's request tasks
    // may write earlier answers late, after it (up to 12 seen with three
    // test binaries on two cores), so the equal run is the control, not a
    // bound: the priority must add at least 10 overtaken answers to it.
    let same = overtaken(-1);
    let higher = overtaken(1);
    eprintln!("answers after the last request: {same} at equal priority, {higher} at a higher one");
    assert!(higher >= 20, "{higher} earlier answers came after it");
    assert!(
        higher >= same + 10,
        "{higher} at a higher priority against {same} at an equal one"
    );
}
