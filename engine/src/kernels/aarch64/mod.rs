//! aarch64 kernels, chosen at run time from what the CPU reports: NEON (every aarch64
//! application core: Cortex-A53, A72), NEON with the dot-product extension (`sdot`:
//! Cortex-A55, A76, A78AE (Jetson Orin), Neoverse N1, Apple M1), and I8MM (`usdot`, and the
//! matrix multiplies `usmmla` and `smmla` (`mmla`): Neoverse V1, V2, N2, Cortex-A510/A710
//! and later, Apple M2 on).
//!
//! The f32 kernels are the shared bodies of `simd` on `lanes::Neon8`, eight lanes as on
//! AVX2, so they give AVX2's bits; the int8 convolutions are the shared tiles on
//! `int8_lanes`, exact integer sums, so they give every backend's bits. Element-wise
//! operations are the portable code, which the compiler vectorizes for NEON as it is.

mod backends;
mod bytes;
mod int8_lanes;
mod lanes;
mod matvec;
mod mmla;

pub use backends::{Dot, I8mm, Neon};

/// The f32 U-Net kernels of `simd::sequence` on NEON.
pub(crate) mod sequence {
    use super::lanes::Neon8;
    crate::kernels::simd::sequence::backend!(neon, super::Neon8, "neon");

    /// `Kernels::matvec` on eight lanes, x86-64's order.
    ///
    /// # Safety
    /// NEON.
    #[target_feature(enable = "neon")]
    pub(crate) unsafe fn matvec(weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
        // SAFETY: this function's contract is the body's.
        unsafe { crate::kernels::simd::sequence::matvec::<Neon8>(weight, input, base, output) }
    }
}

/// The int8 tiles on each backend's dot product. Pixels x vectors of four channels: the
/// digit tiles hold both planes' sums (2 x 2 x 4 = 16 of the 32 registers, 4 weight vectors,
/// the broadcasts); the code tiles two sums a vector (4 x 2 x 2 = 16).
pub(crate) mod int8 {
    use super::int8_lanes::{DotQ, UsdotQ, WideningQ};
    const TILE: (usize, usize) = (2, 4);
    const CODES_TILE: (usize, usize) = (4, 2);
    crate::kernels::simd::int8::backend!(
        neon,
        super::WideningQ,
        super::TILE,
        super::CODES_TILE,
        "neon"
    );
    crate::kernels::simd::int8::backend!(
        dot,
        super::DotQ,
        super::TILE,
        super::CODES_TILE,
        "neon,dotprod"
    );
    crate::kernels::simd::int8::backend!(
        i8mm,
        super::UsdotQ,
        super::TILE,
        super::CODES_TILE,
        "neon,dotprod,i8mm"
    );

    /// The `sdot` tile of bytes, signed or centred (one plane: 16 sums, 4 weight vectors,
    /// the broadcast).
    pub(crate) const BYTES_TILE: (usize, usize) = (4, 4);
    pub(crate) use super::int8_lanes::DotQ as SignedBytes;
}

// Hosted builds ask the OS (`os`, whose two functions shadow the glob import, so it brings
// nothing there); firmware reads the ID registers (`registers`), which not every OS lets
// user code read.
#[allow(unused_imports)]
pub use registers::*;

#[cfg(feature = "std")]
mod os;
#[cfg(feature = "std")]
pub use os::{has_dotprod, has_i8mm};

/// The features read from the ID registers themselves: the engine's answer where there is
/// no OS to ask (firmware, at EL1). On an OS, user code reads them only where the OS
/// emulates the reads (Linux since 4.11, qemu's user mode); elsewhere (macOS) the read
/// traps and ends the process: hosted code asks `aarch64::has_dotprod` and `has_i8mm`, the
/// OS's answers, instead.
pub mod registers {
    /// The dot-product extension (`sdot`, FEAT_DotProd) is present: ID_AA64ISAR0_EL1.DP,
    /// bits 47:44, is 1 or more.
    pub fn has_dotprod() -> bool {
        (id_register::<0>() >> 44) & 0xf >= 1
    }

    /// The int8 matrix multiply extension (`usdot`, `smmla`, FEAT_I8MM) is present, and the
    /// dot product: ID_AA64ISAR1_EL1.I8MM, bits 55:52, is 1 or more.
    pub fn has_i8mm() -> bool {
        (id_register::<1>() >> 52) & 0xf >= 1 && has_dotprod()
    }

    /// ID_AA64ISAR0_EL1 (`N = 0`) or ID_AA64ISAR1_EL1 (`N = 1`).
    fn id_register<const N: usize>() -> u64 {
        let value: u64;
        // SAFETY: reading an ID register touches no memory and has no side effect (where
        // EL0 may not read it and the OS does not emulate the read, it traps: see above).
        unsafe {
            if N == 0 {
                core::arch::asm!("mrs {0}, ID_AA64ISAR0_EL1", out(reg) value, options(nomem, nostack, preserves_flags));
            } else {
                core::arch::asm!("mrs {0}, ID_AA64ISAR1_EL1", out(reg) value, options(nomem, nostack, preserves_flags));
            }
        }
        value
    }
}
