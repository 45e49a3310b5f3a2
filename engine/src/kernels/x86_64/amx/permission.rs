//! Whether this process may use the tile registers: Linux hands them out on request only
//! (`arch_prctl(ARCH_REQ_XCOMP_PERM)`); without an OS the firmware that set XCR0 has enabled
//! them.

use core::arch::asm;

#[cfg(target_os = "linux")]
pub(super) fn tile_data_permitted() -> bool {
    use core::sync::atomic::{AtomicU8, Ordering};
    const UNKNOWN: u8 = 0;
    const GRANTED: u8 = 1;
    const REFUSED: u8 = 2;
    static PERMISSION: AtomicU8 = AtomicU8::new(UNKNOWN);
    match PERMISSION.load(Ordering::Relaxed) {
        GRANTED => true,
        REFUSED => false,
        _ => {
            // Asking twice (two threads racing here) is harmless: the kernel grants the
            // same permission again.
            let granted = request_tile_data();
            let state = if granted { GRANTED } else { REFUSED };
            PERMISSION.store(state, Ordering::Relaxed);
            granted
        }
    }
}

/// `arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`: until a process asks, Linux
/// traps its first tile instruction and kills it. A raw system call, as the engine links
/// no C library.
#[cfg(target_os = "linux")]
fn request_tile_data() -> bool {
    const SYS_ARCH_PRCTL: isize = 158;
    const ARCH_REQ_XCOMP_PERM: usize = 0x1023;
    const XFEATURE_XTILEDATA: usize = 18;
    let result: isize;
    // SAFETY: the system call only changes which register state this process may use; it
    // reads and writes no memory of ours, and `syscall` clobbers only rcx and r11 (declared).
    unsafe {
        asm!(
            "syscall",
            inlateout("rax") SYS_ARCH_PRCTL => result,
            in("rdi") ARCH_REQ_XCOMP_PERM,
            in("rsi") XFEATURE_XTILEDATA,
            lateout("rcx") _,
            lateout("r11") _,
            options(nostack),
        );
    }
    result == 0
}

/// No OS: XCR0, which [`has_amx_int8`](crate::kernels::x86_64::has_amx_int8) read, is the whole story.
#[cfg(target_os = "none")]
pub(super) fn tile_data_permitted() -> bool {
    true
}

/// Another OS may trap tile instructions in ways this code does not know to ask about.
#[cfg(not(any(target_os = "linux", target_os = "none")))]
pub(super) fn tile_data_permitted() -> bool {
    false
}
