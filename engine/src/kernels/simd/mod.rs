//! The SIMD kernels' bodies, written once over small vector traits ([`lanes::Lanes`] for
//! f32, [`int8::Int8Lanes`] for the integer dot products) and instantiated by each
//! architecture's backends (`x86_64/`, `aarch64/`) inside thin `#[target_feature]`
//! wrappers. The same body on any vector width gives the same bits: every output is one
//! FMA chain in the same order, whatever the width (`f32_tile`, `sequence`), and the
//! integer sums are exact (`int8`); so AVX2, AVX-512 and NEON agree.

pub(crate) mod f32_tile;
pub(crate) mod int8;
pub(crate) mod lanes;
pub(crate) mod sequence;

use crate::kernels::ConvShape;

/// Asks the caches for every 64-byte line of the `bytes` bytes from `start`, into L1. A
/// hint only: it reads nothing architecturally and never faults, so `start` may point
/// anywhere (the callers ask for lines past the end of their weights near the end of a
/// layer), hence the wrapping address arithmetic.
#[inline(always)]
pub(crate) fn prefetch_lines<T>(start: *const T, bytes: usize) {
    for line in (0..bytes).step_by(64) {
        prefetch_line::<false>(start.cast::<i8>().wrapping_add(line));
    }
}

/// [`prefetch_lines`] into L2 only: for weight streams asked for far ahead of the loads that
/// read them. Asked into L1 16 KB ahead, the lines wait in the core's few L1 miss buffers
/// and stall the loads the loop needs now; into L2 the f32 U-Net's stream from DRAM ran
/// 1.5-1.7x faster (`benches/README.md`, Zen 4).
#[inline(always)]
pub(crate) fn prefetch_lines_into_l2<T>(start: *const T, bytes: usize) {
    for line in (0..bytes).step_by(64) {
        prefetch_line::<true>(start.cast::<i8>().wrapping_add(line));
    }
}

/// One line asked for, into L1 or (`L2`) into L2 only: `prefetcht0` / `prefetcht1`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn prefetch_line<const L2: bool>(at: *const i8) {
    use core::arch::x86_64::{_MM_HINT_T0, _MM_HINT_T1, _mm_prefetch};
    // SAFETY: a prefetch has no architectural effect and never faults; SSE is part of
    // x86-64.
    unsafe {
        if L2 {
            _mm_prefetch::<_MM_HINT_T1>(at)
        } else {
            _mm_prefetch::<_MM_HINT_T0>(at)
        }
    }
}

/// One line asked for, into L1 or (`L2`) into L2 only: `prfm pldl1keep` / `pldl2keep`.
#[cfg(target_arch = "aarch64")]
#[inline(always)]
fn prefetch_line<const L2: bool>(at: *const i8) {
    // SAFETY: `prfm` is a hint: it has no architectural effect and never faults, whatever
    // the address; it is part of the base A64 instruction set.
    unsafe {
        if L2 {
            core::arch::asm!("prfm pldl2keep, [{0}]", in(reg) at, options(nostack, readonly, preserves_flags))
        } else {
            core::arch::asm!("prfm pldl1keep, [{0}]", in(reg) at, options(nostack, readonly, preserves_flags))
        }
    }
}

/// Elsewhere the hardware prefetchers alone.
#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
#[inline(always)]
fn prefetch_line<const L2: bool>(_at: *const i8) {}

/// Where each pixel of a tile reads kernel tap `(kernel_y, kernel_x)`: `pixels` are the
/// output positions `(out_y, out_x)` of its `N` slots, the first `count` used. The input
/// offset of the pixel's first channel, or `None` when the tap lies in the padding or the
/// slot is unused. The f32 kernels skip those taps exactly as the scalar reference does, so
/// every output pixel is one FMA chain over its inside taps, in tap and input-channel order,
/// whichever tile (or single-pixel call) computes it.
#[inline(always)]
pub(crate) fn tap_offsets<const N: usize>(
    shape: &ConvShape,
    pixels: &[(usize, usize); N],
    count: usize,
    (kernel_y, kernel_x): (usize, usize),
) -> [Option<usize>; N] {
    // A plain loop: `array::from_fn` was not inlined here and cost a tenth of the stem.
    let mut offsets = [None; N];
    for (offset, &(out_y, out_x)) in offsets.iter_mut().zip(pixels).take(count) {
        let in_y = (out_y * shape.stride + kernel_y).checked_sub(shape.padding_height);
        let in_x = (out_x * shape.stride + kernel_x).checked_sub(shape.padding_width);
        *offset = in_y
            .filter(|&y| y < shape.in_height)
            .zip(in_x.filter(|&x| x < shape.in_width))
            .map(|(y, x)| (y * shape.in_width + x) * shape.in_channels);
    }
    offsets
}
