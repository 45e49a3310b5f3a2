//! The tile products: a convolution over bands ([`conv`]), one block's exact sums over
//! every tap and input channel in `tmm0`-`tmm3` ([`tile_sums`]), and the epilogue that
//! turns stored sums into outputs ([`Epilogue`]).

use core::arch::asm;
use core::arch::x86_64::{
    __m512i, _mm512_add_epi32, _mm512_add_ps, _mm512_cvtepi32_ps, _mm512_load_si512,
    _mm512_loadu_ps, _mm512_mul_ps, _mm512_set1_ps, _mm512_setzero_si512, _mm512_slli_epi32,
    _mm512_storeu_ps,
};
use core::mem::MaybeUninit;

use super::band::{
    BAND_BYTES, Band, BandBuffer, BandInput, MAX_PARTIAL_TAPS, fill_band, pack_partial_step,
};
use super::{
    BLOCK_CHANNELS, BLOCK_PIXELS, CHANNELS_PER_STEP, Parameters, ROW_BYTES, ROWS, SUM_COLUMNS,
    TILE_CONFIG,
};
use crate::kernels::ops::DIGIT_BASE;
use crate::kernels::x86_64::int8::{exact_digits_zmm, round_zmm};
use crate::kernels::{
    Accumulate, ConvShape, MAX_DIGIT_CHANNELS, QUAD, int8_quad_stride, int8_quads,
};

/// One tile's worth of bytes, aligned for `tileloadd` / `tilestored` and ZMM moves. Not
/// initialized: written whole (by `tilestored`, or packed) before anything reads it, so a
/// call does not clear 26 KB of stack it will overwrite (the U-Net makes 33 calls a step).
#[derive(Clone, Copy)]
#[repr(C, align(64))]
pub(super) struct TileBuffer(pub(super) [MaybeUninit<u8>; ROWS * ROW_BYTES]);

impl TileBuffer {
    pub(super) const UNWRITTEN: TileBuffer = TileBuffer([MaybeUninit::uninit(); ROWS * ROW_BYTES]);

    pub(super) fn as_ptr(&self) -> *const u8 {
        self.0.as_ptr().cast()
    }

    pub(super) fn as_mut_ptr(&mut self) -> *mut u8 {
        self.0.as_mut_ptr().cast()
    }
}

/// The sum tiles of one block: the high digits' for channels 0-15 and 16-31 of the block,
/// then the low digits', as `tmm0`-`tmm3` hold them.
type BlockSums = [TileBuffer; 4];

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
pub(super) unsafe fn conv<I: BandInput>(
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
pub(super) unsafe fn store_sums(sums: &mut BlockSums) {
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
    pub(super) band: Band,
    origin: (usize, usize),
}

/// What turns a block's exact sums into outputs.
pub(super) struct Epilogue<'p> {
    pub(super) i32_exact: bool,
    pub(super) scale: f32,
    pub(super) parameters: (&'p [f32], &'p [f32]),
    pub(super) out_channels: usize,
    pub(super) out_width: usize,
    pub(super) accumulate: Accumulate,
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
    pub(super) unsafe fn write_group(
        &self,
        (high, low): (__m512i, __m512i),
        channel: usize,
        out: &mut [f32],
    ) {
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
