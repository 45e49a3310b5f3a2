//! AVX-512 f32 convolution for 2-D maps: the AVX2 tile's arithmetic at twice the width.
//! A tile is 8 pixels x 32 channels (16 ZMM accumulators): per input channel and tap, two
//! weight loads and eight broadcasts feed sixteen FMAs. As in the AVX2 kernel, every
//! pixel is one FMA chain over its taps inside the input, in tap and input-channel order
//! from zero, then the bias is added, whether it was computed in a tile or alone. Layers
//! this does not cover (out_channels not a multiple of 32, sequences) are the caller's to
//! route elsewhere.

use core::arch::x86_64::{
    __m512, _mm512_add_ps, _mm512_fmadd_ps, _mm512_loadu_ps, _mm512_set1_ps, _mm512_setzero_ps,
    _mm512_storeu_ps,
};

use super::tap_offsets;
use crate::kernels::{Accumulate, ConvShape};

/// Output pixels per tile (along a row) and output channels per tile.
const PIXELS: usize = 8;
const CHANNELS: usize = 32;

/// Whether [`conv`] and [`conv_pixel`] handle `shape`.
pub fn covers(shape: &ConvShape) -> bool {
    shape.out_channels.is_multiple_of(CHANNELS) && shape.in_height > 1
}

/// Output pixels `out_x .. out_x + count` of row `out_y` (`count <= N`) x 32 channels
/// from `channel`. Per input channel and tap, two weight loads feed two FMAs per pixel
/// whose tap is inside the input ([`tap_offsets`]); where all `N` pixels are inside (the
/// common case) the loop has no per-pixel test.
///
/// # Safety
/// The CPU supports AVX-512F; the slices have the lengths `shape` implies; the pixels
/// are in the output; `channel + 32 <= out_channels`.
#[target_feature(enable = "avx512f")]
unsafe fn tile<const N: usize>(
    shape: &ConvShape,
    (input, weight): (&[f32], &[f32]),
    (out_y, out_x): (usize, usize),
    count: usize,
    channel: usize,
) -> [[__m512; 2]; N] {
    let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
    let mut sums = [[_mm512_setzero_ps(); 2]; N];
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
                // of 32 channels from `channel` is inside the tap's block.
                unsafe {
                    let row = weight.as_ptr().add(taps + input_channel * out_channels);
                    let low = _mm512_loadu_ps(row);
                    let high = _mm512_loadu_ps(row.add(16));
                    let values = input.as_ptr().add(input_channel);
                    for (&offset, sum) in offsets.iter().zip(sums.iter_mut()) {
                        if !inside && offset == usize::MAX {
                            continue;
                        }
                        let value = _mm512_set1_ps(*values.add(offset));
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
/// The CPU supports AVX-512F; `channel + 32 <= out_channels`; the pixels from
/// `first_pixel` are inside `output`.
#[target_feature(enable = "avx512f")]
unsafe fn store_tile(
    sums: &[[__m512; 2]],
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
    for out_y in 0..shape.out_height() {
        for out_x in (0..out_width).step_by(PIXELS) {
            let count = (out_width - out_x).min(PIXELS);
            let first_pixel = out_y * out_width + out_x;
            for channel in (0..shape.out_channels).step_by(CHANNELS) {
                let out = (bias, &mut *output);
                // SAFETY: the caller vouches for the CPU, `covers` and the lengths; the
                // pixels are in the row.
                unsafe {
                    let sums =
                        tile::<PIXELS>(shape, (input, weight), (out_y, out_x), count, channel);
                    let sums = &sums[..count];
                    store_tile(
                        sums,
                        out,
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
    for channel in (0..shape.out_channels).step_by(CHANNELS) {
        // SAFETY: as in `conv`; `output` is the pixel's channels, so pixel 0 is inside it.
        unsafe {
            let sums = tile::<1>(shape, (input, weight), (out_y, out_x), 1, channel);
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
