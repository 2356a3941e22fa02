//! A global allocator that bounds every single allocation and tracks the live heap, so that a
//! reader trusting a length or shape field of a mutated file is caught before it asks the system
//! for terabytes.
//!
//! Install it in a binary or test with
//! `#[global_allocator] static A: ggpt_fuzz::alloc::BoundedAllocator = ggpt_fuzz::alloc::BoundedAllocator;`.
//! A request above [`set_limit`] is refused (null), which Rust turns into an abort; just before,
//! the allocator writes the size, the bound and the current case ([`set_case`]) to stderr with a
//! raw `write(2)` (it cannot allocate). The harness therefore fails loudly and names the case.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// Default bound of one allocation: 256 MiB. Every seed file is < 1 MiB, so an honest reader
/// never needs more than a few MiB for any mutation of it.
pub const DEFAULT_LIMIT_BYTES: usize = 256 << 20;

static LIMIT: AtomicUsize = AtomicUsize::new(DEFAULT_LIMIT_BYTES);
static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);
static INSTALLED: AtomicUsize = AtomicUsize::new(0);
/// Target index (into the names registered by [`set_case`]) and case index.
static CASE_TARGET: AtomicUsize = AtomicUsize::new(usize::MAX);
static CASE_INDEX: AtomicU64 = AtomicU64::new(0);
static CASE_SEED: AtomicU64 = AtomicU64::new(0);
static CASE_NAME: std::sync::OnceLock<&'static [&'static str]> = std::sync::OnceLock::new();

/// The bounded, counting allocator (wraps [`System`]).
pub struct BoundedAllocator;

/// Sets the bound of one allocation in bytes.
pub fn set_limit(bytes: usize) {
    LIMIT.store(bytes, Ordering::Relaxed);
}

/// The bound of one allocation in bytes.
pub fn limit() -> usize {
    LIMIT.load(Ordering::Relaxed)
}

/// Whether [`BoundedAllocator`] is the global allocator of this process (it has served at least
/// one allocation).
pub fn installed() -> bool {
    INSTALLED.load(Ordering::Relaxed) != 0
}

/// Registers the target names once (for the abort message).
pub fn register_targets(names: &'static [&'static str]) {
    let _ = CASE_NAME.set(names);
}

/// Records the case being run (named in the abort message).
pub fn set_case(target: usize, case: u64, seed: u64) {
    CASE_TARGET.store(target, Ordering::Relaxed);
    CASE_INDEX.store(case, Ordering::Relaxed);
    CASE_SEED.store(seed, Ordering::Relaxed);
}

/// Live heap bytes now.
pub fn live_bytes() -> usize {
    LIVE.load(Ordering::Relaxed)
}

/// Resets the peak to the current live bytes and returns that value.
pub fn reset_peak() -> usize {
    let live = LIVE.load(Ordering::Relaxed);
    PEAK.store(live, Ordering::Relaxed);
    live
}

/// Peak live heap bytes since the last [`reset_peak`].
pub fn peak_bytes() -> usize {
    PEAK.load(Ordering::Relaxed)
}

fn write_stderr(bytes: &[u8]) {
    // SAFETY: writing a valid buffer to fd 2; the result is ignored (best effort before abort).
    unsafe {
        libc::write(2, bytes.as_ptr().cast(), bytes.len());
    }
}

/// Decimal digits of `v` into `buf`, returning the used tail.
fn digits(mut v: u64, buf: &mut [u8; 20]) -> &[u8] {
    let mut i = buf.len();
    loop {
        i -= 1;
        buf[i] = b'0' + (v % 10) as u8;
        v /= 10;
        if v == 0 {
            break;
        }
    }
    &buf[i..]
}

fn report_refusal(size: usize) {
    let mut b = [0u8; 20];
    write_stderr(b"\nggpt-fuzz: refused an allocation of ");
    write_stderr(digits(size as u64, &mut b));
    write_stderr(b" bytes (bound ");
    write_stderr(digits(limit() as u64, &mut b));
    write_stderr(b" bytes)");
    let target = CASE_TARGET.load(Ordering::Relaxed);
    if let Some(name) = CASE_NAME.get().and_then(|n| n.get(target)) {
        write_stderr(b" in target ");
        write_stderr(name.as_bytes());
        write_stderr(b", case ");
        write_stderr(digits(CASE_INDEX.load(Ordering::Relaxed), &mut b));
        write_stderr(b", seed ");
        write_stderr(digits(CASE_SEED.load(Ordering::Relaxed), &mut b));
        write_stderr(b" (rerun with: ggpt-fuzz --target ");
        write_stderr(name.as_bytes());
        write_stderr(b" --seed ");
        write_stderr(digits(CASE_SEED.load(Ordering::Relaxed), &mut b));
        write_stderr(b" --case ");
        write_stderr(digits(CASE_INDEX.load(Ordering::Relaxed), &mut b));
        write_stderr(b")");
    }
    write_stderr(b"\n");
}

fn grow(size: usize) {
    let live = LIVE.fetch_add(size, Ordering::Relaxed) + size;
    PEAK.fetch_max(live, Ordering::Relaxed);
}

/// Refuses `layout` above the bound, else allocates it with `allocate` and counts it.
fn bounded(layout: Layout, allocate: impl FnOnce() -> *mut u8) -> *mut u8 {
    INSTALLED.store(1, Ordering::Relaxed);
    if layout.size() > limit() {
        report_refusal(layout.size());
        return std::ptr::null_mut();
    }
    let p = allocate();
    if !p.is_null() {
        grow(layout.size());
    }
    p
}

// SAFETY: every call is forwarded to `System` with the caller's layout; the counters are
// plain atomics and the refusal path allocates nothing.
unsafe impl GlobalAlloc for BoundedAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded with the caller's layout.
        bounded(layout, || unsafe { System.alloc(layout) })
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded with the caller's layout.
        bounded(layout, || unsafe { System.alloc_zeroed(layout) })
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` was allocated by `System` with `layout`.
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > limit() {
            report_refusal(new_size);
            return std::ptr::null_mut();
        }
        // SAFETY: `ptr` was allocated by `System` with `layout`.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            if new_size >= layout.size() {
                grow(new_size - layout.size());
            } else {
                LIVE.fetch_sub(layout.size() - new_size, Ordering::Relaxed);
            }
        }
        p
    }
}
