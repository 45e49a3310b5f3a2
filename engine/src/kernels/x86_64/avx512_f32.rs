//! AVX-512 f32 convolution for 2-D maps: the shared body of [`super::f32_tile`] at twice
//! the AVX2 width, tiles of 8 pixels x 32 channels (16 ZMM accumulators: per input channel
//! and tap, two weight loads and eight broadcasts feed sixteen FMAs). Layers this does not
//! cover (out_channels not a multiple of 32, sequences) are the caller's to route
//! elsewhere.

use super::f32_tile::{self, Zmm};
use crate::kernels::{Accumulate, ConvShape};

/// Output pixels per tile (along a row) and output channels per tile.
const PIXELS: usize = 8;
const CHANNELS: usize = 32;

/// Whether [`conv`] and [`conv_pixel`] handle `shape`.
pub fn covers(shape: &ConvShape) -> bool {
    shape.out_channels.is_multiple_of(CHANNELS) && shape.in_height > 1
}

/// [`Kernels::conv`](crate::kernels::Kernels::conv) for a shape [`covers`] accepts.
///
/// # Safety
/// The CPU supports AVX-512F; `covers(shape)`; the slices have the lengths `shape` implies.
#[target_feature(enable = "avx512f")]
pub unsafe fn conv(
    shape: &ConvShape,
    parameters: (&[f32], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    // SAFETY: this function's contract is the body's (32 = 2 x 16 lanes).
    unsafe { f32_tile::conv::<Zmm, PIXELS>(shape, parameters, output, accumulate) }
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
