//! The `planet-server` binary: single-database mode, the `healthcheck`
//! subcommand, SIGHUP (re-open) and SIGTERM (drain and exit).

#[path = "../../server/tests/common/mod.rs"]
mod common;

use std::time::Duration;

use common::build_db;
use planet_protocol::Hello;

#[test]
fn binary_single_database_mode_healthcheck_sighup_sigterm() {
    use std::io::{BufRead, BufReader};
    use std::process::{Command, Stdio};
    let bin = env!("CARGO_BIN_EXE_planet-server");
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("earth.planetdb");
    let recs = build_db(&db, 1);
    let mut child = Command::new(bin)
        .args([
            "--database",
            db.to_str().unwrap(),
            "--listen",
            "127.0.0.1:0",
        ])
        .args([
            "--dev-cert",
            "--metrics",
            "127.0.0.1:0",
            "--log-format",
            "json",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let mut field = |prefix: &str| -> String {
        let line = lines.next().expect("line").expect("read");
        line.strip_prefix(prefix)
            .unwrap_or_else(|| panic!("expected {prefix:?}, got {line:?}"))
            .trim()
            .to_string()
    };
    let fingerprint = field("cert-sha256 ");
    let addr: std::net::SocketAddr = field("listening ").parse().unwrap();
    let metrics = field("metrics ");
    let health = |path: &str| {
        Command::new(bin)
            .args(["healthcheck", "--url", &format!("http://{metrics}{path}")])
            .status()
            .unwrap()
            .success()
    };
    assert!(health("/healthz"));
    assert!(health("/readyz"));
    assert!(!health("/nope"));

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let tls = planet_session::tls::pinned(&fingerprint).unwrap();
    let (off, size) = recs[0];
    rt.block_on(async {
        let (conn, w) = planet_session::net::Connection::connect(
            addr,
            "localhost",
            tls.clone(),
            Hello::new("public", "", "earth"),
        )
        .await
        .unwrap();
        assert_eq!(w.database, "earth");
        assert_eq!(conn.fetch(1, off, size).await.unwrap().len(), size as usize);
        conn.close();
    });
    let pid = child.id().to_string();
    assert!(Command::new("kill")
        .args(["-HUP", &pid])
        .status()
        .unwrap()
        .success());
    std::thread::sleep(Duration::from_millis(200));
    assert!(health("/healthz"), "still alive after SIGHUP");
    assert!(Command::new("kill")
        .args(["-TERM", &pid])
        .status()
        .unwrap()
        .success());
    let status = child.wait().unwrap();
    assert!(status.success(), "{status:?}");
}
