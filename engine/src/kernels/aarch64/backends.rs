//! The three aarch64 backends: the same f32 kernels (NEON, eight lanes as AVX2), the int8
//! tiles on each one's dot product.

use super::lanes::Neon8;
use super::{int8, sequence};
use crate::kernels::scalar::{
    Scalar, assert_conv_columns, assert_conv_lengths, assert_conv_pixel_lengths,
};
use crate::kernels::simd;
use crate::kernels::simd::f32_tile;
use crate::kernels::simd::int8::{checked_conv, checked_conv_codes, checked_conv_pixel};
use crate::kernels::simd::sequence::Sequence;
use crate::kernels::{
    Accumulate, ByteRows, CodeRows, ConvShape, DigitRows, Kernels, NarrowForm, SignedByteRows,
};

/// Output pixels and channels of an f32 tile: AVX2's (6 x 16: 24 of the 32 registers hold
/// sums), so the same layers take the tiles and the others the scalar reference, as there.
const PIXELS: usize = 6;
const CHANNELS: usize = 16;

/// NEON kernels (every aarch64 application core). Reachable only through
/// [`Neon::detect`].
#[derive(Debug)]
pub struct Neon {
    _checked: (),
}

/// NEON with the dot-product extension (`sdot`). Reachable only through [`Dot::detect`].
#[derive(Debug)]
pub struct Dot {
    _checked: (),
}

/// NEON with the dot product and I8MM (the byte convolutions on `usmmla` and `smmla`, the
/// digit planes on `usdot`). Reachable only through
/// [`I8mm::detect`].
#[derive(Debug)]
pub struct I8mm {
    _checked: (),
}

static NEON: Neon = Neon { _checked: () };
static DOT: Dot = Dot { _checked: () };
static I8MM: I8mm = I8mm { _checked: () };

impl Neon {
    /// `None` on a target built without NEON (`aarch64-unknown-none-softfloat`).
    pub fn detect() -> Option<&'static Neon> {
        cfg!(target_feature = "neon").then_some(&NEON)
    }
}

impl Dot {
    /// `None` unless the CPU has the dot-product extension.
    pub fn detect() -> Option<&'static Dot> {
        (Neon::detect().is_some() && super::has_dotprod()).then_some(&DOT)
    }
}

impl I8mm {
    /// `None` unless the CPU has I8MM and the dot product.
    pub fn detect() -> Option<&'static I8mm> {
        (Neon::detect().is_some() && super::has_i8mm()).then_some(&I8MM)
    }
}

/// [`f32_tile::conv_columns`] compiled for NEON: output channels `columns` (all, or those
/// of `conv_channels`) into `output` (`[positions, columns.len()]`).
///
/// # Safety
/// NEON; `input`, `weight` and `bias` have the lengths `shape` implies, `output` at least
/// `positions x columns.len()`; `out_channels` is a multiple of 16, and so are `columns`'
/// ends.
#[target_feature(enable = "neon")]
unsafe fn conv_tiles(
    shape: &ConvShape,
    parameters: (&[f32], &[f32], &[f32]),
    columns: core::ops::Range<usize>,
    output: &mut [f32],
    accumulate: Accumulate,
) {
    // SAFETY: this function's contract is the body's.
    unsafe {
        f32_tile::conv_columns::<Neon8, PIXELS, 2>(shape, parameters, columns, output, accumulate)
    }
}

/// [`f32_tile::conv_pixel`] compiled for NEON.
///
/// # Safety
/// As for [`conv_tiles`]; the pixel is in the output and `output` holds its channels.
#[target_feature(enable = "neon")]
unsafe fn conv_one_pixel(
    shape: &ConvShape,
    parameters: (&[f32], &[f32], &[f32]),
    pixel: (usize, usize),
    output: &mut [f32],
) {
    // SAFETY: this function's contract is the body's.
    unsafe { f32_tile::conv_pixel::<Neon8>(shape, parameters, pixel, output) }
}

/// `Kernels::conv` on NEON: AVX2's choice of path for each shape.
fn conv_f32(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    // SAFETY: the backends exist only on NEON targets.
    if unsafe { sequence::neon::conv(shape, (input, weight, bias), output, accumulate) }.is_some() {
        return;
    }
    assert_conv_lengths(shape, (input, weight, bias), output.len());
    if !shape.out_channels.is_multiple_of(CHANNELS) {
        return Scalar.conv(shape, input, weight, bias, output, accumulate);
    }
    let columns = 0..shape.out_channels;
    // SAFETY: NEON; the asserts above fix the slice lengths; out_channels is a multiple of 16.
    unsafe { conv_tiles(shape, (input, weight, bias), columns, output, accumulate) }
}

/// `Kernels::conv_channels` on NEON: the sequences' streaming kernel, or the 2-D tiles.
fn conv_channels_f32(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
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
        // SAFETY: NEON; the asserts fix the lengths, and the columns' ends are multiples of
        // 16 (64, or out_channels).
        unsafe { conv_tiles(shape, parameters, channels, output, accumulate) };
        return true;
    }
    let parameters = (input, weight, &bias[channels.clone()]);
    // SAFETY: the backends exist only on NEON targets.
    unsafe { sequence::neon::conv_channels(shape, parameters, channels, output, accumulate) }
        .is_some()
}

/// `Kernels::conv_pixel` on NEON.
fn conv_pixel_f32(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    (out_y, out_x): (usize, usize),
    output: &mut [f32],
) {
    assert_conv_pixel_lengths(shape, (input, weight, bias), (out_y, out_x), output.len());
    if Sequence::from_shape(shape).is_some() || !shape.out_channels.is_multiple_of(CHANNELS) {
        return Scalar.conv_pixel(shape, input, weight, bias, (out_y, out_x), output);
    }
    // SAFETY: NEON; the pixel is in the output (asserted) and `output` holds its channels.
    unsafe { conv_one_pixel(shape, (input, weight, bias), (out_y, out_x), output) }
}

/// `Kernels::conv_int8_signed_bytes` with `sdot` (signed by signed: the weights as they
/// are).
///
/// # Safety
/// The CPU has the dot-product extension.
#[target_feature(enable = "neon,dotprod")]
unsafe fn checked_conv_signed_bytes(
    shape: &ConvShape,
    input: &SignedByteRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    const TILE: (usize, usize) = int8::BYTES_TILE;
    // SAFETY: the dot product (this function's contract).
    unsafe {
        simd::int8::checked_conv_signed_bytes::<int8::SignedBytes, { TILE.0 }, { TILE.1 }>(
            shape, input, parameters, output, accumulate,
        )
    }
}

/// The [`Kernels`] methods every aarch64 backend implements alike, the int8 ones on the
/// tiles of `int8::$module`. Expanded only inside the `impl Kernels` of a backend type that
/// exists once its features were detected, which every `unsafe` call relies on.
macro_rules! shared_kernels {
    ($module:ident) => {
        fn conv(
            &self,
            shape: &ConvShape,
            input: &[f32],
            weight: &[f32],
            bias: &[f32],
            output: &mut [f32],
            accumulate: Accumulate,
        ) {
            conv_f32(shape, (input, weight, bias), output, accumulate)
        }

        fn conv_pixel(
            &self,
            shape: &ConvShape,
            input: &[f32],
            weight: &[f32],
            bias: &[f32],
            pixel: (usize, usize),
            output: &mut [f32],
        ) {
            conv_pixel_f32(shape, (input, weight, bias), pixel, output)
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
            conv_channels_f32(shape, (input, weight, bias), channels, output, accumulate)
        }

        fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
            // SAFETY: the backends exist only on NEON targets.
            unsafe { sequence::matvec(weight, input, base, output) }
        }

        fn conv_int8(
            &self,
            shape: &ConvShape,
            input: &DigitRows<'_>,
            weight: &[i8],
            weight_scales: &[f32],
            bias: &[f32],
            output: &mut [f32],
            accumulate: Accumulate,
        ) {
            let parameters = (weight, weight_scales, bias);
            let kernel = int8::$module::conv;
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { checked_conv(kernel, shape, input, parameters, output, accumulate) }
        }

        fn conv_int8_pixel(
            &self,
            shape: &ConvShape,
            input: &DigitRows<'_>,
            weight: &[i8],
            weight_scales: &[f32],
            bias: &[f32],
            pixel: (usize, usize),
            output: &mut [f32],
        ) {
            let parameters = (weight, weight_scales, bias);
            let kernel = int8::$module::conv_pixel;
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { checked_conv_pixel(kernel, shape, input, parameters, pixel, output) }
        }

        fn conv_int8_codes(
            &self,
            shape: &ConvShape,
            input: &CodeRows<'_>,
            weight: &[i8],
            weight_scales: &[f32],
            bias: &[f32],
            output: &mut [f32],
            accumulate: Accumulate,
        ) {
            let parameters = (weight, weight_scales, bias);
            let kernel = int8::$module::conv_codes;
            // SAFETY: `self` exists only on a CPU with the backend's features.
            unsafe { checked_conv_codes(kernel, shape, input, parameters, output, accumulate) }
        }
    };
}

impl Kernels for Neon {
    fn name(&self) -> &'static str {
        "neon"
    }

    /// The 16-bit codes' pair products (`smull`) take the U-Net's narrow codes widened once.
    fn multiplies_signed_bytes(&self) -> bool {
        false
    }

    fn matvec_int8_codes(
        &self,
        weight: &[i8],
        row_scales: &[f32],
        input: &CodeRows<'_>,
        base: &[f32],
        output: &mut [f32],
    ) {
        // SAFETY: `self` exists only on NEON targets.
        unsafe { int8::neon::matvec_codes(weight, row_scales, input, base, output) }
    }

    shared_kernels!(neon);
}

/// `Kernels::matvec_int8_codes` on `sdot` ([`super::matvec`]), for the backends that
/// have it; the shared kernel of `int8::$module` for rows too wide for it.
macro_rules! matvec_on_sdot {
    ($module:ident) => {
        fn matvec_int8_codes(
            &self,
            weight: &[i8],
            row_scales: &[f32],
            input: &CodeRows<'_>,
            base: &[f32],
            output: &mut [f32],
        ) {
            // SAFETY: `self` exists only when the dot product was detected.
            unsafe {
                if super::matvec::matvec_codes(weight, row_scales, input, base, output).is_none() {
                    int8::$module::matvec_codes(weight, row_scales, input, base, output)
                }
            }
        }
    };
}

impl Kernels for Dot {
    fn name(&self) -> &'static str {
        "dot"
    }

    fn conv_int8_bytes(
        &self,
        shape: &ConvShape,
        input: &ByteRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let parameters = (weight, weight_scales, bias);
        // SAFETY: `self` exists only when the dot product was detected.
        unsafe { super::bytes::checked_conv_bytes(shape, input, parameters, output, accumulate) }
    }

    /// `sdot` takes whole bytes centred (the `bytes` module).
    fn narrow_form(&self) -> NarrowForm {
        NarrowForm::Bytes
    }

    fn conv_int8_signed_bytes(
        &self,
        shape: &ConvShape,
        input: &SignedByteRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let parameters = (weight, weight_scales, bias);
        // SAFETY: `self` exists only when the dot product was detected.
        unsafe { checked_conv_signed_bytes(shape, input, parameters, output, accumulate) }
    }

    matvec_on_sdot!(dot);
    shared_kernels!(dot);
}

impl Kernels for I8mm {
    fn name(&self) -> &'static str {
        "i8mm"
    }

    fn conv_int8_bytes(
        &self,
        shape: &ConvShape,
        input: &ByteRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let parameters = (weight, weight_scales, bias);
        // SAFETY: `self` exists only when I8MM was detected.
        unsafe {
            super::mmla::checked_conv_bytes(shape, input, parameters, None, output, accumulate)
        }
    }

    fn conv_int8_bytes_paired(
        &self,
        shape: &ConvShape,
        input: &ByteRows<'_>,
        weight: &[i8],
        pairs: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let parameters = (weight, weight_scales, bias);
        let pairs = Some(pairs);
        // SAFETY: `self` exists only when I8MM was detected.
        unsafe {
            super::mmla::checked_conv_bytes(shape, input, parameters, pairs, output, accumulate)
        }
    }

    fn conv_int8_signed_bytes(
        &self,
        shape: &ConvShape,
        input: &SignedByteRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let parameters = (weight, weight_scales, bias);
        let run = super::mmla::checked_conv_signed_bytes;
        // SAFETY: `self` exists only when I8MM was detected.
        unsafe { run(shape, input, parameters, None, output, accumulate) }
    }

    fn conv_int8_signed_bytes_paired(
        &self,
        shape: &ConvShape,
        input: &SignedByteRows<'_>,
        weight: &[i8],
        pairs: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let parameters = (weight, weight_scales, bias);
        let run = super::mmla::checked_conv_signed_bytes;
        // SAFETY: `self` exists only when I8MM was detected.
        unsafe { run(shape, input, parameters, Some(pairs), output, accumulate) }
    }

    matvec_on_sdot!(i8mm);

    /// `usmmla` multiplies whole bytes.
    fn narrow_form(&self) -> NarrowForm {
        NarrowForm::Bytes
    }

    shared_kernels!(i8mm);
}
