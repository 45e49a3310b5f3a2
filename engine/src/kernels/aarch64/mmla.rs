//! The int8 convolutions on I8MM's matrix multiply: `usmmla` (whole bytes, u8 x i8) and
//! `smmla` (signed narrow codes, i8 x i8) multiply a 2 x 8 matrix by an 8 x 2 one into a
//! 2 x 2 block of i32 sums, 32 products an instruction where `usdot` and `sdot` make 16.
//!
//! Both operands hold two rows of eight bytes that run over the same eight inputs: the
//! first two pixels (each pixel's row of activations is contiguous, so a pair is two 8-byte
//! loads), the second two output channels. The weights are stored in input-channel quads,
//! four channels a 16-byte row (`[c0 k0..4, c1 k0..4, c2 k0..4, c3 k0..4]`) and the next
//! quad's row a quad stride further, so one `zip1` / `zip2` of two consecutive quad rows
//! gives channels (c0, c1) and (c2, c3) over eight inputs. Every operand thus costs one
//! vector instruction besides the multiplies (the pair's second load, `ld1 {v.d}[1]`, or a
//! zip), on the same pipes: a tile of `PAIRS` pixel pairs by `V` vectors of four channels
//! (`2 V` channel pairs) runs `2 PAIRS V` multiplies in `2 PAIRS V + PAIRS + 2 V` vector
//! instructions. 6 pairs by 2 vectors (12 pixels by 8 channels, 24 sums of the 32
//! registers) is the most the registers hold: 24 multiplies in 34 instructions, 70.6% of
//! the multiplies' peak, against the dot products' 50%. Where the file holds the weights in
//! the pair layout as well (eight inputs a group, `crate::shape::int8_pair_index`), each
//! channel pair is one plain load, off those pipes, so the tile turns to fewer pixels and
//! more channels: 3 pairs by 4 vectors (6 pixels by 16 channels) is 24 multiplies and 3
//! lane loads, 89% of the peak on the pipes (llvm-mca's schedule: 79-83%, benches/README.md).
//!
//! The sums are exact integers as the dot products' are, so every output has the same bits
//! as on every other backend.

use core::arch::aarch64::{
    int8x16_t, int32x4_t, vcombine_s8, vcreate_s8, vdupq_n_s32, vld1q_s8, vreinterpretq_s8_s32,
    vreinterpretq_s32_s8, vreinterpretq_s32_s64, vreinterpretq_s64_s32, vzip1q_s32, vzip1q_s64,
    vzip2q_s32, vzip2q_s64,
};

use super::int8_lanes::DotQ;
use crate::kernels::scalar::{
    CodeSums, assert_byte_lengths, assert_signed_byte_lengths, conv_int8_bytes, conv_int8_pixels,
};
use crate::kernels::simd::int8::{
    Int8Lanes, PREFETCH_QUADS, PixelTile, SignedByteLanes, ZERO_ROW, store,
};
use crate::kernels::simd::prefetch_lines_into_l2;
use crate::kernels::{
    Accumulate, ByteRows, CodeRows, ConvShape, INT8_CHANNEL_BLOCK, PAIR, QUAD, SignedByteRows,
    int8_pair_index, int8_quad_stride,
};

/// Pixel pairs x vectors of four channels of the main tile on quads: 24 sums, the pairs'
/// operands and two vectors' weights in the 32 registers.
const QUADS_TILE: (usize, usize) = (6, 2);

/// The main tile on the pair layout (6 pixels by 16 channels): 24 sums, three pixel pairs'
/// operands and a weight operand at a time in the registers. Its weights cost loads only,
/// so it takes more channels and fewer pixels: 24 multiplies and 3 lane loads a step, 89% of
/// the multiplies' peak (the quads' tile of 12 x 8 would reach 80%).
const PAIRS_TILE: (usize, usize) = (3, 4);

/// Pixel pairs of the tile that takes a map's last pixels, up to 8 of them (a map of 16
/// pixels: 12 and 4): 2 pairs by 2 vectors take 14 vector instructions a step to the main
/// tile's 34, so even two of them cost less than a main tile mostly empty.
const SMALL_PAIRS: usize = 2;

/// The lanes whose f32 operations finish a tile (scaling, bias, store).
type Lanes = DotQ;

/// One of I8MM's matrix multiplies: `sum + a b^T`, `a` and `b` two rows of eight bytes each,
/// the sum `[a0 . b0, a0 . b1, a1 . b0, a1 . b1]`.
trait MatrixProduct {
    /// # Safety
    /// The CPU has I8MM.
    unsafe fn multiply(sum: int32x4_t, a: int8x16_t, b: int8x16_t) -> int32x4_t;
}

/// `usmmla`: `a` unsigned (whole bytes), `b` signed (the weights).
struct Unsigned;

/// `smmla`: both sides signed.
struct Signed;

impl MatrixProduct for Unsigned {
    #[inline(always)]
    unsafe fn multiply(mut sum: int32x4_t, a: int8x16_t, b: int8x16_t) -> int32x4_t {
        // SAFETY: `usmmla` reads and writes registers only; the caller runs on a CPU with I8MM.
        unsafe {
            core::arch::asm!(
                "usmmla {sum:v}.4s, {a:v}.16b, {b:v}.16b",
                sum = inout(vreg) sum,
                a = in(vreg) a,
                b = in(vreg) b,
                options(pure, nomem, nostack, preserves_flags),
            );
        }
        sum
    }
}

impl MatrixProduct for Signed {
    #[inline(always)]
    unsafe fn multiply(mut sum: int32x4_t, a: int8x16_t, b: int8x16_t) -> int32x4_t {
        // SAFETY: `smmla` reads and writes registers only; the caller runs on a CPU with I8MM.
        unsafe {
            core::arch::asm!(
                "smmla {sum:v}.4s, {a:v}.16b, {b:v}.16b",
                sum = inout(vreg) sum,
                a = in(vreg) a,
                b = in(vreg) b,
                options(pure, nomem, nostack, preserves_flags),
            );
        }
        sum
    }
}

/// The sums of a tile: per pixel pair and vector of four channels, the 2 x 2 blocks of
/// channels (0, 1) and (2, 3).
type Sums<const PAIRS: usize, const V: usize> = [[[int32x4_t; 2]; V]; PAIRS];

/// Activations in byte rows that the matrix tiles read, with the product that takes them.
trait MatrixInput: CodeSums {
    type Product: MatrixProduct;
    /// Whether the weights stream from L3 (the U-Net's, read once a denoising step), so
    /// L2 is asked for them ahead, as the dot products' tiles do.
    const STREAMED: bool;
    /// The rows of bytes, one a pixel, `row_stride` apart.
    fn rows(&self) -> &[i8];
    /// Bytes from one pixel's row to the next: whole input-channel quads.
    fn row_stride(shape: &ConvShape) -> usize;
}

impl MatrixInput for ByteRows<'_> {
    type Product = Unsigned;
    const STREAMED: bool = false;
    fn rows(&self) -> &[i8] {
        bytemuck::cast_slice(self.bytes)
    }
    fn row_stride(shape: &ConvShape) -> usize {
        shape.in_channels
    }
}

impl MatrixInput for SignedByteRows<'_> {
    type Product = Signed;
    const STREAMED: bool = true;
    fn rows(&self) -> &[i8] {
        self.codes
    }
    fn row_stride(shape: &ConvShape) -> usize {
        CodeRows::row_stride(shape.in_channels)
    }
}

/// How the weights a tile reads are laid out: the quads every backend reads, or the pair
/// layout a file may hold beside them.
trait WeightLayout {
    /// Whether a step loads every pixel pair's operand first and streams the weights past
    /// them (weights that cost a load only), or holds the weights and streams the pixels
    /// (weights that cost a `zip` each).
    const PIXELS_FIRST: bool;

    /// Index of tap `tap`'s first inputs of channel `channel` (a multiple of four).
    fn tap_start(shape: &ConvShape, tap: usize, channel: usize) -> usize;

    /// Channels (c0, c1) and (c2, c3) of the `vector`-th four from the step's first (eight
    /// inputs a step: one step's weights start at `step`, steps `2 quad_stride` bytes
    /// apart); `last` for a step of one quad, whose other four inputs weigh zero.
    ///
    /// # Safety
    /// NEON; the step's weights of the vector's four channels are readable.
    unsafe fn channel_pairs(
        step: *const i8,
        vector: usize,
        quad_stride: usize,
        last: bool,
    ) -> [int8x16_t; 2];

    /// Asks L2 for the weights of `V` vectors at `ahead` (a step's start, maybe past the
    /// end: a hint never faults).
    fn prefetch<const V: usize>(ahead: *const i8, quad_stride: usize);
}

/// Input-channel quads: a step is two quad rows, paired by `zip`.
struct Quads;

/// The pair layout: a step's channel pairs as stored.
struct Pairs;

impl WeightLayout for Quads {
    const PIXELS_FIRST: bool = false;

    fn tap_start(shape: &ConvShape, tap: usize, channel: usize) -> usize {
        shape.int8_index(tap, 0, channel)
    }

    #[inline(always)]
    unsafe fn channel_pairs(
        step: *const i8,
        vector: usize,
        quad_stride: usize,
        last: bool,
    ) -> [int8x16_t; 2] {
        let first = step.wrapping_add(vector * Lanes::WIDTH * QUAD);
        // SAFETY: the quad rows the caller vouches for; NEON (likewise).
        unsafe {
            let high = match last {
                true => vreinterpretq_s8_s32(vdupq_n_s32(0)),
                false => vld1q_s8(first.add(quad_stride)),
            };
            channel_pairs(vld1q_s8(first), high)
        }
    }

    #[inline(always)]
    fn prefetch<const V: usize>(ahead: *const i8, quad_stride: usize) {
        prefetch_lines_into_l2(ahead, V * Lanes::WIDTH * QUAD);
        prefetch_lines_into_l2(ahead.wrapping_add(quad_stride), V * Lanes::WIDTH * QUAD);
    }
}

impl WeightLayout for Pairs {
    const PIXELS_FIRST: bool = true;

    fn tap_start(shape: &ConvShape, tap: usize, channel: usize) -> usize {
        let taps = shape.kernel_height * shape.kernel_width;
        int8_pair_index(
            taps,
            shape.in_channels,
            shape.out_channels,
            (tap, 0, channel),
        )
    }

    #[inline(always)]
    unsafe fn channel_pairs(step: *const i8, vector: usize, _: usize, _: bool) -> [int8x16_t; 2] {
        // A last group of four stores the other four as zeros.
        let first = step.wrapping_add(vector * Lanes::WIDTH * PAIR);
        // SAFETY: the step's pairs the caller vouches for; NEON (likewise).
        unsafe { [vld1q_s8(first), vld1q_s8(first.add(2 * PAIR))] }
    }

    #[inline(always)]
    fn prefetch<const V: usize>(ahead: *const i8, _: usize) {
        prefetch_lines_into_l2(ahead, V * Lanes::WIDTH * PAIR);
    }
}

/// `sums +` one kernel tap's products: `sources` are each pair's two rows of `quads` whole
/// quads, `weights` the tap's first inputs of the block's first channel in layout `W`
/// (`quad_stride` the quads' stride), `4 V` channels each. Eight inputs a step; an odd last
/// quad pairs with zeros.
///
/// # Safety
/// The CPU has I8MM; the rows and the weights are readable as described.
#[inline(always)]
unsafe fn add_tap<I: MatrixInput, W: WeightLayout, const PAIRS: usize, const V: usize>(
    mut sums: Sums<PAIRS, V>,
    sources: &[[*const i8; 2]; PAIRS],
    weights: *const i8,
    quads: usize,
    quad_stride: usize,
) -> Sums<PAIRS, V> {
    // SAFETY (both parts): every read is inside a source row's `quads` quads or the tap's
    // weights of the block (the caller's promise); I8MM (likewise).
    unsafe {
        for step in 0..quads / 2 {
            let at = 2 * QUAD * step;
            let row = weights.add(2 * step * quad_stride);
            if I::STREAMED {
                // A hint only (it never faults), hence the wrapping address.
                W::prefetch::<V>(row.wrapping_add(PREFETCH_QUADS * quad_stride), quad_stride);
            }
            if W::PIXELS_FIRST {
                // Every pair's operand, then one weight operand at a time, used at once.
                let pairs = sources.map(|rows| pixel_pair(rows[0].add(at), rows[1].add(at)));
                for vector in 0..V {
                    let channels = W::channel_pairs(row, vector, quad_stride, false);
                    for (half, &channels) in channels.iter().enumerate() {
                        for (sums, &pair) in sums.iter_mut().zip(&pairs) {
                            let sum = &mut sums[vector][half];
                            *sum = I::Product::multiply(*sum, pair, channels);
                        }
                    }
                }
                continue;
            }
            let mut channels = [[vreinterpretq_s8_s32(vdupq_n_s32(0)); 2]; V];
            for (vector, channels) in channels.iter_mut().enumerate() {
                *channels = W::channel_pairs(row, vector, quad_stride, false);
            }
            // One pair's operand at a time, used at once: the sums, the weights and one
            // operand fill the registers.
            for (rows, sums) in sources.iter().zip(sums.iter_mut()) {
                let pair = pixel_pair(rows[0].add(at), rows[1].add(at));
                for (sums, channels) in sums.iter_mut().zip(&channels) {
                    for (sum, &channels) in sums.iter_mut().zip(channels) {
                        *sum = I::Product::multiply(*sum, pair, channels);
                    }
                }
            }
        }
        if quads % 2 == 1 {
            // The last quad: four inputs, the weights' other half zero, so whatever the
            // pixels' other half holds adds nothing; it is read as zeros (4-byte loads stay
            // inside the rows).
            let at = (quads - 1) * QUAD;
            let row = weights.add((quads - 1) * quad_stride);
            let mut pairs = [vreinterpretq_s8_s32(vdupq_n_s32(0)); PAIRS];
            for (pair, rows) in pairs.iter_mut().zip(sources) {
                let first = rows[0].add(at).cast::<u32>().read_unaligned();
                let second = rows[1].add(at).cast::<u32>().read_unaligned();
                *pair = vcombine_s8(vcreate_s8(first.into()), vcreate_s8(second.into()));
            }
            for vector in 0..V {
                let channels = W::channel_pairs(row, vector, quad_stride, true);
                for (pair, sums) in pairs.iter().zip(sums.iter_mut()) {
                    for (sum, channels) in sums[vector].iter_mut().zip(channels) {
                        *sum = I::Product::multiply(*sum, *pair, channels);
                    }
                }
            }
        }
    }
    sums
}

/// Eight bytes from each of two rows: `[first 0..8, second 0..8]`.
///
/// # Safety
/// NEON; 8 bytes readable from each pointer.
#[inline(always)]
unsafe fn pixel_pair(first: *const i8, second: *const i8) -> int8x16_t {
    let pair: int8x16_t;
    // SAFETY: the loads read the 8 bytes the caller vouches for; NEON (likewise). `ldr d`
    // takes a load pipe only; the compiler's own sequence loaded both halves and moved the
    // second across (`mov v.d[1]`), a register more for each pair of the tile.
    unsafe {
        core::arch::asm!(
            "ldr {pair:d}, [{first}]",
            "ld1 {{{pair:v}.d}}[1], [{second}]",
            pair = out(vreg) pair,
            first = in(reg) first,
            second = in(reg) second,
            options(pure, readonly, nostack, preserves_flags),
        );
    }
    pair
}

/// Channels (c0, c1) and (c2, c3) over eight inputs, from the quad rows of four channels
/// over inputs 0..4 (`low`) and 4..8 (`high`).
///
/// # Safety
/// NEON.
#[inline(always)]
unsafe fn channel_pairs(low: int8x16_t, high: int8x16_t) -> [int8x16_t; 2] {
    // SAFETY: NEON (the caller's promise).
    unsafe {
        let (low, high) = (vreinterpretq_s32_s8(low), vreinterpretq_s32_s8(high));
        [
            vreinterpretq_s8_s32(vzip1q_s32(low, high)),
            vreinterpretq_s8_s32(vzip2q_s32(low, high)),
        ]
    }
}

/// A tile's exact sums over the whole kernel (at most `MAX_BYTE_TERMS` products of 255 x
/// 128: inside i32), rounded and scaled: per pixel pair, its two pixels' `V` vectors.
///
/// # Safety
/// The CPU has I8MM; the slices have the lengths `shape` implies, rows of whole quads no
/// longer than [`ZERO_ROW`]; `pixels` are tiles of this output; the block's `4 V` channels
/// from `channel` are inside the output channels.
#[inline(always)]
unsafe fn tile_totals<I: MatrixInput, W: WeightLayout, const PAIRS: usize, const V: usize>(
    shape: &ConvShape,
    input: &I,
    weight: &[i8],
    pixels: &[PixelTile<2>; PAIRS],
    channel: usize,
) -> [[[<Lanes as Int8Lanes>::Floats; V]; 2]; PAIRS] {
    let row_stride = I::row_stride(shape);
    let quads = row_stride / QUAD;
    let quad_stride = int8_quad_stride(shape.out_channels, channel);
    let rows = input.rows();
    // SAFETY: NEON.
    let mut sums = [[[unsafe { vdupq_n_s32(0) }; 2]; V]; PAIRS];
    for kernel_y in 0..shape.kernel_height {
        for kernel_x in 0..shape.kernel_width {
            let taps = pixels.map(|pair| pair.rows(shape, kernel_y, kernel_x));
            if taps.iter().flatten().all(Option::is_none) {
                continue;
            }
            // Padding (and a pixel past the map's end) reads zeros, which add nothing.
            let sources = taps.map(|pair| {
                pair.map(|row| match row {
                    Some(row) => rows[row * row_stride..][..row_stride].as_ptr(),
                    None => ZERO_ROW.as_ptr().cast(),
                })
            });
            let tap = kernel_y * shape.kernel_width + kernel_x;
            let weights = weight[W::tap_start(shape, tap, channel)..].as_ptr();
            // SAFETY: every source is a row of `quads` whole quads or the zero row, at least
            // as long; the tap's quads of the block are inside `weight`: the caller's
            // promises.
            sums =
                unsafe { add_tap::<I, W, PAIRS, V>(sums, &sources, weights, quads, quad_stride) };
        }
    }
    // SAFETY: NEON.
    let mut totals = [[[unsafe { Lanes::zero_floats() }; V]; 2]; PAIRS];
    for (totals, sums) in totals.iter_mut().zip(&sums) {
        for (vector, [low, high]) in sums.iter().enumerate() {
            // SAFETY: NEON. Each block's rows are the pair's pixels: the first pixel's
            // four channels are the low halves of both blocks, the second's the high.
            unsafe {
                let (low, high) = (vreinterpretq_s64_s32(*low), vreinterpretq_s64_s32(*high));
                let first = vreinterpretq_s32_s64(vzip1q_s64(low, high));
                let second = vreinterpretq_s32_s64(vzip2q_s64(low, high));
                totals[0][vector] = Lanes::integers_scaled(first, input.scale());
                totals[1][vector] = Lanes::integers_scaled(second, input.scale());
            }
        }
    }
    totals
}

/// The convolution on tiles of `PAIRS` pixel pairs from `first` (fewer at the map's end)
/// by `V` vectors of channels from `channel`.
///
/// # Safety
/// As for [`tile_totals`]; `first` is inside the map.
#[inline(always)]
unsafe fn tile<I: MatrixInput, W: WeightLayout, const PAIRS: usize, const V: usize>(
    shape: &ConvShape,
    input: &I,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
    (first, channel): (usize, usize),
) {
    let positions = shape.out_height() * shape.out_width();
    let out_channels = shape.out_channels;
    let pixels: [PixelTile<2>; PAIRS] = core::array::from_fn(|pair| {
        let start = first + 2 * pair;
        PixelTile::new(shape, start, positions.saturating_sub(start).min(2))
    });
    // SAFETY: the caller's promises.
    let totals = unsafe { tile_totals::<I, W, PAIRS, V>(shape, input, weight, &pixels, channel) };
    let block = channel..channel + V * Lanes::WIDTH;
    let parameters = (&weight_scales[block.clone()], &bias[block]);
    for (pair, (pixels, totals)) in pixels.iter().zip(&totals).enumerate() {
        if pixels.count == 0 {
            break;
        }
        let out = &mut output[(first + 2 * pair) * out_channels + channel..];
        // SAFETY: NEON; the block's channels of the pair's pixels are inside `out`.
        unsafe {
            store::<Lanes, 2, V>(
                totals,
                pixels.count,
                parameters,
                out,
                out_channels,
                accumulate,
            )
        }
    }
}

/// The channel blocks of `V` vectors from `*channel` while they fit, each over every pixel
/// (tiles of `PAIRS` pairs, the last pixels on smaller ones where those waste less);
/// advances `*channel` past them.
///
/// # Safety
/// As for [`conv`].
#[inline(always)]
unsafe fn channel_blocks<I: MatrixInput, W: WeightLayout, const PAIRS: usize, const V: usize>(
    shape: &ConvShape,
    input: &I,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
    channel: &mut usize,
) {
    // The quad stride holds inside one 64-channel block of the layout: blocks from a
    // multiple of their width never straddle one.
    const { assert!(INT8_CHANNEL_BLOCK.is_multiple_of(V * Lanes::WIDTH)) };
    let positions = shape.out_height() * shape.out_width();
    while *channel + V * Lanes::WIDTH <= shape.out_channels {
        let mut first = 0;
        // SAFETY (all three): the caller's promises; `first` is inside the map.
        while positions.saturating_sub(first) > 4 * SMALL_PAIRS {
            unsafe {
                tile::<I, W, PAIRS, V>(
                    shape,
                    input,
                    parameters,
                    output,
                    accumulate,
                    (first, *channel),
                )
            };
            first += 2 * PAIRS;
        }
        while first < positions {
            unsafe {
                let at = (first, *channel);
                tile::<I, W, SMALL_PAIRS, V>(shape, input, parameters, output, accumulate, at)
            };
            first += 2 * SMALL_PAIRS;
        }
        *channel += V * Lanes::WIDTH;
    }
}

/// The whole convolution on the matrix tiles: blocks of `V` vectors of channels on tiles of
/// `PAIRS` pixel pairs, then single vectors, the channels left over (not a multiple of four)
/// on the scalar reference. The tiles read the weights in layout `W` (`layout`: the quads
/// of `parameters`, or their pairs), the scalar reference the quads.
///
/// # Safety
/// The CPU has I8MM; the slice lengths are those `shape` implies; rows of whole quads no
/// longer than [`ZERO_ROW`].
#[inline(always)]
unsafe fn conv<I: MatrixInput, W: WeightLayout, const PAIRS: usize, const V: usize>(
    shape: &ConvShape,
    input: &I,
    parameters: (&[i8], &[f32], &[f32]),
    layout: &[i8],
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let mut channel = 0;
    let tiles = (layout, parameters.1, parameters.2);
    // SAFETY: this function's contract is theirs.
    unsafe {
        channel_blocks::<I, W, PAIRS, V>(shape, input, tiles, output, accumulate, &mut channel);
        channel_blocks::<I, W, PAIRS, 1>(shape, input, tiles, output, accumulate, &mut channel);
    }
    if channel < shape.out_channels {
        let positions = shape.out_height() * shape.out_width();
        let channels = channel..shape.out_channels;
        conv_int8_pixels(
            shape,
            input,
            parameters,
            output,
            accumulate,
            0..positions,
            channels,
        );
    }
}

/// [`conv`] on the pair layout, functions of their own (their loops apart from the quads'
/// in the binary, where `benches/arm/mca.sh` finds them by name).
macro_rules! conv_on_pairs {
    ($name:ident, $input:ty) => {
        /// # Safety
        /// As for [`conv`], `pairs` the pair layout of `parameters`' weights.
        #[target_feature(enable = "neon,dotprod,i8mm")]
        #[inline(never)]
        unsafe fn $name(
            shape: &ConvShape,
            input: &$input,
            parameters: (&[i8], &[f32], &[f32]),
            pairs: &[i8],
            output: &mut [f32],
            accumulate: Accumulate,
        ) {
            // SAFETY: this function's contract is `conv`'s.
            unsafe {
                conv::<_, Pairs, { PAIRS_TILE.0 }, { PAIRS_TILE.1 }>(
                    shape, input, parameters, pairs, output, accumulate,
                )
            }
        }
    };
}
conv_on_pairs!(paired_conv_bytes, ByteRows<'_>);
conv_on_pairs!(paired_conv_signed_bytes, SignedByteRows<'_>);

/// `Kernels::conv_int8_bytes` on `usmmla`, the lengths checked; inputs not in whole quads on
/// the scalar reference. `pairs`: the weights' pair layout, read instead of pairing quads.
///
/// # Safety
/// The CPU has I8MM.
#[target_feature(enable = "neon,dotprod,i8mm")]
pub(crate) unsafe fn checked_conv_bytes(
    shape: &ConvShape,
    input: &ByteRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    pairs: Option<&[i8]>,
    output: &mut [f32],
    accumulate: Accumulate,
) {
    assert_byte_lengths(shape, input, parameters, output.len());
    if !shape.in_channels.is_multiple_of(QUAD) {
        return conv_int8_bytes(shape, input, parameters, output, accumulate);
    }
    // SAFETY: I8MM (this function's contract); the lengths were asserted (at most
    // `MAX_DIGIT_CHANNELS` inputs: rows no longer than the zero row), the pairs' below, and
    // the quads checked just above.
    unsafe {
        match pairs {
            Some(pairs) => {
                assert_eq!(pairs.len(), shape.int8_pair_weight_len());
                paired_conv_bytes(shape, input, parameters, pairs, output, accumulate)
            }
            None => {
                let quads = parameters.0;
                conv::<_, Quads, { QUADS_TILE.0 }, { QUADS_TILE.1 }>(
                    shape, input, parameters, quads, output, accumulate,
                )
            }
        }
    }
}

/// `Kernels::conv_int8_signed_bytes` on `smmla`, the lengths checked; `pairs` as for
/// [`checked_conv_bytes`].
///
/// # Safety
/// The CPU has I8MM.
#[target_feature(enable = "neon,dotprod,i8mm")]
pub(crate) unsafe fn checked_conv_signed_bytes(
    shape: &ConvShape,
    input: &SignedByteRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    pairs: Option<&[i8]>,
    output: &mut [f32],
    accumulate: Accumulate,
) {
    assert_signed_byte_lengths(shape, input, parameters, output.len());
    // SAFETY: I8MM (this function's contract); the lengths were asserted (at most
    // `MAX_DIGIT_CHANNELS` inputs, padded to whole quads: rows no longer than the zero row)
    // just above, the pairs' below.
    unsafe {
        match pairs {
            Some(pairs) => {
                assert_eq!(pairs.len(), shape.int8_pair_weight_len());
                paired_conv_signed_bytes(shape, input, parameters, pairs, output, accumulate)
            }
            None => {
                let quads = parameters.0;
                conv::<_, Quads, { QUADS_TILE.0 }, { QUADS_TILE.1 }>(
                    shape, input, parameters, quads, output, accumulate,
                )
            }
        }
    }
}
