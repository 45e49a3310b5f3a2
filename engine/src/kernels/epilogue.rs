//! What follows each of the U-Net's convolution blocks: GroupNorm over its output, an
//! activation, then FiLM (`scale x + bias`, the scale and bias a matrix-vector product of
//! the condition). Each group's moments come from its own channels alone, and each FiLM row
//! is one sum, so a block of output channels that holds whole groups can run it alone with
//! the bits of the whole output: [`Split`](super::Split) runs it on each block of a
//! convolution cut by channels, on the core that computed the block, which keeps the
//! values in that core's caches and takes GroupNorm off the calling core.

use core::ops::Range;

use super::ops::Activation;
use super::{CodeRows, Kernels};

/// The weights of FiLM's `[2 channels, cols]` product (scale rows, then bias rows) and the
/// input it multiplies.
#[derive(Clone, Copy, Debug)]
pub enum FilmWeights<'a> {
    F32 {
        weight: &'a [f32],
        input: &'a [f32],
    },
    /// Int8 rows ([`Kernels::matvec_int8_codes`]) on the input's codes.
    Int8 {
        weight: &'a [i8],
        row_scales: &'a [f32],
        input: CodeRows<'a>,
    },
    /// Computed already ([`Film::rows`] of the weights above): the base holds FiLM's values.
    Computed,
}

/// FiLM after the activation: `x = scale x + bias`, `[scale; bias] = base + W input`.
#[derive(Clone, Copy, Debug)]
pub struct Film<'a> {
    pub weights: FilmWeights<'a>,
    /// `2 channels` values: the products are added to them.
    pub base: &'a [f32],
}

impl Film<'_> {
    /// FiLM's values for rows `rows` into `output`: each row one sum, whatever the rows
    /// asked together.
    pub fn rows(&self, kernels: &dyn Kernels, rows: Range<usize>, output: &mut [f32]) {
        let base = &self.base[rows.clone()];
        match self.weights {
            FilmWeights::Computed => output.copy_from_slice(base),
            FilmWeights::F32 { weight, input } => {
                let cols = input.len();
                let weight = &weight[rows.start * cols..rows.end * cols];
                kernels.matvec(weight, input, base, output)
            }
            // No codes to make of no input: the sums are empty.
            FilmWeights::Int8 { input, .. } if input.codes.is_empty() => {
                output.copy_from_slice(base)
            }
            FilmWeights::Int8 {
                weight,
                row_scales,
                input,
            } => {
                let cols = weight.len() / self.base.len().max(1);
                let weight = &weight[rows.start * cols..rows.end * cols];
                kernels.matvec_int8_codes(weight, &row_scales[rows], &input, base, output)
            }
        }
    }
}

/// GroupNorm over `groups` groups of a `[positions, channels]` output (`affine` its gamma
/// and beta), `activation`, then FiLM where given.
#[derive(Clone, Copy, Debug)]
pub struct Epilogue<'a> {
    pub groups: usize,
    pub affine: (&'a [f32], &'a [f32]),
    pub activation: Activation,
    pub film: Option<Film<'a>>,
}

impl Epilogue<'_> {
    /// Channels of a group, of an output of `channels`.
    pub(crate) fn group_size(&self, channels: usize) -> usize {
        channels / self.groups.max(1)
    }

    /// Runs on output channels `block_channels` (whole groups) of an output of `channels`,
    /// held in `block` (`[positions, block_channels.len()]`); `film` takes those channels'
    /// FiLM scales, then their biases (`2 block_channels.len()` values).
    pub(crate) fn run(
        &self,
        kernels: &dyn Kernels,
        channels: usize,
        block_channels: Range<usize>,
        block: &mut [f32],
        film: &mut [f32],
    ) {
        let width = block_channels.len();
        let groups = width / self.group_size(channels).max(1);
        let (gamma, beta) = self.affine;
        let affine = (
            &gamma[block_channels.clone()],
            &beta[block_channels.clone()],
        );
        kernels.group_norm(block, width, groups, affine, self.activation);
        let Some(rows) = self.film else {
            return;
        };
        let film = &mut film[..2 * width];
        if width == channels {
            rows.rows(kernels, 0..2 * channels, film);
        } else {
            let (scale, bias) = film.split_at_mut(width);
            rows.rows(kernels, block_channels.clone(), scale);
            let bias_rows = channels + block_channels.start..channels + block_channels.end;
            rows.rows(kernels, bias_rows, bias);
        }
        let (scale, bias) = film.split_at(width);
        for position in block.chunks_exact_mut(width) {
            for ((value, &s), &b) in position.iter_mut().zip(scale).zip(bias) {
                *value = s * *value + b;
            }
        }
    }

    /// Runs on a whole `[positions, channels]` output; `film` is scratch for FiLM's `2
    /// channels` scales and biases.
    pub fn apply(
        &self,
        kernels: &dyn Kernels,
        channels: usize,
        output: &mut [f32],
        film: &mut [f32],
    ) {
        self.run(kernels, channels, 0..channels, output, film)
    }
}

/// A 1-D convolution's `[positions, channels]` output, then `epilogue` on it: `conv` makes
/// the convolution (one call, with [`Accumulate::Overwrite`](super::Accumulate)) through
/// the kernels it is handed, into the output it is handed; `film` is scratch for FiLM's
/// `2 channels` scales and biases. Kernels that cut calls over workers ([`Split`](super::Split))
/// run the epilogue on each block of channels as it is computed: the same bits.
pub fn conv_then(
    kernels: &dyn Kernels,
    output: &mut [f32],
    channels: usize,
    epilogue: &Epilogue<'_>,
    film: &mut [f32],
    conv: &mut dyn FnMut(&dyn Kernels, &mut [f32]),
) {
    if !kernels.conv_then(output, channels, epilogue, film, conv) {
        conv(kernels, output);
        epilogue.apply(kernels, channels, output, film);
    }
}
