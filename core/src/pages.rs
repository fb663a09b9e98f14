//! Transparent huge pages off for the binaries that run long and allocate
//! per request or per frame (`planet-server`, `planet-view`,
//! `planet-bench`), as database servers with many small allocations do
//! (Redis, MongoDB).
//!
//! mimalloc, their allocator, asks for huge pages on its arenas
//! (`MADV_HUGEPAGE`). On a host whose THP setting is `madvise` or `always`
//! that costs twice:
//! - **Memory.** khugepaged may collapse a sparsely used 2 MiB range into
//!   one huge page, the rest filled with zeros, and a huge page returns to
//!   the host only whole. In the 2-hour soaks the server's anonymous memory
//!   stepped up by 5–10 MiB for good while other processes ran on the host,
//!   when 18 of its 29 MiB were huge pages (docs/BENCHMARKS.md "Soak").
//! - **Frame time.** A vector that grows into memory mimalloc had returned
//!   faults in a whole huge page, and the kernel zeroes 2 MiB inside the
//!   frame: 6 % of `Client::frame`'s CPU for a moving eye in
//!   `planet-bench resident`, and its slowest frames.
//!
//! With THP off, the 64 KiB pages that mimalloc purges go back to the host
//! and come back one by one. `planet-build` keeps huge pages: it allocates
//! large grids once, where fewer TLB misses help.

/// Turn transparent huge pages off for this process (`PR_SET_THP_DISABLE`,
/// inherited by its children). Call first thing in `main`: memory the
/// allocator has already mapped keeps the pages it has. A failure (an old
/// kernel) costs only the above, so it is reported on stderr and the
/// process goes on.
pub fn no_transparent_huge_pages() {
    #[cfg(target_os = "linux")]
    if let Err(e) = rustix::thread::disable_transparent_huge_pages(true) {
        eprintln!("cannot turn transparent huge pages off (prctl PR_SET_THP_DISABLE): {e}");
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    /// The flag is set and reads back (the test's process keeps it, which
    /// changes nothing for the other tests but their page sizes).
    #[test]
    fn huge_pages_read_back_as_off() {
        super::no_transparent_huge_pages();
        assert_eq!(
            rustix::thread::transparent_huge_pages_are_disabled().ok(),
            Some(true)
        );
    }
}
