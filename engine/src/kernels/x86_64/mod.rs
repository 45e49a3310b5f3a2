//! x86-64 kernels, chosen at run time from what the CPU reports (CPUID works without std).

/// The [`Kernels`](crate::kernels::Kernels) methods both x86-64 backends implement alike,
/// each on its own compiled bodies: the U-Net's f32 kernels of `sequence::$backend`, the
/// int8 convolutions of `int8::$backend`, the element-wise operations of `elementwise::$backend`.
/// Expanded only inside the `impl Kernels` of a backend type that exists once CPUID has
/// reported the features those bodies are compiled for (its `detect`), which is what every
/// `unsafe` call below relies on.
macro_rules! shared_kernels {
    ($backend:ident) => {
        fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { sequence::$backend::matvec(weight, input, base, output) }
        }

        fn conv_int8(
            &self,
            shape: &ConvShape,
            input: &DigitRows<'_>,
            weight: &[i8],
            weight_scales: &[f32],
            bias: &[f32],
            output: &mut [f32],
            accumulate: Accumulate,
        ) {
            let parameters = (weight, weight_scales, bias);
            let kernel = int8::$backend::conv;
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { int8::checked_conv(kernel, shape, input, parameters, output, accumulate) }
        }

        fn conv_int8_pixel(
            &self,
            shape: &ConvShape,
            input: &DigitRows<'_>,
            weight: &[i8],
            weight_scales: &[f32],
            bias: &[f32],
            pixel: (usize, usize),
            output: &mut [f32],
        ) {
            let parameters = (weight, weight_scales, bias);
            let kernel = int8::$backend::conv_pixel;
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { int8::checked_conv_pixel(kernel, shape, input, parameters, pixel, output) }
        }

        fn conv_int8_codes(
            &self,
            shape: &ConvShape,
            input: &CodeRows<'_>,
            weight: &[i8],
            weight_scales: &[f32],
            bias: &[f32],
            output: &mut [f32],
            accumulate: Accumulate,
        ) {
            let parameters = (weight, weight_scales, bias);
            let kernel = int8::$backend::conv_codes;
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                int8::checked_conv_codes(kernel, shape, input, parameters, output, accumulate)
            }
        }

        fn matvec_int8_codes(
            &self,
            weight: &[i8],
            row_scales: &[f32],
            input: &CodeRows<'_>,
            base: &[f32],
            output: &mut [f32],
        ) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { int8::$backend::matvec_codes(weight, row_scales, input, base, output) }
        }

        fn quantize_digits(&self, input: &[f32], digits: (&mut [i8], &mut [i8])) -> (f32, bool) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { elementwise::$backend::quantize_digits(input, digits) }
        }

        fn quantize_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { elementwise::$backend::quantize_codes(input, row_len, codes) }
        }

        fn quantize_narrow_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { elementwise::$backend::quantize_narrow_codes(input, row_len, codes) }
        }

        fn quantize_signed_bytes(
            &self,
            input: &[f32],
            row_len: usize,
            codes: &mut [i8],
            row_sums: &mut [i32],
        ) -> f32 {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { elementwise::$backend::quantize_signed_bytes(input, row_len, codes, row_sums) }
        }

        fn quantize_narrow(
            &self,
            input: &[f32],
            scratch: &mut [i8],
            form: crate::kernels::NarrowForm,
        ) -> f32 {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { elementwise::$backend::quantize_narrow(input, scratch, form) }
        }

        fn group_norm(
            &self,
            data: &mut [f32],
            channels: usize,
            groups: usize,
            affine: (&[f32], &[f32]),
            activation: Activation,
        ) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { elementwise::$backend::group_norm(data, channels, groups, affine, activation) }
        }

        fn add_activate(&self, target: &mut [f32], source: &[f32], activation: Activation) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { elementwise::$backend::add_activate(target, source, activation) }
        }

        fn add_channel_moments(
            &self,
            data: &[f32],
            channels: usize,
            moments: (&mut [f64], &mut [f64]),
        ) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { elementwise::$backend::add_channel_moments(data, channels, moments) }
        }

        fn normalize_max_pool(
            &self,
            input: &[f32],
            dims: (usize, usize, usize),
            affine: (&[f32], &[f32]),
            activation: Activation,
            output: &mut [f32],
        ) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                elementwise::$backend::normalize_max_pool(input, dims, affine, activation, output)
            }
        }

        fn max_pool_3x3_stride_2(
            &self,
            input: &[f32],
            dims: (usize, usize, usize),
            output: &mut [f32],
        ) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { elementwise::$backend::max_pool_3x3_stride_2(input, dims, output) }
        }
    };
}

pub mod amx;
pub mod avx2;
pub mod avx512;
pub mod avx512_f32;
mod elementwise;
mod f32_tile;
mod int8;
mod lanes;
pub(crate) mod sequence;

use core::arch::x86_64::{__cpuid, __cpuid_count, _MM_HINT_T0, _MM_HINT_T1, _mm_prefetch, _xgetbv};

use crate::kernels::ConvShape;

/// Asks the caches for every 64-byte line of the `bytes` bytes from `start`, into L1. A
/// hint only: it reads nothing architecturally and never faults, so `start` may point
/// anywhere (the callers ask for lines past the end of their weights near the end of a
/// layer), hence the wrapping address arithmetic.
#[inline(always)]
fn prefetch_lines<T>(start: *const T, bytes: usize) {
    prefetch_lines_with::<_MM_HINT_T0, T>(start, bytes);
}

/// [`prefetch_lines`] into L2 only (`prefetcht1`): for weight streams asked for far ahead of
/// the loads that read them. Asked into L1 16 KB ahead, the lines wait in the core's few
/// L1 miss buffers and stall the loads the loop needs now; into L2 the f32 U-Net's stream
/// from DRAM ran 1.5-1.7x faster (`benches/README.md`, Zen 4).
#[inline(always)]
fn prefetch_lines_into_l2<T>(start: *const T, bytes: usize) {
    prefetch_lines_with::<_MM_HINT_T1, T>(start, bytes);
}

/// The lines of `bytes` bytes from `start` asked for with prefetch hint `HINT`.
#[inline(always)]
fn prefetch_lines_with<const HINT: i32, T>(start: *const T, bytes: usize) {
    let start = start.cast::<i8>();
    for line in (0..bytes).step_by(64) {
        // SAFETY: a prefetch has no architectural effect and never faults; SSE is part of
        // x86-64.
        unsafe { _mm_prefetch::<HINT>(start.wrapping_add(line)) };
    }
}

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

/// AVX-512 F, BW, VL and VNNI are present and the OS saves the opmask and ZMM registers
/// (XCR0 bits 5 to 7) as well as the YMM ones (bits 1 and 2).
pub fn has_avx512_vnni() -> bool {
    // CPUID is safe on x86-64; leaf 1 exists on every such processor.
    let osxsave = __cpuid(1).ecx & (1 << 27) != 0;
    if !osxsave || __cpuid(0).eax < 7 {
        return false;
    }
    let features = __cpuid_count(7, 0);
    let foundation = features.ebx & (1 << 16) != 0;
    let byte_word = features.ebx & (1 << 30) != 0;
    let vector_length = features.ebx & (1 << 31) != 0;
    let vnni = features.ecx & (1 << 11) != 0;
    if !(foundation && byte_word && vector_length && vnni) {
        return false;
    }
    // SAFETY: OSXSAVE is set, so XGETBV may be executed.
    let state = unsafe { os_enabled_state() };
    state & 0b1110_0110 == 0b1110_0110
}

/// AMX-TILE and AMX-INT8 are present and the OS saves the tile configuration and tile data
/// (XCR0 bits 17 and 18). Whether this process may use them is the OS's to say
/// ([`amx::Amx::detect`] asks).
pub fn has_amx_int8() -> bool {
    // CPUID is safe on x86-64; leaf 1 exists on every such processor.
    let osxsave = __cpuid(1).ecx & (1 << 27) != 0;
    if !osxsave || __cpuid(0).eax < 7 {
        return false;
    }
    let features = __cpuid_count(7, 0);
    let tile = features.edx & (1 << 24) != 0;
    let int8 = features.edx & (1 << 25) != 0;
    if !(tile && int8) {
        return false;
    }
    // SAFETY: OSXSAVE is set, so XGETBV may be executed.
    let state = unsafe { os_enabled_state() };
    state & (0b11 << 17) == 0b11 << 17
}
