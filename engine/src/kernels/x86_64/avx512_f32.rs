//! AVX-512 f32 convolution for 2-D maps: the AVX2 tile's arithmetic at twice the width.
//! A tile is 8 pixels x 32 channels (16 ZMM accumulators): per input channel and tap, two
//! weight loads and eight broadcasts feed sixteen FMAs. As in the AVX2 kernel, every
//! interior pixel is one FMA chain in tap and input-channel order from zero, then the bias
//! is added, whether it was computed in a tile or alone; border pixels are the scalar
//! reference's. Layers this does not cover (out_channels not a multiple of 32, sequences)
//! are the caller's to route elsewhere.

use core::arch::x86_64::{
    __m512, _mm512_add_ps, _mm512_fmadd_ps, _mm512_loadu_ps, _mm512_set1_ps, _mm512_setzero_ps,
    _mm512_storeu_ps,
};

use super::{Run, interior, walk_pixels};
use crate::kernels::scalar::{conv_pixel as scalar_pixel, conv_pixels};
use crate::kernels::{Accumulate, ConvShape};

/// Output pixels per tile (along a row) and output channels per tile.
const PIXELS: usize = 8;
const CHANNELS: usize = 32;

/// Whether [`conv`] and [`conv_pixel`] handle `shape`.
pub fn covers(shape: &ConvShape) -> bool {
    shape.out_channels.is_multiple_of(CHANNELS) && shape.in_height > 1
}

/// `N` output pixels x 32 channels from `channel`, all taps inside the input.
///
/// # Safety
/// The CPU supports AVX-512F; the slices have the lengths `shape` implies;
/// `interior(shape, out_y, out_x, N)` holds; `channel + 32 <= out_channels`.
#[target_feature(enable = "avx512f")]
unsafe fn interior_tile<const N: usize>(
    shape: &ConvShape,
    input: &[f32],
    weight: &[f32],
    (out_y, out_x): (usize, usize),
    channel: usize,
) -> [[__m512; 2]; N] {
    let in_channels = shape.in_channels;
    let out_channels = shape.out_channels;
    let stride = shape.stride;
    let pixel_step = stride * in_channels;
    let mut sums = [[_mm512_setzero_ps(); 2]; N];
    for kernel_y in 0..shape.kernel_height {
        let in_y = out_y * stride + kernel_y - shape.padding_height;
        for kernel_x in 0..shape.kernel_width {
            let in_x = out_x * stride + kernel_x - shape.padding_width;
            let first = (in_y * shape.in_width + in_x) * in_channels;
            let taps =
                (kernel_y * shape.kernel_width + kernel_x) * in_channels * out_channels + channel;
            for input_channel in 0..in_channels {
                // SAFETY: `interior` puts all N pixels of this tap inside the input, and the
                // weight row of 32 channels from `channel` is inside the tap's block.
                unsafe {
                    let row = weight.as_ptr().add(taps + input_channel * out_channels);
                    let low = _mm512_loadu_ps(row);
                    let high = _mm512_loadu_ps(row.add(16));
                    let values = input.as_ptr().add(first + input_channel);
                    for (pixel, sum) in sums.iter_mut().enumerate() {
                        let value = _mm512_set1_ps(*values.add(pixel * pixel_step));
                        sum[0] = _mm512_fmadd_ps(value, low, sum[0]);
                        sum[1] = _mm512_fmadd_ps(value, high, sum[1]);
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
/// The CPU supports AVX-512F; `channel + 32 <= out_channels`; the `N` pixels from
/// `first_pixel` are inside `output`.
#[target_feature(enable = "avx512f")]
unsafe fn store_tile<const N: usize>(
    sums: &[[__m512; 2]; N],
    (bias, output): (&[f32], &mut [f32]),
    out_channels: usize,
    first_pixel: usize,
    channel: usize,
    accumulate: Accumulate,
) {
    let bias = &bias[channel..channel + CHANNELS];
    for (pixel, sum) in sums.iter().enumerate() {
        let out = &mut output[(first_pixel + pixel) * out_channels + channel..][..CHANNELS];
        for (half, &value) in sum.iter().enumerate() {
            let at = 16 * half;
            // SAFETY: `out` and `bias` hold 32 floats; each access covers 16 from `at`.
            unsafe {
                let mut value = _mm512_add_ps(value, _mm512_loadu_ps(bias.as_ptr().add(at)));
                if accumulate == Accumulate::Add {
                    value = _mm512_add_ps(value, _mm512_loadu_ps(out.as_ptr().add(at)));
                }
                _mm512_storeu_ps(out.as_mut_ptr().add(at), value);
            }
        }
    }
}

/// [`Kernels::conv`](crate::kernels::Kernels::conv) for a shape [`covers`] accepts.
///
/// # Safety
/// The CPU supports AVX-512F; `covers(shape)`; the slices have the lengths `shape` implies.
pub unsafe fn conv(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
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
            let at = (out_y, out_x);
            let out = (bias, &mut *output);
            // SAFETY: the caller vouches for the CPU, `covers` and the lengths;
            // `walk_pixels` checked `interior` for these pixels.
            unsafe {
                if pixels == PIXELS {
                    let sums = interior_tile::<PIXELS>(shape, input, weight, at, channel);
                    store_tile(
                        &sums,
                        out,
                        shape.out_channels,
                        first_pixel,
                        channel,
                        accumulate,
                    );
                } else {
                    let sums = interior_tile::<1>(shape, input, weight, at, channel);
                    store_tile(
                        &sums,
                        out,
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

/// [`Kernels::conv_pixel`](crate::kernels::Kernels::conv_pixel) matching [`conv`].
///
/// # Safety
/// As for [`conv`]; `output` holds `out_channels` values and the pixel is in the output.
pub unsafe fn conv_pixel(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    (out_y, out_x): (usize, usize),
    output: &mut [f32],
) {
    if !interior(shape, out_y, out_x, 1) {
        let accumulate = Accumulate::Overwrite;
        return scalar_pixel(
            shape,
            (input, weight, bias),
            output,
            accumulate,
            (out_y, out_x),
        );
    }
    for channel in (0..shape.out_channels).step_by(CHANNELS) {
        // SAFETY: as in `conv`; `output` is the pixel's channels, so pixel 0 is inside it.
        unsafe {
            let sums = interior_tile::<1>(shape, input, weight, (out_y, out_x), channel);
            let out = (bias, &mut *output);
            store_tile(
                &sums,
                out,
                shape.out_channels,
                0,
                channel,
                Accumulate::Overwrite,
            );
        }
    }
}
