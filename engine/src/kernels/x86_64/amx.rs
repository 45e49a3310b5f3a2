//! Intel AMX: the int8 convolutions on the tile matrix unit (`tdpbusd`, `tdpbssd`): the
//! trunk's on digit planes, the U-Net's on signed codes; every other kernel from [`Avx512`].
//!
//! One `tdpbusd` multiplies a 16 x 64 tile of u8 activations (16 output positions, 64
//! input channels) by a 16 x 64 tile of i8 weights (16 input-channel quads, 16 output
//! channels) into 16 x 16 exact i32 sums: 16,384 products where `vpdpbusd` does 64. A block
//! is 16 positions x 32 channels: the two activation tiles are the positions' high and low
//! digits, the two weight tiles 16 channels each, and the four sum tiles one per digit and
//! weight tile, all eight tile registers. The contract's sums are exact over the whole
//! kernel and the input has one scale, so the sum tiles run across taps and input channels
//! alike and are stored once per block, each pixel's `128 high + low` formed, rounded and
//! scaled then (same bits as the scalar reference, tested on every backend).
//!
//! On this project's machines a `tileloadd` whose rows are not 64-byte aligned, or that
//! a tile gathered through vector stores just before, costs several `tdpbusd`s, and the
//! unit cannot hide more than about one load per multiplication. So every tile is loaded
//! straight from aligned memory: the input is copied a band at a time into a stack buffer
//! with its zero padding and each pixel padded to whole 64-channel steps (`Band`), laid
//! out so that any 16 consecutive positions read 16 equally spaced pixels at every tap;
//! the weight tiles are read in place from the file's layout ([`int8_quad_index`]: 64-byte
//! rows of 16 channels).
//!
//! The U-Net's signed codes are split into digits as a band is copied: `high = code >> 7`
//! (-128..=127) takes the signed-by-signed `tdpbssd`, `low = code & 127` the same
//! `tdpbusd` as the trunk's, and `128 high + low` is the code, so the sums are the same
//! exact code sums. Its sequences are 4 to 16 positions, one or two tiles: the vector
//! kernels spent most of their time widening each weight for every 4 positions. Those of at
//! most 8 output positions, which hold nearly all its weights, go to `short_sequence`:
//! both digits in one tile, so a pass covers a whole 64-channel block of the layout.
//!
//! Linux hands out the tile registers on request only (`arch_prctl(ARCH_REQ_XCOMP_PERM)`);
//! without an OS (`target_os = "none"`) the firmware that set XCR0 has enabled them.

use core::arch::asm;
use core::arch::x86_64::{
    __m512i, _mm256_store_si256, _mm512_add_epi32, _mm512_add_ps, _mm512_and_si512,
    _mm512_cvtepi16_epi8, _mm512_cvtepi32_ps, _mm512_load_si512, _mm512_loadu_ps,
    _mm512_maskz_loadu_epi8, _mm512_maskz_loadu_epi16, _mm512_mul_ps, _mm512_set1_epi16,
    _mm512_set1_ps, _mm512_setzero_si512, _mm512_slli_epi32, _mm512_srai_epi16, _mm512_store_si512,
    _mm512_storeu_ps,
};
use core::mem::MaybeUninit;

mod short_sequence;

use super::avx512::Avx512;
use super::int8::{exact_digits_zmm, round_zmm};
#[cfg(doc)]
use crate::kernels::int8_quad_index;
use crate::kernels::ops::{Activation, DIGIT_BASE};
use crate::kernels::scalar::{assert_byte_lengths, assert_code_lengths, assert_int8_lengths};
use crate::kernels::{
    Accumulate, ByteRows, CodeRows, ConvShape, DigitRows, Kernels, MAX_DIGIT_CHANNELS,
    MAX_DIGIT_TERMS, QUAD, int8_quad_stride, int8_quads,
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
    /// whole input-channel quads (a last partial 64-channel step is zero-padded, for
    /// kernels of up to `MAX_PARTIAL_TAPS` taps), whole 32-channel blocks, and a band of
    /// at least one output pixel fits the stack buffer (other shapes go to [`Avx512`]).
    /// Every int8 layer of the model qualifies, the stem's 196-byte patches included.
    pub fn covers(shape: &ConvShape, input: &DigitRows<'_>) -> bool {
        short_sequence_takes(shape, input) || band(shape, input).is_some()
    }

    /// [`covers`](Self::covers) for [`Kernels::conv_int8_bytes`]: the stem's patches
    /// qualify.
    pub fn covers_bytes(shape: &ConvShape, input: &ByteRows<'_>) -> bool {
        band(shape, input).is_some()
    }

    /// The layout in which [`conv_int8_on_tiles`](Self::conv_int8_on_tiles) copies the
    /// input of `shape`, `None` when the tiles do not take it. Tests use it to know that
    /// both layouts ran.
    pub fn tile_layout(shape: &ConvShape, input: &DigitRows<'_>) -> Option<TileLayout> {
        band(shape, input).map(|band| band.layout)
    }

    /// [`covers`](Self::covers) for [`Kernels::conv_int8_codes`]: every U-Net convolution
    /// with int8 weights qualifies.
    pub fn covers_codes(shape: &ConvShape, input: &CodeRows<'_>) -> bool {
        short_sequence_takes(shape, input) || band(shape, input).is_some()
    }

    /// Whether [`covers_codes`](Self::covers_codes) takes `shape` as a short sequence: one
    /// output row of at most 8 positions, whole 64-channel steps in and blocks out, both
    /// digits in one tile and 64 channels a pass (the U-Net's sequences of 8 and 4).
    pub fn covers_short_sequence(shape: &ConvShape, input: &CodeRows<'_>) -> bool {
        short_sequence_takes(shape, input)
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
        let parameters = (weight, weight_scales, bias);
        self.on_tiles(shape, input, parameters, output, accumulate)
    }

    /// [`Kernels::conv_int8_bytes`] on the tiles, 32 positions' whole bytes a block;
    /// `false`, with nothing written, when they do not apply (output channels not in whole
    /// 32-channel blocks). Tests call it to know the tiles ran.
    ///
    /// # Panics
    /// If the shape is not pointwise or a slice is shorter than the contract makes it.
    pub fn conv_int8_bytes_on_tiles(
        &self,
        shape: &ConvShape,
        input: &ByteRows<'_>,
        parameters: (&[i8], &[f32], &[f32]),
        output: &mut [f32],
        accumulate: Accumulate,
    ) -> bool {
        let Some(band) = band(shape, input) else {
            return false;
        };
        input.assert_lengths(shape, parameters, output.len());
        // SAFETY: `self` exists only once AMX, AVX-512 and the permission were detected;
        // the lengths were asserted and the band planned just above.
        unsafe { conv(shape, input, parameters, output, accumulate, band) };
        true
    }

    /// [`Kernels::conv_int8_codes`] on the tiles; `false`, with nothing written, when they
    /// do not apply ([`Amx::covers_codes`]).
    #[allow(clippy::too_many_arguments)]
    pub fn conv_int8_codes_on_tiles(
        &self,
        shape: &ConvShape,
        input: &CodeRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) -> bool {
        let parameters = (weight, weight_scales, bias);
        self.on_tiles(shape, input, parameters, output, accumulate)
    }

    /// [`Kernels::conv_int8_pixels`] on the tiles, 8 pixels a pass (`short_sequence`'s
    /// kernel over pixels gathered per tap); `false`, with nothing written, when they do not
    /// apply: the input must be nonnegative, in whole 64-channel steps, the output whole
    /// 64-channel blocks. Tests call it to know the tiles ran.
    ///
    /// # Panics
    /// If a slice is shorter than the contract makes it or a pixel lies outside the output.
    pub fn conv_int8_pixels_on_tiles(
        &self,
        shape: &ConvShape,
        input: &DigitRows<'_>,
        parameters: (&[i8], &[f32], &[f32]),
        pixels: &[(usize, usize)],
        output: &mut [f32],
    ) -> bool {
        let channels = DigitRows::channels(shape);
        if !tiles_take(shape, input) || !short_sequence::applies_to_cells(shape, channels) {
            return false;
        }
        input.assert_lengths(shape, parameters, output.len());
        let (out_height, out_width) = (shape.out_height(), shape.out_width());
        for &(row, column) in pixels {
            assert!(
                row < out_height && column < out_width,
                "pixel outside the output"
            );
        }
        // SAFETY: `self` exists only once AMX, AVX-512 and the permission were detected; the
        // lengths and pixels were checked just above, the shape by `band` and
        // `applies_to_cells`.
        unsafe { short_sequence::conv_cells(shape, input, parameters, pixels, output) };
        true
    }

    /// Either convolution on the tiles, when they take it.
    fn on_tiles<I: BandInput>(
        &self,
        shape: &ConvShape,
        input: &I,
        parameters: Parameters<'_>,
        output: &mut [f32],
        accumulate: Accumulate,
    ) -> bool {
        // A short sequence needs no band plan: choosing one (both layouts costed) for each
        // of the U-Net's convolutions was work thrown away.
        if short_sequence_takes(shape, input) {
            input.assert_lengths(shape, parameters, output.len());
            // SAFETY: as below; `short_sequence_takes` was checked just above.
            unsafe { short_sequence::conv(shape, input, parameters, output, accumulate) };
            return true;
        }
        let Some(band) = band(shape, input) else {
            return false;
        };
        input.assert_lengths(shape, parameters, output.len());
        // SAFETY: `self` exists only once AMX, AVX-512 and the permission were detected;
        // the lengths were asserted and the band planned just above.
        unsafe { conv(shape, input, parameters, output, accumulate, band) };
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

/// One tile's worth of bytes, aligned for `tileloadd` / `tilestored` and ZMM moves. Not
/// initialized: written whole (by `tilestored`, or packed) before anything reads it, so a
/// call does not clear 26 KB of stack it will overwrite (the U-Net makes 33 calls a step).
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct TileBuffer([MaybeUninit<u8>; ROWS * ROW_BYTES]);

impl TileBuffer {
    const UNWRITTEN: TileBuffer = TileBuffer([MaybeUninit::uninit(); ROWS * ROW_BYTES]);

    fn as_ptr(&self) -> *const u8 {
        self.0.as_ptr().cast()
    }

    fn as_mut_ptr(&mut self) -> *mut u8 {
        self.0.as_mut_ptr().cast()
    }
}

/// Whether every tile kernel can take a convolution on `input`: digits the products
/// take, whole quads, exact sums, whole 32-channel blocks, and a partial last step packable.
fn tiles_take<I: BandInput>(shape: &ConvShape, input: &I) -> bool {
    let channels = I::channels(shape);
    let taps = shape.kernel_height * shape.kernel_width;
    let partial_fits = channels.is_multiple_of(CHANNELS_PER_STEP) || taps <= MAX_PARTIAL_TAPS;
    input.digits_fit()
        && channels.is_multiple_of(QUAD)
        && taps * channels <= MAX_DIGIT_TERMS
        && shape.out_channels.is_multiple_of(BLOCK_CHANNELS)
        && partial_fits
}

/// Whether the tiles take a convolution of two digit planes as a short sequence.
fn short_sequence_takes<I: BandInput>(shape: &ConvShape, input: &I) -> bool {
    I::PLANES == 2 && tiles_take(shape, input) && short_sequence::applies(shape, I::channels(shape))
}

/// The band plan of a convolution the tiles take, `None` for one they do not.
fn band<I: BandInput>(shape: &ConvShape, input: &I) -> Option<Band> {
    if tiles_take(shape, input) {
        Band::plan(shape, I::channels(shape), I::PLANES)
    } else {
        None
    }
}

/// Activations the tiles read as two digit planes, `code = 128 high + low`: the trunk's
/// [`DigitRows`] as they are, the U-Net's signed [`CodeRows`] split while a band is copied;
/// or as one plane of whole bytes, the stem's [`ByteRows`].
trait BandInput {
    /// The high digits can be negative (`tdpbssd`, signed by signed bytes); otherwise both
    /// digits are in 0..=127 (`tdpbusd`).
    const SIGNED_HIGH: bool;

    /// Planes a band holds: 2 (the high and low digits), or 1 (bytes, each multiplied
    /// whole by `tdpbusd`).
    const PLANES: usize;

    /// Channels a pixel of the input holds: the layer's input channels, in whole quads.
    fn channels(shape: &ConvShape) -> usize;

    /// Whether the digits take the products above (the trunk's must be nonnegative).
    fn digits_fit(&self) -> bool;

    fn scale(&self) -> f32;

    /// Panics unless the slices have the lengths the convolution's contract gives them.
    fn assert_lengths(&self, shape: &ConvShape, parameters: Parameters<'_>, output_len: usize);

    /// Copies the digits of `count` input pixels from pixel `first` into `high` and `low`,
    /// `pitch` bytes a pixel, zero past [`channels`](Self::channels).
    ///
    /// # Safety
    /// AVX-512F/BW; the pixels are inside the input; `high` and `low` are 64-byte aligned
    /// and writable for `count pitch` bytes; `pitch` is a multiple of 64, at least the
    /// channels.
    unsafe fn copy_digits(
        &self,
        shape: &ConvShape,
        pixels: (usize, usize),
        rows: (*mut u8, *mut u8),
        pitch: usize,
    );
}

impl BandInput for DigitRows<'_> {
    const SIGNED_HIGH: bool = false;
    const PLANES: usize = 2;

    fn channels(shape: &ConvShape) -> usize {
        shape.in_channels
    }

    fn digits_fit(&self) -> bool {
        self.nonnegative
    }

    fn scale(&self) -> f32 {
        self.scale
    }

    fn assert_lengths(&self, shape: &ConvShape, parameters: Parameters<'_>, output_len: usize) {
        assert_int8_lengths(shape, self, parameters, output_len)
    }

    #[inline(always)]
    unsafe fn copy_digits(
        &self,
        shape: &ConvShape,
        (first, count): (usize, usize),
        (high, low): (*mut u8, *mut u8),
        pitch: usize,
    ) {
        let channels = shape.in_channels;
        for (plane, to) in [(self.high, high), (self.low, low)] {
            let from = &plane[first * channels..][..count * channels];
            // SAFETY: the caller's promises.
            unsafe { copy_pixels(from, channels, to, pitch) };
        }
    }
}

impl BandInput for CodeRows<'_> {
    const SIGNED_HIGH: bool = true;
    const PLANES: usize = 2;

    fn channels(shape: &ConvShape) -> usize {
        CodeRows::row_stride(shape.in_channels)
    }

    fn digits_fit(&self) -> bool {
        true
    }

    fn scale(&self) -> f32 {
        self.scale
    }

    fn assert_lengths(&self, shape: &ConvShape, parameters: Parameters<'_>, output_len: usize) {
        assert_code_lengths(shape, self, parameters, output_len)
    }

    /// `high = code >> 7` (arithmetic: -128..=127 for codes in -16383..=16383) and
    /// `low = code & 127`, 32 codes at a time.
    #[inline(always)]
    unsafe fn copy_digits(
        &self,
        shape: &ConvShape,
        (first, count): (usize, usize),
        (high, low): (*mut u8, *mut u8),
        pitch: usize,
    ) {
        const CODES: usize = ROW_BYTES / 2;
        let channels = Self::channels(shape);
        let codes = &self.codes[first * channels..][..count * channels];
        for (pixel, row) in codes.chunks_exact(channels).enumerate() {
            for step in (0..pitch).step_by(CODES) {
                let width = channels.saturating_sub(step).min(CODES);
                // Masked codes are neither read nor able to fault; they load as zero.
                let mask = u32::MAX.checked_shr((CODES - width) as u32).unwrap_or(0);
                // SAFETY: AVX-512F/BW; the mask keeps the load inside the row; each store is
                // 32 bytes of the caller's rows, 32-byte aligned (64-byte rows, 32-code
                // steps).
                unsafe {
                    let values =
                        _mm512_maskz_loadu_epi16(mask, row.as_ptr().add(step.min(channels)));
                    let at = pixel * pitch + step;
                    let high_digits = _mm512_cvtepi16_epi8(_mm512_srai_epi16::<7>(values));
                    let low_digits =
                        _mm512_cvtepi16_epi8(_mm512_and_si512(values, _mm512_set1_epi16(127)));
                    _mm256_store_si256(high.add(at).cast(), high_digits);
                    _mm256_store_si256(low.add(at).cast(), low_digits);
                }
            }
        }
    }
}

impl BandInput for ByteRows<'_> {
    const SIGNED_HIGH: bool = false;
    const PLANES: usize = 1;

    fn channels(shape: &ConvShape) -> usize {
        shape.in_channels
    }

    fn digits_fit(&self) -> bool {
        true
    }

    fn scale(&self) -> f32 {
        self.scale
    }

    fn assert_lengths(&self, shape: &ConvShape, parameters: Parameters<'_>, output_len: usize) {
        assert_byte_lengths(shape, self, parameters, output_len)
    }

    /// The bytes as they are, into `high` (one plane: `low` is not written).
    #[inline(always)]
    unsafe fn copy_digits(
        &self,
        shape: &ConvShape,
        (first, count): (usize, usize),
        (high, _): (*mut u8, *mut u8),
        pitch: usize,
    ) {
        let channels = shape.in_channels;
        let from: &[i8] = bytemuck::cast_slice(&self.bytes[first * channels..][..count * channels]);
        // SAFETY: the caller's promises.
        unsafe { copy_pixels(from, channels, high, pitch) };
    }
}

/// `in_channels` rounded up to whole 64-channel steps: the bytes a pixel takes in a band
/// (the channels past `in_channels` zero).
const fn step_channels(in_channels: usize) -> usize {
    in_channels.next_multiple_of(CHANNELS_PER_STEP)
}

/// Bytes of the stack buffer a band of the input (both digit planes, padded) is copied
/// into: a whole panda layer4 input (10 x 12 padded pixels of 512 channels, 120 KB), so its
/// 2.4 MB of weights stream through once.
const BAND_BYTES: usize = 128 * 1024;

/// Kernel taps whose weights a partly filled last 64-channel step can have packed (with
/// zero rows past the last quad) for one block: the stem's patches have one, a 3x3 kernel
/// nine.
const MAX_PARTIAL_TAPS: usize = 9;

/// How a band's input is laid out for the tiles, which need the 16 positions of a tile to
/// read 16 equally spaced pixels at every kernel tap.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TileLayout {
    /// Each padded input row copied once; a band row is `grid` positions, the output's
    /// columns and the `kernel_width - 1` (or so) padding columns after them, computed and
    /// dropped. Cheap to copy; on small maps the dropped positions cost whole tiles (a 4 x 4
    /// map is 24 positions, two tiles for 16 pixels).
    Grid,
    /// One image per kernel column holding just the pixels that column reads for the
    /// band's outputs, so positions are the output pixels and nothing is dropped, for
    /// `kernel_width` times the copying.
    KernelColumns,
}

/// Where the tiles of one band read.
///
/// A band is `rows` x `columns` output pixels. Its input is copied, zero padding included,
/// into `phases x column_images` images per plane (two digit planes, or one of bytes).
/// Image `(r, c)` holds the padded input rows `band_top * stride + j * stride + r`; each of
/// its rows is `row_pixels()` pixels of `pitch` bytes (whole 64-channel steps). An output
/// pixel is a position `q = row * grid + column` of the band, and at kernel tap `(ky, kx)`
/// it reads pixel `step * q + (ky / stride) * row_pixels() + offset` of image
/// `(ky % stride, c)`:
/// - [`TileLayout::Grid`]: one column image, every padded column from the band's first
///   (`step = stride`, `c = 0`, `offset = kx`); the positions `column >= columns` are
///   computed and dropped;
/// - [`TileLayout::KernelColumns`]: image `c = kx` holds padded columns
///   `band_left * stride + kx + j * stride` (`step = 1`, `offset = 0`, `grid = columns`).
///
/// Either way 16 consecutive positions read 16 pixels `step * pitch` bytes apart, one
/// `tileloadd` whatever the padding and wherever a row of the map ends.
#[derive(Clone, Copy, Debug)]
struct Band {
    layout: TileLayout,
    rows: usize,
    columns: usize,
    stride: usize,
    /// Positions a band row holds.
    grid: usize,
    /// Pixels from one position to the next.
    step: usize,
    phases: usize,
    column_images: usize,
    /// Image rows copied: the band's rows and the kernel's reach below them.
    image_rows: usize,
    /// Pixels of each image: its rows and the slack the last tile of positions reads past
    /// them (zero).
    image_pixels: usize,
    pitch: usize,
    /// [`BandInput::PLANES`].
    planes: usize,
    /// Tiles of 16 positions one block of sums covers: 1 (both digits of 16 positions in
    /// the four sum tiles) or, for one plane of bytes, 2 (32 positions).
    tiles_per_block: usize,
    /// Tiles of 16 positions covering `rows * grid`, a whole number of blocks.
    tiles: usize,
}

impl Band {
    /// The band of `rows` x `columns` output pixels of a convolution whose input pixels
    /// hold `channels` values in `planes` planes.
    fn new(
        shape: &ConvShape,
        (channels, planes): (usize, usize),
        layout: TileLayout,
        (rows, columns): (usize, usize),
    ) -> Self {
        let stride = shape.stride;
        let (grid, step, column_images, reach) = match layout {
            TileLayout::Grid => {
                let grid = ((columns - 1) * stride + shape.kernel_width).div_ceil(stride);
                (grid, stride, 1, shape.kernel_width - 1)
            }
            TileLayout::KernelColumns => (columns, 1, shape.kernel_width, 0),
        };
        let below = (shape.kernel_height - 1) / stride;
        let tiles_per_block = if planes == 1 { 2 } else { 1 };
        let block_positions = tiles_per_block * BLOCK_PIXELS;
        let tiles = (rows * grid).div_ceil(block_positions) * tiles_per_block;
        let row_pixels = grid * step;
        let last_read = step * (tiles * BLOCK_PIXELS - 1) + below * row_pixels + reach;
        let image_rows = rows + below;
        Band {
            layout,
            rows,
            columns,
            stride,
            grid,
            step,
            phases: stride.min(shape.kernel_height),
            column_images,
            image_rows,
            image_pixels: (last_read + 1).max(image_rows * row_pixels),
            pitch: step_channels(channels),
            planes,
            tiles_per_block,
            tiles,
        }
    }

    const fn row_pixels(&self) -> usize {
        self.grid * self.step
    }

    const fn image_bytes(&self) -> usize {
        self.image_pixels * self.pitch
    }

    const fn images(&self) -> usize {
        self.phases * self.column_images
    }

    const fn bytes(&self) -> usize {
        self.planes * self.images() * self.image_bytes()
    }

    /// The image and the pixel in it that position 0 of the band reads at tap `(ky, kx)`.
    const fn tap_origin(&self, kernel_y: usize, kernel_x: usize) -> (usize, usize) {
        let (column_image, offset) = match self.layout {
            TileLayout::Grid => (0, kernel_x),
            TileLayout::KernelColumns => (kernel_x, 0),
        };
        let image = (kernel_y % self.stride) * self.column_images + column_image;
        (image, kernel_y / self.stride * self.row_pixels() + offset)
    }

    /// The band plan for `shape`: of the two layouts' plans, the one [`Band::cost`] rates
    /// cheaper; `None` when not even one output pixel fits.
    fn plan(shape: &ConvShape, channels: usize, planes: usize) -> Option<Band> {
        let channels = (channels, planes);
        let grid = Band::plan_in(shape, channels, TileLayout::Grid)?;
        Some(
            match Band::plan_in(shape, channels, TileLayout::KernelColumns) {
                Some(columns) if columns.cost(shape) < grid.cost(shape) => columns,
                _ => grid,
            },
        )
    }

    /// The largest band of whole output rows in `layout` that fits [`BAND_BYTES`] (spread
    /// evenly over the map), or of part of one row; `None` when not even one output pixel
    /// fits.
    fn plan_in(shape: &ConvShape, channels: (usize, usize), layout: TileLayout) -> Option<Band> {
        let (out_height, out_width) = (shape.out_height(), shape.out_width());
        let band = |rows, columns| Band::new(shape, channels, layout, (rows, columns));
        let fits = |rows, columns| band(rows, columns).bytes() <= BAND_BYTES;
        if out_height == 0 || out_width == 0 {
            return None;
        }
        if !fits(1, out_width) {
            let columns = (1..out_width).rev().find(|&columns| fits(1, columns))?;
            return Some(band(1, columns));
        }
        // The bytes grow with the rows: the most rows that fit, by bisection.
        let (mut fitting, mut too_many) = (1, out_height + 1);
        while too_many - fitting > 1 {
            let rows = (fitting + too_many) / 2;
            if fits(rows, out_width) {
                fitting = rows;
            } else {
                too_many = rows;
            }
        }
        let rows = out_height.div_ceil(out_height.div_ceil(fitting));
        Some(band(rows, out_width))
    }

    /// The bands covering the output with this plan, as [`conv`] walks them: each band's
    /// geometry and first output pixel.
    fn bands(self, shape: &ConvShape) -> impl Iterator<Item = (Band, (usize, usize))> {
        let (out_height, out_width) = (shape.out_height(), shape.out_width());
        // The pitch is the channels rounded up to whole steps: `Band::new` rounds it to itself.
        let channels = (self.pitch, self.planes);
        (0..out_height).step_by(self.rows).flat_map(move |top| {
            (0..out_width).step_by(self.columns).map(move |left| {
                let size = (
                    self.rows.min(out_height - top),
                    self.columns.min(out_width - left),
                );
                (Band::new(shape, channels, self.layout, size), (top, left))
            })
        })
    }

    /// A rough count of cycles for the whole convolution in this plan, to choose a layout:
    /// the products (a `tdpbusd` per digit, weight tile and 64-channel step, about 16
    /// cycles each), the copying of the bands and the weights streamed again for every
    /// band (about 8 bytes a cycle each, measured: the layouts' times on the model's
    /// layers order as this cost does).
    fn cost(self, shape: &ConvShape) -> usize {
        const PRODUCT_CYCLES: usize = 16;
        const BYTES_PER_CYCLE: usize = 8;
        let taps = shape.kernel_height * shape.kernel_width;
        let steps = taps * self.pitch / CHANNELS_PER_STEP;
        let blocks = shape.out_channels / BLOCK_CHANNELS;
        // Four products a step for each block: 16 positions' two digits, or 32 positions.
        let products_per_tile = blocks * steps * 4 / self.tiles_per_block;
        self.bands(shape)
            .map(|(band, _)| {
                band.tiles * products_per_tile * PRODUCT_CYCLES
                    + (band.bytes() + shape.int8_weight_len()) / BYTES_PER_CYCLE
            })
            .sum()
    }
}

/// The convolution's slices, as [`Kernels::conv_int8`] takes them.
type Parameters<'p> = (&'p [i8], &'p [f32], &'p [f32]);

/// The sum tiles of one block: the high digits' for channels 0-15 and 16-31 of the block,
/// then the low digits', as `tmm0`-`tmm3` hold them.
type BlockSums = [TileBuffer; 4];

/// A band of the input, as [`Band`] lays it out: the high plane's images, then the low's.
#[repr(C, align(64))]
struct BandBuffer([MaybeUninit<u8>; BAND_BYTES]);

/// The whole convolution on tiles, a band of output pixels at a time: the band's input is
/// copied into `band` with its padding, then every block of 32 output channels runs over
/// it, 16 positions at a time; the four sum tiles run across every tap and input channel
/// (the contract's sums are exact over the whole kernel) and are stored once per 16
/// positions. The weight tiles are read where the file keeps them (16 quads of 16 channels,
/// 64-byte rows [`int8_quad_stride`] apart), except a partly filled last step's, which are
/// packed with zero rows past the last quad.
///
/// # Safety
/// The CPU supports AVX-512F/BW, AMX-TILE and AMX-INT8 and this thread may use the tile
/// state; the slice lengths are those the input's `assert_lengths` checks; [`band`] planned
/// `plan` for this shape and input.
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn conv<I: BandInput>(
    shape: &ConvShape,
    input: &I,
    (weight, weight_scales, bias): Parameters<'_>,
    output: &mut [f32],
    accumulate: Accumulate,
    plan: Band,
) {
    let out_width = shape.out_width();
    let taps = shape.kernel_height * shape.kernel_width;
    let channels = I::channels(shape);
    // The i32 bound takes digits of at most 127 in magnitude; a byte's sums are whole
    // (`MAX_BYTE_CHANNELS`).
    let i32_exact = I::PLANES == 1 || (!I::SIGNED_HIGH && taps * channels <= MAX_DIGIT_CHANNELS);
    let partial = !channels.is_multiple_of(CHANNELS_PER_STEP);
    let mut band = BandBuffer([MaybeUninit::uninit(); BAND_BYTES]);
    let mut packed = [TileBuffer::UNWRITTEN; 2 * MAX_PARTIAL_TAPS];
    // Two sets: one block's sums are written out while the tiles compute the next.
    let mut sums = [[TileBuffer::UNWRITTEN; 4]; 2];
    let mut pending: Option<Pending> = None;
    let epilogue = Epilogue {
        i32_exact,
        scale: input.scale(),
        parameters: (weight_scales, bias),
        out_channels: shape.out_channels,
        out_width,
        accumulate,
    };
    // SAFETY: the caller vouches for AMX and the permission; the configuration is a valid
    // palette-1 layout (64 aligned bytes).
    unsafe { asm!("ldtilecfg [{}]", in(reg) TILE_CONFIG.0.as_ptr(), options(nostack)) };
    for (geometry, origin) in plan.bands(shape) {
        // SAFETY: AVX-512F; `geometry` is no larger than `plan`, which fits the buffer.
        unsafe { fill_band(shape, input, &geometry, origin, &mut band) };
        for channel in (0..shape.out_channels).step_by(BLOCK_CHANNELS) {
            if partial {
                // SAFETY: the block's channels and every tap are inside `weight`.
                unsafe { pack_partial_step(shape, channels, weight, channel, &mut packed) };
            }
            for tile in (0..geometry.tiles).step_by(geometry.tiles_per_block) {
                let first = tile * BLOCK_PIXELS;
                // SAFETY: the band holds every pixel the tile reads (`Band`); the block's
                // weights are inside `weight`.
                unsafe {
                    tile_sums::<I>(shape, &geometry, &band, (weight, channel), &packed, first)
                };
                // The previous block's sums go out while the matrix unit works.
                let set = match pending.take() {
                    Some(previous) => {
                        // SAFETY: AVX-512F; `previous` names pixels of the output.
                        unsafe { epilogue.write(&sums[previous.set], &previous, output) };
                        1 - previous.set
                    }
                    None => 0,
                };
                // SAFETY: tiles configured above.
                unsafe { store_sums(&mut sums[set]) };
                pending = Some(Pending {
                    set,
                    channel,
                    first,
                    band: geometry,
                    origin,
                });
            }
        }
    }
    if let Some(last) = pending {
        // SAFETY: AVX-512F; `last` names pixels of the output.
        unsafe { epilogue.write(&sums[last.set], &last, output) };
    }
    // SAFETY: as for `ldtilecfg`; releasing lets the OS skip saving 8 KB of tile data.
    unsafe { asm!("tilerelease", options(nostack, nomem)) };
}

/// Copies the input pixels band `geometry` at output pixel `(top, left)` reads into
/// `band`, both digit planes, zero where they lie in the padding, past the channels and in
/// the slack after each image.
///
/// # Safety
/// AVX-512F/BW; `geometry` fits [`BAND_BYTES`]; the input holds `shape`'s pixels.
#[inline(always)]
unsafe fn fill_band<I: BandInput>(
    shape: &ConvShape,
    input: &I,
    geometry: &Band,
    (top, left): (usize, usize),
    band: &mut BandBuffer,
) {
    let (in_height, in_width) = (shape.in_height, shape.in_width);
    let pitch = geometry.pitch;
    let row_pixels = geometry.row_pixels();
    let row_bytes = row_pixels * pitch;
    let base = band.0.as_mut_ptr().cast::<u8>();
    let low_images = geometry.images() * geometry.image_bytes();
    for phase in 0..geometry.phases {
        for column_image in 0..geometry.column_images {
            let image = phase * geometry.column_images + column_image;
            // Pixel `c` of an image row is padded column `left * stride + column_image +
            // c * column_step`, input column that minus the padding.
            let column_step = geometry.stride / geometry.step;
            let shift =
                (left * geometry.stride + column_image) as isize - shape.padding_width as isize;
            let inside = |column: isize| -> usize {
                let pixels = (column - shift).max(0) as usize;
                pixels.div_ceil(column_step).min(row_pixels)
            };
            let (first, end) = (inside(0), inside(in_width as isize));
            // SAFETY: the images lie inside the buffer (`geometry.bytes() <= BAND_BYTES`).
            let high = unsafe { base.add(image * geometry.image_bytes()) };
            // With one plane this lies past the band and is never written (nor read).
            let low = high.wrapping_add(low_images);
            for image_row in 0..geometry.image_rows {
                let padded_row = (top + image_row) * geometry.stride + phase;
                let in_row = padded_row as isize - shape.padding_height as isize;
                let at = image_row * row_bytes;
                // SAFETY: the row lies inside the image (and inside the low digits' image
                // when there is one).
                let to = unsafe { (high.add(at), low.wrapping_add(at)) };
                let planes = [to.0, to.1];
                let planes = &planes[..geometry.planes];
                if !(0..in_height as isize).contains(&in_row) || first == end {
                    for to in planes {
                        unsafe { to.write_bytes(0, row_bytes) };
                    }
                    continue;
                }
                let first_column = (shift + (first * column_step) as isize) as usize;
                let first_pixel = in_row as usize * in_width + first_column;
                // SAFETY: the row lies inside each image; the inside pixels are the input's.
                unsafe {
                    for to in planes {
                        to.write_bytes(0, first * pitch);
                        to.add(end * pitch)
                            .write_bytes(0, (row_pixels - end) * pitch);
                    }
                    let rows = (to.0.add(first * pitch), to.1.wrapping_add(first * pitch));
                    if column_step == 1 {
                        input.copy_digits(shape, (first_pixel, end - first), rows, pitch);
                    } else {
                        for pixel in 0..end - first {
                            let at = pixel * pitch;
                            let from = first_pixel + pixel * column_step;
                            let to = (rows.0.add(at), rows.1.wrapping_add(at));
                            input.copy_digits(shape, (from, 1), to, pitch);
                        }
                    }
                }
            }
            let copied = geometry.image_rows * row_bytes;
            for &image in &[high, low][..geometry.planes] {
                // SAFETY: the slack lies inside each image.
                unsafe {
                    image
                        .add(copied)
                        .write_bytes(0, geometry.image_bytes() - copied)
                };
            }
        }
    }
}

/// Copies pixels of `in_channels` bytes to `pitch` bytes apart at `to`, zero past
/// `in_channels`.
///
/// # Safety
/// AVX-512F/BW; `to` is 64-byte aligned and writable for `from.len() / in_channels * pitch`
/// bytes; `pitch` is a multiple of 64 and at least `in_channels`.
#[inline(always)]
unsafe fn copy_pixels(from: &[i8], in_channels: usize, to: *mut u8, pitch: usize) {
    // One pixel (the strided copies of `TileLayout::KernelColumns`) is a few vector moves,
    // cheaper inline than a call.
    if pitch == in_channels && from.len() > in_channels {
        // SAFETY: the caller's promise; `from` is a slice of as many bytes.
        unsafe { core::ptr::copy_nonoverlapping(from.as_ptr().cast(), to, from.len()) };
        return;
    }
    for (pixel, values) in from.chunks_exact(in_channels).enumerate() {
        for step in (0..pitch).step_by(ROW_BYTES) {
            let width = in_channels.saturating_sub(step).min(ROW_BYTES);
            // Masked bytes are neither read nor able to fault; they load as zero.
            let mask = u64::MAX
                .checked_shr((ROW_BYTES - width) as u32)
                .unwrap_or(0);
            // SAFETY: AVX-512F/BW; the mask keeps the load inside the pixel's values; the
            // store is 64 aligned bytes of the caller's buffer.
            unsafe {
                let bytes =
                    _mm512_maskz_loadu_epi8(mask, values.as_ptr().add(step.min(in_channels)));
                _mm512_store_si512(to.add(pixel * pitch + step).cast(), bytes);
            }
        }
    }
}

/// Packs the weight tiles of a partly filled last 64-channel step, for the 32 channels
/// from `channel` and every tap: two tiles a tap, rows past the last quad zero (read in
/// place they would run into the next tap's quads, or past the kernel's end).
///
/// # Safety
/// AVX-512F; the kernel has at most [`MAX_PARTIAL_TAPS`] taps and holds the block's channels.
#[inline(always)]
unsafe fn pack_partial_step(
    shape: &ConvShape,
    channels: usize,
    weight: &[i8],
    channel: usize,
    packed: &mut [TileBuffer; 2 * MAX_PARTIAL_TAPS],
) {
    let taps = shape.kernel_height * shape.kernel_width;
    let first_quad = channels / CHANNELS_PER_STEP * ROWS;
    let quads = channels / QUAD - first_quad;
    for tap in 0..taps {
        for (tile, buffer) in packed[2 * tap..2 * tap + 2].iter_mut().enumerate() {
            let channels = channel + tile * SUM_COLUMNS;
            for row in 0..ROWS {
                // SAFETY: the row is 64 bytes of the buffer; the quad's 16 channels are
                // inside `weight` (the caller's promise).
                unsafe {
                    let to = buffer.as_mut_ptr().add(row * ROW_BYTES);
                    if row < quads {
                        let from = shape.int8_index(tap, (first_quad + row) * QUAD, channels);
                        let from = weight[from..][..ROW_BYTES].as_ptr().cast();
                        core::ptr::copy_nonoverlapping(from, to, ROW_BYTES);
                    } else {
                        to.write_bytes(0, ROW_BYTES);
                    }
                }
            }
        }
    }
}

/// The exact sums of 16 positions from `first` of `geometry`'s band over every tap and
/// input channel, for the 32 channels from `channel`, into `tmm0`-`tmm3`.
///
/// # Safety
/// Tiles configured as [`TILE_CONFIG`] says; the band was filled for `geometry`; the block's
/// channels are inside `weight`; `packed` holds the partial step's tiles when there is one.
#[inline(always)]
unsafe fn tile_sums<I: BandInput>(
    shape: &ConvShape,
    geometry: &Band,
    band: &BandBuffer,
    (weight, channel): (&[i8], usize),
    packed: &[TileBuffer; 2 * MAX_PARTIAL_TAPS],
    first: usize,
) {
    let pitch = geometry.pitch;
    let row_step = geometry.step * pitch;
    // Whole quads: the weights' quads, zero-padded past the input channels.
    let quads = int8_quads(shape.in_channels);
    let full_steps = quads / ROWS;
    let quad_stride = int8_quad_stride(shape.out_channels, channel);
    let weights = weight[shape.int8_index(0, 0, channel)..]
        .as_ptr()
        .cast::<u8>();
    let band = band.0.as_ptr().cast::<u8>();
    let low_images = geometry.images() * geometry.image_bytes();
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
    for kernel_y in 0..shape.kernel_height {
        for kernel_x in 0..shape.kernel_width {
            let tap = kernel_y * shape.kernel_width + kernel_x;
            let (image, origin) = geometry.tap_origin(kernel_y, kernel_x);
            let pixel = geometry.step * first + origin;
            // SAFETY (all below): `Band` puts every pixel 16 positions read inside the
            // image, and the block's quads of every step inside `weight`.
            let high = unsafe { band.add(image * geometry.image_bytes() + pixel * pitch) };
            // One plane of bytes: the "low" tile is the next 16 positions.
            let low = match geometry.planes {
                1 => unsafe { high.add(BLOCK_PIXELS * row_step) },
                _ => unsafe { high.add(low_images) },
            };
            for step in 0..full_steps {
                let channels = step * CHANNELS_PER_STEP;
                let rows = unsafe { weights.add((tap * quads + step * ROWS) * quad_stride) };
                unsafe {
                    multiply_step(
                        (high.add(channels), low.add(channels), row_step),
                        (rows, quad_stride),
                        I::SIGNED_HIGH,
                    )
                };
            }
            if full_steps * ROWS < quads {
                let channels = full_steps * CHANNELS_PER_STEP;
                let (first, second) = (&packed[2 * tap], &packed[2 * tap + 1]);
                unsafe {
                    multiply_step_tiles(
                        (high.add(channels), low.add(channels), row_step),
                        (first.as_ptr(), second.as_ptr(), ROW_BYTES),
                        I::SIGNED_HIGH,
                    )
                };
            }
        }
    }
}

/// Stores `tmm0`-`tmm3` into `sums`.
///
/// # Safety
/// Tiles configured as [`TILE_CONFIG`] says.
#[inline(always)]
unsafe fn store_sums(sums: &mut BlockSums) {
    let [s0, s1, s2, s3] = sums;
    // SAFETY: each buffer is 16 rows of 64 bytes.
    unsafe {
        asm!(
            "tilestored [{s0} + {stride}], tmm0",
            "tilestored [{s1} + {stride}], tmm1",
            "tilestored [{s2} + {stride}], tmm2",
            "tilestored [{s3} + {stride}], tmm3",
            s0 = in(reg) s0.as_mut_ptr(),
            s1 = in(reg) s1.as_mut_ptr(),
            s2 = in(reg) s2.as_mut_ptr(),
            s3 = in(reg) s3.as_mut_ptr(),
            stride = in(reg) ROW_BYTES,
            options(nostack, preserves_flags)
        );
    }
}

/// One 64-channel step: the high and low digits of 16 positions (first rows, and their
/// row stride in bytes) times the step's weights for 32 channels (the first row of 16
/// quads x 16 channels, whose next 16 channels are 64 bytes on, and the quad row stride),
/// added to the four sum tiles.
///
/// # Safety
/// As for [`multiply_step_tiles`].
#[inline(always)]
unsafe fn multiply_step(
    (high, low, row_step): (*const u8, *const u8, usize),
    (weights, quad_stride): (*const u8, usize),
    signed_high: bool,
) {
    // SAFETY: the caller's promises.
    unsafe {
        multiply_step_tiles(
            (high, low, row_step),
            (weights, weights.add(SUM_COLUMNS * QUAD), quad_stride),
            signed_high,
        )
    }
}

/// One 64-channel step: both digit tiles (`high`, `low`, rows `row_step` bytes apart) times
/// two weight tiles (`first`, `second`, rows `weight_step` bytes apart), added to `tmm0`-`tmm3`.
///
/// # Safety
/// Tiles configured as [`TILE_CONFIG`] says; each pointer starts 16 readable rows of 64
/// bytes at its step, each row 64-byte aligned for speed.
#[inline(always)]
unsafe fn multiply_step_tiles(
    (high, low, row_step): (*const u8, *const u8, usize),
    (first, second, weight_step): (*const u8, *const u8, usize),
    signed_high: bool,
) {
    // Each activation tile is loaded just before its first product, so the unit can start
    // on the high digits while the low ones load; the high digits of signed codes take the
    // signed-by-signed product.
    macro_rules! step {
        ($high_product:literal) => {
            asm!(
                "tileloadd tmm4, [{high} + {row_step}]",
                "tileloadd tmm6, [{first} + {weight_step}]",
                concat!($high_product, " tmm0, tmm4, tmm6"),
                "tileloadd tmm7, [{second} + {weight_step}]",
                concat!($high_product, " tmm1, tmm4, tmm7"),
                "tileloadd tmm5, [{low} + {row_step}]",
                "tdpbusd tmm2, tmm5, tmm6",
                "tdpbusd tmm3, tmm5, tmm7",
                high = in(reg) high,
                low = in(reg) low,
                row_step = in(reg) row_step,
                first = in(reg) first,
                second = in(reg) second,
                weight_step = in(reg) weight_step,
                options(nostack, readonly, preserves_flags)
            )
        };
    }
    // SAFETY: the caller's promises.
    unsafe {
        if signed_high {
            step!("tdpbssd")
        } else {
            step!("tdpbusd")
        }
    }
}

/// A block's sums stored from the tiles, waiting to be written out.
#[derive(Clone, Copy)]
struct Pending {
    /// Which of the two sets of sum buffers holds them.
    set: usize,
    /// The block's first output channel.
    channel: usize,
    /// The band's position of the first sum row, the band and its first output pixel
    /// `(row, column)`.
    first: usize,
    band: Band,
    origin: (usize, usize),
}

/// What turns a block's exact sums into outputs.
struct Epilogue<'p> {
    i32_exact: bool,
    scale: f32,
    parameters: (&'p [f32], &'p [f32]),
    out_channels: usize,
    out_width: usize,
    accumulate: Accumulate,
}

impl Epilogue<'_> {
    /// `out (+)= round(128 high + low) * scale * weight_scales + bias` for each output
    /// pixel of `block`'s sum rows (the block's 32 channels), each a product then a sum as
    /// the scalar reference does. `128 high + low` is formed exactly in i32 when the kernel
    /// has at most [`MAX_DIGIT_CHANNELS`] products (`i32_exact`: one tap's bound,
    /// `|code| <= 16383`, `|q_w| <= 128`), else in f64; its conversion to f32 rounds to
    /// nearest either way.
    ///
    /// # Safety
    /// AVX-512F; the block's pixels and channels are inside `output` and the parameters.
    #[inline(always)]
    unsafe fn write(&self, sums: &BlockSums, block: &Pending, output: &mut [f32]) {
        let channel = block.channel;
        let band = &block.band;
        let (mut y, mut x) = (block.first / band.grid, block.first % band.grid);
        for row in 0..band.tiles_per_block * BLOCK_PIXELS {
            if y >= band.rows {
                break;
            }
            let inside = x < band.columns;
            let pixel = (block.origin.0 + y) * self.out_width + block.origin.1 + x;
            (y, x) = if x + 1 == band.grid {
                (y + 1, 0)
            } else {
                (y, x + 1)
            };
            if !inside {
                continue;
            }
            let out = &mut output[pixel * self.out_channels + channel..][..BLOCK_CHANNELS];
            let at = row % ROWS * ROW_BYTES;
            for (vector, out) in out.chunks_exact_mut(SUM_COLUMNS).enumerate() {
                // SAFETY: AVX-512F; each sum buffer row is 64 aligned bytes.
                unsafe {
                    let (high, low) = if band.planes == 1 {
                        // Whole sums, the second tile's positions in the last two.
                        let sum = &sums[row / ROWS * 2 + vector];
                        (
                            _mm512_setzero_si512(),
                            _mm512_load_si512(sum.as_ptr().add(at).cast()),
                        )
                    } else {
                        let high = _mm512_load_si512(sums[vector].as_ptr().add(at).cast());
                        let low = _mm512_load_si512(sums[2 + vector].as_ptr().add(at).cast());
                        (high, low)
                    };
                    self.write_group((high, low), channel + vector * SUM_COLUMNS, out);
                }
            }
        }
    }

    /// `out (+)= round(128 high + low) * scale * weight_scales + bias` for the 16 channels
    /// from `channel` of one output pixel: `high` and `low` its digits' exact sums.
    ///
    /// # Safety
    /// AVX-512F; the channels are inside the parameters; `out` holds 16 values.
    #[inline(always)]
    unsafe fn write_group(&self, (high, low): (__m512i, __m512i), channel: usize, out: &mut [f32]) {
        let out = &mut out[..SUM_COLUMNS];
        let weight_scales = &self.parameters.0[channel..][..SUM_COLUMNS];
        let bias = &self.parameters.1[channel..][..SUM_COLUMNS];
        // SAFETY: AVX-512F; 16 floats in each slice.
        unsafe {
            let rounded = if self.i32_exact {
                // The shift by 7 is the multiplication by the digit base.
                const { assert!(DIGIT_BASE == (1 << 7) as f32) };
                _mm512_cvtepi32_ps(_mm512_add_epi32(_mm512_slli_epi32::<7>(high), low))
            } else {
                round_zmm(exact_digits_zmm(high, low))
            };
            let total = _mm512_mul_ps(rounded, _mm512_set1_ps(self.scale));
            let scaled = _mm512_mul_ps(total, _mm512_loadu_ps(weight_scales.as_ptr()));
            let mut value = _mm512_add_ps(scaled, _mm512_loadu_ps(bias.as_ptr()));
            if self.accumulate == Accumulate::Add {
                value = _mm512_add_ps(_mm512_loadu_ps(out.as_ptr()), value);
            }
            _mm512_storeu_ps(out.as_mut_ptr(), value);
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
        let parameters = (weight, weight_scales, bias);
        if !self.conv_int8_pixels_on_tiles(shape, input, parameters, pixels, output) {
            crate::kernels::each_pixel(self.avx512, shape, input, parameters, pixels, output)
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
        if !self.conv_int8_bytes_on_tiles(shape, input, parameters, output, accumulate) {
            self.avx512.conv_int8_bytes(
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
        if !self.conv_int8_codes_on_tiles(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
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

    fn add_channel_moments(
        &self,
        data: &[f32],
        channels: usize,
        moments: (&mut [f64], &mut [f64]),
    ) {
        self.avx512.add_channel_moments(data, channels, moments)
    }

    fn normalize_max_pool(
        &self,
        input: &[f32],
        dims: (usize, usize, usize),
        affine: (&[f32], &[f32]),
        activation: Activation,
        output: &mut [f32],
    ) {
        self.avx512
            .normalize_max_pool(input, dims, affine, activation, output)
    }

    fn max_pool_3x3_stride_2(
        &self,
        input: &[f32],
        dims: (usize, usize, usize),
        output: &mut [f32],
    ) {
        self.avx512.max_pool_3x3_stride_2(input, dims, output)
    }
}
