//! The model's tensors, bound by name and shape to a [`WeightsFile`] (or to anything else
//! implementing [`TensorSource`], which is how the weights tool learns what to write).
//!
//! The order in which [`ModelWeights::bind`] asks for tensors *is* the layout of the weights
//! file: the tool records it and writes the tensors in that order, the engine reads them back
//! in that order and checks every name and shape.
//!
//! Layouts are the engine's, not PyTorch's (the tool packs them offline):
//! - 2-D convolutions: `[kh, kw, in, out]`, feature maps `[H, W, C]`;
//! - 1-D convolutions: `[k, in, out]`, sequences `[T, C]`; the transposed convolutions
//!   lowered to ordinary ones of 2 taps and twice the output channels;
//! - FiLM: the global-condition part of the linear layer `[2 out, global_cond_dim]`, and the
//!   time-embedding part with the bias folded in, precomputed per inference step `[steps, 2 out]`;
//! - BatchNorm does not appear: it is folded into the convolution before it.

use core::fmt::{self, Write};

use crate::config::{BackboneNorm, ModelConfig, PYRAMID_LEVELS, UNET_LEVELS};
use crate::error::Error;
use crate::format::{DType, Quant, TensorEntry, WeightsFile};

/// Anything that can hand out the model's tensors in order.
pub trait TensorSource<'w> {
    /// The next tensor, which must be called `name` and have exactly `dims`.
    fn f32_tensor(&mut self, name: fmt::Arguments<'_>, dims: &[usize]) -> Result<&'w [f32], Error>;

    /// The next weight matrix or kernel called `name` with `dims`: f32, or int8 followed by
    /// its `channels` per-channel scales called `scale_name`. The weights tool chooses, and
    /// for an int8 layer that `narrow` allows ([`ActivationCodes::Narrow`]) also the codes
    /// its input is quantized to.
    fn weight(
        &mut self,
        name: fmt::Arguments<'_>,
        scale_name: fmt::Arguments<'_>,
        dims: &[usize],
        channels: usize,
        narrow: NarrowCodes,
    ) -> Result<Weight<'w>, Error>;
}

/// Whether a layer can take [`ActivationCodes::Narrow`]: the residual blocks'
/// convolutions, the trunk's (whose inputs are ReLU outputs in one map) and the U-Net's
/// (whose inputs are one sequence, signed).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NarrowCodes {
    Allowed,
    NotAllowed,
}

/// The codes an int8 layer quantizes its input to (one scale for the whole input either
/// way; docs/QUANTIZATION.md).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ActivationCodes {
    /// 15-bit codes: two digit planes in the trunk, whole i16 codes in the U-Net and FiLM.
    Wide,
    /// 8-bit codes, one byte a value: unsigned in the trunk, whose inputs are nonnegative
    /// (`scale = max / 255`), signed in the U-Net (`scale = max |x| / 127`); half the
    /// integer products of the wide codes where whole bytes can be multiplied.
    Narrow,
}

/// A weight tensor as stored: f32, or symmetric int8 with one scale per output channel
/// (`value = q * scale`, plus the residual plane's `r * residual_scale` where the file
/// refined it) and the codes its layer's input is quantized to.
#[derive(Clone, Copy, Debug)]
pub enum Weight<'w> {
    F32(&'w [f32]),
    Int8 {
        values: &'w [i8],
        scales: &'w [f32],
        activations: ActivationCodes,
        residual: Option<Residual<'w>>,
        /// The same values in the pair layout, where the file holds it ([`DType::I8Pairs`]:
        /// 8-bit codes only).
        pairs: Option<&'w [i8]>,
    },
}

/// The second plane of refined int8 weights ([`DType::I8Refined`]): the first plane's
/// rounding error, quantized again with its own scales, in the first plane's layout.
#[derive(Clone, Copy, Debug)]
pub struct Residual<'w> {
    pub values: &'w [i8],
    pub scales: &'w [f32],
    /// Its values in the pair layout, where the file holds the weight's.
    pub pairs: Option<&'w [i8]>,
}

/// The most output channels a refined layer may have: its residual plane's convolution
/// adds to the first plane's output with a zero bias of this length.
pub const MAX_REFINED_CHANNELS: usize = 1024;

impl Default for Weight<'_> {
    fn default() -> Self {
        Weight::F32(&[])
    }
}

impl Weight<'_> {
    pub fn len(&self) -> usize {
        match self {
            Weight::F32(values) => values.len(),
            Weight::Int8 { values, .. } => values.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Reads tensors in place from a validated file, in table order.
pub struct FileSource<'w> {
    file: WeightsFile<'w>,
    next: usize,
    /// Whether any weight was stored as int8, to check the header's storage field.
    int8_seen: bool,
}

impl<'w> FileSource<'w> {
    pub fn new(file: WeightsFile<'w>) -> Self {
        FileSource {
            file,
            next: 0,
            int8_seen: false,
        }
    }

    /// Fails unless every tensor of the file was used, and the header's weight storage
    /// says int8 exactly when some weight is int8 (the field is a promise tools read).
    pub fn finish(self) -> Result<(), Error> {
        if self.next != self.file.tensor_count() {
            return Err(Error::ExtraTensors);
        }
        if self.int8_seen != (self.file.quant() == Quant::Int8) {
            return Err(Error::BadHeader);
        }
        Ok(())
    }
}

impl<'w> FileSource<'w> {
    /// The next entry, checked against `name` and `dims`; any dtype.
    fn next_entry(
        &mut self,
        name: fmt::Arguments<'_>,
        dims: &[usize],
    ) -> Result<(usize, TensorEntry<'w>), Error> {
        let index = self.next;
        let entry = self.file.entry(index)?;
        if !named(&entry, name, index)? || entry.dims() != dims {
            return Err(Error::UnexpectedTensor { index });
        }
        self.next += 1;
        Ok((index, entry))
    }

    fn f32_data(&self, index: usize, entry: &TensorEntry<'w>) -> Result<&'w [f32], Error> {
        if entry.dtype != DType::F32 {
            return Err(Error::UnexpectedTensor { index });
        }
        bytemuck::try_cast_slice(self.file.data(entry)).map_err(|_| Error::BadTensorEntry { index })
    }
}

/// Whether `entry` (table row `index`) is named `name`; a name too long for the table is
/// an unexpected tensor there.
fn named(entry: &TensorEntry<'_>, name: fmt::Arguments<'_>, index: usize) -> Result<bool, Error> {
    let mut expected = heapless::String::<64>::new();
    expected
        .write_fmt(name)
        .map_err(|_| Error::UnexpectedTensor { index })?;
    Ok(entry.name == expected.as_str())
}

impl<'w> FileSource<'w> {
    /// The optional pair layout of the int8 weight `name` just read (`dtype`): the next
    /// entry when it is named `NAME.pairs`. Only 8-bit codes have one, with the weight's
    /// dims and planes.
    fn pairs(
        &mut self,
        name: fmt::Arguments<'_>,
        dims: &[usize],
        dtype: DType,
    ) -> Result<Option<&'w [i8]>, Error> {
        let index = self.next;
        if index >= self.file.tensor_count() {
            return Ok(None);
        }
        let entry = self.file.entry(index)?;
        let unexpected = Error::UnexpectedTensor { index };
        if !named(&entry, format_args!("{name}.pairs"), index)? {
            return Ok(None);
        }
        let expected = match dtype {
            DType::I8Narrow => DType::I8Pairs,
            DType::I8NarrowRefined => DType::I8RefinedPairs,
            _ => return Err(unexpected),
        };
        if entry.dtype != expected || entry.dims() != dims {
            return Err(unexpected);
        }
        self.next += 1;
        Ok(Some(bytemuck::cast_slice(self.file.data(&entry))))
    }
}

impl<'w> TensorSource<'w> for FileSource<'w> {
    fn f32_tensor(&mut self, name: fmt::Arguments<'_>, dims: &[usize]) -> Result<&'w [f32], Error> {
        let (index, entry) = self.next_entry(name, dims)?;
        self.f32_data(index, &entry)
    }

    fn weight(
        &mut self,
        name: fmt::Arguments<'_>,
        scale_name: fmt::Arguments<'_>,
        dims: &[usize],
        channels: usize,
        narrow: NarrowCodes,
    ) -> Result<Weight<'w>, Error> {
        let (index, entry) = self.next_entry(name, dims)?;
        let activations = match entry.dtype {
            DType::F32 => return Ok(Weight::F32(self.f32_data(index, &entry)?)),
            DType::I8 | DType::I8Refined => ActivationCodes::Wide,
            DType::I8Narrow | DType::I8NarrowRefined => ActivationCodes::Narrow,
            // A pair layout comes after its weight's scales, never in a weight's place.
            DType::I8Pairs | DType::I8RefinedPairs => {
                return Err(Error::UnexpectedTensor { index });
            }
        };
        let refined = entry.dtype.is_refined();
        // A layer whose input may be negative, or is quantized for several readers at once,
        // has no narrow path; only the residual blocks' convolutions, whose codes feed their
        // own layer alone, run a second weight plane on them.
        if (activations == ActivationCodes::Narrow || refined) && narrow == NarrowCodes::NotAllowed
        {
            return Err(Error::UnexpectedTensor { index });
        }
        // An int8 convolution sums its codes exactly in i32 only up to MAX_DIGIT_CHANNELS
        // inputs (the tool stores wider ones in f32).
        if !crate::kernels::int8_fits(dims) || (refined && channels > MAX_REFINED_CHANNELS) {
            return Err(Error::UnexpectedTensor { index });
        }
        let values: &'w [i8] = bytemuck::cast_slice(self.file.data(&entry));
        let scales = if refined {
            self.f32_tensor(scale_name, &[2, channels])?
        } else {
            self.f32_tensor(scale_name, &[channels])?
        };
        // A zero, negative or non-finite scale is not a quantization anyone wrote.
        if scales.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(Error::UnexpectedTensor { index: index + 1 });
        }
        self.int8_seen = true;
        let pairs = self.pairs(name, dims, entry.dtype)?;
        let (first_pairs, residual_pairs) = match pairs {
            Some(pairs) if refined => {
                let (first, second) = pairs.split_at(pairs.len() / 2);
                (Some(first), Some(second))
            }
            pairs => (pairs, None),
        };
        let (values, scales, residual) = if refined {
            let (values, residual_values) = values.split_at(values.len() / 2);
            let (scales, residual_scales) = scales.split_at(channels);
            let residual = Residual {
                values: residual_values,
                scales: residual_scales,
                pairs: residual_pairs,
            };
            (values, scales, Some(residual))
        } else {
            (values, scales, None)
        };
        Ok(Weight::Int8 {
            values,
            scales,
            activations,
            residual,
            pairs: first_pairs,
        })
    }
}

/// A convolution (any rank) or linear layer: packed weight (one int8 scale per output
/// channel, the last axis) and bias.
#[derive(Clone, Copy, Debug, Default)]
pub struct Conv<'w> {
    pub weight: Weight<'w>,
    pub bias: &'w [f32],
}

/// GroupNorm affine parameters.
#[derive(Clone, Copy, Debug, Default)]
pub struct Norm<'w> {
    pub gamma: &'w [f32],
    pub beta: &'w [f32],
}

/// A trunk convolution and its normalization: `None` when BatchNorm was folded into it.
#[derive(Clone, Copy, Debug, Default)]
pub struct ConvNorm<'w> {
    pub conv: Conv<'w>,
    pub norm: Option<Norm<'w>>,
}

/// torchvision's BasicBlock.
#[derive(Clone, Copy, Debug, Default)]
pub struct BasicBlock<'w> {
    pub first: ConvNorm<'w>,
    pub second: ConvNorm<'w>,
    pub downsample: Option<ConvNorm<'w>>,
}

/// ResNet-18 trunk and the five 3x3 projections.
#[derive(Clone, Copy, Debug, Default)]
pub struct PyramidWeights<'w> {
    pub stem: ConvNorm<'w>,
    pub stages: [[BasicBlock<'w>; 2]; 4],
    pub projections: [Conv<'w>; PYRAMID_LEVELS],
}

/// Diffusion Policy's ConditionalResidualBlock1D with FiLM.
#[derive(Clone, Copy, Debug, Default)]
pub struct ResidualBlock<'w> {
    pub in_channels: usize,
    pub out_channels: usize,
    pub conv0: Conv<'w>,
    pub norm0: Norm<'w>,
    pub conv1: Conv<'w>,
    pub norm1: Norm<'w>,
    /// `[2 out, global_cond_dim]`: rows 0..out give the scale, out..2 out the bias (int8
    /// scales per row).
    pub film_weight: Weight<'w>,
    /// `[steps, 2 out]`: the time-embedding term plus the linear bias, per inference step.
    pub film_table: &'w [f32],
    pub residual: Option<Conv<'w>>,
}

/// ConditionalUnet1D.
#[derive(Clone, Copy, Debug, Default)]
pub struct DenoiserWeights<'w> {
    pub down: [[ResidualBlock<'w>; 2]; UNET_LEVELS],
    pub downsample: [Conv<'w>; UNET_LEVELS - 1],
    pub mid: [ResidualBlock<'w>; 2],
    pub up: [[ResidualBlock<'w>; 2]; UNET_LEVELS - 1],
    /// The transposed convolutions, as the tool lowers them (docs/FORMAT.md):
    /// [`UPSAMPLE_TAPS`] taps, `channels` -> `2 channels`, position `p` holding output `2 p`
    /// and output `2 p - 1`.
    pub upsample: [Conv<'w>; UNET_LEVELS - 1],
    pub final_conv: Conv<'w>,
    pub final_norm: Norm<'w>,
    pub final_projection: Conv<'w>,
}

/// Diffusion Policy's LinearNormalizer: `normalized = raw * scale + offset`.
#[derive(Clone, Copy, Debug, Default)]
pub struct Normalizer<'w> {
    pub action_scale: &'w [f32],
    pub action_offset: &'w [f32],
    pub state_scale: &'w [f32],
    pub state_offset: &'w [f32],
}

/// Per inference step: `sqrt(a_t), sqrt(1 - a_t), sqrt(a_prev), sqrt(1 - a_prev)`.
pub const SCHEDULE_COLUMNS: usize = 4;

/// Taps of a lowered transposed convolution: inputs `p - 1` and `p` of output position `p`.
pub const UPSAMPLE_TAPS: usize = 2;

#[derive(Clone, Copy, Debug, Default)]
pub struct ModelWeights<'w> {
    pub pyramid: PyramidWeights<'w>,
    pub denoiser: DenoiserWeights<'w>,
    pub normalizer: Normalizer<'w>,
    /// `[steps, 4]`, see [`SCHEDULE_COLUMNS`].
    pub schedule: &'w [f32],
}

fn conv<'w>(
    source: &mut impl TensorSource<'w>,
    name: fmt::Arguments<'_>,
    weight_dims: &[usize],
) -> Result<Conv<'w>, Error> {
    conv_codes(source, name, weight_dims, NarrowCodes::NotAllowed)
}

fn conv_codes<'w>(
    source: &mut impl TensorSource<'w>,
    name: fmt::Arguments<'_>,
    weight_dims: &[usize],
    narrow: NarrowCodes,
) -> Result<Conv<'w>, Error> {
    let out = weight_dims[weight_dims.len() - 1];
    Ok(Conv {
        weight: source.weight(
            format_args!("{name}.weight"),
            format_args!("{name}.weight_scale"),
            weight_dims,
            out,
            narrow,
        )?,
        bias: source.f32_tensor(format_args!("{name}.bias"), &[out])?,
    })
}

fn norm<'w>(
    source: &mut impl TensorSource<'w>,
    name: fmt::Arguments<'_>,
    channels: usize,
) -> Result<Norm<'w>, Error> {
    Ok(Norm {
        gamma: source.f32_tensor(format_args!("{name}.weight"), &[channels])?,
        beta: source.f32_tensor(format_args!("{name}.bias"), &[channels])?,
    })
}

fn conv_norm<'w>(
    source: &mut impl TensorSource<'w>,
    config: &ModelConfig,
    (conv_name, norm_name): (fmt::Arguments<'_>, fmt::Arguments<'_>),
    weight_dims: &[usize],
    narrow: NarrowCodes,
) -> Result<ConvNorm<'w>, Error> {
    let conv = conv_codes(source, conv_name, weight_dims, narrow)?;
    let norm = match config.backbone_norm {
        BackboneNorm::Group => Some(norm(source, norm_name, weight_dims[3])?),
        BackboneNorm::Batch => None,
    };
    Ok(ConvNorm { conv, norm })
}

fn residual_block<'w>(
    source: &mut impl TensorSource<'w>,
    config: &ModelConfig,
    name: fmt::Arguments<'_>,
    in_channels: usize,
    out_channels: usize,
) -> Result<ResidualBlock<'w>, Error> {
    let kernel = config.kernel_size as usize;
    let steps = config.num_inference_steps as usize;
    Ok(ResidualBlock {
        in_channels,
        out_channels,
        conv0: conv_codes(
            source,
            format_args!("{name}.conv0"),
            &[kernel, in_channels, out_channels],
            NarrowCodes::Allowed,
        )?,
        norm0: norm(source, format_args!("{name}.norm0"), out_channels)?,
        conv1: conv_codes(
            source,
            format_args!("{name}.conv1"),
            &[kernel, out_channels, out_channels],
            NarrowCodes::Allowed,
        )?,
        norm1: norm(source, format_args!("{name}.norm1"), out_channels)?,
        film_weight: source.weight(
            format_args!("{name}.film.weight"),
            format_args!("{name}.film.weight_scale"),
            &[2 * out_channels, config.global_cond_dim()],
            2 * out_channels,
            NarrowCodes::NotAllowed,
        )?,
        film_table: source.f32_tensor(
            format_args!("{name}.film.table"),
            &[steps, 2 * out_channels],
        )?,
        residual: if in_channels != out_channels {
            Some(conv(
                source,
                format_args!("{name}.residual"),
                &[1, in_channels, out_channels],
            )?)
        } else {
            None
        },
    })
}

impl<'w> ModelWeights<'w> {
    /// Asks `source` for every tensor of the model described by `config`, in file order.
    pub fn bind(config: &ModelConfig, source: &mut impl TensorSource<'w>) -> Result<Self, Error> {
        config.validate()?;
        let mut weights = ModelWeights::default();

        let width = config.stage_channels(0);
        let pyramid = &mut weights.pyramid;
        // The stem reads the image bytes, already 8-bit codes.
        pyramid.stem = conv_norm(
            source,
            config,
            (format_args!("backbone.conv1"), format_args!("backbone.bn1")),
            &[7, 7, 3, width],
            NarrowCodes::NotAllowed,
        )?;
        let mut in_channels = width;
        for (stage, blocks) in pyramid.stages.iter_mut().enumerate() {
            let out_channels = config.stage_channels(stage);
            let layer = stage + 1;
            for (index, block) in blocks.iter_mut().enumerate() {
                let block_in = if index == 0 {
                    in_channels
                } else {
                    out_channels
                };
                // Every input of a residual block's convolutions is a ReLU output.
                let narrow = NarrowCodes::Allowed;
                block.first = conv_norm(
                    source,
                    config,
                    (
                        format_args!("backbone.layer{layer}.{index}.conv1"),
                        format_args!("backbone.layer{layer}.{index}.bn1"),
                    ),
                    &[3, 3, block_in, out_channels],
                    narrow,
                )?;
                block.second = conv_norm(
                    source,
                    config,
                    (
                        format_args!("backbone.layer{layer}.{index}.conv2"),
                        format_args!("backbone.layer{layer}.{index}.bn2"),
                    ),
                    &[3, 3, out_channels, out_channels],
                    narrow,
                )?;
                block.downsample = if index == 0 && stage > 0 {
                    Some(conv_norm(
                        source,
                        config,
                        (
                            format_args!("backbone.layer{layer}.0.downsample.0"),
                            format_args!("backbone.layer{layer}.0.downsample.1"),
                        ),
                        &[1, 1, block_in, out_channels],
                        narrow,
                    )?)
                } else {
                    None
                };
            }
            in_channels = out_channels;
        }
        let feature_dim = config.feature_dim as usize;
        for (level, projection) in pyramid.projections.iter_mut().enumerate() {
            *projection = conv(
                source,
                format_args!("proj.{level}"),
                &[3, 3, config.pyramid_channels(level), feature_dim],
            )?;
        }

        let denoiser = &mut weights.denoiser;
        let dims = config.down_dims.map(|dim| dim as usize);
        let mut level_in = config.action_dim as usize;
        for (level, blocks) in denoiser.down.iter_mut().enumerate() {
            blocks[0] = residual_block(
                source,
                config,
                format_args!("unet.down.{level}.0"),
                level_in,
                dims[level],
            )?;
            blocks[1] = residual_block(
                source,
                config,
                format_args!("unet.down.{level}.1"),
                dims[level],
                dims[level],
            )?;
            if level + 1 < UNET_LEVELS {
                denoiser.downsample[level] = conv(
                    source,
                    format_args!("unet.down.{level}.downsample"),
                    &[3, dims[level], dims[level]],
                )?;
            }
            level_in = dims[level];
        }
        let deepest = dims[UNET_LEVELS - 1];
        for (index, block) in denoiser.mid.iter_mut().enumerate() {
            *block = residual_block(
                source,
                config,
                format_args!("unet.mid.{index}"),
                deepest,
                deepest,
            )?;
        }
        for (index, blocks) in denoiser.up.iter_mut().enumerate() {
            // Up level `index` mirrors down level UNET_LEVELS - 2 - index, whose output it
            // produces; its input is the level below concatenated with that level's skip.
            let level = UNET_LEVELS - 2 - index;
            let below = dims[level + 1];
            blocks[0] = residual_block(
                source,
                config,
                format_args!("unet.up.{index}.0"),
                2 * below,
                dims[level],
            )?;
            blocks[1] = residual_block(
                source,
                config,
                format_args!("unet.up.{index}.1"),
                dims[level],
                dims[level],
            )?;
            let channels = dims[level];
            denoiser.upsample[index] = conv(
                source,
                format_args!("unet.up.{index}.upsample"),
                &[UPSAMPLE_TAPS, channels, 2 * channels],
            )?;
        }
        let kernel = config.kernel_size as usize;
        denoiser.final_conv = conv(
            source,
            format_args!("unet.final.conv"),
            &[kernel, dims[0], dims[0]],
        )?;
        denoiser.final_norm = norm(source, format_args!("unet.final.norm"), dims[0])?;
        denoiser.final_projection = conv(
            source,
            format_args!("unet.final.projection"),
            &[1, dims[0], config.action_dim as usize],
        )?;

        let action_dim = config.action_dim as usize;
        let state_dim = config.state_dim as usize;
        weights.normalizer = Normalizer {
            action_scale: source
                .f32_tensor(format_args!("normalizer.action.scale"), &[action_dim])?,
            action_offset: source
                .f32_tensor(format_args!("normalizer.action.offset"), &[action_dim])?,
            state_scale: source.f32_tensor(format_args!("normalizer.state.scale"), &[state_dim])?,
            state_offset: source
                .f32_tensor(format_args!("normalizer.state.offset"), &[state_dim])?,
        };
        weights.schedule = source.f32_tensor(
            format_args!("scheduler.ddim"),
            &[config.num_inference_steps as usize, SCHEDULE_COLUMNS],
        )?;
        Ok(weights)
    }
}
