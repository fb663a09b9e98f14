//! Shared by the viewer's window tests (`viewer.rs`, `controls.rs`): a
//! private Xvfb display, a child process killed on drop, and a private
//! `XDG_RUNTIME_DIR`.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// `name` on the `PATH`, if installed.
pub fn which(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|p| p.join(name))
            .find(|p| p.is_file())
    })
}

/// A child process (Xvfb, the viewer) killed and reaped on drop.
pub struct Killed(pub Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `xvfb` on the first free display from `base + pid % 400` (50
/// tries) with one screen of `screen` (e.g. `800x600x24`); `None` when none
/// started.
pub fn start_xvfb(xvfb: &Path, base: u32, screen: &str) -> Option<(Killed, u32)> {
    let base = base + std::process::id() % 400;
    for n in base..base + 50 {
        let lock = PathBuf::from(format!("/tmp/.X{n}-lock"));
        let sock = PathBuf::from(format!("/tmp/.X11-unix/X{n}"));
        if lock.exists() || sock.exists() {
            continue;
        }
        let child = Command::new(xvfb)
            .arg(format!(":{n}"))
            .args(["-screen", "0", screen, "-nolisten", "tcp"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .ok()?;
        let mut x = Killed(child);
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(10) {
            if sock.exists() {
                return Some((x, n));
            }
            if let Ok(Some(_)) = x.0.try_wait() {
                break; // lost a race for the display: try the next one
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    None
}

/// `dir/xdg`, created with mode 0700, for the viewer's `XDG_RUNTIME_DIR`.
pub fn xdg_runtime(dir: &Path) -> PathBuf {
    let p = dir.join("xdg");
    std::fs::create_dir_all(&p).unwrap();
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o700)).unwrap();
    }
    p
}

/// Skips a test that cannot run here; fails in CI
/// ([`planet_testkit::skip_or_fail`]).
#[allow(unused_imports)] // not every test file that shares this module skips
pub use planet_testkit::skip_or_fail;
