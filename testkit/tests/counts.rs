//! The counter counts this thread's allocations and nothing else.

#[global_allocator]
static GLOBAL: irtrack_testkit::CountingAlloc = irtrack_testkit::CountingAlloc;

use irtrack_testkit::allocations;

#[test]
fn counts_allocations_and_reallocations_of_this_thread_only() {
    let before = allocations();
    let mut v: Vec<u64> = Vec::with_capacity(4);
    assert_eq!(allocations() - before, 1);
    v.extend(0..100); // grows: at least one realloc
    let grown = allocations() - before;
    assert!(grown >= 2, "{grown}");
    let z = vec![0u8; 1 << 16]; // alloc_zeroed
    assert_eq!(allocations() - before, grown + 1);
    drop((v, z));
    let other = std::thread::spawn(|| {
        let b = allocations();
        let _w: Vec<u8> = Vec::with_capacity(8);
        allocations() - b
    });
    let here = allocations();
    assert_eq!(other.join().unwrap(), 1);
    // Spawning and joining allocate on this thread; the other thread's Vec was not counted here.
    let spawn_cost = allocations() - here;
    let x: Box<u32> = Box::new(1);
    assert_eq!(allocations() - here, spawn_cost + 1);
    drop(x);
    // Stack-only work allocates nothing.
    let before = allocations();
    let s: u64 = (0..1000u64).map(|i| i * i).sum();
    assert_eq!(allocations() - before, 0, "{s}");
}
