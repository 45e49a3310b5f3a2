//! AVX-512 f32 convolution for 2-D maps: the shared body of `f32_tile` at twice
//! the AVX2 width, tiles of 14 pixels x 32 channels (28 of the 32 ZMM registers as
//! accumulators: per input channel and tap, two weight loads and fourteen broadcasts feed
//! 28 FMAs, so each weight byte loaded serves 14 pixels). Layers this does not
//! cover (out_channels not a multiple of 32, sequences) are the caller's to route
//! elsewhere.

use super::f32_tile;
use super::lanes::Zmm;
use crate::kernels::{Accumulate, ConvShape};

/// Output pixels per tile and output channels per tile (14 was fastest of 8, 12 and 14 on
/// the panda layers of `--bench kernels`).
const PIXELS: usize = 14;
const CHANNELS: usize = 32;

/// Pixels per tile where 14-pixel tiles would leave more than a quarter of their slots empty.
const SMALL_MAP_PIXELS: usize = 8;

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
    // Small maps (metaworld's layer4 has 16 positions) would leave most of a second
    // 14-pixel tile empty; 8-pixel tiles waste nothing there. Each pixel's chain is the same
    // whichever tile computes it.
    let positions = shape.out_height() * shape.out_width();
    let waste = positions.div_ceil(PIXELS) * PIXELS - positions;
    // SAFETY: this function's contract is the body's (32 = 2 x 16 lanes).
    unsafe {
        if 4 * waste > positions {
            f32_tile::conv::<Zmm, SMALL_MAP_PIXELS>(shape, parameters, output, accumulate)
        } else {
            f32_tile::conv::<Zmm, PIXELS>(shape, parameters, output, accumulate)
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
