//! Handing freed heap memory back to the operating system, so that the node's resident size
//! follows what it holds over a day-long run.
//!
//! glibc's allocator keeps what a thread frees in that thread's arena, and raises its mmap
//! threshold after the first large buffer is freed, so later frame-sized buffers (a 1–5 MB
//! image message from the DDS receiver, the detector's per-frame vectors) come from the heap
//! and stay resident once freed. Which arena, and where in it, depends on thread timing: over
//! a run with mode changes (tracking off and on, a marker lost and found) the resident size
//! wandered by ±10 % around the same live memory (`test/run_soak.sh`: −4 % and +6 % between
//! two quiet spans of two runs). `malloc_trim` returns the free pages of every arena. It took
//! 1.7 ms (median; at most 7 ms) on a 1 MP soak run and holds each arena's lock while it
//! walks it, so it runs every [`RELEASE_PERIOD`], off the frame path: a frame that allocates
//! meanwhile waits, once in ten seconds, below the latency's 99th percentile.

use std::time::{Duration, Instant};

/// How often freed memory is handed back.
pub const RELEASE_PERIOD: Duration = Duration::from_secs(10);

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
