//! Frame -> feature pyramid: the ResNet-18 trunk's taps C1..C5 and their 3x3 projections
//! F1..F5 (SPEC section 2), once per frame.

use crate::config::ModelConfig;
use crate::kernels::ops::{self, Activation};
use crate::kernels::{self, Accumulate, Activations, ConvShape, Kernels, QuantizeScratch};
use crate::plan::FrameLayout;
use crate::weights::{Conv, ConvNorm, PyramidWeights};

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
        Activations::Digits(quantized),
    );
    let output = &mut output[..shape.output_len()];
    match &layer.norm {
        Some(norm) => kernels.group_norm(
            output,
            shape.out_channels,
            ModelConfig::backbone_groups(shape.out_channels),
            (norm.gamma, norm.beta),
            activation,
        ),
        None => ops::activate_all(output, activation),
    }
}

/// One history frame's persistent buffers, as [`FrameLayout`] lays them out.
pub struct FrameStore<'a> {
    pub maps: &'a mut [f32],
    pub taps: &'a mut [f32],
    pub tap_scales: &'a mut [f32],
    pub computed: &'a mut [u32],
}

/// One level's part of a [`FrameStore`]; the last three are empty for a dense level.
struct LevelStore<'s> {
    map: &'s mut [f32],
    taps: &'s mut [f32],
    /// The scale of `taps` when int8 (empty for a dense level).
    tap_scale: &'s mut [f32],
    computed: &'s mut [u32],
}

impl<'a> FrameStore<'a> {
    /// Splits one frame's region of the arena.
    pub fn new(region: &'a mut [f32], layout: &FrameLayout) -> Self {
        let (maps, rest) = region.split_at_mut(layout.maps);
        let (taps, rest) = rest.split_at_mut(layout.taps);
        let (tap_scales, rest) = rest.split_at_mut(layout.tap_scales);
        let computed = &mut rest[..layout.computed];
        FrameStore {
            maps,
            taps,
            tap_scales,
            computed: bytemuck::cast_slice_mut(computed),
        }
    }

    fn level(&mut self, config: &ModelConfig, level: usize) -> LevelStore<'_> {
        let (map_at, tap_at, word_at) = level_offsets(config, level);
        let feature_dim = config.feature_dim as usize;
        let (height, width) = config.pyramid_size(level);
        let cells = height * width;
        let map = &mut self.maps[map_at..][..cells * feature_dim];
        if !config.projection_on_demand(level) {
            return LevelStore {
                map,
                taps: &mut [],
                tap_scale: &mut [],
                computed: &mut [],
            };
        }
        LevelStore {
            map,
            taps: &mut self.taps[tap_at..][..cells * config.pyramid_channels(level)],
            tap_scale: &mut self.tap_scales[level..][..1],
            computed: &mut self.computed[word_at..][..cells.div_ceil(32)],
        }
    }

    /// Projected map F(level + 1), `[H_n, W_n, d]`; for an on-demand level only the cells
    /// computed so far are meaningful (see [`complete`](Self::complete)).
    pub fn map(&mut self, config: &ModelConfig, level: usize) -> &[f32] {
        self.level(config, level).map
    }

    /// [`map`](Self::map), keeping the arena's lifetime.
    pub fn into_map(self, config: &ModelConfig, level: usize) -> &'a [f32] {
        let (map_at, ..) = level_offsets(config, level);
        let (height, width) = config.pyramid_size(level);
        &self.maps[map_at..][..height * width * config.feature_dim as usize]
    }

    /// Makes sure the cells `(row, column)` of on-demand level `level` are computed.
    pub fn ensure_cells(
        &mut self,
        kernels: &dyn Kernels,
        config: &ModelConfig,
        projection: &Conv<'_>,
        level: usize,
        cells: impl Iterator<Item = (usize, usize)>,
    ) {
        if !config.projection_on_demand(level) {
            return;
        }
        let store = self.level(config, level);
        let (height, width) = config.pyramid_size(level);
        let feature_dim = config.feature_dim as usize;
        let shape = projection_shape(config, level);
        for (row, column) in cells {
            if row >= height || column >= width {
                continue;
            }
            let cell = row * width + column;
            let (word, bit) = (cell / 32, 1u32 << (cell % 32));
            if store.computed[word] & bit != 0 {
                continue;
            }
            kernels::convolve_pixel(
                kernels,
                &shape,
                (store.taps, store.tap_scale[0]),
                (&projection.weight, projection.bias),
                (row, column),
                &mut store.map[cell * feature_dim..][..feature_dim],
            );
            store.computed[word] |= bit;
        }
    }

    /// Computes every cell of `level` not computed yet: the map is then what a dense
    /// projection gives.
    pub fn complete(
        &mut self,
        kernels: &dyn Kernels,
        config: &ModelConfig,
        projection: &Conv<'_>,
        level: usize,
    ) {
        let (height, width) = config.pyramid_size(level);
        let cells = (0..height).flat_map(|row| (0..width).map(move |column| (row, column)));
        self.ensure_cells(kernels, config, projection, level, cells);
    }
}

/// Where `level` starts in each part of a [`FrameStore`]: map values, tap values and
/// computed-bit words (the tap scales are one per level).
fn level_offsets(config: &ModelConfig, level: usize) -> (usize, usize, usize) {
    let (mut map_at, mut tap_at, mut word_at) = (0, 0, 0);
    for before in 0..level {
        let (height, width) = config.pyramid_size(before);
        map_at += height * width * config.feature_dim as usize;
        if config.projection_on_demand(before) {
            tap_at += height * width * config.pyramid_channels(before);
            word_at += (height * width).div_ceil(32);
        }
    }
    (map_at, tap_at, word_at)
}

/// The 3x3 projection of tap C(level + 1) to `feature_dim` channels.
fn projection_shape(config: &ModelConfig, level: usize) -> ConvShape {
    let (height, width) = config.pyramid_size(level);
    ConvShape::square(
        (height, width, config.pyramid_channels(level)),
        config.feature_dim as usize,
        3,
        1,
        1,
    )
}

/// Encodes a preprocessed image (already in `scratch.first`) into `frame`: the five
/// projected maps, except that a level projected on demand keeps its input instead.
pub fn encode(
    kernels: &dyn Kernels,
    config: &ModelConfig,
    weights: &PyramidWeights<'_>,
    mut scratch: TrunkScratch<'_>,
    frame: &mut FrameStore<'_>,
) {
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
    // Projects tap C(level + 1), or keeps it for on-demand projection.
    let mut project = |level: usize, input: &[f32], quantized: &mut QuantizeScratch<'_>| {
        let shape = projection_shape(config, level);
        let projection = &weights.projections[level];
        let store = frame.level(config, level);
        if config.projection_on_demand(level) {
            store.tap_scale[0] = kernels::store_input(
                kernels,
                &projection.weight,
                &input[..shape.input_len()],
                store.taps,
            );
            store.computed.fill(0);
        } else {
            kernels::convolve(
                kernels,
                &shape,
                input,
                &projection.weight,
                projection.bias,
                store.map,
                Accumulate::Overwrite,
                Activations::Digits(quantized),
            );
        }
    };
    project(0, buffers[0], &mut quantized);

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
            kernels.add_activate(&mut output[..output_len], identity, Activation::Relu);
            // The block's output becomes the next block's input.
            buffers.swap(0, 2);
            (height, width, channels) = (out_height, out_width, out_channels);
        }
        project(stage + 1, buffers[0], &mut quantized);
    }
}
