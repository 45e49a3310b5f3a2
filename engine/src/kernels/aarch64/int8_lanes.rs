//! The aarch64 integer dot products of the int8 kernels, four output channels a NEON
//! register: widening multiplies (`smull`, pairwise adds) on every NEON core, `sdot` with the
//! dot-product extension, `usdot` with I8MM. All exact, so the shared tiles give the same
//! bits as on x86-64.

use core::arch::aarch64::{
    float32x4_t, float64x2_t, int32x4_t, vaddlvq_s32, vaddq_f64, vaddq_s32, vcvt_f32_f64,
    vcvt_high_f32_f64, vcvtq_f32_s32, vcvtq_f64_s64, vdupq_n_f32, vdupq_n_f64, vdupq_n_s32,
    vdupq_n_s64, vget_high_s16, vget_low_s8, vget_low_s16, vget_low_s32, vld1_s8, vld1q_f32,
    vld1q_s8, vld1q_s16, vld1q_s32, vmovl_high_s32, vmovl_s8, vmovl_s32, vmull_high_s8, vmull_s8,
    vmull_s16, vmulq_f32, vmulq_f64, vpaddlq_s16, vpaddq_s32, vreinterpretq_s8_s32,
    vreinterpretq_s16_s32, vreinterpretq_s16_s64, vreinterpretq_s32_s8, vreinterpretq_s32_s16,
    vst1q_f32,
};

use crate::kernels::ops;
use crate::kernels::simd::int8::{CenteredByteLanes, Int8Lanes, SignedByteLanes};

/// Baseline NEON: a quad's products by `smull` / `smull2` (i8 x i8 into i16), adjacent pairs
/// widened and added into i32 (`saddlp`), the two pairs of a channel added (`addp`): exact
/// for any signed bytes.
pub(crate) struct WideningQ;

/// The dot-product extension: `sdot` adds a quad's four i8 x i8 products into each i32 lane
/// in one instruction, exact (activations here are digits, 0..=127 or signed).
pub(crate) struct DotQ;

/// I8MM: `usdot` multiplies four u8 activations by four i8 weights into each i32 lane, exact
/// (VNNI's `vpdpbusd`); the digit tiles run on it (whole bytes take the matrix multiplies,
/// `super::mmla`).
pub(crate) struct UsdotQ;

/// `sum + a . w` per i32 lane by widening multiplies.
///
/// # Safety
/// NEON.
#[inline(always)]
unsafe fn widening_dot(sum: int32x4_t, a: int32x4_t, w: int32x4_t) -> int32x4_t {
    // SAFETY: NEON (the caller's promise).
    unsafe {
        let (a, w) = (vreinterpretq_s8_s32(a), vreinterpretq_s8_s32(w));
        // Channels 0 and 1 (bytes 0..8), then 2 and 3: i16 products, each pair's sum widened
        // to i32 before it is added (a pair of -128 x -128 would not fit i16).
        let low = vpaddlq_s16(vmull_s8(vget_low_s8(a), vget_low_s8(w)));
        let high = vpaddlq_s16(vmull_high_s8(a, w));
        vaddq_s32(sum, vpaddq_s32(low, high))
    }
}

/// The methods all three share; `$dot` is the quad product.
macro_rules! common {
    ($dot:expr) => {
        type Integers = int32x4_t;
        type Floats = float32x4_t;
        type Exact = (float64x2_t, float64x2_t);
        const WIDTH: usize = 4;
        #[inline(always)]
        unsafe fn zero_integers() -> int32x4_t {
            // SAFETY: NEON (trait contract).
            unsafe { vdupq_n_s32(0) }
        }
        #[inline(always)]
        unsafe fn zero_floats() -> float32x4_t {
            // SAFETY: NEON (trait contract).
            unsafe { vdupq_n_f32(0.0) }
        }
        #[inline(always)]
        unsafe fn zero_exact() -> (float64x2_t, float64x2_t) {
            // SAFETY: NEON (trait contract).
            unsafe { (vdupq_n_f64(0.0), vdupq_n_f64(0.0)) }
        }
        #[inline(always)]
        unsafe fn load_weights(from: *const i8) -> int32x4_t {
            // SAFETY: NEON, and 16 bytes readable (trait contract).
            unsafe { vreinterpretq_s32_s8(vld1q_s8(from)) }
        }
        #[inline(always)]
        unsafe fn broadcast_quad(from: *const i8) -> int32x4_t {
            // SAFETY: NEON, and 4 bytes readable (trait contract).
            unsafe { broadcast_word(from.cast::<i32>().read_unaligned()) }
        }
        #[inline(always)]
        unsafe fn dot_quads(
            sum: int32x4_t,
            activations: int32x4_t,
            weights: int32x4_t,
        ) -> int32x4_t {
            // SAFETY: the caller runs on the lanes' CPU (trait contract).
            unsafe { $dot(sum, activations, weights) }
        }
        #[inline(always)]
        unsafe fn widen_quads(from: *const i8) -> int32x4_t {
            // SAFETY: NEON, and 8 bytes readable (trait contract).
            unsafe { vreinterpretq_s32_s16(vmovl_s8(vld1_s8(from))) }
        }
        #[inline(always)]
        unsafe fn broadcast_codes(from: *const i16) -> int32x4_t {
            // SAFETY: NEON, and 8 bytes readable (trait contract).
            unsafe {
                let quad = vreinterpretq_s16_s64(vdupq_n_s64(from.cast::<i64>().read_unaligned()));
                vreinterpretq_s32_s16(quad)
            }
        }
        #[inline(always)]
        unsafe fn dot_code_pairs(
            sum: int32x4_t,
            codes: int32x4_t,
            weights: int32x4_t,
        ) -> int32x4_t {
            // SAFETY: NEON (trait contract). Products i16 x i16 into i32 (`smull`, `smull2`),
            // adjacent pairs added (`addp`): lane k is c[2k] w[2k] + c[2k + 1] w[2k + 1], as
            // `vpmaddwd` gives; the sums fit (`MAX_DIGIT_CHANNELS`).
            unsafe {
                let (c, w) = (vreinterpretq_s16_s32(codes), vreinterpretq_s16_s32(weights));
                let low = vmull_s16(vget_low_s16(c), vget_low_s16(w));
                let high = vmull_s16(vget_high_s16(c), vget_high_s16(w));
                vaddq_s32(sum, vpaddq_s32(low, high))
            }
        }
        #[inline(always)]
        unsafe fn load_codes(from: *const i16) -> int32x4_t {
            // SAFETY: NEON, and 16 bytes readable (trait contract).
            unsafe { vreinterpretq_s32_s16(vld1q_s16(from)) }
        }
        #[inline(always)]
        unsafe fn add_integers(a: int32x4_t, b: int32x4_t) -> int32x4_t {
            // SAFETY: NEON (trait contract).
            unsafe { vaddq_s32(a, b) }
        }
        #[inline(always)]
        unsafe fn lane_sum(sums: int32x4_t) -> i64 {
            // SAFETY: NEON (trait contract). `saddlv` adds the lanes in i64.
            unsafe { vaddlvq_s32(sums) }
        }
        #[inline(always)]
        unsafe fn add_lane_pairs(first: int32x4_t, second: int32x4_t) -> int32x4_t {
            // SAFETY: NEON (trait contract).
            unsafe { vpaddq_s32(first, second) }
        }
        #[inline(always)]
        unsafe fn add_exact(
            total: (float64x2_t, float64x2_t),
            sum: int32x4_t,
        ) -> (float64x2_t, float64x2_t) {
            // SAFETY: NEON (trait contract).
            unsafe {
                let (low, high) = widen(sum);
                (vaddq_f64(total.0, low), vaddq_f64(total.1, high))
            }
        }
        #[inline(always)]
        unsafe fn exact_digits(high: int32x4_t, low: int32x4_t) -> (float64x2_t, float64x2_t) {
            // SAFETY: NEON (trait contract).
            unsafe {
                let base = vdupq_n_f64(f64::from(ops::DIGIT_BASE));
                let (high, low) = (widen(high), widen(low));
                (
                    vaddq_f64(vmulq_f64(high.0, base), low.0),
                    vaddq_f64(vmulq_f64(high.1, base), low.1),
                )
            }
        }
        #[inline(always)]
        unsafe fn round_scaled(total: (float64x2_t, float64x2_t), scale: f32) -> float32x4_t {
            // SAFETY: NEON (trait contract). `fcvtn` rounds as FPCR says: to nearest (Rust
            // code never changes it).
            unsafe {
                let rounded = vcvt_high_f32_f64(vcvt_f32_f64(total.0), total.1);
                vmulq_f32(rounded, vdupq_n_f32(scale))
            }
        }
        #[inline(always)]
        unsafe fn load(from: *const f32) -> float32x4_t {
            // SAFETY: NEON, and 4 floats readable (trait contract).
            unsafe { vld1q_f32(from) }
        }
        #[inline(always)]
        unsafe fn store(to: *mut f32, value: float32x4_t) {
            // SAFETY: NEON, and 4 floats writable (trait contract).
            unsafe { vst1q_f32(to, value) }
        }
        #[inline(always)]
        unsafe fn mul(a: float32x4_t, b: float32x4_t) -> float32x4_t {
            // SAFETY: NEON (trait contract).
            unsafe { vmulq_f32(a, b) }
        }
        #[inline(always)]
        unsafe fn add(a: float32x4_t, b: float32x4_t) -> float32x4_t {
            // SAFETY: NEON (trait contract).
            unsafe { core::arch::aarch64::vaddq_f32(a, b) }
        }
    };
}

/// `word` in every i32 lane, by `dup` from a general register. Left to itself the compiler
/// loads a broadcast quad with `ld1r`, which on Neoverse N1 (the Cortex-A76's core) and V2
/// takes one of the vector pipes the dot products need: the tiles' loops ran at 80% and
/// 75% of their peak by llvm-mca, against 100% with the load in a general register.
///
/// # Safety
/// NEON.
#[inline(always)]
unsafe fn broadcast_word(word: i32) -> int32x4_t {
    let lanes: int32x4_t;
    // SAFETY: `dup` reads and writes registers only; NEON (the caller's promise).
    unsafe {
        core::arch::asm!(
            "dup {lanes:v}.4s, {word:w}",
            lanes = out(vreg) lanes,
            word = in(reg) word,
            options(pure, nomem, nostack, preserves_flags),
        );
    }
    lanes
}

/// The four i32 lanes as f64, low two then high two (exact).
///
/// # Safety
/// NEON.
#[inline(always)]
unsafe fn widen(sum: int32x4_t) -> (float64x2_t, float64x2_t) {
    // SAFETY: NEON (the caller's promise).
    unsafe {
        (
            vcvtq_f64_s64(vmovl_s32(vget_low_s32(sum))),
            vcvtq_f64_s64(vmovl_high_s32(sum)),
        )
    }
}

/// `sum + a . w` per lane with `sdot` (i8 x i8).
///
/// # Safety
/// The dot-product extension.
#[inline(always)]
pub(super) unsafe fn sdot(mut sum: int32x4_t, a: int32x4_t, w: int32x4_t) -> int32x4_t {
    // SAFETY: `sdot` reads and writes registers only; the caller runs on a CPU with it.
    unsafe {
        core::arch::asm!(
            "sdot {sum:v}.4s, {a:v}.16b, {w:v}.16b",
            sum = inout(vreg) sum,
            a = in(vreg) a,
            w = in(vreg) w,
            options(pure, nomem, nostack, preserves_flags),
        );
    }
    sum
}

/// `sum + a . w` per lane with `usdot` (`a` u8, `w` i8).
///
/// # Safety
/// I8MM.
#[inline(always)]
unsafe fn usdot(mut sum: int32x4_t, a: int32x4_t, w: int32x4_t) -> int32x4_t {
    // SAFETY: `usdot` reads and writes registers only; the caller runs on a CPU with I8MM.
    unsafe {
        core::arch::asm!(
            "usdot {sum:v}.4s, {a:v}.16b, {w:v}.16b",
            sum = inout(vreg) sum,
            a = in(vreg) a,
            w = in(vreg) w,
            options(pure, nomem, nostack, preserves_flags),
        );
    }
    sum
}

// SAFETY: each method is the NEON sequence its comment names; the trait's contract passes
// the CPU (NEON) and pointer requirements on to the caller.
unsafe impl Int8Lanes for WideningQ {
    common!(widening_dot);
}

// SAFETY: as for `WideningQ`, with the dot-product extension for `dot_quads`.
unsafe impl Int8Lanes for DotQ {
    common!(sdot);
}

// SAFETY: as for `WideningQ`, with I8MM for `dot_quads`.
unsafe impl Int8Lanes for UsdotQ {
    common!(usdot);
}

// SAFETY: as for its `Int8Lanes`; `sdot` multiplies signed bytes by signed bytes, so the
// weights need no offset.
unsafe impl SignedByteLanes for DotQ {
    const WEIGHT_OFFSET: i32 = 0;
    #[inline(always)]
    unsafe fn offset_bytes(bytes: int32x4_t) -> int32x4_t {
        bytes
    }
    #[inline(always)]
    unsafe fn splat_integers(value: i32) -> int32x4_t {
        // SAFETY: NEON (trait contract).
        unsafe { vdupq_n_s32(value) }
    }
    #[inline(always)]
    unsafe fn integers_scaled(sums: int32x4_t, scale: f32) -> float32x4_t {
        // SAFETY: NEON (trait contract). `scvtf` rounds as FPCR says: to nearest.
        unsafe { vmulq_f32(vcvtq_f32_s32(sums), vdupq_n_f32(scale)) }
    }
}

// SAFETY: as for its `Int8Lanes`.
unsafe impl CenteredByteLanes for DotQ {
    #[inline(always)]
    unsafe fn broadcast_centred_quad(from: *const i8) -> int32x4_t {
        // Centred in the general register, so the vector pipes do only the dot products.
        // SAFETY: NEON, and 4 bytes readable (trait contract).
        unsafe {
            let word = i32::from_ne_bytes([0x80; 4]) ^ from.cast::<i32>().read_unaligned();
            broadcast_word(word)
        }
    }
    #[inline(always)]
    unsafe fn load_integers(from: *const i32) -> int32x4_t {
        // SAFETY: NEON, and 4 integers readable (trait contract).
        unsafe { vld1q_s32(from) }
    }
}
