//! PyTorch state dict -> the engine's tensors. All weight-only work happens here, offline,
//! so the engine only does runtime work:
//! - convolution weights repacked to the engine's layouts (`[kh, kw, in, out]`, `[k, in, out]`);
//! - eval-mode BatchNorm folded into the convolution before it;
//! - the FiLM linear layers split: the time-embedding half, with its bias, evaluated for each
//!   inference timestep (the diffusion step encoder never runs on the robot); the
//!   global-condition half kept as a matrix;
//! - the DDIM coefficients of each inference step.
//!
//! Arithmetic that combines weights is done in f64 and rounded once.

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{Context, Result, bail, ensure};
use scdp_engine::config::{BackboneNorm, ModelConfig, UNET_LEVELS};
use scdp_engine::weights::{ActivationCodes, NarrowCodes};

use crate::quant::Quant;
use crate::writer::{ResidualPlane, Stored};

/// A PyTorch tensor as the lowering reads it: shape and row-major values.
pub struct TensorRef<'a> {
    pub shape: &'a [usize],
    pub data: &'a [f32],
}

/// Looks up a state-dict key.
pub trait StateDictLookup {
    fn tensor(&self, key: &str) -> Option<TensorRef<'_>>;
}

/// The engine's tensors by engine name, in engine layout.
pub type Lowered = BTreeMap<String, Vec<f32>>;

struct Lowering<'s, S: StateDictLookup> {
    state: &'s S,
    config: ModelConfig,
    out: Lowered,
}

const BATCH_NORM_EPSILON: f64 = 1e-5;

fn mish(x: f64) -> f64 {
    let softplus = if x > 20.0 { x } else { x.exp().ln_1p() };
    x * softplus.tanh()
}

impl<S: StateDictLookup> Lowering<'_, S> {
    fn get(&self, key: &str, shape: &[usize]) -> Result<&[f32]> {
        let tensor = self
            .state
            .tensor(key)
            .with_context(|| format!("state dict has no key `{key}`"))?;
        ensure!(
            tensor.shape == shape,
            "`{key}` has shape {:?}, expected {shape:?}",
            tensor.shape
        );
        Ok(tensor.data)
    }

    fn put(&mut self, name: String, values: Vec<f32>) {
        self.out.insert(name, values);
    }

    /// `[out, in, kh, kw]` (or `[out, in, k]`) -> `[kh, kw, in, out]` (or `[k, in, out]`),
    /// each output channel multiplied by `scale[out]`.
    fn pack_conv(
        weight: &[f32],
        out: usize,
        inputs: usize,
        taps: usize,
        scale: &[f64],
    ) -> Vec<f32> {
        let mut packed = vec![0.0; weight.len()];
        for o in 0..out {
            for i in 0..inputs {
                for tap in 0..taps {
                    let value = weight[(o * inputs + i) * taps + tap] as f64 * scale[o];
                    packed[(tap * inputs + i) * out + o] = value as f32;
                }
            }
        }
        packed
    }

    /// A trunk convolution (no bias in PyTorch) and the norm after it.
    fn trunk_conv(
        &mut self,
        conv_key: &str,
        norm_key: &str,
        engine: &str,
        norm_engine: &str,
        dims: [usize; 4],
    ) -> Result<()> {
        let [out, inputs, kh, kw] = dims;
        let weight = self.get(&format!("{conv_key}.weight"), &dims)?.to_vec();
        match self.config.backbone_norm {
            BackboneNorm::Group => {
                let gamma = self.get(&format!("{norm_key}.weight"), &[out])?.to_vec();
                let beta = self.get(&format!("{norm_key}.bias"), &[out])?.to_vec();
                self.put(
                    format!("{engine}.weight"),
                    Self::pack_conv(&weight, out, inputs, kh * kw, &vec![1.0; out]),
                );
                self.put(format!("{engine}.bias"), vec![0.0; out]);
                self.put(format!("{norm_engine}.weight"), gamma);
                self.put(format!("{norm_engine}.bias"), beta);
            }
            BackboneNorm::Batch => {
                let gamma = self.get(&format!("{norm_key}.weight"), &[out])?;
                let beta = self.get(&format!("{norm_key}.bias"), &[out])?;
                let mean = self.get(&format!("{norm_key}.running_mean"), &[out])?;
                let var = self.get(&format!("{norm_key}.running_var"), &[out])?;
                let scale: Vec<f64> = (0..out)
                    .map(|o| gamma[o] as f64 / (var[o] as f64 + BATCH_NORM_EPSILON).sqrt())
                    .collect();
                let bias: Vec<f32> = (0..out)
                    .map(|o| (beta[o] as f64 - mean[o] as f64 * scale[o]) as f32)
                    .collect();
                self.put(
                    format!("{engine}.weight"),
                    Self::pack_conv(&weight, out, inputs, kh * kw, &scale),
                );
                self.put(format!("{engine}.bias"), bias);
            }
        }
        Ok(())
    }

    /// A convolution with bias: `[out, in, taps...]` -> packed.
    fn conv(
        &mut self,
        key: &str,
        engine: &str,
        out: usize,
        inputs: usize,
        taps: &[usize],
    ) -> Result<()> {
        let mut dims = vec![out, inputs];
        dims.extend_from_slice(taps);
        let weight = self.get(&format!("{key}.weight"), &dims)?.to_vec();
        let bias = self.get(&format!("{key}.bias"), &[out])?.to_vec();
        let tap_count = taps.iter().product();
        self.put(
            format!("{engine}.weight"),
            Self::pack_conv(&weight, out, inputs, tap_count, &vec![1.0; out]),
        );
        self.put(format!("{engine}.bias"), bias);
        Ok(())
    }

    fn copy(&mut self, key: &str, engine: String, len: usize) -> Result<()> {
        let values = self.get(key, &[len])?.to_vec();
        self.put(engine, values);
        Ok(())
    }

    fn backbone(&mut self) -> Result<()> {
        let prefix = "obs_encoder.backbone";
        let width = self.config.stage_channels(0);
        self.trunk_conv(
            &format!("{prefix}.conv1"),
            &format!("{prefix}.bn1"),
            "backbone.conv1",
            "backbone.bn1",
            [width, 3, 7, 7],
        )?;
        let mut in_channels = width;
        for stage in 0..4 {
            let out = self.config.stage_channels(stage);
            let layer = stage + 1;
            for block in 0..2 {
                let block_in = if block == 0 { in_channels } else { out };
                let key = format!("{prefix}.layer{layer}.{block}");
                let engine = format!("backbone.layer{layer}.{block}");
                self.trunk_conv(
                    &format!("{key}.conv1"),
                    &format!("{key}.bn1"),
                    &format!("{engine}.conv1"),
                    &format!("{engine}.bn1"),
                    [out, block_in, 3, 3],
                )?;
                self.trunk_conv(
                    &format!("{key}.conv2"),
                    &format!("{key}.bn2"),
                    &format!("{engine}.conv2"),
                    &format!("{engine}.bn2"),
                    [out, out, 3, 3],
                )?;
                if block == 0 && stage > 0 {
                    self.trunk_conv(
                        &format!("{key}.downsample.0"),
                        &format!("{key}.downsample.1"),
                        &format!("{engine}.downsample.0"),
                        &format!("{engine}.downsample.1"),
                        [out, block_in, 1, 1],
                    )?;
                }
            }
            in_channels = out;
        }
        let feature_dim = self.config.feature_dim as usize;
        for level in 0..5 {
            let channels = self.config.pyramid_channels(level);
            self.conv(
                &format!("obs_encoder.proj.{level}"),
                &format!("proj.{level}"),
                feature_dim,
                channels,
                &[3, 3],
            )?;
        }
        Ok(())
    }

    /// The diffusion step encoder at timestep `t`, in f64.
    fn time_embedding(&self, t: f64) -> Result<Vec<f64>> {
        let e = self.config.diffusion_step_embed_dim as usize;
        let half = e / 2;
        let step = (10000f64).ln() / (half as f64 - 1.0);
        let mut sinusoid = vec![0.0; e];
        for i in 0..half {
            let angle = t * (-(i as f64) * step).exp();
            sinusoid[i] = angle.sin();
            sinusoid[half + i] = angle.cos();
        }
        let linear = |key: &str, input: &[f64], out: usize| -> Result<Vec<f64>> {
            let weight = self.get(
                &format!("model.diffusion_step_encoder.{key}.weight"),
                &[out, input.len()],
            )?;
            let bias = self.get(&format!("model.diffusion_step_encoder.{key}.bias"), &[out])?;
            Ok((0..out)
                .map(|o| {
                    bias[o] as f64
                        + weight[o * input.len()..][..input.len()]
                            .iter()
                            .zip(input)
                            .map(|(&w, &x)| w as f64 * x)
                            .sum::<f64>()
                })
                .collect())
        };
        let hidden: Vec<f64> = linear("1", &sinusoid, 4 * e)?
            .into_iter()
            .map(mish)
            .collect();
        linear("3", &hidden, e)
    }

    fn residual_block(
        &mut self,
        key: &str,
        engine: &str,
        inputs: usize,
        out: usize,
        activated_embeddings: &[Vec<f64>],
    ) -> Result<()> {
        let kernel = self.config.kernel_size as usize;
        self.conv(
            &format!("{key}.blocks.0.block.0"),
            &format!("{engine}.conv0"),
            out,
            inputs,
            &[kernel],
        )?;
        self.copy(
            &format!("{key}.blocks.0.block.1.weight"),
            format!("{engine}.norm0.weight"),
            out,
        )?;
        self.copy(
            &format!("{key}.blocks.0.block.1.bias"),
            format!("{engine}.norm0.bias"),
            out,
        )?;
        self.conv(
            &format!("{key}.blocks.1.block.0"),
            &format!("{engine}.conv1"),
            out,
            out,
            &[kernel],
        )?;
        self.copy(
            &format!("{key}.blocks.1.block.1.weight"),
            format!("{engine}.norm1.weight"),
            out,
        )?;
        self.copy(
            &format!("{key}.blocks.1.block.1.bias"),
            format!("{engine}.norm1.bias"),
            out,
        )?;

        let embed = self.config.diffusion_step_embed_dim as usize;
        let global = self.config.global_cond_dim();
        let cond = embed + global;
        let weight = self
            .get(&format!("{key}.cond_encoder.1.weight"), &[2 * out, cond])?
            .to_vec();
        let bias = self
            .get(&format!("{key}.cond_encoder.1.bias"), &[2 * out])?
            .to_vec();
        let global_part: Vec<f32> = weight
            .chunks_exact(cond)
            .flat_map(|row| row[embed..].iter().copied())
            .collect();
        let mut table = Vec::with_capacity(activated_embeddings.len() * 2 * out);
        for embedding in activated_embeddings {
            for (row, &b) in weight.chunks_exact(cond).zip(&bias) {
                let time_term: f64 = row[..embed]
                    .iter()
                    .zip(embedding)
                    .map(|(&w, &x)| w as f64 * x)
                    .sum();
                table.push((b as f64 + time_term) as f32);
            }
        }
        self.put(format!("{engine}.film.weight"), global_part);
        self.put(format!("{engine}.film.table"), table);
        if inputs != out {
            self.conv(
                &format!("{key}.residual_conv"),
                &format!("{engine}.residual"),
                out,
                inputs,
                &[1],
            )?;
        }
        Ok(())
    }

    fn denoiser(&mut self, timesteps: &[u32]) -> Result<()> {
        let activated: Vec<Vec<f64>> = timesteps
            .iter()
            .map(|&t| {
                Ok(self
                    .time_embedding(t as f64)?
                    .into_iter()
                    .map(mish)
                    .collect())
            })
            .collect::<Result<_>>()?;
        let dims = self.config.down_dims.map(|d| d as usize);
        let mut level_in = self.config.action_dim as usize;
        for (level, &width) in dims.iter().enumerate() {
            let key = format!("model.down_modules.{level}");
            let engine = format!("unet.down.{level}");
            self.residual_block(
                &format!("{key}.0"),
                &format!("{engine}.0"),
                level_in,
                width,
                &activated,
            )?;
            self.residual_block(
                &format!("{key}.1"),
                &format!("{engine}.1"),
                width,
                width,
                &activated,
            )?;
            if level + 1 < UNET_LEVELS {
                self.conv(
                    &format!("{key}.2.conv"),
                    &format!("{engine}.downsample"),
                    width,
                    width,
                    &[3],
                )?;
            }
            level_in = width;
        }
        for index in 0..2 {
            let deepest = dims[UNET_LEVELS - 1];
            self.residual_block(
                &format!("model.mid_modules.{index}"),
                &format!("unet.mid.{index}"),
                deepest,
                deepest,
                &activated,
            )?;
        }
        for index in 0..UNET_LEVELS - 1 {
            let level = UNET_LEVELS - 2 - index;
            let key = format!("model.up_modules.{index}");
            let engine = format!("unet.up.{index}");
            self.residual_block(
                &format!("{key}.0"),
                &format!("{engine}.0"),
                2 * dims[level + 1],
                dims[level],
                &activated,
            )?;
            self.residual_block(
                &format!("{key}.1"),
                &format!("{engine}.1"),
                dims[level],
                dims[level],
                &activated,
            )?;
            let channels = dims[level];
            let weight = self
                .get(&format!("{key}.2.conv.weight"), &[channels, channels, 4])?
                .to_vec();
            let bias = self.get(&format!("{key}.2.conv.bias"), &[channels])?;
            let (weight, bias) = lower_upsample(&weight, bias);
            self.put(format!("{engine}.upsample.weight"), weight);
            self.put(format!("{engine}.upsample.bias"), bias);
        }
        let kernel = self.config.kernel_size as usize;
        self.conv(
            "model.final_conv.0.block.0",
            "unet.final.conv",
            dims[0],
            dims[0],
            &[kernel],
        )?;
        self.copy(
            "model.final_conv.0.block.1.weight",
            "unet.final.norm.weight".into(),
            dims[0],
        )?;
        self.copy(
            "model.final_conv.0.block.1.bias",
            "unet.final.norm.bias".into(),
            dims[0],
        )?;
        self.conv(
            "model.final_conv.1",
            "unet.final.projection",
            self.config.action_dim as usize,
            dims[0],
            &[1],
        )?;
        Ok(())
    }

    fn normalizer(&mut self) -> Result<()> {
        let action_dim = self.config.action_dim as usize;
        let state_dim = self.config.state_dim as usize;
        let params = "normalizer.params_dict";
        self.copy(
            &format!("{params}.action.scale"),
            "normalizer.action.scale".into(),
            action_dim,
        )?;
        self.copy(
            &format!("{params}.action.offset"),
            "normalizer.action.offset".into(),
            action_dim,
        )?;
        self.copy(
            &format!("{params}.agent_pos.scale"),
            "normalizer.state.scale".into(),
            state_dim,
        )?;
        self.copy(
            &format!("{params}.agent_pos.offset"),
            "normalizer.state.offset".into(),
            state_dim,
        )?;
        for (name, values) in &self.out {
            if name.ends_with(".scale")
                && name.starts_with("normalizer.")
                && values.iter().any(|&v| v == 0.0 || !v.is_finite())
            {
                bail!(
                    "`{name}` has a zero or non-finite entry: the actions could not be unnormalized"
                );
            }
        }
        Ok(())
    }
}

/// DDIM inference timesteps ("leading" spacing, steps_offset 0), first to last.
pub fn inference_timesteps(config: &ModelConfig) -> Vec<u32> {
    let ratio = config.num_train_timesteps / config.num_inference_steps;
    (0..config.num_inference_steps)
        .rev()
        .map(|i| i * ratio)
        .collect()
}

/// diffusers' `alphas_cumprod` for `squaredcos_cap_v2`: betas in f64 stored as f32, the
/// running product accumulated in f64 and stored as f32 at each step (as torch.cumprod does).
pub fn alphas_cumprod(config: &ModelConfig) -> Vec<f32> {
    let steps = config.num_train_timesteps as usize;
    let alpha_bar = |x: f64| {
        ((x + 0.008) / 1.008 * std::f64::consts::FRAC_PI_2)
            .cos()
            .powi(2)
    };
    let mut product = 1.0f64;
    (0..steps)
        .map(|i| {
            let beta = (1.0
                - alpha_bar((i + 1) as f64 / steps as f64) / alpha_bar(i as f64 / steps as f64))
            .min(0.999);
            let alpha = 1.0f32 - beta as f32;
            product *= alpha as f64;
            product as f32
        })
        .collect()
}

/// `[steps, 4]`: sqrt(a_t), sqrt(1 - a_t), sqrt(a_prev), sqrt(1 - a_prev).
pub fn ddim_table(config: &ModelConfig) -> Vec<f32> {
    let cumulative = alphas_cumprod(config);
    let ratio = (config.num_train_timesteps / config.num_inference_steps) as i64;
    let mut table = Vec::new();
    for t in inference_timesteps(config) {
        let alpha = cumulative[t as usize] as f64;
        let previous = t as i64 - ratio;
        let alpha_prev = if previous >= 0 {
            cumulative[previous as usize] as f64
        } else {
            1.0
        };
        // 1 - a is formed in f32 first, as diffusers does.
        let one_minus = |a: f64| (1.0f32 - a as f32) as f64;
        table.extend(
            [
                alpha.sqrt(),
                one_minus(alpha).sqrt(),
                alpha_prev.sqrt(),
                one_minus(alpha_prev).sqrt(),
            ]
            .map(|v| v as f32),
        );
    }
    table
}

/// ConvTranspose1d(kernel 4, stride 2, padding 1) of `channels = bias.len()` channels in and
/// out (PyTorch's weight `[channels, channels, 4]` and bias) as the ordinary convolution the
/// engine runs: 2 taps, padding 1, `2 channels` outputs, weight `[2, channels, 2 channels]`,
/// the bias twice. Output `t` of the transposed convolution takes input `s` through tap
/// `t + 1 - 2 s`, so output `2 j` is tap 3 on input `j - 1` plus tap 1 on input `j`, and
/// output `2 j + 1` is tap 2 on input `j` plus tap 0 on input `j + 1`. Position `p` of the
/// lowered convolution reads inputs `p - 1` and `p`, and holds output `2 p` in its first
/// `channels` and output `2 (p - 1) + 1` in its last: `length + 1` positions, of which the
/// engine keeps the even half of positions `0..length` and the odd half of `1..=length`.
/// Every weight is the transposed convolution's, none zero (format version 5 had a third tap
/// per position, a third of the kernel zeros, streamed every denoising step).
pub fn lower_upsample(weight: &[f32], bias: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let channels = bias.len();
    assert_eq!(
        weight.len(),
        4 * channels * channels,
        "ConvTranspose1d weight"
    );
    // Taps 0 and 1 below: inputs `p - 1` and `p`, the engine's two.
    const { assert!(scdp_engine::weights::UPSAMPLE_TAPS == 2) };
    let wide = 2 * channels;
    let mut lowered = vec![0.0; scdp_engine::weights::UPSAMPLE_TAPS * channels * wide];
    for input in 0..channels {
        for output in 0..channels {
            let tap = |k: usize| weight[(input * channels + output) * 4 + k];
            let at = |lowered_tap: usize, column: usize| {
                (lowered_tap * channels + input) * wide + column
            };
            // Tap 0 reads input `p - 1`, tap 1 input `p`.
            lowered[at(0, output)] = tap(3);
            lowered[at(1, output)] = tap(1);
            lowered[at(0, channels + output)] = tap(2);
            lowered[at(1, channels + output)] = tap(0);
        }
    }
    (lowered, [bias, bias].concat())
}

/// Every engine tensor for `config`, from a PyTorch state dict.
pub fn lower(config: &ModelConfig, state: &impl StateDictLookup) -> Result<Lowered> {
    config
        .validate()
        .map_err(|error| anyhow::anyhow!("config: {error}"))?;
    let mut lowering = Lowering {
        state,
        config: *config,
        out: Lowered::new(),
    };
    lowering.backbone()?;
    lowering.denoiser(&inference_timesteps(config))?;
    lowering.normalizer()?;
    lowering
        .out
        .insert("scheduler.ddim".into(), ddim_table(config));
    Ok(lowering.out)
}

impl StateDictLookup for crate::state_dict::StateDict {
    fn tensor(&self, key: &str) -> Option<TensorRef<'_>> {
        self.get(key).map(|tensor| TensorRef {
            shape: &tensor.shape,
            data: &tensor.data,
        })
    }
}

/// Weights the int8 mode still stores in f32, and why (measured with
/// `cargo test -p scdp-tests --test int8_fidelity -- --nocapture`; see docs/QUANTIZATION.md).
pub const INT8_KEEP_F32: &[(&str, &str)] = &[
    (
        "unet.final.projection.weight",
        "the predicted noise itself: 1k weights, its error goes straight into every DDIM step",
    ),
    (
        "unet.up.1.upsample.weight",
        "the last transposed convolution (0.26 MB in f32): int8, it took panda/edge's max action \
         error to 0.029, over the 0.02 floor (docs/QUANTIZATION.md)",
    ),
];

/// The stem convolution's kernel.
pub const STEM_WEIGHT: &str = "backbone.conv1.weight";

/// Why the stem stays f32 with ImageNet normalization: its int8 form reads the image bytes
/// as codes, exact only when a zero byte is the network's zero (the padding).
pub const STEM_KEPT_F32: &str =
    "ImageNet normalization: the int8 stem reads the raw bytes, whose zero is not the padding's";

/// The weights `config`'s int8 files keep in f32, and why: [`INT8_KEEP_F32`], and the
/// stem when the config normalizes images.
pub fn int8_kept_f32(config: &ModelConfig) -> Vec<(&'static str, &'static str)> {
    let mut kept = INT8_KEEP_F32.to_vec();
    if config.imagenet_norm {
        kept.push((STEM_WEIGHT, STEM_KEPT_F32));
    }
    kept
}

/// Whether the tool offers a tensor a second weight plane: the trunk's residual-block
/// convolutions (`backbone.layer*`, which the engine also allows narrow codes). The engine
/// would take one on the U-Net's too, but with their weights in f32 door-open's largest
/// action differences did not fall (docs/METAWORLD.md).
fn may_refine(name: &str, narrow: NarrowCodes) -> bool {
    narrow == NarrowCodes::Allowed && name.starts_with("backbone.layer")
}

/// What int8 rounding left of `values` (`values - quantized * scale`), quantized again per
/// channel to nearest: with it the weights are about 15 bits.
fn residual_plane(
    values: &[f32],
    quantized: &[i8],
    scales: &[f32],
    axis: ChannelAxis,
) -> ResidualPlane {
    let channels = scales.len();
    let per_channel = values.len() / channels;
    let channel_of = |index: usize| match axis {
        ChannelAxis::First => index / per_channel,
        ChannelAxis::Last => index % channels,
    };
    let left: Vec<f32> = values
        .iter()
        .zip(quantized)
        .enumerate()
        .map(|(index, (&value, &q))| {
            (f64::from(value) - f64::from(q) * f64::from(scales[channel_of(index)])) as f32
        })
        .collect();
    let (values, scales) = quantize_per_channel(&left, channels, axis);
    ResidualPlane { values, scales }
}

/// Symmetric int8 with one scale per channel: `scale = max |w| / 127` over the channel,
/// `q = round(w / scale)`. Channels are the last axis (convolutions, `[.., out]`) or, with
/// `ChannelAxis::First`, the first (FiLM matrices, one row per output).
fn quantize_per_channel(values: &[f32], channels: usize, axis: ChannelAxis) -> (Vec<i8>, Vec<f32>) {
    let per_channel = values.len() / channels;
    let channel_of = |index: usize| match axis {
        ChannelAxis::First => index / per_channel,
        ChannelAxis::Last => index % channels,
    };
    let mut largest = vec![0.0f32; channels];
    for (index, &value) in values.iter().enumerate() {
        let channel = channel_of(index);
        largest[channel] = largest[channel].max(value.abs());
    }
    // An all-zero channel keeps scale 1 (its values quantize to 0 either way).
    let scales: Vec<f32> = largest
        .iter()
        .map(|&m| if m > 0.0 { m / 127.0 } else { 1.0 })
        .collect();
    let quantized = values
        .iter()
        .enumerate()
        .map(|(index, &value)| {
            (value as f64 / scales[channel_of(index)] as f64)
                .round()
                .clamp(-127.0, 127.0) as i8
        })
        .collect();
    (quantized, scales)
}

/// How a weight tensor's values are laid out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ChannelAxis {
    /// `[inputs, channels]`: convolution kernels, `[taps, in, out]` flattened.
    Last,
    /// `[channels, inputs]`: FiLM matrices, one row per output.
    First,
}

/// Calibration moments ([`crate::calibrate::Moments`]); none exist without the `gptq` feature.
#[cfg(feature = "gptq")]
pub use crate::calibrate::Moments;
/// Calibration moments: none exist without the `gptq` feature.
#[cfg(not(feature = "gptq"))]
pub enum Moments {}

/// How int8 weights are rounded.
#[derive(Clone, Copy, Default)]
pub enum Rounding<'m> {
    /// Each weight to the nearest step.
    #[default]
    Nearest,
    /// GPTQ with the input moments of calibration scenes ([`calibrate`]); weights without a
    /// moment are rounded to nearest.
    Calibrated(&'m Moments),
}

/// GPTQ damping: this fraction of the mean diagonal of an input moment is added to its
/// diagonal. Measured in docs/QUANTIZATION.md.
pub const GPTQ_DAMPING: f64 = 0.01;

/// Chooses each tensor's storage: everything f32, or int8 for every weight the engine can
/// take as int8 except [`int8_kept_f32`].
pub fn store(
    config: &ModelConfig,
    lowered: Lowered,
    quant: Quant,
    rounding: Rounding<'_>,
) -> Result<BTreeMap<String, Stored>> {
    let kept = int8_kept_f32(config);
    store_keeping(config, lowered, quant, rounding, |name| {
        kept.iter().any(|(kept, _)| *kept == name)
    })
}

/// The tensors that may be stored as int8, with the length of their reduction axis (the
/// inputs one output channel sums over).
pub fn int8_tensors(config: &ModelConfig) -> Result<Vec<(String, usize)>> {
    Ok(crate::writer::tensor_specs(config)?
        .into_iter()
        .filter_map(|spec| {
            let (_, channels) = spec.int8_scales?;
            let elements: usize = spec.dims.iter().product();
            Some((spec.name, elements / channels))
        })
        .collect())
}

/// Runs the f32 model `lowered` on `scenes` and returns the input moments of its
/// int8-capable weights, for [`Rounding::Calibrated`].
#[cfg(feature = "gptq")]
pub fn calibrate(
    config: &ModelConfig,
    lowered: &Lowered,
    scenes: &[crate::run::RunInputs],
    progress: bool,
) -> Result<crate::calibrate::Moments> {
    let f32_file = crate::writer::write_weights_file(
        config,
        &store(config, lowered.clone(), Quant::F32, Rounding::Nearest)?,
    )?;
    crate::calibrate::input_moments(&f32_file, &int8_tensors(config)?, scenes, progress)
}

/// `name`'s weights rounded by GPTQ with its calibration moment; `None` for a weight
/// without one (rounded to nearest).
#[cfg(feature = "gptq")]
fn gptq_rounding(
    moments: &Moments,
    name: &str,
    values: &[f32],
    scales: &[f32],
    axis: ChannelAxis,
) -> Result<Option<Vec<i8>>> {
    let Some(moment) = moments.get(name) else {
        return Ok(None);
    };
    crate::gptq::quantize(values, scales, axis, moment, GPTQ_DAMPING)
        .map(Some)
        .with_context(|| format!("GPTQ rounding of `{name}`"))
}

#[cfg(not(feature = "gptq"))]
fn gptq_rounding(
    moments: &Moments,
    _: &str,
    _: &[f32],
    _: &[f32],
    _: ChannelAxis,
) -> Result<Option<Vec<i8>>> {
    match *moments {}
}

/// [`store`] with a custom choice of the weights kept in f32 in int8 mode (for measuring
/// which layers need it).
pub fn store_keeping(
    config: &ModelConfig,
    lowered: Lowered,
    quant: Quant,
    rounding: Rounding<'_>,
    keep_f32: impl Fn(&str) -> bool + Sync,
) -> Result<BTreeMap<String, Stored>> {
    store_keeping_on(config, lowered, (quant, rounding), keep_f32, 1)
}

/// [`store`] with the tensors shared out over `threads` threads (GPTQ rounds each tensor
/// on its own): the same stored values for any number.
pub fn store_on(
    config: &ModelConfig,
    lowered: Lowered,
    (quant, rounding): (Quant, Rounding<'_>),
    threads: usize,
) -> Result<BTreeMap<String, Stored>> {
    let kept = int8_kept_f32(config);
    let keep = |name: &str| kept.iter().any(|(kept, _)| *kept == name);
    store_keeping_on(config, lowered, (quant, rounding), keep, threads)
}

fn store_keeping_on(
    config: &ModelConfig,
    lowered: Lowered,
    (quant, rounding): (Quant, Rounding<'_>),
    keep_f32: impl Fn(&str) -> bool + Sync,
    threads: usize,
) -> Result<BTreeMap<String, Stored>> {
    let specs = crate::writer::tensor_specs(config)?;
    let names: Vec<String> = lowered.keys().cloned().collect();
    // Each tensor's values, taken (not copied) by the thread that stores it.
    let inputs: Vec<Mutex<Option<Vec<f32>>>> = lowered
        .into_values()
        .map(|values| Mutex::new(Some(values)))
        .collect();
    let outputs: Vec<Mutex<Option<Result<Stored>>>> =
        names.iter().map(|_| Mutex::new(None)).collect();
    let next = AtomicUsize::new(0);
    let work = || {
        loop {
            let index = next.fetch_add(1, Ordering::Relaxed);
            let Some(name) = names.get(index) else {
                return;
            };
            let values = inputs[index]
                .lock()
                .expect("a tensor")
                .take()
                .expect("taken once");
            let result = store_tensor(&specs, name, values, (quant, rounding), &keep_f32);
            *outputs[index].lock().expect("a tensor's result") = Some(result);
        }
    };
    std::thread::scope(|scope| {
        for _ in 1..threads.max(1) {
            scope.spawn(work);
        }
        work();
    });
    let mut stored = BTreeMap::new();
    for (name, output) in names.into_iter().zip(outputs) {
        let tensor = output
            .into_inner()
            .expect("a tensor's result")
            .expect("every tensor stored")?;
        stored.insert(name, tensor);
    }
    Ok(stored)
}

/// How `name` (lowered to `values`) is stored.
fn store_tensor(
    specs: &[crate::writer::TensorSpec],
    name: &str,
    values: Vec<f32>,
    (quant, rounding): (Quant, Rounding<'_>),
    keep_f32: &(impl Fn(&str) -> bool + Sync),
) -> Result<Stored> {
    let spec = specs.iter().find(|spec| spec.name == name);
    let int8_channels =
        spec.and_then(|spec| spec.int8_scales.as_ref().map(|(_, channels)| *channels));
    // The engine's exact int8 sums reach `MAX_DIGIT_CHANNELS` inputs (the widest
    // product layer has 768); a wider convolution stays f32.
    let too_wide = spec.is_some_and(|spec| !scdp_engine::kernels::int8_fits(&spec.dims));
    let keep = keep_f32(name) || too_wide;
    let tensor = match (quant, int8_channels, spec) {
        (Quant::Int8, Some(channels), Some(spec)) if !keep => {
            let axis = if name.ends_with(".film.weight") {
                ChannelAxis::First
            } else {
                ChannelAxis::Last
            };
            let (mut quantized, scales) = quantize_per_channel(&values, channels, axis);
            if let Rounding::Calibrated(moments) = rounding
                && let Some(rounded) = gptq_rounding(moments, name, &values, &scales, axis)?
            {
                quantized = rounded;
            }
            // The trunk's residual-block convolutions may be refined by a second plane
            // (whether they are is measured later, `crate::refine`): what the rounding
            // left.
            let residual = may_refine(name, spec.narrow)
                .then(|| residual_plane(&values, &quantized, &scales, axis));
            // Convolutions take int8 activations: their kernels go to the layout of the
            // integer dot products (docs/FORMAT.md); FiLM matrices stay as they are.
            let (values, residual) = match scdp_engine::kernels::int8_convolution(&spec.dims) {
                Some((_, input, output)) => {
                    let stored = scdp_engine::kernels::int8_stored_elements(&spec.dims)
                        .with_context(|| format!("size of `{name}`"))?;
                    let pack = |values: &[i8]| {
                        let mut packed = vec![0i8; stored];
                        scdp_engine::kernels::pack_int8_quads(values, input, output, &mut packed);
                        packed
                    };
                    let residual = residual.map(|residual| ResidualPlane {
                        values: pack(&residual.values),
                        scales: residual.scales,
                    });
                    (pack(&quantized), residual)
                }
                None => (quantized, residual),
            };
            Stored::Int8 {
                values,
                scales,
                activations: ActivationCodes::Wide,
                residual,
                refined: false,
            }
        }
        _ => Stored::F32(values),
    };
    Ok(tensor)
}

/// The weights file for `config` holding `state` (a state dict that passed
/// [`crate::keys::check_keys`]) at precision `quant`.
pub fn lower_to_weights_file(
    config: &ModelConfig,
    state: &impl StateDictLookup,
    quant: Quant,
) -> Result<Vec<u8>> {
    crate::writer::write_weights_file(
        config,
        &store(config, lower(config, state)?, quant, Rounding::Nearest)?,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The two planes give back every weight within half the residual's step, and that step
    /// is at most 1/254 of the first plane's (the first plane leaves at most half a step,
    /// spread over 127 steps).
    #[test]
    fn the_residual_plane_takes_the_weights_to_about_15_bits() {
        let (channels, inputs) = (6, 50);
        let values: Vec<f32> = (0..channels * inputs)
            .map(|index| {
                ((index * 7919 % 1000) as f32 / 500.0 - 1.0) * (1 + index % channels) as f32
            })
            .collect();
        for axis in [ChannelAxis::Last, ChannelAxis::First] {
            let channel_of = |index: usize| match axis {
                ChannelAxis::Last => index % channels,
                ChannelAxis::First => index / inputs,
            };
            let (quantized, scales) = quantize_per_channel(&values, channels, axis);
            let residual = residual_plane(&values, &quantized, &scales, axis);
            for (residual_scale, scale) in residual.scales.iter().zip(&scales) {
                let ratio = residual_scale / scale;
                assert!(ratio > 0.0 && ratio <= (1.0 + 1e-5) / 254.0, "{ratio}");
            }
            for (index, &value) in values.iter().enumerate() {
                let channel = channel_of(index);
                let refined = f64::from(quantized[index]) * f64::from(scales[channel])
                    + f64::from(residual.values[index]) * f64::from(residual.scales[channel]);
                let error = (refined - f64::from(value)).abs();
                let bound = 0.5 * f64::from(residual.scales[channel]) * (1.0 + 1e-5);
                assert!(error <= bound, "{index}: {error} > {bound}");
            }
        }
    }
}
