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
            unsafe { crate::kernels::x86_64::sequence::matvec(weight, input, base, output) }
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
            let kernel = crate::kernels::x86_64::int8::$backend::conv;
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::simd::int8::checked_conv(
                    kernel, shape, input, parameters, output, accumulate,
                )
            }
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
            let kernel = crate::kernels::x86_64::int8::$backend::conv_pixel;
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::simd::int8::checked_conv_pixel(
                    kernel, shape, input, parameters, pixel, output,
                )
            }
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
            let kernel = crate::kernels::x86_64::int8::$backend::conv_codes;
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::simd::int8::checked_conv_codes(
                    kernel, shape, input, parameters, output, accumulate,
                )
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
            unsafe {
                crate::kernels::x86_64::int8::$backend::matvec_codes(
                    weight, row_scales, input, base, output,
                )
            }
        }

        fn quantize_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::quantize_codes(input, row_len, codes)
            }
        }

        fn quantize_narrow_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::quantize_narrow_codes(
                    input, row_len, codes,
                )
            }
        }

        fn quantize_signed_bytes(
            &self,
            input: &[f32],
            row_len: usize,
            codes: &mut [i8],
            row_sums: &mut [i32],
        ) -> f32 {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::quantize_signed_bytes(
                    input, row_len, codes, row_sums,
                )
            }
        }

        fn quantize_digits(&self, input: &[f32], digits: (&mut [i8], &mut [i8])) -> (f32, bool) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { crate::kernels::x86_64::elementwise::$backend::quantize_digits(input, digits) }
        }

        fn quantize_narrow(
            &self,
            input: &[f32],
            scratch: &mut [i8],
            form: crate::kernels::NarrowForm,
        ) -> f32 {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::quantize_narrow(input, scratch, form)
            }
        }

        fn largest_magnitude(&self, input: &[f32]) -> f32 {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { crate::kernels::x86_64::elementwise::$backend::largest_magnitude(input) }
        }

        fn quantize_digits_within(
            &self,
            input: &[f32],
            largest: f32,
            digits: (&mut [i8], &mut [i8]),
        ) -> (f32, bool) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::quantize_digits_within(
                    input, largest, digits,
                )
            }
        }

        fn quantize_narrow_within(
            &self,
            input: &[f32],
            largest: f32,
            codes: (&mut [i8], &mut [i8]),
            form: crate::kernels::NarrowForm,
        ) -> f32 {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::quantize_narrow_within(
                    input, largest, codes, form,
                )
            }
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
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::group_norm(
                    data, channels, groups, affine, activation,
                )
            }
        }

        fn affine_activate(
            &self,
            data: &mut [f32],
            channels: usize,
            affine: (&[f32], &[f32]),
            activation: Activation,
        ) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::affine_activate(
                    data, channels, affine, activation,
                )
            }
        }

        fn add_activate(&self, target: &mut [f32], source: &[f32], activation: Activation) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::add_activate(
                    target, source, activation,
                )
            }
        }

        fn add_channel_moments(
            &self,
            data: &[f32],
            channels: usize,
            moments: (&mut [f64], &mut [f64]),
        ) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::add_channel_moments(
                    data, channels, moments,
                )
            }
        }

        fn normalize_max_pool(
            &self,
            input: &[f32],
            dims: (usize, usize, usize),
            affine: (&[f32], &[f32]),
            activation: Activation,
            output: &mut [f32],
            first_row: usize,
        ) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::normalize_max_pool(
                    input, dims, affine, activation, output, first_row,
                )
            }
        }

        fn max_pool_3x3_stride_2(
            &self,
            input: &[f32],
            dims: (usize, usize, usize),
            output: &mut [f32],
        ) {
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe {
                crate::kernels::x86_64::elementwise::$backend::max_pool_3x3_stride_2(
                    input, dims, output,
                )
            }
        }
    };
}

pub mod amx;
pub mod avx2;
pub mod avx512;
pub mod avx512_f32;
mod elementwise;
mod int8;
mod int8_lanes;
mod lanes;

use core::arch::x86_64::{__cpuid, __cpuid_count, _xgetbv};

/// The f32 U-Net kernels of `simd::sequence`: the convolutions on YMM and ZMM vectors.
pub(crate) mod sequence {
    use super::lanes::{Ymm, Zmm};
    crate::kernels::simd::sequence::backend!(avx2, super::Ymm, "avx2,fma");
    crate::kernels::simd::sequence::backend!(avx512, super::Zmm, "avx512f,avx512bw,avx512vl");

    /// `Kernels::matvec` of both x86-64 backends, on YMM vectors: its sums run in lane
    /// order, and eight lanes is the order every backend (NEON's too) shares, so one file
    /// gives one answer. The f32 FiLM rows stream from memory at every step; wider vectors
    /// would not read them faster.
    ///
    /// # Safety
    /// The CPU supports AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    pub(crate) unsafe fn matvec(weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
        // SAFETY: this function's contract is the body's.
        unsafe { crate::kernels::simd::sequence::matvec::<Ymm>(weight, input, base, output) }
    }
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
