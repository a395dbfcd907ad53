//! Keeping the node's resident size on what it holds over a day-long run.
//!
//! glibc's allocator raises its mmap threshold each time a large buffer is freed (up to
//! 32 MB), so frame-sized buffers (a 1–5 MB image message from the DDS receiver, the
//! detector's per-frame vectors) soon come from the threads' heap arenas, and what is freed
//! there stays resident until trimmed, wherever it lies. Which arena, and where in it, depends
//! on thread timing: over a 2-minute soak run (`test/run_soak.sh`) the resident size rose by
//! 10–14 MiB between trims and two quiet spans of one run differed by −4 % to +7 % around the
//! same live memory. So at start the threshold is fixed at [`MMAP_THRESHOLD`] (buffers that
//! size and larger are mapped for themselves and unmapped when freed), and the arenas' free
//! pages are handed back every [`RELEASE_PERIOD`] (`malloc_trim`, off the frame path: 1.7 ms
//! median, at most 7 ms on a 1 MP soak run, holding each arena's lock while it walks it).

use std::time::{Duration, Instant};

/// Allocations of at least this many bytes are mapped apart from the heap (glibc's
/// `M_MMAP_THRESHOLD`, fixed: its default adapts upwards). A 1 MP 8-bit frame is 1 MiB; the
/// field fit's per-sweep vectors stay below it.
pub const MMAP_THRESHOLD: usize = 256 * 1024;

/// How often the arenas' free pages are handed back.
pub const RELEASE_PERIOD: Duration = Duration::from_secs(10);

/// Fixes the allocator's mmap threshold at [`MMAP_THRESHOLD`] (glibc; nothing elsewhere).
/// Call once at start, before the threads.
pub fn configure_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets the allocator's parameters; called before other threads run.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD as libc::c_int);
    }
}

/// Hands freed memory back every [`RELEASE_PERIOD`] ([`MemoryRelease::when_due`]).
pub struct MemoryRelease {
    last: Instant,
}

impl Default for MemoryRelease {
    fn default() -> Self {
        Self {
            last: Instant::now(),
        }
    }
}

impl MemoryRelease {
    /// Returns the allocator's free pages to the operating system (glibc's `malloc_trim(0)`;
    /// nothing elsewhere) when [`RELEASE_PERIOD`] has passed since the last time.
    pub fn when_due(&mut self, now: Instant) {
        if now.duration_since(self.last) < RELEASE_PERIOD {
            return;
        }
        self.last = now;
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        // SAFETY: malloc_trim only walks the allocator's own arenas, under their locks.
        unsafe {
            libc::malloc_trim(0);
        }
    }
}
