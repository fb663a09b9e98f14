//! The far end of one shaped direction: packets leave the link at the times
//! the [`crate::shaper::Shaper`] gave them, in `(time, seq)` order,
//! whatever order they were scheduled in (jitter and reordering). One loop
//! for every kind of packet: the UDP relay's datagrams and the TUN link's
//! IP packets.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::future::Future;
use std::time::Instant;

use tokio::sync::mpsc;

use crate::shaper::Timed;

/// Receive scheduled packets from `rx` and hand each to `deliver` at its
/// time; once every sender is gone, the packets still on the link arrive
/// and the loop ends.
pub(crate) async fn delivery_loop<T, F, Fut>(
    mut rx: mpsc::UnboundedReceiver<Timed<T>>,
    mut deliver: F,
) where
    F: FnMut(T) -> Fut,
    Fut: Future<Output = ()>,
{
    let mut heap: BinaryHeap<Reverse<Timed<T>>> = BinaryHeap::new();
    let mut open = true;
    loop {
        let now = Instant::now();
        while heap.peek().is_some_and(|Reverse(p)| p.at <= now) {
            if let Some(Reverse(p)) = heap.pop() {
                deliver(p.item).await;
            }
        }
        let next = heap.peek().map(|Reverse(p)| p.at);
        if !open {
            match next {
                Some(at) => tokio::time::sleep_until(at.into()).await,
                None => return,
            }
            continue;
        }
        tokio::select! {
            msg = rx.recv() => match msg {
                Some(p) => {
                    heap.push(Reverse(p));
                    while let Ok(p) = rx.try_recv() {
                        heap.push(Reverse(p));
                    }
                }
                None => open = false,
            },
            _ = sleep_until_opt(next) => {}
        }
    }
}

async fn sleep_until_opt(at: Option<Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at.into()).await,
        None => std::future::pending().await,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};
    use std::time::Duration;

    /// Packets scheduled out of order leave in time order, each not before
    /// its time, those on the link when the senders go still arrive, and
    /// then the loop ends.
    #[tokio::test]
    async fn delivers_in_time_order() {
        let (tx, rx) = mpsc::unbounded_channel();
        let t0 = Instant::now();
        for (seq, ms) in [(0u64, 30u64), (1, 10), (2, 20), (3, 10)] {
            let at = t0 + Duration::from_millis(ms);
            tx.send(Timed {
                at,
                seq,
                item: (seq, at),
            })
            .unwrap();
        }
        drop(tx);
        let got = Arc::new(Mutex::new(Vec::new()));
        let g = Arc::clone(&got);
        delivery_loop(rx, move |(seq, at): (u64, Instant)| {
            let g = Arc::clone(&g);
            async move {
                assert!(Instant::now() >= at, "packet {seq} left early");
                g.lock().unwrap().push(seq);
            }
        })
        .await;
        assert_eq!(*got.lock().unwrap(), vec![1, 3, 2, 0]);
    }
}
