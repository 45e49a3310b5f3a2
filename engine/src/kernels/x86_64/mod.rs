//! x86-64 kernels, chosen at run time from what the CPU reports (CPUID works without std).

pub mod avx2;
pub mod sequence;

use core::arch::x86_64::{__cpuid, __cpuid_count, _xgetbv};

/// Reads XCR0. Only called once CPUID has reported OSXSAVE.
#[target_feature(enable = "xsave")]
fn os_enabled_state() -> u64 {
    // SAFETY: `xgetbv` is available: the caller checked CPUID's OSXSAVE bit, which the
    // target_feature contract of this function stands for.
    unsafe { _xgetbv(0) }
}

/// AVX2 and FMA are present and the OS saves the YMM registers.
pub fn has_avx2_fma() -> bool {
    // CPUID is safe on x86-64; leaf 1 exists on every such processor.
    let basic = __cpuid(1);
    let fma = basic.ecx & (1 << 12) != 0;
    let osxsave = basic.ecx & (1 << 27) != 0;
    let avx = basic.ecx & (1 << 28) != 0;
    if !(fma && osxsave && avx) {
        return false;
    }
    // SAFETY: OSXSAVE is set, so XGETBV may be executed.
    let state = unsafe { os_enabled_state() };
    if state & 0b110 != 0b110 {
        return false;
    }
    // Leaf 0 reports the highest leaf; leaf 7 (structured features) is read only if present.
    let highest = __cpuid(0).eax;
    highest >= 7 && __cpuid_count(7, 0).ebx & (1 << 5) != 0
}
