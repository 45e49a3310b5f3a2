//! The int8 convolution ([`Kernels::conv_int8`](crate::kernels::Kernels) and its
//! single-pixel form) both x86-64 backends run: one generic body over an integer dot
//! product ([`Int8Lanes`]: AVX2 `vpmaddubsw` on YMM, AVX-512 VNNI `vpdpbusd` on ZMM),
//! instantiated inside each backend's thin `#[target_feature]` wrapper, as
//! [`super::f32_tile`] is for f32.
//!
//! A tile is `P` consecutive output positions (row-major over the output map, so a tile may
//! wrap onto the next row, and maps of one or two pixels still use it) times `V` vectors of
//! output channels. The tile's exact i32 sums of one digit plane are accumulated in
//! registers over every kernel tap and input-channel quad (the contract's sums run over the
//! whole kernel and the input has one scale), then the two planes' sums combined exactly,
//! rounded and scaled once. A pixel whose tap falls in the padding reads a row of zero
//! codes ([`ZERO_ROW`]), as the convolution defines it, so border pixels need no separate
//! path, and every output value is the same whichever tile (or the single-pixel path)
//! computes it.
//!
//! Channel blocks are the outer loop and pixel tiles the inner one, so a block's weights
//! (up to 295 KB, ResNet layer4 at 64 channels) stay in the L2 cache while every pixel
//! reads them; the other order streamed the whole kernel from L3 once per pixel tile. The
//! weight layout keeps each 64-channel block's quads in one stretch, in the order a tile
//! reads them ([`int8_quad_index`](crate::kernels::int8_quad_index)), so they spread over
//! every cache set.
//!
//! The unsigned-by-signed byte products need activations in 0..=127, which every trunk input
//! is (a ReLU output); [`DigitRows::nonnegative`] says so, and any other input goes to the
//! scalar reference.
//!
//! The U-Net's inputs have both signs: [`Kernels::conv_int8_codes`] reads whole signed codes
//! ([`CodeRows`], i16) and multiplies them by the weights widened to i16, two products a
//! lane (AVX-512 VNNI `vpdpwssd`, AVX2 `vpmaddwd`): the same tiles, the same exact sums.
//! A quad's four weights of one output channel, widened, fill two lanes, which meet the
//! same quad's codes broadcast as (c0, c1), (c2, c3); the two lanes of each channel are
//! added once per tap, and the taps' i32 sums added exactly in f64 (a whole kernel's can
//! exceed i32).
//!
//! [`DigitRows::nonnegative`]: crate::kernels::DigitRows::nonnegative
//! [`Kernels::conv_int8_codes`]: crate::kernels::Kernels::conv_int8_codes

mod lanes;
mod matvec;
mod tiles;

use crate::kernels::scalar::{
    assert_code_lengths, assert_int8_lengths, assert_int8_pixel_lengths,
    assert_signed_byte_lengths, conv_int8_pixel, conv_int8_pixels,
};
use crate::kernels::{Accumulate, CodeRows, ConvShape, DigitRows, SignedByteRows};
#[cfg(target_arch = "aarch64")]
pub(crate) use lanes::CenteredByteLanes;
#[cfg(target_arch = "x86_64")]
pub(crate) use lanes::WholeByteLanes;
pub(crate) use lanes::{Int8Lanes, SignedByteLanes};
pub(crate) use matvec::matvec_codes;
#[cfg(target_arch = "aarch64")]
pub(crate) use tiles::{CenteredBytes, PREFETCH_QUADS, PixelTile, ZERO_ROW, store};
pub(crate) use tiles::{byte_tiles_apply, conv, conv_pixel, tiles_apply};

/// A backend's [`conv`] wrapper.
pub(crate) type ConvKernel =
    unsafe fn(&ConvShape, &DigitRows<'_>, (&[i8], &[f32], &[f32]), &mut [f32], Accumulate);

/// A backend's [`conv`] wrapper for signed codes.
pub(crate) type CodesKernel =
    unsafe fn(&ConvShape, &CodeRows<'_>, (&[i8], &[f32], &[f32]), &mut [f32], Accumulate);

/// A backend's [`conv_pixel`] wrapper.
pub(crate) type PixelKernel =
    unsafe fn(&ConvShape, &DigitRows<'_>, (&[i8], &[f32], &[f32]), (usize, usize), &mut [f32]);

/// [`Kernels::conv_int8`](crate::kernels::Kernels::conv_int8) on `kernel`: the lengths
/// checked, inputs the tiles do not take ([`tiles_apply`]) on the scalar reference.
///
/// # Safety
/// The CPU supports what `kernel` requires.
pub(crate) unsafe fn checked_conv(
    kernel: ConvKernel,
    shape: &ConvShape,
    input: &DigitRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    assert_int8_lengths(shape, input, (weight, weight_scales, bias), output.len());
    if !tiles_apply(shape, input) {
        let positions = shape.out_height() * shape.out_width();
        let parameters = (weight, weight_scales, bias);
        let channels = 0..shape.out_channels;
        return conv_int8_pixels(
            shape,
            input,
            parameters,
            output,
            accumulate,
            0..positions,
            channels,
        );
    }
    // SAFETY: the caller vouches for the CPU; the lengths were asserted and `tiles_apply`
    // checked just above.
    unsafe {
        kernel(
            shape,
            input,
            (weight, weight_scales, bias),
            output,
            accumulate,
        )
    }
}

/// [`Kernels::conv_int8_pixel`](crate::kernels::Kernels::conv_int8_pixel) on `kernel`, as
/// [`checked_conv`] is for the whole map.
///
/// # Safety
/// The CPU supports what `kernel` requires.
pub(crate) unsafe fn checked_conv_pixel(
    kernel: PixelKernel,
    shape: &ConvShape,
    input: &DigitRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    (out_y, out_x): (usize, usize),
    output: &mut [f32],
) {
    let parameters = (weight, weight_scales, bias);
    assert_int8_pixel_lengths(shape, input, parameters, (out_y, out_x), output.len());
    if !tiles_apply(shape, input) {
        let (channels, pixel) = (0..shape.out_channels, (out_y, out_x));
        let overwrite = Accumulate::Overwrite;
        return conv_int8_pixel(shape, input, parameters, output, overwrite, pixel, channels);
    }
    // SAFETY: the caller vouches for the CPU; the lengths and the pixel were asserted and
    // `tiles_apply` checked just above.
    unsafe { kernel(shape, input, parameters, (out_y, out_x), output) }
}

/// [`Kernels::conv_int8_codes`](crate::kernels::Kernels::conv_int8_codes) on `kernel`, the
/// lengths checked (every input of whole codes suits the tiles).
///
/// # Safety
/// The CPU supports what `kernel` requires.
pub(crate) unsafe fn checked_conv_codes(
    kernel: CodesKernel,
    shape: &ConvShape,
    input: &CodeRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    assert_code_lengths(shape, input, parameters, output.len());
    // SAFETY: the caller vouches for the CPU; the lengths were asserted just above.
    unsafe { kernel(shape, input, parameters, output, accumulate) }
}

/// [`Kernels::conv_int8_bytes`](crate::kernels::Kernels::conv_int8_bytes) on lanes whose
/// products take whole bytes, `P` x `V` tiles: the lengths checked, shapes the tiles do not
/// take on the scalar reference. Each backend calls it inside its `#[target_feature]`
/// wrapper.
///
/// # Safety
/// The CPU supports `L`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(crate) unsafe fn checked_conv_bytes<L: WholeByteLanes, const P: usize, const V: usize>(
    shape: &ConvShape,
    input: &crate::kernels::ByteRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    use crate::kernels::ByteRows;
    use crate::kernels::scalar::{assert_byte_lengths, conv_int8_bytes};
    assert_byte_lengths(shape, input, parameters, output.len());
    if !byte_tiles_apply(shape) {
        return conv_int8_bytes(shape, input, parameters, output, accumulate);
    }
    // SAFETY: the caller vouches for the CPU; the lengths were asserted and the quads
    // checked just above.
    unsafe { conv::<L, ByteRows<'_>, P, V>(shape, input, parameters, output, accumulate) }
}

/// [`Kernels::conv_int8_signed_bytes`](crate::kernels::Kernels::conv_int8_signed_bytes) on
/// `P` x `V` tiles of lanes `L`, the lengths checked (every input of whole codes suits the
/// tiles).
///
/// # Safety
/// The CPU supports `L`.
#[inline(always)]
pub(crate) unsafe fn checked_conv_signed_bytes<
    L: SignedByteLanes,
    const P: usize,
    const V: usize,
>(
    shape: &ConvShape,
    input: &SignedByteRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    assert_signed_byte_lengths(shape, input, parameters, output.len());
    // SAFETY: the caller vouches for the CPU; the lengths were asserted just above.
    unsafe { conv::<L, SignedByteRows<'_>, P, V>(shape, input, parameters, output, accumulate) }
}

/// [`conv`] and [`conv_pixel`] compiled for one backend: the thin `#[target_feature]`
/// wrappers of the shared body. `$lanes` names the [`Int8Lanes`] type and `$tile` and
/// `$codes_tile` the (pixels, channel vectors) of the digit and code tiles, as seen from
/// inside the generated module.
macro_rules! backend {
    ($module:ident, $lanes:ty, $tile:expr, $codes_tile:expr, $features:literal) => {
        pub(crate) mod $module {
            use $crate::kernels::{Accumulate, CodeRows, ConvShape, DigitRows};

            const TILE: (usize, usize) = $tile;
            const CODES_TILE: (usize, usize) = $codes_tile;

            /// `matvec_codes` on this backend.
            ///
            /// # Safety
            /// The CPU supports the backend's features.
            #[target_feature(enable = $features)]
            pub(crate) unsafe fn matvec_codes(
                weight: &[i8],
                row_scales: &[f32],
                input: &CodeRows<'_>,
                base: &[f32],
                output: &mut [f32],
            ) {
                // SAFETY: this function's contract is the body's.
                unsafe { $crate::kernels::simd::int8::matvec_codes::<$lanes>(weight, row_scales, input, base, output) }
            }

            /// `conv` of signed codes on this backend.
            ///
            /// # Safety
            /// The CPU supports the backend's features; otherwise as for the body.
            #[target_feature(enable = $features)]
            pub(crate) unsafe fn conv_codes(
                shape: &ConvShape,
                input: &CodeRows<'_>,
                parameters: (&[i8], &[f32], &[f32]),
                output: &mut [f32],
                accumulate: Accumulate,
            ) {
                // SAFETY: this function's contract is the body's.
                unsafe {
                    $crate::kernels::simd::int8::conv::<$lanes, CodeRows<'_>, { CODES_TILE.0 }, { CODES_TILE.1 }>(
                        shape, input, parameters, output, accumulate,
                    )
                }
            }

            /// `conv` on this backend.
            ///
            /// # Safety
            /// The CPU supports the backend's features; otherwise as for the body.
            #[target_feature(enable = $features)]
            pub(crate) unsafe fn conv(
                shape: &ConvShape,
                input: &DigitRows<'_>,
                parameters: (&[i8], &[f32], &[f32]),
                output: &mut [f32],
                accumulate: Accumulate,
            ) {
                // SAFETY: this function's contract is the body's.
                unsafe {
                    $crate::kernels::simd::int8::conv::<$lanes, DigitRows<'_>, { TILE.0 }, { TILE.1 }>(
                        shape, input, parameters, output, accumulate,
                    )
                }
            }

            /// `conv_pixel` on this backend.
            ///
            /// # Safety
            /// As for [`conv`]; the pixel is in the output and `output` holds its channels.
            #[target_feature(enable = $features)]
            pub(crate) unsafe fn conv_pixel(
                shape: &ConvShape,
                input: &DigitRows<'_>,
                parameters: (&[i8], &[f32], &[f32]),
                pixel: (usize, usize),
                output: &mut [f32],
            ) {
                // SAFETY: this function's contract is the body's.
                unsafe {
                    $crate::kernels::simd::int8::conv_pixel::<$lanes, { TILE.1 }>(shape, input, parameters, pixel, output)
                }
            }
        }
    };
}

pub(crate) use backend;
