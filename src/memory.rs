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
