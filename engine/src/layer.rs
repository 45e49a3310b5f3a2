//! One layer of the model with whichever weights the file holds: f32 weights go to the f32
//! kernels, int8 weights have their input quantized first (the trunk's to digit planes, or
//! to bytes where the file chose 8-bit codes; the U-Net's to whole codes, or to signed
//! bytes where the file chose 8-bit codes) and go to the integer kernels. The bridge between the weights
//! file's types and the kernels, which know neither the file nor the model.

use crate::kernels::{Accumulate, ConvShape, DigitRows, Kernels, QuantizeScratch, TrunkCodes};
use crate::weights::{ActivationCodes, MAX_REFINED_CHANNELS, Residual, Weight};

/// How a layer with int8 weights reads 15-bit codes of its input (one scale for the whole
/// input either way; the trunk's 8-bit layers are the pyramid's, [`convolve_codes`]).
#[derive(Debug)]
pub enum Activations<'s, 'a> {
    /// Two digit planes for unsigned-by-signed byte dot products: the trunk, whose inputs
    /// are ReLU outputs.
    Digits(&'s mut QuantizeScratch<'a>),
    /// Whole signed codes for 16-bit dot products (signed bytes where the file chose 8-bit
    /// codes): the U-Net, whose inputs have both signs.
    Codes(&'s mut QuantizeScratch<'a>),
}

/// What a refined layer's residual plane adds to the first plane's output (its bias is
/// already there).
static ZERO_BIAS: [f32; MAX_REFINED_CHANNELS] = [0.0; MAX_REFINED_CHANNELS];

/// One int8 weight plane of a layer: its values (and their pair layout where the file holds
/// it), scales, the bias it adds and how it writes the output.
pub type Plane<'p> = (
    (&'p [i8], Option<&'p [i8]>),
    &'p [f32],
    &'p [f32],
    Accumulate,
);

/// The int8 planes of a layer, run one after the other on the same input codes: the
/// weights with the layer's bias and `accumulate`, then a refined layer's residual plane
/// added without bias (the loader bounds its channels by [`MAX_REFINED_CHANNELS`]).
pub fn planes<'p>(
    (values, pairs, scales): (&'p [i8], Option<&'p [i8]>, &'p [f32]),
    residual: Option<Residual<'p>>,
    bias: &'p [f32],
    accumulate: Accumulate,
) -> impl Iterator<Item = Plane<'p>> {
    let residual = residual.map(|residual| {
        let zero = &ZERO_BIAS[..bias.len()];
        let values = (residual.values, residual.pairs);
        (values, residual.scales, zero, Accumulate::Add)
    });
    core::iter::once(((values, pairs), scales, bias, accumulate)).chain(residual)
}

/// A convolution with whichever weights the file holds.
#[allow(clippy::too_many_arguments)]
pub fn convolve(
    kernels: &dyn Kernels,
    shape: &ConvShape,
    input: &[f32],
    weight: &Weight<'_>,
    bias: &[f32],
    output: &mut [f32],
    accumulate: Accumulate,
    activations: Activations<'_, '_>,
) {
    let input = &input[..shape.input_len()];
    let output = &mut output[..shape.output_len()];
    let (values, pairs, scales, codes, residual) = match *weight {
        Weight::F32(values) => return kernels.conv(shape, input, values, bias, output, accumulate),
        Weight::Int8 {
            values,
            scales,
            activations,
            residual,
            pairs,
        } => (values, pairs, scales, activations, residual),
    };
    let planes = planes((values, pairs, scales), residual, bias, accumulate);
    match (codes, activations) {
        (_, Activations::Digits(scratch)) => {
            let digits = scratch.quantize(kernels, input);
            for ((values, _), scales, bias, accumulate) in planes {
                kernels.conv_int8(shape, &digits, values, scales, bias, output, accumulate)
            }
        }
        (ActivationCodes::Narrow, Activations::Codes(scratch)) => {
            let channels = shape.in_channels;
            if kernels.multiplies_signed_bytes() {
                let codes = scratch.quantize_signed_bytes(kernels, input, channels);
                for ((values, pairs), scales, bias, accumulate) in planes {
                    match pairs {
                        Some(pairs) => kernels.conv_int8_signed_bytes_paired(
                            shape, &codes, values, pairs, scales, bias, output, accumulate,
                        ),
                        None => kernels.conv_int8_signed_bytes(
                            shape, &codes, values, scales, bias, output, accumulate,
                        ),
                    }
                }
            } else {
                let codes = scratch.quantize_narrow_codes(kernels, input, channels);
                for ((values, _), scales, bias, accumulate) in planes {
                    kernels.conv_int8_codes(shape, &codes, values, scales, bias, output, accumulate)
                }
            }
        }
        (ActivationCodes::Wide, Activations::Codes(scratch)) => {
            let codes = scratch.quantize_codes(kernels, input, shape.in_channels);
            for ((values, _), scales, bias, accumulate) in planes {
                kernels.conv_int8_codes(shape, &codes, values, scales, bias, output, accumulate)
            }
        }
    }
}

/// Keeps a layer's input for later [`convolve_pixels`] calls, in the form its weights
/// read: copied for f32 weights; quantized for int8 weights, the two digit planes as bytes
/// at the front of `values`. Returns the input's scale (1 for f32 weights, unused) and
/// whether every code is nonnegative (true for f32 weights).
pub fn store_input(
    kernels: &dyn Kernels,
    weight: &Weight<'_>,
    input: &[f32],
    values: &mut [f32],
) -> (f32, bool) {
    match weight {
        Weight::F32(_) => {
            values[..input.len()].copy_from_slice(input);
            (1.0, true)
        }
        Weight::Int8 { .. } => {
            let bytes: &mut [i8] = bytemuck::cast_slice_mut(values);
            let (high, low) = bytes[..2 * input.len()].split_at_mut(input.len());
            kernels.quantize_digits(input, (high, low))
        }
    }
}

/// Output pixels `pixels` of [`convolve`] with [`Accumulate::Overwrite`], into their places
/// in `output` (the whole map), from an input kept by [`store_input`] (`values` and the
/// scale and sign flag it returned).
pub fn convolve_pixels(
    kernels: &dyn Kernels,
    shape: &ConvShape,
    (values, scale, nonnegative): (&[f32], f32, bool),
    (weight, bias): (&Weight<'_>, &[f32]),
    pixels: &[(usize, usize)],
    output: &mut [f32],
) {
    match *weight {
        Weight::F32(weights) => {
            let input = &values[..shape.input_len()];
            kernels.conv_pixels(shape, input, weights, bias, pixels, output)
        }
        Weight::Int8 {
            values: weights,
            scales: weight_scales,
            ..
        } => {
            let values: &[i8] = &bytemuck::cast_slice(values)[..2 * shape.input_len()];
            let digits = DigitRows::from_planes(values, scale, nonnegative);
            kernels.conv_int8_pixels(shape, &digits, weights, weight_scales, bias, pixels, output)
        }
    }
}

/// An int8 trunk convolution on its input's codes, in whichever form they were quantized
/// to, one weight plane after the other ([`planes`]).
pub fn convolve_codes<'p>(
    kernels: &dyn Kernels,
    shape: &ConvShape,
    codes: &TrunkCodes<'_>,
    planes: impl Iterator<Item = Plane<'p>>,
    output: &mut [f32],
) {
    for ((weight, pairs), weight_scales, bias, accumulate) in planes {
        match (codes, pairs) {
            (TrunkCodes::Digits(digits), _) => kernels.conv_int8(
                shape,
                digits,
                weight,
                weight_scales,
                bias,
                output,
                accumulate,
            ),
            (TrunkCodes::Bytes(bytes), Some(pairs)) => kernels.conv_int8_bytes_paired(
                shape,
                bytes,
                weight,
                pairs,
                weight_scales,
                bias,
                output,
                accumulate,
            ),
            (TrunkCodes::Bytes(bytes), None) => kernels.conv_int8_bytes(
                shape,
                bytes,
                weight,
                weight_scales,
                bias,
                output,
                accumulate,
            ),
        }
    }
}
