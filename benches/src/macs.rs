//! Multiply-accumulates and weight bytes of one inference, layer by layer, from a
//! [`ModelConfig`]: the work the kernels cannot avoid, to set measured latencies against the
//! core's peak rates (`cargo run -p scdp-benches --release --bin macs`).
//!
//! Convention (PyTorch's `torch.utils.flop_counter`, which the tests check against): a
//! convolution costs `output positions x kernel taps x in x out` MACs, taps that fall on the
//! zero padding included; a transposed convolution costs `input positions x taps x in x out`.
//! A linear layer or matrix-vector product costs `rows x columns`. Normalizations,
//! activations, pooling and additions are not MACs and are left out (they are element-wise,
//! a few operations per value, far below the convolutions).
//!
//! What the engine computes differs from the PyTorch module in two places. The FiLM layers'
//! time-embedding half (and the step encoder before it) depends only on the step, so the
//! weights tool precomputes it per step (`film.table`); per step only the `[2 out, g]` part
//! runs. [`Stage::Film`] counts that part; [`torch_only_per_step`] the rest. And the
//! transposed convolutions run as the tool lowers them, ordinary convolutions of 2 taps and
//! twice the output channels at one more position than their input: counted as such, their
//! excess over PyTorch's count (that extra position) is [`engine_only_per_step`].

use scdp_engine::ModelConfig;
use scdp_engine::config::{PYRAMID_LEVELS, UNET_LEVELS};

/// Where a layer runs: once per frame, or once per denoising step.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Stage {
    /// The 7x7 stride-2 stem convolution.
    Stem,
    /// ResNet stage `n` (`layer1` .. `layer4`): BasicBlocks with their downsample convs.
    Layer(u8),
    /// The five 3x3 projections to `feature_dim`.
    Projections,
    /// U-Net down level `n`: two residual blocks' convolutions, then the stride-2 conv.
    Down(u8),
    /// The two middle residual blocks.
    Mid,
    /// U-Net up level `n`: two residual blocks' convolutions, then the transposed conv.
    Up(u8),
    /// The head: Conv1dBlock and the 1x1 convolution to `action_dim`.
    Final,
    /// Every residual block's FiLM matrix-vector product (global-condition part).
    Film,
    /// Anchors, bilinear pooling of the context and the DDIM update.
    Conditioning,
}

impl Stage {
    /// Whether the stage runs once per frame (else once per denoising step).
    pub fn per_frame(self) -> bool {
        matches!(self, Stage::Stem | Stage::Layer(_) | Stage::Projections)
    }

    pub fn label(self) -> String {
        match self {
            Stage::Stem => "trunk stem 7x7/2".to_owned(),
            Stage::Layer(n) => format!("trunk layer{n}"),
            Stage::Projections => "projections 3x3 -> d".to_owned(),
            Stage::Down(n) => format!("U-Net down {n}"),
            Stage::Mid => "U-Net mid".to_owned(),
            Stage::Up(n) => format!("U-Net up {n}"),
            Stage::Final => "U-Net head".to_owned(),
            Stage::Film => "FiLM matvecs".to_owned(),
            Stage::Conditioning => "anchors, pooling, DDIM".to_owned(),
        }
    }
}

/// One layer: its MACs per run of its stage and the weight values it reads.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Layer {
    pub stage: Stage,
    pub name: String,
    pub macs: u64,
    /// Values of the weight matrix or kernel (biases and norm parameters not included).
    pub weights: u64,
}

fn layer(stage: Stage, name: String, macs: usize, weights: usize) -> Layer {
    Layer {
        stage,
        name,
        macs: macs as u64,
        weights: weights as u64,
    }
}

/// A 2-D convolution over an `[height, width]` output.
fn conv2d(
    stage: Stage,
    name: String,
    (out_height, out_width): (usize, usize),
    kernel: usize,
    in_channels: usize,
    out_channels: usize,
) -> Layer {
    let weights = kernel * kernel * in_channels * out_channels;
    layer(stage, name, out_height * out_width * weights, weights)
}

/// A 1-D convolution over `length` output positions.
fn conv1d(
    stage: Stage,
    name: String,
    length: usize,
    kernel: usize,
    in_channels: usize,
    out_channels: usize,
) -> Layer {
    let weights = kernel * in_channels * out_channels;
    layer(stage, name, length * weights, weights)
}

fn halve(size: (usize, usize)) -> (usize, usize) {
    // A 3x3 stride-2 convolution with padding 1 (and the 1x1 stride-2 shortcut) both give
    // ceil(n / 2), PyTorch's floor((n + 2 - 3) / 2) + 1.
    (size.0.div_ceil(2), size.1.div_ceil(2))
}

/// The layers run once per frame: trunk and projections.
pub fn frame_layers(config: &ModelConfig) -> Vec<Layer> {
    let mut layers = Vec::new();
    let width = config.backbone_width as usize;
    let image = (config.image_height as usize, config.image_width as usize);
    let stem = (image.0.div_ceil(2), image.1.div_ceil(2));
    layers.push(conv2d(Stage::Stem, "conv1".into(), stem, 7, 3, width));
    // The 3x3 stride-2 max pool.
    let mut size = halve(stem);
    let mut taps = vec![(size, width)];
    let mut channels = width;
    for stage in 1..=4u8 {
        let out_channels = width << (stage - 1);
        for block in 0..2 {
            let downsample = block == 0 && stage > 1;
            let out_size = if downsample { halve(size) } else { size };
            let name = |conv: &str| format!("layer{stage}.{block}.{conv}");
            let stage = Stage::Layer(stage);
            layers.push(conv2d(
                stage,
                name("conv1"),
                out_size,
                3,
                channels,
                out_channels,
            ));
            layers.push(conv2d(
                stage,
                name("conv2"),
                out_size,
                3,
                out_channels,
                out_channels,
            ));
            if downsample {
                layers.push(conv2d(
                    stage,
                    name("downsample"),
                    out_size,
                    1,
                    channels,
                    out_channels,
                ));
            }
            (size, channels) = (out_size, out_channels);
        }
        taps.push((size, channels));
    }
    let feature_dim = config.feature_dim as usize;
    for (level, (size, channels)) in taps.into_iter().enumerate() {
        layers.push(conv2d(
            Stage::Projections,
            format!("proj.{level}"),
            size,
            3,
            channels,
            feature_dim,
        ));
    }
    layers
}

/// The layers run once per denoising step: the U-Net as the engine runs it, the FiLM
/// products and the per-step conditioning.
pub fn step_layers(config: &ModelConfig) -> Vec<Layer> {
    let mut layers = Vec::new();
    let kernel = config.kernel_size as usize;
    let horizon = config.horizon as usize;
    let dims = config.down_dims.map(|d| d as usize);
    let cond = config.global_cond_dim();
    // Conv1dBlock(in -> out), FiLM(out), Conv1dBlock(out -> out), 1x1 residual if in != out.
    let residual_block = |layers: &mut Vec<Layer>,
                          stage: Stage,
                          name: String,
                          length: usize,
                          in_channels: usize,
                          out_channels: usize| {
        let conv = |conv: &str, input: usize| {
            conv1d(
                stage,
                format!("{name}.{conv}"),
                length,
                kernel,
                input,
                out_channels,
            )
        };
        layers.push(conv("conv0", in_channels));
        layers.push(conv("conv1", out_channels));
        if in_channels != out_channels {
            layers.push(conv1d(
                stage,
                format!("{name}.residual"),
                length,
                1,
                in_channels,
                out_channels,
            ));
        }
        let film = 2 * out_channels * cond;
        layers.push(layer(Stage::Film, format!("{name}.film"), film, film));
    };

    let mut level_in = config.action_dim as usize;
    for (level, &channels) in dims.iter().enumerate() {
        let length = horizon >> level;
        let stage = Stage::Down(level as u8);
        let name = |block: usize| format!("down.{level}.{block}");
        residual_block(&mut layers, stage, name(0), length, level_in, channels);
        residual_block(&mut layers, stage, name(1), length, channels, channels);
        if level + 1 < UNET_LEVELS {
            let name = format!("down.{level}.downsample");
            layers.push(conv1d(stage, name, length / 2, 3, channels, channels));
        }
        level_in = channels;
    }
    let deepest = dims[UNET_LEVELS - 1];
    let bottom = horizon >> (UNET_LEVELS - 1);
    for block in 0..2 {
        let name = format!("mid.{block}");
        residual_block(&mut layers, Stage::Mid, name, bottom, deepest, deepest);
    }
    for index in 0..UNET_LEVELS - 1 {
        let level = UNET_LEVELS - 2 - index;
        let length = horizon >> (level + 1);
        let stage = Stage::Up(index as u8);
        let (below, channels) = (dims[level + 1], dims[level]);
        let name = |block: usize| format!("up.{index}.{block}");
        residual_block(&mut layers, stage, name(0), length, 2 * below, channels);
        residual_block(&mut layers, stage, name(1), length, channels, channels);
        // ConvTranspose1d(4, stride 2), lowered: 2 taps over its input positions, to twice
        // the channels, at one more position than the input has.
        let name = format!("up.{index}.upsample");
        layers.push(conv1d(stage, name, length + 1, 2, channels, 2 * channels));
    }
    let action_dim = config.action_dim as usize;
    layers.push(conv1d(
        Stage::Final,
        "final.conv".into(),
        horizon,
        kernel,
        dims[0],
        dims[0],
    ));
    layers.push(conv1d(
        Stage::Final,
        "final.projection".into(),
        horizon,
        1,
        dims[0],
        action_dim,
    ));

    let anchors = config.anchor_count();
    let frames = config.n_obs_steps as usize;
    let feature_dim = config.feature_dim as usize;
    // Each anchor: R P (9) and the position update (3); each frame, level and anchor: four
    // bilinear taps of d values; DDIM: two multiply-adds per value.
    let anchor_macs = anchors * 12;
    let pooling = frames * PYRAMID_LEVELS * anchors * 4 * feature_dim;
    let ddim = 2 * horizon * action_dim;
    let conditioning = Stage::Conditioning;
    layers.push(layer(conditioning, "anchors".into(), anchor_macs, 0));
    layers.push(layer(conditioning, "bilinear pooling".into(), pooling, 0));
    layers.push(layer(conditioning, "ddim".into(), ddim, 0));
    layers
}

/// MACs per step that PyTorch's module runs and the engine does not (precomputed per step
/// by the weights tool): the step encoder's two linears and the FiLM layers' columns for
/// the time embedding.
pub fn torch_only_per_step(config: &ModelConfig) -> u64 {
    let embed = config.diffusion_step_embed_dim as u64;
    let film_rows: u64 = step_layers(config)
        .iter()
        .filter(|layer| layer.stage == Stage::Film)
        .map(|layer| layer.macs / config.global_cond_dim() as u64)
        .sum();
    2 * embed * 4 * embed + film_rows * embed
}

/// MACs per step that the engine runs and PyTorch's module does not: the lowered transposed
/// convolutions' `(length + 1) x 2 x C x 2C` against PyTorch's `length x 4 x C x C`, the
/// extra position's `4 C^2` (its even half and the odd half of position 0 are discarded).
pub fn engine_only_per_step(config: &ModelConfig) -> u64 {
    (0..UNET_LEVELS - 1)
        .map(|index| {
            let level = UNET_LEVELS - 2 - index;
            let channels = config.down_dims[level] as u64;
            4 * channels * channels
        })
        .sum()
}

/// One row of the per-stage table.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StageCount {
    pub stage: Stage,
    pub macs: u64,
    pub weights: u64,
}

/// Layers summed by stage, in inference order.
pub fn by_stage(layers: &[Layer]) -> Vec<StageCount> {
    let mut rows: Vec<StageCount> = Vec::new();
    for layer in layers {
        match rows.iter_mut().find(|row| row.stage == layer.stage) {
            Some(row) => {
                row.macs += layer.macs;
                row.weights += layer.weights;
            }
            None => rows.push(StageCount {
                stage: layer.stage,
                macs: layer.macs,
                weights: layer.weights,
            }),
        }
    }
    rows.sort_by_key(|row| row.stage);
    rows
}

/// Whole-inference totals.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Totals {
    pub frame_macs: u64,
    pub step_macs: u64,
    /// `n_obs_steps` frames encoded, then every denoising step (a cold start).
    pub end_to_end_macs: u64,
    /// The newest frame only, then every step (steady state).
    pub streaming_macs: u64,
    pub frame_weights: u64,
    pub step_weights: u64,
}

pub fn totals(config: &ModelConfig) -> Totals {
    let sum = |layers: Vec<Layer>| {
        layers
            .iter()
            .fold((0, 0), |(m, w), l| (m + l.macs, w + l.weights))
    };
    let (frame_macs, frame_weights) = sum(frame_layers(config));
    let (step_macs, step_weights) = sum(step_layers(config));
    let steps = config.num_inference_steps as u64;
    Totals {
        frame_macs,
        step_macs,
        end_to_end_macs: config.n_obs_steps as u64 * frame_macs + steps * step_macs,
        streaming_macs: frame_macs + steps * step_macs,
        frame_weights,
        step_weights,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scdp_engine::error::Error;
    use scdp_engine::weights::{ModelWeights, NarrowCodes, TensorSource, Weight};
    use std::fmt;

    /// PyTorch's own count, `torch.utils.flop_counter.FlopCounterMode` over the reference
    /// modules of `tests/reference/` (`python benches/peer/peer.py --flops`), in FLOPs
    /// (2 per MAC): one frame's trunk stages and projections, and one U-Net call (which
    /// includes the step encoder and the whole FiLM linears).
    struct TorchFlops {
        stem: u64,
        layers: [u64; 4],
        projections: u64,
        unet_step: u64,
    }

    const TORCH_METAWORLD: TorchFlops = TorchFlops {
        stem: 77_070_336,
        layers: [301_989_888, 268_435_456, 268_435_456, 268_435_456],
        projections: 217_055_232,
        unet_step: 118_431_744,
    };

    const TORCH_PANDA: TorchFlops = TorchFlops {
        stem: 361_267_200,
        layers: [1_415_577_600, 1_258_291_200, 1_258_291_200, 1_342_177_280],
        projections: 1_020_395_520,
        unet_step: 118_579_200,
    };

    fn stage_macs(layers: &[Layer], wanted: impl Fn(Stage) -> bool) -> u64 {
        layers
            .iter()
            .filter(|layer| wanted(layer.stage))
            .map(|layer| layer.macs)
            .sum()
    }

    fn check_against_torch(config: &ModelConfig, torch: &TorchFlops) {
        let frame = frame_layers(config);
        assert_eq!(
            2 * stage_macs(&frame, |s| s == Stage::Stem),
            torch.stem,
            "stem"
        );
        for (n, &flops) in torch.layers.iter().enumerate() {
            let stage = Stage::Layer(n as u8 + 1);
            assert_eq!(2 * stage_macs(&frame, |s| s == stage), flops, "{stage:?}");
        }
        let projections = stage_macs(&frame, |s| s == Stage::Projections);
        assert_eq!(2 * projections, torch.projections, "projections");
        let step = step_layers(config);
        let unet = stage_macs(&step, |s| s != Stage::Conditioning);
        assert_eq!(
            2 * (unet + torch_only_per_step(config) - engine_only_per_step(config)),
            torch.unet_step,
            "U-Net step"
        );
    }

    #[test]
    fn counts_match_pytorchs_flop_counter() {
        check_against_torch(&ModelConfig::METAWORLD, &TORCH_METAWORLD);
        check_against_torch(&ModelConfig::PANDA, &TORCH_PANDA);
    }

    /// Records every tensor the engine binds, handing out zeros.
    struct Recorder<'z> {
        zeros: &'z [f32],
        tensors: Vec<(String, Vec<usize>)>,
    }

    impl<'z> Recorder<'z> {
        fn record(&mut self, name: fmt::Arguments<'_>, dims: &[usize]) -> &'z [f32] {
            self.tensors.push((name.to_string(), dims.to_vec()));
            &self.zeros[..dims.iter().product::<usize>()]
        }
    }

    impl<'z> TensorSource<'z> for Recorder<'z> {
        fn f32_tensor(
            &mut self,
            name: fmt::Arguments<'_>,
            dims: &[usize],
        ) -> Result<&'z [f32], Error> {
            Ok(self.record(name, dims))
        }

        fn weight(
            &mut self,
            name: fmt::Arguments<'_>,
            _scale_name: fmt::Arguments<'_>,
            dims: &[usize],
            _channels: usize,
            _narrow: NarrowCodes,
        ) -> Result<Weight<'z>, Error> {
            Ok(Weight::F32(self.record(name, dims)))
        }
    }

    /// Every weight matrix or kernel the engine binds (rank >= 2 and named `*.weight`), per
    /// stage: the count's layer list must cover exactly those, value for value.
    fn check_against_bound_weights(config: &ModelConfig) {
        let zeros = vec![0.0f32; 1 << 22];
        let mut recorder = Recorder {
            zeros: &zeros,
            tensors: Vec::new(),
        };
        ModelWeights::bind(config, &mut recorder).expect("bind");
        let bound = |prefix: &str| -> u64 {
            recorder
                .tensors
                .iter()
                .filter(|(name, dims)| {
                    name.starts_with(prefix) && name.ends_with(".weight") && dims.len() >= 2
                })
                .map(|(_, dims)| dims.iter().product::<usize>() as u64)
                .sum()
        };
        let counted = |layers: &[Layer], wanted: &dyn Fn(Stage) -> bool| -> u64 {
            layers
                .iter()
                .filter(|layer| wanted(layer.stage))
                .map(|layer| layer.weights)
                .sum()
        };
        let frame = frame_layers(config);
        let step = step_layers(config);
        assert_eq!(
            counted(&frame, &|s| s != Stage::Projections),
            bound("backbone.")
        );
        assert_eq!(
            counted(&frame, &|s| s == Stage::Projections),
            bound("proj.")
        );
        assert_eq!(
            counted(&step, &|s| s == Stage::Film),
            recorder
                .tensors
                .iter()
                .filter(|(name, _)| name.ends_with(".film.weight"))
                .map(|(_, dims)| dims.iter().product::<usize>() as u64)
                .sum::<u64>()
        );
        assert_eq!(counted(&step, &|_| true), bound("unet."));
    }

    #[test]
    fn weights_cover_every_tensor_the_engine_binds() {
        check_against_bound_weights(&ModelConfig::METAWORLD);
        check_against_bound_weights(&ModelConfig::PANDA);
        check_against_bound_weights(&ModelConfig::TINY);
    }

    #[test]
    fn totals_add_up() {
        let config = ModelConfig::PANDA;
        let totals = totals(&config);
        let by_frame: u64 = by_stage(&frame_layers(&config))
            .iter()
            .map(|row| row.macs)
            .sum();
        assert_eq!(by_frame, totals.frame_macs);
        assert_eq!(
            totals.end_to_end_macs - totals.streaming_macs,
            totals.frame_macs
        );
        assert!(
            by_stage(&step_layers(&config))
                .iter()
                .all(|row| !row.stage.per_frame())
        );
    }
}
