//! The reference implementation of [`Kernels`]: plain loops, written for clarity. Faster
//! implementations are tested against it.

use super::{
    Accumulate, ByteRows, CodeRows, ConvShape, DigitRows, INT8_CHANNEL_BLOCK, Kernels,
    MAX_BYTE_TERMS, MAX_DIGIT_CHANNELS, MAX_DIGIT_TERMS, NarrowForm, QUAD, SignedByteRows, ops,
};

/// Output channels accumulated at once in the int8 kernels (an i32 block on the stack): at
/// most one block of the weight layout, whose quads are contiguous per input quad.
const INT8_BLOCK: usize = INT8_CHANNEL_BLOCK;

/// The kernel taps of output pixel `(out_y, out_x)` that read inside the input (padding
/// taps contribute zero and are skipped): the input pixel's index and the tap's index
/// `kernel_y * kernel_width + kernel_x`.
pub(crate) fn taps_inside(
    shape: &ConvShape,
    out_y: usize,
    out_x: usize,
) -> impl Iterator<Item = (usize, usize)> + '_ {
    (0..shape.kernel_height)
        .flat_map(move |kernel_y| (0..shape.kernel_width).map(move |kernel_x| (kernel_y, kernel_x)))
        .filter_map(move |(kernel_y, kernel_x)| {
            let pixel = tap_input(shape, (out_y, out_x), (kernel_y, kernel_x))?;
            Some((pixel, kernel_y * shape.kernel_width + kernel_x))
        })
}

/// The input pixel (row-major index) that output pixel `(out_y, out_x)` reads at kernel tap
/// `(kernel_y, kernel_x)`, `None` in the padding.
pub(crate) fn tap_input(
    shape: &ConvShape,
    (out_y, out_x): (usize, usize),
    (kernel_y, kernel_x): (usize, usize),
) -> Option<usize> {
    let in_y = (out_y * shape.stride + kernel_y).checked_sub(shape.padding_height)?;
    let in_x = (out_x * shape.stride + kernel_x).checked_sub(shape.padding_width)?;
    (in_y < shape.in_height && in_x < shape.in_width).then_some(in_y * shape.in_width + in_x)
}

/// The f32 convolution of output pixels `columns` of row `out_y`: the whole reference
/// kernel, and the border pixels of the SIMD ones.
pub(crate) fn conv_pixels(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
    out_y: usize,
    columns: core::ops::Range<usize>,
) {
    let out_channels = shape.out_channels;
    for out_x in columns {
        let out = &mut output[(out_y * shape.out_width() + out_x) * out_channels..][..out_channels];
        conv_pixel(
            shape,
            (input, weight, bias),
            out,
            accumulate,
            (out_y, out_x),
        );
    }
}

/// The f32 convolution at output pixel `(out_y, out_x)` into `out` (its channels): bias
/// first, then every product in tap and input-channel order.
pub(crate) fn conv_pixel(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    out: &mut [f32],
    accumulate: Accumulate,
    (out_y, out_x): (usize, usize),
) {
    let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
    match accumulate {
        Accumulate::Overwrite => out.copy_from_slice(bias),
        Accumulate::Add => out.iter_mut().zip(bias).for_each(|(o, b)| *o += b),
    }
    for (row, tap) in taps_inside(shape, out_y, out_x) {
        let pixel = &input[row * in_channels..][..in_channels];
        let taps = &weight[tap * in_channels * out_channels..][..in_channels * out_channels];
        for (&value, weights) in pixel.iter().zip(taps.chunks_exact(out_channels)) {
            for (o, &w) in out.iter_mut().zip(weights) {
                *o += value * w;
            }
        }
    }
}

/// `out (+)= totals * weight_scales + bias` over output `channels` (product, then sum): the
/// last step of both int8 kernels.
fn store_scaled(
    out: &mut [f32],
    totals: &[f32],
    (weight_scales, bias): (&[f32], &[f32]),
    channels: core::ops::Range<usize>,
    accumulate: Accumulate,
) {
    let parameters = weight_scales[channels.clone()].iter().zip(&bias[channels]);
    for ((o, &total), (&scale, &b)) in out.iter_mut().zip(totals).zip(parameters) {
        let value = total * scale + b;
        match accumulate {
            Accumulate::Overwrite => *o = value,
            Accumulate::Add => *o += value,
        }
    }
}

/// The slice lengths [`Kernels::conv`] promises.
pub(crate) fn assert_conv_lengths(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    output_len: usize,
) {
    assert_eq!(input.len(), shape.input_len());
    assert_eq!(weight.len(), shape.weight_len());
    assert_eq!(bias.len(), shape.out_channels);
    assert_eq!(output_len, shape.output_len());
}

/// The slice lengths [`Kernels::conv_channels`] promises on a 2-D map, and its channels:
/// inside the output channels, from a multiple of 64 to one or to the last channel.
pub(crate) fn assert_conv_columns(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    columns: &core::ops::Range<usize>,
    output_len: usize,
) {
    assert_eq!(input.len(), shape.input_len());
    assert_eq!(weight.len(), shape.weight_len());
    assert_eq!(bias.len(), shape.out_channels);
    assert!(columns.start <= columns.end && columns.end <= shape.out_channels);
    assert!(columns.start.is_multiple_of(64));
    assert!(columns.end.is_multiple_of(64) || columns.end == shape.out_channels);
    let positions = shape.out_height() * shape.out_width();
    assert!(output_len >= positions * columns.len());
}

/// The slice lengths [`Kernels::conv_pixel`] promises, and the pixel inside the output.
pub(crate) fn assert_conv_pixel_lengths(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    (out_y, out_x): (usize, usize),
    output_len: usize,
) {
    assert_eq!(input.len(), shape.input_len());
    assert_eq!(weight.len(), shape.weight_len());
    assert_eq!(bias.len(), shape.out_channels);
    assert_eq!(output_len, shape.out_channels);
    assert!(out_y < shape.out_height() && out_x < shape.out_width());
}

/// The slice lengths [`Kernels::conv_int8`] promises.
pub(crate) fn assert_int8_lengths(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output_len: usize,
) {
    assert_int8_inputs(shape, input, parameters);
    assert_eq!(output_len, shape.output_len());
}

/// The slice lengths [`Kernels::conv_int8_pixel`] promises, and the pixel inside the output.
pub(crate) fn assert_int8_pixel_lengths(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    (out_y, out_x): (usize, usize),
    output_len: usize,
) {
    assert_int8_inputs(shape, input, parameters);
    assert_eq!(output_len, shape.out_channels);
    assert!(out_y < shape.out_height() && out_x < shape.out_width());
}

fn assert_int8_inputs(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
) {
    assert!(shape.in_channels <= MAX_DIGIT_CHANNELS);
    assert!(shape.kernel_height * shape.kernel_width * shape.in_channels <= MAX_DIGIT_TERMS);
    assert_eq!(input.high.len(), shape.input_len());
    assert_eq!(input.low.len(), shape.input_len());
    assert_eq!(weight.len(), shape.int8_weight_len());
    assert_eq!(weight_scales.len(), shape.out_channels);
    assert_eq!(bias.len(), shape.out_channels);
}

/// The shape and slice lengths [`Kernels::conv_int8_bytes`] promises.
pub(crate) fn assert_byte_lengths(
    shape: &ConvShape,
    input: &ByteRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output_len: usize,
) {
    assert!(shape.in_channels >= 1 && shape.in_channels <= MAX_DIGIT_CHANNELS);
    assert!(shape.kernel_height * shape.kernel_width * shape.in_channels <= MAX_BYTE_TERMS);
    assert_eq!(input.bytes.len(), shape.input_len());
    assert_eq!(weight.len(), shape.int8_weight_len());
    assert_eq!(weight_scales.len(), shape.out_channels);
    assert_eq!(bias.len(), shape.out_channels);
    assert_eq!(output_len, shape.output_len());
}

/// The slice lengths [`Kernels::conv_int8_codes`] promises.
pub(crate) fn assert_code_lengths(
    shape: &ConvShape,
    input: &CodeRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output_len: usize,
) {
    let rows = shape.in_height * shape.in_width;
    assert!(shape.in_channels <= MAX_DIGIT_CHANNELS);
    assert_eq!(
        input.codes.len(),
        rows * CodeRows::row_stride(shape.in_channels)
    );
    assert_eq!(weight.len(), shape.int8_weight_len());
    assert_eq!(weight_scales.len(), shape.out_channels);
    assert_eq!(bias.len(), shape.out_channels);
    assert_eq!(output_len, shape.output_len());
}

/// The shape and slice lengths [`Kernels::conv_int8_signed_bytes`] promises.
pub(crate) fn assert_signed_byte_lengths(
    shape: &ConvShape,
    input: &SignedByteRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output_len: usize,
) {
    let rows = shape.in_height * shape.in_width;
    assert!(shape.in_channels <= MAX_DIGIT_CHANNELS);
    assert!(shape.kernel_height * shape.kernel_width * shape.in_channels <= MAX_BYTE_TERMS);
    assert_eq!(
        input.codes.len(),
        rows * CodeRows::row_stride(shape.in_channels)
    );
    assert_eq!(input.row_sums.len(), rows);
    assert_eq!(weight.len(), shape.int8_weight_len());
    assert_eq!(weight_scales.len(), shape.out_channels);
    assert_eq!(bias.len(), shape.out_channels);
    assert_eq!(output_len, shape.output_len());
}

/// [`Kernels::conv_int8_signed_bytes`] on the reference kernel (lengths unchecked).
pub(crate) fn conv_int8_signed_bytes(
    shape: &ConvShape,
    input: &SignedByteRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    conv_int8_map(shape, input, parameters, output, accumulate);
}

/// The int8 convolution of output `positions` (row-major over the output map), output
/// `channels` only: the whole reference kernel, and the tails of the SIMD ones.
pub(crate) fn conv_int8_pixels(
    shape: &ConvShape,
    input: &impl CodeSums,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
    positions: core::ops::Range<usize>,
    channels: core::ops::Range<usize>,
) {
    let out_width = shape.out_width();
    let out_channels = shape.out_channels;
    for position in positions {
        let out = &mut output[position * out_channels..][..out_channels];
        let pixel = (position / out_width, position % out_width);
        let parameters = (weight, weight_scales, bias);
        conv_int8_pixel(
            shape,
            input,
            parameters,
            out,
            accumulate,
            pixel,
            channels.clone(),
        );
    }
}

/// [`Kernels::conv_int8_bytes`] on the reference kernel (lengths unchecked).
pub(crate) fn conv_int8_bytes(
    shape: &ConvShape,
    input: &ByteRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    conv_int8_map(shape, input, parameters, output, accumulate);
}

/// The whole int8 convolution, every output pixel and channel: the reference kernel.
fn conv_int8_map(
    shape: &ConvShape,
    input: &impl CodeSums,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let positions = 0..shape.out_height() * shape.out_width();
    let channels = 0..shape.out_channels;
    conv_int8_pixels(
        shape, input, parameters, output, accumulate, positions, channels,
    );
}

/// The int8 convolution at output pixel `(out_y, out_x)`, output `channels` only, into
/// `out` (the pixel's `out_channels` values), as [`Kernels::conv_int8`] prescribes: the
/// exact per-tap sums added up in i64 (exact), rounded to f32, scaled.
pub(crate) fn conv_int8_pixel(
    shape: &ConvShape,
    input: &impl CodeSums,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    out: &mut [f32],
    accumulate: Accumulate,
    (out_y, out_x): (usize, usize),
    channels: core::ops::Range<usize>,
) {
    let mut block = channels.start;
    while block < channels.end {
        // Up to the end of the layout block that holds `block`.
        let width = (channels.end - block).min(INT8_BLOCK - block % INT8_BLOCK);
        let mut sums = [0i64; INT8_BLOCK];
        for (row, tap) in taps_inside(shape, out_y, out_x) {
            let tap_sums = input.code_sums(shape, weight, (row, tap), block, width);
            for (sum, &tap_sum) in sums.iter_mut().zip(&tap_sums) {
                *sum += i64::from(tap_sum);
            }
        }
        let scale = input.scale();
        let totals: [f32; INT8_BLOCK] = core::array::from_fn(|o| sums[o] as f32 * scale);
        let channels = block..block + width;
        store_scaled(
            &mut out[channels.clone()],
            &totals[..width],
            (weight_scales, bias),
            channels,
            accumulate,
        );
        block += width;
    }
}

/// Quantized activations as the reference reads them: the exact per-tap code sums and the
/// input's scale.
pub(crate) trait CodeSums {
    /// `sum_c code[row, c] q_w[tap, c, o]` for the `width` output channels from `block`
    /// (`row_tap`: the input pixel and the kernel tap).
    fn code_sums(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        row_tap: (usize, usize),
        block: usize,
        width: usize,
    ) -> [i32; INT8_BLOCK];

    fn scale(&self) -> f32;
}

impl CodeSums for DigitRows<'_> {
    fn code_sums(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        (row, tap): (usize, usize),
        block: usize,
        width: usize,
    ) -> [i32; INT8_BLOCK] {
        let high = digit_sums(shape, self.high, weight, (row, tap), block, width);
        let mut sums = digit_sums(shape, self.low, weight, (row, tap), block, width);
        for (sum, &high) in sums.iter_mut().zip(&high) {
            // `128 high + low` is the exact code sum (it fits i32, [`MAX_DIGIT_CHANNELS`]);
            // the high part alone may not, so the arithmetic wraps, which is exact modulo
            // 2^32 and therefore exact for the result.
            *sum = high.wrapping_mul(DIGIT_BASE).wrapping_add(*sum);
        }
        sums
    }

    fn scale(&self) -> f32 {
        self.scale
    }
}

impl CodeSums for ByteRows<'_> {
    fn code_sums(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        (row, tap): (usize, usize),
        block: usize,
        width: usize,
    ) -> [i32; INT8_BLOCK] {
        // One plane, read as the digit planes are: at most MAX_BYTE_TERMS products of
        // 255 x 128, exact in i32.
        digit_sums(shape, self.bytes, weight, (row, tap), block, width)
    }

    fn scale(&self) -> f32 {
        self.scale
    }
}

impl CodeSums for CodeRows<'_> {
    fn code_sums(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        (row, tap): (usize, usize),
        block: usize,
        width: usize,
    ) -> [i32; INT8_BLOCK] {
        let row_stride = CodeRows::row_stride(shape.in_channels);
        let codes = &self.codes[row * row_stride..][..row_stride];
        // |code| <= 16383 and |q_w| <= 128: each product and the sum of up to
        // MAX_DIGIT_CHANNELS of them fit i32.
        row_code_sums(shape, codes, weight, tap, block, width)
    }

    fn scale(&self) -> f32 {
        self.scale
    }
}

impl CodeSums for SignedByteRows<'_> {
    fn code_sums(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        (row, tap): (usize, usize),
        block: usize,
        width: usize,
    ) -> [i32; INT8_BLOCK] {
        let row_stride = CodeRows::row_stride(shape.in_channels);
        let codes = &self.codes[row * row_stride..][..row_stride];
        row_code_sums(shape, codes, weight, tap, block, width)
    }

    fn scale(&self) -> f32 {
        self.scale
    }
}

/// `sum_c codes[c] q_w[tap, c, o]` of one input row of whole codes (padded to quads) for
/// the `width` output channels from `block`.
fn row_code_sums<C: Copy + Into<i32>>(
    shape: &ConvShape,
    codes: &[C],
    weight: &[i8],
    tap: usize,
    block: usize,
    width: usize,
) -> [i32; INT8_BLOCK] {
    let mut sums = [0i32; INT8_BLOCK];
    for (quad, codes) in codes.chunks_exact(QUAD).enumerate() {
        let first = shape.int8_index(tap, quad * QUAD, block);
        let weights = &weight[first..][..width * QUAD];
        for (sum, weights) in sums.iter_mut().zip(weights.chunks_exact(QUAD)) {
            *sum += codes
                .iter()
                .zip(weights)
                .map(|(&code, &w)| code.into() * i32::from(w))
                .sum::<i32>();
        }
    }
    sums
}

/// The column count of [`Kernels::matvec_int8_codes`]' weight for `rows` rows, every length
/// checked.
///
/// # Panics
/// If the lengths disagree (the model code never passes such slices).
pub(crate) fn assert_matvec_codes_lengths(
    weight: &[i8],
    row_scales: &[f32],
    input: &CodeRows<'_>,
    base: &[f32],
    rows: usize,
) -> usize {
    assert_eq!(row_scales.len(), rows);
    assert_eq!(base.len(), rows);
    let cols = weight.len().checked_div(rows).unwrap_or(0);
    assert_eq!(weight.len(), rows * cols);
    assert!(input.codes.len() >= cols);
    cols
}

/// `sum_c weights[c] codes[c]` over the weights' columns, exact (i64).
pub(crate) fn exact_row_sum(weights: &[i8], codes: &[i16]) -> i64 {
    weights
        .iter()
        .zip(codes)
        .map(|(&w, &code)| i64::from(w) * i64::from(code))
        .sum()
}

/// What [`Kernels::matvec_int8_codes`] stores for a row's exact sum: rounded once to f32,
/// times the input's scale, times the row's, plus the base.
#[inline(always)]
pub(crate) fn scaled_row_sum(sum: i64, scale: f32, row_scale: f32, base: f32) -> f32 {
    base + (sum as f32 * scale) * row_scale
}

/// Base of the activation digits as an integer factor (`code = 128 high + low`).
const DIGIT_BASE: i32 = ops::DIGIT_BASE as i32;

/// The exact sums `sum_c digit[row, c] q_w[tap, c, o]` for the `width` output channels from
/// `block`, one digit plane (i8 digits, or u8 bytes).
fn digit_sums<Digit: Copy + Into<i16>>(
    shape: &ConvShape,
    plane: &[Digit],
    weight: &[i8],
    (row, tap): (usize, usize),
    block: usize,
    width: usize,
) -> [i32; INT8_BLOCK] {
    let in_channels = shape.in_channels;
    let pixel = &plane[row * in_channels..][..in_channels];
    // One partial sum per weight of a quad row, added up per output channel after the last
    // quad: the inner loop then runs over contiguous weights, which the compiler vectorizes
    // (integer sums are exact in any order).
    let mut partials = [0i32; QUAD * INT8_BLOCK];
    let partials = &mut partials[..width * QUAD];
    for (quad, values) in pixel.chunks(QUAD).enumerate() {
        // The padding channels of a last, partial quad have zero weights.
        let mut value = [0i16; QUAD];
        value
            .iter_mut()
            .zip(values)
            .for_each(|(v, &q)| *v = q.into());
        let first = shape.int8_index(tap, quad * QUAD, block);
        let weights = &weight[first..][..width * QUAD];
        for (partial, w) in partials
            .chunks_exact_mut(QUAD)
            .zip(weights.chunks_exact(QUAD))
        {
            // Any i8 or u8 by i8 product fits i16 (at most 255 x 128 = 32640): 16-bit
            // multiplies exist on every SIMD ISA, 32-bit ones not on baseline x86-64 (SSE2).
            for ((partial, &w), &value) in partial.iter_mut().zip(w).zip(&value) {
                *partial += (value * w as i16) as i32;
            }
        }
    }
    let mut sums = [0i32; INT8_BLOCK];
    for (sum, partial) in sums.iter_mut().zip(partials.chunks_exact(QUAD)) {
        *sum = partial.iter().sum();
    }
    sums
}

/// Portable scalar kernels (the compiler may still auto-vectorise the inner loops).
pub struct Scalar;

impl Kernels for Scalar {
    fn name(&self) -> &'static str {
        "scalar"
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
        assert_conv_lengths(shape, (input, weight, bias), output.len());
        for out_y in 0..shape.out_height() {
            conv_pixels(
                shape,
                (input, weight, bias),
                output,
                accumulate,
                out_y,
                0..shape.out_width(),
            );
        }
    }

    fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
        assert_eq!(weight.len(), output.len() * input.len());
        assert_eq!(base.len(), output.len());
        if input.is_empty() {
            // Rows of no columns (which `chunks_exact` cannot cut): the sums are empty.
            return output.copy_from_slice(base);
        }
        for ((out, row), &start) in output
            .iter_mut()
            .zip(weight.chunks_exact(input.len()))
            .zip(base)
        {
            *out = start + row.iter().zip(input).map(|(w, x)| w * x).sum::<f32>();
        }
    }

    fn matvec_int8_codes(
        &self,
        weight: &[i8],
        row_scales: &[f32],
        input: &CodeRows<'_>,
        base: &[f32],
        output: &mut [f32],
    ) {
        let cols = assert_matvec_codes_lengths(weight, row_scales, input, base, output.len());
        for (r, out) in output.iter_mut().enumerate() {
            let sum = exact_row_sum(&weight[r * cols..][..cols], input.codes);
            *out = scaled_row_sum(sum, input.scale, row_scales[r], base[r]);
        }
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
        assert_int8_lengths(shape, input, (weight, weight_scales, bias), output.len());
        let parameters = (weight, weight_scales, bias);
        conv_int8_map(shape, input, parameters, output, accumulate);
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
        assert_code_lengths(shape, input, (weight, weight_scales, bias), output.len());
        let parameters = (weight, weight_scales, bias);
        conv_int8_map(shape, input, parameters, output, accumulate);
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
        assert_byte_lengths(shape, input, (weight, weight_scales, bias), output.len());
        conv_int8_bytes(
            shape,
            input,
            (weight, weight_scales, bias),
            output,
            accumulate,
        );
    }

    /// The reference reads whole bytes.
    fn narrow_form(&self) -> NarrowForm {
        NarrowForm::Bytes
    }
}
