//! Test support shared by irtrack's test suites, benchmarks and xtask. Never a dependency of
//! shipped code.
//!
//! With the `harness` feature, [`harness`] runs irtrackd and other workspace binaries and talks
//! to them (HTTP, WebSocket, operator sign-in); the system tests in `tests/` and xtask's demo,
//! soak and image system test use it.
//!
//! With `mcap-check`, [`mcap_check`] reads MCAP recordings back with PyPI's independent
//! reader in a separate process.
//!
//! With `update-bundles`, [`update_bundles`] makes signing keys and RAUC bundles for the update
//! tests with the host's `openssl` and `rauc`.
//!
//! [`flood::Flood`] holds idle connections against a port, as a connection flood would.
//!
//! [`CountingAlloc`] proves "no allocation per frame": install it as the global allocator of a
//! test binary and compare [`allocations`] before and after the code under test.
//!
//! ```ignore
//! #[global_allocator]
//! static GLOBAL: irtrack_testkit::CountingAlloc = irtrack_testkit::CountingAlloc;
//! let before = irtrack_testkit::allocations();
//! run_frames();
//! assert_eq!(irtrack_testkit::allocations() - before, 0);
//! ```

#![deny(missing_docs)]

pub mod flood;
#[cfg(feature = "harness")]
pub mod harness;
#[cfg(feature = "mcap-check")]
pub mod mcap_check;
#[cfg(feature = "update-bundles")]
pub mod update_bundles;

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

thread_local! {
    // Per thread, so the test harness's other threads do not disturb a count. Const-initialized
    // without a destructor: touching it never allocates.
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

fn bump() {
    // `try_with`: during thread teardown the slot may be gone; such calls are not counted.
    let _ = ALLOCATIONS.try_with(|c| c.set(c.get() + 1));
}

/// The system allocator, counting `alloc`, `alloc_zeroed` and `realloc` calls per thread.
#[derive(Debug, Clone, Copy, Default)]
pub struct CountingAlloc;

// SAFETY: every call is forwarded unchanged to the system allocator; only a thread-local
// counter is incremented, which neither allocates nor touches the memory handed out.
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        bump();
        // SAFETY: the caller upholds `GlobalAlloc::alloc`'s contract.
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        bump();
        // SAFETY: the caller upholds `GlobalAlloc::alloc_zeroed`'s contract.
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        bump();
        // SAFETY: the caller upholds `GlobalAlloc::realloc`'s contract.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: the caller upholds `GlobalAlloc::dealloc`'s contract.
        unsafe { System.dealloc(ptr, layout) }
    }
}

/// Allocations made by the calling thread so far (only counted when [`CountingAlloc`] is the
/// global allocator of the binary).
pub fn allocations() -> u64 {
    ALLOCATIONS.with(|c| c.get())
}
