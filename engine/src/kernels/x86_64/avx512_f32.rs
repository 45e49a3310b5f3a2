//! AVX-512 f32 convolution for 2-D maps: the shared body of `f32_tile` at twice
//! the AVX2 width, tiles of 6 pixels x 64 channels where the layer has whole blocks of 64
//! (every layer of the product models), else 14 pixels x 32 channels. Both keep 24-28 of
//! the 32 ZMM registers as accumulators; per input channel and tap, the wide tile's four
//! weight loads and six broadcasts feed 24 FMAs. The narrow tile's fourteen broadcasts each
//! read a pixel pointer the compiler had to keep on the stack (14 pointers do not fit the
//! general registers): 30 loads for 28 FMAs, against 10 for 24. Layers this does not cover
//! (out_channels not a multiple of 32, sequences) are the caller's to route elsewhere.

use super::lanes::Zmm;
use crate::kernels::simd::f32_tile;
use crate::kernels::{Accumulate, ConvShape};

/// Output pixels per tile and output channels per tile where the output channels are not a
/// multiple of 64 (14 was fastest of 8, 12 and 14 on the panda layers of `--bench kernels`,
/// before the wide tile took them).
const PIXELS: usize = 14;
const CHANNELS: usize = 32;

/// The wide tile: 6 pixels x 64 channels (on the panda trunk's layers, against 14 x 32:
/// 0.72x in all; 7, 5 and 4 pixels 0.78x, 0.73x and 0.78x; 2 x 128 1.09x).
const WIDE_PIXELS: usize = 6;
const WIDE_CHANNELS: usize = 64;

/// Pixels per tile where 14-pixel tiles would leave more than a quarter of their slots empty.
const SMALL_MAP_PIXELS: usize = 8;

/// Whether [`conv`] and [`conv_pixel`] handle `shape`.
pub fn covers(shape: &ConvShape) -> bool {
    shape.out_channels.is_multiple_of(CHANNELS) && shape.in_height > 1
}

/// Output channels `columns` of [`Kernels::conv`](crate::kernels::Kernels::conv) (all of
/// them, or those of [`Kernels::conv_channels`](crate::kernels::Kernels::conv_channels):
/// `output` is `[positions, columns.len()]`) for a shape [`covers`] accepts.
///
/// # Safety
/// The CPU supports AVX-512F; `covers(shape)`; `input`, `weight` and `bias` have the lengths
/// `shape` implies, `output` at least `positions x columns.len()`; `columns` lies inside
/// `out_channels`, its start a multiple of 64 and its end one or `out_channels`.
#[target_feature(enable = "avx512f")]
pub unsafe fn conv(
    shape: &ConvShape,
    parameters: (&[f32], &[f32], &[f32]),
    columns: core::ops::Range<usize>,
    output: &mut [f32],
    accumulate: Accumulate,
) {
    // Each pixel's chain is the same whichever tile computes it. For the narrow tiles, small
    // maps (16 positions) would leave most of a second 14-pixel tile empty; 8-pixel tiles
    // waste nothing there.
    let positions = shape.out_height() * shape.out_width();
    let waste = positions.div_ceil(PIXELS) * PIXELS - positions;
    // SAFETY: this function's contract is the body's (64 = 4 x 16 lanes, 32 = 2 x 16; the
    // columns' ends are multiples of both, or the channels').
    unsafe {
        if shape.out_channels.is_multiple_of(WIDE_CHANNELS) {
            f32_tile::conv_columns::<Zmm, WIDE_PIXELS, 4>(
                shape, parameters, columns, output, accumulate,
            )
        } else if 4 * waste > positions {
            f32_tile::conv_columns::<Zmm, SMALL_MAP_PIXELS, 2>(
                shape, parameters, columns, output, accumulate,
            )
        } else {
            f32_tile::conv_columns::<Zmm, PIXELS, 2>(shape, parameters, columns, output, accumulate)
        }
    }
}

/// [`Kernels::conv_pixel`](crate::kernels::Kernels::conv_pixel) matching [`conv`].
///
/// # Safety
/// As for [`conv`]; `output` holds `out_channels` values and the pixel is in the output.
#[target_feature(enable = "avx512f")]
pub unsafe fn conv_pixel(
    shape: &ConvShape,
    parameters: (&[f32], &[f32], &[f32]),
    pixel: (usize, usize),
    output: &mut [f32],
) {
    // SAFETY: this function's contract is the body's.
    unsafe { f32_tile::conv_pixel::<Zmm>(shape, parameters, pixel, output) }
}
