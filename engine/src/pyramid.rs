//! Frame -> feature pyramid: the ResNet-18 trunk's taps C1..C5 and their 3x3 projections
//! F1..F5 (SPEC section 2), once per frame.

use crate::config::ModelConfig;
use crate::kernels::ops::{self, Activation};
use crate::kernels::{self, Accumulate, Activations, ConvShape, Kernels, QuantizeScratch};
use crate::weights::{ConvNorm, PyramidWeights};

/// Four activation buffers the residual blocks rotate through; the first holds the image.
pub struct TrunkScratch<'a> {
    pub first: &'a mut [f32],
    /// The stem's output lives here first; afterwards it is split into the other three.
    pub rest: &'a mut [f32],
    pub activation_len: usize,
    /// Int8 copy of a layer's input, for int8 weights.
    pub quantized: QuantizeScratch<'a>,
}

/// Convolution, then norm (GroupNorm when the trunk has one; BatchNorm is already folded)
/// and `activation`, in place in `output`.
fn conv_norm(
    kernels: &dyn Kernels,
    layer: &ConvNorm<'_>,
    shape: &ConvShape,
    input: &[f32],
    output: &mut [f32],
    activation: Activation,
    quantized: &mut QuantizeScratch<'_>,
) {
    kernels::convolve(
        kernels,
        shape,
        input,
        &layer.conv.weight,
        layer.conv.bias,
        output,
        Accumulate::Overwrite,
        Activations::Int8(quantized),
    );
    let output = &mut output[..shape.output_len()];
    match &layer.norm {
        Some(norm) => ops::group_norm(
            output,
            shape.out_channels,
            ModelConfig::backbone_groups(shape.out_channels),
            norm.gamma,
            norm.beta,
            activation,
        ),
        None => ops::activate_all(output, activation),
    }
}

/// Encodes a preprocessed image (already in `scratch.first`) into `features`, the five
/// projected maps `[H_n, W_n, d]` back to back.
pub fn encode(
    kernels: &dyn Kernels,
    config: &ModelConfig,
    weights: &PyramidWeights<'_>,
    mut scratch: TrunkScratch<'_>,
    features: &mut [f32],
) {
    let feature_dim = config.feature_dim as usize;
    let stem_channels = config.stage_channels(0);
    let image = (config.image_height as usize, config.image_width as usize, 3);
    let stem_shape = ConvShape::square(image, stem_channels, 7, 2, 3);
    let (stem_height, stem_width) = config.stem_size();
    conv_norm(
        kernels,
        &weights.stem,
        &stem_shape,
        scratch.first,
        scratch.rest,
        Activation::Relu,
        &mut scratch.quantized,
    );
    let (height, width) = config.pyramid_size(0);
    ops::max_pool_3x3_stride_2(
        &scratch.rest[..stem_height * stem_width * stem_channels],
        (stem_height, stem_width, stem_channels),
        &mut scratch.first[..height * width * stem_channels],
    );

    let (second, rest) = scratch.rest.split_at_mut(scratch.activation_len);
    let (third, fourth) = rest.split_at_mut(scratch.activation_len);
    let mut buffers: [&mut [f32]; 4] = [
        scratch.first,
        second,
        third,
        &mut fourth[..scratch.activation_len],
    ];

    let mut quantized = scratch.quantized;
    let mut feature_maps = features;
    // Projects tap C(level + 1) into the next map of `feature_maps`.
    let project = |level: usize,
                   input: &[f32],
                   maps: &mut &mut [f32],
                   quantized: &mut QuantizeScratch<'_>| {
        let (height, width) = config.pyramid_size(level);
        let shape = ConvShape::square(
            (height, width, config.pyramid_channels(level)),
            feature_dim,
            3,
            1,
            1,
        );
        let (map, rest) = core::mem::take(maps).split_at_mut(shape.output_len());
        let projection = &weights.projections[level];
        kernels::convolve(
            kernels,
            &shape,
            input,
            &projection.weight,
            projection.bias,
            map,
            Accumulate::Overwrite,
            Activations::Int8(quantized),
        );
        *maps = rest;
    };
    project(0, buffers[0], &mut feature_maps, &mut quantized);

    let (mut height, mut width) = (height, width);
    let mut channels = stem_channels;
    for (stage, blocks) in weights.stages.iter().enumerate() {
        let out_channels = config.stage_channels(stage);
        for block in blocks {
            let stride = if block.downsample.is_some() { 2 } else { 1 };
            let first_shape =
                ConvShape::square((height, width, channels), out_channels, 3, stride, 1);
            let (out_height, out_width) = (first_shape.out_height(), first_shape.out_width());
            let second_shape =
                ConvShape::square((out_height, out_width, out_channels), out_channels, 3, 1, 1);
            let [input, middle, output, shortcut] = &mut buffers;
            conv_norm(
                kernels,
                &block.first,
                &first_shape,
                input,
                middle,
                Activation::Relu,
                &mut quantized,
            );
            conv_norm(
                kernels,
                &block.second,
                &second_shape,
                middle,
                output,
                Activation::None,
                &mut quantized,
            );
            let output_len = second_shape.output_len();
            let identity: &[f32] = match &block.downsample {
                Some(downsample) => {
                    let shape = ConvShape::square((height, width, channels), out_channels, 1, 2, 0);
                    conv_norm(
                        kernels,
                        downsample,
                        &shape,
                        input,
                        shortcut,
                        Activation::None,
                        &mut quantized,
                    );
                    &shortcut[..output_len]
                }
                None => &input[..output_len],
            };
            ops::add_activate(&mut output[..output_len], identity, Activation::Relu);
            // The block's output becomes the next block's input.
            buffers.swap(0, 2);
            (height, width, channels) = (out_height, out_width, out_channels);
        }
        project(stage + 1, buffers[0], &mut feature_maps, &mut quantized);
    }
}
