//! AVX2 + FMA kernels. The convolution keeps a 4-pixel x 16-channel tile of outputs in eight
//! YMM accumulators: per input channel and tap, two weight loads and four broadcasts feed
//! eight FMAs (the scalar reference reloads and stores its output for every product).
//! Border pixels and the few that do not fill a tile are single-pixel FMA chains. The
//! U-Net's 1-D convolutions, upsampling and matrix-vector products use the weight-streaming
//! [`sequence`] kernels.

use core::arch::x86_64::{
    __m256, _mm256_add_ps, _mm256_fmadd_ps, _mm256_loadu_ps, _mm256_set1_ps, _mm256_setzero_ps,
    _mm256_storeu_ps,
};

use super::sequence::{self, Sequence};
use super::tap_offsets;
use crate::kernels::scalar::Scalar;
use crate::kernels::{Accumulate, ConvShape, Kernels, QuantizedRows};

/// Output pixels per tile (along a row) and output channels per tile.
const PIXELS: usize = 4;
const CHANNELS: usize = 16;

/// AVX2 + FMA kernels. Reachable only through [`Avx2::detect`], which checks the CPU.
#[derive(Debug)]
pub struct Avx2 {
    _checked: (),
}

pub(super) static INSTANCE: Avx2 = Avx2 { _checked: () };

impl Avx2 {
    /// `None` unless the CPU and OS support AVX2 and FMA.
    pub fn detect() -> Option<&'static Avx2> {
        super::has_avx2_fma().then_some(&INSTANCE)
    }
}

/// The 1-D convolution `shape` describes (one input row, one kernel row, no vertical
/// padding), for the sequence kernels.
fn as_sequence(shape: &ConvShape) -> Option<Sequence> {
    (shape.in_height == 1 && shape.kernel_height == 1 && shape.padding_height == 0).then(|| {
        Sequence::convolution(
            shape.in_width,
            (shape.in_channels, shape.out_channels),
            shape.kernel_width,
            shape.stride,
            shape.padding_width,
        )
    })
}

/// Output pixels `out_x .. out_x + count` of row `out_y` (`count <= N`) x 16 channels
/// from `channel`. Per input channel and tap, two weight loads feed two FMAs per pixel
/// whose tap is inside the input ([`tap_offsets`]); where all `N` pixels are inside (the
/// common case) the loop has no per-pixel test.
///
/// # Safety
/// The CPU supports AVX2 and FMA; the slices have the lengths `shape` implies; the pixels
/// are in the output; `channel + 16 <= out_channels`.
#[target_feature(enable = "avx2,fma")]
unsafe fn tile<const N: usize>(
    shape: &ConvShape,
    (input, weight): (&[f32], &[f32]),
    (out_y, out_x): (usize, usize),
    count: usize,
    channel: usize,
) -> [[__m256; 2]; N] {
    let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
    let mut sums = [[_mm256_setzero_ps(); 2]; N];
    for kernel_y in 0..shape.kernel_height {
        for kernel_x in 0..shape.kernel_width {
            let offsets = tap_offsets::<N>(shape, (out_y, out_x), count, (kernel_y, kernel_x));
            let taps =
                (kernel_y * shape.kernel_width + kernel_x) * in_channels * out_channels + channel;
            // The common case, every pixel inside: no per-pixel test in the loop.
            let inside = offsets.iter().all(Option::is_some);
            let offsets = offsets.map(|offset| offset.unwrap_or(usize::MAX));
            for input_channel in 0..in_channels {
                // SAFETY: each offset other than usize::MAX is a pixel inside the input
                // (`tap_offsets`), so `offset + input_channel` is inside it; the weight row
                // of 16 channels from `channel` is inside the tap's block.
                unsafe {
                    let row = weight.as_ptr().add(taps + input_channel * out_channels);
                    let low = _mm256_loadu_ps(row);
                    let high = _mm256_loadu_ps(row.add(8));
                    let values = input.as_ptr().add(input_channel);
                    for (&offset, sum) in offsets.iter().zip(sums.iter_mut()) {
                        if !inside && offset == usize::MAX {
                            continue;
                        }
                        let value = _mm256_set1_ps(*values.add(offset));
                        sum[0] = _mm256_fmadd_ps(value, low, sum[0]);
                        sum[1] = _mm256_fmadd_ps(value, high, sum[1]);
                    }
                }
            }
        }
    }
    sums
}

/// Adds the bias (and the existing output with [`Accumulate::Add`]) and stores a tile.
///
/// # Safety
/// The CPU supports AVX2; `channel + 16 <= out_channels`; the pixels from `first_pixel`
/// are inside `output`.
#[target_feature(enable = "avx2,fma")]
unsafe fn store_tile(
    sums: &[[__m256; 2]],
    bias: &[f32],
    output: &mut [f32],
    out_channels: usize,
    first_pixel: usize,
    channel: usize,
    accumulate: Accumulate,
) {
    let bias = &bias[channel..channel + CHANNELS];
    for (pixel, sum) in sums.iter().enumerate() {
        let out = &mut output[(first_pixel + pixel) * out_channels + channel..][..CHANNELS];
        for (half, &value) in sum.iter().enumerate() {
            let at = 8 * half;
            // SAFETY: `out` and `bias` hold 16 floats; each access covers 8 from `at`.
            unsafe {
                let mut value = _mm256_add_ps(value, _mm256_loadu_ps(bias.as_ptr().add(at)));
                if accumulate == Accumulate::Add {
                    value = _mm256_add_ps(value, _mm256_loadu_ps(out.as_ptr().add(at)));
                }
                _mm256_storeu_ps(out.as_mut_ptr().add(at), value);
            }
        }
    }
}

impl Kernels for Avx2 {
    fn name(&self) -> &'static str {
        "avx2"
    }

    fn conv(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        assert_eq!(input.len(), shape.input_len());
        assert_eq!(weight.len(), shape.weight_len());
        assert_eq!(bias.len(), shape.out_channels);
        assert_eq!(output.len(), shape.output_len());
        if let Some(sequence) = as_sequence(shape) {
            // SAFETY: `self` exists only when AVX2 and FMA were detected.
            return unsafe {
                sequence::convolve_f32(&sequence, input, weight, bias, output, accumulate)
            };
        }
        // Narrow layers (the tiny model's trunk) are not worth a tail path.
        if !shape.out_channels.is_multiple_of(CHANNELS) {
            return Scalar.conv(shape, input, weight, bias, output, accumulate);
        }
        let out_width = shape.out_width();
        for out_y in 0..shape.out_height() {
            for out_x in (0..out_width).step_by(PIXELS) {
                let count = (out_width - out_x).min(PIXELS);
                let first_pixel = out_y * out_width + out_x;
                for channel in (0..shape.out_channels).step_by(CHANNELS) {
                    // SAFETY: `self` exists only when AVX2 and FMA were detected; the asserts
                    // above fix the slice lengths; the pixels are in the row, and
                    // `channel + 16 <= out_channels` as out_channels is a multiple of 16.
                    unsafe {
                        let sums =
                            tile::<PIXELS>(shape, (input, weight), (out_y, out_x), count, channel);
                        store_tile(
                            &sums[..count],
                            bias,
                            output,
                            shape.out_channels,
                            first_pixel,
                            channel,
                            accumulate,
                        );
                    }
                }
            }
        }
    }

    fn conv_pixel(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        (out_y, out_x): (usize, usize),
        output: &mut [f32],
    ) {
        assert_eq!(input.len(), shape.input_len());
        assert_eq!(weight.len(), shape.weight_len());
        assert_eq!(bias.len(), shape.out_channels);
        assert_eq!(output.len(), shape.out_channels);
        assert!(out_y < shape.out_height() && out_x < shape.out_width());
        // The paths `conv` takes for this pixel.
        if as_sequence(shape).is_some() || !shape.out_channels.is_multiple_of(CHANNELS) {
            return Scalar.conv_pixel(shape, input, weight, bias, (out_y, out_x), output);
        }
        for channel in (0..shape.out_channels).step_by(CHANNELS) {
            // SAFETY: as in `conv`; `output` holds the pixel's channels, so the one pixel
            // from index 0 is inside it.
            unsafe {
                let sums = tile::<1>(shape, (input, weight), (out_y, out_x), 1, channel);
                store_tile(
                    &sums,
                    bias,
                    output,
                    shape.out_channels,
                    0,
                    channel,
                    Accumulate::Overwrite,
                );
            }
        }
    }

    fn upsample_conv(
        &self,
        length: usize,
        in_channels: usize,
        out_channels: usize,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        output: &mut [f32],
    ) {
        assert_eq!(input.len(), length * in_channels);
        assert_eq!(weight.len(), 4 * in_channels * out_channels);
        assert_eq!(output.len(), 2 * length * out_channels);
        for parity in 0..2 {
            let half = Sequence::upsample_half(length, in_channels, out_channels, parity);
            // SAFETY: `self` exists only when AVX2 and FMA were detected.
            unsafe {
                sequence::convolve_f32(&half, input, weight, bias, output, Accumulate::Overwrite)
            };
        }
    }

    fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
        // SAFETY: `self` exists only when AVX2 and FMA were detected.
        unsafe { sequence::matvec(weight, None, input, base, output) }
    }

    fn conv_int8(
        &self,
        shape: &ConvShape,
        input: &QuantizedRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        crate::kernels::scalar::assert_int8_lengths(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
        );
        if !super::int8::tiles_apply(shape, input) {
            return Scalar.conv_int8(
                shape,
                input,
                weight,
                weight_scales,
                bias,
                output,
                accumulate,
            );
        }
        // SAFETY: `self` exists only when AVX2 and FMA were detected; the lengths were
        // asserted and `tiles_apply` checked just above.
        unsafe {
            super::int8::conv_int8_avx2(
                shape,
                input,
                (weight, weight_scales, bias),
                output,
                accumulate,
            )
        }
    }

    fn conv_weight_int8(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        assert_eq!(input.len(), shape.input_len());
        assert_eq!(weight.len(), shape.weight_len());
        assert_eq!(output.len(), shape.output_len());
        match as_sequence(shape) {
            // SAFETY: `self` exists only when AVX2 and FMA were detected.
            Some(sequence) => unsafe {
                sequence::convolve(
                    &sequence,
                    input,
                    weight,
                    Some(weight_scales),
                    bias,
                    output,
                    accumulate,
                )
            },
            None => Scalar.conv_weight_int8(
                shape,
                input,
                weight,
                weight_scales,
                bias,
                output,
                accumulate,
            ),
        }
    }

    fn matvec_weight_int8(
        &self,
        weight: &[i8],
        row_scales: &[f32],
        input: &[f32],
        base: &[f32],
        output: &mut [f32],
    ) {
        // SAFETY: `self` exists only when AVX2 and FMA were detected.
        unsafe { sequence::matvec(weight, Some(row_scales), input, base, output) }
    }
}
