//! Sample + condition -> predicted noise: Diffusion Policy's ConditionalUnet1D with FiLM
//! (docs/SPEC.md section 4), over `[T, C]` sequences.

use core::ops::Range;

use crate::config::{FINAL_BLOCK_GROUPS, ModelConfig, UNET_LEVELS};
use crate::kernels::board::{self, Board, Collected};
use crate::kernels::ops::{self, Activation};
use crate::kernels::{
    Accumulate, CodeRows, ConvShape, Epilogue, Film, FilmWeights, Kernels, QuantizeScratch,
};
use crate::layer::{self, Activations};
use crate::weights::{Conv, DenoiserWeights, Norm, ResidualBlock, UPSAMPLE_TAPS, Weight};

/// The U-Net's buffers (lengths from the arena plan).
pub struct DenoiserScratch<'a> {
    pub work: [&'a mut [f32]; 4],
    /// Outputs of down levels 1 and 2, read again by the up path.
    pub skips: [&'a mut [f32]; UNET_LEVELS - 1],
    /// FiLM scale and bias of the block being run.
    pub film: &'a mut [f32],
    /// A convolution's input quantized for int8 weights.
    pub quantized: QuantizeScratch<'a>,
    /// The FiLM layers' input quantized for int8 weights, once a step.
    pub cond_codes: QuantizeScratch<'a>,
}

/// Residual blocks of the U-Net: two a level down and up, two in the middle.
const BLOCKS: usize = 2 * (2 * UNET_LEVELS - 1) + 2;

/// FiLM rows a background chunk computes at least.
const CHUNK_ROWS: usize = 64;

/// Where a denoising step cut over several workers ([`Board`]) runs: the board, the
/// kernels its helpers run the FiLM products with, and where those go (every block's `2
/// out` values, in block order).
pub struct Helpers<'h> {
    pub board: &'h Board,
    pub kernels: &'h dyn Kernels,
    pub films: &'h mut [f32],
}

/// Every block's FiLM values, computed in the background: block `b`'s are `ranges[b]` of
/// what `collected` holds once chunk `last[b]` is complete.
struct Films<'f> {
    collected: &'f Collected<'f>,
    ranges: &'f [Range<usize>; BLOCKS],
    last: &'f [usize; BLOCKS],
}

struct Context<'a> {
    kernels: &'a dyn Kernels,
    config: &'a ModelConfig,
    step: usize,
    /// The FiLM values computed in the background, and the residual blocks run so far.
    films: Option<&'a Films<'a>>,
    block: usize,
    /// `Mish(g)`: the FiLM layers' input (the time-embedding part is precomputed).
    activated_cond: &'a [f32],
    /// Its codes, for int8 FiLM weights.
    cond_codes: Option<CodeRows<'a>>,
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

    /// Conv1d(k, padding k/2) -> GroupNorm(groups) -> Mish (-> FiLM), `[length, in]` ->
    /// `[length, out]`.
    #[allow(clippy::too_many_arguments)]
    fn conv_block(
        &mut self,
        conv: &Conv<'_>,
        norm: &Norm<'_>,
        groups: usize,
        (length, in_channels): (usize, usize),
        film: Option<Film<'_>>,
        input: &[f32],
        output: &mut [f32],
    ) {
        let kernel = self.config.kernel_size as usize;
        let out_channels = norm.gamma.len();
        let shape = ConvShape::sequence(length, in_channels, out_channels, kernel, 1, kernel / 2);
        let epilogue = Epilogue {
            groups,
            affine: (norm.gamma, norm.beta),
            activation: Activation::Mish,
            film,
        };
        let output = &mut output[..shape.output_len()];
        let quantized = &mut self.quantized;
        let mut convolve = |kernels: &dyn Kernels, output: &mut [f32]| {
            let codes = Activations::Codes(&mut *quantized);
            let (weight, bias) = (&conv.weight, conv.bias);
            layer::convolve(
                kernels,
                &shape,
                input,
                weight,
                bias,
                output,
                Accumulate::Overwrite,
                codes,
            )
        };
        // A refined layer's second plane adds to the first's output: the epilogue follows
        // both, so the convolution runs whole first.
        let refined = matches!(
            conv.weight,
            Weight::Int8 {
                residual: Some(_),
                ..
            }
        );
        if refined {
            convolve(self.kernels, output);
            return epilogue.apply(self.kernels, out_channels, output, self.film);
        }
        crate::kernels::conv_then(
            self.kernels,
            output,
            out_channels,
            &epilogue,
            self.film,
            &mut convolve,
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
        let index = self.block;
        self.block += 1;
        let film = match self.films {
            Some(films) if index < BLOCKS => Film {
                weights: FilmWeights::Computed,
                base: &films.collected.complete(films.last[index])[films.ranges[index].clone()],
            },
            _ => block_film(block, self.step, self.activated_cond, self.cond_codes),
        };
        self.conv_block(
            &block.conv0,
            &block.norm0,
            groups,
            (length, block.in_channels),
            Some(film),
            input,
            temporary,
        );
        self.conv_block(
            &block.conv1,
            &block.norm1,
            groups,
            (length, out_channels),
            None,
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

/// The FiLM product of `block` at inference step `step`.
fn block_film<'b>(
    block: &ResidualBlock<'b>,
    step: usize,
    activated_cond: &'b [f32],
    cond_codes: Option<CodeRows<'b>>,
) -> Film<'b> {
    let rows = 2 * block.out_channels;
    let base = &block.film_table[step * rows..][..rows];
    // No condition, no codes: FiLM is then its base.
    let no_codes = CodeRows {
        codes: &[],
        scale: 0.0,
    };
    let weights = match &block.film_weight {
        Weight::F32(weight) => FilmWeights::F32 {
            weight,
            input: activated_cond,
        },
        Weight::Int8 { values, scales, .. } => FilmWeights::Int8 {
            weight: values,
            row_scales: scales,
            input: cond_codes.unwrap_or(no_codes),
        },
    };
    Film { weights, base }
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
/// `eps` `[horizon, action_dim]`. With `helpers`, every block's FiLM product runs in the
/// background on the board's other workers while the blocks before it run.
#[allow(clippy::too_many_arguments)]
pub fn predict_noise(
    kernels: &dyn Kernels,
    config: &ModelConfig,
    weights: &DenoiserWeights<'_>,
    step: usize,
    sample: &[f32],
    activated_cond: &[f32],
    scratch: DenoiserScratch<'_>,
    helpers: Option<Helpers<'_>>,
    eps: &mut [f32],
) {
    let DenoiserScratch {
        work,
        skips,
        film,
        quantized,
        mut cond_codes,
    } = scratch;
    let blocks = || {
        let down = weights.down.iter().flatten();
        down.chain(&weights.mid).chain(weights.up.iter().flatten())
    };
    // Every block's FiLM reads the same condition: quantized once.
    let int8_film = blocks().any(|block| matches!(block.film_weight, Weight::Int8 { .. }));
    let cond_codes = (int8_film && !activated_cond.is_empty())
        .then(|| cond_codes.quantize_codes(kernels, activated_cond, activated_cond.len()));
    // Each block's `2 out` FiLM rows cut into chunks of at least CHUNK_ROWS, few enough
    // for the board (each block's last chunk may be short); where they do not fit, the
    // epilogues compute them.
    let total: usize = blocks().map(|block| 2 * block.out_channels).sum();
    let chunk_rows = CHUNK_ROWS.max(total.div_ceil(board::MAX_CHUNKS - BLOCKS));
    let mut chunks = heapless::Vec::<Range<usize>, { board::MAX_CHUNKS }>::new();
    let mut ranges: [Range<usize>; BLOCKS] = core::array::from_fn(|_| 0..0);
    let mut last = [0usize; BLOCKS];
    let mut start = 0;
    for (index, block) in blocks().enumerate().take(BLOCKS) {
        let rows = 2 * block.out_channels;
        ranges[index] = start..start + rows;
        for row in (0..rows).step_by(chunk_rows.max(1)) {
            let end = (row + chunk_rows).min(rows);
            if chunks.push(start + row..start + end).is_err() {
                break;
            }
        }
        last[index] = chunks.len().saturating_sub(1);
        start += rows;
    }
    let planned = chunks.last().is_some_and(|chunk| chunk.end == start);
    // The arena plan holds every block's FiLM values (`ArenaPlan::unet_films`).
    debug_assert!(
        helpers
            .as_ref()
            .is_none_or(|helpers| helpers.films.len() >= start)
    );
    let helpers = helpers.filter(|helpers| planned && helpers.films.len() >= start);
    let Some(Helpers {
        board,
        kernels: helper_kernels,
        films,
    }) = helpers
    else {
        let mut context = Context {
            kernels,
            config,
            step,
            films: None,
            block: 0,
            activated_cond,
            cond_codes,
            film,
            quantized,
        };
        return run_unet(&mut context, weights, sample, work, skips, eps);
    };
    let all: heapless::Vec<&ResidualBlock<'_>, BLOCKS> = blocks().take(BLOCKS).collect();
    let film_rows = |chunk: usize, values: &mut [f32]| {
        let range = &chunks[chunk];
        // The block whose rows hold the chunk (chunks never span two).
        let Some(index) = ranges.iter().position(|rows| rows.contains(&range.start)) else {
            return;
        };
        let Some(block) = all.get(index) else {
            return;
        };
        let rows = range.start - ranges[index].start..range.end - ranges[index].start;
        block_film(block, step, activated_cond, cond_codes).rows(helper_kernels, rows, values);
    };
    board.with_background(&mut films[..start], &chunks, &film_rows, |_, collected| {
        let films = Films {
            collected,
            ranges: &ranges,
            last: &last,
        };
        let mut context = Context {
            kernels,
            config,
            step,
            films: Some(&films),
            block: 0,
            activated_cond,
            cond_codes,
            film,
            quantized,
        };
        run_unet(&mut context, weights, sample, work, skips, eps)
    });
}

/// The U-Net's layers, `sample` -> `eps`.
fn run_unet(
    context: &mut Context<'_>,
    weights: &DenoiserWeights<'_>,
    sample: &[f32],
    [w0, w1, w2, w3]: [&mut [f32]; 4],
    [skip1, skip2]: [&mut [f32]; UNET_LEVELS - 1],
    eps: &mut [f32],
) {
    let config = context.config;
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
        (horizon, dims[0]),
        None,
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
