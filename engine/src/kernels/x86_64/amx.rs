//! Intel AMX: the int8 convolutions on the tile matrix unit (`tdpbusd`, `tdpbssd`): the
//! trunk's on digit planes (15-bit codes) or whole bytes (8-bit codes, the stem's patches),
//! the U-Net's on 15-bit signed codes; every other kernel from [`Avx512`].
//!
//! One `tdpbusd` multiplies a 16 x 64 tile of u8 activations (16 output positions, 64
//! input channels) by a 16 x 64 tile of i8 weights (16 input-channel quads, 16 output
//! channels) into 16 x 16 exact i32 sums: 16,384 products where `vpdpbusd` does 64. A block
//! is 16 positions x 32 channels: the two activation tiles are the positions' high and low
//! digits, the two weight tiles 16 channels each, and the four sum tiles one per digit and
//! weight tile, all eight tile registers. The contract's sums are exact over the whole
//! kernel and the input has one scale, so the sum tiles run across taps and input channels
//! alike and are stored once per block, each pixel's `128 high + low` formed, rounded and
//! scaled then (same bits as the scalar reference, tested on every backend). A plane of
//! whole bytes is one activation tile per 16 positions, so a block is 32 positions: the
//! same four loads for four products, each product a whole byte instead of a digit.
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
//! both digits in one tile, so a pass covers a whole 64-channel block of the layout. Its
//! 8-bit signed codes run VNNI's kernel: the loop is as long as its weights take to stream
//! from L3 whichever unit multiplies them.
//!
//! Linux hands out the tile registers on request only (`arch_prctl(ARCH_REQ_XCOMP_PERM)`);
//! without an OS (`target_os = "none"`) the firmware that set XCR0 has enabled them.

mod band;
mod permission;
mod short_sequence;
mod tiles;

use super::avx512::Avx512;
#[cfg(doc)]
use crate::kernels::int8_quad_index;
use crate::kernels::ops::Activation;
use crate::kernels::{
    Accumulate, ByteRows, CodeRows, ConvShape, DigitRows, Kernels, NarrowForm, SignedByteRows,
};
pub use band::TileLayout;
use band::{BandInput, band, short_sequence_takes, tiles_take};
use permission::tile_data_permitted;
use tiles::conv;

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

    /// [`covers`](Self::covers) for [`Kernels::conv_int8_bytes`]: the stem's patches and
    /// every residual-block layer qualify.
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

    /// [`Kernels::conv_int8_bytes`] on the tiles, 32 positions' whole bytes a block (the
    /// stem's patches, the residual blocks' narrow codes); `false`, with nothing written,
    /// when they do not apply ([`Amx::covers_bytes`]). Tests call it to know the tiles ran.
    ///
    /// # Panics
    /// If a slice is shorter than the contract makes it.
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

/// The convolution's slices, as [`Kernels::conv_int8`] takes them.
type Parameters<'p> = (&'p [i8], &'p [f32], &'p [f32]);

impl Kernels for Amx {
    fn name(&self) -> &'static str {
        "amx"
    }

    fn int8_pixel_block(&self) -> usize {
        BLOCK_PIXELS
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

    fn conv_channels(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        channels: core::ops::Range<usize>,
        output: &mut [f32],
        accumulate: Accumulate,
    ) -> bool {
        self.avx512
            .conv_channels(shape, input, weight, bias, channels, output, accumulate)
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

    /// VNNI's whole-byte tile. On the tiles (each code split into the digits of the same
    /// code widened, the short-sequence kernel) these layers were faster alone but not in
    /// the loop, which streams them from L3: door-open's 8-bit layers took 25.2 GB/s of
    /// weights there against VNNI's 27.2-27.4 (`benches/README.md`, "Lessons: tried and not
    /// kept").
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
        self.avx512.conv_int8_signed_bytes(
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

    fn quantize_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
        self.avx512.quantize_codes(input, row_len, codes)
    }

    fn quantize_narrow_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
        self.avx512.quantize_narrow_codes(input, row_len, codes)
    }

    fn quantize_signed_bytes(
        &self,
        input: &[f32],
        row_len: usize,
        codes: &mut [i8],
        row_sums: &mut [i32],
    ) -> f32 {
        self.avx512
            .quantize_signed_bytes(input, row_len, codes, row_sums)
    }

    /// One plane of bytes, one `tdpbusd` per byte product: half the products and half the
    /// activation tile loads of the two digit planes.
    fn narrow_form(&self) -> NarrowForm {
        NarrowForm::Bytes
    }

    fn quantize_digits(&self, input: &[f32], digits: (&mut [i8], &mut [i8])) -> (f32, bool) {
        self.avx512.quantize_digits(input, digits)
    }

    fn quantize_narrow(&self, input: &[f32], scratch: &mut [i8], form: NarrowForm) -> f32 {
        self.avx512.quantize_narrow(input, scratch, form)
    }

    fn largest_magnitude(&self, input: &[f32]) -> f32 {
        self.avx512.largest_magnitude(input)
    }

    fn quantize_digits_within(
        &self,
        input: &[f32],
        largest: f32,
        digits: (&mut [i8], &mut [i8]),
    ) -> (f32, bool) {
        self.avx512.quantize_digits_within(input, largest, digits)
    }

    fn quantize_narrow_within(
        &self,
        input: &[f32],
        largest: f32,
        codes: (&mut [i8], &mut [i8]),
        form: NarrowForm,
    ) -> f32 {
        self.avx512
            .quantize_narrow_within(input, largest, codes, form)
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

    fn affine_activate(
        &self,
        data: &mut [f32],
        channels: usize,
        affine: (&[f32], &[f32]),
        activation: Activation,
    ) {
        self.avx512
            .affine_activate(data, channels, affine, activation)
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
        first_row: usize,
    ) {
        self.avx512
            .normalize_max_pool(input, dims, affine, activation, output, first_row)
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
