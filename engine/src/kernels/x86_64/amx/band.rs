//! The band: a stretch of the input copied to aligned stack memory with its zero padding,
//! each pixel padded to whole 64-channel steps, laid out so that any 16 consecutive output
//! positions read 16 equally spaced pixels at every tap ([`Band`], [`TileLayout`]); which
//! inputs the tiles take; and the copy itself ([`fill_band`]).

use core::arch::x86_64::{
    _mm256_store_si256, _mm512_and_si512, _mm512_cvtepi16_epi8, _mm512_maskz_loadu_epi8,
    _mm512_maskz_loadu_epi16, _mm512_set1_epi16, _mm512_srai_epi16, _mm512_store_si512,
};
use core::mem::MaybeUninit;

use super::tiles::TileBuffer;
use super::{
    BLOCK_CHANNELS, BLOCK_PIXELS, CHANNELS_PER_STEP, Parameters, ROW_BYTES, ROWS, SUM_COLUMNS,
    short_sequence,
};
use crate::kernels::scalar::{assert_byte_lengths, assert_code_lengths, assert_int8_lengths};
use crate::kernels::{
    ByteRows, CodeRows, ConvShape, DigitRows, MAX_BYTE_TERMS, MAX_DIGIT_TERMS, QUAD,
};

/// Whether every tile kernel can take a convolution on `input`: digits the products
/// take, whole quads, exact sums, whole 32-channel blocks, and a partial last step packable.
pub(super) fn tiles_take<I: BandInput>(shape: &ConvShape, input: &I) -> bool {
    let channels = I::channels(shape);
    let taps = shape.kernel_height * shape.kernel_width;
    let partial_fits = channels.is_multiple_of(CHANNELS_PER_STEP) || taps <= MAX_PARTIAL_TAPS;
    input.digits_fit()
        && channels.is_multiple_of(QUAD)
        && taps * channels <= I::MAX_TERMS
        && shape.out_channels.is_multiple_of(BLOCK_CHANNELS)
        && partial_fits
}

/// Whether the tiles take a convolution of two digit planes as a short sequence.
pub(super) fn short_sequence_takes<I: BandInput>(shape: &ConvShape, input: &I) -> bool {
    I::PLANES == 2 && tiles_take(shape, input) && short_sequence::applies(shape, I::channels(shape))
}

/// The band plan of a convolution the tiles take, `None` for one they do not.
pub(super) fn band<I: BandInput>(shape: &ConvShape, input: &I) -> Option<Band> {
    if tiles_take(shape, input) {
        Band::plan(shape, I::channels(shape), I::PLANES)
    } else {
        None
    }
}

/// Activations the tiles read as two digit planes, `code = 128 high + low`: the trunk's
/// [`DigitRows`] as they are, the U-Net's signed [`CodeRows`] split while a band is copied;
/// or as one plane of whole bytes, [`ByteRows`] (the stem's patches, the residual blocks'
/// narrow codes).
pub(super) trait BandInput {
    /// The high digits can be negative (`tdpbssd`, signed by signed bytes); otherwise both
    /// digits are in 0..=127 (`tdpbusd`).
    const SIGNED_HIGH: bool;

    /// Planes a band holds: 2 (the high and low digits), or 1 (bytes, each multiplied
    /// whole by `tdpbusd`).
    const PLANES: usize;

    /// Products (kernel taps x channels) up to which a plane's sums over a whole kernel fit
    /// i32: fewer for whole bytes (up to 255) than for digits.
    const MAX_TERMS: usize;

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
    const MAX_TERMS: usize = MAX_DIGIT_TERMS;

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
    const MAX_TERMS: usize = MAX_DIGIT_TERMS;

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
    const MAX_TERMS: usize = MAX_BYTE_TERMS;

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
pub(super) const BAND_BYTES: usize = 128 * 1024;

/// Kernel taps whose weights a partly filled last 64-channel step can have packed (with
/// zero rows past the last quad) for one block: the stem's patches have one, a 3x3 kernel
/// nine.
pub(super) const MAX_PARTIAL_TAPS: usize = 9;

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
pub(super) struct Band {
    pub(super) layout: TileLayout,
    pub(super) rows: usize,
    pub(super) columns: usize,
    stride: usize,
    /// Positions a band row holds.
    pub(super) grid: usize,
    /// Pixels from one position to the next.
    pub(super) step: usize,
    phases: usize,
    column_images: usize,
    /// Image rows copied: the band's rows and the kernel's reach below them.
    image_rows: usize,
    /// Pixels of each image: its rows and the slack the last tile of positions reads past
    /// them (zero).
    image_pixels: usize,
    pub(super) pitch: usize,
    /// [`BandInput::PLANES`].
    pub(super) planes: usize,
    /// Tiles of 16 positions one block of sums covers: 1 (both digits of 16 positions in
    /// the four sum tiles) or, for one plane of bytes, 2 (32 positions).
    pub(super) tiles_per_block: usize,
    /// Tiles of 16 positions covering `rows * grid`, a whole number of blocks.
    pub(super) tiles: usize,
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

    pub(super) const fn image_bytes(&self) -> usize {
        self.image_pixels * self.pitch
    }

    pub(super) const fn images(&self) -> usize {
        self.phases * self.column_images
    }

    const fn bytes(&self) -> usize {
        self.planes * self.images() * self.image_bytes()
    }

    /// The image and the pixel in it that position 0 of the band reads at tap `(ky, kx)`.
    pub(super) const fn tap_origin(&self, kernel_y: usize, kernel_x: usize) -> (usize, usize) {
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
    pub(super) fn bands(self, shape: &ConvShape) -> impl Iterator<Item = (Band, (usize, usize))> {
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

/// A band of the input, as [`Band`] lays it out: the high plane's images, then the low's.
#[repr(C, align(64))]
pub(super) struct BandBuffer(pub(super) [MaybeUninit<u8>; BAND_BYTES]);

/// Copies the input pixels band `geometry` at output pixel `(top, left)` reads into
/// `band`, both digit planes, zero where they lie in the padding, past the channels and in
/// the slack after each image.
///
/// # Safety
/// AVX-512F/BW; `geometry` fits [`BAND_BYTES`]; the input holds `shape`'s pixels.
#[inline(always)]
pub(super) unsafe fn fill_band<I: BandInput>(
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
pub(super) unsafe fn pack_partial_step(
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
