//! The f32 2-D convolution both x86-64 backends run: one generic body over a vector width
//! ([`Lanes`]: YMM for AVX2, ZMM for AVX-512, as the U-Net kernels of `sequence` are),
//! instantiated inside each backend's thin `#[target_feature]` wrapper, where
//! `#[inline(always)]` lets the intrinsics compile with that backend's instructions.
//!
//! A tile is `N` consecutive output positions (row-major, wrapping onto the next row) x `V`
//! vectors of output channels. Per input channel and tap, `V` weight loads feed `V` FMAs per
//! pixel whose tap is inside the input ([`tap_offsets`]); padding taps are skipped per pixel
//! as the scalar reference skips them. Every pixel is therefore one FMA chain over its
//! inside taps, in tap and input-channel order from zero, then the bias is added, whichever
//! tile computes it: the single-pixel path ([`conv_pixel`]) is the one-pixel tile and gives
//! the same bits.

use super::lanes::Lanes;

use super::{prefetch_lines, tap_offsets};
use crate::kernels::{Accumulate, ConvShape};

/// Output positions `first .. first + count` (`count <= N`, row-major over the output map,
/// so a tile may wrap onto the next row and small maps fill whole tiles) x `V WIDTH`
/// channels from `channel`: `sums` (zero, or the partial sums of the taps before) plus the
/// products of `taps`.
///
/// A kernel row whose taps are all inside the input for every pixel (or, for some, all in
/// the vertical padding) is one run of `kernel_width x in_channels` consecutive input values
/// per pixel (channels-last), and its weights are as many consecutive rows: it is walked as
/// one long tap, in the same tap and channel order, so the same bits. For the stem (7x7 over
/// 3 channels) that is a loop of 21 instead of seven loops of 3.
///
/// # Safety
/// The CPU supports `L`; the slices have the lengths `shape` implies; the pixels are in the
/// output; `channel + V WIDTH <= out_channels`.
#[inline(always)]
unsafe fn tile<L: Lanes, const N: usize, const V: usize>(
    shape: &ConvShape,
    (input, weight): (&[f32], &[f32]),
    (first, count): (usize, usize),
    channel: usize,
    (taps, mut sums): (Taps, [[L::Vector; V]; N]),
) -> [[L::Vector; V]; N] {
    let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
    let kernel_width = shape.kernel_width;
    let out_width = shape.out_width();
    // Stepped rather than divided per slot: two divisions per slot were a visible part of
    // the stem's short runs.
    let mut pixels = [(0, 0); N];
    let (mut out_y, mut out_x) = (first / out_width, first % out_width);
    for pixel in &mut pixels {
        *pixel = (out_y, out_x);
        out_x += 1;
        if out_x == out_width {
            (out_y, out_x) = (out_y + 1, 0);
        }
    }
    let whole = taps.columns == (0..kernel_width);
    for kernel_y in taps.rows {
        let row_taps = (kernel_y * kernel_width) * in_channels * out_channels + channel;
        if let Some(row_first) = whole_rows::<N>(shape, &pixels, count, kernel_y).filter(|_| whole)
        {
            let run = (row_taps, kernel_width * in_channels);
            // SAFETY: every used pixel's run of the kernel row is inside the input; the
            // caller's promises cover the rest.
            unsafe {
                accumulate_run::<L, N, V>(&mut sums, (input, weight), row_first, run, out_channels)
            };
            continue;
        }
        for kernel_x in taps.columns.clone() {
            let offsets = tap_offsets::<N>(shape, &pixels, count, (kernel_y, kernel_x));
            let run = (
                row_taps + kernel_x * in_channels * out_channels,
                in_channels,
            );
            // SAFETY: `tap_offsets` gives pixels inside the input, or `None`.
            unsafe {
                accumulate_run::<L, N, V>(&mut sums, (input, weight), offsets, run, out_channels)
            };
        }
    }
    sums
}

/// Where each pixel's run of kernel row `kernel_y` starts, if every used pixel either has
/// the whole row inside the input or has it entirely in the vertical padding (`None`: it
/// skips every tap of the row, as the reference does); `None` if some pixel has only part
/// of the row inside, which then goes tap by tap.
#[inline(always)]
fn whole_rows<const N: usize>(
    shape: &ConvShape,
    pixels: &[(usize, usize); N],
    count: usize,
    kernel_y: usize,
) -> Option<[Option<usize>; N]> {
    let mut offsets = [None; N];
    for (offset, &(out_y, out_x)) in offsets.iter_mut().zip(pixels).take(count) {
        let in_y = (out_y * shape.stride + kernel_y).checked_sub(shape.padding_height);
        let Some(in_y) = in_y.filter(|&y| y < shape.in_height) else {
            continue;
        };
        let in_x = (out_x * shape.stride).checked_sub(shape.padding_width)?;
        if in_x + shape.kernel_width > shape.in_width {
            return None;
        }
        *offset = Some((in_y * shape.in_width + in_x) * shape.in_channels);
    }
    Some(offsets)
}

/// Weight rows [`accumulate_run`] prefetches ahead of the one it reads.
const PREFETCH_ROWS: usize = 8;

/// Adds to `sums` the products of `length` consecutive input values from each pixel's
/// offset (pixels with `None` skipped) by as many weight rows from `first_weight`, in order.
///
/// # Safety
/// The CPU supports `L`; each `Some` offset starts `length` input values; the weight rows
/// `first_weight + i out_channels .. + V WIDTH` for `i < length` are inside `weight`.
#[inline(always)]
unsafe fn accumulate_run<L: Lanes, const N: usize, const V: usize>(
    sums: &mut [[L::Vector; V]; N],
    (input, weight): (&[f32], &[f32]),
    offsets: [Option<usize>; N],
    run: (usize, usize),
    out_channels: usize,
) {
    // Two copies of the loop: a test per pixel and row in the common case, where every
    // pixel reads, was a branch next to every four FMAs, on a port the FMAs use.
    let skipping = offsets.iter().any(Option::is_none);
    let offsets = offsets.map(|offset| offset.unwrap_or(usize::MAX));
    // SAFETY: the caller's promises; `usize::MAX` marks the pixels to skip.
    unsafe {
        if skipping {
            accumulate_rows::<L, N, V, true>(sums, (input, weight), offsets, run, out_channels)
        } else {
            accumulate_rows::<L, N, V, false>(sums, (input, weight), offsets, run, out_channels)
        }
    }
}

/// [`accumulate_run`]'s loop; with `SKIPPING`, offsets of `usize::MAX` are skipped.
///
/// # Safety
/// As for [`accumulate_run`], each offset other than `usize::MAX` (with `SKIPPING`; every
/// offset without) starting `length` input values.
#[inline(always)]
unsafe fn accumulate_rows<L: Lanes, const N: usize, const V: usize, const SKIPPING: bool>(
    sums: &mut [[L::Vector; V]; N],
    (input, weight): (&[f32], &[f32]),
    offsets: [usize; N],
    (first_weight, length): (usize, usize),
    out_channels: usize,
) {
    for index in 0..length {
        // SAFETY: each read offset starts `length` input values; the weight row of V WIDTH
        // channels is inside `weight` (the caller's promises).
        unsafe {
            let row = weight.as_ptr().add(first_weight + index * out_channels);
            // Rows lie `out_channels` floats apart, a power of two that crowds them into a
            // few L1 sets, so most come from L2: ask for them a few rows ahead. A hint only
            // (it never faults), hence the wrapping address.
            let ahead = row.wrapping_add(PREFETCH_ROWS * out_channels);
            for vector in 0..V {
                prefetch_lines(ahead.wrapping_add(vector * L::WIDTH), 1);
            }
            let mut lanes = [L::zero(); V];
            for (vector, lane) in lanes.iter_mut().enumerate() {
                *lane = L::load(row.add(vector * L::WIDTH));
            }
            let values = input.as_ptr().add(index);
            for (&offset, sum) in offsets.iter().zip(sums.iter_mut()) {
                if SKIPPING && offset == usize::MAX {
                    continue;
                }
                let value = L::splat(*values.add(offset));
                for (sum, &lane) in sum.iter_mut().zip(&lanes) {
                    *sum = L::fma(value, lane, *sum);
                }
            }
        }
    }
}

/// Adds the bias of output channels `channel..` (and the existing output with
/// [`Accumulate::Add`]) and stores the pixels of a tile from `first_pixel`, at `column` of
/// output rows `out_stride` floats long.
///
/// # Safety
/// The CPU supports `L`; `column + V WIDTH <= out_stride`; the pixels are inside `output`.
#[inline(always)]
unsafe fn store_tile<L: Lanes, const V: usize>(
    sums: &[[L::Vector; V]],
    (bias, output): (&[f32], &mut [f32]),
    out_stride: usize,
    (first_pixel, channel, column): (usize, usize, usize),
    accumulate: Accumulate,
) {
    let bias = &bias[channel..channel + V * L::WIDTH];
    for (pixel, sum) in sums.iter().enumerate() {
        let out = &mut output[(first_pixel + pixel) * out_stride + column..][..V * L::WIDTH];
        for (vector, &value) in sum.iter().enumerate() {
            let at = L::WIDTH * vector;
            // SAFETY: `out` and `bias` hold V WIDTH floats; each access covers WIDTH from
            // `at`; the caller runs on `L`'s CPU.
            unsafe {
                let mut value = L::add(value, L::load(bias.as_ptr().add(at)));
                if accumulate == Accumulate::Add {
                    value = L::add(value, L::load(out.as_ptr().add(at)));
                }
                L::store(out.as_mut_ptr().add(at), value);
            }
        }
    }
}

/// Kernel taps of one pass over a tile: rows x columns of the kernel.
#[derive(Clone, Debug, PartialEq, Eq)]
struct Taps {
    rows: core::ops::Range<usize>,
    columns: core::ops::Range<usize>,
}

/// A channel block's weights above this many bytes are walked a kernel row at a time, or a
/// tap at a time if a row is still larger. Their rows lie `4 out_channels` bytes apart, a
/// power of two that uses only a fraction of the L2 cache's sets (1/16 of them at 512
/// channels: 128 KB of 2 MB), so ResNet layer4's 590 KB block came from L3 again for every
/// pixel tile; a tap of it (64 KB) stays.
const CHUNKED_BLOCK_BYTES: usize = 96 * 1024;

/// The passes over each tile, in kernel order, as `(row chunks, column chunks)`: the whole
/// kernel, or one pass per row, or one per tap, whichever first keeps a channel block's
/// weights under [`CHUNKED_BLOCK_BYTES`]. Between passes the partial sums wait in the output,
/// which only an overwriting convolution may use.
fn passes(shape: &ConvShape, block_channels: usize, accumulate: Accumulate) -> (usize, usize) {
    let (height, width) = (shape.kernel_height, shape.kernel_width);
    let tap_bytes = shape.in_channels * block_channels * 4;
    if accumulate == Accumulate::Add || height * width * tap_bytes <= CHUNKED_BLOCK_BYTES {
        (1, 1)
    } else if width * tap_bytes <= CHUNKED_BLOCK_BYTES {
        (height, 1)
    } else {
        (height, width)
    }
}

/// Pass `part` of `passes`: its kernel rows and columns.
fn pass_taps(shape: &ConvShape, (row_chunks, column_chunks): (usize, usize), part: usize) -> Taps {
    let (height, width) = (shape.kernel_height, shape.kernel_width);
    let (row, column) = (part / column_chunks, part % column_chunks);
    Taps {
        rows: if row_chunks == 1 {
            0..height
        } else {
            row..row + 1
        },
        columns: if column_chunks == 1 {
            0..width
        } else {
            column..column + 1
        },
    }
}

/// Output channels `columns` of the convolution (all of them, or those of
/// `Kernels::conv_channels`), tiles of `N` consecutive output positions, into `output`
/// (`[positions, columns.len()]`, holding those channels' values before the call for
/// [`Accumulate::Add`]); `bias` is the whole layer's. Each pixel's chain is the same
/// whichever channels a call covers: the same bits.
///
/// # Safety
/// The CPU supports `L`; `input`, `weight` and `bias` have the lengths `shape` implies,
/// `output` at least `positions x columns.len()`; `columns` lies inside `out_channels`, its
/// start and length multiples of `V WIDTH`.
#[inline(always)]
pub(crate) unsafe fn conv_columns<L: Lanes, const N: usize, const V: usize>(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    columns: core::ops::Range<usize>,
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let positions = shape.out_height() * shape.out_width();
    let out_stride = columns.len();
    // Each pixel's FMA chain goes on across passes in the same order: the same bits as one.
    let chunks = passes(shape, V * L::WIDTH, accumulate);
    let parts = chunks.0 * chunks.1;
    // Channel blocks outside, pixels inside: a block's weights stay in the L2 cache while
    // every pixel reads them, instead of the whole kernel being streamed from L3 once per
    // pixel tile.
    for channel in columns.clone().step_by(V * L::WIDTH) {
        let column = channel - columns.start;
        for part in 0..parts {
            let taps = pass_taps(shape, chunks, part);
            let last = part + 1 == parts;
            for first in (0..positions).step_by(N) {
                let count = (positions - first).min(N);
                // SAFETY: the caller vouches for the CPU and the lengths; the pixels are in
                // the output and the channel block inside `out_channels`.
                unsafe {
                    let start = if part == 0 {
                        [[L::zero(); V]; N]
                    } else {
                        load_partial::<L, N, V>(output, out_stride, (first, count), column)
                    };
                    let taps = (taps.clone(), start);
                    let sums =
                        tile::<L, N, V>(shape, (input, weight), (first, count), channel, taps);
                    if last {
                        let at = (first, channel, column);
                        let out = (bias, &mut *output);
                        store_tile::<L, V>(&sums[..count], out, out_stride, at, accumulate);
                    } else {
                        let at = (first, column);
                        store_partial::<L, V>(&sums[..count], output, out_stride, at);
                    }
                }
            }
        }
    }
}

/// The partial sums [`store_partial`] left for the tile's `count` pixels (zero past them),
/// at `column` of output rows `out_stride` floats long.
///
/// # Safety
/// The CPU supports `L`; the pixels and the block's `V WIDTH` columns are in `output`.
#[inline(always)]
unsafe fn load_partial<L: Lanes, const N: usize, const V: usize>(
    output: &[f32],
    out_stride: usize,
    (first, count): (usize, usize),
    column: usize,
) -> [[L::Vector; V]; N] {
    // SAFETY: the caller runs on `L`'s CPU.
    let mut sums = [[unsafe { L::zero() }; V]; N];
    for (pixel, sum) in sums.iter_mut().enumerate().take(count) {
        let from = &output[(first + pixel) * out_stride + column..][..V * L::WIDTH];
        for (vector, sum) in sum.iter_mut().enumerate() {
            // SAFETY: `from` holds V WIDTH floats; the caller runs on `L`'s CPU.
            *sum = unsafe { L::load(from.as_ptr().add(vector * L::WIDTH)) };
        }
    }
    sums
}

/// Stores a tile's partial sums, without the bias, where [`load_partial`] finds them.
///
/// # Safety
/// The CPU supports `L`; the pixels and the block's `V WIDTH` columns are in `output`.
#[inline(always)]
unsafe fn store_partial<L: Lanes, const V: usize>(
    sums: &[[L::Vector; V]],
    output: &mut [f32],
    out_stride: usize,
    (first, column): (usize, usize),
) {
    for (pixel, sum) in sums.iter().enumerate() {
        let to = &mut output[(first + pixel) * out_stride + column..][..V * L::WIDTH];
        for (vector, &sum) in sum.iter().enumerate() {
            // SAFETY: `to` holds V WIDTH floats; the caller runs on `L`'s CPU.
            unsafe { L::store(to.as_mut_ptr().add(vector * L::WIDTH), sum) };
        }
    }
}

/// Output pixel `pixel` of [`conv_columns`] (overwriting), into `output` (`out_channels` values).
///
/// # Safety
/// As for [`conv_columns`] over every channel; the pixel is in the output.
#[inline(always)]
pub(crate) unsafe fn conv_pixel<L: Lanes>(
    shape: &ConvShape,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    pixel: (usize, usize),
    output: &mut [f32],
) {
    for channel in (0..shape.out_channels).step_by(2 * L::WIDTH) {
        // SAFETY: as in `conv`; `output` is the pixel's channels, so pixel 0 is inside it.
        unsafe {
            let position = pixel.0 * shape.out_width() + pixel.1;
            // The whole kernel in one pass, as `conv` runs it when it does not chunk.
            let taps = pass_taps(shape, (1, 1), 0);
            let sums = tile::<L, 1, 2>(
                shape,
                (input, weight),
                (position, 1),
                channel,
                (taps, [[L::zero(); 2]; 1]),
            );
            let out = (bias, &mut *output);
            store_tile::<L, 2>(
                &sums,
                out,
                shape.out_channels,
                (0, channel, channel),
                Accumulate::Overwrite,
            );
        }
    }
}
