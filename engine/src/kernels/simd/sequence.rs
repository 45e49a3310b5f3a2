//! Kernels for the conditional U-Net's f32 weights, over a vector width ([`Lanes`]: YMM for
//! AVX2, ZMM for AVX-512; one generic body, instantiated in the thin `#[target_feature]`
//! wrappers at the end): 1-D convolutions over short sequences (`[T, C]`, T = 16, 8 or 4)
//! and the FiLM matrix-vector products of f32 weights (int8 ones multiply codes, in
//! `int8`). Their weights are read at every denoising step, so these kernels read each
//! weight once per call where they can:
//! - on sequences of up to 16 positions (all of the product models'), the weights are
//!   streamed in memory order, a block of eight rows applied to every position while the
//!   sums sit in registers (59 MB of f32 weights come from L3 at every step);
//! - longer sequences use a register tile of 4 positions x 2 vectors of channels.
//!
//! The int8 convolutions of the U-Net take int8 activations: `sequence_int8`.

use super::lanes::Lanes;
use super::{prefetch_lines, prefetch_lines_into_l2};
use crate::kernels::{Accumulate, ConvShape};

/// Output positions per register tile: 4 positions x 2 vectors are eight accumulators,
/// leaving registers for the two weight vectors and the broadcast input (AVX2 has 16).
const POSITIONS: usize = 4;

/// A 1-D convolution seen from its outputs: output position `t` (of `positions`), tap `i`
/// (of `taps`) multiplies weight block `i` (`[in, out]`) with input row `t * stride +
/// first_offset + i`, and is skipped when that row is outside `0 .. in_length` (zero
/// padding: `first_offset = -padding`).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Sequence {
    pub in_length: usize,
    pub in_channels: usize,
    pub out_channels: usize,
    pub positions: usize,
    pub stride: usize,
    pub taps: usize,
    pub first_offset: isize,
}

impl Sequence {
    /// The 1-D convolution `shape` describes, if it is one (one input row, one kernel row,
    /// no vertical padding).
    pub(crate) fn from_shape(shape: &ConvShape) -> Option<Sequence> {
        (shape.in_height == 1
            && shape.kernel_height == 1
            && shape.padding_height + shape.padding_bottom == 0)
            .then(|| {
                Sequence::convolution(
                    shape.in_width,
                    (shape.in_channels, shape.out_channels),
                    shape.kernel_width,
                    shape.stride,
                    shape.padding_width,
                )
            })
    }

    /// A convolution with kernel `taps`, `stride` and zero `padding`.
    pub fn convolution(
        in_length: usize,
        (in_channels, out_channels): (usize, usize),
        taps: usize,
        stride: usize,
        padding: usize,
    ) -> Self {
        let positions = crate::shape::conv_output(in_length, taps, stride, padding);
        Sequence {
            in_length,
            in_channels,
            out_channels,
            positions,
            stride,
            taps,
            first_offset: -(padding as isize),
        }
    }

    /// Kernel tap `index` and the offset of the input row it reads from `t * stride`.
    fn tap(&self, index: usize) -> (usize, isize) {
        (index, self.first_offset + index as isize)
    }

    /// The positions `first .. first + count` whose input row for a tap with this `offset`
    /// is inside the input, as a range relative to `first` (empty when `start >= end`).
    fn inside(&self, offset: isize, first: usize, count: usize) -> (usize, usize) {
        let stride = self.stride as isize;
        let first = first as isize;
        // Smallest t with t * stride + offset >= 0, and smallest t with it >= in_length.
        let low = if offset >= 0 {
            0
        } else {
            (-offset + stride - 1) / stride
        };
        let high = (self.in_length as isize - offset + stride - 1).max(0) / stride;
        let start = (low - first).clamp(0, count as isize) as usize;
        let end = (high - first).clamp(0, count as isize) as usize;
        (start, end)
    }

    /// Panics unless the slices are long enough for this sequence (the model code never
    /// passes shorter ones; the kernels read them unchecked).
    fn assert_lengths(&self, input: usize, weight: usize, output: usize, bias: usize) {
        let (in_channels, out_channels) = (self.in_channels, self.out_channels);
        assert!(input >= self.in_length * in_channels);
        assert!(weight >= self.taps * in_channels * out_channels);
        assert!(output >= self.positions * out_channels);
        assert_eq!(bias, out_channels);
    }
}

/// Runs `sequence` on register tiles: `output[row, o] (+)= sum + bias[o]`.
///
/// # Safety
/// The CPU supports `L`.
///
/// # Panics
/// If a slice is shorter than `sequence` needs (the model code never passes such slices).
#[inline(always)]
unsafe fn convolve<L: Lanes>(
    sequence: &Sequence,
    input: &[f32],
    weight: &[f32],
    bias: &[f32],
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let out_channels = sequence.out_channels;
    sequence.assert_lengths(input.len(), weight.len(), output.len(), bias.len());
    if out_channels == 0 {
        return;
    }
    let vector_channels = out_channels - out_channels % L::WIDTH;
    // The output holds the running sums: bias first, then one partial sum per chunk.
    for position in 0..sequence.positions {
        let out = &mut output[position * out_channels..][..vector_channels];
        match accumulate {
            Accumulate::Overwrite => out.copy_from_slice(&bias[..vector_channels]),
            Accumulate::Add => out.iter_mut().zip(bias).for_each(|(o, b)| *o += b),
        }
    }
    // Channel blocks outside: a block's weights come from memory for the first tile of
    // positions and from the caches for the others; with the positions outside, every tile
    // of positions streamed the whole kernel from memory.
    let mut channel = 0;
    while channel + 2 * L::WIDTH <= vector_channels {
        for first in (0..sequence.positions).step_by(POSITIONS) {
            // SAFETY: the caller runs on `L`'s CPU; the asserts above bound every row the
            // tile reads or writes; `channel + 2 WIDTH <= out_channels`.
            unsafe {
                let sums = tile::<L, 2>(sequence, input, weight, first, channel);
                add_sums::<L, 2>(sequence, &sums, first, channel, output);
            }
        }
        channel += 2 * L::WIDTH;
    }
    if channel < vector_channels {
        for first in (0..sequence.positions).step_by(POSITIONS) {
            // SAFETY: as above, with `channel + WIDTH == vector_channels <= out_channels`.
            unsafe {
                let sums = tile::<L, 1>(sequence, input, weight, first, channel);
                add_sums::<L, 1>(sequence, &sums, first, channel, output);
            }
        }
    }
    if vector_channels < out_channels {
        narrow_channels(
            sequence,
            (input, weight, bias),
            output,
            accumulate,
            vector_channels,
        );
    }
}

/// Bytes ahead of the weight row being read that [`convolve_streaming`] asks L2 for. The
/// weights are one stream in memory order, yet the hardware prefetchers alone left the f32
/// loop at about 7 GB/s (4-16 KB ahead into L1 gave 0.71-0.77x of the loop without it,
/// from the 260 MB L3 of a Xeon VM). Where the 59 MB a step come from DRAM (a
/// 32 MB L3), asking into L1 8-32 KB ahead made no difference and asking into L2 16 KB
/// ahead ran the loop 1.5-1.7x faster; 32-64 KB measured the same as 16
/// (`benches/README.md`, Zen 4).
const STREAMING_PREFETCH: usize = 16384;

/// Whole weight rows of `row_stride` floats that cover [`STREAMING_PREFETCH`] bytes: the
/// distance the prefetches run ahead. A call cut by output channels reads a segment of each
/// row; a distance of some rows and a part of one put the prefetches of 384-channel layers
/// in the other worker's columns, and those layers' own weights came unasked (the door-open
/// f32 loop on 2 threads 19.4-20.0 ms against 17.4-18.0 a whole number of rows ahead; one
/// thread the same either way).
fn prefetch_rows(row_stride: usize) -> usize {
    STREAMING_PREFETCH.div_ceil(row_stride.max(1) * size_of::<f32>())
}

/// Bytes ahead of the columns being read that [`matvec`] asks the caches for (the f32 FiLM
/// rows, 16 MB a step, one stream as the int8 ones: `int8::MATVEC_PREFETCH`).
const MATVEC_PREFETCH: usize = 4096;

/// Up to this many output positions (every U-Net layer of the product models), f32
/// weights are streamed ([`convolve_streaming`]); longer sequences use the register tiles.
pub(crate) const STREAMING_POSITIONS: usize = 16;

/// [`convolve`] with f32 weights, by whichever loop is faster for the sequence length.
///
/// # Safety
/// The CPU supports `L`.
///
/// # Panics
/// If a slice is shorter than `sequence` needs (the model code never passes such slices).
#[inline(always)]
pub(crate) unsafe fn convolve_f32<L: Lanes>(
    sequence: &Sequence,
    input: &[f32],
    weight: &[f32],
    bias: &[f32],
    output: &mut [f32],
    accumulate: Accumulate,
) {
    // SAFETY: the caller runs on `L`'s CPU.
    unsafe {
        if sequence.positions <= STREAMING_POSITIONS {
            convolve_streaming::<L>(sequence, input, weight, bias, output, accumulate)
        } else {
            convolve::<L>(sequence, input, weight, bias, output, accumulate)
        }
    }
}

/// [`convolve`] for f32 weights, read strictly in memory order: a block of
/// [`STREAMED_ROWS`] weight rows (input channels, `out_channels` weights each, contiguous)
/// is applied to every output position and channel before the next block, each vector of
/// channels' sums for all positions held in registers across the block's rows. With f32
/// weights the U-Net's layers come from L3 at every step, and one sequential stream is
/// what the hardware prefetcher serves best (measured: the register tiles, which walk rows
/// `out_channels` apart, ran 2-4x slower than this on cold weights). Every output's sum is
/// one chain from the bias, in tap and input-channel order. Updating the sums in memory once
/// per row (a load and a store per position and vector for every row) held the sequences of
/// 8 and 16 positions to 9-12 GB/s of weights.
///
/// # Safety
/// The CPU supports `L`.
///
/// # Panics
/// If a slice is shorter than `sequence` needs (the model code never passes such slices).
#[inline(always)]
unsafe fn convolve_streaming<L: Lanes>(
    sequence: &Sequence,
    input: &[f32],
    weight: &[f32],
    bias: &[f32],
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let columns = 0..sequence.out_channels;
    // SAFETY: the caller's promise.
    unsafe { convolve_columns::<L>(sequence, (input, weight, bias), columns, output, accumulate) }
}

/// [`convolve_streaming`] for output channels `columns` only: `bias` and `output`
/// (`[positions, columns.len()]`) hold just those, `weight` is the whole kernel. Each
/// channel's sum is the same chain as in the whole convolution, so the same bits, as long
/// as `columns` starts at a whole vector (the channels of the last, partial vector are
/// summed unfused, in both).
///
/// # Safety
/// The CPU supports `L`.
///
/// # Panics
/// If a slice is shorter than `sequence` needs, `columns` is not inside its output channels
/// or does not start at a multiple of `L::WIDTH`.
#[inline(always)]
pub(crate) unsafe fn convolve_columns<L: Lanes>(
    sequence: &Sequence,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    columns: core::ops::Range<usize>,
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let (in_channels, row_stride) = (sequence.in_channels, sequence.out_channels);
    let out_channels = columns.len();
    assert!(columns.end <= row_stride && columns.start.is_multiple_of(L::WIDTH));
    assert!(input.len() >= sequence.in_length * in_channels);
    assert!(weight.len() >= sequence.taps * in_channels * row_stride);
    assert!(output.len() >= sequence.positions * out_channels);
    assert_eq!(bias.len(), out_channels);
    assert!(sequence.positions <= STREAMING_POSITIONS);
    for position in 0..sequence.positions {
        let out = &mut output[position * out_channels..][..out_channels];
        match accumulate {
            Accumulate::Overwrite => out.copy_from_slice(bias),
            Accumulate::Add => out.iter_mut().zip(bias).for_each(|(o, b)| *o += b),
        }
    }
    for index in 0..sequence.taps {
        let (tap, offset) = sequence.tap(index);
        let (start, end) = sequence.inside(offset, 0, sequence.positions);
        if start >= end {
            continue;
        }
        let block = &weight[tap * in_channels * row_stride + columns.start..]
            [..(in_channels - 1) * row_stride + out_channels];
        let input_row = (start * sequence.stride) as isize + offset;
        let tap_input = &input[input_row as usize * in_channels..];
        let out = &mut output[start * out_channels..];
        let strides = (sequence.stride * in_channels, out_channels);
        macro_rules! positions {
            ($($count:literal => ($first:literal, $second:literal)),*) => {
                match end - start {
                    $(
                        // SAFETY: the caller runs on `L`'s CPU; `stream_tap` asserts what it
                        // reads and writes (`inside` keeps the tap's input rows of these
                        // positions inside the input).
                        $count => unsafe {
                            stream_tap::<L, $first, $second>(
                                block,
                                (tap_input, out),
                                strides,
                                (in_channels, row_stride, out_channels),
                            )
                        },
                    )*
                    _ => unreachable!(),
                }
            };
        }
        const { assert!(STREAMING_POSITIONS == 16, "the table below covers 1 to 16") };
        positions!(
            1 => (1, 0), 2 => (2, 0), 3 => (3, 0), 4 => (4, 0), 5 => (5, 0), 6 => (6, 0),
            7 => (7, 0), 8 => (8, 0), 9 => (8, 1), 10 => (8, 2), 11 => (8, 3), 12 => (8, 4),
            13 => (8, 5), 14 => (8, 6), 15 => (8, 7), 16 => (8, 8)
        );
    }
}

/// Input channels whose weight rows [`convolve_streaming`] applies while the sums stay in
/// registers: eight rows of 256 channels are 8 KB of one stream.
const STREAMED_ROWS: usize = 8;

/// One tap of [`convolve_streaming`] for `P + Q` consecutive output positions:
/// `out[p] += sum_c input[p, c] block[c]`, `input` and `out` from the first position's rows,
/// the positions `strides` floats apart in each; `block`'s rows are `row_stride` floats
/// apart, `out_channels` of each read. The sums of the first `P` positions, then
/// of the other `Q`, stay in registers over a block of rows (at most 8 positions at a time;
/// all 16 at once spilled).
///
/// # Safety
/// The CPU supports `L`.
///
/// # Panics
/// If `input`, `out` or `block` is shorter than the positions and channels need.
#[inline(always)]
unsafe fn stream_tap<L: Lanes, const P: usize, const Q: usize>(
    block: &[f32],
    (input, out): (&[f32], &mut [f32]),
    (input_stride, out_stride): (usize, usize),
    (in_channels, row_stride, out_channels): (usize, usize, usize),
) {
    let positions = P + Q;
    assert!(input.len() >= (positions - 1) * input_stride + in_channels);
    assert!(out.len() >= (positions - 1) * out_stride + out_channels);
    let vector_channels = out_channels - out_channels % L::WIDTH;
    let (input, out) = (input.as_ptr(), out.as_mut_ptr());
    for first_row in (0..in_channels).step_by(STREAMED_ROWS) {
        let rows = (in_channels - first_row).min(STREAMED_ROWS);
        let weights =
            block[first_row * row_stride..][..(rows - 1) * row_stride + out_channels].as_ptr();
        let ahead = weights.wrapping_add(prefetch_rows(row_stride) * row_stride);
        for channel in (0..vector_channels).step_by(L::WIDTH) {
            // The lines `prefetch_rows` ahead of the ones this vector reads, spread over
            // the loop (asked for all at once, they filled the line buffers and stalled it).
            for row in 0..rows {
                prefetch_lines_into_l2(ahead.wrapping_add(row * row_stride + channel), 1);
            }
            let lanes = weights.wrapping_add(channel);
            let at = (first_row, channel);
            let strides = (input_stride, out_stride);
            let rows = (rows, row_stride);
            // SAFETY: the rows and channels are inside `block`, the positions' sums inside
            // `out` and their values inside `input` (asserted above); the caller runs on
            // `L`'s CPU.
            unsafe {
                stream_positions::<L, P>((input, out), strides, lanes, at, rows);
                if Q > 0 {
                    let input = input.add(P * input_stride);
                    let out = out.add(P * out_stride);
                    stream_positions::<L, Q>((input, out), strides, lanes, at, rows);
                }
            }
        }
        if vector_channels < out_channels {
            let tail = (out_channels - vector_channels) * size_of::<f32>();
            for row in 0..rows {
                prefetch_lines(ahead.wrapping_add(row * row_stride + vector_channels), tail);
            }
        }
        // The channels past the last whole vector (the narrow noise head), one at a time in
        // the same order.
        for channel in vector_channels..out_channels {
            for row in 0..rows {
                // SAFETY: as above.
                unsafe {
                    let w = *weights.add(row * row_stride + channel);
                    for p in 0..positions {
                        let x = *input.add(p * input_stride + first_row + row);
                        *out.add(p * out_stride + channel) += x * w;
                    }
                }
            }
        }
    }
}

/// `out[p, channel..+WIDTH] += sum_r input[p, first_row + r] lanes[r]` for `P` positions and
/// `rows` weight rows (`lanes`: the first row's vector, rows `row_stride` apart), the sums
/// in registers from the load to the store.
///
/// # Safety
/// The CPU supports `L`; `input` is readable and `out` writable at `p * stride + ...` for
/// every `p < P` (`input` at `first_row .. first_row + rows`, `out` at `channel ..
/// channel + WIDTH`); `lanes` holds `rows` rows of `WIDTH` floats `row_stride` apart.
#[inline(always)]
unsafe fn stream_positions<L: Lanes, const P: usize>(
    (input, out): (*const f32, *mut f32),
    (input_stride, out_stride): (usize, usize),
    lanes: *const f32,
    (first_row, channel): (usize, usize),
    (rows, row_stride): (usize, usize),
) {
    // SAFETY (this block): the caller's promises. Loops, not `array::from_fn`: a closure
    // does not inherit the caller's target features, and its intrinsics would become calls.
    unsafe {
        let mut sums = [L::zero(); P];
        for (p, sum) in sums.iter_mut().enumerate() {
            *sum = L::load(out.add(p * out_stride + channel));
        }
        for row in 0..rows {
            let weights = L::load(lanes.add(row * row_stride));
            for (p, sum) in sums.iter_mut().enumerate() {
                let x = L::splat(*input.add(p * input_stride + first_row + row));
                *sum = L::fma(x, weights, *sum);
            }
        }
        for (p, sum) in sums.iter().enumerate() {
            L::store(out.add(p * out_stride + channel), *sum);
        }
    }
}

/// The sums of output positions `first ..` (up to four) for output channels `channel ..
/// channel + VECS WIDTH`.
///
/// # Safety
/// The CPU supports `L`; the slices have the lengths [`convolve`] asserts;
/// `channel + VECS WIDTH <= out_channels`.
#[inline(always)]
unsafe fn tile<L: Lanes, const VECS: usize>(
    sequence: &Sequence,
    input: &[f32],
    weight: &[f32],
    first: usize,
    channel: usize,
) -> [[L::Vector; VECS]; POSITIONS] {
    let (in_channels, out_channels) = (sequence.in_channels, sequence.out_channels);
    let count = (sequence.positions - first).min(POSITIONS);
    let input_step = sequence.stride * in_channels;
    // SAFETY: the caller runs on `L`'s CPU.
    let mut sums = [[unsafe { L::zero() }; VECS]; POSITIONS];
    for index in 0..sequence.taps {
        let (tap, offset) = sequence.tap(index);
        let (start, end) = sequence.inside(offset, first, count);
        if start >= end {
            continue;
        }
        let row = ((first + start) * sequence.stride) as isize + offset;
        // SAFETY: `inside` keeps `row` and the rows `input_step` apart up to `end` inside the
        // input; the tap's weight block is inside `weight` (asserted by `convolve`).
        let rows = (
            unsafe { input.as_ptr().add(row as usize * in_channels) },
            input_step,
        );
        let weights = unsafe {
            weight
                .as_ptr()
                .add(tap * in_channels * out_channels + channel)
        };
        macro_rules! run {
            ($(($start:literal, $end:literal)),*) => {
                match (start, end) {
                    $(
                        // SAFETY: see above; the range was computed by `inside`.
                        ($start, $end) => unsafe {
                            accumulate::<L, VECS, $start, $end>(
                                &mut sums, rows, weights, out_channels, in_channels,
                            )
                        },
                    )*
                    _ => unreachable!(),
                }
            };
        }
        run!(
            (0, 1),
            (0, 2),
            (0, 3),
            (0, 4),
            (1, 2),
            (1, 3),
            (1, 4),
            (2, 3),
            (2, 4),
            (3, 4)
        );
    }
    sums
}

/// Weight rows [`accumulate`] prefetches ahead of the one it reads.
const PREFETCH_ROWS: usize = 16;

/// `sums[t] += x[t, c] * w[c]` over `in_channels` input channels, for tile positions
/// `START .. END` (a compile-time range keeps the accumulators in registers).
///
/// # Safety
/// The CPU supports `L`; `rows.0` points at the input row of position `START`, later
/// positions `rows.1` floats apart, each with `in_channels` readable values; `weights`
/// points at `in_channels` rows, `weight_step` apart, of `VECS WIDTH` readable weights.
#[inline(always)]
unsafe fn accumulate<L: Lanes, const VECS: usize, const START: usize, const END: usize>(
    sums: &mut [[L::Vector; VECS]; POSITIONS],
    (rows, input_step): (*const f32, usize),
    weights: *const f32,
    weight_step: usize,
    in_channels: usize,
) {
    // Plain index loops with constant bounds: LLVM unrolls them and keeps `sums` in
    // registers (iterator adapters here were left as calls, with the sums in memory).
    #[allow(clippy::needless_range_loop)]
    for c in 0..in_channels {
        // The weight rows lie `out_channels` apart, one cache line each: ask for the line
        // `PREFETCH_ROWS` ahead. A hint only (it never faults), hence the wrapping address.
        prefetch_lines(weights.wrapping_add((c + PREFETCH_ROWS) * weight_step), 1);
        // SAFETY (this block): row `c` of the weights holds `VECS WIDTH` readable values, the
        // input row of each position `in_channels`; the caller runs on `L`'s CPU.
        let lanes: [L::Vector; VECS] = core::array::from_fn(|vec| unsafe {
            L::load(weights.add(c * weight_step + L::WIDTH * vec))
        });
        for position in START..END {
            let x = unsafe { L::splat(*rows.add((position - START) * input_step + c)) };
            for vec in 0..VECS {
                sums[position][vec] = unsafe { L::fma(x, lanes[vec], sums[position][vec]) };
            }
        }
    }
}

/// `output += sums` for a tile.
///
/// # Safety
/// The CPU supports `L`; `output` holds the sequence's rows; `channel + VECS WIDTH <=
/// out_channels`.
#[inline(always)]
unsafe fn add_sums<L: Lanes, const VECS: usize>(
    sequence: &Sequence,
    sums: &[[L::Vector; VECS]; POSITIONS],
    first: usize,
    channel: usize,
    output: &mut [f32],
) {
    let count = (sequence.positions - first).min(POSITIONS);
    for (position, sum) in sums.iter().enumerate().take(count) {
        let out =
            &mut output[(first + position) * sequence.out_channels + channel..][..L::WIDTH * VECS];
        for (vec, &value) in sum.iter().enumerate() {
            // SAFETY: `out` holds `VECS WIDTH` floats; the caller runs on `L`'s CPU.
            unsafe {
                let target = out.as_mut_ptr().add(L::WIDTH * vec);
                L::store(target, L::add(value, L::load(target)));
            }
        }
    }
}

/// The last `out_channels - channel < 8` channels, one at a time (the narrow noise head).
fn narrow_channels(
    sequence: &Sequence,
    (input, weight, bias): (&[f32], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
    channel: usize,
) {
    let (in_channels, out_channels) = (sequence.in_channels, sequence.out_channels);
    for position in 0..sequence.positions {
        for o in channel..out_channels {
            let mut sum = 0.0;
            for index in 0..sequence.taps {
                let (tap, offset) = sequence.tap(index);
                let (start, end) = sequence.inside(offset, position, 1);
                if start >= end {
                    continue;
                }
                let input_row = (position * sequence.stride) as isize + offset;
                let values = &input[input_row as usize * in_channels..][..in_channels];
                let taps =
                    &weight[tap * in_channels * out_channels..][..in_channels * out_channels];
                for (&x, weights) in values.iter().zip(taps.chunks_exact(out_channels)) {
                    sum += x * weights[o];
                }
            }
            let value = sum + bias[o];
            let out = &mut output[position * out_channels + o];
            match accumulate {
                Accumulate::Overwrite => *out = value,
                Accumulate::Add => *out += value,
            }
        }
    }
}

/// `output[r] = base[r] + sum_c w[r, c] input[c]` for a row-major `[rows, cols]` weight
/// (f32 FiLM layers: rows of ~650 weights, each read once).
///
/// # Safety
/// The CPU supports `L`.
///
/// # Panics
/// If the lengths disagree (the model code never passes such slices).
#[inline(always)]
pub(crate) unsafe fn matvec<L: Lanes>(
    weight: &[f32],
    input: &[f32],
    base: &[f32],
    output: &mut [f32],
) {
    let cols = input.len();
    assert_eq!(weight.len(), output.len() * cols);
    assert_eq!(base.len(), output.len());
    if cols == 0 {
        output.copy_from_slice(base);
        return;
    }
    let width = L::WIDTH;
    let vector_cols = cols - cols % width;
    for (r, (out, row)) in output.iter_mut().zip(weight.chunks_exact(cols)).enumerate() {
        // Four independent sums hide the FMA latency.
        // SAFETY: the caller runs on `L`'s CPU.
        let mut sums = [unsafe { L::zero() }; 4];
        let mut c = 0;
        while c + 4 * width <= vector_cols {
            let ahead = row
                .as_ptr()
                .wrapping_add(c)
                .wrapping_byte_add(MATVEC_PREFETCH);
            prefetch_lines(ahead, 4 * width * size_of::<f32>());
            for (k, sum) in sums.iter_mut().enumerate() {
                // SAFETY: `c + WIDTH (k + 1) <= cols`, the length of `row` and `input`.
                unsafe {
                    let w = L::load(row.as_ptr().add(c + width * k));
                    let x = L::load(input.as_ptr().add(c + width * k));
                    *sum = L::fma(w, x, *sum);
                }
            }
            c += 4 * width;
        }
        while c < vector_cols {
            // SAFETY: `c + WIDTH <= vector_cols <= cols`.
            unsafe {
                let w = L::load(row.as_ptr().add(c));
                let x = L::load(input.as_ptr().add(c));
                sums[0] = L::fma(w, x, sums[0]);
            }
            c += width;
        }
        // SAFETY: the caller runs on `L`'s CPU.
        let mut sum = unsafe {
            L::horizontal_sum(L::add(L::add(sums[0], sums[1]), L::add(sums[2], sums[3])))
        };
        for (&w, &x) in row[vector_cols..].iter().zip(&input[vector_cols..]) {
            sum += w * x;
        }
        *out = base[r] + sum;
    }
}

/// The convolutions of this module compiled for one backend (AVX2 + FMA on YMM, AVX-512F on
/// ZMM, NEON: the same body), as the [`Kernels::conv`](crate::kernels::Kernels::conv) of 1-D
/// shapes. ([`matvec`] sums in lane order, so each architecture compiles it for one vector
/// width only: eight lanes.) `$lanes` names the [`Lanes`] type as seen from inside
/// the generated module.
macro_rules! backend {
    ($module:ident, $lanes:ty, $features:literal) => {
        pub(crate) mod $module {
            use $crate::kernels::scalar::assert_conv_lengths;
            use $crate::kernels::simd::sequence::Sequence;
            use $crate::kernels::{Accumulate, ConvShape};

            /// `convolve_f32` on this backend's vectors.
            ///
            /// # Safety
            /// The CPU supports the backend's features.
            #[target_feature(enable = $features)]
            unsafe fn convolve_f32(
                sequence: &Sequence,
                input: &[f32],
                weight: &[f32],
                bias: &[f32],
                output: &mut [f32],
                accumulate: Accumulate,
            ) {
                // SAFETY: this function's contract is the body's.
                unsafe {
                    $crate::kernels::simd::sequence::convolve_f32::<$lanes>(
                        sequence, input, weight, bias, output, accumulate,
                    )
                }
            }

            /// `Kernels::conv` for 1-D shapes; `None` (nothing done) for 2-D ones.
            ///
            /// # Safety
            /// The CPU supports the backend's features.
            pub(crate) unsafe fn conv(
                shape: &ConvShape,
                (input, weight, bias): (&[f32], &[f32], &[f32]),
                output: &mut [f32],
                accumulate: Accumulate,
            ) -> Option<()> {
                let sequence = Sequence::from_shape(shape)?;
                assert_conv_lengths(shape, (input, weight, bias), output.len());
                // SAFETY: the caller vouches for the CPU.
                unsafe { convolve_f32(&sequence, input, weight, bias, output, accumulate) };
                Some(())
            }

            /// `convolve_columns` on this backend's vectors.
            ///
            /// # Safety
            /// The CPU supports the backend's features.
            #[target_feature(enable = $features)]
            unsafe fn convolve_columns(
                sequence: &Sequence,
                parameters: (&[f32], &[f32], &[f32]),
                columns: core::ops::Range<usize>,
                output: &mut [f32],
                accumulate: Accumulate,
            ) {
                // SAFETY: this function's contract is the body's.
                unsafe {
                    $crate::kernels::simd::sequence::convolve_columns::<$lanes>(
                        sequence, parameters, columns, output, accumulate,
                    )
                }
            }

            /// `Kernels::conv_channels`: `None` (nothing done) where `conv` would not
            /// stream this shape's weights.
            ///
            /// # Safety
            /// The CPU supports the backend's features.
            pub(crate) unsafe fn conv_channels(
                shape: &ConvShape,
                parameters: (&[f32], &[f32], &[f32]),
                columns: core::ops::Range<usize>,
                output: &mut [f32],
                accumulate: Accumulate,
            ) -> Option<()> {
                let sequence = Sequence::from_shape(shape)?;
                let streams =
                    sequence.positions <= $crate::kernels::simd::sequence::STREAMING_POSITIONS;
                let whole_vector = columns
                    .start
                    .is_multiple_of(<$lanes as $crate::kernels::simd::lanes::Lanes>::WIDTH);
                if !streams || !whole_vector || columns.end > shape.out_channels {
                    return None;
                }
                if columns.is_empty() {
                    return Some(());
                }
                // SAFETY: the caller vouches for the CPU.
                unsafe { convolve_columns(&sequence, parameters, columns, output, accumulate) };
                Some(())
            }
        }
    };
}

pub(crate) use backend;
