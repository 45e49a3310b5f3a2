//! Element-wise and normalization operations over channels-last data. Cheap next to the
//! convolutions, so one portable implementation serves every backend.

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
#[inline]
pub fn mish(x: f32) -> f32 {
    if x > 20.0 {
        return x;
    }
    let e = libm::expf(x);
    let n = e * (e + 2.0);
    x * n / (n + 2.0)
}

#[inline]
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
pub fn group_norm(
    data: &mut [f32],
    channels: usize,
    groups: usize,
    gamma: &[f32],
    beta: &[f32],
    activation: Activation,
) {
    let group_size = channels / groups;
    let positions = data.len() / channels;
    let count = (positions * group_size) as f64;
    for group in 0..groups {
        let first = group * group_size;
        let mut sum = 0.0f64;
        for pixel in data.chunks_exact(channels) {
            sum += pixel[first..first + group_size]
                .iter()
                .map(|&x| x as f64)
                .sum::<f64>();
        }
        let mean = sum / count;
        let mut squares = 0.0f64;
        for pixel in data.chunks_exact(channels) {
            squares += pixel[first..first + group_size]
                .iter()
                .map(|&x| {
                    let centred = x as f64 - mean;
                    centred * centred
                })
                .sum::<f64>();
        }
        let inverse_std = 1.0 / libm::sqrt(squares / count + NORM_EPSILON);
        let mut scale = [0.0f32; 64];
        let mut shift = [0.0f32; 64];
        for start in (0..group_size).step_by(64) {
            let len = (group_size - start).min(64);
            for offset in 0..len {
                let channel = first + start + offset;
                scale[offset] = (gamma[channel] as f64 * inverse_std) as f32;
                shift[offset] =
                    (beta[channel] as f64 - mean * gamma[channel] as f64 * inverse_std) as f32;
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

/// 3x3 max pool, stride 2, padding 1 (padding never wins) over `[H, W, C]`.
pub fn max_pool_3x3_stride_2(
    input: &[f32],
    (height, width, channels): (usize, usize, usize),
    output: &mut [f32],
) {
    let out_height = crate::config::conv_output(height, 3, 2, 1);
    let out_width = crate::config::conv_output(width, 3, 2, 1);
    debug_assert_eq!(output.len(), out_height * out_width * channels);
    for (position, out) in output.chunks_exact_mut(channels).enumerate() {
        let out_y = position / out_width;
        let out_x = position % out_width;
        out.fill(f32::NEG_INFINITY);
        for in_y in (2 * out_y).saturating_sub(1)..(2 * out_y + 2).min(height) {
            for in_x in (2 * out_x).saturating_sub(1)..(2 * out_x + 2).min(width) {
                let pixel = &input[(in_y * width + in_x) * channels..][..channels];
                for (o, &x) in out.iter_mut().zip(pixel) {
                    *o = o.max(x);
                }
            }
        }
    }
}

/// `target += source` then `activation`, element-wise.
pub fn add_activate(target: &mut [f32], source: &[f32], activation: Activation) {
    for (t, &s) in target.iter_mut().zip(source) {
        *t = activate(*t + s, activation);
    }
}

/// Symmetric per-tensor int8 quantization: `scale = max |x| / 127`,
/// `q = round(x / scale)` (ties away from zero) in [-127, 127]. Returns the scale: 1 for an
/// all-zero input, NaN when the input holds NaN or infinity (so the NaN reaches the result
/// and the engine reports it instead of acting on it).
pub fn quantize_symmetric(input: &[f32], output: &mut [i8]) -> f32 {
    quantize_symmetric_signs(input, output).0
}

/// [`quantize_symmetric`], also telling whether every quantized value is nonnegative (found
/// in the quantizing loop itself: no second pass over the output).
pub fn quantize_symmetric_signs(input: &[f32], output: &mut [i8]) -> (f32, bool) {
    let largest = input.iter().fold(0.0f32, |m, &x| {
        if x.abs() > m || x.is_nan() {
            x.abs()
        } else {
            m
        }
    });
    if !largest.is_finite() {
        output.fill(0);
        return (f32::NAN, true);
    }
    if largest == 0.0 {
        output.fill(0);
        return (1.0, true);
    }
    let inverse = 127.0 / largest;
    let mut lowest = 0i8;
    for (q, &x) in output.iter_mut().zip(input) {
        *q = libm::roundf(x * inverse).clamp(-127.0, 127.0) as i8;
        lowest = lowest.min(*q);
    }
    (largest / 127.0, lowest >= 0)
}
