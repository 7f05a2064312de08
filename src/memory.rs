//! How the process asks the C allocator for memory.
//!
//! A reconstruction allocates and frees buffers of tens of megabytes over and
//! over (cost volumes, BP messages, the refinement's window sums, one set per
//! pyramid level and direction). glibc serves each of them with a fresh
//! `mmap` and gives it back with `munmap` on free, so every buffer's pages
//! are faulted in and zeroed again: on a 1280×960 pair that was 2.0–2.4 s of
//! system time in a 5.1–5.5 s run. [`keep_large_buffers`] makes glibc serve
//! them from the heap and keep freed pages for the next buffer (the same
//! `sdsem reconstruct`: system time 1.0 s, wall 4.3–4.6 s, peak RSS +2 %);
//! [`release_free_memory`] hands the kept pages back, which the daemon does
//! after every job so an idle daemon stays small.
//!
//! Both are no-ops off glibc (musl, macOS), where the allocators differ.
//!
//! [`PrefaultZeroed`], the binary's global allocator, writes large zeroed
//! blocks instead of leaving their fresh pages to the zero page: on the same
//! pair system time 1.2 → 0.7 s, minor faults 227 k → 191–207 k, and the
//! copy-on-write faults with their TLB shootdowns (5 % of the CPU samples)
//! gone from the profile.

/// Largest allocation served from the heap rather than by its own `mmap`,
/// and the free space at the top of the heap kept rather than trimmed, bytes.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const KEEP_BYTES: libc::c_int = 1 << 30;

/// Lets the allocator keep large freed buffers for reuse. Call once, first
/// thing in `main`, before any thread starts.
pub fn keep_large_buffers() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallopt only changes the allocator's tuning parameters; it
        // is called before any other thread exists, and a refused value
        // (return 0) leaves glibc's defaults, which are as correct.
        let ok = unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, KEEP_BYTES) == 1
                && libc::mallopt(libc::M_TRIM_THRESHOLD, KEEP_BYTES) == 1
        };
        if !ok {
            tracing::debug!("mallopt refused the large-buffer tuning; glibc defaults stay");
        }
    }
}

/// Returns the free pages the allocator keeps to the operating system.
pub fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: malloc_trim only releases free memory of the allocator's
        // own arenas; it is thread-safe and touches no live allocation.
        unsafe {
            libc::malloc_trim(0);
        }
    }
}

/// Zeroed allocations of at least this many bytes are written at once.
const PREFAULT_BYTES: usize = 1 << 20;

/// The system allocator, except that a large zeroed allocation is written
/// with zeros instead of relying on fresh pages being zero.
///
/// `calloc` hands out fresh pages unwritten. The image code then reads many
/// of them before it writes them (`+=` into a zeroed accumulator, the first
/// BP sweep reading its zeroed messages): the first read maps the shared
/// zero page, the first write copies it, and that copy flushes the TLB of
/// every core running the process (an inter-processor interrupt). Writing
/// the zeros first gives each page one ordinary fault instead.
pub struct PrefaultZeroed;

// SAFETY: every method forwards to `System` with the caller's layout; the
// only addition writes `layout.size()` bytes into the block `System.alloc`
// just returned for that layout (checked for null first).
unsafe impl std::alloc::GlobalAlloc for PrefaultZeroed {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        // SAFETY: the caller's contract is the same as System's.
        unsafe { std::alloc::System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: std::alloc::Layout) -> *mut u8 {
        if layout.size() < PREFAULT_BYTES {
            // SAFETY: the caller's contract is the same as System's.
            return unsafe { std::alloc::System.alloc_zeroed(layout) };
        }
        // SAFETY: the caller's contract is the same as System's; a non-null
        // block holds `layout.size()` writable bytes.
        unsafe {
            let p = std::alloc::System.alloc(layout);
            if !p.is_null() {
                std::ptr::write_bytes(p, 0, layout.size());
            }
            p
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: std::alloc::Layout) {
        // SAFETY: the caller's contract is the same as System's.
        unsafe { std::alloc::System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: std::alloc::Layout, new_size: usize) -> *mut u8 {
        // SAFETY: the caller's contract is the same as System's.
        unsafe { std::alloc::System.realloc(ptr, layout, new_size) }
    }
}

#[cfg(test)]
mod tests {
    use std::alloc::{GlobalAlloc, Layout};

    use super::*;

    /// Zeroed blocks below and above the threshold are zero, and every
    /// method hands blocks back and forth with the system allocator.
    #[test]
    fn zeroed_blocks_are_zero_on_both_sides_of_the_threshold() {
        let a = PrefaultZeroed;
        for size in [
            64,
            PREFAULT_BYTES - 1,
            PREFAULT_BYTES,
            3 * PREFAULT_BYTES + 5,
        ] {
            let layout = Layout::from_size_align(size, 64).unwrap();
            // SAFETY: a non-zero size; each block is freed with its layout.
            unsafe {
                // Dirty a block of the same size first, so that a reuse of
                // it could not pass for zeroing.
                let dirty = a.alloc(layout);
                assert!(!dirty.is_null());
                std::ptr::write_bytes(dirty, 0xA5, size);
                a.dealloc(dirty, layout);
                let p = a.alloc_zeroed(layout);
                assert!(!p.is_null());
                let bytes = std::slice::from_raw_parts(p, size);
                assert!(bytes.iter().all(|&b| b == 0), "size {size}");
                let q = a.realloc(p, layout, 2 * size);
                assert!(!q.is_null());
                assert!(std::slice::from_raw_parts(q, size).iter().all(|&b| b == 0));
                a.dealloc(q, Layout::from_size_align(2 * size, 64).unwrap());
            }
        }
    }
}
