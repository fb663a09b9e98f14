//! Quiet exit on a closed standard output, as ripgrep and the C tools do.
//!
//! Rust ignores SIGPIPE, so `println!` to a pipe whose reader has gone
//! (`planet-build inspect DB | head -1`) panics with "failed printing to
//! stdout: Broken pipe". A command-line tool should instead stop quietly:
//! [`exit_quietly_on_broken_pipe`] installs a panic hook that ends the
//! process with status 0 for exactly that panic (the message std's `print!`
//! family panics with) and leaves every other panic to the previous hook.
//! SIGPIPE itself stays ignored, so servers' socket writes still get EPIPE
//! errors instead of killing the process.

/// Whether a panic message is std's failure to print to a closed stdout or
/// stderr pipe.
pub fn is_broken_pipe_panic(msg: &str) -> bool {
    (msg.starts_with("failed printing to stdout") || msg.starts_with("failed printing to stderr"))
        && (msg.contains("Broken pipe") || msg.contains("os error 32"))
}

/// Install the hook (call first thing in `main`).
pub fn exit_quietly_on_broken_pipe() {
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let payload = info.payload();
        let msg = payload
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| payload.downcast_ref::<&str>().copied())
            .unwrap_or("");
        if is_broken_pipe_panic(msg) {
            std::process::exit(0);
        }
        previous(info);
    }));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recognises_only_the_pipe_panic() {
        assert!(is_broken_pipe_panic(
            "failed printing to stdout: Broken pipe (os error 32)"
        ));
        assert!(!is_broken_pipe_panic(
            "failed printing to stdout: disk full"
        ));
        assert!(!is_broken_pipe_panic("index out of bounds"));
    }
}
