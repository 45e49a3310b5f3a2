//! Convolutions whose output is one row of at most 8 positions: the U-Net's sequences of 8
//! and 4 and its downsampling to them, which hold nearly all of its weights.
//!
//! There the general kernel's tile of 16 positions is at most half used, and its blocks of
//! 32 channels read each 256-byte row of the layout's 64-channel blocks in two passes (the
//! first half of every row, then the second): measured with tiles alone streaming from L3,
//! 23.7 GB/s against 28.9 for one pass over whole rows. Here an activation tile holds the
//! high digits of the 8 positions in its first rows and their low digits in its last, so
//! one product gives both digits' sums and a pass covers 64 channels, four sum tiles, each
//! weight read once in address order. The input is laid out once per tap (an im2col of at
//! most 8 positions), so the tiles read it whatever the stride and padding.
//!
//! The same pass serves chosen pixels of a 2-D map, 8 at a time ([`conv_cells`]): the
//! projections evaluated on demand at the cells an inference step's anchors sample, which
//! ran one pixel at a time on the vector units.
//!
//! The low digits are 0..=127, the same value as signed or unsigned bytes, so the product
//! the high digits take (`tdpbssd` for the U-Net's signed codes) serves both, and the sums
//! are the general kernel's exact sums: the same bits.

use core::arch::asm;
use core::arch::x86_64::_mm512_load_si512;
use core::mem::MaybeUninit;

use super::band::{BAND_BYTES, BandBuffer, BandInput};
use super::tiles::{Epilogue, TileBuffer, store_sums};
use super::{CHANNELS_PER_STEP, Parameters, ROW_BYTES, ROWS, SUM_COLUMNS, TILE_CONFIG};
use crate::kernels::scalar::tap_input;
use crate::kernels::{
    Accumulate, ConvShape, INT8_CHANNEL_BLOCK, MAX_DIGIT_CHANNELS, int8_quad_stride,
};

/// Output positions an activation tile holds: its first rows are their high digits, the
/// rest their low digits.
const POSITIONS: usize = ROWS / 2;

/// Output channels of a pass: one block of the weight layout, four sum tiles.
const PASS_CHANNELS: usize = INT8_CHANNEL_BLOCK;
const PASS_TILES: usize = PASS_CHANNELS / SUM_COLUMNS;
const _: () = assert!(PASS_TILES == 4, "a pass keeps its sums in tmm0-tmm3");

/// The four sum tiles of a pass, 16 channels each: rows `0..POSITIONS` the high digits'
/// sums, rows `POSITIONS..` the low digits'.
type PassSums = [TileBuffer; PASS_TILES];

/// Whether `shape` is a short sequence this kernel takes: one output row of at most
/// [`POSITIONS`] positions, whole 64-channel steps in, whole layout blocks out, and every
/// tap's activation tiles fitting the stack buffer. The caller has checked what every tile
/// kernel needs ([`super::tiles_take`]).
pub(super) fn applies(shape: &ConvShape, channels: usize) -> bool {
    shape.in_height == 1
        && shape.kernel_height == 1
        && shape.padding_height + shape.padding_bottom == 0
        && shape.out_width() <= POSITIONS
        && applies_to_cells(shape, channels)
}

/// Whether [`conv_cells`] takes `shape`'s output pixels a few at a time: whole 64-channel
/// steps in, whole layout blocks out, every tap's activation tiles fitting the stack buffer.
/// The caller has checked what every tile kernel needs ([`super::tiles_take`]).
pub(super) fn applies_to_cells(shape: &ConvShape, channels: usize) -> bool {
    channels == shape.in_channels
        && channels.is_multiple_of(CHANNELS_PER_STEP)
        && shape.out_channels.is_multiple_of(PASS_CHANNELS)
        && shape.kernel_height * shape.kernel_width * ROWS * channels <= BAND_BYTES
}

/// The convolution, 64 output channels a pass: each tap's activation rows, laid out by
/// [`fill_taps`], times the block's weights read in place, the four sums across every tap
/// and input channel; a pass's sums are written out while the tiles compute the next.
///
/// # Safety
/// The CPU supports AVX-512F/BW, AMX-TILE and AMX-INT8 and this thread may use the tile
/// state; the slice lengths are those the input's `assert_lengths` checks; [`applies`]
/// holds and [`super::tiles_take`] accepts the shape.
#[target_feature(enable = "avx512f,avx512bw")]
pub(super) unsafe fn conv<I: BandInput>(
    shape: &ConvShape,
    input: &I,
    parameters: Parameters<'_>,
    output: &mut [f32],
    accumulate: Accumulate,
) {
    // The sequence's positions, as pixels of its one output row.
    let pixels: [(usize, usize); POSITIONS] = core::array::from_fn(|column| (0, column));
    let pixels = &pixels[..shape.out_width()];
    // SAFETY: the caller's promises.
    unsafe { conv_pixels(shape, input, parameters, pixels, output, accumulate) }
}

/// Output pixels `cells` of the convolution (overwritten), [`POSITIONS`] at a time; the
/// others are not touched.
///
/// # Safety
/// As for [`conv`], with [`applies_to_cells`] for [`applies`]; every cell is inside the
/// output.
#[target_feature(enable = "avx512f,avx512bw")]
pub(super) unsafe fn conv_cells<I: BandInput>(
    shape: &ConvShape,
    input: &I,
    parameters: Parameters<'_>,
    cells: &[(usize, usize)],
    output: &mut [f32],
) {
    for group in cells.chunks(POSITIONS) {
        // SAFETY: the caller's promises.
        unsafe {
            conv_pixels(
                shape,
                input,
                parameters,
                group,
                output,
                Accumulate::Overwrite,
            )
        }
    }
}

/// The output pixels `pixels` (`(row, column)`) of the convolution: [`fill_taps`], then a
/// pass per 64-channel block of the weights.
///
/// # Safety
/// As for [`conv`]; [`applies_to_cells`] holds; `pixels` has at most [`POSITIONS`] pixels,
/// each inside the output.
#[inline(always)]
unsafe fn conv_pixels<I: BandInput>(
    shape: &ConvShape,
    input: &I,
    (weight, weight_scales, bias): Parameters<'_>,
    pixels: &[(usize, usize)],
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let channels = shape.in_channels;
    let taps = shape.kernel_height * shape.kernel_width;
    let mut tap_rows = BandBuffer([MaybeUninit::uninit(); BAND_BYTES]);
    // SAFETY: AVX-512F/BW; `applies` bounds the taps' rows by the buffer.
    unsafe { fill_taps(shape, input, pixels, &mut tap_rows) };
    let epilogue = Epilogue {
        i32_exact: !I::SIGNED_HIGH && taps * channels <= MAX_DIGIT_CHANNELS,
        scale: input.scale(),
        parameters: (weight_scales, bias),
        out_channels: shape.out_channels,
        out_width: shape.out_width(),
        accumulate,
    };
    let mut sums = [[TileBuffer::UNWRITTEN; PASS_TILES]; 2];
    let mut pending: Option<(usize, usize)> = None;
    // SAFETY: the caller vouches for AMX and the permission; the configuration is a valid
    // palette-1 layout (64 aligned bytes).
    unsafe { asm!("ldtilecfg [{}]", in(reg) TILE_CONFIG.0.as_ptr(), options(nostack)) };
    for channel in (0..shape.out_channels).step_by(PASS_CHANNELS) {
        // SAFETY: tiles configured; the rows were filled; the block is inside `weight`.
        unsafe { pass_sums::<I>(shape, &tap_rows, weight, channel) };
        let set = match pending.take() {
            Some((set, previous)) => {
                // SAFETY: AVX-512F; the previous pass's channels are inside the output.
                unsafe { write_pass(&epilogue, &sums[set], pixels, previous, output) };
                1 - set
            }
            None => 0,
        };
        // SAFETY: tiles configured; each buffer is 16 rows of 64 bytes.
        unsafe { store_sums(&mut sums[set]) };
        pending = Some((set, channel));
    }
    if let Some((set, channel)) = pending {
        // SAFETY: as above.
        unsafe { write_pass(&epilogue, &sums[set], pixels, channel, output) };
    }
    // SAFETY: as for `ldtilecfg`; releasing lets the OS skip saving 8 KB of tile data.
    unsafe { asm!("tilerelease", options(nostack, nomem)) };
}

/// Lays the input out for the tiles: for every tap, [`ROWS`] rows of `in_channels` bytes,
/// row `p` the high digits and row `POSITIONS + p` the low digits of the input pixel
/// position `p` reads at that tap, zero where that is padding or past the positions.
///
/// # Safety
/// AVX-512F/BW; [`applies_to_cells`] holds; `pixels` has at most [`POSITIONS`] pixels.
#[inline(always)]
unsafe fn fill_taps<I: BandInput>(
    shape: &ConvShape,
    input: &I,
    pixels: &[(usize, usize)],
    buffer: &mut BandBuffer,
) {
    let pitch = shape.in_channels;
    let base = buffer.0.as_mut_ptr().cast::<u8>();
    for kernel_y in 0..shape.kernel_height {
        for kernel_x in 0..shape.kernel_width {
            let tap = kernel_y * shape.kernel_width + kernel_x;
            for position in 0..POSITIONS {
                // SAFETY: `applies_to_cells` keeps every tap's rows inside the buffer;
                // `pitch` is a multiple of 64, so each row is 64-byte aligned.
                let high = unsafe { base.add((tap * ROWS + position) * pitch) };
                let low = unsafe { high.add(POSITIONS * pitch) };
                let pixel = pixels
                    .get(position)
                    .and_then(|&pixel| tap_input(shape, pixel, (kernel_y, kernel_x)));
                // SAFETY: the pixel is inside the input; each row is `pitch` writable bytes.
                unsafe {
                    match pixel {
                        Some(pixel) => input.copy_digits(shape, (pixel, 1), (high, low), pitch),
                        None => {
                            high.write_bytes(0, pitch);
                            low.write_bytes(0, pitch);
                        }
                    }
                }
            }
        }
    }
}

/// The exact sums of every output position, for the 64 channels from `channel`, over every
/// tap and input channel, into `tmm0`-`tmm3`.
///
/// # Safety
/// Tiles configured as [`TILE_CONFIG`] says; `tap_rows` filled by [`fill_taps`]; the
/// block's channels are inside `weight`.
#[inline(always)]
unsafe fn pass_sums<I: BandInput>(
    shape: &ConvShape,
    tap_rows: &BandBuffer,
    weight: &[i8],
    channel: usize,
) {
    let pitch = shape.in_channels;
    let quad_stride = int8_quad_stride(shape.out_channels, channel);
    let rows = tap_rows.0.as_ptr().cast::<u8>();
    // SAFETY: tiles are configured (caller).
    unsafe {
        asm!(
            "tilezero tmm0",
            "tilezero tmm1",
            "tilezero tmm2",
            "tilezero tmm3",
            options(nostack, nomem)
        )
    };
    for tap in 0..shape.kernel_height * shape.kernel_width {
        for step in (0..pitch).step_by(CHANNELS_PER_STEP) {
            // SAFETY: the tap's rows hold `pitch` bytes from each row start; the step's 16
            // quads of the block's 64 channels are inside `weight` (the caller's promise).
            unsafe {
                let activations = rows.add(tap * ROWS * pitch + step);
                let weights = weight[shape.int8_index(tap, step, channel)..]
                    .as_ptr()
                    .cast::<u8>();
                multiply_step::<I>((activations, pitch), (weights, quad_stride));
            }
        }
    }
}

/// One 64-channel step: the activation tile (rows `row_step` bytes apart) times the four
/// weight tiles of the block's 16-channel groups (64 bytes apart, rows `quad_stride` bytes
/// apart), added to `tmm0`-`tmm3`. The weight tiles cycle through three registers; each is
/// loaded just before its product.
///
/// # Safety
/// Tiles configured as [`TILE_CONFIG`] says; `activations` starts 16 readable 64-byte rows
/// `row_step` apart, `weights` 16 readable 256-byte rows `quad_stride` apart; rows 64-byte
/// aligned for speed.
#[inline(always)]
unsafe fn multiply_step<I: BandInput>(
    (activations, row_step): (*const u8, usize),
    (weights, quad_stride): (*const u8, usize),
) {
    macro_rules! step {
        ($product:literal) => {
            asm!(
                "tileloadd tmm4, [{activations} + {row_step}]",
                "tileloadd tmm5, [{weights} + {quad_stride}]",
                concat!($product, " tmm0, tmm4, tmm5"),
                "tileloadd tmm6, [{weights} + {quad_stride} + 64]",
                concat!($product, " tmm1, tmm4, tmm6"),
                "tileloadd tmm7, [{weights} + {quad_stride} + 128]",
                concat!($product, " tmm2, tmm4, tmm7"),
                "tileloadd tmm5, [{weights} + {quad_stride} + 192]",
                concat!($product, " tmm3, tmm4, tmm5"),
                activations = in(reg) activations,
                row_step = in(reg) row_step,
                weights = in(reg) weights,
                quad_stride = in(reg) quad_stride,
                options(nostack, readonly, preserves_flags)
            )
        };
    }
    // SAFETY: the caller's promises.
    unsafe {
        if I::SIGNED_HIGH {
            step!("tdpbssd")
        } else {
            step!("tdpbusd")
        }
    }
}

/// Writes a pass's outputs: for each output position, each 16-channel group's high and low
/// digit sums (rows `p` and `POSITIONS + p` of its tile) through the epilogue, to its output
/// pixel.
///
/// # Safety
/// AVX-512F; the pass's channels are inside the output and the parameters; `sums` were
/// written by [`super::store_sums`].
#[inline(always)]
unsafe fn write_pass(
    epilogue: &Epilogue<'_>,
    sums: &PassSums,
    pixels: &[(usize, usize)],
    channel: usize,
    output: &mut [f32],
) {
    for (position, &(row, column)) in pixels.iter().enumerate() {
        let pixel = row * epilogue.out_width + column;
        for (group, tile) in sums.iter().enumerate() {
            let channel = channel + group * SUM_COLUMNS;
            // SAFETY: AVX-512F; both rows are 64 aligned bytes of the stored tile.
            unsafe {
                let high = _mm512_load_si512(tile.as_ptr().add(position * ROW_BYTES).cast());
                let low =
                    _mm512_load_si512(tile.as_ptr().add((POSITIONS + position) * ROW_BYTES).cast());
                let out = &mut output[pixel * epilogue.out_channels + channel..][..SUM_COLUMNS];
                epilogue.write_group((high, low), channel, out);
            }
        }
    }
}
