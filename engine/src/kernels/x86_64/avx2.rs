//! AVX2 + FMA kernels. The 2-D convolution is the shared body of `f32_tile` on YMM
//! vectors, tiles of 6 pixels x 16 channels in twelve accumulators (of 16 registers; the
//! scalar reference reloads and stores its output for every product); the int8 one is the
//! shared body of `int8` on YMM vectors. The U-Net's 1-D convolutions, upsampling and
//! matrix-vector products use the weight-streaming `sequence` kernels.

use super::lanes::Ymm;
use super::sequence;
use crate::kernels::ops::Activation;
use crate::kernels::scalar::{
    Scalar, assert_conv_columns, assert_conv_lengths, assert_conv_pixel_lengths,
};
use crate::kernels::simd::f32_tile;
use crate::kernels::simd::sequence::Sequence;
use crate::kernels::{Accumulate, CodeRows, ConvShape, DigitRows, Kernels};

/// Output pixels per tile and output channels per tile (6 was fastest of 4, 5 and 6 on
/// the panda layers of `--bench kernels`).
const PIXELS: usize = 6;
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

/// The shared f32 body ([`f32_tile`]) compiled for AVX2 + FMA: output channels `columns`
/// (all, or those of `conv_channels`) into `output` (`[positions, columns.len()]`).
///
/// # Safety
/// The CPU supports AVX2 and FMA; `input`, `weight` and `bias` have the lengths `shape`
/// implies, `output` at least `positions x columns.len()`; `out_channels` is a multiple of
/// 16, and so are `columns`' ends.
#[target_feature(enable = "avx2,fma")]
unsafe fn conv_tiles(
    shape: &ConvShape,
    parameters: (&[f32], &[f32], &[f32]),
    columns: core::ops::Range<usize>,
    output: &mut [f32],
    accumulate: Accumulate,
) {
    // SAFETY: this function's contract is the body's.
    unsafe {
        f32_tile::conv_columns::<Ymm, PIXELS, 2>(shape, parameters, columns, output, accumulate)
    }
}

/// [`f32_tile::conv_pixel`] compiled for AVX2 + FMA.
///
/// # Safety
/// As for [`conv_tiles`]; the pixel is in the output and `output` holds its channels.
#[target_feature(enable = "avx2,fma")]
unsafe fn conv_one_pixel(
    shape: &ConvShape,
    parameters: (&[f32], &[f32], &[f32]),
    pixel: (usize, usize),
    output: &mut [f32],
) {
    // SAFETY: this function's contract is the body's.
    unsafe { f32_tile::conv_pixel::<Ymm>(shape, parameters, pixel, output) }
}

impl Kernels for Avx2 {
    fn name(&self) -> &'static str {
        "avx2"
    }

    /// `vpmaddwd` takes 16-bit codes: bytes widened once, as they are quantized, not at
    /// every broadcast (the panda denoising loop 1.13-1.23x as long that way), so AVX2 has
    /// no signed-byte tile and `conv_int8_signed_bytes` is the scalar reference's.
    fn multiplies_signed_bytes(&self) -> bool {
        false
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
        // SAFETY: `self` exists only when AVX2 and FMA were detected.
        if unsafe { sequence::avx2::conv(shape, (input, weight, bias), output, accumulate) }
            .is_some()
        {
            return;
        }
        assert_conv_lengths(shape, (input, weight, bias), output.len());
        // Narrow layers (the tiny model's trunk) are not worth a tail path.
        if !shape.out_channels.is_multiple_of(CHANNELS) {
            return Scalar.conv(shape, input, weight, bias, output, accumulate);
        }
        let columns = 0..shape.out_channels;
        // SAFETY: `self` exists only when AVX2 and FMA were detected; the asserts above fix
        // the slice lengths, and out_channels is a multiple of 16.
        unsafe { conv_tiles(shape, (input, weight, bias), columns, output, accumulate) }
    }

    fn conv_channels(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        channels: core::ops::Range<usize>,
        output: &mut [f32],
        accumulate: Accumulate,
    ) -> bool {
        if channels.end > bias.len() || channels.start > channels.end {
            return false;
        }
        if shape.in_height > 1 {
            if !shape.out_channels.is_multiple_of(CHANNELS) {
                return false;
            }
            let parameters = (input, weight, bias);
            assert_conv_columns(shape, parameters, &channels, output.len());
            // SAFETY: `self` exists only when AVX2 and FMA were detected; the asserts fix
            // the lengths, and the columns' ends are multiples of 16 (64, or out_channels).
            unsafe { conv_tiles(shape, parameters, channels, output, accumulate) };
            return true;
        }
        let parameters = (input, weight, &bias[channels.clone()]);
        // SAFETY: `self` exists only when AVX2 and FMA were detected.
        unsafe { sequence::avx2::conv_channels(shape, parameters, channels, output, accumulate) }
            .is_some()
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
        assert_conv_pixel_lengths(shape, (input, weight, bias), (out_y, out_x), output.len());
        // The paths `conv` takes for this pixel.
        if Sequence::from_shape(shape).is_some() || !shape.out_channels.is_multiple_of(CHANNELS) {
            return Scalar.conv_pixel(shape, input, weight, bias, (out_y, out_x), output);
        }
        // SAFETY: as in `conv`; the pixel is in the output (asserted) and `output` holds
        // its channels.
        unsafe { conv_one_pixel(shape, (input, weight, bias), (out_y, out_x), output) }
    }

    shared_kernels!(avx2);
}
