//! The C memory functions the compiler emits calls to. On x86_64-unknown-linux-gnu the
//! prebuilt compiler_builtins leaves them to libc (its `mem` feature is off), so a binary
//! without libc must define them. Written with string instructions: a plain Rust loop here
//! could be recognised by LLVM as a memcpy idiom and compiled into a call to itself.

use core::arch::asm;
use core::ffi::c_int;

/// # Safety
/// As C `memcpy`: `count` bytes readable at `source`, writable at `destination`, no overlap.
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
