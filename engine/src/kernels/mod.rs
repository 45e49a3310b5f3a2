//! Compute kernels, apart from the model code that calls them.
//!
//! Each heavy kernel family is a method of [`Kernels`], the contract every implementation
//! meets; [`scalar::Scalar`] is the reference, always compiled, against which any faster
//! implementation is tested. Light element-wise operations live in [`ops`] as portable code;
//! they are [`Kernels`] methods too, so a SIMD backend can compile that same code for its
//! vectors (same bits, tested).
//!
//! The SIMD backends of each architecture (`x86_64/`: AVX2, AVX-512, AMX; `aarch64/`: NEON,
//! dot product, I8MM) share their bodies (`simd/`), written over small vector traits; a
//! backend is a type implementing [`Kernels`] (methods it does not speed up fall back on
//! [`scalar::Scalar`] or the portable defaults), a [`Backend`] variant and a branch in
//! [`select`] behind its own feature detection; the kernel tests run every backend in
//! [`available`] against the reference, and `SCDP_REQUIRE_BACKENDS` makes one that did not
//! run fail them. The int8 weight layout (input-channel quads,
//! `[out/64, kh, kw, in/4, 64, 4]`, [`int8_quad_index`], docs/FORMAT.md) is the four bytes
//! one `vpdpbusd` or `sdot` lane reads.

#[cfg(target_arch = "aarch64")]
pub mod aarch64;
pub mod board;
pub mod epilogue;
pub mod ops;
pub mod scalar;
#[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
pub(crate) mod simd;
pub mod split;
pub mod workers;
#[cfg(target_arch = "x86_64")]
pub mod x86_64;

pub use board::{Board, Collected};
pub use epilogue::{Epilogue, Film, FilmWeights, conv_then};
pub use split::Split;
pub use workers::{Sequential, Workers, run_each};

use ops::Activation;

// The plain shapes the kernels' contract is written in, under the names the kernels have
// always exported them by.
pub use crate::shape::{
    ConvShape, INT8_CHANNEL_BLOCK, PAIR, QUAD, int8_convolution, int8_pair_index, int8_pairs,
    int8_quad_index, int8_quad_stride, int8_quads, int8_stored_elements, pack_int8_pairs,
    pack_int8_quads,
};

/// Which kernel implementation to run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum Backend {
    /// The fastest the CPU supports.
    Auto,
    /// The portable reference.
    Scalar,
    /// x86-64 AVX2 + FMA.
    Avx2,
    /// x86-64 AVX-512 (F, BW, VL) with VNNI: the int8 and f32 2-D convolutions, the U-Net
    /// kernels and the element-wise operations on ZMM vectors; AVX2 where those do not apply.
    Avx512,
    /// x86-64 AMX (TILE, INT8): the int8 convolutions (trunk and U-Net) on the tile matrix
    /// unit, the rest as [`Backend::Avx512`]. On Linux, detection asks the OS for the tile
    /// registers.
    Amx,
    /// aarch64 NEON: the f32 kernels on NEON vectors (AVX2's bits), int8 on widening
    /// multiplies.
    Neon,
    /// aarch64 NEON with the dot-product extension: the int8 convolutions on `sdot`.
    Dot,
    /// aarch64 with I8MM: the convolutions on bytes (the stem, the trunk's narrow
    /// activations on `usmmla`, the U-Net's on `smmla`) on its matrix multiplies, the rest as
    /// [`Backend::Dot`].
    I8mm,
}

impl Backend {
    /// Every backend, [`Backend::Auto`] first.
    pub const ALL: [Backend; 8] = [
        Backend::Auto,
        Backend::Scalar,
        Backend::Avx2,
        Backend::Avx512,
        Backend::Amx,
        Backend::Neon,
        Backend::Dot,
        Backend::I8mm,
    ];

    /// The name [`Kernels::name`] reports for it (`"auto"` for [`Backend::Auto`]).
    pub const fn name(self) -> &'static str {
        match self {
            Backend::Auto => "auto",
            Backend::Scalar => "scalar",
            Backend::Avx2 => "avx2",
            Backend::Avx512 => "avx512",
            Backend::Amx => "amx",
            Backend::Neon => "neon",
            Backend::Dot => "dot",
            Backend::I8mm => "i8mm",
        }
    }

    /// The backend of that name.
    pub fn from_name(name: &str) -> Option<Backend> {
        Backend::ALL
            .into_iter()
            .find(|backend| backend.name() == name)
    }
}

/// The implementation for `backend`, or `None` when this CPU cannot run it. Detection uses
/// CPUID, so it works without std.
pub fn select(backend: Backend) -> Option<&'static dyn Kernels> {
    match backend {
        Backend::Scalar => Some(&scalar::Scalar),
        Backend::Avx2 => avx2(),
        Backend::Avx512 => avx512(),
        Backend::Amx => amx(),
        Backend::Neon => neon(),
        Backend::Dot => dot(),
        Backend::I8mm => i8mm(),
        Backend::Auto => available().next(),
    }
}

/// Every implementation this CPU can run, fastest first, the scalar reference last.
pub fn available() -> impl Iterator<Item = &'static dyn Kernels> {
    [
        Backend::Amx,
        Backend::Avx512,
        Backend::Avx2,
        Backend::I8mm,
        Backend::Dot,
        Backend::Neon,
        Backend::Scalar,
    ]
    .into_iter()
    .filter_map(select)
}

#[cfg(target_arch = "aarch64")]
fn neon() -> Option<&'static dyn Kernels> {
    aarch64::Neon::detect().map(|kernels| kernels as &'static dyn Kernels)
}

#[cfg(target_arch = "aarch64")]
fn dot() -> Option<&'static dyn Kernels> {
    aarch64::Dot::detect().map(|kernels| kernels as &'static dyn Kernels)
}

#[cfg(target_arch = "aarch64")]
fn i8mm() -> Option<&'static dyn Kernels> {
    aarch64::I8mm::detect().map(|kernels| kernels as &'static dyn Kernels)
}

#[cfg(not(target_arch = "aarch64"))]
fn neon() -> Option<&'static dyn Kernels> {
    None
}

#[cfg(not(target_arch = "aarch64"))]
fn dot() -> Option<&'static dyn Kernels> {
    None
}

#[cfg(not(target_arch = "aarch64"))]
fn i8mm() -> Option<&'static dyn Kernels> {
    None
}

#[cfg(target_arch = "x86_64")]
fn avx2() -> Option<&'static dyn Kernels> {
    x86_64::avx2::Avx2::detect().map(|kernels| kernels as &'static dyn Kernels)
}

#[cfg(target_arch = "x86_64")]
fn avx512() -> Option<&'static dyn Kernels> {
    x86_64::avx512::Avx512::detect().map(|kernels| kernels as &'static dyn Kernels)
}

#[cfg(target_arch = "x86_64")]
fn amx() -> Option<&'static dyn Kernels> {
    x86_64::amx::Amx::detect().map(|kernels| kernels as &'static dyn Kernels)
}

#[cfg(not(target_arch = "x86_64"))]
fn amx() -> Option<&'static dyn Kernels> {
    None
}

#[cfg(not(target_arch = "x86_64"))]
fn avx2() -> Option<&'static dyn Kernels> {
    None
}

#[cfg(not(target_arch = "x86_64"))]
fn avx512() -> Option<&'static dyn Kernels> {
    None
}

/// Whether an int8 tensor of `dims` can be run: a convolution's exact i32 code sums hold up
/// to [`MAX_DIGIT_CHANNELS`] inputs (wider ones are stored in f32 by the tool).
pub fn int8_fits(dims: &[usize]) -> bool {
    int8_convolution(dims).is_none_or(|(_, inputs, _)| inputs <= MAX_DIGIT_CHANNELS)
}

/// Whether a convolution overwrites its output or adds to it (residual connections).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accumulate {
    Overwrite,
    Add,
}

/// The contract of a kernel implementation. Slices have exactly the lengths the shapes
/// imply (the model code guarantees it; implementations may assert it).
pub trait Kernels: Sync {
    /// Name used in benchmarks and to prove which backend ran.
    fn name(&self) -> &'static str;

    /// `output = conv(input) + bias` (or `+=` with [`Accumulate::Add`]); zero padding.
    fn conv(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    );

    /// Output pixel `pixel = (out_y, out_x)` of [`conv`](Self::conv) with
    /// [`Accumulate::Overwrite`], written to `output` (`out_channels` values): bit for bit
    /// what `conv` writes there on this implementation, for 2-D maps (`in_height > 1`; the
    /// 1-D sequence kernels have no single-position form). The pyramid evaluates large
    /// projections only at the cells the anchors sample, and must get the dense values.
    #[allow(clippy::too_many_arguments)]
    fn conv_pixel(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        pixel: (usize, usize),
        output: &mut [f32],
    ) {
        scalar::conv_pixel(
            shape,
            (input, weight, bias),
            output,
            Accumulate::Overwrite,
            pixel,
        );
    }

    /// [`conv_pixel`](Self::conv_pixel) at each of `pixels` (`(row, column)`, inside the
    /// output), into `output`, the whole output map: only those pixels are written. The
    /// f32 projections evaluated on demand ask for the cells an inference step's anchors
    /// sample, a few dozen at a time.
    #[allow(clippy::too_many_arguments)]
    fn conv_pixels(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        pixels: &[(usize, usize)],
        output: &mut [f32],
    ) {
        for &pixel in pixels {
            let out = &mut output[shape.pixel_values(pixel)];
            self.conv_pixel(shape, input, weight, bias, pixel, out);
        }
    }

    /// [`conv_pixel`](Self::conv_pixel) for [`conv_int8`](Self::conv_int8).
    #[allow(clippy::too_many_arguments)]
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
        scalar::conv_int8_pixel(
            shape,
            input,
            (weight, weight_scales, bias),
            output,
            Accumulate::Overwrite,
            pixel,
            0..shape.out_channels,
        );
    }

    /// [`conv_int8_pixel`](Self::conv_int8_pixel) at each of `pixels` (`(row, column)`,
    /// inside the output), into `output`, the whole output map: only those pixels are
    /// written. The projections evaluated on demand ask for the cells an inference step's
    /// anchors sample, a few dozen at a time.
    #[allow(clippy::too_many_arguments)]
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
        each_pixel(self, shape, input, parameters, pixels, output)
    }

    /// Output channels `channels` of [`conv`](Self::conv), into `output` (`[positions,
    /// channels.len()]`, holding those channels' values before the call for
    /// [`Accumulate::Add`]; `bias` is the whole layer's): bit for bit what `conv` writes at
    /// those channels, for `channels` starting at a multiple of 64 and ending at one or at
    /// the last channel. Returns `false`, writing nothing, where this implementation has no
    /// such form for `shape` (this default: never), whatever `channels`; so empty
    /// `channels` only ask. The U-Net's f32 layers, and the trunk's small maps whose weights
    /// outweigh their input, are cut by output channels over several workers this way
    /// ([`split::Split`]), each worker reading its own share of the weights.
    #[allow(clippy::too_many_arguments)]
    fn conv_channels(
        &self,
        _shape: &ConvShape,
        _input: &[f32],
        _weight: &[f32],
        _bias: &[f32],
        _channels: core::ops::Range<usize>,
        _output: &mut [f32],
        _accumulate: Accumulate,
    ) -> bool {
        false
    }

    /// `output[r] = base[r] + sum_c weight[r, c] input[c]` for a row-major `[rows, cols]`.
    fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]);

    /// [`conv`](Self::conv) on 15-bit activation codes in two int8 digit planes
    /// (`code = 128 high + low`, [`DigitRows`]) with one scale for the whole input, the
    /// kernel in the quad layout of [`int8_quad_index`] (`shape.int8_weight_len()` values).
    /// For each output position, the integer sum `S[o] = sum code q_w` over every kernel tap
    /// inside the input (padding reads zero codes) and every input channel is exact (the part
    /// every implementation must reproduce; it may be computed as
    /// `128 sum high q_w + sum low q_w`, each digit's sum exact in i32 for
    /// [`MAX_DIGIT_TERMS`] products), then rounded once to f32 (to nearest);
    /// `acc[o] = S[o] * input scale` and `output[o] = acc[o] * weight_scales[o] + bias[o]`
    /// (with [`Accumulate::Add`], `output[o] += that`), each a product then a sum, not a
    /// fused multiply-add. Every implementation therefore gives bit-identical outputs.
    #[allow(clippy::too_many_arguments)]
    fn conv_int8(
        &self,
        shape: &ConvShape,
        input: &DigitRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    );

    /// [`conv_int8`](Self::conv_int8) on codes that are bytes in one plane ([`ByteRows`]:
    /// the stem's patches of image bytes, as a pointwise convolution, and the residual
    /// blocks' narrow activations): the same exact sums (over at most [`MAX_BYTE_TERMS`]
    /// products, so they fit i32), rounding and scaling, so the same bits as `conv_int8` on
    /// the bytes split into digits (`byte = 128 (byte >> 7) + (byte & 127)`). This default
    /// does that split a few pixels at a time for a pointwise convolution and runs the
    /// scalar reference otherwise; VNNI's and the AMX tiles' byte products take whole bytes,
    /// half the products. Up to [`MAX_DIGIT_CHANNELS`] inputs, as `conv_int8`: the SIMD
    /// tiles read the padding's zeros from a row that long.
    ///
    /// # Panics
    /// If a slice is shorter than the contract makes it, or the shape has more inputs.
    #[allow(clippy::too_many_arguments)]
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
        const CHUNK: usize = 4 * MAX_BYTE_CHANNELS;
        scalar::assert_byte_lengths(shape, input, (weight, weight_scales, bias), output.len());
        let (channels, out_channels) = (shape.in_channels, shape.out_channels);
        if !shape.is_pointwise() || channels > MAX_BYTE_CHANNELS {
            let parameters = (weight, weight_scales, bias);
            return scalar::conv_int8_bytes(shape, input, parameters, output, accumulate);
        }
        let (mut high, mut low) = ([0i8; CHUNK], [0i8; CHUNK]);
        let pixels_per_chunk = CHUNK / channels;
        let rows = input.bytes.chunks(pixels_per_chunk * channels);
        let outputs = output.chunks_mut(pixels_per_chunk * out_channels);
        for (bytes, output) in rows.zip(outputs) {
            for ((high, low), &byte) in high.iter_mut().zip(low.iter_mut()).zip(bytes) {
                (*high, *low) = ((byte >> 7) as i8, (byte & 127) as i8);
            }
            let pixels = bytes.len() / channels;
            let chunk = ConvShape::square((1, pixels, channels), out_channels, 1, 1, 0);
            let digits = DigitRows {
                high: &high[..bytes.len()],
                low: &low[..bytes.len()],
                scale: input.scale,
                nonnegative: true,
            };
            self.conv_int8(
                &chunk,
                &digits,
                weight,
                weight_scales,
                bias,
                output,
                accumulate,
            );
        }
    }

    /// [`conv_int8`](Self::conv_int8) on the same 15-bit codes kept whole and signed
    /// ([`CodeRows`]: i16, rows padded to whole input-channel quads), for 1-D convolutions
    /// (`in_height == 1`, the U-Net's): the same exact code sums over all taps (exact in i32
    /// per tap, up to [`MAX_DIGIT_CHANNELS`] inputs, not always over the whole kernel),
    /// rounded, scaled and stored in the same order, so every implementation gives the same
    /// bits.
    #[allow(clippy::too_many_arguments)]
    fn conv_int8_codes(
        &self,
        shape: &ConvShape,
        input: &CodeRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    );

    /// [`conv_int8_bytes`](Self::conv_int8_bytes) given the same weights in the pair layout
    /// too (`pairs`: [`int8_pair_index`], `shape.int8_pair_weight_len()` values, where the
    /// file holds them): the same bits. I8MM's matrix multiplies take eight inputs of two
    /// channels an operand, which the pairs are as stored; this default reads the quads.
    ///
    /// # Panics
    /// As `conv_int8_bytes`, and if `pairs` has another length where it is read.
    #[allow(clippy::too_many_arguments)]
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
        let _ = pairs;
        self.conv_int8_bytes(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        )
    }

    /// [`conv_int8_codes`](Self::conv_int8_codes) on narrow signed codes
    /// ([`SignedByteRows`]: one signed byte a value, |code| <= 127, rows padded to whole
    /// quads as [`CodeRows`]' are): the same exact sums (over at most [`MAX_BYTE_TERMS`]
    /// products), rounding and scaling, so the same bits as `conv_int8_codes` on the same
    /// codes widened to i16. This default runs the scalar reference; VNNI multiplies whole
    /// bytes, AVX2 widens them to its 16-bit products. Up to [`MAX_DIGIT_CHANNELS`] inputs,
    /// as `conv_int8_codes`.
    ///
    /// # Panics
    /// If a slice is shorter than the contract makes it, or the shape has more inputs.
    #[allow(clippy::too_many_arguments)]
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
        let parameters = (weight, weight_scales, bias);
        scalar::assert_signed_byte_lengths(shape, input, parameters, output.len());
        scalar::conv_int8_signed_bytes(shape, input, parameters, output, accumulate);
    }

    /// [`conv_int8_signed_bytes`](Self::conv_int8_signed_bytes) given the weights in the
    /// pair layout too, as [`conv_int8_bytes_paired`](Self::conv_int8_bytes_paired): the
    /// same bits; this default reads the quads.
    ///
    /// # Panics
    /// As `conv_int8_signed_bytes`, and if `pairs` has another length where it is read.
    #[allow(clippy::too_many_arguments)]
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
        let _ = pairs;
        self.conv_int8_signed_bytes(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        )
    }

    /// [`matvec`](Self::matvec) with int8 weights (row-major `[rows, cols]`, one scale per
    /// row) on the input's 15-bit codes ([`CodeRows`]: one row of `cols` codes, padded to
    /// whole quads, and its scale). The integer sum `S[r] = sum_c code[c] q_w[r, c]` is
    /// exact (what every implementation must reproduce), then rounded once to f32 (to
    /// nearest); `output[r] = base[r] + (S[r] * input scale) * row_scales[r]`, products then
    /// a sum, not fused, so every implementation gives the same bits.
    fn matvec_int8_codes(
        &self,
        weight: &[i8],
        row_scales: &[f32],
        input: &CodeRows<'_>,
        base: &[f32],
        output: &mut [f32],
    );

    /// [`ops::quantize_split_signs`]: 15-bit symmetric quantization of `input`, one scale
    /// for all of it, into two int8 digit planes; returns the scale and whether every code
    /// is nonnegative. Element-wise, like the methods below: implementations compile the
    /// portable code for their vectors and give the same bits.
    fn quantize_digits(&self, input: &[f32], digits: (&mut [i8], &mut [i8])) -> (f32, bool) {
        ops::quantize_split_signs(input, digits.0, digits.1)
    }

    /// [`ops::largest_magnitude`], what a quantization's scale comes from: the largest of
    /// several parts' results, their bits compared as integers, is the whole input's.
    fn largest_magnitude(&self, input: &[f32]) -> f32 {
        ops::largest_magnitude(input)
    }

    /// [`quantize_digits`](Self::quantize_digits) of a part of an input whose largest
    /// magnitude is `largest`: that part of the whole input's digits, the scale, and whether
    /// the part's codes are nonnegative ([`ops::quantize_split_signs_within`]).
    fn quantize_digits_within(
        &self,
        input: &[f32],
        largest: f32,
        digits: (&mut [i8], &mut [i8]),
    ) -> (f32, bool) {
        ops::quantize_split_signs_within(input, largest, digits.0, digits.1)
    }

    /// [`quantize_narrow`](Self::quantize_narrow) of a part of an input whose largest
    /// magnitude is `largest`, into `codes`: the part's bytes, or its parts of the two digit
    /// planes ([`ops::quantize_narrow_within`]).
    fn quantize_narrow_within(
        &self,
        input: &[f32],
        largest: f32,
        codes: (&mut [i8], &mut [i8]),
        form: NarrowForm,
    ) -> f32 {
        ops::quantize_narrow_within(input, largest, codes, form)
    }

    /// The form in which this implementation takes narrow codes fastest: whole bytes for
    /// [`conv_int8_bytes`](Self::conv_int8_bytes), or (the default, which every
    /// implementation's [`conv_int8`](Self::conv_int8) takes) two digit planes. The codes,
    /// and so the bits, are the same either way.
    fn narrow_form(&self) -> NarrowForm {
        NarrowForm::Digits
    }

    /// [`ops::quantize_narrow`]: the 8-bit codes of a nonnegative `input` (one scale for all
    /// of it) into the front of `scratch` in `form`; returns the scale. Element-wise, the
    /// portable code compiled for each implementation's vectors.
    fn quantize_narrow(&self, input: &[f32], scratch: &mut [i8], form: NarrowForm) -> f32 {
        ops::quantize_narrow(input, scratch, form)
    }

    /// [`ops::quantize_rows_codes`]: 15-bit symmetric quantization of `input`, one scale
    /// for all of it, into whole codes, rows of `row_len` padded to whole quads
    /// ([`CodeRows`]); returns the scale.
    fn quantize_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
        let row_stride = CodeRows::row_stride(row_len);
        ops::quantize_rows_codes(input, (row_len, row_stride), codes)
    }

    /// [`ops::quantize_rows_signed_bytes`]: narrow signed quantization of `input`, one scale
    /// for all of it, rows of `row_len` padded to whole quads ([`SignedByteRows`]), with each
    /// row's code sum; returns the scale.
    fn quantize_signed_bytes(
        &self,
        input: &[f32],
        row_len: usize,
        codes: &mut [i8],
        row_sums: &mut [i32],
    ) -> f32 {
        let row_stride = CodeRows::row_stride(row_len);
        ops::quantize_rows_signed_bytes(input, (row_len, row_stride), codes, row_sums)
    }

    /// [`ops::quantize_rows_narrow_codes`]: the codes of
    /// [`quantize_signed_bytes`](Self::quantize_signed_bytes) as whole 16-bit codes
    /// ([`CodeRows`]); returns the scale.
    fn quantize_narrow_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16]) -> f32 {
        let row_stride = CodeRows::row_stride(row_len);
        ops::quantize_rows_narrow_codes(input, (row_len, row_stride), codes)
    }

    /// Output pixels this implementation's int8 convolutions of 2-D maps compute at once
    /// (AMX: a tile's 16 rows): a piece of a call cut by output rows that holds fewer still
    /// computes a whole run, so [`Split`] cuts such maps by output channels instead.
    fn int8_pixel_block(&self) -> usize {
        1
    }

    /// Whether this implementation multiplies the U-Net's narrow codes fastest as signed
    /// bytes ([`conv_int8_signed_bytes`](Self::conv_int8_signed_bytes), the default) or
    /// widened to 16 bits once, as they are quantized
    /// ([`quantize_narrow_codes`](Self::quantize_narrow_codes) and
    /// [`conv_int8_codes`](Self::conv_int8_codes)): the same codes, exact sums and
    /// roundings, so the same bits.
    fn multiplies_signed_bytes(&self) -> bool {
        true
    }

    /// [`ops::group_norm`], in place.
    fn group_norm(
        &self,
        data: &mut [f32],
        channels: usize,
        groups: usize,
        (gamma, beta): (&[f32], &[f32]),
        activation: Activation,
    ) {
        ops::group_norm(data, channels, groups, gamma, beta, activation)
    }

    /// [`ops::affine_activate`]: `activation(x * scale + shift)` per channel, in place.
    fn affine_activate(
        &self,
        data: &mut [f32],
        channels: usize,
        affine: (&[f32], &[f32]),
        activation: Activation,
    ) {
        ops::affine_activate(data, channels, affine, activation)
    }

    /// [`epilogue::conv_then`] where this implementation runs it its own way (cut over
    /// workers: [`Split`]); `false`, having run nothing, where it does not.
    fn conv_then(
        &self,
        output: &mut [f32],
        channels: usize,
        epilogue: &Epilogue<'_>,
        film: &mut [f32],
        conv: &mut dyn FnMut(&dyn Kernels, &mut [f32]),
    ) -> bool {
        let _ = (output, channels, epilogue, film, conv);
        false
    }

    /// [`ops::add_activate`]: `target += source`, then `activation`.
    fn add_activate(&self, target: &mut [f32], source: &[f32], activation: Activation) {
        ops::add_activate(target, source, activation)
    }

    /// [`ops::add_channel_moments`]: adds each channel's sum and sum of squares over
    /// `data`'s pixels to `moments`.
    fn add_channel_moments(
        &self,
        data: &[f32],
        channels: usize,
        moments: (&mut [f64], &mut [f64]),
    ) {
        ops::add_channel_moments(data, channels, moments)
    }

    /// [`ops::normalize_max_pool`]: the max pool of `activation(x * scale + shift)`, its
    /// rows from `first_row` on into `output`.
    fn normalize_max_pool(
        &self,
        input: &[f32],
        dims: (usize, usize, usize),
        affine: (&[f32], &[f32]),
        activation: Activation,
        output: &mut [f32],
        first_row: usize,
    ) {
        ops::normalize_max_pool(input, dims, affine, activation, output, first_row)
    }

    /// [`ops::max_pool_3x3_stride_2`]: `[height, width, channels]` -> the pooled map.
    fn max_pool_3x3_stride_2(
        &self,
        input: &[f32],
        dims: (usize, usize, usize),
        output: &mut [f32],
    ) {
        ops::max_pool_3x3_stride_2(input, dims, output)
    }
}

/// Input channels up to which the exact sum of one kernel tap fits i32:
/// `|code| <= 16383`, `|q_w| <= 128`, `16383 x 128 x 1024 < 2^31`. ResNet-18's widest layer
/// has 512.
pub const MAX_DIGIT_CHANNELS: usize = 1024;

/// Products (kernel taps x input channels) up to which a digit plane's exact sum over a
/// whole kernel fits i32: `|digit| <= 128`, `|q_w| <= 128`, `16384 x 131072 = 2^31`. A 7x7
/// kernel over [`MAX_DIGIT_CHANNELS`] inputs has 50,176.
pub const MAX_DIGIT_TERMS: usize = 131_072;

/// Input channels of a pointwise convolution on [`ByteRows`] that the default
/// [`Kernels::conv_int8_bytes`] splits into digit planes on the stack: the stem's patches
/// have 196.
pub const MAX_BYTE_CHANNELS: usize = 256;

/// Products (kernel taps x input channels) up to which a convolution's exact sum over
/// bytes fits i32: `255 x 128 x 65536 < 2^31`. A 3x3 kernel over 1024 inputs has 9,216.
pub const MAX_BYTE_TERMS: usize = 65_536;

/// Activation codes that are bytes (0..=255) in one plane, with one scale for the whole
/// input: the int8 stem's patches of image bytes, and the narrow activations of the
/// residual blocks ([`ops::quantize_bytes`]). VNNI's `vpdpbusd` and the matrix tiles
/// multiply whole bytes; AVX2 reads them as two digit planes ([`DigitRows`]).
#[derive(Clone, Copy, Debug)]
pub struct ByteRows<'a> {
    pub bytes: &'a [u8],
    pub scale: f32,
}

/// Activations quantized to signed 15-bit codes ([`ops::quantize_rows_codes`]) with one scale
/// for the whole input (`value ~ code * scale`), each row (position) padded with zero codes
/// to whole input-channel quads (`int8_quads(channels) * 4` codes a row), so a kernel reads
/// four codes where the weights have a quad.
#[derive(Clone, Copy, Debug)]
pub struct CodeRows<'a> {
    pub codes: &'a [i16],
    pub scale: f32,
}

impl CodeRows<'_> {
    /// Codes a row of `channels` values takes: whole quads.
    pub const fn row_stride(channels: usize) -> usize {
        int8_quads(channels) * QUAD
    }
}

/// The U-Net's narrow activations ([`ops::quantize_rows_signed_bytes`]): signed 8-bit codes
/// (|code| <= 127) with one scale for the whole input (`value ~ code * scale`), rows
/// (positions) padded with zero codes to whole input-channel quads as [`CodeRows`]' are,
/// and each row's code sum, which lets byte products that take one unsigned side run them
/// on weights offset by 128 and take the offset's share back out.
#[derive(Clone, Copy, Debug)]
pub struct SignedByteRows<'a> {
    pub codes: &'a [i8],
    /// `sum_c code[row, c]` per row.
    pub row_sums: &'a [i32],
    pub scale: f32,
}

/// How narrow (8-bit) codes are laid out: one plane of bytes ([`ByteRows`]), or the same
/// codes as two digit planes ([`DigitRows`], the high digit 0 or 1) for byte products
/// that take 7-bit activations only.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NarrowForm {
    Bytes,
    Digits,
}

/// A trunk layer's quantized input as its convolution reads it:
/// [`Kernels::conv_int8`] on digit planes (15-bit codes, or narrow codes split),
/// [`Kernels::conv_int8_bytes`] on whole bytes.
#[derive(Clone, Copy, Debug)]
pub enum TrunkCodes<'a> {
    Digits(DigitRows<'a>),
    Bytes(ByteRows<'a>),
}

/// What one quantization left at the front of a [`QuantizeScratch`], to view it again
/// ([`QuantizeScratch::view`]) for another layer reading the same input.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Quantized {
    /// Values quantized.
    pub len: usize,
    /// One plane of bytes (narrow codes) or two digit planes.
    pub form: NarrowForm,
    pub scale: f32,
    /// Every code is nonnegative ([`DigitRows::nonnegative`]; narrow codes always are).
    pub nonnegative: bool,
}

/// Arena space for quantizing one layer input: its two digit planes (the high digits, then
/// the low ones), its bytes, or its whole codes.
#[derive(Debug)]
pub struct QuantizeScratch<'a> {
    pub values: &'a mut [i8],
}

/// Activations quantized to 15-bit codes in two int8 digit planes
/// ([`ops::quantize_split_signs`]) with one scale for the whole input:
/// `value ~ (128 high + low) * scale`. The low digits are always nonnegative.
#[derive(Clone, Copy, Debug)]
pub struct DigitRows<'a> {
    pub high: &'a [i8],
    pub low: &'a [i8],
    pub scale: f32,
    /// Every code is nonnegative (true of every ReLU output): both digits are then in
    /// 0..=127 and read the same as u8, which the unsigned-by-signed integer dot products
    /// need. `false` only promises nothing. For [`Kernels::conv_int8_pixel`] it need only
    /// hold on the rows that pixel's taps read.
    pub nonnegative: bool,
}

impl<'a> DigitRows<'a> {
    /// The view of planes written back to back in `values` (`2 rows row_len` bytes).
    pub fn from_planes(values: &'a [i8], scale: f32, nonnegative: bool) -> Self {
        let (high, low) = values.split_at(values.len() / 2);
        DigitRows {
            high,
            low,
            scale,
            nonnegative,
        }
    }
}

impl QuantizeScratch<'_> {
    /// Quantizes `input` (the activation scheme of int8 weights files,
    /// [`ops::quantize_split_signs`]) and returns the view.
    pub fn quantize(&mut self, kernels: &dyn Kernels, input: &[f32]) -> DigitRows<'_> {
        let quantized = self.quantize_wide(kernels, input);
        DigitRows::from_planes(
            &self.values[..2 * input.len()],
            quantized.scale,
            quantized.nonnegative,
        )
    }

    /// [`quantize`](Self::quantize), returning what [`view`](Self::view) needs.
    pub fn quantize_wide(&mut self, kernels: &dyn Kernels, input: &[f32]) -> Quantized {
        let (high, low) = self.values[..2 * input.len()].split_at_mut(input.len());
        let (scale, nonnegative) = kernels.quantize_digits(input, (high, low));
        Quantized {
            len: input.len(),
            form: NarrowForm::Digits,
            scale,
            nonnegative,
        }
    }

    /// Quantizes a nonnegative `input` to narrow codes ([`ops::quantize_bytes`]) in the
    /// form `kernels` reads fastest.
    pub fn quantize_narrow(&mut self, kernels: &dyn Kernels, input: &[f32]) -> Quantized {
        let form = kernels.narrow_form();
        let scale = kernels.quantize_narrow(input, self.values, form);
        Quantized {
            len: input.len(),
            form,
            scale,
            nonnegative: true,
        }
    }

    /// The codes a quantization of this scratch left, as a convolution reads them.
    pub fn view(&self, quantized: &Quantized) -> TrunkCodes<'_> {
        let Quantized {
            len,
            form,
            scale,
            nonnegative,
        } = *quantized;
        match form {
            NarrowForm::Bytes => TrunkCodes::Bytes(ByteRows {
                bytes: bytemuck::cast_slice(&self.values[..len]),
                scale,
            }),
            NarrowForm::Digits => TrunkCodes::Digits(DigitRows::from_planes(
                &self.values[..2 * len],
                scale,
                nonnegative,
            )),
        }
    }

    /// Quantizes `input`, rows of `row_len` values, to whole codes ([`CodeRows`]) in the
    /// same bytes.
    pub fn quantize_codes(
        &mut self,
        kernels: &dyn Kernels,
        input: &[f32],
        row_len: usize,
    ) -> CodeRows<'_> {
        self.whole_codes(input, row_len, |input, codes| {
            kernels.quantize_codes(input, row_len, codes)
        })
    }
}

impl QuantizeScratch<'_> {
    /// Quantizes `input`, rows of `row_len` values, to narrow signed codes kept as whole
    /// 16-bit codes ([`Kernels::quantize_narrow_codes`]) in the same bytes.
    pub fn quantize_narrow_codes(
        &mut self,
        kernels: &dyn Kernels,
        input: &[f32],
        row_len: usize,
    ) -> CodeRows<'_> {
        self.whole_codes(input, row_len, |input, codes| {
            kernels.quantize_narrow_codes(input, row_len, codes)
        })
    }

    /// The rows of i16 codes `quantize` writes for `input` (returning their scale), at the
    /// front of this scratch.
    fn whole_codes(
        &mut self,
        input: &[f32],
        row_len: usize,
        quantize: impl FnOnce(&[f32], &mut [i16]) -> f32,
    ) -> CodeRows<'_> {
        let rows = input.len() / row_len;
        let row_stride = CodeRows::row_stride(row_len);
        let codes: &mut [i16] = bytemuck::cast_slice_mut(&mut self.values[..2 * rows * row_stride]);
        let scale = quantize(input, codes);
        CodeRows { codes, scale }
    }

    /// Quantizes `input`, rows of `row_len` values, to narrow signed codes
    /// ([`SignedByteRows`]): the row sums at the front, the rows of codes after them. Needs
    /// no more space than [`quantize_codes`](Self::quantize_codes) (4 bytes a row for its
    /// sum, at most as many as a row of i16 codes saves), from a 4-byte aligned start (the
    /// arena's regions are 64-byte aligned).
    pub fn quantize_signed_bytes(
        &mut self,
        kernels: &dyn Kernels,
        input: &[f32],
        row_len: usize,
    ) -> SignedByteRows<'_> {
        let rows = input.len() / row_len;
        let row_stride = CodeRows::row_stride(row_len);
        let (_, words, _) = bytemuck::pod_align_to_mut::<i8, i32>(self.values);
        let (row_sums, rest) = words.split_at_mut(rows);
        let codes: &mut [i8] = &mut bytemuck::cast_slice_mut(rest)[..rows * row_stride];
        let scale = kernels.quantize_signed_bytes(input, row_len, codes, row_sums);
        SignedByteRows {
            codes,
            row_sums,
            scale,
        }
    }
}

/// [`Kernels::conv_int8_pixels`] one [`Kernels::conv_int8_pixel`] at a time.
pub fn each_pixel<K: Kernels + ?Sized>(
    kernels: &K,
    shape: &ConvShape,
    input: &DigitRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    pixels: &[(usize, usize)],
    output: &mut [f32],
) {
    for &pixel in pixels {
        let out = &mut output[shape.pixel_values(pixel)];
        kernels.conv_int8_pixel(shape, input, weight, weight_scales, bias, pixel, out);
    }
}
