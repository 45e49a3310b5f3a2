//! The int8 convolution of the SIMD backends ([`Kernels::conv_int8`](crate::kernels::Kernels)):
//! what they share, and the AVX2 integer tile.
//!
//! A tile is [`PIXELS`] consecutive output positions (row-major over the output map, so a
//! tile may wrap onto the next row, and maps of one or two pixels still use it) times a block
//! of output channels. Per kernel tap, the tile's exact i32 sums are accumulated in registers
//! over all input-channel quads, then converted and added to f32 totals with each pixel's
//! row scale, in kernel order as the contract says. A pixel whose tap falls in the padding
//! computes a sum of some other row that is thrown away: it is skipped exactly where the
//! reference skips it, so border pixels need no separate path.
//!
//! The unsigned-by-signed byte products need activations in 0..=127, which every trunk input
//! is (a ReLU output); [`QuantizedRows::nonnegative`] says so, and any other input goes to the
//! scalar reference.

use core::arch::x86_64::{
    __m256, __m256i, _mm256_add_epi32, _mm256_add_ps, _mm256_cvtepi32_ps, _mm256_loadu_ps,
    _mm256_loadu_si256, _mm256_madd_epi16, _mm256_maddubs_epi16, _mm256_mul_ps, _mm256_set1_epi16,
    _mm256_set1_epi32, _mm256_set1_ps, _mm256_setzero_ps, _mm256_setzero_si256, _mm256_storeu_ps,
};

use crate::kernels::scalar::conv_int8_pixels;
use crate::kernels::{Accumulate, ConvShape, QUAD, QuantizedRows, int8_quad_index};

/// Output positions per tile.
pub(crate) const PIXELS: usize = 4;

/// The pixels of one tile: the first output position and how many there are (the last tile
/// of a map may be short).
#[derive(Clone, Copy, Debug)]
pub(crate) struct PixelTile {
    pub first: usize,
    pub count: usize,
    /// Input coordinates of kernel tap (0, 0) per pixel, negative inside the padding.
    origins: [(isize, isize); PIXELS],
}

impl PixelTile {
    fn new(shape: &ConvShape, first: usize, count: usize) -> Self {
        let out_width = shape.out_width();
        let origins = core::array::from_fn(|pixel| {
            let position = first + pixel;
            (
                ((position / out_width) * shape.stride) as isize - shape.padding_height as isize,
                ((position % out_width) * shape.stride) as isize - shape.padding_width as isize,
            )
        });
        PixelTile {
            first,
            count,
            origins,
        }
    }

    /// The input row (pixel) each pixel of the tile reads at kernel tap `(kernel_y,
    /// kernel_x)`, or `None` where the tap lies in the padding or the pixel is past `count`.
    pub fn rows(
        &self,
        shape: &ConvShape,
        kernel_y: usize,
        kernel_x: usize,
    ) -> [Option<usize>; PIXELS] {
        core::array::from_fn(|pixel| {
            let (top, left) = self.origins[pixel];
            let in_y = top + kernel_y as isize;
            let in_x = left + kernel_x as isize;
            let inside = pixel < self.count
                && (0..shape.in_height as isize).contains(&in_y)
                && (0..shape.in_width as isize).contains(&in_x);
            inside.then(|| in_y as usize * shape.in_width + in_x as usize)
        })
    }
}

/// Whether the SIMD int8 tiles apply: activations readable as u8, and whole input-channel
/// quads in each row (so a 4-byte activation load stays inside its pixel). The int8 layers
/// of the model all qualify; the stem (3 channels, kept f32 by the tool) would not.
pub(crate) fn tiles_apply(shape: &ConvShape, input: &QuantizedRows<'_>) -> bool {
    input.nonnegative && shape.in_channels.is_multiple_of(QUAD)
}

/// Runs `tile(pixels, channel, width)` over the whole output for each channel block, widest
/// of `widths` first (each a multiple of the next); channels left over go to the scalar
/// reference.
pub(crate) fn for_each_tile(
    shape: &ConvShape,
    input: &QuantizedRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
    widths: &[usize],
    mut tile: impl FnMut(&PixelTile, usize, usize, &mut [f32]),
) {
    let positions = shape.out_height() * shape.out_width();
    for first in (0..positions).step_by(PIXELS) {
        let pixels = PixelTile::new(shape, first, (positions - first).min(PIXELS));
        let mut channel = 0;
        for &width in widths {
            while channel + width <= shape.out_channels {
                tile(&pixels, channel, width, output);
                channel += width;
            }
        }
        if channel < shape.out_channels {
            conv_int8_pixels(
                shape,
                input,
                parameters,
                output,
                accumulate,
                first..first + pixels.count,
                channel..shape.out_channels,
            );
        }
    }
}

/// Channels of one AVX2 vector (eight i32 or f32 lanes; 32 weight bytes, one quad each).
pub(crate) const AVX2_LANES: usize = 8;

/// f32 totals of an AVX2 tile: `VECTORS` x 8 channels per pixel.
type Avx2Totals<const VECTORS: usize> = [[__m256; VECTORS]; PIXELS];

/// The f32 totals of the tile `pixels` x `VECTORS * 8` channels from `channel`.
///
/// Per quad and 8 output channels, `vpmaddubsw` multiplies the pixel's four activations (u8)
/// by the four weights (i8) and adds adjacent pairs into i16 lanes, `vpmaddwd` by ones adds
/// the two pairs into an i32 lane, `vpaddd` accumulates. `vpmaddubsw` saturates its i16 pair
/// sums; with activations in 0..=127 and weights in -127..=127 (the tool's range) a pair sum
/// lies within ±2 x 127 x 127 = ±32258, and even a weight of -128 (which no tool writes, but
/// a file may hold) gives at most 2 x 127 x 128 = 32512: inside i16's -32768..=32767, so
/// nothing saturates and the sums are exact. (An activation of -1 as i8 reads as 255 as u8
/// and could reach 2 x 255 x 127 = 64770: why negative rows never come here.) The i32 sum of a tap cannot overflow either:
/// 127 x 127 x in_channels < 2^31 up to 133,000 input channels.
///
/// # Safety
/// The CPU supports AVX2 and FMA; the slices have the lengths `shape` implies;
/// [`tiles_apply`] holds; `channel + VECTORS * 8 <= out_channels`; `pixels` is a tile of
/// this output.
#[target_feature(enable = "avx2,fma")]
unsafe fn avx2_tile<const VECTORS: usize>(
    shape: &ConvShape,
    input: &QuantizedRows<'_>,
    weight: &[i8],
    pixels: &PixelTile,
    channel: usize,
) -> Avx2Totals<VECTORS> {
    let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
    let quads = in_channels / QUAD;
    let ones = _mm256_set1_epi16(1);
    let mut totals = [[_mm256_setzero_ps(); VECTORS]; PIXELS];
    for kernel_y in 0..shape.kernel_height {
        for kernel_x in 0..shape.kernel_width {
            let rows = pixels.rows(shape, kernel_y, kernel_x);
            // A pixel off the input reads the first one on it; its sum is discarded below.
            let Some(&Some(any_row)) = rows.iter().find(|row| row.is_some()) else {
                continue;
            };
            let activations: [*const u8; PIXELS] = rows.map(|row| {
                input.values[row.unwrap_or(any_row) * in_channels..]
                    .as_ptr()
                    .cast::<u8>()
            });
            let tap = kernel_y * shape.kernel_width + kernel_x;
            let taps = &weight[int8_quad_index(in_channels, out_channels, tap, 0, channel)..];
            let mut sums = [[_mm256_setzero_si256(); VECTORS]; PIXELS];
            for quad in 0..quads {
                // SAFETY: the quad's `VECTORS * 32` weight bytes from `channel` lie inside the
                // tap (`channel + 8 VECTORS <= out_channels`); each pixel pointer starts a row
                // of `in_channels` values, a multiple of 4, so bytes 4 quad .. 4 quad + 4 are
                // inside it.
                unsafe {
                    let row = taps.as_ptr().add(quad * out_channels * QUAD);
                    let weights: [__m256i; VECTORS] = core::array::from_fn(|vector| {
                        _mm256_loadu_si256(row.add(vector * AVX2_LANES * QUAD).cast())
                    });
                    for (sum, &pixel) in sums.iter_mut().zip(&activations) {
                        let quad_bytes = pixel.add(quad * QUAD).cast::<i32>().read_unaligned();
                        let broadcast = _mm256_set1_epi32(quad_bytes);
                        for (sum, &weights) in sum.iter_mut().zip(&weights) {
                            let pairs = _mm256_maddubs_epi16(broadcast, weights);
                            *sum = _mm256_add_epi32(*sum, _mm256_madd_epi16(pairs, ones));
                        }
                    }
                }
            }
            for ((total, sum), row) in totals.iter_mut().zip(&sums).zip(rows) {
                let Some(row) = row else { continue };
                let scale = _mm256_set1_ps(input.scales[row]);
                for (total, &sum) in total.iter_mut().zip(sum) {
                    *total = _mm256_add_ps(*total, _mm256_mul_ps(_mm256_cvtepi32_ps(sum), scale));
                }
            }
        }
    }
    totals
}

/// `output (+)= totals * weight_scales + bias` for the tile's pixels, unfused as the scalar
/// reference does it.
///
/// # Safety
/// The CPU supports AVX2; `channel + VECTORS * 8 <= out_channels`; the tile's pixels are
/// inside `output`.
#[target_feature(enable = "avx2,fma")]
unsafe fn avx2_store<const VECTORS: usize>(
    totals: &Avx2Totals<VECTORS>,
    pixels: &PixelTile,
    (weight_scales, bias): (&[f32], &[f32]),
    output: &mut [f32],
    out_channels: usize,
    channel: usize,
    accumulate: Accumulate,
) {
    let width = VECTORS * AVX2_LANES;
    let weight_scales = &weight_scales[channel..channel + width];
    let bias = &bias[channel..channel + width];
    for (pixel, total) in totals.iter().enumerate().take(pixels.count) {
        let out = &mut output[(pixels.first + pixel) * out_channels + channel..][..width];
        for (vector, &total) in total.iter().enumerate() {
            let at = vector * AVX2_LANES;
            // SAFETY: `out`, `weight_scales` and `bias` hold `width` floats; each access
            // covers 8 from `at < width`.
            unsafe {
                let scaled = _mm256_mul_ps(total, _mm256_loadu_ps(weight_scales.as_ptr().add(at)));
                let mut value = _mm256_add_ps(scaled, _mm256_loadu_ps(bias.as_ptr().add(at)));
                if accumulate == Accumulate::Add {
                    value = _mm256_add_ps(_mm256_loadu_ps(out.as_ptr().add(at)), value);
                }
                _mm256_storeu_ps(out.as_mut_ptr().add(at), value);
            }
        }
    }
}

/// The AVX2 int8 convolution: tiles of 4 pixels x 16 channels, then 8, the rest scalar.
///
/// # Safety
/// The CPU supports AVX2 and FMA; the slice lengths are those
/// [`assert_int8_lengths`](crate::kernels::scalar::assert_int8_lengths) checks;
/// [`tiles_apply`] holds.
pub(crate) unsafe fn conv_int8_avx2(
    shape: &ConvShape,
    input: &QuantizedRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let out_channels = shape.out_channels;
    for_each_tile(
        shape,
        input,
        (weight, weight_scales, bias),
        output,
        accumulate,
        &[2 * AVX2_LANES, AVX2_LANES],
        |pixels, channel, width, output| {
            // SAFETY: the caller's promises, and `for_each_tile` hands out channel blocks of
            // `width` inside `out_channels` and tiles of this output.
            unsafe {
                if width == 2 * AVX2_LANES {
                    let totals = avx2_tile::<2>(shape, input, weight, pixels, channel);
                    let parameters = (weight_scales, bias);
                    avx2_store(
                        &totals,
                        pixels,
                        parameters,
                        output,
                        out_channels,
                        channel,
                        accumulate,
                    );
                } else {
                    let totals = avx2_tile::<1>(shape, input, weight, pixels, channel);
                    let parameters = (weight_scales, bias);
                    avx2_store(
                        &totals,
                        pixels,
                        parameters,
                        output,
                        out_channels,
                        channel,
                        accumulate,
                    );
                }
            }
        },
    );
}
