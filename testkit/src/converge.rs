//! The "step until idle" loop of the client's tests: one frame against a
//! [`FakeServer`], the idle test, and the loop itself.

use crate::testdb::{FakeServer, TestDb};
use planet_client::{Camera, Client, FrameOutput};

/// True when the client has nothing under way after the frame that gave
/// `out`: nothing sent, nothing in flight, no split or merge pending,
/// nothing decoding.
pub fn client_idle(c: &Client, out: &FrameOutput) -> bool {
    out.send.is_empty()
        && c.queue().in_flight() == 0
        && c.pending_ops().is_empty()
        && c.decoding() == 0
}

/// One frame (1/60 s) of `c` against `s` serving `db`: the frame's requests
/// submitted, the answers due delivered, and the decodes waited for.
pub fn step(c: &mut Client, s: &mut FakeServer, db: &TestDb, cam: &Camera) -> FrameOutput {
    let out = c.frame(cam, 1.0 / 60.0);
    s.submit(&out);
    for (id, bytes) in s.tick(db) {
        c.deliver(id, Ok(bytes));
    }
    c.wait_for_decodes();
    out
}

/// Runs [`step`] until nothing is sent, in flight, decoding, waiting for a
/// retry or pending at the server for 3 frames in a row, with the tree
/// validated after every frame; the last frame's output. Panics after `max`
/// frames (`DEBUG_CONVERGE` set: prints every frame's state).
pub fn converge(
    c: &mut Client,
    s: &mut FakeServer,
    db: &TestDb,
    cam: &Camera,
    max: usize,
) -> FrameOutput {
    let mut quiet = 0;
    for _ in 0..max {
        let out = step(c, s, db, cam);
        c.tree().validate().expect("valid");
        let idle = client_idle(c, &out) && c.retries_waiting() == 0 && s.pending() == 0;
        quiet = if idle { quiet + 1 } else { 0 };
        if quiet >= 3 {
            return out;
        }
        if std::env::var("DEBUG_CONVERGE").is_ok() {
            eprintln!(
                "{:?} send {:?} ops {:?} decoding {} pending {} err {:?}",
                out.stats,
                out.send,
                c.pending_ops(),
                c.decoding(),
                s.pending(),
                c.last_error()
            );
        }
    }
    panic!("did not converge in {max} frames");
}
