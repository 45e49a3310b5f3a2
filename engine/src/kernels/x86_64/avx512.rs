//! AVX-512 kernels: the int8 convolution with VNNI's `vpdpbusd`, which multiplies four u8
//! activations by four i8 weights and adds them into an i32 lane in one instruction, without
//! intermediate saturation (so exact for any activation in 0..=255, here 0..=127). A tile is
//! 4 pixels x 64 channels (16 i32 accumulators in ZMM registers, then 16 channels for the
//! rest); the tiling is that of [`super::int8`]. The f32 2-D convolution is
//! [`super::avx512_f32`]'s; every other kernel is the AVX2 one.

use core::arch::x86_64::{
    __m512, __m512i, _mm512_add_ps, _mm512_cvtepi32_ps, _mm512_dpbusd_epi32, _mm512_loadu_ps,
    _mm512_loadu_si512, _mm512_mul_ps, _mm512_set1_epi32, _mm512_set1_ps, _mm512_setzero_ps,
    _mm512_setzero_si512, _mm512_storeu_ps,
};

use super::avx2::Avx2;
use super::avx512_f32;
use super::int8::{PIXELS, PixelTile, for_each_tile, tiles_apply};
use crate::kernels::scalar::{
    Scalar, assert_conv_lengths, assert_conv_pixel_lengths, assert_int8_lengths,
};
use crate::kernels::{Accumulate, ConvShape, Kernels, QUAD, QuantizedRows, int8_quad_index};

/// Channels of one ZMM vector (16 i32 or f32 lanes; 64 weight bytes, one quad each).
const LANES: usize = 16;

/// AVX-512 F/BW/VL + VNNI kernels (and AVX2 + FMA). Reachable only through
/// [`Avx512::detect`], which checks the CPU.
#[derive(Debug)]
pub struct Avx512 {
    /// The AVX2 kernels the methods this backend does not specialize use.
    avx2: &'static Avx2,
}

static INSTANCE: Avx512 = Avx512 {
    avx2: &super::avx2::INSTANCE,
};

impl Avx512 {
    /// `None` unless the CPU and OS support AVX-512 F, BW, VL and VNNI, and AVX2 and FMA.
    pub fn detect() -> Option<&'static Avx512> {
        (super::has_avx512_vnni() && Avx2::detect().is_some()).then_some(&INSTANCE)
    }

    fn avx2(&self) -> &'static Avx2 {
        self.avx2
    }
}

/// f32 totals of a tile: `VECTORS` x 16 channels per pixel.
type Totals<const VECTORS: usize> = [[__m512; VECTORS]; PIXELS];

/// The f32 totals of the tile `pixels` x `VECTORS * 16` channels from `channel`.
///
/// # Safety
/// The CPU supports AVX-512 F, BW, VL and VNNI; the slices have the lengths `shape` implies;
/// [`tiles_apply`] holds; `channel + VECTORS * 16 <= out_channels`; `pixels` is a tile of
/// this output.
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vnni")]
unsafe fn tile<const VECTORS: usize>(
    shape: &ConvShape,
    input: &QuantizedRows<'_>,
    weight: &[i8],
    pixels: &PixelTile,
    channel: usize,
) -> Totals<VECTORS> {
    let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
    let quads = in_channels / QUAD;
    let mut totals = [[_mm512_setzero_ps(); VECTORS]; PIXELS];
    for kernel_y in 0..shape.kernel_height {
        for kernel_x in 0..shape.kernel_width {
            let rows = pixels.rows(shape, kernel_y, kernel_x);
            // A pixel off the input reads the first one on it; its sum is discarded below.
            let Some(&Some(any_row)) = rows.iter().find(|row| row.is_some()) else {
                continue;
            };
            let activations: [*const i8; PIXELS] =
                rows.map(|row| input.values[row.unwrap_or(any_row) * in_channels..].as_ptr());
            let tap = kernel_y * shape.kernel_width + kernel_x;
            let taps = &weight[int8_quad_index(in_channels, out_channels, tap, 0, channel)..];
            let mut sums = [[_mm512_setzero_si512(); VECTORS]; PIXELS];
            for quad in 0..quads {
                // SAFETY: the quad's `VECTORS * 64` weight bytes from `channel` lie inside the
                // tap (`channel + 16 VECTORS <= out_channels`); each pixel pointer starts a row
                // of `in_channels` values, a multiple of 4, so bytes 4 quad .. 4 quad + 4 are
                // inside it.
                unsafe {
                    let row = taps.as_ptr().add(quad * out_channels * QUAD);
                    let weights: [__m512i; VECTORS] = core::array::from_fn(|vector| {
                        _mm512_loadu_si512(row.add(vector * LANES * QUAD).cast())
                    });
                    for (sum, &pixel) in sums.iter_mut().zip(&activations) {
                        let quad_bytes = pixel.add(quad * QUAD).cast::<i32>().read_unaligned();
                        let broadcast = _mm512_set1_epi32(quad_bytes);
                        for (sum, &weights) in sum.iter_mut().zip(&weights) {
                            // Activations (u8, 0..=127) by weights (i8): exact i32.
                            *sum = _mm512_dpbusd_epi32(*sum, broadcast, weights);
                        }
                    }
                }
            }
            for ((total, sum), row) in totals.iter_mut().zip(&sums).zip(rows) {
                let Some(row) = row else { continue };
                let scale = _mm512_set1_ps(input.scales[row]);
                for (total, &sum) in total.iter_mut().zip(sum) {
                    *total = _mm512_add_ps(*total, _mm512_mul_ps(_mm512_cvtepi32_ps(sum), scale));
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
/// The CPU supports AVX-512 F; `channel + VECTORS * 16 <= out_channels`; the tile's pixels
/// are inside `output`.
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vnni")]
unsafe fn store<const VECTORS: usize>(
    totals: &Totals<VECTORS>,
    pixels: &PixelTile,
    (weight_scales, bias): (&[f32], &[f32]),
    output: &mut [f32],
    out_channels: usize,
    channel: usize,
    accumulate: Accumulate,
) {
    let width = VECTORS * LANES;
    let weight_scales = &weight_scales[channel..channel + width];
    let bias = &bias[channel..channel + width];
    for (pixel, total) in totals.iter().enumerate().take(pixels.count) {
        let out = &mut output[(pixels.first + pixel) * out_channels + channel..][..width];
        for (vector, &total) in total.iter().enumerate() {
            let at = vector * LANES;
            // SAFETY: `out`, `weight_scales` and `bias` hold `width` floats; each access
            // covers 16 from `at < width`.
            unsafe {
                let scaled = _mm512_mul_ps(total, _mm512_loadu_ps(weight_scales.as_ptr().add(at)));
                let mut value = _mm512_add_ps(scaled, _mm512_loadu_ps(bias.as_ptr().add(at)));
                if accumulate == Accumulate::Add {
                    value = _mm512_add_ps(_mm512_loadu_ps(out.as_ptr().add(at)), value);
                }
                _mm512_storeu_ps(out.as_mut_ptr().add(at), value);
            }
        }
    }
}

impl Kernels for Avx512 {
    fn name(&self) -> &'static str {
        "avx512"
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
        if !avx512_f32::covers(shape) {
            return self
                .avx2()
                .conv(shape, input, weight, bias, output, accumulate);
        }
        assert_conv_lengths(shape, (input, weight, bias), output.len());
        // SAFETY: `self` exists only when AVX-512F was detected; `covers` holds and the
        // asserts fix the lengths.
        unsafe { avx512_f32::conv(shape, (input, weight, bias), output, accumulate) }
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
        if !avx512_f32::covers(shape) {
            return self
                .avx2()
                .conv_pixel(shape, input, weight, bias, pixel, output);
        }
        assert_conv_pixel_lengths(shape, (input, weight, bias), pixel, output.len());
        // SAFETY: as in `conv`, and the pixel is inside the output.
        unsafe { avx512_f32::conv_pixel(shape, (input, weight, bias), pixel, output) }
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
        self.avx2().upsample_conv(
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
        self.avx2().matvec(weight, input, base, output)
    }

    fn conv_int8(
        &self,
        shape: &ConvShape,
        input: &QuantizedRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        assert_int8_lengths(shape, input, weight, weight_scales, bias, output);
        if !tiles_apply(shape, input) {
            return Scalar.conv_int8(
                shape,
                input,
                weight,
                weight_scales,
                bias,
                output,
                accumulate,
            );
        }
        let out_channels = shape.out_channels;
        for_each_tile(
            shape,
            input,
            (weight, weight_scales, bias),
            output,
            accumulate,
            &[4 * LANES, LANES],
            |pixels, channel, width, output| {
                let parameters = (weight_scales, bias);
                // SAFETY: `self` exists only when AVX-512 F/BW/VL/VNNI were detected; the
                // lengths were asserted and `tiles_apply` checked above; `for_each_tile`
                // hands out channel blocks of `width` inside `out_channels` and tiles of
                // this output.
                unsafe {
                    if width == 4 * LANES {
                        let totals = tile::<4>(shape, input, weight, pixels, channel);
                        store(
                            &totals,
                            pixels,
                            parameters,
                            output,
                            out_channels,
                            channel,
                            accumulate,
                        );
                    } else {
                        let totals = tile::<1>(shape, input, weight, pixels, channel);
                        store(
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

    fn conv_weight_int8(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        self.avx2().conv_weight_int8(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        )
    }

    fn matvec_weight_int8(
        &self,
        weight: &[i8],
        row_scales: &[f32],
        input: &[f32],
        base: &[f32],
        output: &mut [f32],
    ) {
        self.avx2()
            .matvec_weight_int8(weight, row_scales, input, base, output)
    }
}
