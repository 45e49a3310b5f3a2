//! Element-wise and normalization operations over channels-last data: one portable
//! implementation, which the SIMD backends compile again with their vector width (the
//! functions are `#[inline(always)]` so the backends' `#[target_feature]` wrappers get their
//! own copy; see [`Kernels::group_norm`](super::Kernels::group_norm)). Every operation keeps
//! its order of floating-point operations whatever the width (no reassociation, no fused
//! multiply-add), so every backend gives the same bits.

/// The activation applied after a normalization.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Activation {
    None,
    Relu,
    Mish,
}

/// PyTorch's GroupNorm epsilon and BatchNorm epsilon.
pub const NORM_EPSILON: f64 = 1e-5;

/// `x tanh(softplus(x))`, with PyTorch's softplus threshold (x above 20 is returned as is).
///
/// `tanh(ln(1 + e^x)) = n / (n + 2)` with `n = e^x (e^x + 2)`: one exponential instead of
/// exp, log1p and tanh.
#[inline(always)]
pub fn mish(x: f32) -> f32 {
    if x > 20.0 {
        return x;
    }
    let e = exp(x);
    let n = e * (e + 2.0);
    x * n / (n + 2.0)
}

/// `e^x` within 2 ulp of the exact value for x in -87.3..=88, branch-free so that loops of
/// it vectorize (`libm::expf` is a call per value; Mish after every U-Net GroupNorm made it
/// a tenth of the denoising loop). Arguments outside that range are clamped to it (Mish only
/// needs it up to 20; below -87.3 the result is tiny either way); NaN stays NaN.
///
/// `x = n ln 2 + r` with `n` the nearest integer to `x / ln 2` and |r| <= ln 2 / 2; `ln 2` is
/// split in two (Cody and Waite) so `r` is exact enough; `e^r` is Cephes' degree-6
/// polynomial; `2^n` is built in the exponent bits.
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    // 1.5 x 2^23: adding it rounds to an integer (ties to even), which then sits in the low
    // mantissa bits, so the integer is read from the bits: no float-to-int conversion.
    const ROUNDER: f32 = 12_582_912.0;
    const LOG2_E: f32 = core::f32::consts::LOG2_E;
    const LN2_HIGH: f32 = 0.693_359_4;
    const LN2_LOW: f32 = -2.121_944_4e-4;
    let x = x.clamp(-87.3, 88.0);
    let shifted = x * LOG2_E + ROUNDER;
    let n = shifted - ROUNDER;
    let exponent = (shifted.to_bits() as i32).wrapping_sub(ROUNDER.to_bits() as i32);
    let r = x - n * LN2_HIGH - n * LN2_LOW;
    let polynomial =
        ((((1.987_569_2e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
            + 1.666_666_5e-1)
            * r
            + 0.5;
    let e_r = polynomial * (r * r) + r + 1.0;
    let power = f32::from_bits((exponent.wrapping_add(127) as u32) << 23);
    e_r * power
}

#[inline(always)]
pub fn activate(x: f32, activation: Activation) -> f32 {
    match activation {
        Activation::None => x,
        Activation::Relu => x.max(0.0),
        Activation::Mish => mish(x),
    }
}

pub fn activate_all(data: &mut [f32], activation: Activation) {
    if activation != Activation::None {
        data.iter_mut().for_each(|x| *x = activate(*x, activation));
    }
}

/// GroupNorm over `[positions, channels]` (groups of consecutive channels, statistics over
/// all positions), then the affine transform and `activation`, in place. Two-pass mean and
/// variance in f64 accumulators: the trunk's groups hold up to 300k values.
#[inline(always)]
pub fn group_norm(
    data: &mut [f32],
    channels: usize,
    groups: usize,
    gamma: &[f32],
    beta: &[f32],
    activation: Activation,
) {
    // Groups are processed a chunk at a time (whole groups, at most `CHANNELS` channels, or
    // one group, a block of `CHANNELS` at a time, if it is wider), each pass walking the
    // data in memory order.
    let group_size = channels / groups;
    let count = ((data.len() / channels) * group_size) as f64;
    let groups_per_chunk = (CHANNELS / group_size).max(1);
    for first_group in (0..groups).step_by(groups_per_chunk) {
        let chunk_groups = (groups - first_group).min(groups_per_chunk);
        let first = first_group * group_size;
        let width = chunk_groups * group_size;
        let span = first..first + width;
        // One pass for both moments, in f64: a square of an f32 is exact in f64, and the sums
        // of up to a few hundred thousand of them lose ~1e-11 of their value, so the
        // variance `E[x^2] - E[x]^2` keeps f32 precision unless the mean is ~1e4 standard
        // deviations from zero (no normalization input is). A second pass over the data for
        // the centred squares cost a third of GroupNorm's memory traffic.
        let mut mean = [0.0f64; CHANNELS];
        let mut inverse_std = [0.0f64; CHANNELS];
        moments_per_group(
            data,
            channels,
            span,
            group_size,
            (&mut mean, &mut inverse_std),
        );
        for (mean, squares) in mean[..chunk_groups]
            .iter_mut()
            .zip(&mut inverse_std[..chunk_groups])
        {
            (*mean, *squares) = mean_inverse_std((*mean, *squares), count);
        }
        let mut scale = [0.0f32; CHANNELS];
        let mut shift = [0.0f32; CHANNELS];
        for start in (0..width).step_by(CHANNELS) {
            let len = (width - start).min(CHANNELS);
            let channels_of = first + start..first + start + len;
            let per_group = scale[..len]
                .chunks_mut(group_size)
                .zip(shift[..len].chunks_mut(group_size))
                .zip(gamma[channels_of.clone()].chunks(group_size))
                .zip(beta[channels_of].chunks(group_size));
            for (group, (((scale, shift), gamma), beta)) in (start / group_size..).zip(per_group) {
                let moments = (mean[group], inverse_std[group]);
                channel_affine(moments, (gamma, beta), (scale, shift));
            }
            for pixel in data.chunks_exact_mut(channels) {
                let values = &mut pixel[first + start..first + start + len];
                for ((x, &a), &b) in values.iter_mut().zip(&scale[..len]).zip(&shift[..len]) {
                    *x = activate(*x * a + b, activation);
                }
            }
        }
    }
}

/// `x.sqrt()`, correctly rounded as IEEE 754 defines it (so the same bits whichever way).
/// On x86-64 through the SSE2 intrinsic, which the compiler encodes for the caller's target
/// features (VEX inside the AVX backends): `libm::sqrt` is an inline `sqrtsd` there, and
/// that legacy encoding among AVX-512 instructions (an SSE/AVX transition each time) took
/// half of the U-Net's GroupNorm, whose eight groups a call each take one.
#[inline(always)]
fn sqrt(x: f64) -> f64 {
    #[cfg(target_arch = "x86_64")]
    {
        use core::arch::x86_64::{_mm_cvtsd_f64, _mm_set_sd, _mm_sqrt_pd};
        // SAFETY: SSE2 is part of x86-64; the intrinsics touch no memory.
        unsafe { _mm_cvtsd_f64(_mm_sqrt_pd(_mm_set_sd(x))) }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        libm::sqrt(x)
    }
}

/// Channels (and at most as many groups) [`group_norm`] handles at once: its per-channel
/// buffers live on the stack.
const CHANNELS: usize = 256;

/// Channels whose moments [`moments_per_group`] sums in one walk over the pixels: 32 f64
/// sums and as many sums of squares, eight ZMM registers.
const MOMENT_LANES: usize = 32;

/// Adds to `sums[g]` and `squares[g]`, for each group `g` of the channels `span`
/// (`group_size` channels each), the sum of the group's values and of their squares, in
/// f64. `span` is whole groups of at most [`CHANNELS`] channels, or one group. Sums are kept
/// per channel, one f64 lane each, adding the pixels in memory order, and only then folded
/// into their groups in channel order: the per-pixel loop is element-wise and vectorizes.
/// (Summing each group's channels inside every pixel was a dependent chain; with it,
/// GroupNorm cost as much as the VNNI convolutions of the int8 trunk.) The groups are
/// walked a chunk of `group_size` channels at a time: a division per channel to find its
/// group was most of the U-Net's GroupNorm, whose maps have 4 to 16 positions.
#[inline(always)]
fn moments_per_group(
    data: &[f32],
    channels: usize,
    span: core::ops::Range<usize>,
    group_size: usize,
    (sums, squares): (&mut [f64], &mut [f64]),
) {
    let mut channel_sums = [0.0f64; CHANNELS];
    let mut channel_squares = [0.0f64; CHANNELS];
    for start in span.clone().step_by(CHANNELS) {
        let len = (span.end - start).min(CHANNELS);
        // The block's first group: whole groups start at the span's start; a block of one
        // wide group lies inside group 0 of the span.
        let first_group = (start - span.start) / group_size;
        let channel_sums = &mut channel_sums[..len];
        let channel_squares = &mut channel_squares[..len];
        channel_sums.fill(0.0);
        channel_squares.fill(0.0);
        let span = start..start + len;
        add_block_moments(
            data,
            channels,
            span,
            (&mut *channel_sums, &mut *channel_squares),
        );
        let per_group = channel_sums
            .chunks(group_size)
            .zip(channel_squares.chunks(group_size))
            .zip(
                sums[first_group..]
                    .iter_mut()
                    .zip(&mut squares[first_group..]),
            );
        for ((channel_sums, channel_squares), (sum, square)) in per_group {
            channel_sums
                .iter()
                .for_each(|&channel_sum| *sum += channel_sum);
            channel_squares
                .iter()
                .for_each(|&channel_square| *square += channel_square);
        }
    }
}

/// Positions whose moments [`group_norm`] sums on their own before adding them to the
/// map's: a map's moments are the same sums whichever way its blocks are shared out, so
/// several workers can each measure their own blocks ([`add_channel_moments`]).
pub const MOMENT_BLOCK: usize = 64;

/// Adds each channel's sum and sum of squares over the pixels of `data` (`[positions,
/// channels]`) to `sums[c]` and `squares[c]`, in f64: [`group_norm`]'s per-channel moments.
/// Each block of [`MOMENT_BLOCK`] pixels from `data`'s start is summed from zero in memory
/// order, then added to the sums, blocks in order; so a map's bands passed in order make
/// the same additions as the whole map when each band but the last holds whole blocks, as
/// do its blocks' sums taken apart and added in order, and [`group_scale_shift`] then gives
/// [`group_norm`]'s bits. Lets a map be measured band by band while each band is still in
/// the caches, or its blocks by several workers.
#[inline(always)]
pub fn add_channel_moments(
    data: &[f32],
    channels: usize,
    (sums, squares): (&mut [f64], &mut [f64]),
) {
    for start in (0..channels).step_by(CHANNELS) {
        let span = start..(start + CHANNELS).min(channels);
        let moments = (&mut sums[span.clone()], &mut squares[span.clone()]);
        add_block_moments(data, channels, span, moments);
    }
}

/// [`add_span_moments`] a block of [`MOMENT_BLOCK`] pixels at a time, each block's sums
/// from zero, then added to `sums` and `squares` (at most [`CHANNELS`] channels).
#[inline(always)]
fn add_block_moments(
    data: &[f32],
    channels: usize,
    span: core::ops::Range<usize>,
    (sums, squares): (&mut [f64], &mut [f64]),
) {
    let len = span.len();
    let mut block_sums = [0.0f64; CHANNELS];
    let mut block_squares = [0.0f64; CHANNELS];
    let (block_sums, block_squares) = (&mut block_sums[..len], &mut block_squares[..len]);
    for block in data.chunks(MOMENT_BLOCK * channels) {
        block_sums.fill(0.0);
        block_squares.fill(0.0);
        add_span_moments(block, channels, span.clone(), (block_sums, block_squares));
        for (sum, &block_sum) in sums[..len].iter_mut().zip(&*block_sums) {
            *sum += block_sum;
        }
        for (square, &block_square) in squares[..len].iter_mut().zip(&*block_squares) {
            *square += block_square;
        }
    }
}

/// `activation(x * scale + shift)` per channel over `[positions, channels]` `data`, in place:
/// [`group_norm`]'s last step, the same arithmetic, for a map whose moments were taken apart
/// ([`add_channel_moments`], [`group_scale_shift`]).
#[inline(always)]
pub fn affine_activate(
    data: &mut [f32],
    channels: usize,
    (scale, shift): (&[f32], &[f32]),
    activation: Activation,
) {
    let (scale, shift) = (&scale[..channels], &shift[..channels]);
    for pixel in data.chunks_exact_mut(channels) {
        for ((x, &a), &b) in pixel.iter_mut().zip(scale).zip(shift) {
            *x = activate(*x * a + b, activation);
        }
    }
}

/// Adds, for each channel `span.start + c` of `data`'s pixels (`channels` values each), the
/// sum of its values and of their squares to `sums[c]` and `squares[c]`, in f64, pixels in
/// memory order. Blocks of [`MOMENT_LANES`] channels walk all pixels with their sums in
/// registers (a whole chunk's, kept on the stack, were loaded and stored again at every
/// pixel, most of GroupNorm's time), then what is left of the span.
#[inline(always)]
fn add_span_moments(
    data: &[f32],
    channels: usize,
    span: core::ops::Range<usize>,
    (sums, squares): (&mut [f64], &mut [f64]),
) {
    let len = span.len();
    let (sums, squares) = (&mut sums[..len], &mut squares[..len]);
    let whole = len - len % MOMENT_LANES;
    for block in (0..whole).step_by(MOMENT_LANES) {
        let mut block_sums: [f64; MOMENT_LANES] = sums[block..][..MOMENT_LANES]
            .try_into()
            .expect("a block of lanes");
        let mut block_squares: [f64; MOMENT_LANES] = squares[block..][..MOMENT_LANES]
            .try_into()
            .expect("a block of lanes");
        for pixel in data.chunks_exact(channels) {
            let values = &pixel[span.start + block..][..MOMENT_LANES];
            for ((sum, square), &x) in block_sums
                .iter_mut()
                .zip(block_squares.iter_mut())
                .zip(values)
            {
                let x = x as f64;
                *sum += x;
                *square += x * x;
            }
        }
        sums[block..][..MOMENT_LANES].copy_from_slice(&block_sums);
        squares[block..][..MOMENT_LANES].copy_from_slice(&block_squares);
    }
    if whole < len {
        for pixel in data.chunks_exact(channels) {
            for ((sum, square), &x) in sums[whole..]
                .iter_mut()
                .zip(squares[whole..].iter_mut())
                .zip(&pixel[span.start + whole..span.end])
            {
                let x = x as f64;
                *sum += x;
                *square += x * x;
            }
        }
    }
}

/// Channels a GroupNorm may have for [`group_scale_shift`] to give [`group_norm`]'s bits:
/// the channels [`group_norm`] normalizes in one chunk.
pub const GROUP_NORM_CHUNK: usize = CHANNELS;

/// The per-channel `scale` and `shift` that [`group_norm`] applies (`x * scale + shift`),
/// from the channels' moments over `positions` pixels ([`add_channel_moments`]): the same
/// arithmetic in the same order, so the same bits when the channels fit one of its chunks
/// ([`GROUP_NORM_CHUNK`], as the stem's 64 do).
pub fn group_scale_shift(
    (sums, squares): (&[f64], &[f64]),
    positions: usize,
    groups: usize,
    (gamma, beta): (&[f32], &[f32]),
    (scale, shift): (&mut [f32], &mut [f32]),
) {
    let channels = gamma.len();
    let group_size = channels / groups;
    let count = (positions * group_size) as f64;
    let per_group = sums[..channels]
        .chunks_exact(group_size)
        .zip(squares[..channels].chunks_exact(group_size))
        .zip(
            gamma
                .chunks_exact(group_size)
                .zip(beta.chunks_exact(group_size)),
        )
        .zip(
            scale[..channels]
                .chunks_exact_mut(group_size)
                .zip(shift[..channels].chunks_exact_mut(group_size)),
        );
    for (((channel_sums, channel_squares), (gamma, beta)), (scale, shift)) in per_group {
        let mut sum = 0.0f64;
        channel_sums
            .iter()
            .for_each(|&channel_sum| sum += channel_sum);
        let mut square = 0.0f64;
        channel_squares
            .iter()
            .for_each(|&channel_square| square += channel_square);
        let moments = mean_inverse_std((sum, square), count);
        channel_affine(moments, (gamma, beta), (scale, shift));
    }
}

/// A group's mean and `1 / sqrt(variance + eps)` from the sums of its `count` values and of
/// their squares.
#[inline(always)]
fn mean_inverse_std((sum, square): (f64, f64), count: f64) -> (f64, f64) {
    let mean = sum / count;
    let variance = (square / count - mean * mean).max(0.0);
    (mean, 1.0 / sqrt(variance + NORM_EPSILON))
}

/// The `scale` and `shift` of a group's channels (`x * scale + shift`) from its mean and
/// inverse standard deviation and their affine parameters.
#[inline(always)]
fn channel_affine(
    (mean, inverse_std): (f64, f64),
    (gamma, beta): (&[f32], &[f32]),
    (scale, shift): (&mut [f32], &mut [f32]),
) {
    for (((scale, shift), &gamma), &beta) in
        scale.iter_mut().zip(shift.iter_mut()).zip(gamma).zip(beta)
    {
        *scale = (gamma as f64 * inverse_std) as f32;
        *shift = (beta as f64 - mean * gamma as f64 * inverse_std) as f32;
    }
}

/// [`max_pool_3x3_stride_2`] of `activation(x * scale + shift)` (per channel): normalizing
/// then pooling, the same bits, without storing the normalized map (the panda stem's is 4.9
/// MB, so each pass over it goes to L3). `output` holds the pooled rows from `first_row`
/// on (as many as it has room for): each pooled pixel reads its own window, so a band of
/// them is the whole pool's.
#[inline(always)]
pub fn normalize_max_pool(
    input: &[f32],
    dims: (usize, usize, usize),
    (scale, shift): (&[f32], &[f32]),
    activation: Activation,
    output: &mut [f32],
    first_row: usize,
) {
    let channels = dims.2;
    let (scale, shift) = (&scale[..channels], &shift[..channels]);
    pool_windows(input, dims, output, first_row, |out, pixel| {
        for (((o, &x), &a), &b) in out.iter_mut().zip(pixel).zip(scale).zip(shift) {
            *o = o.max(activate(x * a + b, activation));
        }
    });
}

/// 3x3 max pool, stride 2, padding 1 (padding never wins) over `[H, W, C]`.
#[inline(always)]
pub fn max_pool_3x3_stride_2(input: &[f32], dims: (usize, usize, usize), output: &mut [f32]) {
    pool_windows(input, dims, output, 0, |out, pixel| {
        for (o, &x) in out.iter_mut().zip(pixel) {
            *o = o.max(x);
        }
    });
}

/// The 3x3 / 2 pool's walk (padding 1, never read): each output pixel of `[H, W, C]`
/// `input`'s pooled map, `output` holding its rows from `first_row` on, starts at minus
/// infinity and `take(out, pixel)` folds in each input pixel of its window, rows then
/// columns in order.
#[inline(always)]
fn pool_windows(
    input: &[f32],
    (height, width, channels): (usize, usize, usize),
    output: &mut [f32],
    first_row: usize,
    mut take: impl FnMut(&mut [f32], &[f32]),
) {
    let out_height = crate::shape::conv_output(height, 3, 2, 1);
    let out_width = crate::shape::conv_output(width, 3, 2, 1);
    debug_assert!(output.len() <= out_height.saturating_sub(first_row) * out_width * channels);
    for (position, out) in output.chunks_exact_mut(channels).enumerate() {
        let out_y = first_row + position / out_width;
        let out_x = position % out_width;
        out.fill(f32::NEG_INFINITY);
        for in_y in (2 * out_y).saturating_sub(1)..(2 * out_y + 2).min(height) {
            for in_x in (2 * out_x).saturating_sub(1)..(2 * out_x + 2).min(width) {
                take(out, &input[(in_y * width + in_x) * channels..][..channels]);
            }
        }
    }
}

/// `target += source` then `activation`, element-wise.
#[inline(always)]
pub fn add_activate(target: &mut [f32], source: &[f32], activation: Activation) {
    for (t, &s) in target.iter_mut().zip(source) {
        *t = activate(*t + s, activation);
    }
}

/// `roundf(value)` (ties away from zero) as an integer, for |value| < 2^23, in operations
/// that vectorize (`libm::roundf` is a bit-twiddling call per value): there the truncation
/// and the fraction `value - truncated` are exact, so comparing the fraction with ±0.5
/// decides exactly as `roundf` does.
///
/// # Safety
/// `value` is finite and |value| < 2^23.
#[inline(always)]
unsafe fn round_half_away(value: f32) -> i32 {
    // SAFETY: finite and inside i32's range (the caller's promise). `as i32` would saturate
    // and map NaN to 0, which the compiler scalarizes: a conversion per lane with branches,
    // most of the quantizer's time.
    let truncated: i32 = unsafe { value.to_int_unchecked() };
    let fraction = value - truncated as f32;
    truncated + i32::from(fraction >= 0.5) - i32::from(fraction <= -0.5)
}

/// Symmetric per-tensor int8 quantization: `scale = max |x| / 127`,
/// `q = round(x / scale)` (ties away from zero) in [-127, 127]. Returns the scale: 1 for an
/// all-zero or near-zero input, NaN when the input holds NaN or infinity (so the NaN reaches
/// the result and the engine reports it instead of acting on it), with zero codes
/// (`code_inverse`).
pub fn quantize_symmetric(input: &[f32], output: &mut [i8]) -> f32 {
    quantize_symmetric_signs(input, output).0
}

/// [`quantize_symmetric`], also telling whether every quantized value is nonnegative (found
/// in the quantizing loop itself: no second pass over the output).
#[inline(always)]
pub fn quantize_symmetric_signs(input: &[f32], output: &mut [i8]) -> (f32, bool) {
    let largest = largest_magnitude(input);
    let inverse = match code_inverse(largest, 127.0) {
        Ok(inverse) => inverse,
        Err(scale) => {
            output.fill(0);
            return (scale, true);
        }
    };
    let mut lowest = 0i8;
    for (q, &x) in output.iter_mut().zip(input) {
        // SAFETY: x is finite with |x| <= largest, and `inverse = 127 / largest` is finite
        // (`code_inverse`), so |x * inverse| is at most 127 and a rounding.
        *q = unsafe { round_half_away(x * inverse) }.clamp(-127, 127) as i8;
        lowest = lowest.min(*q);
    }
    (largest / 127.0, lowest >= 0)
}

/// `max |x|` over `input`, or a value that is not finite when the input holds NaN or an
/// infinity. |x| as bits: for numbers the integer order is the float order, and NaN patterns
/// sort above infinity, so one integer maximum finds max |x| or reports a non-finite input.
/// It vectorizes; a float fold that must notice NaN does not (it was a fifth of the int8
/// trunk's time). The same order makes the largest of several parts' results, their bits
/// compared as integers, the whole input's.
#[inline(always)]
pub fn largest_magnitude(input: &[f32]) -> f32 {
    let bits = input
        .iter()
        .fold(0u32, |largest, &x| largest.max(x.to_bits() & 0x7fff_ffff));
    f32::from_bits(bits)
}

/// Where a quantizer's largest magnitude comes from.
#[derive(Clone, Copy)]
enum Largest {
    /// [`largest_magnitude`] of the very input being quantized (made only by
    /// [`Largest::of`]): every value lies inside it.
    Own(f32),
    /// A caller's, for a part of a larger input: the values are held inside it.
    Given(f32),
}

impl Largest {
    #[inline(always)]
    fn of(input: &[f32]) -> Self {
        Largest::Own(largest_magnitude(input))
    }

    #[inline(always)]
    fn value(self) -> f32 {
        match self {
            Largest::Own(largest) | Largest::Given(largest) => largest,
        }
    }

    /// `x`, one of the input's values, inside `[-largest, largest]`: itself for the
    /// input's own largest; held inside a given one (NaN to `-largest`), which is the
    /// identity for a part of an input whose largest magnitude it is, and keeps a code's
    /// rounding in range whatever a caller gives. Finite wherever `code_inverse` accepted
    /// the largest.
    #[inline(always)]
    fn hold(self, x: f32) -> f32 {
        match self {
            Largest::Own(_) => x,
            Largest::Given(largest) => {
                let x = if x > -largest { x } else { -largest };
                if x < largest { x } else { largest }
            }
        }
    }
}

/// Largest code of the trunk's activation scheme: 14 bits and a sign, so that a code splits
/// into two int8 digits of base [`DIGIT_BASE`] ([`quantize_split_signs`]).
pub const SPLIT_CODE_LIMIT: f32 = 16383.0;

/// Base of the two digits of a 14-bit activation code: `code = high * 128 + low`.
pub const DIGIT_BASE: f32 = 128.0;

/// `limit / largest`, the factor that takes an input whose largest magnitude is `largest`
/// to codes of at most `limit`; or, where every code is zero, the scale to report: NaN for
/// a non-finite input (so the NaN reaches the result and the engine reports it), 1 for an
/// all-zero one and for one so close to zero that the factor overflows (`largest` below
/// `limit / f32::MAX`: 4.8e-35 for 15-bit codes, 3.7e-37 for signed bytes), whose values are
/// zero to any layer after it (the next bias, GroupNorm's epsilon).
#[inline(always)]
fn code_inverse(largest: f32, limit: f32) -> Result<f32, f32> {
    if !largest.is_finite() {
        return Err(f32::NAN);
    }
    let inverse = limit / largest;
    if inverse.is_finite() {
        Ok(inverse)
    } else {
        Err(1.0)
    }
}

/// The 15-bit code of `x` for `inverse = 16383 / largest`: `round(x * inverse)`, ties away
/// from zero, in [-16383, 16383].
///
/// # Safety
/// `x` is finite and |x| <= `largest`, and `inverse` is finite (`code_inverse`).
#[inline(always)]
unsafe fn split_code(x: f32, inverse: f32) -> i32 {
    // SAFETY: |x * inverse| is at most 16383 (the caller's promise), finite, and a rounding.
    unsafe { round_half_away(x * inverse) }.clamp(-16383, 16383)
}

/// Symmetric 15-bit quantization split into two int8 digits: `scale = max |x| / 16383`,
/// `code = round(x / scale)` (ties away from zero) in [-16383, 16383], written as
/// `high = floor(code / 128)` (in [-128, 127]; in [0, 127] for `code >= 0`) and
/// `low = code - 128 high` (in [0, 127]). The int8 kernel sums each digit plane over the
/// same weights with int8 dot products and forms `128 high + low`, the exact code sum:
/// activations within 3e-5 of their range (7 bits: 4e-3, which cost more accuracy
/// than the int8 weights did) at the price of twice the integer products.
/// Returns the scale (1 for an all-zero or near-zero input, NaN for a non-finite one, with
/// zero digits: `code_inverse`) and whether every code is nonnegative.
#[inline(always)]
pub fn quantize_split_signs(input: &[f32], high: &mut [i8], low: &mut [i8]) -> (f32, bool) {
    split_signs(input, Largest::of(input), high, low)
}

/// [`quantize_split_signs`] of `input`, a part of a map whose largest magnitude
/// ([`largest_magnitude`]) is `largest`: that part of the whole map's digits, its scale, and
/// whether this part's codes are nonnegative. Values outside `[-largest, largest]` (none,
/// for the map's own largest) take the nearest end.
#[inline(always)]
pub fn quantize_split_signs_within(
    input: &[f32],
    largest: f32,
    high: &mut [i8],
    low: &mut [i8],
) -> (f32, bool) {
    split_signs(input, Largest::Given(largest), high, low)
}

/// [`quantize_split_signs`] for `largest`.
#[inline(always)]
fn split_signs(input: &[f32], largest: Largest, high: &mut [i8], low: &mut [i8]) -> (f32, bool) {
    let inverse = match code_inverse(largest.value(), SPLIT_CODE_LIMIT) {
        Ok(inverse) => inverse,
        Err(scale) => {
            high.fill(0);
            low.fill(0);
            return (scale, true);
        }
    };
    let mut lowest = 0i32;
    for ((h, l), &x) in high.iter_mut().zip(low.iter_mut()).zip(input) {
        // SAFETY: `hold` gives a finite x at most `largest` in magnitude (`code_inverse`
        // accepted it), and `code_inverse` gave a finite `inverse`.
        let code = unsafe { split_code(largest.hold(x), inverse) };
        // An arithmetic shift floors, so `low` is the nonnegative remainder.
        *h = (code >> 7) as i8;
        *l = (code & 127) as i8;
        lowest = lowest.min(code);
    }
    (largest.value() / SPLIT_CODE_LIMIT, lowest >= 0)
}

/// The 15-bit codes of [`quantize_split_signs`] kept whole, rows of `row_len` values into
/// rows of `row_stride >= row_len` codes (the padding codes, up to whole input-channel
/// quads, set to 0): `scale = max |x| / 16383` over the whole input, `code = round(x /
/// scale)` (ties away from zero) in [-16383, 16383], as i16 (the U-Net's activations,
/// signed, for 16-bit integer dot products). Returns the scale (1 for an all-zero or
/// near-zero input, NaN for a non-finite one, with zero codes: `code_inverse`).
#[inline(always)]
pub fn quantize_rows_codes(input: &[f32], rows: (usize, usize), codes: &mut [i16]) -> f32 {
    quantize_rows_whole(input, rows, codes, SPLIT_CODE_LIMIT)
}

/// Symmetric quantization to whole codes of at most `limit` in magnitude (an integer below
/// 2^15), rows of `row_len` values into rows of `row_stride` i16 codes, the padding 0;
/// returns the scale, `max |x| / limit` (1 for an all-zero or near-zero input, NaN for a
/// non-finite one, with zero codes: `code_inverse`).
#[inline(always)]
fn quantize_rows_whole(
    input: &[f32],
    (row_len, row_stride): (usize, usize),
    codes: &mut [i16],
    limit: f32,
) -> f32 {
    let largest = largest_magnitude(input);
    let inverse = match code_inverse(largest, limit) {
        Ok(inverse) => inverse,
        Err(scale) => {
            codes.fill(0);
            return scale;
        }
    };
    let bound = limit as i32;
    for (row, codes) in input
        .chunks_exact(row_len)
        .zip(codes.chunks_exact_mut(row_stride))
    {
        let (codes, padding) = codes.split_at_mut(row_len);
        for (code, &x) in codes.iter_mut().zip(row) {
            // SAFETY: |x * inverse| is at most `limit` (x is one of the values `largest` was
            // taken over, `inverse = limit / largest` finite by `code_inverse`), and a
            // rounding.
            *code = unsafe { round_half_away(x * inverse) }.clamp(-bound, bound) as i16;
        }
        padding.fill(0);
    }
    largest / limit
}

/// Largest magnitude of the U-Net's narrow codes: a signed byte, symmetric.
pub const SIGNED_BYTE_CODE_LIMIT: f32 = 127.0;

/// Narrow symmetric quantization of the U-Net's signed activations, one scale for all of
/// the input: `scale = max |x| / 127`, `code = round(x / scale)` (ties away from zero) in
/// [-127, 127], one signed byte a value, rows of `row_len` padded with zero codes to
/// `row_stride` as [`quantize_rows_codes`] pads them; `row_sums[r]` is row `r`'s code sum.
/// Returns the scale (1 for an all-zero or near-zero input, NaN for a non-finite one, with
/// zero codes: `code_inverse`).
#[inline(always)]
pub fn quantize_rows_signed_bytes(
    input: &[f32],
    (row_len, row_stride): (usize, usize),
    codes: &mut [i8],
    row_sums: &mut [i32],
) -> f32 {
    let largest = largest_magnitude(input);
    let inverse = match code_inverse(largest, SIGNED_BYTE_CODE_LIMIT) {
        Ok(inverse) => inverse,
        Err(scale) => {
            codes.fill(0);
            row_sums.fill(0);
            return scale;
        }
    };
    let rows = input.chunks_exact(row_len);
    for ((row, codes), row_sum) in rows.zip(codes.chunks_exact_mut(row_stride)).zip(row_sums) {
        let (codes, padding) = codes.split_at_mut(row_len);
        let mut sum = 0;
        for (code, &x) in codes.iter_mut().zip(row) {
            // SAFETY: |x * inverse| is at most 127 (x is one of the values `largest` was taken
            // over, `inverse = 127 / largest` finite by `code_inverse`), and a rounding.
            let value = unsafe { round_half_away(x * inverse) }.clamp(-127, 127);
            *code = value as i8;
            sum += value;
        }
        padding.fill(0);
        *row_sum = sum;
    }
    largest / SIGNED_BYTE_CODE_LIMIT
}

/// The codes of [`quantize_rows_signed_bytes`] (the same scale and values) kept as i16
/// rows, as [`quantize_rows_codes`] lays them out, for 16-bit products that would widen
/// bytes anyway (AVX2's), without the row sums.
#[inline(always)]
pub fn quantize_rows_narrow_codes(input: &[f32], rows: (usize, usize), codes: &mut [i16]) -> f32 {
    quantize_rows_whole(input, rows, codes, SIGNED_BYTE_CODE_LIMIT)
}

/// Largest code of the narrow activation scheme: one unsigned byte.
pub const BYTE_CODE_LIMIT: f32 = 255.0;

/// The narrow code of `x` for `inverse = 255 / largest`: `round(x * inverse)`, ties away
/// from zero, in [0, 255] (a negative value, which no ReLU output is, becomes 0).
///
/// # Safety
/// `x` is finite and |x| <= `largest`, and `inverse` is finite (`code_inverse`).
#[inline(always)]
unsafe fn byte_code(x: f32, inverse: f32) -> i32 {
    // SAFETY: |x * inverse| is at most 255 (the caller's promise), finite, and a rounding.
    unsafe { round_half_away(x * inverse) }.clamp(0, 255)
}

/// Unsigned 8-bit quantization of a nonnegative input (a ReLU output), one scale for all
/// of it: `scale = max |x| / 255`, `code = round(x / scale)` (ties away from zero) in
/// [0, 255], one byte a value: the narrow activations, whose byte products are half the
/// two digit planes' of [`quantize_split_signs`]. Returns the scale (1 for an all-zero
/// or near-zero input, NaN for a non-finite one, with zero codes: `code_inverse`).
#[inline(always)]
pub fn quantize_bytes(input: &[f32], bytes: &mut [u8]) -> f32 {
    bytes_of(input, Largest::of(input), bytes)
}

/// [`quantize_bytes`] for `largest`.
#[inline(always)]
fn bytes_of(input: &[f32], largest: Largest, bytes: &mut [u8]) -> f32 {
    let inverse = match code_inverse(largest.value(), BYTE_CODE_LIMIT) {
        Ok(inverse) => inverse,
        Err(scale) => {
            bytes.fill(0);
            return scale;
        }
    };
    for (byte, &x) in bytes.iter_mut().zip(input) {
        // SAFETY: `hold` gives a finite x at most `largest` in magnitude (`code_inverse`
        // accepted it), and `code_inverse` gave a finite `inverse`.
        *byte = unsafe { byte_code(largest.hold(x), inverse) } as u8;
    }
    largest.value() / BYTE_CODE_LIMIT
}

/// [`quantize_bytes`] into the front of `scratch` in `form`: whole bytes (`input.len()`
/// bytes), or the two digit planes of [`quantize_bytes_split`] back to back (twice that).
#[inline(always)]
pub fn quantize_narrow(input: &[f32], scratch: &mut [i8], form: super::NarrowForm) -> f32 {
    let len = input.len();
    let codes = match form {
        super::NarrowForm::Bytes => (&mut scratch[..len], &mut [][..]),
        super::NarrowForm::Digits => scratch[..2 * len].split_at_mut(len),
    };
    narrow(input, Largest::of(input), codes, form)
}

/// [`quantize_narrow`] of a part of a map whose largest magnitude is `largest`, into
/// `codes`: the part's bytes (the first, `input.len()` of them), or its two digit planes'
/// parts, as [`quantize_split_signs_within`] is of [`quantize_split_signs`].
#[inline(always)]
pub fn quantize_narrow_within(
    input: &[f32],
    largest: f32,
    (first, second): (&mut [i8], &mut [i8]),
    form: super::NarrowForm,
) -> f32 {
    narrow(input, Largest::Given(largest), (first, second), form)
}

/// [`quantize_narrow_within`] for `largest`.
#[inline(always)]
fn narrow(
    input: &[f32],
    largest: Largest,
    (first, second): (&mut [i8], &mut [i8]),
    form: super::NarrowForm,
) -> f32 {
    let len = input.len();
    match form {
        super::NarrowForm::Bytes => {
            bytes_of(input, largest, bytemuck::cast_slice_mut(&mut first[..len]))
        }
        super::NarrowForm::Digits => {
            bytes_split(input, largest, &mut first[..len], &mut second[..len])
        }
    }
}

/// The codes of [`quantize_bytes`] written as two digit planes, `high = code >> 7` (0 or 1)
/// and `low = code & 127`, for integer products that take 7-bit activations only (AVX2's
/// `vpmaddubsw` saturates on 255 x 127 pairs): the same codes, so a kernel summing
/// `128 high + low` gets the same exact sums. Returns the scale as [`quantize_bytes`] does.
#[inline(always)]
pub fn quantize_bytes_split(input: &[f32], high: &mut [i8], low: &mut [i8]) -> f32 {
    bytes_split(input, Largest::of(input), high, low)
}

/// [`quantize_bytes_split`] for `largest`.
#[inline(always)]
fn bytes_split(input: &[f32], largest: Largest, high: &mut [i8], low: &mut [i8]) -> f32 {
    let inverse = match code_inverse(largest.value(), BYTE_CODE_LIMIT) {
        Ok(inverse) => inverse,
        Err(scale) => {
            high.fill(0);
            low.fill(0);
            return scale;
        }
    };
    for ((h, l), &x) in high.iter_mut().zip(low.iter_mut()).zip(input) {
        // SAFETY: as in `bytes_of`.
        let code = unsafe { byte_code(largest.hold(x), inverse) };
        *h = (code >> 7) as i8;
        *l = (code & 127) as i8;
    }
    largest.value() / BYTE_CODE_LIMIT
}

#[cfg(test)]
mod tests {
    use super::{exp, round_half_away};

    /// Within 2 ulp of the correctly rounded `e^x` (f64 `exp` rounded to f32) over the
    /// range Mish uses and the ends of the clamp, and NaN in, NaN out.
    #[test]
    fn exp_is_within_two_ulp() {
        let ulps = |found: f32, exact: f32| (found.to_bits() as i64 - exact.to_bits() as i64).abs();
        let sweep = (0..400_000).map(|i| -87.3f32 + i as f32 * (88.0 + 87.3) / 400_000.0);
        let special = [
            0.0f32, -0.0, 1e-30, -1e-30, 0.5, -0.5, 1.0, 20.0, -20.0, 88.0, -87.3,
        ];
        for x in sweep.chain(special) {
            let exact = libm::exp(x as f64) as f32;
            assert!(
                ulps(exp(x), exact) <= 2,
                "exp({x:e}) = {:e}, exact {exact:e}",
                exp(x)
            );
        }
        assert!(exp(f32::NAN).is_nan());
    }

    /// Equal to `libm::roundf` at every halfway point of the activation range, the floats
    /// next to them, and a dense sweep (the quantizer's values are within ±127.5).
    #[test]
    fn round_half_away_is_roundf() {
        let halfway = (-140..=140).flat_map(|k| {
            let half = k as f32 + 0.5;
            [half, half.next_up(), half.next_down(), k as f32]
        });
        let special = [0.49999997f32, -0.49999997, 0.5, -0.5, -0.0, 1e-30, -1e-30];
        let sweep = (0..200_000).map(|i| (i as f32 - 100_000.0) * 0.0013);
        for value in halfway.chain(special).chain(sweep) {
            assert_eq!(
                // SAFETY: every value is finite and within ±300.
                unsafe { round_half_away(value) },
                libm::roundf(value) as i32,
                "{value:e}"
            );
        }
    }
}
