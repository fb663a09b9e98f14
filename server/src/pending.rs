//! Pre-authentication slots (`max_pending_handshakes`), shared fairly
//! between client addresses.
//!
//! A connection holds a pending slot from the moment it passes the accept
//! limits until its `Welcome` is written (or it ends). The budget is small
//! and global, so a flood from a few addresses could fill it and lock out
//! everyone else until the flooders' handshake deadlines pass. When the
//! table is full, a newcomer therefore takes the slot of the **oldest
//! pending connection of the address holding the most slots**, provided
//! that address holds at least two more than the newcomer's own address
//! does. A client from an address with no pending connection gets in as
//! long as some address holds two or more: an attacker cannot keep a fresh
//! client out without spreading over as many (validated, see QUIC Retry in
//! the accept loop) addresses as there are slots. An address never evicts
//! its own connections, and equal shares are never disturbed (that would
//! only trade one waiting client for another).
//!
//! The evicted connection is told through its [`Notify`] and closes itself
//! with `server_busy`, counted `planet_handshakes_total{outcome="evicted"}`.

use std::collections::{HashMap, VecDeque};
use std::net::IpAddr;
use std::sync::{Arc, Mutex, MutexGuard};

use tokio::sync::Notify;

/// One pending connection's place in the table.
#[derive(Debug)]
pub(crate) struct Admitted {
    /// Identity of the slot, for [`PendingTable::remove`].
    pub(crate) id: u64,
    /// Notified when another address's newcomer took this slot.
    pub(crate) evict: Arc<Notify>,
    /// This admission evicted another connection.
    pub(crate) evicted_other: bool,
}

#[derive(Debug)]
struct Entry {
    id: u64,
    evict: Arc<Notify>,
}

#[derive(Debug, Default)]
struct Inner {
    next: u64,
    total: usize,
    /// Each address's pending connections, oldest first.
    by_addr: HashMap<IpAddr, VecDeque<Entry>>,
}

impl Inner {
    /// The address holding the most slots and how many (ties: any).
    fn busiest(&self) -> Option<(IpAddr, usize)> {
        self.by_addr
            .iter()
            .map(|(ip, q)| (*ip, q.len()))
            .max_by_key(|&(_, n)| n)
    }

    fn own(&self, ip: IpAddr) -> usize {
        self.by_addr.get(&ip).map_or(0, VecDeque::len)
    }

    /// The address whose oldest connection a newcomer from `ip` may evict.
    fn victim(&self, ip: IpAddr) -> Option<IpAddr> {
        let (busiest, n) = self.busiest()?;
        (busiest != ip && n >= self.own(ip) + 2).then_some(busiest)
    }
}

/// The table of pending connections ([module docs](self)).
#[derive(Debug, Default)]
pub(crate) struct PendingTable {
    inner: Mutex<Inner>,
}

impl PendingTable {
    fn lock(&self) -> MutexGuard<'_, Inner> {
        match self.inner.lock() {
            Ok(g) => g,
            Err(p) => p.into_inner(),
        }
    }

    /// Connections holding a pending slot now.
    pub(crate) fn len(&self) -> usize {
        self.lock().total
    }

    /// Whether a newcomer from `ip` would get a slot of `max` now (a free
    /// one, or by eviction). Checked before spending anything on it; the
    /// admission itself is [`PendingTable::admit`].
    pub(crate) fn would_admit(&self, ip: IpAddr, max: usize) -> bool {
        let g = self.lock();
        g.total < max || g.victim(ip).is_some()
    }

    /// Takes a slot of `max` for a connection from `ip`: a free one, or the
    /// slot of the oldest connection of the busiest address (which is
    /// notified). `None`: full, and no address holds enough to give one up.
    pub(crate) fn admit(&self, ip: IpAddr, max: usize) -> Option<Admitted> {
        let mut g = self.lock();
        let mut evicted_other = false;
        if g.total >= max {
            let victim = g.victim(ip)?;
            let queue = g.by_addr.get_mut(&victim)?;
            let old = queue.pop_front()?;
            if queue.is_empty() {
                g.by_addr.remove(&victim);
            }
            old.evict.notify_one();
            evicted_other = true;
        } else {
            g.total += 1;
        }
        let id = g.next;
        g.next += 1;
        let evict = Arc::new(Notify::new());
        g.by_addr.entry(ip).or_default().push_back(Entry {
            id,
            evict: Arc::clone(&evict),
        });
        Some(Admitted {
            id,
            evict,
            evicted_other,
        })
    }

    /// Gives slot `id` of `ip` back (authenticated, or the connection
    /// ended). A slot already taken by eviction is not counted twice:
    /// `false` then.
    pub(crate) fn remove(&self, ip: IpAddr, id: u64) -> bool {
        let mut g = self.lock();
        let Some(queue) = g.by_addr.get_mut(&ip) else {
            return false;
        };
        let Some(pos) = queue.iter().position(|e| e.id == id) else {
            return false;
        };
        queue.remove(pos);
        if queue.is_empty() {
            g.by_addr.remove(&ip);
        }
        g.total -= 1;
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(n: u8) -> IpAddr {
        IpAddr::from([10, 0, 0, n])
    }

    fn notified(a: &Admitted) -> bool {
        // A stored permit completes `notified()` at once.
        let f = a.evict.notified();
        futures_util::FutureExt::now_or_never(f).is_some()
    }

    #[test]
    fn free_slots_are_taken_until_full() {
        let t = PendingTable::default();
        let a: Vec<_> = (0..4).map(|_| t.admit(ip(1), 4).unwrap()).collect();
        assert_eq!(t.len(), 4);
        assert!(a.iter().all(|a| !a.evicted_other));
        // The same address cannot evict itself.
        assert!(!t.would_admit(ip(1), 4));
        assert!(t.admit(ip(1), 4).is_none());
        assert!(t.remove(ip(1), a[2].id));
        assert!(!t.remove(ip(1), a[2].id), "removed twice");
        assert_eq!(t.len(), 3);
        assert!(t.admit(ip(1), 4).is_some());
        assert_eq!(t.len(), 4);
    }

    #[test]
    fn a_newcomer_evicts_the_oldest_of_the_busiest_address() {
        let t = PendingTable::default();
        let flood: Vec<_> = (0..3).map(|_| t.admit(ip(1), 4).unwrap()).collect();
        let other = t.admit(ip(2), 4).unwrap();
        assert_eq!(t.len(), 4);
        let fresh = t.admit(ip(3), 4).expect("a fresh address gets a slot");
        assert!(fresh.evicted_other);
        assert_eq!(t.len(), 4);
        assert!(notified(&flood[0]), "the oldest of the busiest is told");
        assert!(!notified(&flood[1]) && !notified(&flood[2]) && !notified(&other));
        // The evicted slot's later release does not free a second slot.
        assert!(!t.remove(ip(1), flood[0].id));
        assert_eq!(t.len(), 4);
        // Now 1 holds 2, 2 and 3 hold 1 each: a fourth address evicts 1's
        // next oldest; after that all hold one and nobody is evicted.
        assert!(t.admit(ip(4), 4).unwrap().evicted_other);
        assert!(notified(&flood[1]));
        assert!(!t.would_admit(ip(5), 4));
        assert!(t.admit(ip(5), 4).is_none());
        assert!(!notified(&other) && !notified(&fresh) && !notified(&flood[2]));
    }

    #[test]
    fn an_address_with_slots_needs_a_larger_share_to_evict() {
        let t = PendingTable::default();
        let _a: Vec<_> = (0..2).map(|_| t.admit(ip(1), 3).unwrap()).collect();
        let _b = t.admit(ip(2), 3).unwrap();
        // 2 holds one, 1 holds two: equal after the move, refused.
        assert!(!t.would_admit(ip(2), 3));
        assert!(t.admit(ip(2), 3).is_none());
        // A fresh address gets in.
        assert!(t.would_admit(ip(3), 3));
    }

    #[test]
    fn the_count_matches_the_entries_after_any_sequence() {
        // Random admits and removes (a fixed LCG, addresses 0..5, max 6):
        // the count never exceeds the budget and equals the entries left.
        let t = PendingTable::default();
        let mut live: Vec<(IpAddr, u64)> = Vec::new();
        let mut x: u64 = 12345;
        for _ in 0..5000 {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let r = (x >> 33) as usize;
            if r.is_multiple_of(3) && !live.is_empty() {
                let (a, id) = live.swap_remove(r % live.len());
                t.remove(a, id);
            } else {
                let a = ip((r % 5) as u8);
                if let Some(ad) = t.admit(a, 6) {
                    live.push((a, ad.id));
                }
            }
            assert!(t.len() <= 6);
            let entries: usize = t.lock().by_addr.values().map(VecDeque::len).sum();
            assert_eq!(t.len(), entries);
        }
    }
}
