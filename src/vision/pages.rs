//! Large working buffers on transparent huge pages.
//!
//! A buffer of tens of MB that is written once (a descriptor image, a cost volume, the BP
//! messages, a scale space) costs more in first-touch page faults than in its arithmetic: one
//! fault per 4 KiB page (measured on the 1280×960 pair: 150 000 faults, an eighth of the
//! process's CPU). Backed by 2 MiB pages the same memory takes a 512th of the faults (measured:
//! 128 MiB first touched in 140 ms on 4 KiB pages, 34 ms on huge pages). Advice only: the
//! contents are the same, and nothing changes where transparent huge pages are off.

/// Smallest buffer that is advised: above glibc's largest dynamic mmap threshold (32 MiB on
/// 64-bit), so always a mapping of its own, which is unmapped when freed. Advice on the C
/// allocator's heap would outlive the buffer and back later small allocations with whole huge
/// pages (measured: +40 MiB peak RSS).
const HUGE_PAGES_FROM: usize = 33 << 20;

/// Buffers from this size on get huge pages: their room is reserved up to [`HUGE_PAGES_FROM`]
/// (address space only; the room beyond their length is never touched, so never resident).
const HUGE_PAGES_WORTH: usize = 4 << 20;

/// An element whose all-zero bytes are its zero, so that `vec![ZERO; n]` is a `calloc`
/// (fresh mapped memory that nothing writes before the caller).
pub(crate) trait Zero: Copy {
    const ZERO: Self;
}

impl Zero for u8 {
    const ZERO: Self = 0;
}

impl Zero for u16 {
    const ZERO: Self = 0;
}

impl Zero for f32 {
    const ZERO: Self = 0.0;
}

/// Elements of room a buffer of `len` elements gets (at least `len`).
fn capacity_for<T>(len: usize) -> usize {
    let size = size_of::<T>().max(1);
    if len.saturating_mul(size) < HUGE_PAGES_WORTH {
        len
    } else {
        len.max(HUGE_PAGES_FROM.div_ceil(size))
    }
}

/// `len` zeros; on huge pages when the buffer is large.
#[must_use]
pub(crate) fn zeroed<T: Zero>(len: usize) -> Vec<T> {
    let cap = capacity_for::<T>(len);
    if cap == len && len * size_of::<T>() < HUGE_PAGES_FROM {
        return vec![T::ZERO; len];
    }
    // Fresh zeroed memory is not written by the allocator: the advice comes before the first
    // touch.
    let mut v = vec![T::ZERO; cap];
    v.truncate(len);
    advise(&v);
    v
}

/// An empty buffer with room for `len` elements; on huge pages when it is large.
#[must_use]
pub(crate) fn room<T>(len: usize) -> Vec<T> {
    let v = Vec::with_capacity(capacity_for::<T>(len));
    advise(&v);
    v
}

/// Asks the kernel to back the whole 2 MiB pages inside `v`'s room with huge pages, when the
/// room is a mapping of its own ([`HUGE_PAGES_FROM`]).
fn advise<T>(v: &Vec<T>) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let bytes = v.capacity() * size_of::<T>();
        let start = v.as_ptr() as usize;
        let (a, b) = (start.next_multiple_of(HUGE), (start + bytes) / HUGE * HUGE);
        if bytes >= HUGE_PAGES_FROM && b > a {
            // SAFETY: `madvise` with MADV_HUGEPAGE on whole pages inside this vector's
            // allocation changes neither contents nor validity of the memory, only how the
            // kernel backs it; a failure (advice refused) is harmless and ignored.
            unsafe {
                libc::madvise(a as *mut libc::c_void, b - a, libc::MADV_HUGEPAGE);
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = v;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zeroed_buffers_hold_zeros_of_the_asked_length() {
        for len in [0, 1, 1000, (8 << 20) / 4 + 3, (40 << 20) / 2] {
            let v: Vec<u16> = zeroed(len);
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x == 0));
            let f: Vec<f32> = zeroed(len);
            assert_eq!(f.len(), len);
            assert!(f.iter().all(|&x| x.to_bits() == 0));
        }
    }

    #[test]
    fn large_buffers_reserve_a_mapping_of_their_own() {
        let small: Vec<u8> = room(1000);
        assert!(small.capacity() >= 1000 && small.capacity() < HUGE_PAGES_FROM);
        let large: Vec<f32> = room((9 << 20) / 4);
        assert!(large.capacity() * 4 >= HUGE_PAGES_FROM);
        assert!(large.is_empty());
    }
}
