//! The subprocesses a benchmark started (planet-server), stopped with it:
//! `planet-bench soak` stopped by a job runner's timeout (SIGTERM) or by
//! `kill` must not leave its server running, as the default action of
//! those signals would (Drop does not run).
//!
//! A child is registered when spawned and unregistered once it has been
//! waited for (so its pid cannot have been reused by then). On SIGTERM,
//! SIGINT or SIGHUP, every registered child gets SIGTERM and the benchmark
//! exits with 128 + the signal's number.

use std::sync::Mutex;

use rustix::process::{kill_process, Pid, Signal};

static CHILDREN: Mutex<Vec<u32>> = Mutex::new(Vec::new());

fn children() -> std::sync::MutexGuard<'static, Vec<u32>> {
    CHILDREN.lock().unwrap_or_else(|p| p.into_inner())
}

/// Stop `pid` with the benchmark.
pub fn register(pid: u32) {
    children().push(pid);
}

/// `pid` has been waited for.
pub fn unregister(pid: u32) {
    children().retain(|&p| p != pid);
}

/// Sends SIGTERM to every registered child.
fn terminate_all() {
    for &pid in children().iter() {
        if let Some(pid) = i32::try_from(pid).ok().and_then(Pid::from_raw) {
            let _ = kill_process(pid, Signal::TERM);
        }
    }
}

/// Install the handler (first thing in `main`): a thread waits for the
/// signals on a small runtime of its own.
pub fn stop_with_signals() {
    let spawned = std::thread::Builder::new()
        .name("signals".into())
        .spawn(|| {
            let Ok(rt) = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
            else {
                return;
            };
            rt.block_on(async {
                use tokio::signal::unix::{signal, SignalKind};
                let (Ok(mut term), Ok(mut int), Ok(mut hup)) = (
                    signal(SignalKind::terminate()),
                    signal(SignalKind::interrupt()),
                    signal(SignalKind::hangup()),
                ) else {
                    return;
                };
                let code = tokio::select! {
                    _ = term.recv() => 128 + 15,
                    _ = int.recv() => 128 + 2,
                    _ = hup.recv() => 128 + 1,
                };
                terminate_all();
                std::process::exit(code);
            });
        });
    if let Err(e) = spawned {
        eprintln!("planet-bench: no signal handler ({e}): a killed benchmark may leave its server running");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A registered child gets SIGTERM; an unregistered one is left alone.
    #[test]
    fn registered_children_are_terminated() {
        let mut a = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .expect("sleep");
        let mut b = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .expect("sleep");
        register(a.id());
        register(b.id());
        unregister(b.id());
        terminate_all();
        let status = a.wait().expect("wait");
        use std::os::unix::process::ExitStatusExt;
        assert_eq!(status.signal(), Some(15), "{status:?}");
        unregister(a.id());
        assert!(
            b.try_wait().expect("try_wait").is_none(),
            "b was not registered"
        );
        let _ = b.kill();
        let _ = b.wait();
    }
}
