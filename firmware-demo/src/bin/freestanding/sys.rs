//! Everything a C runtime would have provided, for Linux on x86-64 and aarch64: the entry
//! point, raw system calls for output, time and exit, and the panic handler.

use core::arch::{asm, global_asm};
use core::fmt;

#[cfg(target_arch = "x86_64")]
mod numbers {
    pub const SYS_WRITE: usize = 1;
    pub const SYS_CLOCK_GETTIME: usize = 228;
    pub const SYS_EXIT_GROUP: usize = 231;
}

// aarch64 uses the generic system call table.
#[cfg(target_arch = "aarch64")]
mod numbers {
    pub const SYS_WRITE: usize = 64;
    pub const SYS_CLOCK_GETTIME: usize = 113;
    pub const SYS_EXIT_GROUP: usize = 94;
}

use numbers::{SYS_CLOCK_GETTIME, SYS_EXIT_GROUP, SYS_WRITE};
const CLOCK_MONOTONIC: usize = 1;
const STDOUT: usize = 1;
const STDERR: usize = 2;
const EINTR: isize = 4;

// The kernel enters with the stack pointer 16-byte aligned and pointing at argc; the System
// V ABI wants it 16-byte aligned *before* a call, so re-align and call into Rust. `ud2`
// traps should the entry function ever return.
#[cfg(target_arch = "x86_64")]
global_asm!(
    ".globl _start",
    ".type _start, @function",
    "_start:",
    "xor ebp, ebp",
    "and rsp, -16",
    "call {entry}",
    "ud2",
    entry = sym entry,
);

// The kernel enters with sp 16-byte aligned, as the AAPCS64 wants at every call; the frame
// and link registers are cleared so that nothing unwinds past the entry. `udf` traps should
// the entry function ever return.
#[cfg(target_arch = "aarch64")]
global_asm!(
    ".globl _start",
    ".type _start, %function",
    "_start:",
    "mov x29, xzr",
    "mov x30, xzr",
    "bl {entry}",
    "udf #0",
    entry = sym entry,
);

extern "C" fn entry() -> ! {
    exit(crate::run())
}

/// # Safety
/// `number` and the arguments must form a valid Linux x86-64 system call.
#[cfg(target_arch = "x86_64")]
unsafe fn syscall3(number: usize, first: usize, second: usize, third: usize) -> isize {
    let result: isize;
    // SAFETY: the caller vouches for the call; `syscall` clobbers only rcx and r11.
    unsafe {
        asm!(
            "syscall",
            inlateout("rax") number as isize => result,
            in("rdi") first,
            in("rsi") second,
            in("rdx") third,
            lateout("rcx") _,
            lateout("r11") _,
            options(nostack),
        );
    }
    result
}

/// # Safety
/// `number` and the arguments must form a valid Linux aarch64 system call.
#[cfg(target_arch = "aarch64")]
unsafe fn syscall3(number: usize, first: usize, second: usize, third: usize) -> isize {
    let result: isize;
    // SAFETY: the caller vouches for the call; `svc #0` takes the number in x8 and the
    // arguments in x0-x2, returns in x0 and clobbers nothing else.
    unsafe {
        asm!(
            "svc #0",
            in("x8") number,
            inlateout("x0") first as isize => result,
            in("x1") second,
            in("x2") third,
            options(nostack),
        );
    }
    result
}

/// Stops the program on an instruction that always traps.
fn trap() -> ! {
    // SAFETY: the instruction is undefined by design: the process gets SIGILL.
    unsafe {
        #[cfg(target_arch = "x86_64")]
        asm!("ud2", options(noreturn));
        #[cfg(target_arch = "aarch64")]
        asm!("udf #0", options(noreturn));
    }
}

pub fn exit(status: u8) -> ! {
    // SAFETY: exit_group takes one integer and does not return.
    unsafe { syscall3(SYS_EXIT_GROUP, usize::from(status), 0, 0) };
    trap()
}

fn write_all(descriptor: usize, mut bytes: &[u8]) -> fmt::Result {
    while !bytes.is_empty() {
        // SAFETY: the pointer and length describe a live byte slice.
        let written =
            unsafe { syscall3(SYS_WRITE, descriptor, bytes.as_ptr() as usize, bytes.len()) };
        match written {
            count if count > 0 => bytes = &bytes[count as usize..],
            error if error == -EINTR => {}
            _ => return Err(fmt::Error),
        }
    }
    Ok(())
}

/// Standard output or error as a `core::fmt::Write`, unbuffered.
pub struct Output(usize);

impl fmt::Write for Output {
    fn write_str(&mut self, text: &str) -> fmt::Result {
        write_all(self.0, text.as_bytes())
    }
}

pub fn stdout() -> Output {
    Output(STDOUT)
}

pub fn stderr() -> Output {
    Output(STDERR)
}

/// CLOCK_MONOTONIC in microseconds.
pub fn monotonic_us() -> u64 {
    let mut time = [0i64; 2];
    // SAFETY: clock_gettime writes one `struct timespec` (two i64) to the pointer.
    let status = unsafe {
        syscall3(
            SYS_CLOCK_GETTIME,
            CLOCK_MONOTONIC,
            time.as_mut_ptr() as usize,
            0,
        )
    };
    if status != 0 {
        return 0;
    }
    let [seconds, nanoseconds] = time;
    seconds as u64 * 1_000_000 + nanoseconds as u64 / 1_000
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
    use core::fmt::Write as _;
    let _ = writeln!(stderr(), "firmware-freestanding: panic: {info}");
    exit(101)
}

/// The libc symbols the C part of Debian's aarch64 compiler_builtins names (its initialisers
/// of the outline atomics and of the CPU feature bits). Without a C runtime those
/// initialisers never run, and the defaults they leave (no LSE atomics: load/store-exclusive
/// loops) serve a single-threaded binary; the link only needs the names.
#[cfg(target_arch = "aarch64")]
mod libc_names {
    /// No auxiliary vector entry is known.
    #[unsafe(no_mangle)]
    pub extern "C" fn getauxval(_entry: core::ffi::c_ulong) -> core::ffi::c_ulong {
        0
    }

    /// The stack protector's canary, for the C code built with it.
    #[unsafe(no_mangle)]
    pub static __stack_chk_guard: usize = 0x5ca1_ab1e_0dd5_eed5;

    /// A smashed stack in that C code: stop.
    #[unsafe(no_mangle)]
    pub extern "C" fn __stack_chk_fail() -> ! {
        super::trap()
    }
}
