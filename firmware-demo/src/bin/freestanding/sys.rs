//! Everything a C runtime would have provided, for x86-64 Linux: the entry point, raw
//! system calls for output, time and exit, and the panic handler.

use core::arch::{asm, global_asm};
use core::fmt;

const SYS_WRITE: usize = 1;
const SYS_CLOCK_GETTIME: usize = 228;
const SYS_EXIT_GROUP: usize = 231;
const CLOCK_MONOTONIC: usize = 1;
const STDOUT: usize = 1;
const STDERR: usize = 2;
const EINTR: isize = 4;

// The kernel enters with the stack pointer 16-byte aligned and pointing at argc; the System
// V ABI wants it 16-byte aligned *before* a call, so re-align and call into Rust. `ud2`
// traps should the entry function ever return.
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

extern "C" fn entry() -> ! {
    exit(crate::run())
}

/// # Safety
/// `number` and the arguments must form a valid Linux x86-64 system call.
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

pub fn exit(status: u8) -> ! {
    // SAFETY: exit_group takes one integer and does not return.
    unsafe {
        syscall3(SYS_EXIT_GROUP, usize::from(status), 0, 0);
        asm!("ud2", options(noreturn));
    }
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
