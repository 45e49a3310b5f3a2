//! The portable element-wise operations of `ops` compiled for AVX2 and for AVX-512: the
//! same `#[inline(always)]` code inside a `#[target_feature]` function, so the compiler
//! vectorizes it 8 or 16 lanes wide instead of the baseline's 4 (quantizing and normalizing
//! the trunk's activations was a quarter of the int8 encode). The order of operations is
//! the portable one, so the bits are too.

/// The wrappers for one backend.
macro_rules! backend {
    ($module:ident, $features:literal) => {
        pub(crate) mod $module {
            use crate::kernels::ops::{self, Activation};

            /// [`ops::quantize_split_signs`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn quantize_digits(
                input: &[f32],
                (high, low): (&mut [i8], &mut [i8]),
            ) -> (f32, bool) {
                ops::quantize_split_signs(input, high, low)
            }

            /// [`ops::quantize_narrow`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn quantize_narrow(
                input: &[f32],
                scratch: &mut [i8],
                form: crate::kernels::NarrowForm,
            ) -> f32 {
                ops::quantize_narrow(input, scratch, form)
            }

            /// [`ops::largest_magnitude`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn largest_magnitude(input: &[f32]) -> f32 {
                ops::largest_magnitude(input)
            }

            /// [`ops::quantize_split_signs_within`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn quantize_digits_within(
                input: &[f32],
                largest: f32,
                (high, low): (&mut [i8], &mut [i8]),
            ) -> (f32, bool) {
                ops::quantize_split_signs_within(input, largest, high, low)
            }

            /// [`ops::quantize_narrow_within`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn quantize_narrow_within(
                input: &[f32],
                largest: f32,
                codes: (&mut [i8], &mut [i8]),
                form: crate::kernels::NarrowForm,
            ) -> f32 {
                ops::quantize_narrow_within(input, largest, codes, form)
            }

            /// [`ops::quantize_rows_codes`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn quantize_codes(input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
                let row_stride = crate::kernels::CodeRows::row_stride(row_len);
                ops::quantize_rows_codes(input, (row_len, row_stride), codes)
            }

            /// [`ops::quantize_rows_narrow_codes`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn quantize_narrow_codes(
                input: &[f32],
                row_len: usize,
                codes: &mut [i16],
            ) -> f32 {
                let row_stride = crate::kernels::CodeRows::row_stride(row_len);
                ops::quantize_rows_narrow_codes(input, (row_len, row_stride), codes)
            }

            /// [`ops::quantize_rows_signed_bytes`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn quantize_signed_bytes(
                input: &[f32],
                row_len: usize,
                codes: &mut [i8],
                row_sums: &mut [i32],
            ) -> f32 {
                let row_stride = crate::kernels::CodeRows::row_stride(row_len);
                ops::quantize_rows_signed_bytes(input, (row_len, row_stride), codes, row_sums)
            }

            /// [`ops::group_norm`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn group_norm(
                data: &mut [f32],
                channels: usize,
                groups: usize,
                (gamma, beta): (&[f32], &[f32]),
                activation: Activation,
            ) {
                ops::group_norm(data, channels, groups, gamma, beta, activation)
            }

            /// [`ops::affine_activate`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn affine_activate(
                data: &mut [f32],
                channels: usize,
                affine: (&[f32], &[f32]),
                activation: Activation,
            ) {
                ops::affine_activate(data, channels, affine, activation)
            }

            /// [`ops::add_activate`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn add_activate(target: &mut [f32], source: &[f32], activation: Activation) {
                ops::add_activate(target, source, activation)
            }

            /// [`ops::add_channel_moments`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn add_channel_moments(
                data: &[f32],
                channels: usize,
                moments: (&mut [f64], &mut [f64]),
            ) {
                ops::add_channel_moments(data, channels, moments)
            }

            /// [`ops::normalize_max_pool`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn normalize_max_pool(
                input: &[f32],
                dims: (usize, usize, usize),
                affine: (&[f32], &[f32]),
                activation: Activation,
                output: &mut [f32],
                first_row: usize,
            ) {
                ops::normalize_max_pool(input, dims, affine, activation, output, first_row)
            }

            /// [`ops::max_pool_3x3_stride_2`] on this backend's vectors.
            #[target_feature(enable = $features)]
            pub(crate) fn max_pool_3x3_stride_2(
                input: &[f32],
                dims: (usize, usize, usize),
                output: &mut [f32],
            ) {
                ops::max_pool_3x3_stride_2(input, dims, output)
            }
        }
    };
}

backend!(avx2, "avx2,fma");
backend!(avx512, "avx512f,avx512bw,avx512vl");
