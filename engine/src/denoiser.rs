//! Sample + condition -> predicted noise: Diffusion Policy's ConditionalUnet1D with FiLM
//! (docs/SPEC.md section 4), over `[T, C]` sequences.

use crate::config::{FINAL_BLOCK_GROUPS, ModelConfig, UNET_LEVELS};
use crate::kernels::ops::{self, Activation};
use crate::kernels::{Accumulate, ConvShape, Kernels, QuantizeScratch};
use crate::layer::{self, Activations};
use crate::weights::{Conv, DenoiserWeights, Norm, ResidualBlock, UPSAMPLE_TAPS};

/// The U-Net's buffers (lengths from the arena plan).
pub struct DenoiserScratch<'a> {
    pub work: [&'a mut [f32]; 4],
    /// Outputs of down levels 1 and 2, read again by the up path.
    pub skips: [&'a mut [f32]; UNET_LEVELS - 1],
    /// FiLM scale and bias of the block being run.
    pub film: &'a mut [f32],
    /// A convolution's input quantized for int8 weights.
    pub quantized: QuantizeScratch<'a>,
}

struct Context<'a> {
    kernels: &'a dyn Kernels,
    config: &'a ModelConfig,
    step: usize,
    /// `Mish(g)`: the FiLM layers' input (the time-embedding part is precomputed).
    activated_cond: &'a [f32],
    film: &'a mut [f32],
    quantized: QuantizeScratch<'a>,
}

impl Context<'_> {
    fn convolve(
        &mut self,
        shape: &ConvShape,
        conv: &Conv<'_>,
        input: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        layer::convolve(
            self.kernels,
            shape,
            input,
            &conv.weight,
            conv.bias,
            output,
            accumulate,
            Activations::Codes(&mut self.quantized),
        );
    }

    /// Conv1d(k, padding k/2) -> GroupNorm(groups) -> Mish, `[length, in]` -> `[length, out]`.
    #[allow(clippy::too_many_arguments)]
    fn conv_block(
        &mut self,
        conv: &Conv<'_>,
        norm: &Norm<'_>,
        groups: usize,
        length: usize,
        in_channels: usize,
        input: &[f32],
        output: &mut [f32],
    ) {
        let kernel = self.config.kernel_size as usize;
        let out_channels = norm.gamma.len();
        let shape = ConvShape::sequence(length, in_channels, out_channels, kernel, 1, kernel / 2);
        self.convolve(&shape, conv, input, output, Accumulate::Overwrite);
        let output = &mut output[..shape.output_len()];
        self.kernels.group_norm(
            output,
            out_channels,
            groups,
            (norm.gamma, norm.beta),
            Activation::Mish,
        );
    }

    /// ConditionalResidualBlock1D: `input` `[length, in]` -> `output` `[length, out]`.
    fn residual_block(
        &mut self,
        block: &ResidualBlock<'_>,
        length: usize,
        input: &[f32],
        temporary: &mut [f32],
        output: &mut [f32],
    ) {
        let out_channels = block.out_channels;
        let groups = self.config.n_groups as usize;
        self.conv_block(
            &block.conv0,
            &block.norm0,
            groups,
            length,
            block.in_channels,
            input,
            temporary,
        );
        let film = &mut self.film[..2 * out_channels];
        let base = &block.film_table[self.step * 2 * out_channels..][..2 * out_channels];
        layer::linear(
            self.kernels,
            &block.film_weight,
            self.activated_cond,
            (base, film),
            &mut self.quantized,
        );
        let (scale, bias) = film.split_at(out_channels);
        for position in temporary[..length * out_channels].chunks_exact_mut(out_channels) {
            for ((value, &s), &b) in position.iter_mut().zip(scale).zip(bias) {
                *value = s * *value + b;
            }
        }
        self.conv_block(
            &block.conv1,
            &block.norm1,
            groups,
            length,
            out_channels,
            temporary,
            output,
        );
        let input = &input[..length * block.in_channels];
        match &block.residual {
            Some(residual) => {
                let shape = ConvShape::sequence(length, block.in_channels, out_channels, 1, 1, 0);
                self.convolve(&shape, residual, input, output, Accumulate::Add);
            }
            None => ops::add_activate(
                &mut output[..length * out_channels],
                input,
                Activation::None,
            ),
        }
    }

    /// Conv1d(3, stride 2, padding 1): `[length, channels]` -> `[length / 2, channels]`.
    fn downsample(
        &mut self,
        conv: &Conv<'_>,
        length: usize,
        channels: usize,
        input: &[f32],
        output: &mut [f32],
    ) {
        let shape = ConvShape::sequence(length, channels, channels, 3, 2, 1);
        self.convolve(&shape, conv, input, output, Accumulate::Overwrite);
    }

    /// ConvTranspose1d(4, stride 2, padding 1): `[length, channels]` -> `[2 length, channels]`.
    /// The tool lowered it to a convolution of 2 taps (padding 1) to `2 channels` whose
    /// position `p` holds output `2 p` then output `2 p - 1`: its `length + 1` positions,
    /// once each odd half moves up a position, are `[length, 2 channels]`, which is
    /// `[2 length, channels]`.
    fn upsample(
        &mut self,
        conv: &Conv<'_>,
        length: usize,
        channels: usize,
        input: &[f32],
        output: &mut [f32],
    ) {
        let shape = ConvShape::sequence(length, channels, 2 * channels, UPSAMPLE_TAPS, 1, 1);
        self.convolve(&shape, conv, input, output, Accumulate::Overwrite);
        let wide = 2 * channels;
        for position in 0..length {
            let (this, next) = output[position * wide..][..2 * wide].split_at_mut(wide);
            this[channels..].copy_from_slice(&next[channels..]);
        }
    }
}

/// Interleaves `[length, a]` and `[length, b]` into `[length, a + b]` (torch.cat on channels).
fn concat_channels(
    first: &[f32],
    a: usize,
    second: &[f32],
    b: usize,
    length: usize,
    output: &mut [f32],
) {
    for position in 0..length {
        let out = &mut output[position * (a + b)..][..a + b];
        out[..a].copy_from_slice(&first[position * a..][..a]);
        out[a..].copy_from_slice(&second[position * b..][..b]);
    }
}

/// One U-Net evaluation at inference step `step`: `sample` `[horizon, action_dim]` ->
/// `eps` `[horizon, action_dim]`.
#[allow(clippy::too_many_arguments)]
pub fn predict_noise(
    kernels: &dyn Kernels,
    config: &ModelConfig,
    weights: &DenoiserWeights<'_>,
    step: usize,
    sample: &[f32],
    activated_cond: &[f32],
    scratch: DenoiserScratch<'_>,
    eps: &mut [f32],
) {
    let DenoiserScratch {
        work: [w0, w1, w2, w3],
        skips: [skip1, skip2],
        film,
        quantized,
    } = scratch;
    let mut context = Context {
        kernels,
        config,
        step,
        activated_cond,
        film,
        quantized,
    };
    let horizon = config.horizon as usize;
    let dims = config.down_dims.map(|d| d as usize);
    let [level0, level1, level2] = &weights.down;

    // Down path. The level-0 skip is never read (as in Diffusion Policy), so it is not kept.
    context.residual_block(&level0[0], horizon, sample, w3, w0);
    context.residual_block(&level0[1], horizon, w0, w3, w1);
    context.downsample(&weights.downsample[0], horizon, dims[0], w1, w0);
    let half = horizon / 2;
    context.residual_block(&level1[0], half, w0, w3, w1);
    context.residual_block(&level1[1], half, w1, w3, skip1);
    context.downsample(&weights.downsample[1], half, dims[1], skip1, w0);
    let quarter = horizon / 4;
    context.residual_block(&level2[0], quarter, w0, w3, w1);
    context.residual_block(&level2[1], quarter, w1, w3, skip2);

    context.residual_block(&weights.mid[0], quarter, skip2, w3, w0);
    context.residual_block(&weights.mid[1], quarter, w0, w3, w1);

    // Up path: concatenate the skip of the same resolution, two blocks, upsample.
    concat_channels(w1, dims[2], skip2, dims[2], quarter, w0);
    context.residual_block(&weights.up[0][0], quarter, w0, w3, w1);
    context.residual_block(&weights.up[0][1], quarter, w1, w3, w2);
    context.upsample(&weights.upsample[0], quarter, dims[1], w2, w0);
    concat_channels(w0, dims[1], skip1, dims[1], half, w1);
    context.residual_block(&weights.up[1][0], half, w1, w3, w0);
    context.residual_block(&weights.up[1][1], half, w0, w3, w2);
    context.upsample(&weights.upsample[1], half, dims[0], w2, w0);

    context.conv_block(
        &weights.final_conv,
        &weights.final_norm,
        FINAL_BLOCK_GROUPS,
        horizon,
        dims[0],
        w0,
        w1,
    );
    let action_dim = config.action_dim as usize;
    let shape = ConvShape::sequence(horizon, dims[0], action_dim, 1, 1, 0);
    context.convolve(
        &shape,
        &weights.final_projection,
        w1,
        eps,
        Accumulate::Overwrite,
    );
}
