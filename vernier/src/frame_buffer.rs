//! Frame-sized buffers (a camera frame's file bytes, its working image): made fresh when they
//! must grow, and backed by transparent huge pages on Linux.
//!
//! A one-shot run touches every page of its 5 MB file buffer and 20 MB working image for the
//! first time: 6,000 page faults of 4 KiB, most of the first frame's extra time over a steady
//! one. Advised before they are touched (`madvise(MADV_HUGEPAGE)`, which the kernel's default
//! `madvise` mode of transparent huge pages honours), the same buffers fault in 2 MiB at a
//! time. The advice changes nothing else: where huge pages are off or unavailable the pages
//! stay small.

/// Buffers of at least this many bytes are advised: one huge page.
const HUGE_PAGE: usize = 2 << 20;

/// Empties `buffer` and makes its capacity at least `len` elements. A buffer that must grow
/// is replaced by a fresh one (its contents are not copied: the caller fills it), advised for
/// huge pages before anything touches it.
pub(crate) fn reserve_fresh<T>(buffer: &mut Vec<T>, len: usize) {
    buffer.clear();
    if buffer.capacity() >= len {
        return;
    }
    *buffer = Vec::with_capacity(len);
    advise_huge_pages(
        buffer.as_mut_ptr().cast(),
        len.saturating_mul(size_of::<T>()),
    );
}

/// Asks the kernel to back the whole 4 KiB pages of `bytes` bytes from `start` with huge pages.
#[cfg(target_os = "linux")]
fn advise_huge_pages(start: *mut u8, bytes: usize) {
    const PAGE: usize = 4096;
    if bytes < HUGE_PAGE {
        return;
    }
    let first = (start as usize).next_multiple_of(PAGE);
    let end = (start as usize).saturating_add(bytes) / PAGE * PAGE;
    if end > first {
        // SAFETY: advice on whole pages inside one live allocation of this process; it moves
        // no data, and an error (huge pages off, an old kernel) leaves the mapping as it was.
        unsafe {
            libc::madvise(first as *mut libc::c_void, end - first, libc::MADV_HUGEPAGE);
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn advise_huge_pages(_start: *mut u8, _bytes: usize) {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_buffer_grows_fresh_and_keeps_its_capacity_when_large_enough() {
        let mut buffer: Vec<f32> = vec![1.0; 10];
        reserve_fresh(&mut buffer, 5);
        assert!(buffer.is_empty() && buffer.capacity() >= 10);
        reserve_fresh(&mut buffer, 3 << 20);
        assert!(buffer.is_empty() && buffer.capacity() >= 3 << 20);
        buffer.resize(3 << 20, 2.0);
        assert!(buffer.iter().all(|&v| v == 2.0));
    }
}
