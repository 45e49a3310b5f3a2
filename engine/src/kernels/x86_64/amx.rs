//! Intel AMX: the int8 convolution of the trunk on the tile matrix unit (`tdpbusd`), every
//! other kernel from [`Avx512`].
//!
//! One `tdpbusd` multiplies a 16 x 64 tile of u8 activations (16 output pixels, 64 input
//! channels) by a 16 x 64 tile of i8 weights (16 input-channel quads, 16 output channels)
//! into 16 x 16 exact i32 sums: 16,384 products where `vpdpbusd` does 64. A block is 16
//! pixels x 32 channels: the two activation tiles are the pixels' high and low digits, the
//! two weight tiles 16 channels each, and the four sum tiles one per digit and weight tile,
//! all eight tile registers. The contract's sums are exact over the whole kernel and the
//! input has one scale, so the sum tiles run across taps and input channels alike: they
//! are stored once per block and run of taps, and each pixel's `128 high + low` formed,
//! rounded and scaled then (same bits as the scalar reference, tested on every backend).
//!
//! Channel blocks are the outer loop; inside one, a group of 128 pixels parks its exact
//! sums on the stack (32 KB) between runs of taps, and a run's weights for the block are
//! copied once into tile order ([`PackedRun`], at most 36 KB: every tap of layer1 and
//! layer2, two of layer4) for the group's eight blocks. The kernel uses about 72 KB of stack.
//!
//! An activation tile is loaded straight from the input when its 16 pixels read input rows
//! equally spaced (`tileloadd` takes a row stride: the inside of a map, stride 1 or 2);
//! otherwise (padding, a tile wrapping onto the next output row, the short last tile) its
//! rows are gathered into a scratch tile, zero where a pixel reads nothing (the padding's
//! zero codes). Input channels need only be whole quads: a last 64-channel step only
//! partly filled (the stem's 196-byte patches: 3 x 64 + 4) is gathered with masked loads,
//! zero past the last channel, against weight tiles whose rows past the last quad are
//! zero.
//!
//! Linux hands out the tile registers on request only (`arch_prctl(ARCH_REQ_XCOMP_PERM)`);
//! without an OS (`target_os = "none"`) the firmware that set XCR0 has enabled them.

use core::arch::asm;
use core::arch::x86_64::{
    _mm512_add_epi32, _mm512_add_ps, _mm512_cvtepi32_ps, _mm512_load_si512, _mm512_loadu_ps,
    _mm512_loadu_si512, _mm512_maskz_loadu_epi8, _mm512_mul_ps, _mm512_set1_ps,
    _mm512_setzero_si512, _mm512_slli_epi32, _mm512_store_si512, _mm512_storeu_ps,
};

use super::avx512::Avx512;
use super::int8::{PixelTile, exact_digits_zmm, round_zmm, tap_rows};
use crate::kernels::ops::{Activation, DIGIT_BASE};
use crate::kernels::scalar::assert_int8_lengths;
use crate::kernels::{
    Accumulate, CodeRows, ConvShape, DigitRows, Kernels, MAX_DIGIT_CHANNELS, QUAD, int8_quad_stride,
};

/// Rows of every tile: pixels of an activation tile, quads of a weight tile, pixels of a
/// sum tile.
const ROWS: usize = 16;
/// Bytes of every tile row: 64 activations, 16 weight quads, 16 i32 sums.
const ROW_BYTES: usize = 64;
/// Input channels one `tdpbusd` consumes.
const CHANNELS_PER_STEP: usize = ROW_BYTES;
/// Output channels of a sum tile.
const SUM_COLUMNS: usize = ROW_BYTES / 4;
/// Pixels and output channels of a block.
const BLOCK_PIXELS: usize = ROWS;
const BLOCK_CHANNELS: usize = 2 * SUM_COLUMNS;

/// AMX-TILE and AMX-INT8 kernels (and AVX-512, AVX2). Reachable only through
/// [`Amx::detect`], which checks the CPU, the OS and the permission.
#[derive(Debug)]
pub struct Amx {
    /// The kernels the methods this backend does not specialize use.
    avx512: &'static Avx512,
}

static INSTANCE: Amx = Amx {
    avx512: &super::avx512::INSTANCE,
};

impl Amx {
    /// Whether [`Kernels::conv_int8`] runs on the tiles here: activations readable as u8,
    /// whole input-channel quads up to [`MAX_IN_CHANNELS`] (a last partial 64-channel step
    /// is gathered, zero-padded), whole 32-channel blocks (other shapes go to [`Avx512`]).
    /// Every int8 layer of the model qualifies, the stem's 196-byte patches included.
    pub fn covers(shape: &ConvShape, input: &DigitRows<'_>) -> bool {
        input.nonnegative
            && shape.in_channels.is_multiple_of(QUAD)
            && step_channels(shape.in_channels) <= MAX_IN_CHANNELS
            && shape.out_channels.is_multiple_of(BLOCK_CHANNELS)
    }

    /// [`Kernels::conv_int8`] on the tiles; `false`, with nothing written, when they do not
    /// apply ([`Amx::covers`]). Tests call it to know the tiles ran.
    #[allow(clippy::too_many_arguments)]
    pub fn conv_int8_on_tiles(
        &self,
        shape: &ConvShape,
        input: &DigitRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) -> bool {
        if !Self::covers(shape, input) {
            return false;
        }
        let parameters = (weight, weight_scales, bias);
        assert_int8_lengths(shape, input, parameters, output.len());
        // SAFETY: `self` exists only once AMX, AVX-512 and the permission were detected;
        // the lengths were asserted and `covers` checked just above.
        unsafe { conv(shape, input, parameters, output, accumulate) };
        true
    }

    /// `None` unless the CPU supports AMX-TILE and AMX-INT8 as well as everything
    /// [`Avx512::detect`] asks for, the OS saves the tile state, and this process may use it.
    pub fn detect() -> Option<&'static Amx> {
        let avx512 = Avx512::detect().is_some();
        (avx512 && super::has_amx_int8() && tile_data_permitted()).then_some(&INSTANCE)
    }
}

#[cfg(target_os = "linux")]
fn tile_data_permitted() -> bool {
    use core::sync::atomic::{AtomicU8, Ordering};
    const UNKNOWN: u8 = 0;
    const GRANTED: u8 = 1;
    const REFUSED: u8 = 2;
    static PERMISSION: AtomicU8 = AtomicU8::new(UNKNOWN);
    match PERMISSION.load(Ordering::Relaxed) {
        GRANTED => true,
        REFUSED => false,
        _ => {
            // Asking twice (two threads racing here) is harmless: the kernel grants the
            // same permission again.
            let granted = request_tile_data();
            let state = if granted { GRANTED } else { REFUSED };
            PERMISSION.store(state, Ordering::Relaxed);
            granted
        }
    }
}

/// `arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`: until a process asks, Linux
/// traps its first tile instruction and kills it. A raw system call, as the engine links
/// no C library.
#[cfg(target_os = "linux")]
fn request_tile_data() -> bool {
    const SYS_ARCH_PRCTL: isize = 158;
    const ARCH_REQ_XCOMP_PERM: usize = 0x1023;
    const XFEATURE_XTILEDATA: usize = 18;
    let result: isize;
    // SAFETY: the system call only changes which register state this process may use; it
    // reads and writes no memory of ours, and `syscall` clobbers only rcx and r11 (declared).
    unsafe {
        asm!(
            "syscall",
            inlateout("rax") SYS_ARCH_PRCTL => result,
            in("rdi") ARCH_REQ_XCOMP_PERM,
            in("rsi") XFEATURE_XTILEDATA,
            lateout("rcx") _,
            lateout("r11") _,
            options(nostack),
        );
    }
    result == 0
}

/// No OS: XCR0, which [`super::has_amx_int8`] read, is the whole story.
#[cfg(target_os = "none")]
fn tile_data_permitted() -> bool {
    true
}

/// Another OS may trap tile instructions in ways this code does not know to ask about.
#[cfg(not(any(target_os = "linux", target_os = "none")))]
fn tile_data_permitted() -> bool {
    false
}

/// `ldtilecfg`'s operand: palette 1, all eight tiles 16 rows of 64 bytes.
#[repr(C, align(64))]
struct TileConfig([u8; 64]);

static TILE_CONFIG: TileConfig = {
    let mut bytes = [0u8; 64];
    bytes[0] = 1;
    let mut tile = 0;
    while tile < 8 {
        bytes[16 + 2 * tile] = ROW_BYTES as u8;
        bytes[48 + tile] = ROWS as u8;
        tile += 1;
    }
    TileConfig(bytes)
};

/// One tile's worth of bytes, aligned for `tileloadd` / `tilestored` and ZMM moves.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct TileBuffer([u8; ROWS * ROW_BYTES]);

/// Input channels an activation tile row can hold at most (the widest ResNet-18 layer).
const MAX_IN_CHANNELS: usize = 512;

/// `in_channels` rounded up to whole 64-channel steps: what a tap's packed weights cover
/// (the channels past `in_channels` with zero weights).
const fn step_channels(in_channels: usize) -> usize {
    in_channels.next_multiple_of(CHANNELS_PER_STEP)
}
/// Bytes of packed weights a run of taps takes at most: all nine taps of a 3x3 layer up to
/// 128 input channels (36 KB, ResNet-18's layer1 and layer2), two taps of the widest.
const RUN_BYTES: usize = 9 * 128 * BLOCK_CHANNELS;
const _: () = assert!(RUN_BYTES >= MAX_IN_CHANNELS * BLOCK_CHANNELS);
// A block's quads are `quad_stride` apart only inside one block of the weight layout.
const _: () = assert!(crate::kernels::INT8_CHANNEL_BLOCK.is_multiple_of(BLOCK_CHANNELS));
/// Blocks of pixels whose sums are parked on the stack between runs of taps: the weights
/// of a run are packed once for all of them.
const GROUP_BLOCKS: usize = 8;
const GROUP_PIXELS: usize = GROUP_BLOCKS * BLOCK_PIXELS;

/// The input rows a whole block of pixels on one output row (`origin`: where its first
/// pixel's tap (0, 0) lies) reads at a kernel tap, as a first row and a row step, when all
/// are inside the input: found in a few operations, where [`tap_rows`] takes one per pixel.
fn line_source(
    shape: &ConvShape,
    (top, left): (isize, isize),
    (kernel_y, kernel_x): (usize, usize),
) -> Option<(usize, usize)> {
    let in_y = top + kernel_y as isize;
    let first_x = left + kernel_x as isize;
    let last_x = first_x + ((BLOCK_PIXELS - 1) * shape.stride) as isize;
    let inside = (0..shape.in_height as isize).contains(&in_y)
        && first_x >= 0
        && last_x < shape.in_width as isize;
    inside.then(|| {
        (
            in_y as usize * shape.in_width + first_x as usize,
            shape.stride,
        )
    })
}

/// The 16 rows a direct source `(first row, row step)` reads, for a gathered tile.
fn line_rows(first: usize, step: usize) -> [Option<usize>; BLOCK_PIXELS] {
    let mut rows = [None; BLOCK_PIXELS];
    for (pixel, row) in rows.iter_mut().enumerate() {
        *row = Some(first + pixel * step);
    }
    rows
}

/// Where an activation tile comes from at one tap: straight from the input (first row and
/// row step, in input rows) when its 16 pixels read equally spaced rows, else gathered.
fn direct_source(rows: &[Option<usize>]) -> Option<(usize, usize)> {
    let first = rows[0]?;
    let second = rows[1]?;
    let step = second.checked_sub(first)?;
    rows.iter()
        .enumerate()
        .all(|(index, row)| *row == Some(first + index * step))
        .then_some((first, step))
}

/// A run of taps' weights for one block of 32 output channels, as the weight tiles read
/// them: per tap and 64-channel step, two tiles of 16 quads x 16 channels, each 1 KB
/// contiguous. Read in place, a weight tile's rows lie `4 out_channels` bytes apart, a
/// power of two that puts them in a few cache sets (two of L1's; too few of L2's to hold
/// layer4's block).
#[repr(C, align(64))]
struct PackedRun([u8; RUN_BYTES]);

/// The exact sums of one block: the high digits' for channels 0-15 and 16-31 of the block,
/// then the low digits', as the sum tiles `tmm0`-`tmm3` hold them.
type BlockSums = [TileBuffer; 4];

/// The whole convolution on tiles.
///
/// Per block of 16 pixels x 32 channels the sum tiles run over every tap and input channel
/// (the contract's sums are exact over the whole kernel), so they are stored once per run
/// of taps whose packed weights fit [`RUN_BYTES`] (once per block for most layers), not
/// once per tap.
///
/// # Safety
/// The CPU supports AVX-512F/BW, AMX-TILE and AMX-INT8 and this thread may use the tile
/// state; the slice lengths are those [`assert_int8_lengths`] checks; [`Amx::covers`] holds.
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn conv(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
    let positions = shape.out_height() * shape.out_width();
    let taps = shape.kernel_height * shape.kernel_width;
    let tap_bytes = step_channels(in_channels) * BLOCK_CHANNELS;
    let run_taps = (RUN_BYTES / tap_bytes).min(taps);
    let i32_exact = taps * in_channels <= MAX_DIGIT_CHANNELS;
    let mut packed = PackedRun([0; RUN_BYTES]);
    let mut gathered = [TileBuffer([0; ROWS * ROW_BYTES]); 2];
    let mut sums = [[TileBuffer([0; ROWS * ROW_BYTES]); 4]; GROUP_BLOCKS];
    // SAFETY: the caller vouches for AMX and the permission; the configuration is a valid
    // palette-1 layout (64 aligned bytes).
    unsafe { asm!("ldtilecfg [{}]", in(reg) TILE_CONFIG.0.as_ptr(), options(nostack)) };
    for channel in (0..out_channels).step_by(BLOCK_CHANNELS) {
        let single_run = run_taps == taps;
        // SAFETY (both): AVX-512F; the run's taps are inside the kernel and their quads of
        // the block's 32 channels inside `weight` (lengths asserted by the caller).
        if single_run {
            unsafe { pack_run(shape, weight, (channel, 0..taps), &mut packed) };
        }
        for group in (0..positions).step_by(GROUP_PIXELS) {
            let group_count = (positions - group).min(GROUP_PIXELS);
            // Worked out once per group, not once per tap (a division per pixel).
            let origins = PixelTile::<GROUP_PIXELS>::new(shape, group, group_count).origins;
            for first_tap in (0..taps).step_by(run_taps) {
                let run = first_tap..(first_tap + run_taps).min(taps);
                if !single_run {
                    unsafe { pack_run(shape, weight, (channel, run.clone()), &mut packed) };
                }
                for block in (0..group_count).step_by(BLOCK_PIXELS) {
                    let count = (group_count - block).min(BLOCK_PIXELS);
                    let sums = &mut sums[block / BLOCK_PIXELS];
                    // SAFETY: the caller's promises; the packed run holds `run`'s taps.
                    unsafe {
                        run_sums(
                            shape,
                            input,
                            &packed,
                            (&origins[block..], count),
                            (run.clone(), first_tap == 0),
                            &mut gathered,
                            sums,
                        )
                    };
                }
            }
            let parameters = (&weight_scales[channel..], &bias[channel..]);
            for block in (0..group_count).step_by(BLOCK_PIXELS) {
                let count = (group_count - block).min(BLOCK_PIXELS);
                let pixel = group + block;
                let out = &mut output[pixel * out_channels + channel..];
                // SAFETY: AVX-512F; the block's channels are inside the output and
                // parameters.
                unsafe {
                    store(
                        &sums[block / BLOCK_PIXELS],
                        (count, i32_exact),
                        input.scale,
                        parameters,
                        (out, out_channels),
                        accumulate,
                    )
                };
            }
        }
    }
    // SAFETY: as for `ldtilecfg`; releasing lets the OS skip saving 8 KB of tile data.
    unsafe { asm!("tilerelease", options(nostack, nomem)) };
}

/// Copies the quads of 32 channels from `channel` of the taps `run` into tile order in
/// `packed`, tap after tap.
///
/// # Safety
/// AVX-512F; the taps are inside the kernel and hold the block's channels; the run's
/// packed weights fit [`RUN_BYTES`].
#[inline(always)]
unsafe fn pack_run(
    shape: &ConvShape,
    weight: &[i8],
    (channel, run): (usize, core::ops::Range<usize>),
    packed: &mut PackedRun,
) {
    let tap_bytes = step_channels(shape.in_channels) * BLOCK_CHANNELS;
    let quad_stride = int8_quad_stride(shape.out_channels, channel);
    for (index, tap) in run.enumerate() {
        let first_quad = shape.int8_index(tap, 0, channel);
        let to = &mut packed.0[index * tap_bytes..][..tap_bytes];
        // SAFETY: the caller's promises.
        unsafe { pack_tap(shape, (&weight[first_quad..], quad_stride), to) };
    }
}

/// Copies one tap's quads of 32 channels (`weights` from quad 0 of the block's first
/// channel) into tile order in `packed` (`step_channels(in_channels) * 32` bytes), zero
/// quads past `in_channels`.
///
/// # Safety
/// AVX-512F; `weights` holds the tap's `in_channels / 4` quads of the block's channels,
/// `quad_stride` bytes apart.
#[inline(always)]
unsafe fn pack_tap(shape: &ConvShape, (weights, quad_stride): (&[i8], usize), packed: &mut [u8]) {
    let quads = shape.in_channels / QUAD;
    // A partial last step: its weight tiles' rows past the last quad stay zero.
    if !quads.is_multiple_of(ROWS) {
        packed.fill(0);
    }
    for quad in 0..quads {
        let (step, row) = (quad / ROWS, quad % ROWS);
        for tile in 0..2 {
            let from = quad * quad_stride + tile * SUM_COLUMNS * QUAD;
            let to = ((2 * step + tile) * ROWS + row) * ROW_BYTES;
            // SAFETY: the caller's promise for `from`; `to` is a 64-byte row of `packed`,
            // which holds `2 in_channels / 64` tiles, aligned as `PackedRun` is (every tap
            // starts at a multiple of 2 KB).
            unsafe {
                let bytes = _mm512_loadu_si512(weights[from..][..ROW_BYTES].as_ptr().cast());
                _mm512_store_si512(packed[to..][..ROW_BYTES].as_mut_ptr().cast(), bytes);
            }
        }
    }
}

/// Adds one run of taps to a block's exact sums (`sums`, tile order): starts them at zero
/// when `first`, else from what the previous run stored.
///
/// # Safety
/// As for [`conv`]; `packed` holds the run's taps; `origins` holds the block's `count`
/// pixels.
#[inline(always)]
unsafe fn run_sums(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    packed: &PackedRun,
    (origins, count): (&[(isize, isize)], usize),
    (run, first): (core::ops::Range<usize>, bool),
    gathered: &mut [TileBuffer; 2],
    sums: &mut BlockSums,
) {
    let in_channels = shape.in_channels;
    let planes = [input.high, input.low];
    let [s0, s1, s2, s3] = sums;
    let pointers = [s0, s1, s2, s3].map(|buffer| buffer.0.as_mut_ptr());
    // SAFETY: tiles are configured (caller); each buffer is 16 rows of 64 bytes.
    unsafe {
        if first {
            asm!(
                "tilezero tmm0",
                "tilezero tmm1",
                "tilezero tmm2",
                "tilezero tmm3",
                options(nostack, nomem)
            );
        } else {
            asm!(
                "tileloadd tmm0, [{s0} + {stride}]",
                "tileloadd tmm1, [{s1} + {stride}]",
                "tileloadd tmm2, [{s2} + {stride}]",
                "tileloadd tmm3, [{s3} + {stride}]",
                s0 = in(reg) pointers[0],
                s1 = in(reg) pointers[1],
                s2 = in(reg) pointers[2],
                s3 = in(reg) pointers[3],
                stride = in(reg) ROW_BYTES,
                options(nostack, readonly, preserves_flags)
            );
        }
    }
    let tap_bytes = step_channels(in_channels) * BLOCK_CHANNELS;
    // A whole block on one output row: most taps read a line of the input.
    let line = (count == BLOCK_PIXELS && origins[0].0 == origins[BLOCK_PIXELS - 1].0)
        .then_some(origins[0]);
    for (index, tap) in run.clone().enumerate() {
        let kernel = (tap / shape.kernel_width, tap % shape.kernel_width);
        let (direct, rows) = match line.and_then(|origin| line_source(shape, origin, kernel)) {
            Some(direct) => (Some(direct), [None; BLOCK_PIXELS]),
            None => {
                let rows = tap_rows(shape, origins, count, kernel);
                if rows.iter().all(Option::is_none) {
                    continue;
                }
                (direct_source(&rows), rows)
            }
        };
        for step in 0..in_channels / CHANNELS_PER_STEP {
            let first_channel = step * CHANNELS_PER_STEP;
            let mut sources = [(core::ptr::null::<i8>(), 0usize); 2];
            for (digit, plane) in planes.iter().enumerate() {
                sources[digit] = match direct {
                    Some((row, row_step)) => (
                        plane[row * in_channels + first_channel..].as_ptr(),
                        row_step * in_channels,
                    ),
                    None => {
                        let buffer = &mut gathered[digit];
                        // SAFETY: AVX-512F; each `Some` row holds `in_channels` values, so
                        // its 64 from `first_channel` are readable; the buffer holds 16
                        // rows of 64.
                        unsafe { gather(plane, in_channels, first_channel, &rows, buffer) };
                        (buffer.0.as_ptr().cast::<i8>(), ROW_BYTES)
                    }
                };
            }
            let weights = &packed.0[index * tap_bytes + 2 * step * ROWS * ROW_BYTES..];
            // SAFETY: the activation sources cover 16 rows of 64 bytes at their strides
            // (direct rows are input rows; the gathered buffers are 16 x 64); the step's two
            // weight tiles are 2 KB of `packed`.
            unsafe { multiply_step(sources, weights[..2 * ROWS * ROW_BYTES].as_ptr()) };
        }
        // A last step only partly filled (the stem's patches: 196 = 3 x 64 + 4): its rows
        // are gathered, zero past the last channel, direct or not.
        let width = in_channels % CHANNELS_PER_STEP;
        if width != 0 {
            let first_channel = in_channels - width;
            let direct_rows;
            let rows = match direct {
                Some((row, row_step)) => {
                    direct_rows = line_rows(row, row_step);
                    &direct_rows
                }
                None => &rows,
            };
            let mut sources = [(core::ptr::null::<i8>(), 0usize); 2];
            for (digit, plane) in planes.iter().enumerate() {
                let buffer = &mut gathered[digit];
                let channels = (in_channels, first_channel, width);
                // SAFETY: AVX-512F/BW (`Amx::detect`); each `Some` row holds `in_channels`
                // values (a direct source's 16 rows are inside the input), so the step's
                // `width` from `first_channel` are readable; the buffer holds 16 rows of 64.
                unsafe { gather_partial(plane, channels, rows, buffer) };
                sources[digit] = (buffer.0.as_ptr().cast::<i8>(), ROW_BYTES);
            }
            let step = in_channels / CHANNELS_PER_STEP;
            let weights = &packed.0[index * tap_bytes + 2 * step * ROWS * ROW_BYTES..];
            // SAFETY: the gathered buffers are 16 x 64; the step's two weight tiles are 2 KB
            // of `packed` (a tap's packed weights cover `step_channels(in_channels)`).
            unsafe { multiply_step(sources, weights[..2 * ROWS * ROW_BYTES].as_ptr()) };
        }
    }
    // SAFETY: each buffer is 16 rows of 64 bytes.
    unsafe {
        asm!(
            "tilestored [{s0} + {stride}], tmm0",
            "tilestored [{s1} + {stride}], tmm1",
            "tilestored [{s2} + {stride}], tmm2",
            "tilestored [{s3} + {stride}], tmm3",
            s0 = in(reg) pointers[0],
            s1 = in(reg) pointers[1],
            s2 = in(reg) pointers[2],
            s3 = in(reg) pointers[3],
            stride = in(reg) ROW_BYTES,
            options(nostack, preserves_flags)
        );
    }
}

/// One 64-channel step of a block: both digit planes' activation tiles (`sources`: first
/// row and row stride in bytes) times the step's two weight tiles (`weights`, 2 KB), added
/// to the four sum tiles.
///
/// # Safety
/// Tiles configured as [`TILE_CONFIG`] says, the sums in `tmm0`-`tmm3`; each source covers
/// 16 rows of 64 bytes at its stride; `weights` covers 2 KB.
#[inline(always)]
unsafe fn multiply_step(sources: [(*const i8, usize); 2], weights: *const u8) {
    // SAFETY: the caller's promises.
    unsafe {
        asm!(
            "tileloadd tmm4, [{high} + {high_stride}]",
            "tileloadd tmm5, [{low} + {low_stride}]",
            "tileloadd tmm6, [{b0} + {sb}]",
            "tileloadd tmm7, [{b1} + {sb}]",
            "tdpbusd tmm0, tmm4, tmm6",
            "tdpbusd tmm1, tmm4, tmm7",
            "tdpbusd tmm2, tmm5, tmm6",
            "tdpbusd tmm3, tmm5, tmm7",
            high = in(reg) sources[0].0,
            high_stride = in(reg) sources[0].1,
            low = in(reg) sources[1].0,
            low_stride = in(reg) sources[1].1,
            b0 = in(reg) weights,
            b1 = in(reg) weights.add(ROWS * ROW_BYTES),
            sb = in(reg) ROW_BYTES,
            options(nostack, readonly, preserves_flags)
        );
    }
}

/// Copies 64 activations from `step` of each pixel's row into `buffer`, zeros where the
/// pixel reads nothing (the padding: zero codes, as the contract reads it).
///
/// # Safety
/// AVX-512F; each `Some` row has `in_channels` values in `values`, `step + 64` of them.
#[inline(always)]
unsafe fn gather(
    values: &[i8],
    in_channels: usize,
    step: usize,
    rows: &[Option<usize>],
    buffer: &mut TileBuffer,
) {
    for (pixel, row) in rows.iter().enumerate() {
        // SAFETY: the caller's promise for the row; the buffer row is 64 aligned bytes.
        unsafe {
            let bytes = match row {
                Some(row) => _mm512_loadu_si512(values[row * in_channels + step..].as_ptr().cast()),
                None => _mm512_setzero_si512(),
            };
            _mm512_store_si512(buffer.0[pixel * ROW_BYTES..].as_mut_ptr().cast(), bytes);
        }
    }
}

/// [`gather`] for a last step of `width` (< 64) channels: the rest of each buffer row zero.
///
/// # Safety
/// AVX-512F/BW; each `Some` row has `in_channels` values in `values`, `step + width` of
/// them.
#[inline(always)]
unsafe fn gather_partial(
    values: &[i8],
    (in_channels, step, width): (usize, usize, usize),
    rows: &[Option<usize>],
    buffer: &mut TileBuffer,
) {
    // Masked bytes are neither read nor able to fault.
    let mask = u64::MAX >> (ROW_BYTES - width);
    for (pixel, row) in rows.iter().enumerate() {
        // SAFETY: the caller's promise for the row; the buffer row is 64 aligned bytes.
        unsafe {
            let bytes = match row {
                Some(row) => {
                    let from = &values[row * in_channels + step..][..width];
                    _mm512_maskz_loadu_epi8(mask, from.as_ptr())
                }
                None => _mm512_setzero_si512(),
            };
            _mm512_store_si512(buffer.0[pixel * ROW_BYTES..].as_mut_ptr().cast(), bytes);
        }
    }
}

/// `out (+)= round(128 high + low) * scale * weight_scales + bias` for the block's `count`
/// pixels, `stride` apart in `out`, each a product then a sum as the scalar reference does.
/// `128 high + low` is formed exactly in i32 when the kernel has at most
/// [`MAX_DIGIT_CHANNELS`] products (`i32_exact`: one tap's bound, `|code| <= 16383`,
/// `|q_w| <= 128`), else in f64; its conversion to f32 rounds to nearest either way.
///
/// # Safety
/// AVX-512F; `weight_scales` and `bias` hold the block's 32 channels; `out` holds them for
/// each of the `count` pixels.
#[inline(always)]
unsafe fn store(
    sums: &BlockSums,
    (count, i32_exact): (usize, bool),
    scale: f32,
    (weight_scales, bias): (&[f32], &[f32]),
    (out, stride): (&mut [f32], usize),
    accumulate: Accumulate,
) {
    let (weight_scales, bias) = (&weight_scales[..BLOCK_CHANNELS], &bias[..BLOCK_CHANNELS]);
    for pixel in 0..count {
        let out = &mut out[pixel * stride..][..BLOCK_CHANNELS];
        let at = pixel * ROW_BYTES;
        for vector in 0..2 {
            let channels = vector * SUM_COLUMNS;
            // SAFETY: AVX-512F; each sum buffer row is 64 aligned bytes; 16 floats from
            // `channels` in each slice.
            unsafe {
                let high = _mm512_load_si512(sums[vector].0[at..].as_ptr().cast());
                let low = _mm512_load_si512(sums[2 + vector].0[at..].as_ptr().cast());
                let rounded = if i32_exact {
                    // The shift by 7 is the multiplication by the digit base.
                    const { assert!(DIGIT_BASE == (1 << 7) as f32) };
                    _mm512_cvtepi32_ps(_mm512_add_epi32(_mm512_slli_epi32::<7>(high), low))
                } else {
                    round_zmm(exact_digits_zmm(high, low))
                };
                let total = _mm512_mul_ps(rounded, _mm512_set1_ps(scale));
                let weight_scale = _mm512_loadu_ps(weight_scales[channels..].as_ptr());
                let scaled = _mm512_mul_ps(total, weight_scale);
                let mut value = _mm512_add_ps(scaled, _mm512_loadu_ps(bias[channels..].as_ptr()));
                if accumulate == Accumulate::Add {
                    value = _mm512_add_ps(_mm512_loadu_ps(out[channels..].as_ptr()), value);
                }
                _mm512_storeu_ps(out[channels..].as_mut_ptr(), value);
            }
        }
    }
}

impl Kernels for Amx {
    fn name(&self) -> &'static str {
        "amx"
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
        self.avx512
            .conv(shape, input, weight, bias, output, accumulate)
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
        self.avx512
            .conv_pixel(shape, input, weight, bias, pixel, output)
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
        // One pixel is one row of a tile: the VNNI path is as fast, with the same bits.
        self.avx512
            .conv_int8_pixel(shape, input, weight, weight_scales, bias, pixel, output)
    }

    fn upsample_conv(
        &self,
        length: usize,
        in_channels: usize,
        out_channels: usize,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        output: &mut [f32],
    ) {
        self.avx512.upsample_conv(
            length,
            in_channels,
            out_channels,
            input,
            weight,
            bias,
            output,
        )
    }

    fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
        self.avx512.matvec(weight, input, base, output)
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
        if !self.conv_int8_on_tiles(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        ) {
            self.avx512.conv_int8(
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
        self.avx512.conv_int8_codes(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        )
    }

    fn matvec_int8_codes(
        &self,
        weight: &[i8],
        row_scales: &[f32],
        input: &CodeRows<'_>,
        base: &[f32],
        output: &mut [f32],
    ) {
        self.avx512
            .matvec_int8_codes(weight, row_scales, input, base, output)
    }

    fn quantize_digits(&self, input: &[f32], digits: (&mut [i8], &mut [i8])) -> (f32, bool) {
        self.avx512.quantize_digits(input, digits)
    }

    fn quantize_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
        self.avx512.quantize_codes(input, row_len, codes)
    }

    fn group_norm(
        &self,
        data: &mut [f32],
        channels: usize,
        groups: usize,
        affine: (&[f32], &[f32]),
        activation: Activation,
    ) {
        self.avx512
            .group_norm(data, channels, groups, affine, activation)
    }

    fn add_activate(&self, target: &mut [f32], source: &[f32], activation: Activation) {
        self.avx512.add_activate(target, source, activation)
    }
}
