//! The aarch64 f32 vector: two NEON registers as one vector of eight lanes, so the shared
//! bodies split channels and reduce sums exactly as on AVX2's YMM (same bits).

use core::arch::aarch64::{
    float32x4_t, vadd_f32, vaddq_f32, vdupq_n_f32, vfmaq_f32, vget_high_f32, vget_lane_f32,
    vget_low_f32, vld1q_f32, vst1q_f32,
};

use crate::kernels::simd::lanes::Lanes;

/// Eight f32 lanes in two NEON registers.
pub(crate) struct Neon8;

// SAFETY: each method is the NEON sequence its comment names; NEON is part of every target
// this module is compiled for (its backends check `target_feature = "neon"`); the trait's
// contract passes the pointer requirements on to the caller.
unsafe impl Lanes for Neon8 {
    type Vector = (float32x4_t, float32x4_t);
    const WIDTH: usize = 8;
    #[inline(always)]
    unsafe fn zero() -> Self::Vector {
        // SAFETY: NEON (trait contract).
        unsafe { (vdupq_n_f32(0.0), vdupq_n_f32(0.0)) }
    }
    #[inline(always)]
    unsafe fn load(from: *const f32) -> Self::Vector {
        // SAFETY: NEON, and `from` covers 8 floats (trait contract).
        unsafe { (vld1q_f32(from), vld1q_f32(from.add(4))) }
    }
    #[inline(always)]
    unsafe fn store(to: *mut f32, value: Self::Vector) {
        // SAFETY: NEON, and `to` covers 8 floats (trait contract).
        unsafe {
            vst1q_f32(to, value.0);
            vst1q_f32(to.add(4), value.1);
        }
    }
    #[inline(always)]
    unsafe fn splat(value: f32) -> Self::Vector {
        // SAFETY: NEON (trait contract).
        unsafe { (vdupq_n_f32(value), vdupq_n_f32(value)) }
    }
    #[inline(always)]
    unsafe fn fma(a: Self::Vector, b: Self::Vector, c: Self::Vector) -> Self::Vector {
        // SAFETY: NEON (trait contract). `fmla` rounds once, as `vfmadd` does.
        unsafe { (vfmaq_f32(c.0, a.0, b.0), vfmaq_f32(c.1, a.1, b.1)) }
    }
    #[inline(always)]
    unsafe fn add(a: Self::Vector, b: Self::Vector) -> Self::Vector {
        // SAFETY: NEON (trait contract).
        unsafe { (vaddq_f32(a.0, b.0), vaddq_f32(a.1, b.1)) }
    }
    #[inline(always)]
    unsafe fn horizontal_sum(value: Self::Vector) -> f32 {
        // YMM's order: the two halves added lane by lane (i + 4), then lanes (0 + 2, 1 + 3),
        // then those two.
        // SAFETY: NEON (trait contract).
        unsafe {
            let quad = vaddq_f32(value.0, value.1);
            let pair = vadd_f32(vget_low_f32(quad), vget_high_f32(quad));
            vget_lane_f32::<0>(pair) + vget_lane_f32::<1>(pair)
        }
    }
}
