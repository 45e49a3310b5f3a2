//! Frame -> feature pyramid: the ResNet-18 trunk's taps C1..C5 and their 3x3 projections
//! F1..F5 (docs/SPEC.md section 2), once per frame.

use crate::config::{ModelConfig, PYRAMID_LEVELS, STEM_KERNEL, STEM_PADDING, STEM_STRIDE};
use crate::frame::{self, PATCH_CHANNELS};
use crate::kernels::ops::{self, Activation};
use crate::kernels::{
    Accumulate, ByteRows, ConvShape, DigitRows, Kernels, QuantizeScratch, Quantized, TrunkCodes,
};
use crate::layer::{self, Activations};
use crate::plan::FrameLayout;
use crate::shape::gcd;
use crate::weights::{ActivationCodes, Conv, ConvNorm, PyramidWeights, Weight};

/// Four activation buffers the residual blocks rotate through; the first holds the image
/// (normalized, or its padded bytes for an int8 stem).
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
    scratch: &mut QuantizeScratch<'_>,
) {
    let mut input = LayerInput::new(&input[..shape.input_len()], None, scratch);
    input.conv_norm(kernels, layer, shape, output, activation);
}

fn is_int8(conv: &Conv<'_>) -> bool {
    matches!(conv.weight, Weight::Int8 { .. })
}

/// A trunk map as the layers reading it take it: the values, and for int8 weights their
/// codes, quantized once for all the readers that take the same codes (a block's first
/// convolution and its downsampling and, at a stage's start, the level's projection) and
/// again only when a reader takes the other width.
struct LayerInput<'v, 's, 'a> {
    values: &'v [f32],
    /// The wide digits an on-demand level keeps in the frame for its projection.
    kept: Option<DigitRows<'v>>,
    scratch: &'s mut QuantizeScratch<'a>,
    /// What `scratch` holds of this input, at which width.
    quantized: Option<(ActivationCodes, Quantized)>,
}

impl<'v, 's, 'a> LayerInput<'v, 's, 'a> {
    fn new(
        values: &'v [f32],
        kept: Option<DigitRows<'v>>,
        scratch: &'s mut QuantizeScratch<'a>,
    ) -> Self {
        LayerInput {
            values,
            kept,
            scratch,
            quantized: None,
        }
    }

    /// This input quantized to `width`.
    fn codes(&mut self, kernels: &dyn Kernels, width: ActivationCodes) -> TrunkCodes<'_> {
        if let (ActivationCodes::Wide, Some(kept)) = (width, self.kept) {
            return TrunkCodes::Digits(kept);
        }
        let quantized = match self.quantized {
            Some((held, quantized)) if held == width => quantized,
            _ => {
                let quantized = match width {
                    ActivationCodes::Wide => self.scratch.quantize_wide(kernels, self.values),
                    ActivationCodes::Narrow => self.scratch.quantize_narrow(kernels, self.values),
                };
                self.quantized = Some((width, quantized));
                quantized
            }
        };
        self.scratch.view(&quantized)
    }

    /// [`conv_norm`] on this input.
    fn conv_norm(
        &mut self,
        kernels: &dyn Kernels,
        layer: &ConvNorm<'_>,
        shape: &ConvShape,
        output: &mut [f32],
        activation: Activation,
    ) {
        let output = &mut output[..shape.output_len()];
        self.convolve(kernels, &layer.conv, shape, output);
        normalize(kernels, layer, shape, output, activation);
    }

    /// The convolution of `conv` on this input, overwriting `output`.
    fn convolve(
        &mut self,
        kernels: &dyn Kernels,
        conv: &Conv<'_>,
        shape: &ConvShape,
        output: &mut [f32],
    ) {
        let output = &mut output[..shape.output_len()];
        let overwrite = Accumulate::Overwrite;
        match conv.weight {
            Weight::Int8 {
                values,
                scales,
                activations,
                residual,
                pairs,
            } => {
                let codes = self.codes(kernels, activations);
                let weights = (values, pairs, scales);
                let planes = layer::planes(weights, residual, conv.bias, overwrite);
                layer::convolve_codes(kernels, shape, &codes, planes, output)
            }
            Weight::F32(values) => {
                let input = &self.values[..shape.input_len()];
                kernels.conv(shape, input, values, conv.bias, output, overwrite)
            }
        }
    }
}

/// The norm and activation of [`conv_norm`], on the convolution's output in `output`.
fn normalize(
    kernels: &dyn Kernels,
    layer: &ConvNorm<'_>,
    shape: &ConvShape,
    output: &mut [f32],
    activation: Activation,
) {
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

/// Cells of an on-demand projection computed together: an inference step's anchors sample
/// at most `anchor_count x 4` cells of a level (36 for the product models).
const CELL_BATCH: usize = 48;

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
    /// The scale of `taps` when int8 and whether they are all nonnegative (1 or 0), as
    /// [`layer::store_input`] returned them (empty for a dense level).
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
            tap_scale: &mut self.tap_scales[2 * level..][..2],
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
        let shape = projection_shape(config, level);
        let input = (&*store.taps, store.tap_scale[0], store.tap_scale[1] == 1.0);
        let projection = (&projection.weight, projection.bias);
        // The cells not computed yet, each once, a batch at a time: the kernels take several
        // pixels in one pass over the projection's weights.
        let mut batch = heapless::Vec::<(usize, usize), CELL_BATCH>::new();
        for (row, column) in cells {
            if row >= height || column >= width {
                continue;
            }
            let cell = row * width + column;
            let (word, bit) = (cell / 32, 1u32 << (cell % 32));
            if store.computed[word] & bit != 0 {
                continue;
            }
            store.computed[word] |= bit;
            if batch.is_full() {
                layer::convolve_pixels(kernels, &shape, input, projection, &batch, store.map);
                batch.clear();
            }
            // Room was made just above.
            let _ = batch.push((row, column));
        }
        if !batch.is_empty() {
            layer::convolve_pixels(kernels, &shape, input, projection, &batch, store.map);
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

/// The stem's convolution, norm, ReLU and max pool: `image` (RGB bytes) -> `pooled`, the
/// first pyramid level's input. `map` takes the convolution's output at the stem's size.
///
/// With int8 weights and no ImageNet normalization the image bytes are the input codes
/// exactly (scale `1 / 255`): the stem runs as a 1x1 int8 convolution over its patches
/// ([`frame::PATCH_CHANNELS`] bytes a pixel, [`Kernels::conv_int8_bytes`]: the matrix
/// tiles multiply whole bytes), a band of output rows at a time in the quantization
/// buffer, so its 7x7 kernel over three channels reads 49 quads in one run instead of one
/// quad a tap. It gives exactly what the 7x7 int8 convolution gives on the
/// same codes. There the GroupNorm's moments are taken band by band, while each band is in
/// the caches, and the normalization is applied inside the max pool, so the full-size map
/// (4.9 MB for panda) is written once and read once; the bits are those of GroupNorm then
/// pooling. Otherwise the image is normalized to f32 in `pooled` and convolved as any layer.
///
/// # Panics
/// If a buffer is shorter than the arena plan makes it (the policy's never are).
pub fn stem(
    kernels: &dyn Kernels,
    config: &ModelConfig,
    layer: &ConvNorm<'_>,
    image: &[u8],
    (pooled, map): (&mut [f32], &mut [f32]),
    quantized: &mut QuantizeScratch<'_>,
) {
    let image_shape = (config.image_height as usize, config.image_width as usize, 3);
    let channels = config.stage_channels(0);
    let shape = ConvShape::square(
        image_shape,
        channels,
        STEM_KERNEL,
        STEM_STRIDE,
        STEM_PADDING,
    );
    let (out_height, out_width) = (shape.out_height(), shape.out_width());
    let map_shape = (out_height, out_width, channels);
    let (pooled_height, pooled_width) = config.pyramid_size(0);
    let pooled_len = pooled_height * pooled_width * channels;
    let (values, scales) = match layer.conv.weight {
        Weight::Int8 { values, scales, .. } if !config.imagenet_norm => (values, scales),
        _ => {
            frame::normalize(config, image, pooled);
            let activation = Activation::Relu;
            conv_norm(kernels, layer, &shape, pooled, map, activation, quantized);
            let map = &map[..shape.output_len()];
            kernels.max_pool_3x3_stride_2(map, map_shape, &mut pooled[..pooled_len]);
            return;
        }
    };
    // The moments of a GroupNorm that `group_scale_shift` reproduces (the stem's 64).
    const MOMENT_CHANNELS: usize = ops::GROUP_NORM_CHUNK;
    let mut sums = [0.0f64; MOMENT_CHANNELS];
    let mut squares = [0.0f64; MOMENT_CHANNELS];
    // The plan makes room for at least one row of patches.
    let fitting = (quantized.values.len() / (out_width * PATCH_CHANNELS)).clamp(1, out_height);
    // The moments taken band by band are GroupNorm's when every band but the last holds
    // whole blocks of pixels; where the buffer holds too few rows for that, the map is
    // normalized whole after the convolution.
    let block_rows = ops::MOMENT_BLOCK / gcd(out_width, ops::MOMENT_BLOCK);
    let whole_block_rows = if fitting < out_height {
        fitting - fitting % block_rows
    } else {
        fitting
    };
    let banded_moments = whole_block_rows > 0;
    let band_rows = if banded_moments {
        whole_block_rows
    } else {
        fitting
    };
    let norm = layer
        .norm
        .as_ref()
        .filter(|_| channels <= MOMENT_CHANNELS && banded_moments);
    let padded = frame::pad_image(config, image, bytemuck::cast_slice_mut(pooled));
    for first_row in (0..out_height).step_by(band_rows) {
        let rows = band_rows.min(out_height - first_row);
        let band = ConvShape::square((rows, out_width, PATCH_CHANNELS), channels, 1, 1, 0);
        let patches: &mut [u8] =
            bytemuck::cast_slice_mut(&mut quantized.values[..band.input_len()]);
        frame::patch_rows(config, padded, first_row..first_row + rows, patches);
        let bytes = ByteRows {
            bytes: patches,
            scale: 1.0 / 255.0,
        };
        let output = &mut map[first_row * out_width * channels..][..band.output_len()];
        kernels.conv_int8_bytes(
            &band,
            &bytes,
            values,
            scales,
            layer.conv.bias,
            output,
            Accumulate::Overwrite,
        );
        if norm.is_some() {
            let moments = (&mut sums[..channels], &mut squares[..channels]);
            kernels.add_channel_moments(output, channels, moments);
        }
    }
    let map = &mut map[..shape.output_len()];
    let pooled = &mut pooled[..pooled_len];
    match norm {
        Some(norm) => {
            let mut scale = [0.0f32; MOMENT_CHANNELS];
            let mut shift = [0.0f32; MOMENT_CHANNELS];
            ops::group_scale_shift(
                (&sums[..channels], &squares[..channels]),
                out_height * out_width,
                ModelConfig::backbone_groups(channels),
                (norm.gamma, norm.beta),
                (&mut scale[..channels], &mut shift[..channels]),
            );
            let affine = (&scale[..channels], &shift[..channels]);
            kernels.normalize_max_pool(map, map_shape, affine, Activation::Relu, pooled, 0);
        }
        None => {
            normalize(kernels, layer, &shape, map, Activation::Relu);
            kernels.max_pool_3x3_stride_2(map, map_shape, pooled);
        }
    }
}

/// Encodes `image` (RGB bytes of the config's size) into `frame`: the five projected maps,
/// except that a level projected on demand keeps its input instead.
pub fn encode(
    kernels: &dyn Kernels,
    config: &ModelConfig,
    weights: &PyramidWeights<'_>,
    image: &[u8],
    mut scratch: TrunkScratch<'_>,
    frame: &mut FrameStore<'_>,
) {
    let stem_channels = config.stage_channels(0);
    stem(
        kernels,
        config,
        &weights.stem,
        image,
        (&mut *scratch.first, &mut *scratch.rest),
        &mut scratch.quantized,
    );
    let (height, width) = config.pyramid_size(0);

    let (second, rest) = scratch.rest.split_at_mut(scratch.activation_len);
    let (third, fourth) = rest.split_at_mut(scratch.activation_len);
    let mut buffers: [&mut [f32]; 4] = [
        scratch.first,
        second,
        third,
        &mut fourth[..scratch.activation_len],
    ];

    let mut quantized = scratch.quantized;
    let (mut height, mut width) = (height, width);
    let mut channels = stem_channels;
    for (stage, blocks) in weights.stages.iter().enumerate() {
        let out_channels = config.stage_channels(stage);
        for (index, block) in blocks.iter().enumerate() {
            let stride = if block.downsample.is_some() { 2 } else { 1 };
            let first_shape =
                ConvShape::square((height, width, channels), out_channels, 3, stride, 1);
            let (out_height, out_width) = (first_shape.out_height(), first_shape.out_width());
            let second_shape =
                ConvShape::square((out_height, out_width, out_channels), out_channels, 3, 1, 1);
            let downsample_shape =
                ConvShape::square((height, width, channels), out_channels, 1, 2, 0);
            let [input, middle, output, shortcut] = &mut buffers;
            let values = &input[..first_shape.input_len()];
            // The layers reading the block's input: its first convolution, its downsampling
            // and, at a stage's start, the projection of the level it is the tap of.
            let level = (index == 0).then_some(stage);
            // An on-demand level keeps its input in the frame (quantized, for int8 weights)
            // and the block's wide layers read those digits; a dense level is projected
            // from the codes quantized here for every reader.
            let mut dense_map = None;
            let mut kept = None;
            if let Some(level) = level {
                let projection = &weights.projections[level];
                let LevelStore {
                    map,
                    taps,
                    tap_scale,
                    computed,
                } = frame.level(config, level);
                if config.projection_on_demand(level) {
                    let (scale, nonnegative) =
                        layer::store_input(kernels, &projection.weight, values, taps);
                    tap_scale[0] = scale;
                    tap_scale[1] = f32::from(u8::from(nonnegative));
                    computed.fill(0);
                    if is_int8(projection) {
                        let bytes: &[i8] = bytemuck::cast_slice(&*taps);
                        let planes = &bytes[..2 * values.len()];
                        kept = Some(DigitRows::from_planes(planes, scale, nonnegative));
                    }
                } else {
                    dense_map = Some((level, projection, map));
                }
            }
            let mut shared = LayerInput::new(values, kept, &mut quantized);
            if let Some((level, projection, map)) = dense_map {
                let shape = projection_shape(config, level);
                shared.convolve(kernels, projection, &shape, map);
            }
            shared.conv_norm(
                kernels,
                &block.first,
                &first_shape,
                middle,
                Activation::Relu,
            );
            if let Some(downsample) = &block.downsample {
                shared.conv_norm(
                    kernels,
                    downsample,
                    &downsample_shape,
                    shortcut,
                    Activation::None,
                );
            }
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
                Some(_) => &shortcut[..output_len],
                None => &input[..output_len],
            };
            kernels.add_activate(&mut output[..output_len], identity, Activation::Relu);
            // The block's output becomes the next block's input.
            buffers.swap(0, 2);
            (height, width, channels) = (out_height, out_width, out_channels);
        }
    }
    // The last tap has no block after it.
    let level = PYRAMID_LEVELS - 1;
    let shape = projection_shape(config, level);
    let projection = &weights.projections[level];
    let store = frame.level(config, level);
    let values = &buffers[0][..shape.input_len()];
    if config.projection_on_demand(level) {
        let (scale, nonnegative) =
            layer::store_input(kernels, &projection.weight, values, store.taps);
        store.tap_scale[0] = scale;
        store.tap_scale[1] = f32::from(u8::from(nonnegative));
        store.computed.fill(0);
    } else {
        layer::convolve(
            kernels,
            &shape,
            values,
            &projection.weight,
            projection.bias,
            store.map,
            Accumulate::Overwrite,
            Activations::Digits(&mut quantized),
        );
    }
}
