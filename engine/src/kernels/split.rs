//! One kernel call cut into a piece per worker ([`Workers`]), each piece the same kernel on a
//! smaller problem, so every output value comes out of the same sums in the same order as
//! from the whole call, whatever the number of workers:
//! - 2-D convolutions (the trunk, the projections): bands of output rows, each over the
//!   input rows its taps read ([`ConvShape::row_band`]); the stem's pointwise patches:
//!   runs of pixels. Small maps whose weights outweigh their input 4 to 1 (f32) or whose
//!   bands would hold fewer pixels than the kernels compute at once (int8): blocks of
//!   output channels, as below;
//! - the U-Net's 1-D convolutions: blocks of 64 output channels, so each worker reads its
//!   own share of the weights, which is where the loop's time goes (an int8 block's weights
//!   lie together, [`INT8_CHANNEL_BLOCK`]; f32 ones are read a row segment at a time,
//!   [`Kernels::conv_channels`]). A block's outputs are computed into its part of a scratch
//!   buffer, then copied (or added) into place;
//! - the FiLM products: runs of rows (with several workers a denoising step computes them in
//!   the background instead, [`super::Board`]);
//! - a large map's passes: GroupNorm by runs of whole [`ops::MOMENT_BLOCK`] blocks of
//!   pixels (each block's moments apart, added in block order by the caller, then the scale
//!   and shift applied; the stem's moments the same way), a quantization by runs of values
//!   (their largest magnitudes, then the codes), the residual add by runs, the stem's
//!   normalize-and-pool by bands of pooled rows. These runs follow the convolution's bands,
//!   so each core keeps the rows it wrote.
//!
//! A U-Net convolution with its [`Epilogue`] ([`Kernels::conv_then`]) is cut into blocks of
//! whole groups, and each piece runs the epilogue (GroupNorm, Mish, FiLM) on its own block.
//! Everything else (small maps' passes, the int8 projections evaluated a few cells at a
//! time) runs whole on the caller.

use core::ops::Range;
use core::sync::atomic::{AtomicBool, AtomicU32, AtomicUsize, Ordering};

use super::workers::Workers;
use super::{
    Accumulate, ByteRows, CodeRows, ConvShape, DigitRows, Epilogue, INT8_CHANNEL_BLOCK, Kernels,
    NarrowForm, SignedByteRows, ops, ops::Activation,
};
use crate::shape;

/// One band of a convolution: its shape, the input range it reads, its output.
type Band<'b> = dyn Fn(&ConvShape, Range<usize>, &mut [f32]) + Sync + 'b;

/// An int8 convolution's weights, weight scales and biases.
type Int8Parameters<'p> = (&'p [i8], &'p [f32], &'p [f32]);

/// An int8 convolution kernel on an input fixed by the caller.
/// `channels`: the output channels the call computes, of the whole convolution's.
type Int8Run<'r> =
    dyn Fn(&ConvShape, Int8Parameters<'_>, Range<usize>, &mut [f32], Accumulate) + Sync + 'r;

/// Multiply-adds below which a call runs whole: handing pieces to the other cores costs a
/// microsecond or so.
const MIN_SPLIT_PRODUCTS: usize = 1 << 16;

/// What an element-wise pass over a value counts as, in multiply-adds, against
/// [`MIN_SPLIT_PRODUCTS`]: maps of 32,768 values or more are cut.
const ELEMENT_WORK: usize = 2;

/// [`Kernels`] that cut each heavy call over `workers` and run `kernels` on the pieces.
pub struct Split<'s> {
    kernels: &'s dyn Kernels,
    workers: &'s dyn Workers,
    scratch: Shared,
    /// Multiply-adds below which a call runs whole.
    min_products: usize,
    /// Held while a call uses `scratch`.
    busy: AtomicBool,
    /// The epilogue each block of a channel-cut convolution runs, inside
    /// [`Kernels::conv_then`]; set once a call has run it.
    fused: Option<Fused<'s>>,
    applied: AtomicBool,
    _scratch: core::marker::PhantomData<&'s mut [f32]>,
}

/// An [`Epilogue`] to run on each block: the convolution's output channels, and the FiLM
/// scratch (`2 channels` values), each block taking `2 width` of them at `2 start`.
#[derive(Clone, Copy, Debug)]
struct Fused<'e> {
    epilogue: Epilogue<'e>,
    channels: usize,
    film: Shared,
}

impl core::fmt::Debug for Split<'_> {
    fn fmt(&self, formatter: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        formatter
            .debug_struct("Split")
            .field("kernels", &self.kernels.name())
            .field("workers", &self.workers.count())
            .finish()
    }
}

impl<'s> Split<'s> {
    /// `kernels` over `workers`; `scratch` holds a channel-split call's outputs (a call
    /// whose output it cannot hold runs whole).
    pub fn new(kernels: &'s dyn Kernels, workers: &'s dyn Workers, scratch: &'s mut [f32]) -> Self {
        Split {
            kernels,
            workers,
            scratch: Shared::new(scratch),
            min_products: MIN_SPLIT_PRODUCTS,
            busy: AtomicBool::new(false),
            fused: None,
            applied: AtomicBool::new(false),
            _scratch: core::marker::PhantomData,
        }
    }

    /// GroupNorm of a large map ([`Kernels::group_norm`]) over the workers, each taking runs
    /// of whole [`ops::MOMENT_BLOCK`] blocks of pixels, the runs each core's convolution
    /// pieces mostly wrote: first each block's moments, into the scratch apart; the calling
    /// thread adds them up in block order (the sums `group_norm` makes) and derives each
    /// channel's scale and shift, which the workers then apply to their runs. `false`,
    /// having run nothing, where the call is small or the scratch cannot hold the blocks'
    /// moments.
    fn group_norm_by_blocks(
        &self,
        data: &mut [f32],
        channels: usize,
        groups: usize,
        affine: (&[f32], &[f32]),
        activation: Activation,
    ) -> bool {
        let Some((positions, blocks, pieces)) = self.moment_blocks(data, channels) else {
            return false;
        };
        // Each block's sums and squares (f64), then the channels' scales and shifts.
        let moments_len = 4 * channels * blocks;
        let shaped = groups > 0
            && channels.is_multiple_of(groups)
            && channels / groups <= ops::GROUP_NORM_CHUNK
            && affine.0.len() == channels
            && affine.1.len() == channels;
        if pieces < 2 || !shaped || self.scratch.len < moments_len + 2 * channels {
            return false;
        }
        if self.busy.swap(true, Ordering::Acquire) {
            return false;
        }
        let (scratch, block_len) = (self.scratch, ops::MOMENT_BLOCK * channels);
        let kernels = self.kernels;
        self.block_moments(data, channels, pieces);
        // SAFETY: the pieces are done; `busy` keeps the scratch for this call.
        let (moments, affine_out) =
            unsafe { scratch.slice(0..moments_len + 2 * channels) }.split_at_mut(moments_len);
        let moments: &mut [f64] = bytemuck::cast_slice_mut(moments);
        let (total, rest) = moments.split_at_mut(2 * channels);
        for block in rest.chunks_exact(2 * channels) {
            for (sum, &value) in total.iter_mut().zip(block) {
                *sum += value;
            }
        }
        let (sums, squares) = total.split_at(channels);
        let (scale, shift) = affine_out.split_at_mut(channels);
        ops::group_scale_shift((sums, squares), positions, groups, affine, (scale, shift));
        let (scale, shift) = (&*scale, &*shift);
        let out = Shared::new(data);
        self.workers.run(pieces, &|piece| {
            let run = share(blocks, pieces, piece);
            let pixels = run.start * block_len..(run.end * block_len).min(out.len);
            // SAFETY: the pieces' runs are disjoint parts of `data`, which the caller does
            // not touch until `run` has returned.
            let part = unsafe { out.slice(pixels) };
            kernels.affine_activate(part, channels, (scale, shift), activation);
        });
        self.busy.store(false, Ordering::Release);
        true
    }

    /// The pixels of `data` (`[pixels, channels]`), its blocks of [`ops::MOMENT_BLOCK`]
    /// pixels and the pieces they go to; `None` where `data` is not whole pixels or the
    /// scratch is not on 8-byte boundaries (it holds f64 moments: a caller's scratch on
    /// 4-byte boundaries runs whole).
    fn moment_blocks(&self, data: &[f32], channels: usize) -> Option<(usize, usize, usize)> {
        let positions = data.len().checked_div(channels)?;
        let aligned = (self.scratch.start as usize).is_multiple_of(align_of::<f64>());
        if !aligned || data.len() != positions * channels {
            return None;
        }
        let blocks = positions.div_ceil(ops::MOMENT_BLOCK);
        Some((
            positions,
            blocks,
            self.pieces(blocks, ELEMENT_WORK * data.len()),
        ))
    }

    /// The moments of each block of [`ops::MOMENT_BLOCK`] pixels of `data` (`[pixels,
    /// channels]`), summed from zero over `pieces` workers, runs of blocks each, into the
    /// scratch apart: block `b`'s sums then squares (f64) at `4 channels b`. The caller
    /// holds `busy` and has checked that the scratch holds them, on 8-byte boundaries.
    fn block_moments(&self, data: &[f32], channels: usize, pieces: usize) {
        let (scratch, block_len) = (self.scratch, ops::MOMENT_BLOCK * channels);
        let blocks = data.len().div_ceil(block_len);
        let kernels = self.kernels;
        self.workers.run(pieces, &|piece| {
            for block in share(blocks, pieces, piece) {
                // SAFETY: each block has its own part of the scratch, which `busy` keeps
                // for this call alone.
                let slot =
                    unsafe { scratch.slice(4 * channels * block..4 * channels * (block + 1)) };
                let slot: &mut [f64] = bytemuck::cast_slice_mut(slot);
                slot.fill(0.0);
                let (sums, squares) = slot.split_at_mut(channels);
                let pixels = block * block_len..((block + 1) * block_len).min(data.len());
                kernels.add_channel_moments(&data[pixels], channels, (sums, squares));
            }
        });
    }

    /// [`Kernels::add_channel_moments`] over the workers: each block's moments
    /// ([`Self::block_moments`]), then added to `moments` in block order, the sums the
    /// whole call makes. `false`, having run nothing, where the call is small or the
    /// scratch cannot hold the blocks' moments.
    fn moments_by_blocks(
        &self,
        data: &[f32],
        channels: usize,
        (sums, squares): (&mut [f64], &mut [f64]),
    ) -> bool {
        let Some((_, blocks, pieces)) = self.moment_blocks(data, channels) else {
            return false;
        };
        let moments_len = 4 * channels * blocks;
        let shaped = sums.len() >= channels && squares.len() >= channels;
        if pieces < 2 || !shaped || self.scratch.len < moments_len {
            return false;
        }
        if self.busy.swap(true, Ordering::Acquire) {
            return false;
        }
        self.block_moments(data, channels, pieces);
        // SAFETY: the pieces are done; `busy` keeps the scratch for this call.
        let moments: &[f64] = bytemuck::cast_slice(unsafe { self.scratch.slice(0..moments_len) });
        for block in moments.chunks_exact(2 * channels) {
            let (block_sums, block_squares) = block.split_at(channels);
            sums.iter_mut()
                .zip(block_sums)
                .for_each(|(sum, &value)| *sum += value);
            let squared = squares.iter_mut().zip(block_squares);
            squared.for_each(|(sum, &value)| *sum += value);
        }
        self.busy.store(false, Ordering::Release);
        true
    }

    /// A quantization of `input` cut into runs of values over `pieces` workers: each run's
    /// largest magnitude ([`Kernels::largest_magnitude`]), then `codes(run, largest)` for
    /// each run with the whole input's, which says whether the run's codes are
    /// nonnegative. Returns the whole input's largest magnitude, which alone gives the
    /// scale, and whether every code is nonnegative.
    fn quantize_by_runs(
        &self,
        input: &[f32],
        pieces: usize,
        codes: &(dyn Fn(Range<usize>, f32) -> bool + Sync),
    ) -> (f32, bool) {
        let (kernels, len) = (self.kernels, input.len());
        // `largest_magnitude`'s results as bits: their integer order is its order.
        let largest = AtomicU32::new(0);
        self.workers.run(pieces, &|piece| {
            let part = kernels.largest_magnitude(&input[share(len, pieces, piece)]);
            largest.fetch_max(part.to_bits(), Ordering::Relaxed);
        });
        let largest = f32::from_bits(largest.load(Ordering::Relaxed));
        let nonnegative = AtomicBool::new(true);
        self.workers.run(pieces, &|piece| {
            if !codes(share(len, pieces, piece), largest) {
                nonnegative.store(false, Ordering::Relaxed);
            }
        });
        (largest, nonnegative.load(Ordering::Relaxed))
    }

    /// Cuts every call it can, however small (the tests' small shapes; the same bits).
    #[must_use]
    pub fn cutting_every_call(mut self) -> Self {
        self.min_products = 0;
        self
    }

    /// Pieces for `units` units of work of `products` multiply-adds in all: at most one a
    /// worker and one a unit; 1 (run whole) when too small to share.
    fn pieces(&self, units: usize, products: usize) -> usize {
        if products < self.min_products {
            return 1;
        }
        self.workers.count().min(units).max(1)
    }

    /// Runs `band(shape, input range, output)` on bands of output rows (or, for a
    /// pointwise convolution over one row, runs of pixels) with their own output slices;
    /// `false` when the call is not cut (the caller runs it whole).
    fn split_rows(
        &self,
        shape: &ConvShape,
        input_len: usize,
        output: &mut [f32],
        band: &Band<'_>,
    ) -> bool {
        let products =
            shape.output_len() * shape.kernel_height * shape.kernel_width * shape.in_channels;
        let row_len = shape.in_width * shape.in_channels;
        let out_row = shape.out_width() * shape.out_channels;
        let rows_apply = shape.in_height > 1
            && shape.padding_bottom == shape.padding_height
            && shape.padding_height < shape.kernel_height;
        let pixels_apply = shape.in_height == 1 && shape.is_pointwise();
        let units = if rows_apply {
            shape.out_height()
        } else if pixels_apply {
            shape.in_width
        } else {
            return false;
        };
        // At least two output rows a band: a band of one row of a 1x1 convolution would
        // read one input row, which the kernels take for a sequence and sum in another
        // order.
        let most = if rows_apply { units / 2 } else { units };
        let pieces = self.pieces(most, products);
        if pieces < 2 || input_len < shape.input_len() || output.len() < shape.output_len() {
            return false;
        }
        let out = Shared::new(&mut output[..shape.output_len()]);
        self.workers.run(pieces, &|piece| {
            let units = share(units, pieces, piece);
            if units.is_empty() {
                return;
            }
            let (part, inputs, outputs) = if rows_apply {
                let (part, start) = shape.row_band(units.start, units.len());
                let inputs = start * row_len..(start + part.in_height) * row_len;
                (part, inputs, units.start * out_row..units.end * out_row)
            } else {
                let part = ConvShape {
                    in_width: units.len(),
                    ..*shape
                };
                let (channels, out_channels) = (shape.in_channels, shape.out_channels);
                let inputs = units.start * channels..units.end * channels;
                (
                    part,
                    inputs,
                    units.start * out_channels..units.end * out_channels,
                )
            };
            // SAFETY: the pieces' output ranges are disjoint parts of `output`, which the
            // caller does not touch until `run` has returned.
            let output = unsafe { out.slice(outputs) };
            band(&part, inputs, output);
        });
        true
    }

    /// Runs `block(channels, output)` of a 1-D convolution on blocks of output channels
    /// (`channels` the range, a multiple of [`INT8_CHANNEL_BLOCK`] wide but for the last,
    /// `output` its `[positions, channels]` part of the scratch: written over, or holding
    /// those channels' output values first with [`Store::Continue`]), then puts each into
    /// place as `store` says; `false` when the call is not cut, or when `block` declined
    /// every piece (it declines all or none: its answer depends on the shape alone).
    fn split_channels(
        &self,
        shape: &ConvShape,
        weight_products: usize,
        output: &mut [f32],
        store: Store,
        block: &(dyn Fn(Range<usize>, &mut [f32]) -> bool + Sync),
    ) -> bool {
        let out_channels = shape.out_channels;
        let positions = shape.out_height() * shape.out_width();
        let products = positions * weight_products;
        let blocks = out_channels.div_ceil(INT8_CHANNEL_BLOCK);
        let plain = (INT8_CHANNEL_BLOCK, self.pieces(blocks, products));
        // Blocks of whole groups for the epilogue, unless that leaves fewer pieces.
        let by_groups = self
            .fused
            .filter(|fused| store == Store::Overwrite && fused.channels == out_channels)
            .and_then(|fused| {
                let group = fused.epilogue.group_size(out_channels);
                let whole = group > 0 && out_channels.is_multiple_of(group);
                let unit = whole.then(|| lcm(INT8_CHANNEL_BLOCK, group))?;
                let pieces = self.pieces(out_channels.div_ceil(unit), products);
                (pieces >= plain.1).then_some((fused, unit, pieces))
            });
        let fused = by_groups.map(|(fused, _, _)| fused);
        let (unit, pieces) = by_groups.map_or(plain, |(_, unit, pieces)| (unit, pieces));
        let units = out_channels.div_ceil(unit);
        let fits = output.len() >= positions * out_channels
            && self.scratch.len >= positions * out_channels;
        if pieces < 2 || !fits {
            return false;
        }
        if self.busy.swap(true, Ordering::Acquire) {
            return false;
        }
        let (scratch, out) = (self.scratch, Shared::new(output));
        let done = AtomicUsize::new(0);
        self.workers.run(pieces, &|piece| {
            let units = share(units, pieces, piece);
            let start = units.start * unit;
            let end = (units.end * unit).min(out_channels);
            if start >= end {
                done.fetch_add(1, Ordering::Relaxed);
                return;
            }
            let width = end - start;
            // SAFETY: the pieces' channel ranges are disjoint, so are their parts of the
            // scratch, which `busy` keeps for this call alone.
            let values = unsafe { scratch.slice(positions * start..positions * end) };
            // SAFETY (both blocks below): this piece's channels of one output row: disjoint
            // from every other piece's, and the caller does not touch `output` until `run`
            // has returned.
            let row_of = |position: usize| unsafe {
                let at = position * out_channels + start;
                out.slice(at..at + width)
            };
            if store == Store::Continue {
                for (position, row) in values.chunks_exact_mut(width).enumerate() {
                    row.copy_from_slice(row_of(position));
                }
            }
            if !block(start..end, values) {
                return;
            }
            if let Some(fused) = fused {
                // SAFETY: the pieces' channel ranges are disjoint, so are their parts of
                // the FiLM scratch, which the caller of `conv_then` does not touch until
                // it returns.
                let film = match fused.epilogue.film {
                    Some(_) => unsafe { fused.film.slice(2 * start..2 * end) },
                    None => &mut [],
                };
                let channels = start..end;
                fused
                    .epilogue
                    .run(self.kernels, out_channels, channels, values, film);
            }
            for (position, row) in values.chunks_exact(width).enumerate() {
                let target = row_of(position);
                match store {
                    Store::Overwrite | Store::Continue => target.copy_from_slice(row),
                    // `output += (acc * scale + bias)`: the int8 contract's order exactly.
                    Store::Add => target.iter_mut().zip(row).for_each(|(o, v)| *o += v),
                }
            }
            done.fetch_add(1, Ordering::Relaxed);
        });
        self.busy.store(false, Ordering::Release);
        let done = done.load(Ordering::Relaxed);
        assert!(
            done == 0 || done == pieces,
            "a channel block was declined, not all"
        );
        if fused.is_some() && done == pieces {
            self.applied.store(true, Ordering::Relaxed);
        }
        done == pieces
    }

    /// Whether cutting a 2-D map's output rows over the workers would leave a band with
    /// fewer output pixels than the kernels' int8 convolutions compute at once.
    fn bands_below_block(&self, shape: &ConvShape) -> bool {
        let pieces = self.workers.count().max(1);
        shape.in_height > 1
            && shape.out_height() / pieces * shape.out_width() < self.kernels.int8_pixel_block()
    }

    /// [`Split::int8_by_channels`] where it can cut the call; `false` (nothing run) where
    /// not.
    fn int8_by_channels_cut(
        &self,
        shape: &ConvShape,
        parameters: Int8Parameters<'_>,
        output: &mut [f32],
        accumulate: Accumulate,
        run: &Int8Run<'_>,
    ) -> bool {
        let block = |channels: Range<usize>, output: &mut [f32]| {
            let (part, parameters) = channel_block(shape, parameters, channels.clone());
            run(&part, parameters, channels, output, Accumulate::Overwrite);
            true
        };
        let store = match accumulate {
            Accumulate::Overwrite => Store::Overwrite,
            Accumulate::Add => Store::Add,
        };
        int8_lengths_hold(shape, parameters)
            && self.split_channels(shape, shape.int8_weight_len(), output, store, &block)
    }

    /// A 1-D int8 convolution (`run` the kernel on its input) cut into blocks of output
    /// channels ([`Self::split_channels`]), each block's weights, scales and biases its own
    /// run of the layer's ([`channel_block`]); run whole when it is not cut.
    fn int8_by_channels(
        &self,
        shape: &ConvShape,
        parameters: Int8Parameters<'_>,
        output: &mut [f32],
        accumulate: Accumulate,
        run: &Int8Run<'_>,
    ) {
        if !self.int8_by_channels_cut(shape, parameters, output, accumulate, run) {
            run(shape, parameters, 0..shape.out_channels, output, accumulate)
        }
    }

    /// `conv_int8_bytes` (with the weights' pair layout where given) in bands of output
    /// rows, the whole weights to each.
    fn bytes_by_rows(
        &self,
        shape: &ConvShape,
        input: &ByteRows<'_>,
        (weight, scales, bias): Int8Parameters<'_>,
        pairs: Option<&[i8]>,
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let kernels = self.kernels;
        if self.bands_below_block(shape) {
            let by_channels = |part: &ConvShape,
                               (weight, scales, bias): Int8Parameters<'_>,
                               channels: Range<usize>,
                               output: &mut [f32],
                               accumulate| match pairs {
                Some(pairs) => kernels.conv_int8_bytes_paired(
                    part,
                    input,
                    weight,
                    pairs_block(shape, pairs, channels),
                    scales,
                    bias,
                    output,
                    accumulate,
                ),
                None => {
                    kernels.conv_int8_bytes(part, input, weight, scales, bias, output, accumulate)
                }
            };
            let parameters = (weight, scales, bias);
            if self.int8_by_channels_cut(shape, parameters, output, accumulate, &by_channels) {
                return;
            }
        }
        let run = |shape: &ConvShape, input: &ByteRows<'_>, output: &mut [f32]| match pairs {
            Some(pairs) => kernels.conv_int8_bytes_paired(
                shape, input, weight, pairs, scales, bias, output, accumulate,
            ),
            None => kernels.conv_int8_bytes(shape, input, weight, scales, bias, output, accumulate),
        };
        let band = |part: &ConvShape, inputs: Range<usize>, output: &mut [f32]| {
            let bytes = ByteRows {
                bytes: &input.bytes[inputs],
                ..*input
            };
            run(part, &bytes, output)
        };
        if !self.split_rows(shape, input.bytes.len(), output, &band) {
            run(shape, input, output)
        }
    }

    /// Runs `rows(range, output)` on runs of a matrix-vector product's rows.
    fn split_matrix_rows(
        &self,
        rows: usize,
        cols: usize,
        output: &mut [f32],
        part: &(dyn Fn(Range<usize>, &mut [f32]) + Sync),
    ) -> bool {
        let pieces = self.pieces(rows, rows * cols);
        if pieces < 2 || output.len() != rows {
            return false;
        }
        let out = Shared::new(output);
        self.workers.run(pieces, &|piece| {
            let range = share(rows, pieces, piece);
            // SAFETY: the pieces' row ranges are disjoint parts of `output`, which the
            // caller does not touch until `run` has returned.
            let output = unsafe { out.slice(range.clone()) };
            part(range, output);
        });
        true
    }
}

/// Output channels `channels` (starting at a block) of an int8 convolution: the same
/// convolution with those outputs only, and their weights, scales and biases. The int8
/// layout stores a block's weights together ([`INT8_CHANNEL_BLOCK`]), so they are one run.
fn channel_block<'p>(
    shape: &ConvShape,
    (weight, scales, bias): Int8Parameters<'p>,
    channels: Range<usize>,
) -> (ConvShape, Int8Parameters<'p>) {
    let per_channel = shape.int8_weight_len() / shape.out_channels.max(1);
    let part = ConvShape {
        out_channels: channels.len(),
        ..*shape
    };
    let weights = &weight[channels.start * per_channel..channels.end * per_channel];
    (part, (weights, &scales[channels.clone()], &bias[channels]))
}

/// The pair layout of output channels `channels` (starting at a block) of an int8
/// convolution: it keeps the quads' blocks of channels, so a run of whole blocks is one run
/// of pairs too. Pairs of another length than the shape's are handed on whole, for the
/// kernel to refuse.
fn pairs_block<'p>(shape: &ConvShape, pairs: &'p [i8], channels: Range<usize>) -> &'p [i8] {
    if pairs.len() != shape.int8_pair_weight_len() {
        return pairs;
    }
    let per_channel = shape.int8_pair_weight_len() / shape.out_channels.max(1);
    &pairs[channels.start * per_channel..channels.end * per_channel]
}

/// Whether an int8 convolution's parameters are as long as its shape says (the kernels
/// assert it; a call that breaks it runs whole, to fail there).
fn int8_lengths_hold(shape: &ConvShape, (weight, scales, bias): Int8Parameters<'_>) -> bool {
    let out_channels = shape.out_channels;
    weight.len() == shape.int8_weight_len()
        && scales.len() == out_channels
        && bias.len() == out_channels
}

/// How a channel block's results go into the output.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Store {
    Overwrite,
    /// Added (int8: `output += that`).
    Add,
    /// The block started from the output's values (f32 `Add`: the sums continue them) and
    /// its results replace them.
    Continue,
}

/// The least common multiple of `a` and `b` (both nonzero).
fn lcm(a: usize, b: usize) -> usize {
    a / crate::shape::gcd(a, b) * b
}

/// Piece `piece`'s share of `units` cut into `pieces`: sizes differ by at most one.
fn share(units: usize, pieces: usize, piece: usize) -> Range<usize> {
    units * piece / pieces..units * (piece + 1) / pieces
}

/// Pixels at most that [`Split`]'s `conv_pixels` cuts over the workers (the pyramid asks for
/// 48 at a time): each piece writes its own pixels' values, so the list is checked for
/// repeats first, in `count^2 / 2` comparisons.
const MAX_CUT_PIXELS: usize = 64;

/// Whether no pixel appears twice in `pixels`.
fn distinct(pixels: &[(usize, usize)]) -> bool {
    pixels
        .iter()
        .enumerate()
        .all(|(index, pixel)| !pixels[index + 1..].contains(pixel))
}

/// A mutable slice handed to several pieces, each taking its own disjoint part.
#[derive(Debug)]
struct Shared<T = f32> {
    start: *mut T,
    len: usize,
}

impl<T> Clone for Shared<T> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<T> Copy for Shared<T> {}

// SAFETY: a `Shared` only hands out parts through `slice`, whose callers promise the parts
// they take at the same time are disjoint.
unsafe impl<T: Send> Send for Shared<T> {}
// SAFETY: as above.
unsafe impl<T: Send> Sync for Shared<T> {}

impl<T> Shared<T> {
    fn new(values: &mut [T]) -> Self {
        Shared {
            start: values.as_mut_ptr(),
            len: values.len(),
        }
    }

    /// The values at `range`.
    ///
    /// # Safety
    /// The slice this was made from outlives the result, nothing else reads or writes
    /// those values meanwhile, and no other part taken meanwhile overlaps `range`.
    unsafe fn slice<'a>(self, range: Range<usize>) -> &'a mut [T] {
        assert!(range.start <= range.end && range.end <= self.len);
        // SAFETY: in bounds (asserted); exclusive by the caller's promise.
        unsafe { core::slice::from_raw_parts_mut(self.start.add(range.start), range.len()) }
    }
}

impl Kernels for Split<'_> {
    fn name(&self) -> &'static str {
        self.kernels.name()
    }

    fn conv(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let kernels = self.kernels;
        // A band of a 2-D map's rows reads every weight, a block of output channels the whole
        // input, half of it written by the other core, whose lines come about 4x slower than
        // weights stream from L3 (7 against 27 GB/s, docs/THREADS.md): blocks where the
        // weights outweigh the input 4 to 1 (the small maps of the trunk's last stages).
        let by_channels = (shape.in_height == 1 || shape.weight_len() > 4 * shape.input_len())
            && kernels.conv_channels(shape, input, weight, bias, 0..0, &mut [], accumulate);
        if by_channels {
            let block = |channels: Range<usize>, part: &mut [f32]| {
                kernels.conv_channels(shape, input, weight, bias, channels, part, accumulate)
            };
            let products = shape.weight_len();
            // f32 sums start from the output's value (`Add`): each block starts from its
            // channels' values, and its results replace them.
            let store = match accumulate {
                Accumulate::Overwrite => Store::Overwrite,
                Accumulate::Add => Store::Continue,
            };
            if self.split_channels(shape, products, output, store, &block) {
                return;
            }
        }
        if shape.in_height == 1 {
            // A sequence without a channel form: the f32 kernels sum short and long
            // sequences in different orders, so runs of positions would change bits.
            return kernels.conv(shape, input, weight, bias, output, accumulate);
        }
        let band = |part: &ConvShape, inputs: Range<usize>, output: &mut [f32]| {
            kernels.conv(part, &input[inputs], weight, bias, output, accumulate)
        };
        if !self.split_rows(shape, input.len(), output, &band) {
            kernels.conv(shape, input, weight, bias, output, accumulate)
        }
    }

    fn conv_pixel(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        pixel: (usize, usize),
        output: &mut [f32],
    ) {
        self.kernels
            .conv_pixel(shape, input, weight, bias, pixel, output)
    }

    fn conv_pixels(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        pixels: &[(usize, usize)],
        output: &mut [f32],
    ) {
        let (kernels, count) = (self.kernels, pixels.len());
        let pieces = self.pieces(count, count * shape.weight_len());
        let inside = |&(row, column): &(usize, usize)| {
            row < shape.out_height() && column < shape.out_width()
        };
        let cut = pieces > 1
            && count <= MAX_CUT_PIXELS
            && output.len() >= shape.output_len()
            && pixels.iter().all(inside)
            && distinct(pixels);
        if !cut {
            return kernels.conv_pixels(shape, input, weight, bias, pixels, output);
        }
        let out = Shared::new(output);
        self.workers.run(pieces, &|piece| {
            for &pixel in &pixels[share(count, pieces, piece)] {
                // SAFETY: the pixels are distinct and inside the map (checked above), so their
                // values are disjoint from every other piece's; the caller does not touch
                // `output` until `run` has returned.
                let values = unsafe { out.slice(shape.pixel_values(pixel)) };
                kernels.conv_pixel(shape, input, weight, bias, pixel, values);
            }
        });
    }

    fn conv_int8_pixel(
        &self,
        shape: &ConvShape,
        input: &DigitRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        pixel: (usize, usize),
        output: &mut [f32],
    ) {
        self.kernels
            .conv_int8_pixel(shape, input, weight, weight_scales, bias, pixel, output)
    }

    fn conv_int8_pixels(
        &self,
        shape: &ConvShape,
        input: &DigitRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        pixels: &[(usize, usize)],
        output: &mut [f32],
    ) {
        self.kernels
            .conv_int8_pixels(shape, input, weight, weight_scales, bias, pixels, output)
    }

    fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
        let (rows, cols, kernels) = (output.len(), input.len(), self.kernels);
        let part = |range: Range<usize>, output: &mut [f32]| {
            let weight = &weight[range.start * cols..range.end * cols];
            kernels.matvec(weight, input, &base[range], output)
        };
        if cols == 0
            || weight.len() != rows * cols
            || !self.split_matrix_rows(rows, cols, output, &part)
        {
            kernels.matvec(weight, input, base, output)
        }
    }

    fn conv_int8(
        &self,
        shape: &ConvShape,
        input: &DigitRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let kernels = self.kernels;
        if self.bands_below_block(shape) {
            let run = |part: &ConvShape,
                       (weight, scales, bias): Int8Parameters<'_>,
                       _: Range<usize>,
                       output: &mut [f32],
                       accumulate| {
                kernels.conv_int8(part, input, weight, scales, bias, output, accumulate)
            };
            let parameters = (weight, weight_scales, bias);
            if self.int8_by_channels_cut(shape, parameters, output, accumulate, &run) {
                return;
            }
        }
        let band = |part: &ConvShape, inputs: Range<usize>, output: &mut [f32]| {
            let digits = DigitRows {
                high: &input.high[inputs.clone()],
                low: &input.low[inputs],
                ..*input
            };
            kernels.conv_int8(
                part,
                &digits,
                weight,
                weight_scales,
                bias,
                output,
                accumulate,
            )
        };
        let input_len = input.high.len().min(input.low.len());
        if !self.split_rows(shape, input_len, output, &band) {
            kernels.conv_int8(
                shape,
                input,
                weight,
                weight_scales,
                bias,
                output,
                accumulate,
            )
        }
    }

    fn conv_int8_bytes(
        &self,
        shape: &ConvShape,
        input: &ByteRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let parameters = (weight, weight_scales, bias);
        self.bytes_by_rows(shape, input, parameters, None, output, accumulate)
    }

    fn conv_int8_bytes_paired(
        &self,
        shape: &ConvShape,
        input: &ByteRows<'_>,
        weight: &[i8],
        pairs: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let parameters = (weight, weight_scales, bias);
        self.bytes_by_rows(shape, input, parameters, Some(pairs), output, accumulate)
    }

    fn conv_int8_codes(
        &self,
        shape: &ConvShape,
        input: &CodeRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let kernels = self.kernels;
        let run = |shape: &ConvShape,
                   (weight, scales, bias): Int8Parameters<'_>,
                   _: Range<usize>,
                   output: &mut [f32],
                   accumulate| {
            kernels.conv_int8_codes(shape, input, weight, scales, bias, output, accumulate)
        };
        let parameters = (weight, weight_scales, bias);
        self.int8_by_channels(shape, parameters, output, accumulate, &run)
    }

    fn conv_int8_signed_bytes(
        &self,
        shape: &ConvShape,
        input: &SignedByteRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let kernels = self.kernels;
        let run = |shape: &ConvShape,
                   (weight, scales, bias): Int8Parameters<'_>,
                   _: Range<usize>,
                   output: &mut [f32],
                   accumulate| {
            kernels.conv_int8_signed_bytes(shape, input, weight, scales, bias, output, accumulate)
        };
        let parameters = (weight, weight_scales, bias);
        self.int8_by_channels(shape, parameters, output, accumulate, &run)
    }

    fn conv_int8_signed_bytes_paired(
        &self,
        shape: &ConvShape,
        input: &SignedByteRows<'_>,
        weight: &[i8],
        pairs: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let kernels = self.kernels;
        let run = |part: &ConvShape,
                   (weight, scales, bias): Int8Parameters<'_>,
                   channels: Range<usize>,
                   output: &mut [f32],
                   accumulate| {
            let pairs = pairs_block(shape, pairs, channels);
            kernels.conv_int8_signed_bytes_paired(
                part, input, weight, pairs, scales, bias, output, accumulate,
            )
        };
        let parameters = (weight, weight_scales, bias);
        self.int8_by_channels(shape, parameters, output, accumulate, &run)
    }

    fn matvec_int8_codes(
        &self,
        weight: &[i8],
        row_scales: &[f32],
        input: &CodeRows<'_>,
        base: &[f32],
        output: &mut [f32],
    ) {
        let (rows, kernels) = (output.len(), self.kernels);
        let cols = weight.len().checked_div(rows).unwrap_or(0);
        let part = |range: Range<usize>, output: &mut [f32]| {
            let weight = &weight[range.start * cols..range.end * cols];
            kernels.matvec_int8_codes(
                weight,
                &row_scales[range.clone()],
                input,
                &base[range],
                output,
            )
        };
        let whole = cols == 0
            || weight.len() != rows * cols
            || row_scales.len() != rows
            || base.len() != rows
            || !self.split_matrix_rows(rows, cols, output, &part);
        if whole {
            kernels.matvec_int8_codes(weight, row_scales, input, base, output)
        }
    }

    fn quantize_digits(&self, input: &[f32], digits: (&mut [i8], &mut [i8])) -> (f32, bool) {
        let (kernels, len) = (self.kernels, input.len());
        let pieces = self.pieces(len, ELEMENT_WORK * len);
        if pieces < 2 || digits.0.len() < len || digits.1.len() < len {
            return kernels.quantize_digits(input, digits);
        }
        let (high, low) = (Shared::new(digits.0), Shared::new(digits.1));
        let (largest, nonnegative) = self.quantize_by_runs(input, pieces, &|run, largest| {
            // SAFETY: the pieces' runs are disjoint parts of both planes, which the caller
            // does not touch until `run` has returned.
            let digits = unsafe { (high.slice(run.clone()), low.slice(run.clone())) };
            kernels
                .quantize_digits_within(&input[run], largest, digits)
                .1
        });
        let (scale, _) = kernels.quantize_digits_within(&[], largest, (&mut [], &mut []));
        (scale, nonnegative)
    }

    fn largest_magnitude(&self, input: &[f32]) -> f32 {
        self.kernels.largest_magnitude(input)
    }

    fn quantize_digits_within(
        &self,
        input: &[f32],
        largest: f32,
        digits: (&mut [i8], &mut [i8]),
    ) -> (f32, bool) {
        self.kernels.quantize_digits_within(input, largest, digits)
    }

    fn quantize_narrow_within(
        &self,
        input: &[f32],
        largest: f32,
        codes: (&mut [i8], &mut [i8]),
        form: NarrowForm,
    ) -> f32 {
        self.kernels
            .quantize_narrow_within(input, largest, codes, form)
    }

    fn narrow_form(&self) -> NarrowForm {
        self.kernels.narrow_form()
    }

    fn quantize_narrow(&self, input: &[f32], scratch: &mut [i8], form: NarrowForm) -> f32 {
        let (kernels, len) = (self.kernels, input.len());
        let pieces = self.pieces(len, ELEMENT_WORK * len);
        let planes = match form {
            NarrowForm::Bytes => 1,
            NarrowForm::Digits => 2,
        };
        if pieces < 2 || scratch.len() < planes * len {
            return kernels.quantize_narrow(input, scratch, form);
        }
        let (first, second) = match form {
            NarrowForm::Bytes => (&mut scratch[..len], &mut [][..]),
            NarrowForm::Digits => scratch[..2 * len].split_at_mut(len),
        };
        let (first, second) = (Shared::new(first), Shared::new(second));
        let (largest, _) = self.quantize_by_runs(input, pieces, &|run, largest| {
            let second_run = if planes == 2 { run.clone() } else { 0..0 };
            // SAFETY: the pieces' runs are disjoint parts of the codes, which the caller
            // does not touch until `run` has returned.
            let codes = unsafe { (first.slice(run.clone()), second.slice(second_run)) };
            kernels.quantize_narrow_within(&input[run], largest, codes, form);
            true
        });
        kernels.quantize_narrow_within(&[], largest, (&mut [], &mut []), form)
    }

    fn quantize_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
        self.kernels.quantize_codes(input, row_len, codes)
    }

    fn quantize_signed_bytes(
        &self,
        input: &[f32],
        row_len: usize,
        codes: &mut [i8],
        row_sums: &mut [i32],
    ) -> f32 {
        self.kernels
            .quantize_signed_bytes(input, row_len, codes, row_sums)
    }

    fn quantize_narrow_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
        self.kernels.quantize_narrow_codes(input, row_len, codes)
    }

    fn multiplies_signed_bytes(&self) -> bool {
        self.kernels.multiplies_signed_bytes()
    }

    fn group_norm(
        &self,
        data: &mut [f32],
        channels: usize,
        groups: usize,
        affine: (&[f32], &[f32]),
        activation: Activation,
    ) {
        if !self.group_norm_by_blocks(data, channels, groups, affine, activation) {
            self.kernels
                .group_norm(data, channels, groups, affine, activation)
        }
    }

    fn affine_activate(
        &self,
        data: &mut [f32],
        channels: usize,
        affine: (&[f32], &[f32]),
        activation: Activation,
    ) {
        self.kernels
            .affine_activate(data, channels, affine, activation)
    }

    fn add_activate(&self, target: &mut [f32], source: &[f32], activation: Activation) {
        let (kernels, len) = (self.kernels, target.len());
        // Element-wise: runs of values give the whole call's bits.
        let pieces = self.pieces(len, ELEMENT_WORK * len);
        if pieces < 2 || source.len() < len {
            return kernels.add_activate(target, source, activation);
        }
        let out = Shared::new(target);
        self.workers.run(pieces, &|piece| {
            let run = share(len, pieces, piece);
            // SAFETY: the pieces' runs are disjoint parts of `target`, which the caller
            // does not touch until `run` has returned.
            let part = unsafe { out.slice(run.clone()) };
            kernels.add_activate(part, &source[run], activation);
        });
    }

    fn conv_then(
        &self,
        output: &mut [f32],
        channels: usize,
        epilogue: &Epilogue<'_>,
        film: &mut [f32],
        conv: &mut dyn FnMut(&dyn Kernels, &mut [f32]),
    ) -> bool {
        let film_len = if epilogue.film.is_some() {
            2 * channels
        } else {
            0
        };
        if self.fused.is_some() || film.len() < film_len || self.busy.load(Ordering::Acquire) {
            return false;
        }
        // A view of these kernels whose channel-cut convolution runs the epilogue on each
        // block; this one is not used until it is done.
        let fused = Split {
            kernels: self.kernels,
            workers: self.workers,
            scratch: self.scratch,
            min_products: self.min_products,
            busy: AtomicBool::new(false),
            fused: Some(Fused {
                epilogue: *epilogue,
                channels,
                film: Shared::new(&mut film[..film_len]),
            }),
            applied: AtomicBool::new(false),
            _scratch: core::marker::PhantomData,
        };
        conv(&fused, output);
        if !fused.applied.load(Ordering::Relaxed) {
            epilogue.apply(self, channels, output, film);
        }
        true
    }

    fn add_channel_moments(
        &self,
        data: &[f32],
        channels: usize,
        (sums, squares): (&mut [f64], &mut [f64]),
    ) {
        if !self.moments_by_blocks(data, channels, (&mut *sums, &mut *squares)) {
            self.kernels
                .add_channel_moments(data, channels, (sums, squares))
        }
    }

    fn normalize_max_pool(
        &self,
        input: &[f32],
        dims: (usize, usize, usize),
        affine: (&[f32], &[f32]),
        activation: Activation,
        output: &mut [f32],
        first_row: usize,
    ) {
        let (kernels, channels) = (self.kernels, dims.2);
        let row_len = shape::conv_output(dims.1, 3, 2, 1) * channels;
        let rows = output.len().checked_div(row_len).unwrap_or(0);
        // Bands of pooled rows: each reads the map's rows around twice its own, which the
        // stem's convolution pieces mostly wrote on the same core.
        let pieces = self.pieces(rows, ELEMENT_WORK * input.len());
        if pieces < 2 || output.len() != rows * row_len {
            return kernels.normalize_max_pool(input, dims, affine, activation, output, first_row);
        }
        let out = Shared::new(output);
        self.workers.run(pieces, &|piece| {
            let band = share(rows, pieces, piece);
            // SAFETY: the pieces' bands are disjoint parts of `output`, which the caller
            // does not touch until `run` has returned.
            let part = unsafe { out.slice(band.start * row_len..band.end * row_len) };
            let first = first_row + band.start;
            kernels.normalize_max_pool(input, dims, affine, activation, part, first);
        });
    }

    fn max_pool_3x3_stride_2(
        &self,
        input: &[f32],
        dims: (usize, usize, usize),
        output: &mut [f32],
    ) {
        self.kernels.max_pool_3x3_stride_2(input, dims, output)
    }
}
