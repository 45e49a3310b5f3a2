//! The C memory functions the compiler emits calls to. On the Linux targets the prebuilt
//! compiler_builtins leaves them to libc (its `mem` feature is off), so a binary without
//! libc must define them. A plain Rust loop here could be recognised by LLVM as a memcpy
//! idiom and compiled into a call to itself: on x86-64 they are string instructions, on
//! aarch64 loops of volatile accesses (eight bytes at a time where both sides allow).

#[cfg(target_arch = "x86_64")]
use core::arch::asm;
use core::ffi::c_int;

/// # Safety
/// As C `memcpy`: `count` bytes readable at `source`, writable at `destination`, no overlap.
#[cfg(target_arch = "x86_64")]
#[unsafe(no_mangle)]
pub unsafe extern "C" fn memcpy(destination: *mut u8, source: *const u8, count: usize) -> *mut u8 {
    // SAFETY: `rep movsb` copies `count` bytes forwards, as the caller allows.
    unsafe {
        asm!(
            "rep movsb",
            inout("rcx") count => _,
            inout("rdi") destination => _,
            inout("rsi") source => _,
            options(nostack, preserves_flags),
        );
    }
    destination
}

/// # Safety
/// As C `memmove`: `count` bytes readable at `source`, writable at `destination`.
#[cfg(target_arch = "x86_64")]
#[unsafe(no_mangle)]
pub unsafe extern "C" fn memmove(destination: *mut u8, source: *const u8, count: usize) -> *mut u8 {
    if (destination as usize).wrapping_sub(source as usize) >= count {
        // The destination does not start inside the source: copying forwards is safe.
        // SAFETY: as for `memcpy`; overlap only where forward copying reads before writing.
        return unsafe { memcpy(destination, source, count) };
    }
    // SAFETY: copies backwards from the last byte, so overlapping source bytes are read
    // before they are overwritten; the direction flag is restored before the block ends.
    unsafe {
        asm!(
            "std",
            "rep movsb",
            "cld",
            inout("rcx") count => _,
            inout("rdi") destination.add(count).wrapping_sub(1) => _,
            inout("rsi") source.add(count).wrapping_sub(1) => _,
            options(nostack),
        );
    }
    destination
}

/// # Safety
/// As C `memset`: `count` bytes writable at `destination`.
#[cfg(target_arch = "x86_64")]
#[unsafe(no_mangle)]
pub unsafe extern "C" fn memset(destination: *mut u8, value: c_int, count: usize) -> *mut u8 {
    // SAFETY: `rep stosb` writes `count` bytes forwards, as the caller allows.
    unsafe {
        asm!(
            "rep stosb",
            inout("rcx") count => _,
            inout("rdi") destination => _,
            in("al") value as u8,
            options(nostack, preserves_flags),
        );
    }
    destination
}

/// # Safety
/// As C `memcmp`: `count` bytes readable at both pointers.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn memcmp(first: *const u8, second: *const u8, count: usize) -> c_int {
    for index in 0..count {
        // SAFETY: `index < count`, within both buffers. Volatile so that LLVM cannot turn the
        // loop back into a call to memcmp or bcmp.
        let (a, b) = unsafe {
            (
                first.add(index).read_volatile(),
                second.add(index).read_volatile(),
            )
        };
        if a != b {
            return c_int::from(a) - c_int::from(b);
        }
    }
    0
}

/// # Safety
/// As C `bcmp`: `count` bytes readable at both pointers.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn bcmp(first: *const u8, second: *const u8, count: usize) -> c_int {
    // SAFETY: same contract.
    unsafe { memcmp(first, second, count) }
}

/// # Safety
/// As C `memcpy`: `count` bytes readable at `source`, writable at `destination`, no overlap.
#[cfg(target_arch = "aarch64")]
#[unsafe(no_mangle)]
pub unsafe extern "C" fn memcpy(destination: *mut u8, source: *const u8, count: usize) -> *mut u8 {
    // SAFETY: forwards, as the caller allows.
    unsafe { copy_forwards(destination, source, count) };
    destination
}

/// `count` bytes from `source` to `destination`, lowest address first.
///
/// # Safety
/// As for `memcpy`; overlap only where forward copying reads before it writes.
#[cfg(target_arch = "aarch64")]
unsafe fn copy_forwards(destination: *mut u8, source: *const u8, count: usize) {
    let mut index = 0;
    // SAFETY: every access is below `count`, inside both buffers; words only where both
    // pointers are 8-byte aligned.
    unsafe {
        if (destination as usize | source as usize).is_multiple_of(8) {
            while index + 8 <= count {
                let word = source.add(index).cast::<u64>().read_volatile();
                destination.add(index).cast::<u64>().write_volatile(word);
                index += 8;
            }
        }
        while index < count {
            destination
                .add(index)
                .write_volatile(source.add(index).read_volatile());
            index += 1;
        }
    }
}

/// # Safety
/// As C `memmove`: `count` bytes readable at `source`, writable at `destination`.
#[cfg(target_arch = "aarch64")]
#[unsafe(no_mangle)]
pub unsafe extern "C" fn memmove(destination: *mut u8, source: *const u8, count: usize) -> *mut u8 {
    if (destination as usize).wrapping_sub(source as usize) >= count {
        // The destination does not start inside the source: copying forwards is safe.
        // SAFETY: as for `memcpy`; overlap only where forward copying reads before writing.
        unsafe { copy_forwards(destination, source, count) };
        return destination;
    }
    // SAFETY: backwards from the last byte, so overlapping source bytes are read before they
    // are overwritten.
    unsafe {
        for index in (0..count).rev() {
            destination
                .add(index)
                .write_volatile(source.add(index).read_volatile());
        }
    }
    destination
}

/// # Safety
/// As C `memset`: `count` bytes writable at `destination`.
#[cfg(target_arch = "aarch64")]
#[unsafe(no_mangle)]
pub unsafe extern "C" fn memset(destination: *mut u8, value: c_int, count: usize) -> *mut u8 {
    let byte = value as u8;
    let word = u64::from_ne_bytes([byte; 8]);
    let mut index = 0;
    // SAFETY: every write is below `count`, inside the buffer; words only where it is
    // 8-byte aligned.
    unsafe {
        if (destination as usize).is_multiple_of(8) {
            while index + 8 <= count {
                destination.add(index).cast::<u64>().write_volatile(word);
                index += 8;
            }
        }
        while index < count {
            destination.add(index).write_volatile(byte);
            index += 1;
        }
    }
    destination
}
