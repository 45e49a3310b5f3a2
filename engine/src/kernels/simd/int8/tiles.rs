//! The convolution body of both vector backends: tiles of `P` output positions by `V`
//! vectors of output channels, their exact sums held in registers across the whole kernel
//! (the parent module describes the scheme).

#[cfg(target_arch = "aarch64")]
use super::lanes::CenteredByteLanes;
use super::lanes::{Int8Lanes, SignedByteLanes, WholeByteLanes};
use crate::kernels::scalar::{CodeSums, conv_int8_pixel, conv_int8_pixels};
use crate::kernels::simd::prefetch_lines_into_l2;
use crate::kernels::{
    Accumulate, ByteRows, CodeRows, ConvShape, DigitRows, INT8_CHANNEL_BLOCK, MAX_DIGIT_CHANNELS,
    QUAD, SignedByteRows, int8_quad_stride,
};

/// Zero codes that a pixel whose kernel tap falls in the padding reads instead of an input
/// row (as digits: 2,048 zero bytes): a row of the widest input the kernels take.
pub(crate) static ZERO_ROW: [i16; MAX_DIGIT_CHANNELS] = [0; MAX_DIGIT_CHANNELS];

/// The pixels of one tile: how many there are (`count <= P`; the last tile of a map may be
/// short) and where they read.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PixelTile<const P: usize> {
    pub(crate) count: usize,
    /// Input coordinates of kernel tap (0, 0) per pixel, negative inside the padding.
    pub(crate) origins: [(isize, isize); P],
}

impl<const P: usize> PixelTile<P> {
    pub(crate) fn new(shape: &ConvShape, first: usize, count: usize) -> Self {
        let out_width = shape.out_width();
        let origins = core::array::from_fn(|pixel| {
            let position = first + pixel;
            (
                ((position / out_width) * shape.stride) as isize - shape.padding_height as isize,
                ((position % out_width) * shape.stride) as isize - shape.padding_width as isize,
            )
        });
        PixelTile { count, origins }
    }

    /// The input row (pixel) each pixel of the tile reads at kernel tap `(kernel_y,
    /// kernel_x)`, or `None` where the tap lies in the padding or the pixel is past `count`.
    pub(crate) fn rows(
        &self,
        shape: &ConvShape,
        kernel_y: usize,
        kernel_x: usize,
    ) -> [Option<usize>; P] {
        tap_rows(shape, &self.origins, self.count, (kernel_y, kernel_x))
    }
}

/// The input row (pixel) each of the first `count` pixels whose tap (0, 0) lies at
/// `origins` reads at kernel tap `(kernel_y, kernel_x)`: `None` in the padding and past
/// `count` (the AMX kernel's blocks too).
pub(crate) fn tap_rows<const P: usize>(
    shape: &ConvShape,
    origins: &[(isize, isize)],
    count: usize,
    (kernel_y, kernel_x): (usize, usize),
) -> [Option<usize>; P] {
    let mut rows = [None; P];
    for (row, &(top, left)) in rows.iter_mut().zip(origins).take(count) {
        let in_y = top + kernel_y as isize;
        let in_x = left + kernel_x as isize;
        let inside = (0..shape.in_height as isize).contains(&in_y)
            && (0..shape.in_width as isize).contains(&in_x);
        *row = inside.then(|| in_y as usize * shape.in_width + in_x as usize);
    }
    rows
}

/// Whether the SIMD int8 tiles apply: both digits readable as u8, and whole input-channel
/// quads in each row (so a 4-byte activation load stays inside its pixel). The int8 layers
/// of the model all qualify; the stem's 7x7 kernel over 3 channels would not, which is why it
/// runs over patches (`pyramid::stem`).
pub(crate) fn tiles_apply(shape: &ConvShape, input: &DigitRows<'_>) -> bool {
    input.nonnegative && shape.in_channels.is_multiple_of(QUAD)
}

/// `sums +` the exact i32 products of one kernel tap, both digit planes (high, then low):
/// `P` pixels (their activation rows in each plane) x `V` vectors of channels, over every
/// input-channel quad. The sums stay in registers for the whole quad loop, and each quad's
/// weights, loaded once, serve both planes: a loop per plane loaded them twice, the second
/// time from L1 (in-process A/B, encode 0.93-0.955x on AVX-512 VNNI, 0.90-1.01x on AVX2).
///
/// # Safety
/// The CPU supports `L`; each pointer in `activations` starts a row of `4 quads` readable
/// bytes; `weights` points at quad 0 of the tap's first channel of the block, with `quads`
/// quads, `quad_stride` bytes apart, of `V WIDTH` channels readable from there.
#[inline(always)]
unsafe fn add_digit_products<L: Int8Lanes, const P: usize, const V: usize>(
    mut sums: [[[L::Integers; V]; P]; 2],
    activations: [[*const i8; P]; 2],
    weights: *const i8,
    quads: usize,
    quad_stride: usize,
) -> [[[L::Integers; V]; P]; 2] {
    for quad in 0..quads {
        // SAFETY: quad `quad` of the block's channels and of each row is inside what the
        // caller vouched for.
        unsafe {
            let row = weights.add(quad * quad_stride);
            let vectors: [L::Integers; V] =
                core::array::from_fn(|vector| L::load_weights(row.add(vector * L::WIDTH * QUAD)));
            for pixel in 0..P {
                for plane in 0..2 {
                    let broadcast = L::broadcast_quad(activations[plane][pixel].add(quad * QUAD));
                    for vector in 0..V {
                        sums[plane][pixel][vector] =
                            L::dot_quads(sums[plane][pixel][vector], broadcast, vectors[vector]);
                    }
                }
            }
        }
    }
    sums
}

/// Quantized activations as the SIMD tiles on lanes `L` read them: the exact code sums of a
/// tile over the whole kernel, rounded and scaled, and (through [`CodeSums`]) the
/// reference's reading for what the tiles leave. Whole bytes are read only on
/// [`WholeByteLanes`].
pub(crate) trait TileInput<L: Int8Lanes>: CodeSums {
    /// `round(S) * scale` for `P` pixels x `V` vectors of channels from `channel`, `S` the
    /// exact code sums over every tap and input channel.
    ///
    /// # Safety
    /// The CPU supports `L`; the slices have the lengths `shape` implies; [`tiles_apply`]
    /// holds for digit planes; `pixels` is a tile of this output; the block's `V WIDTH`
    /// channels from `channel` are inside the output channels.
    unsafe fn tile_totals<const P: usize, const V: usize>(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        pixels: &PixelTile<P>,
        channel: usize,
    ) -> [[L::Floats; V]; P];
}

/// Where each of a tile's pixels reads at one kernel tap: its input row of `row_stride`
/// elements in `values`, or [`ZERO_ROW`] in the padding. `None` when no pixel reads the
/// input at this tap (nothing to add).
#[inline(always)]
fn tap_sources<T: Copy, const P: usize>(
    rows: [Option<usize>; P],
    values: &[T],
    row_stride: usize,
) -> Option<[*const T; P]> {
    rows.iter().any(Option::is_some).then(|| {
        rows.map(|row| match row {
            Some(row) => values[row * row_stride..][..row_stride].as_ptr(),
            None => ZERO_ROW.as_ptr().cast(),
        })
    })
}

/// Both digit planes' exact i32 sums over the whole kernel for a tile (exact:
/// [`MAX_DIGIT_TERMS`]), high then low. Each quad's weights serve both planes as they are
/// loaded; the tile is sized so both sets of sums stay in registers.
///
/// # Safety
/// As for [`TileInput::tile_totals`].
#[inline(always)]
unsafe fn digit_sums<L: Int8Lanes, const P: usize, const V: usize>(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    weight: &[i8],
    pixels: &PixelTile<P>,
    channel: usize,
) -> [[[L::Integers; V]; P]; 2] {
    let in_channels = shape.in_channels;
    let quad_stride = int8_quad_stride(shape.out_channels, channel);
    // SAFETY: the caller runs on `L`'s CPU.
    let mut sums = [[[unsafe { L::zero_integers() }; V]; P]; 2];
    for kernel_y in 0..shape.kernel_height {
        for kernel_x in 0..shape.kernel_width {
            let rows = pixels.rows(shape, kernel_y, kernel_x);
            let (Some(high), Some(low)) = (
                tap_sources(rows, input.high, in_channels),
                tap_sources(rows, input.low, in_channels),
            ) else {
                continue;
            };
            let tap = kernel_y * shape.kernel_width + kernel_x;
            let weights = weight[shape.int8_index(tap, 0, channel)..].as_ptr();
            let quads = in_channels / QUAD;
            // SAFETY: every source is an input row of `in_channels` = 4 quads values
            // (`tiles_apply`) or the zero row, as long; the tap's quads of the block's
            // channels are inside `weight` (the caller's promise).
            unsafe {
                sums =
                    add_digit_products::<L, P, V>(sums, [high, low], weights, quads, quad_stride);
            }
        }
    }
    sums
}

impl<L: Int8Lanes> TileInput<L> for DigitRows<'_> {
    /// Each digit plane summed over the whole kernel in i32 (exact: [`MAX_DIGIT_TERMS`]),
    /// the two combined exactly.
    #[inline(always)]
    unsafe fn tile_totals<const P: usize, const V: usize>(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        pixels: &PixelTile<P>,
        channel: usize,
    ) -> [[L::Floats; V]; P] {
        // SAFETY: the caller's promises, passed on.
        let [high, low] = unsafe { digit_sums::<L, P, V>(shape, self, weight, pixels, channel) };
        // Loops, not `array::from_fn`: a closure does not inherit the caller's target
        // features, and its intrinsics would become calls.
        // SAFETY: the caller runs on `L`'s CPU.
        let mut totals = [[unsafe { L::zero_floats() }; V]; P];
        for pixel in 0..P {
            for vector in 0..V {
                // SAFETY: the caller runs on `L`'s CPU.
                totals[pixel][vector] = unsafe {
                    let exact = L::exact_digits(high[pixel][vector], low[pixel][vector]);
                    L::round_scaled(exact, self.scale)
                };
            }
        }
        totals
    }
}

/// Whether the SIMD tiles apply to a convolution on whole bytes: whole input-channel quads
/// in each row, as for digits.
pub(crate) fn byte_tiles_apply(shape: &ConvShape) -> bool {
    shape.in_channels.is_multiple_of(QUAD)
}

impl<L: WholeByteLanes> TileInput<L> for ByteRows<'_> {
    /// One plane of whole bytes summed over the whole kernel in i32 (exact:
    /// [`MAX_BYTE_TERMS`](crate::kernels::MAX_BYTE_TERMS)): half the products of two digit
    /// planes, on lanes whose byte products take 0..=255.
    #[inline(always)]
    unsafe fn tile_totals<const P: usize, const V: usize>(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        pixels: &PixelTile<P>,
        channel: usize,
    ) -> [[L::Floats; V]; P] {
        let in_channels = shape.in_channels;
        let quads = in_channels / QUAD;
        let quad_stride = int8_quad_stride(shape.out_channels, channel);
        let bytes: &[i8] = bytemuck::cast_slice(self.bytes);
        // SAFETY: the caller runs on `L`'s CPU.
        let mut sums = [[unsafe { L::zero_integers() }; V]; P];
        for kernel_y in 0..shape.kernel_height {
            for kernel_x in 0..shape.kernel_width {
                let rows = pixels.rows(shape, kernel_y, kernel_x);
                let Some(sources) = tap_sources(rows, bytes, in_channels) else {
                    continue;
                };
                let tap = kernel_y * shape.kernel_width + kernel_x;
                let weights = weight[shape.int8_index(tap, 0, channel)..].as_ptr();
                // SAFETY: every source is an input row of `quads` whole quads
                // (`byte_tiles_apply`) or the zero row, as long; the tap's quads of the
                // block's channels are inside `weight` (the caller's promise).
                unsafe {
                    for quad in 0..quads {
                        let row = weights.add(quad * quad_stride);
                        let vectors: [L::Integers; V] = core::array::from_fn(|vector| {
                            L::load_weights(row.add(vector * L::WIDTH * QUAD))
                        });
                        for pixel in 0..P {
                            let broadcast = L::broadcast_quad(sources[pixel].add(quad * QUAD));
                            for vector in 0..V {
                                sums[pixel][vector] =
                                    L::dot_quads(sums[pixel][vector], broadcast, vectors[vector]);
                            }
                        }
                    }
                }
            }
        }
        // SAFETY: the caller runs on `L`'s CPU.
        let mut totals = [[unsafe { L::zero_floats() }; V]; P];
        for pixel in 0..P {
            for vector in 0..V {
                // SAFETY: the caller runs on `L`'s CPU.
                totals[pixel][vector] =
                    unsafe { L::integers_scaled(sums[pixel][vector], self.scale) };
            }
        }
        totals
    }
}

/// Whole bytes for lanes whose products are signed by signed (`sdot`): each byte is read
/// centred, `byte - 128`, at every tap, the padding's zero bytes included (so every pixel
/// reads every tap), and `128 sum w` over the whole kernel, the same for every pixel, is
/// added back: `sum (b - 128) w + 128 sum w`, the exact `sum b w`, in one plane where the
/// digits take two.
#[cfg(target_arch = "aarch64")]
#[derive(Clone, Copy, Debug)]
pub(crate) struct CenteredBytes<'a> {
    pub bytes: ByteRows<'a>,
    /// `128 sum w` over every tap and input channel, one per output channel.
    pub weight_shares: &'a [i32],
}

#[cfg(target_arch = "aarch64")]
impl CodeSums for CenteredBytes<'_> {
    fn code_sums(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        row_tap: (usize, usize),
        block: usize,
        width: usize,
    ) -> [i32; INT8_CHANNEL_BLOCK] {
        self.bytes.code_sums(shape, weight, row_tap, block, width)
    }

    fn scale(&self) -> f32 {
        self.bytes.scale
    }
}

#[cfg(target_arch = "aarch64")]
impl<L: CenteredByteLanes> TileInput<L> for CenteredBytes<'_> {
    /// The centred bytes' sums over every tap in i32 (exact: at most
    /// [`MAX_BYTE_TERMS`](crate::kernels::MAX_BYTE_TERMS) products of 128 x 128), plus the
    /// weights' share.
    #[inline(always)]
    unsafe fn tile_totals<const P: usize, const V: usize>(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        pixels: &PixelTile<P>,
        channel: usize,
    ) -> [[L::Floats; V]; P] {
        let in_channels = shape.in_channels;
        let quads = in_channels / QUAD;
        let quad_stride = int8_quad_stride(shape.out_channels, channel);
        let bytes: &[i8] = bytemuck::cast_slice(self.bytes.bytes);
        // SAFETY: the caller runs on `L`'s CPU.
        let mut sums = [[unsafe { L::zero_integers() }; V]; P];
        for kernel_y in 0..shape.kernel_height {
            for kernel_x in 0..shape.kernel_width {
                // Padding reads the zero row, centred to -128 like any zero byte.
                let sources = pixels.rows(shape, kernel_y, kernel_x).map(|row| match row {
                    Some(row) => bytes[row * in_channels..][..in_channels].as_ptr(),
                    None => ZERO_ROW.as_ptr().cast(),
                });
                let tap = kernel_y * shape.kernel_width + kernel_x;
                let weights = weight[shape.int8_index(tap, 0, channel)..].as_ptr();
                // SAFETY: every source is an input row of `quads` whole quads
                // (`byte_tiles_apply`) or the zero row, as long; the tap's quads of the
                // block's channels are inside `weight` (the caller's promise).
                unsafe {
                    for quad in 0..quads {
                        let row = weights.add(quad * quad_stride);
                        let vectors: [L::Integers; V] = core::array::from_fn(|vector| {
                            L::load_weights(row.add(vector * L::WIDTH * QUAD))
                        });
                        for pixel in 0..P {
                            let centred =
                                L::broadcast_centred_quad(sources[pixel].add(quad * QUAD));
                            for vector in 0..V {
                                sums[pixel][vector] =
                                    L::dot_quads(sums[pixel][vector], centred, vectors[vector]);
                            }
                        }
                    }
                }
            }
        }
        // SAFETY: the caller runs on `L`'s CPU; the block's `V WIDTH` channels from
        // `channel` are inside the output, so inside `weight_shares`.
        unsafe {
            let shares: [L::Integers; V] = core::array::from_fn(|vector| {
                L::load_integers(
                    self.weight_shares[channel + vector * L::WIDTH..][..L::WIDTH].as_ptr(),
                )
            });
            let mut totals = [[L::zero_floats(); V]; P];
            for pixel in 0..P {
                for vector in 0..V {
                    let sum = L::add_integers(sums[pixel][vector], shares[vector]);
                    totals[pixel][vector] = L::integers_scaled(sum, self.bytes.scale);
                }
            }
            totals
        }
    }
}

/// Quad rows of weights [`CodeRows`]' tiles ask L2 for ahead of the one they read (64: 16
/// KB for the AVX-512 tile; with 16 rows into L1 the int8 denoising loop took
/// 1.17-1.19x as long on Zen 4, whose L3 is small enough for the stream to matter).
pub(crate) const PREFETCH_QUADS: usize = 64;

/// The codes times the widened weights, two lanes a channel, added up per tap in i32
/// (exact: [`MAX_DIGIT_CHANNELS`]), the taps' sums in f64 (exact), rounded and scaled.
///
/// # Safety
/// As for [`TileInput::tile_totals`]; `codes` are rows of `CodeRows::row_stride(in)`.
#[inline(always)]
unsafe fn pair_totals<L: Int8Lanes, const P: usize, const V: usize>(
    shape: &ConvShape,
    (codes, scale): (&[i16], f32),
    weight: &[i8],
    pixels: &PixelTile<P>,
    channel: usize,
) -> [[L::Floats; V]; P] {
    let row_stride = CodeRows::row_stride(shape.in_channels);
    let quads = row_stride / QUAD;
    let quad_stride = int8_quad_stride(shape.out_channels, channel);
    // SAFETY: the caller runs on `L`'s CPU.
    let mut totals = [[unsafe { L::zero_exact() }; V]; P];
    for kernel_y in 0..shape.kernel_height {
        for kernel_x in 0..shape.kernel_width {
            let rows = pixels.rows(shape, kernel_y, kernel_x);
            let Some(sources) = tap_sources(rows, codes, row_stride) else {
                continue;
            };
            let tap = kernel_y * shape.kernel_width + kernel_x;
            let weights = weight[shape.int8_index(tap, 0, channel)..].as_ptr();
            // SAFETY: every source holds `quads` whole quads of codes (padded rows, or the
            // zero row, at least as long); the tap's (zero-padded) quads of the block are
            // readable: the caller's promises.
            unsafe {
                // Per pixel and vector: the halves of its channels (lane pairs).
                let mut sums = [[(L::zero_integers(), L::zero_integers()); V]; P];
                for quad in 0..quads {
                    let row = weights.add(quad * quad_stride);
                    // The U-Net's weights come from L3 once per step, a quad row's
                    // `V WIDTH` channels (one or two cache lines) `quad_stride` bytes apart:
                    // ask L2 for the lines `PREFETCH_QUADS` rows ahead. A hint only (it
                    // never faults), hence the wrapping address.
                    let ahead = row.wrapping_add(PREFETCH_QUADS * quad_stride);
                    prefetch_lines_into_l2(ahead, V * L::WIDTH * QUAD);
                    let halves: [(L::Integers, L::Integers); V] = core::array::from_fn(|vector| {
                        let first = row.add(vector * L::WIDTH * QUAD);
                        (
                            L::widen_quads(first),
                            L::widen_quads(first.add(L::WIDTH * QUAD / 2)),
                        )
                    });
                    for pixel in 0..P {
                        let broadcast = L::broadcast_codes(sources[pixel].add(quad * QUAD));
                        for vector in 0..V {
                            let (low, high) = &mut sums[pixel][vector];
                            *low = L::dot_code_pairs(*low, broadcast, halves[vector].0);
                            *high = L::dot_code_pairs(*high, broadcast, halves[vector].1);
                        }
                    }
                }
                for pixel in 0..P {
                    for vector in 0..V {
                        let (low, high) = sums[pixel][vector];
                        let total = &mut totals[pixel][vector];
                        *total = L::add_exact(*total, L::add_lane_pairs(low, high));
                    }
                }
            }
        }
    }
    // SAFETY: the caller runs on `L`'s CPU.
    let mut rounded = [[unsafe { L::zero_floats() }; V]; P];
    for pixel in 0..P {
        for vector in 0..V {
            // SAFETY: the caller runs on `L`'s CPU.
            rounded[pixel][vector] = unsafe { L::round_scaled(totals[pixel][vector], scale) };
        }
    }
    rounded
}

impl<L: Int8Lanes> TileInput<L> for CodeRows<'_> {
    /// [`pair_totals`] of the 15-bit codes.
    #[inline(always)]
    unsafe fn tile_totals<const P: usize, const V: usize>(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        pixels: &PixelTile<P>,
        channel: usize,
    ) -> [[L::Floats; V]; P] {
        // SAFETY: the caller's promises, passed on.
        unsafe { pair_totals::<L, P, V>(shape, (self.codes, self.scale), weight, pixels, channel) }
    }
}

impl<L: SignedByteLanes> TileInput<L> for SignedByteRows<'_> {
    /// The weights offset by `WEIGHT_OFFSET` (128: unsigned; or none) times the signed
    /// codes, summed over the whole kernel in i32 (exact: at most
    /// [`MAX_BYTE_TERMS`](crate::kernels::MAX_BYTE_TERMS) products of 255 x 127), less the
    /// offset times the codes the pixel read (its rows' sums): `sum (w + 128) c - 128 sum c`,
    /// the exact `sum w c`, in half the products of widened pairs.
    #[inline(always)]
    unsafe fn tile_totals<const P: usize, const V: usize>(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        pixels: &PixelTile<P>,
        channel: usize,
    ) -> [[L::Floats; V]; P] {
        let row_stride = CodeRows::row_stride(shape.in_channels);
        let quads = row_stride / QUAD;
        let quad_stride = int8_quad_stride(shape.out_channels, channel);
        // SAFETY: the caller runs on `L`'s CPU.
        let mut sums = [[unsafe { L::zero_integers() }; V]; P];
        let mut codes_read = [0i32; P];
        for kernel_y in 0..shape.kernel_height {
            for kernel_x in 0..shape.kernel_width {
                let rows = pixels.rows(shape, kernel_y, kernel_x);
                let Some(sources) = tap_sources(rows, self.codes, row_stride) else {
                    continue;
                };
                for (read, row) in codes_read.iter_mut().zip(rows) {
                    *read += row.map_or(0, |row| self.row_sums[row]);
                }
                let tap = kernel_y * shape.kernel_width + kernel_x;
                let weights = weight[shape.int8_index(tap, 0, channel)..].as_ptr();
                // SAFETY: every source holds `quads` whole quads of codes (padded rows, or
                // the zero row, at least as long); the tap's (zero-padded) quads of the
                // block are readable: the caller's promises.
                unsafe {
                    for quad in 0..quads {
                        let row = weights.add(quad * quad_stride);
                        // As in `pair_totals`: the weights come from L3 at every step.
                        let ahead = row.wrapping_add(PREFETCH_QUADS * quad_stride);
                        prefetch_lines_into_l2(ahead, V * L::WIDTH * QUAD);
                        let vectors: [L::Integers; V] = core::array::from_fn(|vector| {
                            L::offset_bytes(L::load_weights(row.add(vector * L::WIDTH * QUAD)))
                        });
                        for pixel in 0..P {
                            let broadcast = L::broadcast_quad(sources[pixel].add(quad * QUAD));
                            for vector in 0..V {
                                sums[pixel][vector] =
                                    L::dot_quads(sums[pixel][vector], vectors[vector], broadcast);
                            }
                        }
                    }
                }
            }
        }
        // SAFETY: the caller runs on `L`'s CPU.
        let mut totals = [[unsafe { L::zero_floats() }; V]; P];
        for pixel in 0..P {
            // At most 127 x MAX_BYTE_TERMS x 128 in magnitude: no overflow.
            // SAFETY: the caller runs on `L`'s CPU.
            let offset = unsafe { L::splat_integers(-L::WEIGHT_OFFSET * codes_read[pixel]) };
            for vector in 0..V {
                // SAFETY: the caller runs on `L`'s CPU.
                totals[pixel][vector] = unsafe {
                    L::integers_scaled(L::add_integers(sums[pixel][vector], offset), self.scale)
                };
            }
        }
        totals
    }
}

/// `out (+)= totals * weight_scales + bias` for `count` pixels whose channel blocks start
/// at `out[pixel * stride]`, unfused as the scalar reference does it.
///
/// # Safety
/// The CPU supports `L`; `weight_scales` and `bias` hold `V WIDTH` floats; `out` holds the
/// `V WIDTH` channels of each of the `count` pixels, `stride` apart.
#[inline(always)]
pub(crate) unsafe fn store<L: Int8Lanes, const P: usize, const V: usize>(
    totals: &[[L::Floats; V]; P],
    count: usize,
    (weight_scales, bias): (&[f32], &[f32]),
    out: &mut [f32],
    stride: usize,
    accumulate: Accumulate,
) {
    for (pixel, total) in totals.iter().enumerate().take(count) {
        let out = &mut out[pixel * stride..][..V * L::WIDTH];
        for (vector, &total) in total.iter().enumerate() {
            let at = vector * L::WIDTH;
            // SAFETY: `out`, `weight_scales` and `bias` hold `V WIDTH` floats; each access
            // covers WIDTH from `at`; the caller runs on `L`'s CPU.
            unsafe {
                let scaled = L::mul(total, L::load(weight_scales.as_ptr().add(at)));
                let mut value = L::add(scaled, L::load(bias.as_ptr().add(at)));
                if accumulate == Accumulate::Add {
                    value = L::add(L::load(out.as_ptr().add(at)), value);
                }
                L::store(out.as_mut_ptr().add(at), value);
            }
        }
    }
}

/// The channel blocks of `V WIDTH` channels from `*channel` while they fit, each over
/// every pixel tile of the output; advances `*channel` past them.
///
/// # Safety
/// As for [`conv`].
#[inline(always)]
unsafe fn channel_blocks<L: Int8Lanes, I: TileInput<L>, const P: usize, const V: usize>(
    shape: &ConvShape,
    input: &I,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
    channel: &mut usize,
) {
    // A block reads its quads `quad_stride` apart, which holds inside one block of the
    // weight layout: blocks from a multiple of their width never straddle one.
    const { assert!(INT8_CHANNEL_BLOCK.is_multiple_of(V * L::WIDTH)) };
    let out_channels = shape.out_channels;
    let positions = shape.out_height() * shape.out_width();
    let width = V * L::WIDTH;
    while *channel + width <= out_channels {
        let block = *channel..*channel + width;
        for first in (0..positions).step_by(P) {
            let pixels = PixelTile::<P>::new(shape, first, (positions - first).min(P));
            // SAFETY: the caller's promises; the block and the tile are inside the output.
            unsafe {
                let totals = input.tile_totals::<P, V>(shape, weight, &pixels, *channel);
                let out = &mut output[first * out_channels + *channel..];
                let parameters = (&weight_scales[block.clone()], &bias[block.clone()]);
                store::<L, P, V>(
                    &totals,
                    pixels.count,
                    parameters,
                    out,
                    out_channels,
                    accumulate,
                );
            }
        }
        *channel += width;
    }
}

/// The whole int8 convolution: blocks of `V` vectors of channels, then single vectors, the
/// channels left over on the scalar reference.
///
/// # Safety
/// The CPU supports `L`; the slice lengths are those
/// [`assert_int8_lengths`](crate::kernels::scalar::assert_int8_lengths) (or, for codes,
/// `assert_code_lengths`) checks; [`tiles_apply`] holds for digit planes.
#[inline(always)]
pub(crate) unsafe fn conv<L: Int8Lanes, I: TileInput<L>, const P: usize, const V: usize>(
    shape: &ConvShape,
    input: &I,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let mut channel = 0;
    // SAFETY: this function's contract is theirs.
    unsafe {
        channel_blocks::<L, I, P, V>(shape, input, parameters, output, accumulate, &mut channel);
        channel_blocks::<L, I, P, 1>(shape, input, parameters, output, accumulate, &mut channel);
    }
    if channel < shape.out_channels {
        let positions = shape.out_height() * shape.out_width();
        conv_int8_pixels(
            shape,
            input,
            parameters,
            output,
            accumulate,
            0..positions,
            channel..shape.out_channels,
        );
    }
}

/// Output pixel `(out_y, out_x)` of [`conv`] (overwriting) into `output` (its
/// `out_channels` values): the one-pixel tile, so the same bits.
///
/// # Safety
/// As for [`conv`]; the pixel is in the output and `output` holds its channels.
#[inline(always)]
pub(crate) unsafe fn conv_pixel<L: Int8Lanes, const V: usize>(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    (out_y, out_x): (usize, usize),
    output: &mut [f32],
) {
    let pixels = PixelTile::<1>::new(shape, out_y * shape.out_width() + out_x, 1);
    let out_channels = shape.out_channels;
    let overwrite = Accumulate::Overwrite;
    let mut channel = 0;
    while channel < out_channels {
        let block = channel..out_channels;
        let parameters = (&weight_scales[block.clone()], &bias[block.clone()]);
        let out = &mut output[channel..];
        // SAFETY: the caller's promises; each block is inside `out_channels`.
        unsafe {
            if channel + V * L::WIDTH <= out_channels {
                let totals =
                    TileInput::<L>::tile_totals::<1, V>(input, shape, weight, &pixels, channel);
                store::<L, 1, V>(&totals, 1, parameters, out, 0, overwrite);
                channel += V * L::WIDTH;
            } else if channel + L::WIDTH <= out_channels {
                let totals =
                    TileInput::<L>::tile_totals::<1, 1>(input, shape, weight, &pixels, channel);
                store::<L, 1, 1>(&totals, 1, parameters, out, 0, overwrite);
                channel += L::WIDTH;
            } else {
                break;
            }
        }
    }
    if channel < out_channels {
        conv_int8_pixel(
            shape,
            input,
            (weight, weight_scales, bias),
            output,
            overwrite,
            (out_y, out_x),
            channel..out_channels,
        );
    }
}
