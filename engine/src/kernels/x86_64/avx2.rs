//! AVX2 + FMA kernels. The convolution keeps a 4-pixel x 16-channel tile of outputs in eight
//! YMM accumulators: per input channel and tap, two weight loads and four broadcasts feed
//! eight FMAs (the scalar reference reloads and stores its output for every product).
//! Border pixels use the scalar reference; the U-Net's 1-D convolutions, upsampling and
//! matrix-vector products use the weight-streaming [`sequence`] kernels.

use core::arch::x86_64::{
    __m256, _mm256_add_ps, _mm256_fmadd_ps, _mm256_loadu_ps, _mm256_set1_ps, _mm256_setzero_ps,
    _mm256_storeu_ps,
};

use super::sequence::{self, Sequence};
use super::{Run, interior, walk_pixels};
use crate::kernels::scalar::{Scalar, conv_pixels};
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

/// `N` output pixels x 16 channels from `channel`, all taps inside the input. Each pixel's
/// sum is one chain of FMAs in tap and input-channel order, whatever `N` is, so a pixel
/// computed alone equals the same pixel computed in a tile.
///
/// # Safety
/// The CPU supports AVX2 and FMA; the slices have the lengths `shape` implies;
/// `interior(shape, out_y, out_x, N)` holds; `channel + 16 <= out_channels`.
#[target_feature(enable = "avx2,fma")]
unsafe fn interior_tile<const N: usize>(
    shape: &ConvShape,
    input: &[f32],
    weight: &[f32],
    out_y: usize,
    out_x: usize,
    channel: usize,
) -> [[__m256; 2]; N] {
    let in_channels = shape.in_channels;
    let out_channels = shape.out_channels;
    let stride = shape.stride;
    let mut sums = [[_mm256_setzero_ps(); 2]; N];
    for kernel_y in 0..shape.kernel_height {
        let in_y = out_y * stride + kernel_y - shape.padding_height;
        for kernel_x in 0..shape.kernel_width {
            let in_x = out_x * stride + kernel_x - shape.padding_width;
            let first = (in_y * shape.in_width + in_x) * in_channels;
            let pixel_step = stride * in_channels;
            let taps =
                (kernel_y * shape.kernel_width + kernel_x) * in_channels * out_channels + channel;
            for input_channel in 0..in_channels {
                // SAFETY: `interior` puts all four pixels of this tap inside the input, and
                // the weight row of 16 channels from `channel` is inside the tap's block.
                unsafe {
                    let row = weight.as_ptr().add(taps + input_channel * out_channels);
                    let low = _mm256_loadu_ps(row);
                    let high = _mm256_loadu_ps(row.add(8));
                    let values = input.as_ptr().add(first + input_channel);
                    for (pixel, sum) in sums.iter_mut().enumerate() {
                        let value = _mm256_set1_ps(*values.add(pixel * pixel_step));
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
/// The CPU supports AVX2; `channel + 16 <= out_channels`; the `N` pixels from
/// `first_pixel` are inside `output`.
#[target_feature(enable = "avx2,fma")]
unsafe fn store_tile<const N: usize>(
    sums: &[[__m256; 2]; N],
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
        walk_pixels(shape, PIXELS, |out_y, out_x, run| {
            let Run::Interior(pixels) = run else {
                let columns = out_x..out_x + 1;
                return conv_pixels(
                    shape,
                    (input, weight, bias),
                    output,
                    accumulate,
                    out_y,
                    columns,
                );
            };
            let first_pixel = out_y * out_width + out_x;
            for channel in (0..shape.out_channels).step_by(CHANNELS) {
                // SAFETY: `self` exists only when AVX2 and FMA were detected; the asserts
                // above fix the slice lengths; `walk_pixels` checked `interior` for these
                // pixels, and `channel + 16 <= out_channels` as out_channels is a multiple
                // of 16.
                unsafe {
                    if pixels == PIXELS {
                        let sums =
                            interior_tile::<PIXELS>(shape, input, weight, out_y, out_x, channel);
                        store_tile(
                            &sums,
                            bias,
                            output,
                            shape.out_channels,
                            first_pixel,
                            channel,
                            accumulate,
                        );
                    } else {
                        let sums = interior_tile::<1>(shape, input, weight, out_y, out_x, channel);
                        store_tile(
                            &sums,
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
        });
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
        if as_sequence(shape).is_some()
            || !shape.out_channels.is_multiple_of(CHANNELS)
            || !interior(shape, out_y, out_x, 1)
        {
            return Scalar.conv_pixel(shape, input, weight, bias, (out_y, out_x), output);
        }
        for channel in (0..shape.out_channels).step_by(CHANNELS) {
            // SAFETY: as in `conv`; `output` holds the pixel's channels, so the one pixel
            // from index 0 is inside it.
            unsafe {
                let sums = interior_tile::<1>(shape, input, weight, out_y, out_x, channel);
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
