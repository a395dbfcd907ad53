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
//!
//! Mapping every frame-sized buffer afresh costs its page faults and the kernel's zeroing on
//! every frame: a 5 MP frame's DDS reassembly buffer, its deserialised copy and the
//! detector's per-frame vectors were 30 % of the node's CPU (`perf record` on
//! `test/run_bench.sh --kind hpcode_5mp`). The node's allocator, [`FrameBlocks`], therefore
//! keeps the last freed blocks of that size (at most [`CACHED_BLOCKS`] of them and
//! [`CACHED_BYTES`] in all) and hands them out again: the next frame asks for the same sizes.
//! The resident size stays bounded by that cap.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::Mutex;
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

/// Freed blocks kept for reuse by [`FrameBlocks`], at most.
pub const CACHED_BLOCKS: usize = 48;

/// Bytes of freed blocks kept by [`FrameBlocks`], at most: a few 5 MP frames' buffers.
pub const CACHED_BYTES: usize = 128 << 20;

/// Alignment of every block that glibc's `malloc` returns (x86-64 and aarch64): the blocks
/// [`FrameBlocks`] keeps serve requests aligned to it or less.
const MALLOC_ALIGN: usize = 16;

/// The node's global allocator: the system's, except that freed blocks of at least
/// [`MMAP_THRESHOLD`] bytes are kept ([`CACHED_BLOCKS`], [`CACHED_BYTES`]; the oldest handed
/// back first) and reused for the next request they fit, at most twice its size (module
/// docs). Only where `malloc_usable_size` tells a block's real size (glibc); elsewhere it is
/// the system allocator.
pub struct FrameBlocks {
    kept: Mutex<KeptBlocks>,
}

/// The blocks [`FrameBlocks`] keeps: address and usable size, oldest first.
struct KeptBlocks {
    blocks: [(usize, usize); CACHED_BLOCKS],
    count: usize,
    bytes: usize,
}

impl KeptBlocks {
    /// Takes the `k`-th kept block out (the later ones move up): its address.
    fn remove(&mut self, k: usize) -> usize {
        let (address, usable) = self.blocks[k];
        self.blocks.copy_within(k + 1..self.count, k);
        self.count -= 1;
        self.bytes -= usable;
        address
    }
}

impl Default for FrameBlocks {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameBlocks {
    /// An allocator keeping no block yet.
    pub const fn new() -> Self {
        FrameBlocks {
            kept: Mutex::new(KeptBlocks {
                blocks: [(0, 0); CACHED_BLOCKS],
                count: 0,
                bytes: 0,
            }),
        }
    }

    /// Number and bytes of the blocks kept now.
    pub fn kept(&self) -> (usize, usize) {
        let kept = self.lock();
        (kept.count, kept.bytes)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, KeptBlocks> {
        // Nothing panics while the lock is held; a poisoned lock still holds valid blocks.
        self.kept.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Whether blocks of `layout` are kept and reused.
    fn keeps(layout: Layout) -> bool {
        cfg!(all(target_os = "linux", target_env = "gnu"))
            && layout.size() >= MMAP_THRESHOLD
            && layout.align() <= MALLOC_ALIGN
    }

    /// A kept block for `size` bytes (the smallest that fits, at most twice the size),
    /// taken out of the cache.
    fn take(&self, size: usize) -> Option<*mut u8> {
        let mut kept = self.lock();
        let best = (0..kept.count)
            .filter(|&k| (size..=2 * size).contains(&kept.blocks[k].1))
            .min_by_key(|&k| kept.blocks[k].1)?;
        Some(kept.remove(best) as *mut u8)
    }

    /// Keeps the freed block `ptr` of `usable` bytes, handing back the oldest ones that no
    /// longer fit under the caps; `false` (the caller frees it) when it alone is over
    /// [`CACHED_BYTES`].
    ///
    /// # Safety
    /// `ptr` is a live block of the system allocator, given up by its owner.
    unsafe fn keep(&self, ptr: *mut u8, usable: usize) -> bool {
        if usable > CACHED_BYTES {
            return false;
        }
        let mut evicted = [0usize; CACHED_BLOCKS];
        let mut n_evicted = 0;
        {
            let mut kept = self.lock();
            while kept.count == CACHED_BLOCKS || kept.bytes + usable > CACHED_BYTES {
                evicted[n_evicted] = kept.remove(0);
                n_evicted += 1;
            }
            let count = kept.count;
            kept.blocks[count] = (ptr as usize, usable);
            kept.count += 1;
            kept.bytes += usable;
        }
        // Unmapped outside the lock: other threads' large requests need not wait for it.
        for &address in &evicted[..n_evicted] {
            // SAFETY: a block of the system allocator that the cache owned.
            unsafe { libc::free(address as *mut libc::c_void) };
        }
        true
    }
}

/// The usable size of the system allocator's block `ptr`.
///
/// # Safety
/// `ptr` is a live block of the system allocator.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
unsafe fn usable_size(ptr: *mut u8) -> usize {
    // SAFETY: the caller's.
    unsafe { libc::malloc_usable_size(ptr as *mut libc::c_void) }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
unsafe fn usable_size(_ptr: *mut u8) -> usize {
    0 // never called: `FrameBlocks::keeps` is false there
}

// SAFETY: every block comes from `System` (directly, or kept and handed out again, whole and
// to one owner at a time); kept blocks are `malloc` blocks aligned to `MALLOC_ALIGN`, served
// only to requests aligned to it or less, and at least as large as the request.
unsafe impl GlobalAlloc for FrameBlocks {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if Self::keeps(layout) {
            if let Some(ptr) = self.take(layout.size()) {
                return ptr;
            }
        }
        // SAFETY: the caller's contract.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if Self::keeps(layout) {
            if let Some(ptr) = self.take(layout.size()) {
                // SAFETY: the block holds at least `layout.size()` bytes.
                unsafe { std::ptr::write_bytes(ptr, 0, layout.size()) };
                return ptr;
            }
        }
        // SAFETY: the caller's contract.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` is live and from `System` (see the impl's comment).
        if Self::keeps(layout) && unsafe { self.keep(ptr, usable_size(ptr)) } {
            return;
        }
        // SAFETY: the caller's contract.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: the caller's contract makes `new_size` a valid size for this alignment.
        let new_layout = unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) };
        if !Self::keeps(layout) && !Self::keeps(new_layout) {
            // SAFETY: the caller's contract.
            return unsafe { System.realloc(ptr, layout, new_size) };
        }
        // SAFETY: the caller's contract; the new block holds `new_size` bytes.
        unsafe {
            let new = self.alloc(new_layout);
            if !new.is_null() {
                std::ptr::copy_nonoverlapping(ptr, new, layout.size().min(new_size));
                self.dealloc(ptr, layout);
            }
            new
        }
    }
}

#[cfg(all(test, target_os = "linux", target_env = "gnu"))]
mod tests {
    use super::*;

    fn layout(size: usize) -> Layout {
        Layout::from_size_align(size, 8).unwrap()
    }

    #[test]
    fn a_freed_frame_block_serves_the_next_request_of_its_size() {
        let blocks = FrameBlocks::new();
        let size = 5 << 20;
        // SAFETY: each block is used within its layout and freed once, by this allocator.
        unsafe {
            let first = blocks.alloc(layout(size));
            first.write_bytes(7, size);
            blocks.dealloc(first, layout(size));
            assert_eq!(blocks.kept().0, 1);
            // A smaller request that it fits takes it, zeroed when asked.
            let again = blocks.alloc_zeroed(layout(size - 1000));
            assert_eq!(again, first);
            assert!(std::slice::from_raw_parts(again, size - 1000)
                .iter()
                .all(|&b| b == 0));
            assert_eq!(blocks.kept(), (0, 0));
            // One less than half its size does not.
            blocks.dealloc(again, layout(size - 1000));
            let small = blocks.alloc(layout(size / 2 - 100));
            assert_ne!(small, first);
            blocks.dealloc(small, layout(size / 2 - 100));
            // Small blocks are never kept.
            let tiny = blocks.alloc(layout(1000));
            blocks.dealloc(tiny, layout(1000));
            assert_eq!(blocks.kept().0, 2);
            drain(&blocks);
        }
    }

    #[test]
    fn the_cache_stays_under_its_caps_handing_back_the_oldest() {
        let blocks = FrameBlocks::new();
        // Small blocks meet the count's cap, large ones the bytes' cap.
        for (size, n) in [(MMAP_THRESHOLD, CACHED_BLOCKS + 8), (20 << 20, 10)] {
            // SAFETY: as above.
            unsafe {
                let all: Vec<*mut u8> = (0..n).map(|_| blocks.alloc(layout(size))).collect();
                for &p in &all {
                    blocks.dealloc(p, layout(size));
                    let (count, bytes) = blocks.kept();
                    assert!(count <= CACHED_BLOCKS && bytes <= CACHED_BYTES);
                }
                let (count, bytes) = blocks.kept();
                assert!(count == CACHED_BLOCKS || bytes + size > CACHED_BYTES);
                // The newest are the ones kept.
                let newest = blocks.alloc(layout(size));
                assert!(all[n - count..].contains(&newest));
                blocks.dealloc(newest, layout(size));
                drain(&blocks);
            }
        }
        // A block over the whole cap is freed at once.
        // SAFETY: as above.
        unsafe {
            let huge = blocks.alloc(layout(CACHED_BYTES + 1));
            blocks.dealloc(huge, layout(CACHED_BYTES + 1));
        }
        assert_eq!(blocks.kept(), (0, 0));
    }

    #[test]
    fn realloc_keeps_the_contents_across_the_threshold() {
        let blocks = FrameBlocks::new();
        // SAFETY: as above.
        unsafe {
            let small = blocks.alloc(layout(1000));
            small.write_bytes(3, 1000);
            let large = blocks.realloc(small, layout(1000), 1 << 20);
            assert!(std::slice::from_raw_parts(large, 1000)
                .iter()
                .all(|&b| b == 3));
            let back = blocks.realloc(large, layout(1 << 20), 500);
            assert!(std::slice::from_raw_parts(back, 500)
                .iter()
                .all(|&b| b == 3));
            assert_eq!(blocks.kept().0, 1);
            blocks.dealloc(back, layout(500));
            drain(&blocks);
        }
    }

    /// Frees what `blocks` keeps.
    unsafe fn drain(blocks: &FrameBlocks) {
        let mut kept = blocks.lock();
        for &(address, _) in &kept.blocks[..kept.count] {
            // SAFETY: blocks of the system allocator that the cache owned.
            unsafe { libc::free(address as *mut libc::c_void) };
        }
        kept.count = 0;
        kept.bytes = 0;
    }
}
