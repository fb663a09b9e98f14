//! `planet-build inspect DB | head -1`: a closed stdout ends the command
//! quietly with status 0 (as ripgrep does), not with a "failed printing to
//! stdout: Broken pipe" panic.

use std::process::{Command, Stdio};

#[test]
fn closed_stdout_ends_quietly() {
    let exe = env!("CARGO_BIN_EXE_planet-build");
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("p.db");
    let out = Command::new(exe)
        .args([
            "build",
            "--procedural",
            "--levels",
            "1",
            "--no-colour",
            "--quiet",
            "--out",
        ])
        .arg(&db)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for args in [
        &["inspect"][..],
        &["inspect", "--json"][..],
        &["verify"][..],
    ] {
        // The reader goes away before the command prints anything (it
        // first reads the whole database), so its first print meets EPIPE.
        let mut child = Command::new(exe)
            .args(args)
            .arg(&db)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        drop(child.stdout.take());
        let out = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{args:?}: {:?} {err}", out.status);
        assert!(
            !err.contains("panicked") && !err.contains("Broken pipe"),
            "{args:?}: {err}"
        );
    }
    // `head -1` itself, where a shell is there.
    let sh = Command::new("sh")
        .arg("-c")
        .arg(format!("'{exe}' inspect '{}' | head -1", db.display()))
        .output();
    if let Ok(o) = sh {
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!err.contains("panicked"), "{err}");
        assert_eq!(String::from_utf8_lossy(&o.stdout).lines().count(), 1);
    }
}
