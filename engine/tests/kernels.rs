//! The scalar kernels against textbook definitions written the PyTorch way (channels-first
//! tensors, PyTorch weight layouts, f64 accumulation), on random shapes. Tolerance: 1e-5
//! relative to the sum of |terms|, the bound for f32 accumulation of up to ~5000 products.

use scdp_engine::Backend;
use scdp_engine::kernels::ops::{self, Activation};
use scdp_engine::kernels::scalar::Scalar;
#[cfg(target_arch = "x86_64")]
use scdp_engine::kernels::x86_64::amx::{Amx, TileLayout};
use scdp_engine::layer;
use scdp_engine::weights::{ActivationCodes, Weight};
/// Elsewhere no tile layout runs: `check_on_tiles` reports `None`.
#[cfg(not(target_arch = "x86_64"))]
type TileLayout = ();
use scdp_engine::kernels::{
    Accumulate, ByteRows, CodeRows, ConvShape, DigitRows, Epilogue, Film, FilmWeights, Kernels,
    NarrowForm, QuantizeScratch, SignedByteRows, Split, Workers,
};

struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }

    fn vec(&mut self, len: usize) -> Vec<f32> {
        (0..len).map(|_| self.next()).collect()
    }

    fn below(&mut self, n: usize) -> usize {
        ((self.next() + 1.0) * 0.5 * n as f32) as usize % n
    }
}

/// PyTorch Conv2d: input `[C, H, W]`, weight `[out, in, kh, kw]`. Returns `[H', W', out]`
/// values and the matching sums of |terms| for the tolerance.
fn reference_conv(
    shape: &ConvShape,
    input_chw: &[f32],
    weight_oihw: &[f32],
    bias: &[f32],
) -> (Vec<f64>, Vec<f64>) {
    let (oh, ow) = (shape.out_height(), shape.out_width());
    let mut out = vec![0.0; oh * ow * shape.out_channels];
    let mut magnitude = vec![0.0; out.len()];
    for o in 0..shape.out_channels {
        for y in 0..oh {
            for x in 0..ow {
                let mut sum = bias[o] as f64;
                let mut abs = (bias[o] as f64).abs();
                for i in 0..shape.in_channels {
                    for ky in 0..shape.kernel_height {
                        for kx in 0..shape.kernel_width {
                            let iy =
                                (y * shape.stride + ky) as isize - shape.padding_height as isize;
                            let ix =
                                (x * shape.stride + kx) as isize - shape.padding_width as isize;
                            if iy < 0
                                || ix < 0
                                || iy >= shape.in_height as isize
                                || ix >= shape.in_width as isize
                            {
                                continue;
                            }
                            let v = input_chw
                                [(i * shape.in_height + iy as usize) * shape.in_width + ix as usize]
                                as f64;
                            let w = weight_oihw[((o * shape.in_channels + i) * shape.kernel_height
                                + ky)
                                * shape.kernel_width
                                + kx] as f64;
                            sum += v * w;
                            abs += (v * w).abs();
                        }
                    }
                }
                out[(y * ow + x) * shape.out_channels + o] = sum;
                magnitude[(y * ow + x) * shape.out_channels + o] = abs;
            }
        }
    }
    (out, magnitude)
}

fn to_hwc(chw: &[f32], c: usize, h: usize, w: usize) -> Vec<f32> {
    let mut out = vec![0.0; chw.len()];
    for ch in 0..c {
        for p in 0..h * w {
            out[p * c + ch] = chw[ch * h * w + p];
        }
    }
    out
}

fn pack_oihw(weight: &[f32], o: usize, i: usize, kh: usize, kw: usize) -> Vec<f32> {
    let mut out = vec![0.0; weight.len()];
    for a in 0..o {
        for b in 0..i {
            for y in 0..kh {
                for x in 0..kw {
                    out[((y * kw + x) * i + b) * o + a] = weight[((a * i + b) * kh + y) * kw + x];
                }
            }
        }
    }
    out
}

fn assert_close(found: &[f32], expected: &[f64], magnitude: &[f64], what: &str) {
    assert_eq!(found.len(), expected.len(), "{what}: length");
    for (index, ((&f, &e), &m)) in found.iter().zip(expected).zip(magnitude).enumerate() {
        let tolerance = 1e-5 * m.max(1.0);
        assert!(
            (f as f64 - e).abs() <= tolerance,
            "{what}[{index}]: {f} vs {e} (tolerance {tolerance})"
        );
    }
}

/// Every implementation this CPU can run. `SCDP_REQUIRE_BACKENDS=avx2,avx512` (as CI sets
/// it, with amx where the CPU lists it; `neon,dot,i8mm` under emulation of an ARM core that
/// has them) makes a missing backend a failure instead of a silent skip.
fn backends() -> Vec<(&'static str, &'static dyn Kernels)> {
    let mut found = Vec::new();
    for backend in Backend::ALL.into_iter().filter(|&b| b != Backend::Auto) {
        let name = backend.name();
        if let Some(kernels) = scdp_engine::kernels::select(backend) {
            assert_eq!(
                kernels.name(),
                name,
                "select({backend:?}) gave another backend"
            );
            found.push((name, kernels));
        }
    }
    let required = std::env::var("SCDP_REQUIRE_BACKENDS").unwrap_or_default();
    for name in required.split(',').filter(|n| !n.is_empty()) {
        assert!(
            found.iter().any(|(n, _)| *n == name),
            "backend {name} is required but this CPU cannot run it"
        );
    }
    found
}

#[test]
fn convolution_matches_pytorch_definition_on_random_shapes() {
    for (name, kernels) in backends() {
        convolution_matches_pytorch_definition(name, kernels);
    }
}

fn convolution_matches_pytorch_definition(backend: &str, kernels: &dyn Kernels) {
    let mut rng = Lcg(7);
    for case in 0..80 {
        let kernel = [1, 3, 5, 7][rng.below(4)];
        let one_dimensional = case % 3 == 0;
        let stride = 1 + rng.below(2);
        let padding = rng.below(kernel / 2 + 1);
        let in_channels = 1 + rng.below(9);
        // Multiples of 16 reach the SIMD tiles; the rest their fallbacks.
        let out_channels = if case % 2 == 0 {
            16 * (1 + rng.below(3))
        } else {
            1 + rng.below(11)
        };
        let shape = if one_dimensional {
            ConvShape::sequence(
                kernel + rng.below(20),
                in_channels,
                out_channels,
                kernel,
                stride,
                padding,
            )
        } else {
            ConvShape::square(
                (kernel + rng.below(7), kernel + rng.below(16), in_channels),
                out_channels,
                kernel,
                stride,
                padding,
            )
        };
        let input_chw = rng.vec(shape.input_len());
        let weight = rng.vec(shape.weight_len());
        let bias = rng.vec(out_channels);
        let (expected, magnitude) = reference_conv(&shape, &input_chw, &weight, &bias);
        let input = to_hwc(&input_chw, in_channels, shape.in_height, shape.in_width);
        let packed = pack_oihw(
            &weight,
            out_channels,
            in_channels,
            shape.kernel_height,
            shape.kernel_width,
        );
        let mut output = vec![f32::NAN; shape.output_len()];
        kernels.conv(
            &shape,
            &input,
            &packed,
            &bias,
            &mut output,
            Accumulate::Overwrite,
        );
        assert_close(
            &output,
            &expected,
            &magnitude,
            &format!("{backend} case {case} {shape:?}"),
        );

        // Accumulate adds exactly the same convolution on top of what is there.
        let before = rng.vec(shape.output_len());
        let mut accumulated = before.clone();
        kernels.conv(
            &shape,
            &input,
            &packed,
            &bias,
            &mut accumulated,
            Accumulate::Add,
        );
        let expected_sum: Vec<f64> = expected
            .iter()
            .zip(&before)
            .map(|(e, b)| e + *b as f64)
            .collect();
        assert_close(
            &accumulated,
            &expected_sum,
            &magnitude,
            &format!("{backend} accumulate case {case}"),
        );
    }
}

#[test]
fn matvec_adds_base() {
    let mut rng = Lcg(3);
    for (name, kernels) in backends() {
        // Odd lengths reach the SIMD kernels' 4-vector, 1-vector and 1-wide parts (32 / 8
        // on AVX2, 64 / 16 on AVX-512).
        for (rows, cols) in [
            (13, 29),
            (1, 1),
            (5, 8),
            (3, 33),
            (7, 71),
            (2, 64),
            (3, 80),
            (4, 17),
            (40, 784),
        ] {
            let weight = rng.vec(rows * cols);
            let input = rng.vec(cols);
            let base = rng.vec(rows);
            let mut output = vec![f32::NAN; rows];
            kernels.matvec(&weight, &input, &base, &mut output);
            for r in 0..rows {
                let terms = (0..cols).map(|c| weight[r * cols + c] as f64 * input[c] as f64);
                let expected = base[r] as f64 + terms.clone().sum::<f64>();
                let magnitude = base[r].abs() as f64 + terms.map(f64::abs).sum::<f64>();
                assert!(
                    (output[r] as f64 - expected).abs() <= 1e-5 * magnitude.max(1.0),
                    "{name} {rows}x{cols} row {r}: {} vs {expected}",
                    output[r]
                );
            }
        }
    }
}

#[test]
fn mish_matches_definition_including_the_softplus_threshold() {
    for i in -4000..4000 {
        let x = i as f32 * 0.01;
        let softplus = if x as f64 > 20.0 {
            x as f64
        } else {
            (x as f64).exp().ln_1p()
        };
        let expected = x as f64 * softplus.tanh();
        let found = ops::mish(x) as f64;
        // A few f32 ulps: the single-exponential form rounds differently from exp/log1p/tanh.
        assert!(
            (found - expected).abs() <= 6e-7 * expected.abs().max(1e-3),
            "mish({x}) = {found}, expected {expected}"
        );
    }
    assert_eq!(ops::mish(25.0), 25.0);
    assert!(ops::mish(-100.0).abs() < 1e-30);
}

#[test]
fn group_norm_matches_definition() {
    let mut rng = Lcg(5);
    let (positions, channels, groups) = (37, 24, 6);
    let data = rng.vec(positions * channels);
    let gamma = rng.vec(channels);
    let beta = rng.vec(channels);
    for activation in [Activation::None, Activation::Relu, Activation::Mish] {
        let mut normalized = data.clone();
        ops::group_norm(&mut normalized, channels, groups, &gamma, &beta, activation);
        let size = channels / groups;
        for g in 0..groups {
            let values: Vec<f64> = (0..positions)
                .flat_map(|p| (0..size).map(move |c| (p, g * size + c)))
                .map(|(p, c)| data[p * channels + c] as f64)
                .collect();
            let mean = values.iter().sum::<f64>() / values.len() as f64;
            let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / values.len() as f64;
            for p in 0..positions {
                for c in g * size..(g + 1) * size {
                    let y = (data[p * channels + c] as f64 - mean) / (var + 1e-5).sqrt()
                        * gamma[c] as f64
                        + beta[c] as f64;
                    let expected = match activation {
                        Activation::None => y,
                        Activation::Relu => y.max(0.0),
                        Activation::Mish => y * y.exp().ln_1p().tanh(),
                    };
                    let found = normalized[p * channels + c] as f64;
                    assert!(
                        (found - expected).abs() < 1e-5,
                        "{activation:?} p{p} c{c}: {found} vs {expected}"
                    );
                }
            }
        }
    }
}

#[test]
fn max_pool_ignores_padding_even_for_negative_inputs() {
    let (h, w, c) = (5, 4, 2);
    let input: Vec<f32> = (0..h * w * c).map(|i| -(i as f32) - 1.0).collect();
    let mut output = vec![0.0; 3 * 2 * c];
    ops::max_pool_3x3_stride_2(&input, (h, w, c), &mut output);
    for oy in 0..3 {
        for ox in 0..2 {
            for ch in 0..c {
                let mut best = f32::NEG_INFINITY;
                for y in (2 * oy) as isize - 1..=(2 * oy) as isize + 1 {
                    for x in (2 * ox) as isize - 1..=(2 * ox) as isize + 1 {
                        if y >= 0 && x >= 0 && (y as usize) < h && (x as usize) < w {
                            best = best.max(input[(y as usize * w + x as usize) * c + ch]);
                        }
                    }
                }
                assert_eq!(output[(oy * 2 + ox) * c + ch], best);
            }
        }
    }
}

fn random_i8(rng: &mut Lcg, len: usize) -> Vec<i8> {
    (0..len)
        .map(|_| (rng.next() * 127.0).round() as i8)
        .collect()
}

/// Random 15-bit activation codes in -16383..=16383 (0..=16383 when `nonnegative`), with
/// zeros and the extremes, as `quantize_split_signs` writes them.
fn random_codes(rng: &mut Lcg, len: usize, nonnegative: bool) -> Vec<i32> {
    (0..len)
        .map(|_| {
            let code = match rng.below(8) {
                0 => 0,
                1 => 16383,
                _ => (rng.next() * 16383.0).round() as i32,
            };
            if nonnegative { code.abs() } else { code }
        })
        .collect()
}

/// The two digit planes of `codes`, back to back (`code = 128 high + low`, `low` in 0..128).
fn digit_planes(codes: &[i32]) -> Vec<i8> {
    let high = codes.iter().map(|&code| (code >> 7) as i8);
    let low = codes.iter().map(|&code| (code & 127) as i8);
    high.chain(low).collect()
}

#[test]
fn int8_convolution_sums_exactly_over_the_kernel_then_scales() {
    let mut rng = Lcg(17);
    for case in 0..40 {
        let kernel = [1, 3, 5][rng.below(3)];
        let stride = 1 + rng.below(2);
        let padding = rng.below(kernel / 2 + 1);
        let in_channels = 1 + rng.below(40);
        let out_channels = 1 + rng.below(300); // crosses the layout's 64-channel blocks
        let shape = ConvShape::square(
            (kernel + rng.below(5), kernel + rng.below(5), in_channels),
            out_channels,
            kernel,
            stride,
            padding,
        );
        let values = random_codes(&mut rng, shape.input_len(), false);
        let planes = digit_planes(&values);
        let scale = 0.01 + rng.next().abs();
        let weight = random_i8(&mut rng, shape.weight_len());
        let mut packed = vec![1i8; shape.int8_weight_len()];
        scdp_engine::kernels::pack_int8_quads(&weight, in_channels, out_channels, &mut packed);
        let weight_scales: Vec<f32> = (0..out_channels)
            .map(|_| 0.001 + rng.next().abs() * 0.01)
            .collect();
        let bias = rng.vec(out_channels);
        let mut output = vec![f32::NAN; shape.output_len()];
        let input = DigitRows::from_planes(&planes, scale, false);
        Scalar.conv_int8(
            &shape,
            &input,
            &packed,
            &weight_scales,
            &bias,
            &mut output,
            Accumulate::Overwrite,
        );
        // Textbook: the exact integer sum over the kernel (in i64), scaled in f64.
        let (oh, ow) = (shape.out_height(), shape.out_width());
        for y in 0..oh {
            for x in 0..ow {
                for o in 0..out_channels {
                    let mut sum = 0i64;
                    for ky in 0..kernel {
                        for kx in 0..kernel {
                            let iy = (y * stride + ky) as isize - padding as isize;
                            let ix = (x * stride + kx) as isize - padding as isize;
                            if iy < 0
                                || ix < 0
                                || iy >= shape.in_height as isize
                                || ix >= shape.in_width as isize
                            {
                                continue;
                            }
                            let row = iy as usize * shape.in_width + ix as usize;
                            sum += (0..in_channels)
                                .map(|i| {
                                    values[row * in_channels + i] as i64
                                        * weight[((ky * kernel + kx) * in_channels + i)
                                            * out_channels
                                            + o] as i64
                                })
                                .sum::<i64>();
                        }
                    }
                    let scaled = sum as f64 * scale as f64 * weight_scales[o] as f64;
                    let expected = scaled + bias[o] as f64;
                    let found = output[(y * ow + x) * out_channels + o] as f64;
                    // Only the f32 rounding of the sum and the three f32 operations after it
                    // round: a few ulps of the magnitudes (an ulp is 6e-8 of them).
                    let tolerance = 4e-7 * (scaled.abs() + bias[o].abs() as f64).max(1e-6);
                    assert!(
                        (found - expected).abs() <= tolerance,
                        "case {case} ({y},{x},{o}): {found} vs {expected}"
                    );
                }
            }
        }
    }
}

/// Whole codes padded to quads, as `quantize_rows_codes` writes them: `rows` rows of
/// `channels` codes, each followed by zeros up to a multiple of 4.
fn padded_codes(codes: &[i32], channels: usize) -> Vec<i16> {
    let stride = channels.div_ceil(4) * 4;
    let mut padded = vec![0i16; codes.len() / channels.max(1) * stride];
    for (row, values) in codes.chunks_exact(channels).enumerate() {
        for (target, &code) in padded[row * stride..].iter_mut().zip(values) {
            *target = code as i16;
        }
    }
    padded
}

/// A random int8 convolution on signed codes: the codes (unpadded), their scale, the
/// weights (`[taps, in, out]` and packed in quads), weight scales and bias.
struct CodeCase {
    shape: ConvShape,
    codes: Vec<i32>,
    scale: f32,
    weight: Vec<i8>,
    packed: Vec<i8>,
    /// The same weights in the pair layout (`pack_int8_pairs`).
    pairs: Vec<i8>,
    weight_scales: Vec<f32>,
    bias: Vec<f32>,
}

impl CodeCase {
    fn random(rng: &mut Lcg, shape: ConvShape) -> Self {
        let codes = random_codes(rng, shape.input_len(), false)
            .into_iter()
            .map(|code| if rng.below(2) == 0 { -code } else { code })
            .collect();
        let weight = random_weights_with_extremes(rng, shape.weight_len());
        let mut packed = vec![1i8; shape.int8_weight_len()];
        let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
        scdp_engine::kernels::pack_int8_quads(&weight, in_channels, out_channels, &mut packed);
        let mut pairs = vec![1i8; shape.int8_pair_weight_len()];
        scdp_engine::kernels::pack_int8_pairs(&weight, in_channels, out_channels, &mut pairs);
        CodeCase {
            shape,
            codes,
            scale: 0.01 + rng.next().abs(),
            weight,
            packed,
            pairs,
            weight_scales: (0..out_channels)
                .map(|_| 0.001 + rng.next().abs() * 0.01)
                .collect(),
            bias: rng.vec(out_channels),
        }
    }

    /// [`CodeCase::run`] on the AMX tiles alone; panics if they did not take the shape.
    #[cfg(target_arch = "x86_64")]
    fn run_on_tiles(&self, amx: &Amx, accumulate: Accumulate, initial: &[f32]) -> Vec<f32> {
        let codes = padded_codes(&self.codes, self.shape.in_channels);
        let input = CodeRows {
            codes: &codes,
            scale: self.scale,
        };
        let mut output = initial.to_vec();
        let shape = &self.shape;
        let parameters = (&self.packed, &self.weight_scales, &self.bias);
        let taken = amx.conv_int8_codes_on_tiles(
            shape,
            &input,
            parameters.0,
            parameters.1,
            parameters.2,
            &mut output,
            accumulate,
        );
        assert!(taken, "the tiles did not take {shape:?}");
        output
    }

    /// [`CodeCase::run`] with the codes (which must fit a signed byte) as narrow signed
    /// codes: signed bytes and their row sums.
    fn run_signed_bytes(
        &self,
        kernels: &dyn Kernels,
        accumulate: Accumulate,
        initial: &[f32],
    ) -> Vec<f32> {
        self.run_signed_bytes_with(kernels, accumulate, initial, false)
    }

    /// [`CodeCase::run_signed_bytes`] given the weights' pair layout as well.
    fn run_signed_bytes_paired(
        &self,
        kernels: &dyn Kernels,
        accumulate: Accumulate,
        initial: &[f32],
    ) -> Vec<f32> {
        self.run_signed_bytes_with(kernels, accumulate, initial, true)
    }

    fn run_signed_bytes_with(
        &self,
        kernels: &dyn Kernels,
        accumulate: Accumulate,
        initial: &[f32],
        paired: bool,
    ) -> Vec<f32> {
        let codes: Vec<i8> = padded_codes(&self.codes, self.shape.in_channels)
            .into_iter()
            .map(|code| i8::try_from(code).unwrap())
            .collect();
        let stride = CodeRows::row_stride(self.shape.in_channels);
        let row_sums: Vec<i32> = codes
            .chunks_exact(stride)
            .map(|row| row.iter().map(|&code| i32::from(code)).sum())
            .collect();
        let input = SignedByteRows {
            codes: &codes,
            row_sums: &row_sums,
            scale: self.scale,
        };
        let mut output = initial.to_vec();
        let (shape, weight, scales, bias) =
            (&self.shape, &self.packed, &self.weight_scales, &self.bias);
        match paired {
            true => kernels.conv_int8_signed_bytes_paired(
                shape,
                &input,
                weight,
                &self.pairs,
                scales,
                bias,
                &mut output,
                accumulate,
            ),
            false => kernels.conv_int8_signed_bytes(
                shape,
                &input,
                weight,
                scales,
                bias,
                &mut output,
                accumulate,
            ),
        }
        output
    }

    fn run(&self, kernels: &dyn Kernels, accumulate: Accumulate, initial: &[f32]) -> Vec<f32> {
        let codes = padded_codes(&self.codes, self.shape.in_channels);
        let input = CodeRows {
            codes: &codes,
            scale: self.scale,
        };
        let mut output = initial.to_vec();
        kernels.conv_int8_codes(
            &self.shape,
            &input,
            &self.packed,
            &self.weight_scales,
            &self.bias,
            &mut output,
            accumulate,
        );
        output
    }
}

/// The U-Net's int8 convolutions (signed codes) against the textbook: the exact integer sum
/// over the kernel, scaled, in f64; and bit for bit what `conv_int8` computes on the digit
/// planes of the same codes (one contract, two storage forms).
#[test]
fn int8_code_convolution_sums_exactly_over_the_kernel_then_scales() {
    let mut rng = Lcg(19);
    for case in 0..60 {
        let kernel = [1, 3, 5][rng.below(3)];
        let stride = 1 + rng.below(2);
        let padding = rng.below(kernel / 2 + 1);
        let length = kernel + rng.below(17);
        let shape = ConvShape::sequence(
            length,
            1 + rng.below(70),
            1 + rng.below(300), // crosses the layout's 64-channel blocks
            kernel,
            stride,
            padding,
        );
        let code_case = CodeCase::random(&mut rng, shape);
        let CodeCase {
            codes,
            scale,
            weight,
            weight_scales,
            bias,
            ..
        } = &code_case;
        let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
        let output = code_case.run(
            &Scalar,
            Accumulate::Overwrite,
            &vec![f32::NAN; shape.output_len()],
        );
        for t in 0..shape.out_width() {
            for o in 0..out_channels {
                let mut sum = 0i64;
                for tap in 0..kernel {
                    let Some(row) = (t * stride + tap)
                        .checked_sub(padding)
                        .filter(|&row| row < length)
                    else {
                        continue;
                    };
                    sum += (0..in_channels)
                        .map(|i| {
                            codes[row * in_channels + i] as i64
                                * weight[(tap * in_channels + i) * out_channels + o] as i64
                        })
                        .sum::<i64>();
                }
                let scaled = sum as f64 * *scale as f64 * weight_scales[o] as f64;
                let expected = scaled + bias[o] as f64;
                let found = output[t * out_channels + o] as f64;
                // As for the digit planes: four f32 roundings.
                let tolerance = 4e-7 * (scaled.abs() + bias[o].abs() as f64).max(1e-6);
                assert!(
                    (found - expected).abs() <= tolerance,
                    "case {case} ({t},{o}): {found} vs {expected}"
                );
            }
        }
        let planes = digit_planes(codes);
        let digits = DigitRows::from_planes(&planes, *scale, false);
        let mut from_digits = vec![f32::NAN; shape.output_len()];
        Scalar.conv_int8(
            &shape,
            &digits,
            &code_case.packed,
            weight_scales,
            bias,
            &mut from_digits,
            Accumulate::Overwrite,
        );
        assert_same_bits(
            &output,
            &from_digits,
            &format!("case {case}: codes vs digits"),
        );
    }
}

/// Every backend's int8 convolution on signed codes gives the scalar reference's bits: the
/// U-Net's shapes (lengths 16, 8, 4, the k3 s2 downsampling, 1x1 residuals, the 10-channel
/// sample), channel counts off the tiles (in: not whole quads; out: one-vector and scalar
/// tails), a few 2-D maps, and both accumulate modes.
#[test]
fn int8_code_convolution_is_bit_identical_on_every_backend() {
    let mut rng = Lcg(29);
    let mut shapes = vec![
        ConvShape::sequence(16, 10, 128, 5, 1, 2),
        ConvShape::sequence(16, 128, 128, 5, 1, 2),
        ConvShape::sequence(16, 128, 128, 3, 2, 1),
        ConvShape::sequence(8, 128, 256, 1, 1, 0),
        ConvShape::sequence(4, 768, 256, 5, 1, 2),
        ConvShape::sequence(4, 384, 384, 5, 1, 2),
        ConvShape::square((5, 7, 12), 40, 3, 1, 1),
        ConvShape::square((6, 6, 9), 17, 3, 2, 1),
    ];
    for _ in 0..30 {
        let kernel = [1, 3, 5][rng.below(3)];
        shapes.push(ConvShape::sequence(
            1 + rng.below(20),
            1 + rng.below(90),
            [1, 5, 8, 16, 24, 31, 32, 40, 64, 96, 130][rng.below(11)],
            kernel,
            1 + rng.below(2),
            kernel / 2,
        ));
    }
    let shapes: Vec<ConvShape> = shapes
        .into_iter()
        .filter(|shape| shape.in_width + 2 * shape.padding_width >= shape.kernel_width)
        .collect();
    let backends = backends();
    for (case, &shape) in shapes.iter().enumerate() {
        let code_case = CodeCase::random(&mut rng, shape);
        let initial = rng.vec(shape.output_len());
        for accumulate in [Accumulate::Overwrite, Accumulate::Add] {
            let expected = code_case.run(&Scalar, accumulate, &initial);
            for (name, kernels) in &backends {
                let found = code_case.run(*kernels, accumulate, &initial);
                let what = format!("{name} case {case} {shape:?} {accumulate:?}");
                assert_same_bits(&found, &expected, &what);
            }
            // The tiles themselves on every shape of whole 32-channel blocks (as all the
            // U-Net's are), so one quietly sent to the vector kernels cannot pass for them.
            #[cfg(target_arch = "x86_64")]
            if let Some(amx) = Amx::detect().filter(|_| shape.out_channels.is_multiple_of(32)) {
                let found = code_case.run_on_tiles(amx, accumulate, &initial);
                let what = format!("tiles case {case} {shape:?} {accumulate:?}");
                assert_same_bits(&found, &expected, &what);
            }
        }
    }
}

/// The U-Net's narrow signed codes (|code| <= 127, one byte each) on every backend give the
/// bits of the scalar reference's 15-bit code convolution on the same codes widened to i16
/// (one contract, two storage forms; the wide one checked against the textbook above): the
/// U-Net's shapes, random ones with channel tails, codes at +-127 and weights at -128 and
/// 127, both accumulate modes. VNNI runs them as weights offset by 128 times signed bytes
/// less 128 times each pixel's code sum, which only the exact answer can hide.
#[test]
fn narrow_signed_code_convolution_equals_the_code_convolution_on_every_backend() {
    let mut rng = Lcg(97);
    let mut shapes = vec![
        ConvShape::sequence(16, 10, 128, 5, 1, 2),
        ConvShape::sequence(16, 128, 128, 5, 1, 2),
        ConvShape::sequence(8, 256, 256, 5, 1, 2),
        ConvShape::sequence(4, 768, 256, 5, 1, 2),
        ConvShape::sequence(4, 384, 384, 5, 1, 2),
        ConvShape::sequence(16, 128, 128, 3, 2, 1),
    ];
    for _ in 0..30 {
        let kernel = [1, 3, 5][rng.below(3)];
        shapes.push(ConvShape::sequence(
            1 + rng.below(20),
            1 + rng.below(90),
            [1, 5, 8, 16, 24, 31, 32, 40, 64, 96, 130][rng.below(11)],
            kernel,
            1 + rng.below(2),
            kernel / 2,
        ));
    }
    let shapes: Vec<ConvShape> = shapes
        .into_iter()
        .filter(|shape| shape.in_width + 2 * shape.padding_width >= shape.kernel_width)
        .collect();
    let backends = backends();
    for (case, &shape) in shapes.iter().enumerate() {
        let mut code_case = CodeCase::random(&mut rng, shape);
        code_case.codes = (0..shape.input_len())
            .map(|i| match i % 9 {
                2 => 127,
                5 => -127,
                6 => 0,
                _ => (rng.next() * 127.0).round() as i32,
            })
            .collect();
        let initial = rng.vec(shape.output_len());
        for accumulate in [Accumulate::Overwrite, Accumulate::Add] {
            let expected = code_case.run(&Scalar, accumulate, &initial);
            for (name, kernels) in &backends {
                let found = code_case.run_signed_bytes(*kernels, accumulate, &initial);
                let what = format!("{name} case {case} {shape:?} {accumulate:?}");
                assert_same_bits(&found, &expected, &what);
                let found = code_case.run_signed_bytes_paired(*kernels, accumulate, &initial);
                assert_same_bits(&found, &expected, &format!("{what} paired"));
            }
        }
        // The model's path (`layer::convolve` of a narrow layer): each backend quantizes
        // the same input, as signed bytes or (AVX2) as the same codes widened to 16 bits,
        // and convolves it.
        let values: Vec<f32> = rng.vec(shape.input_len()).iter().map(|x| x * 3.0).collect();
        let convolve = |kernels: &dyn Kernels| {
            let mut scratch =
                vec![0i8; 2 * shape.in_width * CodeRows::row_stride(shape.in_channels)];
            let mut quantize = QuantizeScratch {
                values: &mut scratch,
            };
            let mut output = vec![0.0; shape.output_len()];
            // Every other case with the pair layout, as a file may hold it.
            let weight = Weight::Int8 {
                values: &code_case.packed,
                scales: &code_case.weight_scales,
                activations: ActivationCodes::Narrow,
                residual: None,
                pairs: case.is_multiple_of(2).then_some(code_case.pairs.as_slice()),
            };
            layer::convolve(
                kernels,
                &shape,
                &values,
                &weight,
                &code_case.bias,
                &mut output,
                Accumulate::Overwrite,
                layer::Activations::Codes(&mut quantize),
            );
            output
        };
        let expected = convolve(&Scalar);
        for (name, kernels) in &backends {
            let what = format!("case {case} {shape:?} quantized narrow on {name}");
            assert_same_bits(&convolve(*kernels), &expected, &what);
        }
    }
}

/// The widest sums a narrow signed convolution can make (every code +-127, every weight
/// -128 or 127, 768 channels, 5 taps) come out exact on every backend: `(w + 128) c` then
/// less `128 sum c` must not lose a unit anywhere.
#[test]
fn narrow_signed_code_convolution_is_exact_at_the_extremes() {
    let (channels, out_channels) = (768, 64);
    let shape = ConvShape::sequence(4, channels, out_channels, 5, 1, 2);
    for (code, weight_value) in [
        (127i8, i8::MIN),
        (-127, i8::MIN),
        (127, i8::MAX),
        (-127, i8::MAX),
    ] {
        let codes = vec![code; shape.input_len()];
        let weight = vec![weight_value; shape.weight_len()];
        let mut packed = vec![0i8; shape.int8_weight_len()];
        scdp_engine::kernels::pack_int8_quads(&weight, channels, out_channels, &mut packed);
        let row_sums = vec![i32::from(code) * channels as i32; 4];
        let (ones, zeros) = (vec![1.0f32; out_channels], vec![0.0f32; out_channels]);
        let input = SignedByteRows {
            codes: &codes,
            row_sums: &row_sums,
            scale: 1.0,
        };
        for (name, kernels) in backends() {
            let mut output = vec![f32::NAN; shape.output_len()];
            let (ones, zeros) = (&ones, &zeros);
            kernels.conv_int8_signed_bytes(
                &shape,
                &input,
                &packed,
                ones,
                zeros,
                &mut output,
                Accumulate::Overwrite,
            );
            for position in 0..4 {
                // Positions 0 and 3 have two taps in the padding, 1 and 2 one.
                let taps = [3, 4, 4, 3][position] as i64;
                let exact = i64::from(code) * i64::from(weight_value) * channels as i64 * taps;
                for &value in &output[position * out_channels..][..out_channels] {
                    assert_eq!(
                        value, exact as f32,
                        "{name} {code} x {weight_value} at {position}"
                    );
                }
            }
        }
    }
}

/// Narrow signed codes quantize within half a step of the input (one scale: the largest
/// magnitude is code 127), keep the sign, pad rows with zeros, carry each row's code sum,
/// and come out the same on every backend; a non-finite value gives a NaN scale and zero
/// codes.
#[test]
fn narrow_signed_quantization_round_trips_with_row_sums() {
    let mut rng = Lcg(43);
    for (rows, row_len) in [(16, 10), (4, 768), (8, 257), (1, 3)] {
        let input: Vec<f32> = rng.vec(rows * row_len).iter().map(|x| x * 4.0).collect();
        let mut non_finite = input.clone();
        non_finite[(rows - 1) * row_len] = f32::INFINITY;
        let stride = CodeRows::row_stride(row_len);
        let quantize = |kernels: &dyn Kernels, input: &[f32]| {
            let mut codes = vec![7i8; rows * stride];
            let mut row_sums = vec![7i32; rows];
            let scale = kernels.quantize_signed_bytes(input, row_len, &mut codes, &mut row_sums);
            (codes, row_sums, scale)
        };
        let (codes, row_sums, scale) = quantize(&Scalar, &input);
        let largest = input.iter().fold(0.0f32, |m, x| m.max(x.abs()));
        assert_eq!(scale, largest / 127.0);
        assert!(codes.iter().any(|&c| c.abs() == 127));
        for row in 0..rows {
            let values = &input[row * row_len..][..row_len];
            let row_codes = &codes[row * stride..][..stride];
            assert!(
                row_codes[row_len..].iter().all(|&c| c == 0),
                "padding of row {row}"
            );
            let sum: i32 = row_codes.iter().map(|&c| i32::from(c)).sum();
            assert_eq!(row_sums[row], sum, "sum of row {row}");
            for (&value, &code) in values.iter().zip(row_codes) {
                assert!(code != i8::MIN);
                // Half a step, plus the f32 roundings of `x * (127 / max)`.
                let error = (value as f64 - code as f64 * scale as f64).abs();
                assert!(error <= 0.501 * scale as f64, "{value} -> {code}");
            }
        }
        let (nan_codes, nan_sums, nan_scale) = quantize(&Scalar, &non_finite);
        assert!(nan_scale.is_nan());
        assert!(nan_codes.iter().all(|&c| c == 0) && nan_sums.iter().all(|&s| s == 0));
        for (name, kernels) in backends() {
            let found = quantize(kernels, &input);
            assert_eq!((&found.0, &found.1), (&codes, &row_sums), "{name} codes");
            assert_eq!(found.2.to_bits(), scale.to_bits(), "{name} scale");
        }
    }
}

/// The AMX tiles' short-sequence pass (one output row of at most 8 positions, both digits in
/// one tile, 64 channels a pass) gives the scalar reference's bits: the U-Net's sequences
/// of 8 and 4 and its downsamplings to them, one-position and unpadded outputs, several
/// 64-channel blocks and steps, both accumulate modes. Each shape is checked to be one the
/// pass takes, so a change to what it takes cannot leave it untested.
#[cfg(target_arch = "x86_64")]
#[test]
fn amx_short_sequences_are_bit_identical_to_the_scalar_reference() {
    // Fails here when CI requires the amx backend and it cannot run.
    backends();
    let Some(amx) = Amx::detect() else {
        eprintln!("no AMX on this machine: the short-sequence pass cannot run here");
        return;
    };
    let mut rng = Lcg(31);
    let mut shapes = vec![
        ConvShape::sequence(8, 128, 256, 5, 1, 2),
        ConvShape::sequence(8, 256, 256, 1, 1, 0),
        ConvShape::sequence(16, 128, 128, 3, 2, 1),
        ConvShape::sequence(8, 256, 256, 3, 2, 1),
        ConvShape::sequence(4, 768, 256, 5, 1, 2),
        ConvShape::sequence(4, 384, 384, 5, 1, 2),
        ConvShape::sequence(1, 64, 64, 5, 1, 2),
        ConvShape::sequence(3, 192, 128, 3, 1, 0),
        ConvShape::sequence(7, 64, 192, 5, 2, 2),
    ];
    while shapes.len() < 40 {
        let kernel = [1, 3, 5][rng.below(3)];
        let shape = ConvShape::sequence(
            1 + rng.below(16),
            64 * (1 + rng.below(6)),
            64 * (1 + rng.below(3)),
            kernel,
            1 + rng.below(2),
            rng.below(kernel / 2 + 1),
        );
        if shape.in_width + 2 * shape.padding_width >= kernel && shape.out_width() <= 8 {
            shapes.push(shape);
        }
    }
    for (case, &shape) in shapes.iter().enumerate() {
        let code_case = CodeCase::random(&mut rng, shape);
        let codes = padded_codes(&code_case.codes, shape.in_channels);
        let input = CodeRows {
            codes: &codes,
            scale: code_case.scale,
        };
        assert!(
            Amx::covers_short_sequence(&shape, &input),
            "case {case}: the short-sequence pass does not take {shape:?}"
        );
        let initial = rng.vec(shape.output_len());
        for accumulate in [Accumulate::Overwrite, Accumulate::Add] {
            let expected = code_case.run(&Scalar, accumulate, &initial);
            let found = code_case.run_on_tiles(amx, accumulate, &initial);
            let what = format!("short case {case} {shape:?} {accumulate:?}");
            assert_same_bits(&found, &expected, &what);
        }
    }
}

/// The codes' sums are exact at the extremes: every code +-16383 against weights of -128
/// and 127 (the largest products, either sign) over `MAX_DIGIT_CHANNELS` input channels
/// and three taps, three times what i32 holds, on every backend, against the f32 rounding of
/// the exact sum.
#[test]
fn int8_code_convolution_is_exact_at_the_extremes() {
    let channels = scdp_engine::kernels::MAX_DIGIT_CHANNELS;
    // 64 output channels: the tiles' short-sequence pass; 32: their general kernel.
    for out_channels in [32, 64] {
        code_convolution_is_exact_at_the_extremes(channels, out_channels);
    }
}

fn code_convolution_is_exact_at_the_extremes(channels: usize, out_channels: usize) {
    let shape = ConvShape::sequence(4, channels, out_channels, 3, 1, 0);
    for (positive_codes, weight_value) in [(true, i8::MIN), (false, i8::MIN), (true, i8::MAX)] {
        let code = if positive_codes { 16383 } else { -16383 };
        let codes = vec![code as i16; shape.input_len()];
        let weight = vec![weight_value; shape.weight_len()];
        let mut packed = vec![0i8; shape.int8_weight_len()];
        scdp_engine::kernels::pack_int8_quads(&weight, channels, out_channels, &mut packed);
        let ones = vec![1.0f32; out_channels];
        let zeros = vec![0.0f32; out_channels];
        let exact = code as i64 * weight_value as i64 * channels as i64 * 3;
        assert!(exact.abs() > 2 * i32::MAX as i64);
        for (name, kernels) in backends() {
            let mut output = vec![f32::NAN; shape.output_len()];
            let input = CodeRows {
                codes: &codes,
                scale: 1.0,
            };
            kernels.conv_int8_codes(
                &shape,
                &input,
                &packed,
                &ones,
                &zeros,
                &mut output,
                Accumulate::Overwrite,
            );
            for &value in &output {
                assert_eq!(value, exact as f32, "{name} {code} x {weight_value}");
            }
        }
        // The tiles split these codes into a high digit of -128 or 127.
        #[cfg(target_arch = "x86_64")]
        if let Some(amx) = Amx::detect() {
            let mut output = vec![f32::NAN; shape.output_len()];
            let input = CodeRows {
                codes: &codes,
                scale: 1.0,
            };
            assert_eq!(
                Amx::covers_short_sequence(&shape, &input),
                out_channels == 64,
                "which tile kernel takes {shape:?}"
            );
            let parameters = (&packed, &ones, &zeros);
            let taken = amx.conv_int8_codes_on_tiles(
                &shape,
                &input,
                parameters.0,
                parameters.1,
                parameters.2,
                &mut output,
                Accumulate::Overwrite,
            );
            assert!(taken, "the tiles did not take {shape:?}");
            for &value in &output {
                assert_eq!(value, exact as f32, "tiles {code} x {weight_value}");
            }
        }
    }
}

/// Codes quantize within half a step of the input (one scale: the largest magnitude is
/// code 16383), keep the sign, pad rows to whole quads with zeros, and give the same codes
/// and scale on every backend; a non-finite value anywhere gives a NaN scale and zero
/// codes.
#[test]
fn code_quantization_round_trips_and_pads_rows() {
    let mut rng = Lcg(41);
    for (rows, row_len) in [(16, 10), (4, 768), (8, 257), (1, 3)] {
        let mut input: Vec<f32> = rng.vec(rows * row_len).iter().map(|x| x * 4.0).collect();
        if rows > 1 {
            input[..row_len].fill(0.0);
        }
        let mut non_finite = input.clone();
        non_finite[(rows - 1) * row_len] = f32::NAN;
        let stride = row_len.div_ceil(4) * 4;
        let quantize = |kernels: &dyn Kernels, input: &[f32]| {
            let mut codes = vec![7i16; rows * stride];
            let scale = kernels.quantize_codes(input, row_len, &mut codes);
            (codes, scale)
        };
        let (codes, scale) = quantize(&Scalar, &input);
        let largest = input.iter().fold(0.0f32, |m, x| m.max(x.abs()));
        assert_eq!(scale, largest / 16383.0);
        assert!(codes.iter().any(|&c| c.abs() == 16383));
        for row in 0..rows {
            let values = &input[row * row_len..][..row_len];
            let row_codes = &codes[row * stride..][..stride];
            assert!(
                row_codes[row_len..].iter().all(|&c| c == 0),
                "padding of row {row}"
            );
            for (&value, &code) in values.iter().zip(row_codes) {
                assert!(code.abs() <= 16383);
                // Half a step, plus the f32 roundings of `x * (16383 / max)` (a few 2^-24
                // of a code up to 16383: under 0.004 of a step).
                let error = (value as f64 - code as f64 * scale as f64).abs();
                assert!(error <= 0.504 * scale as f64, "{value} -> {code}");
            }
        }
        let zeros = vec![0.0; input.len()];
        assert_eq!(quantize(&Scalar, &zeros), (vec![0; rows * stride], 1.0));
        let (nan_codes, nan_scale) = quantize(&Scalar, &non_finite);
        assert!(nan_scale.is_nan());
        assert!(nan_codes.iter().all(|&c| c == 0));
        for (name, kernels) in backends() {
            let (found_codes, found_scale) = quantize(kernels, &input);
            assert_eq!(found_codes, codes, "{name} codes");
            assert_eq!(found_scale.to_bits(), scale.to_bits(), "{name} scale");
            let (found_codes, found_scale) = quantize(kernels, &non_finite);
            assert!(
                found_scale.is_nan() && found_codes == nan_codes,
                "{name} non-finite"
            );
        }
    }
}

/// The FiLM layers' product on every backend against the textbook: the exact integer sum
/// of codes times int8 weights (i64), rounded once to f32, then scaled and added as the
/// contract orders it (f32 products, not fused), so the bits must agree exactly. Column
/// counts around the vector steps (32 codes on AVX-512, 16 on AVX2), the 4x-unrolled loop,
/// the i32 segments of 1024 columns (1025, 3000), the model's 656 and 658; codes at
/// +-16383 and weights at -128 and 127 in the extreme cases, whose sums exceed i32 beyond
/// 1024 columns.
#[test]
fn int8_code_matrix_vector_product_is_exact_then_scaled() {
    let mut rng = Lcg(23);
    let shapes = [
        (37, 91),
        (1, 7),
        (4, 32),
        (3, 33),
        (5, 128),
        (6, 656),
        (2, 658),
        (3, 1024),
        (2, 1025),
        (2, 3000),
        (0, 16),
    ];
    for (case, (rows, cols)) in shapes.into_iter().enumerate() {
        for extreme in [false, true] {
            let weight: Vec<i8> = if extreme {
                (0..rows * cols)
                    .map(|i| if i % 5 == 0 { -128 } else { 127 })
                    .collect()
            } else {
                random_weights_with_extremes(&mut rng, rows * cols)
            };
            let codes: Vec<i32> = if extreme {
                (0..cols)
                    .map(|c| if c % 7 == 3 { 16383 } else { -16383 })
                    .collect()
            } else {
                random_codes(&mut rng, cols, false)
            };
            let padded = padded_codes(&codes, cols);
            let input = CodeRows {
                codes: &padded,
                scale: 1e-4 + rng.next().abs() * 1e-3,
            };
            let scales: Vec<f32> = (0..rows).map(|_| 0.002 + rng.next().abs() * 0.01).collect();
            let base = rng.vec(rows);
            let expected: Vec<f32> = (0..rows)
                .map(|r| {
                    let sum: i64 = (0..cols)
                        .map(|c| weight[r * cols + c] as i64 * codes[c] as i64)
                        .sum();
                    base[r] + (sum as f32 * input.scale) * scales[r]
                })
                .collect();
            for (name, kernels) in backends() {
                let mut found = vec![f32::NAN; rows];
                kernels.matvec_int8_codes(&weight, &scales, &input, &base, &mut found);
                assert_same_bits(
                    &found,
                    &expected,
                    &format!("case {case} {name} {rows}x{cols} extreme {extreme}"),
                );
            }
        }
    }
}

/// Random int8 weights, with the extremes -128 and 127 forced in now and then.
fn random_weights_with_extremes(rng: &mut Lcg, len: usize) -> Vec<i8> {
    random_i8(rng, len)
        .into_iter()
        .enumerate()
        .map(|(i, q)| match i % 11 {
            3 => i8::MIN,
            7 => i8::MAX,
            _ => q,
        })
        .collect()
}

/// The U-Net's sequence shapes and their awkward cousins, on every backend against the
/// textbook convolution: lengths around the 4-position tiles, channel counts that leave
/// one-vector (8 or 16 wide) and scalar tails, the k3 s2 p1 downsampling (f32 weights; int8
/// ones take int8 activations, tested below).
#[test]
fn sequence_convolutions_match_pytorch_definition() {
    let mut rng = Lcg(31);
    let mut shapes = Vec::new();
    for length in [1, 2, 3, 4, 5, 8, 16, 17] {
        for (kernel, stride, padding) in [(5, 1, 2), (3, 2, 1), (1, 1, 0), (3, 1, 0), (4, 2, 2)] {
            if length + 2 * padding < kernel {
                continue;
            }
            let in_channels = 1 + rng.below(70);
            let out_channels = [1, 7, 8, 13, 16, 24, 31, 40, 48, 64, 129][rng.below(11)];
            shapes.push(ConvShape::sequence(
                length,
                in_channels,
                out_channels,
                kernel,
                stride,
                padding,
            ));
        }
    }
    for (name, kernels) in backends() {
        for shape in &shapes {
            let input_ct = rng.vec(shape.input_len());
            let input = to_hwc(&input_ct, shape.in_channels, 1, shape.in_width);
            let bias = rng.vec(shape.out_channels);
            // Row-major PyTorch `[out, in, k]` weights.
            let float_oik = rng.vec(shape.weight_len());
            let (k, i, o) = (shape.kernel_width, shape.in_channels, shape.out_channels);
            let float_packed = pack_oihw(&float_oik, o, i, 1, k);
            let what = format!("{name} {shape:?}");
            for accumulate in [Accumulate::Overwrite, Accumulate::Add] {
                let before = if accumulate == Accumulate::Add {
                    rng.vec(shape.output_len())
                } else {
                    vec![f32::NAN; shape.output_len()]
                };
                let plus_before = |expected: Vec<f64>| -> Vec<f64> {
                    match accumulate {
                        Accumulate::Overwrite => expected,
                        Accumulate::Add => expected
                            .iter()
                            .zip(&before)
                            .map(|(e, b)| e + *b as f64)
                            .collect(),
                    }
                };
                let (expected, magnitude) = reference_conv(shape, &input_ct, &float_oik, &bias);
                let mut output = before.clone();
                kernels.conv(shape, &input, &float_packed, &bias, &mut output, accumulate);
                assert_close(&output, &plus_before(expected), &magnitude, &what);
            }
        }
    }
}

#[test]
fn symmetric_quantization_round_trips_within_half_a_step() {
    let mut rng = Lcg(29);
    let input: Vec<f32> = (0..1000).map(|_| rng.next() * 3.0).collect();
    let mut quantized = vec![0i8; input.len()];
    let scale = ops::quantize_symmetric(&input, &mut quantized);
    let largest = input.iter().fold(0.0f32, |m, x| m.max(x.abs()));
    assert_eq!(scale, largest / 127.0);
    assert!(quantized.iter().any(|&q| q.unsigned_abs() == 127));
    for (&x, &q) in input.iter().zip(&quantized) {
        assert!(
            (q as f32 * scale - x).abs() <= 0.5 * scale * (1.0 + 1e-5),
            "{x} -> {q}"
        );
    }
    let mut zeros = vec![1i8; 4];
    assert_eq!(ops::quantize_symmetric(&[0.0; 4], &mut zeros), 1.0);
    assert_eq!(zeros, [0; 4]);
    // Non-finite input must not be hidden: the scale carries the NaN into the result.
    assert!(ops::quantize_symmetric(&[1.0, f32::NAN, 2.0], &mut [0; 3]).is_nan());
    assert!(ops::quantize_symmetric(&[1.0, f32::INFINITY], &mut [0; 2]).is_nan());
}

/// The ID registers firmware reads say what the OS says (Linux, and qemu's user mode that
/// CI's aarch64 runs use, emulate the reads): the firmware path's detection, checked at every
/// emulated CPU level.
#[cfg(all(target_arch = "aarch64", target_os = "linux"))]
#[test]
fn firmware_feature_registers_agree_with_the_os() {
    use scdp_engine::kernels::aarch64::registers;
    use std::arch::is_aarch64_feature_detected;
    let dotprod = is_aarch64_feature_detected!("dotprod");
    assert_eq!(registers::has_dotprod(), dotprod, "dot product");
    let i8mm = is_aarch64_feature_detected!("i8mm") && dotprod;
    assert_eq!(registers::has_i8mm(), i8mm, "i8mm");
}

/// An input so close to zero that `limit / max |x|` overflows f32 (max |x| below
/// `limit / f32::MAX`: 4.8e-35 for 15-bit codes, 7.5e-37 for bytes, 3.7e-37 for signed
/// bytes; a fuzzed layer input reached it) quantizes as all zeros with scale 1, like an
/// all-zero input, on every quantizer and backend: computing its codes would round an
/// infinite product (undefined in the rounding's unchecked conversion; an overflow panic in
/// checked builds). Just above the threshold the codes are still computed, the largest value
/// taking the largest code. Negative values where the quantizer is signed.
#[test]
fn quantizing_a_near_zero_input_gives_zero_codes_on_every_backend() {
    let near_zero = [1e-37f32, -2e-38, 0.0, 5e-45, -1e-45, 3e-38, 0.0, 1e-40];
    let nonnegative: Vec<f32> = near_zero.iter().map(|x| x.abs()).collect();
    // Large enough for every limit (the factor 255 / 1e-30 is finite), still tiny.
    let small: Vec<f32> = near_zero.iter().map(|x| x * 1e7).collect();
    let small_nonnegative: Vec<f32> = small.iter().map(|x| x.abs()).collect();
    let (rows, row_len) = (2, 4);
    let stride = CodeRows::row_stride(row_len);
    for (name, kernels) in backends() {
        let mut digits = (vec![9i8; 8], vec![9i8; 8]);
        let found = kernels.quantize_digits(&near_zero, (&mut digits.0, &mut digits.1));
        assert_eq!(found, (1.0, true), "{name} digits");
        assert!(digits.0.iter().chain(&digits.1).all(|&d| d == 0), "{name}");
        let mut codes = vec![9i16; rows * stride];
        assert_eq!(kernels.quantize_codes(&near_zero, row_len, &mut codes), 1.0);
        assert!(codes.iter().all(|&c| c == 0), "{name} codes");
        let mut codes = vec![9i16; rows * stride];
        let scale = kernels.quantize_narrow_codes(&near_zero, row_len, &mut codes);
        assert_eq!(scale, 1.0, "{name} narrow codes");
        assert!(codes.iter().all(|&c| c == 0), "{name} narrow codes");
        let (mut bytes, mut sums) = (vec![9i8; rows * stride], vec![9i32; rows]);
        let scale = kernels.quantize_signed_bytes(&near_zero, row_len, &mut bytes, &mut sums);
        assert_eq!(scale, 1.0, "{name} signed bytes");
        assert!(bytes.iter().all(|&b| b == 0) && sums == [0, 0], "{name}");
        for form in [NarrowForm::Bytes, NarrowForm::Digits] {
            let mut scratch = vec![9i8; 16];
            let scale = kernels.quantize_narrow(&nonnegative, &mut scratch, form);
            assert_eq!(scale, 1.0, "{name} narrow {form:?}");
            let used = if form == NarrowForm::Bytes { 8 } else { 16 };
            assert!(scratch[..used].iter().all(|&b| b == 0), "{name} {form:?}");
        }
        // Just above: codes computed, the largest magnitude (the first value) on the
        // largest code.
        let largest = small[0];
        let mut codes = vec![0i16; rows * stride];
        let scale = kernels.quantize_codes(&small, row_len, &mut codes);
        assert_eq!(scale, largest / 16383.0, "{name} small codes");
        assert_eq!(codes[0], 16383, "{name} small codes {codes:?}");
        let mut scratch = vec![0i8; 8];
        let scale = kernels.quantize_narrow(&small_nonnegative, &mut scratch, NarrowForm::Bytes);
        assert_eq!(scale, largest / 255.0, "{name} small bytes");
        assert_eq!(scratch[0] as u8, 255, "{name} small bytes {scratch:?}");
    }
    let mut symmetric = [9i8; 8];
    assert_eq!(ops::quantize_symmetric(&near_zero, &mut symmetric), 1.0);
    assert_eq!(symmetric, [0; 8]);
}

/// One int8 convolution problem: quantized input, kernel in the engine's layout, parameters.
struct Int8Case {
    shape: ConvShape,
    /// 15-bit activation codes, `[H, W, in]`.
    values: Vec<i32>,
    scale: f32,
    nonnegative: bool,
    /// `[kh, kw, in, out]`, before packing.
    weight: Vec<i8>,
    weight_scales: Vec<f32>,
    bias: Vec<f32>,
}

impl Int8Case {
    fn random(rng: &mut Lcg, shape: ConvShape, nonnegative: bool) -> Self {
        Int8Case {
            values: random_codes(rng, shape.input_len(), nonnegative),
            scale: 0.01 + rng.next().abs(),
            nonnegative,
            weight: random_i8(rng, shape.weight_len()),
            weight_scales: (0..shape.out_channels)
                .map(|_| 0.001 + rng.next().abs() * 0.01)
                .collect(),
            bias: rng.vec(shape.out_channels),
            shape,
        }
    }

    /// The output of `kernels`, starting from `initial` (for [`Accumulate::Add`]).
    fn run(&self, kernels: &dyn Kernels, accumulate: Accumulate, initial: &[f32]) -> Vec<f32> {
        let (packed, planes) = self.packed();
        let input = DigitRows::from_planes(&planes, self.scale, self.nonnegative);
        let mut output = initial.to_vec();
        kernels.conv_int8(
            &self.shape,
            &input,
            &packed,
            &self.weight_scales,
            &self.bias,
            &mut output,
            accumulate,
        );
        output
    }

    /// The kernel in the quad layout and the codes as digit planes.
    fn packed(&self) -> (Vec<i8>, Vec<i8>) {
        let shape = &self.shape;
        let mut packed = vec![0i8; shape.int8_weight_len()];
        let channels = (shape.in_channels, shape.out_channels);
        scdp_engine::kernels::pack_int8_quads(&self.weight, channels.0, channels.1, &mut packed);
        (packed, digit_planes(&self.values))
    }
}

impl Int8Case {
    /// The layout the AMX tiles copy this case's input in.
    #[cfg(target_arch = "x86_64")]
    fn tile_layout(&self) -> Option<TileLayout> {
        let (_, planes) = self.packed();
        let input = DigitRows::from_planes(&planes, self.scale, self.nonnegative);
        Amx::tile_layout(&self.shape, &input)
    }

    /// [`Int8Case::run`] on the AMX tiles alone; panics if they did not take the shape.
    #[cfg(target_arch = "x86_64")]
    fn run_on_tiles(&self, amx: &Amx, accumulate: Accumulate, initial: &[f32]) -> Vec<f32> {
        let (packed, planes) = self.packed();
        let input = DigitRows::from_planes(&planes, self.scale, self.nonnegative);
        let mut output = initial.to_vec();
        let shape = &self.shape;
        assert!(
            amx.conv_int8_on_tiles(
                shape,
                &input,
                &packed,
                &self.weight_scales,
                &self.bias,
                &mut output,
                accumulate
            ),
            "the tiles did not take {shape:?}"
        );
        output
    }
}

fn assert_same_bits(found: &[f32], expected: &[f32], what: &str) {
    assert_eq!(found.len(), expected.len(), "{what}: length");
    for (index, (f, e)) in found.iter().zip(expected).enumerate() {
        assert!(
            f.to_bits() == e.to_bits(),
            "{what}[{index}]: {f} vs {e} (bits {:#x} vs {:#x})",
            f.to_bits(),
            e.to_bits()
        );
    }
}

/// Every backend gives the scalar reference's int8 convolution bit for bit, over the shapes
/// the tiles treat differently: kernels 1/3/7, strides 1/2, padding, maps of one and a few
/// pixels (tiles wrapping onto the next row, short last tiles), input channels from 4 to 512
/// and ones not a multiple of 4, output channels off the 64/16/8-channel blocks, both
/// accumulation modes, nonnegative (ReLU) rows and rows with negative values.
#[test]
fn int8_convolution_is_bit_identical_on_every_backend() {
    let mut rng = Lcg(29);
    let backends = backends();
    for case in 0..120 {
        let kernel = [1, 3, 7][rng.below(3)];
        let stride = 1 + rng.below(2);
        let padding = rng.below(kernel / 2 + 1);
        let in_channels = match case % 6 {
            0 => [4, 8, 12][rng.below(3)],
            1 => 4 * (1 + rng.below(40)),
            2 => [256, 512][rng.below(2)],
            3 => [1, 3, 6, 13][rng.below(4)],
            _ => 4 * (1 + rng.below(20)),
        };
        let out_channels = match case % 4 {
            0 => 64 * (1 + rng.below(3)),
            1 => 16 * (1 + rng.below(6)) + [0, 8, 5][rng.below(3)],
            2 => 1 + rng.below(30),
            _ => 1 + rng.below(150),
        };
        // Big channel counts on small maps, to keep the debug-build reference quick.
        let large = in_channels * kernel * kernel > 1200;
        let (height, width) = match case % 5 {
            0 => (1, 1),
            1 => (2, 3),
            _ if large => (1 + rng.below(4), 1 + rng.below(5)),
            _ => (1 + rng.below(9), 1 + rng.below(11)),
        };
        let shape = ConvShape::square(
            (height, width, in_channels),
            out_channels,
            kernel,
            stride,
            padding,
        );
        if height.min(width) + 2 * padding < kernel {
            continue; // no output pixel
        }
        let nonnegative = case % 7 != 0;
        let problem = Int8Case::random(&mut rng, shape, nonnegative);
        let initial = rng.vec(shape.output_len());
        for accumulate in [Accumulate::Overwrite, Accumulate::Add] {
            let expected = problem.run(&Scalar, accumulate, &initial);
            for (name, kernels) in &backends {
                let found = problem.run(*kernels, accumulate, &initial);
                assert_same_bits(
                    &found,
                    &expected,
                    &format!(
                        "case {case} {name} {shape:?} {accumulate:?} nonnegative {nonnegative}"
                    ),
                );
            }
        }
    }
}

/// The shapes the AMX tiles take (whole input-channel quads up to 512, output channels a
/// multiple of 32), over the cases they treat differently: activation tiles loaded in place
/// (rows equally spaced: inside a map, strides 1 and 2, 1x1 kernels over whole maps) or
/// gathered (padding, tiles wrapping onto the next output row, the short last tile of a map,
/// maps smaller than a tile, a last 64-channel step only partly filled: 196 is the stem's
/// patches), pixel groups of one and several blocks, both accumulation modes. Bit for bit
/// against the scalar reference on every backend.
#[test]
fn int8_convolution_on_matrix_tiles_is_bit_identical() {
    let mut rng = Lcg(31);
    let backends = backends();
    let mut layouts = Vec::new();
    let maps = [
        (1, 1),
        (3, 5),
        (8, 10),
        (5, 17),
        (16, 16),
        (12, 40),
        (2, 33),
    ];
    for case in 0..40 {
        let kernel = [1, 3][case % 2];
        let stride = 1 + (case / 2) % 2;
        let padding = if kernel == 3 { (case / 4) % 2 } else { 0 };
        let in_channels = [64, 128, 256, 512, 196, 4, 100][(case / 3) % 7];
        let out_channels = [32, 64, 96][case % 3];
        let (height, width) = maps[case % maps.len()];
        if height.min(width) + 2 * padding < kernel {
            continue;
        }
        // Keep the reference quick: the widest inputs on the smaller maps.
        let (height, width) = if in_channels >= 256 {
            (height.min(8), width.min(17))
        } else {
            (height, width)
        };
        let shape = ConvShape::square(
            (height, width, in_channels),
            out_channels,
            kernel,
            stride,
            padding,
        );
        layouts.push(check_on_tiles(
            &mut rng,
            &backends,
            shape,
            &format!("case {case}"),
        ));
    }
    // Rows too wide for one band of the tiles' stack buffer (75 pixels of 512 channels, three
    // rows of them): a band is then a span of one row's columns.
    for stride in [1, 2] {
        let shape = ConvShape::square((3, 75, 512), 32, 3, stride, 1);
        layouts.push(check_on_tiles(&mut rng, &backends, shape, "wide rows"));
    }
    // The metaworld trunk's small maps, where the grid layout's dropped positions would cost
    // whole tiles (fewer output channels than the model's, to keep the reference quick).
    for shape in [
        ConvShape::square((4, 4, 512), 64, 3, 1, 1),
        ConvShape::square((8, 8, 256), 64, 3, 2, 1),
        ConvShape::square((16, 16, 128), 64, 1, 2, 0),
    ] {
        layouts.push(check_on_tiles(&mut rng, &backends, shape, "small map"));
    }
    // Both ways of laying a band out ran, when the tiles are here.
    #[cfg(target_arch = "x86_64")]
    if Amx::detect().is_some() {
        for layout in [TileLayout::Grid, TileLayout::KernelColumns] {
            assert!(
                layouts.contains(&Some(layout)),
                "no shape ran in {layout:?}"
            );
        }
    }
}

/// A random int8 convolution of `shape` on every backend and on the AMX tiles alone, bit
/// for bit against the scalar reference, overwriting and adding; the layout the tiles
/// copied its input in (`None` without them).
fn check_on_tiles(
    rng: &mut Lcg,
    backends: &[(&str, &dyn Kernels)],
    shape: ConvShape,
    case: &str,
) -> Option<TileLayout> {
    let problem = Int8Case::random(rng, shape, true);
    #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
    let mut layout = None;
    let initial = rng.vec(shape.output_len());
    for accumulate in [Accumulate::Overwrite, Accumulate::Add] {
        let expected = problem.run(&Scalar, accumulate, &initial);
        for (name, kernels) in backends {
            let found = problem.run(*kernels, accumulate, &initial);
            let what = format!("{case} {name} {shape:?} {accumulate:?}");
            assert_same_bits(&found, &expected, &what);
        }
        // The tiles themselves, so a shape quietly sent elsewhere cannot pass for them.
        #[cfg(target_arch = "x86_64")]
        if let Some(amx) = Amx::detect() {
            let found = problem.run_on_tiles(amx, accumulate, &initial);
            let what = format!("{case} tiles {shape:?} {accumulate:?}");
            assert_same_bits(&found, &expected, &what);
            layout = problem.tile_layout();
        }
    }
    layout
}

/// The pointwise int8 convolution on bytes (the stem's patches): every backend and the AMX
/// tiles alone against the scalar reference, and the reference against `conv_int8` on the
/// bytes split into digits, bit for bit; bytes 0 and 255 and weights -128 and 127 included,
/// pixel counts around the tiles' blocks of 32, channel counts the tiles take and do not.
#[test]
fn byte_convolution_equals_the_digit_convolution_on_every_backend() {
    let mut rng = Lcg(77);
    let backends = backends();
    #[cfg(target_arch = "x86_64")]
    let mut on_tiles = 0;
    for case in 0..24 {
        let pixels = [1, 15, 16, 17, 31, 32, 33, 9 * 160][case % 8];
        let in_channels = [196, 4, 64, 256, 6, 100][case % 6];
        let out_channels = [64, 32, 96, 40][case % 4];
        let shape = ConvShape::square((1, pixels, in_channels), out_channels, 1, 1, 0);
        let problem = ByteCase::random(&mut rng, shape, 1.0 / 255.0);
        let initial = rng.vec(shape.output_len());
        for accumulate in [Accumulate::Overwrite, Accumulate::Add] {
            let what = format!("case {case} {shape:?} {accumulate:?}");
            let expected = problem.check_backends(&backends, accumulate, &initial, &what);
            // The AMX tiles alone, where this architecture has them.
            #[cfg(target_arch = "x86_64")]
            if problem.check_tiles(accumulate, &initial, &expected, &what) {
                on_tiles += 1;
            }
            #[cfg(not(target_arch = "x86_64"))]
            let _ = expected;
        }
    }
    #[cfg(target_arch = "x86_64")]
    if Amx::detect().is_some() {
        assert!(on_tiles >= 10, "only {on_tiles} cases ran on the tiles");
    }
}

/// A convolution on whole bytes: bytes 0 and 255 among random ones, weights -128 and 127
/// among random ones (packed), random scales and bias.
struct ByteCase {
    shape: ConvShape,
    bytes: Vec<u8>,
    scale: f32,
    packed: Vec<i8>,
    /// The same weights in the pair layout (`pack_int8_pairs`).
    pairs: Vec<i8>,
    weight_scales: Vec<f32>,
    bias: Vec<f32>,
}

impl ByteCase {
    fn random(rng: &mut Lcg, shape: ConvShape, scale: f32) -> Self {
        let bytes = (0..shape.input_len())
            .map(|i| match i % 7 {
                0 => 255,
                1 => 0,
                _ => (rng.next().abs() * 255.0) as u8,
            })
            .collect();
        let mut weight = random_i8(rng, shape.weight_len());
        weight[0] = -128;
        weight[shape.weight_len() - 1] = 127;
        let mut packed = vec![0i8; shape.int8_weight_len()];
        let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
        scdp_engine::kernels::pack_int8_quads(&weight, in_channels, out_channels, &mut packed);
        let mut pairs = vec![1i8; shape.int8_pair_weight_len()];
        scdp_engine::kernels::pack_int8_pairs(&weight, in_channels, out_channels, &mut pairs);
        ByteCase {
            shape,
            bytes,
            scale,
            packed,
            pairs,
            weight_scales: (0..out_channels)
                .map(|_| 0.001 + rng.next().abs())
                .collect(),
            bias: rng.vec(out_channels),
        }
    }

    fn input(&self) -> ByteRows<'_> {
        ByteRows {
            bytes: &self.bytes,
            scale: self.scale,
        }
    }

    fn parameters(&self) -> (&[i8], &[f32], &[f32]) {
        (&self.packed, &self.weight_scales, &self.bias)
    }

    /// `conv_int8_bytes_paired` on `kernels`, starting from `initial`.
    fn run_paired(
        &self,
        kernels: &dyn Kernels,
        accumulate: Accumulate,
        initial: &[f32],
    ) -> Vec<f32> {
        let mut output = initial.to_vec();
        let (weight, scales, bias) = self.parameters();
        let input = self.input();
        kernels.conv_int8_bytes_paired(
            &self.shape,
            &input,
            weight,
            &self.pairs,
            scales,
            bias,
            &mut output,
            accumulate,
        );
        output
    }

    /// `conv_int8_bytes` on `kernels`, starting from `initial`.
    fn run(&self, kernels: &dyn Kernels, accumulate: Accumulate, initial: &[f32]) -> Vec<f32> {
        let mut output = initial.to_vec();
        let (weight, scales, bias) = self.parameters();
        let input = self.input();
        kernels.conv_int8_bytes(
            &self.shape,
            &input,
            weight,
            scales,
            bias,
            &mut output,
            accumulate,
        );
        output
    }

    /// The reference's output, after checking that it equals `conv_int8` on the bytes split
    /// into digits and that every backend gives its bits.
    fn check_backends(
        &self,
        backends: &[(&str, &dyn Kernels)],
        accumulate: Accumulate,
        initial: &[f32],
        what: &str,
    ) -> Vec<f32> {
        let expected = self.run(&Scalar, accumulate, initial);
        let split = self.run_split(accumulate, initial);
        assert_same_bits(&split, &expected, &format!("{what}: digits against bytes"));
        for (name, kernels) in backends {
            let found = self.run(*kernels, accumulate, initial);
            assert_same_bits(&found, &expected, &format!("{what} {name}"));
            let found = self.run_paired(*kernels, accumulate, initial);
            assert_same_bits(&found, &expected, &format!("{what} {name} paired"));
        }
        expected
    }

    /// Whether the AMX tiles alone took the convolution, having checked their choice (whole
    /// quads in, whole 32-channel blocks out) and, when they took it, their bits against
    /// `expected`; `false` without AMX.
    #[cfg(target_arch = "x86_64")]
    fn check_tiles(
        &self,
        accumulate: Accumulate,
        initial: &[f32],
        expected: &[f32],
        what: &str,
    ) -> bool {
        let Some(amx) = Amx::detect() else {
            return false;
        };
        let mut found = initial.to_vec();
        let taken = amx.conv_int8_bytes_on_tiles(
            &self.shape,
            &self.input(),
            self.parameters(),
            &mut found,
            accumulate,
        );
        let takes =
            self.shape.in_channels.is_multiple_of(4) && self.shape.out_channels.is_multiple_of(32);
        assert_eq!(taken, takes, "{what}: the tiles' choice");
        if taken {
            assert_same_bits(&found, expected, &format!("{what} tiles"));
        }
        taken
    }

    /// The reference's `conv_int8` on the bytes split into digits.
    fn run_split(&self, accumulate: Accumulate, initial: &[f32]) -> Vec<f32> {
        let high: Vec<i8> = self.bytes.iter().map(|&b| (b >> 7) as i8).collect();
        let low: Vec<i8> = self.bytes.iter().map(|&b| (b & 127) as i8).collect();
        let digits = DigitRows {
            high: &high,
            low: &low,
            scale: self.scale,
            nonnegative: true,
        };
        let mut output = initial.to_vec();
        let (weight, scales, bias) = self.parameters();
        Scalar.conv_int8(
            &self.shape,
            &digits,
            weight,
            scales,
            bias,
            &mut output,
            accumulate,
        );
        output
    }
}

/// The narrow activations' convolution on whole bytes (`conv_int8_bytes` over the residual
/// blocks' shapes: 3x3 and 1x1 kernels, strides 1 and 2, padding, input channels up to 512
/// and ones not a multiple of 4, output channels off the tiles' blocks, maps of one pixel
/// and more): every backend bit for bit against the scalar reference, which equals
/// `conv_int8` on the same bytes split into digits; bytes 0 and 255 and weights -128 and
/// 127 included; the AMX tiles alone too, where they take the shape (whole 32-channel
/// blocks out, whole quads in). Then the path a model takes: each backend quantizes the same
/// input in its own narrow form and convolves it, and gets the reference's bits.
#[test]
fn narrow_byte_convolution_is_bit_identical_on_every_backend() {
    let mut rng = Lcg(83);
    let backends = backends();
    #[cfg(target_arch = "x86_64")]
    let mut on_tiles = 0;
    for case in 0..60 {
        let kernel = [1, 3][case % 2];
        let stride = 1 + rng.below(2);
        let padding = if kernel == 3 { rng.below(2) } else { 0 };
        let in_channels = match case % 5 {
            0 => [256, 512][rng.below(2)],
            1 => [3, 6, 13][rng.below(3)],
            _ => 4 * (1 + rng.below(32)),
        };
        let out_channels = match case % 3 {
            0 => 64 * (1 + rng.below(2)),
            1 => 16 * (1 + rng.below(4)) + [0, 8, 5][rng.below(3)],
            _ => 1 + rng.below(40),
        };
        let (height, width) = if in_channels >= 256 {
            (1 + rng.below(3), 1 + rng.below(4))
        } else {
            (1 + rng.below(7), 1 + rng.below(9))
        };
        if height.min(width) + 2 * padding < kernel {
            continue;
        }
        let shape = ConvShape::square(
            (height, width, in_channels),
            out_channels,
            kernel,
            stride,
            padding,
        );
        let scale = 0.01 + rng.next().abs();
        let problem = ByteCase::random(&mut rng, shape, scale);
        let initial = rng.vec(shape.output_len());
        for accumulate in [Accumulate::Overwrite, Accumulate::Add] {
            let what = format!("case {case} {shape:?} {accumulate:?}");
            let expected = problem.check_backends(&backends, accumulate, &initial, &what);
            // The AMX tiles alone, where this architecture has them.
            #[cfg(target_arch = "x86_64")]
            if problem.check_tiles(accumulate, &initial, &expected, &what) {
                on_tiles += 1;
            }
            #[cfg(not(target_arch = "x86_64"))]
            let _ = expected;
        }
        // The model's path: quantize in the backend's form, then convolve.
        let values: Vec<f32> = (0..shape.input_len())
            .map(|i| {
                if i % 7 == 0 {
                    0.0
                } else {
                    rng.next().abs() * 3.0
                }
            })
            .collect();
        let convolve = |kernels: &dyn Kernels| {
            let mut scratch = vec![0i8; 2 * values.len()];
            let mut quantize = QuantizeScratch {
                values: &mut scratch,
            };
            let quantized = quantize.quantize_narrow(kernels, &values);
            let codes = quantize.view(&quantized);
            let mut output = vec![0.0; shape.output_len()];
            let (weight, scales, bias) = problem.parameters();
            // Every other case with the pair layout, as a file may hold it.
            let pairs = case.is_multiple_of(2).then_some(problem.pairs.as_slice());
            let planes = layer::planes((weight, pairs, scales), None, bias, Accumulate::Overwrite);
            layer::convolve_codes(kernels, &shape, &codes, planes, &mut output);
            output
        };
        let expected = convolve(&Scalar);
        for (name, kernels) in &backends {
            let what = format!("case {case} {shape:?} quantized narrow on {name}");
            assert_same_bits(&convolve(*kernels), &expected, &what);
        }
    }
    #[cfg(target_arch = "x86_64")]
    if Amx::detect().is_some() {
        assert!(on_tiles >= 20, "only {on_tiles} cases ran on the tiles");
    }
}

/// Small byte convolutions of every count of output pixels from 1 to 27, input channels
/// from one quad to five (odd counts of quads too) and output channels in fours and not:
/// every remainder of the SIMD tiles' pixels (the I8MM matrix tiles take them in pairs,
/// 12 or 4 at a time), channels and inputs (8 a step there), on whole bytes (1x1 and padded
/// 3x3 kernels) and on signed narrow codes (1-D, 5 taps), bit for bit the reference's.
#[test]
fn byte_convolutions_cover_every_tile_remainder() {
    let mut rng = Lcg(89);
    let backends = backends();
    for positions in 1..=27 {
        for in_channels in [4, 8, 12, 20] {
            for out_channels in [4, 8, 12, 13, 20] {
                for kernel in [1, 3] {
                    let shape = ConvShape::square(
                        (1, positions, in_channels),
                        out_channels,
                        kernel,
                        1,
                        kernel / 2,
                    );
                    let problem = ByteCase::random(&mut rng, shape, 0.5);
                    let initial = rng.vec(shape.output_len());
                    let what = format!("bytes {shape:?}");
                    problem.check_backends(&backends, Accumulate::Add, &initial, &what);
                }
                let shape = ConvShape::sequence(positions, in_channels + 1, out_channels, 5, 1, 2);
                let mut code_case = CodeCase::random(&mut rng, shape);
                code_case.codes = (0..shape.input_len())
                    .map(|i| match i % 9 {
                        2 => 127,
                        5 => -127,
                        _ => (rng.next() * 127.0).round() as i32,
                    })
                    .collect();
                let initial = rng.vec(shape.output_len());
                let expected = code_case.run(&Scalar, Accumulate::Add, &initial);
                for (name, kernels) in &backends {
                    let found = code_case.run_signed_bytes(*kernels, Accumulate::Add, &initial);
                    assert_same_bits(&found, &expected, &format!("signed {name} {shape:?}"));
                    let found =
                        code_case.run_signed_bytes_paired(*kernels, Accumulate::Add, &initial);
                    let what = format!("signed paired {name} {shape:?}");
                    assert_same_bits(&found, &expected, &what);
                }
            }
        }
    }
}

/// The tiles take whole bytes only while a kernel's exact sum fits i32
/// (`MAX_BYTE_TERMS` products), a lower bound than the digit planes' (`MAX_DIGIT_TERMS`).
#[cfg(target_arch = "x86_64")]
#[test]
fn byte_tiles_stop_at_the_exact_sum_bound() {
    use scdp_engine::kernels::{MAX_BYTE_TERMS, MAX_DIGIT_TERMS};
    const { assert!(MAX_BYTE_TERMS < MAX_DIGIT_TERMS) };
    // An 11x11 kernel over one output pixel: 121 taps of 512 channels (61,952 products)
    // fit, of 576 (69,696) do not; either band fits the stack buffer.
    for (channels, takes) in [(512, true), (576, false)] {
        assert_eq!(121 * channels <= MAX_BYTE_TERMS, takes);
        let shape = ConvShape::square((11, 11, channels), 32, 11, 1, 0);
        let bytes = vec![0u8; shape.input_len()];
        let input = ByteRows {
            bytes: &bytes,
            scale: 1.0,
        };
        assert_eq!(
            Amx::covers_bytes(&shape, &input),
            takes,
            "{channels} channels"
        );
    }
}

/// The narrow forms each backend asks for: whole bytes where its byte products take 0..=255
/// (the reference, VNNI, the AMX tiles, I8MM's `usdot`, `sdot` on centred bytes), digit
/// planes otherwise (AVX2's `vpmaddubsw` saturates; NEON's widening products gain nothing). A backend quietly falling back to the digits would still pass the
/// bit-identity tests while giving up the narrow path's speed.
#[test]
fn backends_read_narrow_codes_in_their_fastest_form() {
    for (name, kernels) in backends() {
        let expected = match name {
            "scalar" | "avx512" | "amx" | "dot" | "i8mm" => NarrowForm::Bytes,
            _ => NarrowForm::Digits,
        };
        assert_eq!(kernels.narrow_form(), expected, "{name}");
    }
}

/// Narrow quantization: `scale = max / 255`, codes within half a step of the input, the
/// largest value at 255, zero at 0; the digit-plane form holds the same codes; every
/// backend's quantizer gives the portable one's bytes; an all-zero input has scale 1 and a
/// non-finite one a NaN scale (so the NaN reaches the result).
#[test]
fn narrow_quantization_round_trips_within_half_a_step() {
    let mut rng = Lcg(97);
    let input: Vec<f32> = (0..1001)
        .map(|i| {
            if i % 9 == 0 {
                0.0
            } else {
                rng.next().abs() * 4.0
            }
        })
        .collect();
    let mut bytes = vec![0u8; input.len()];
    let scale = ops::quantize_bytes(&input, &mut bytes);
    let largest = input.iter().fold(0.0f32, |m, x| m.max(*x));
    assert_eq!(scale, largest / 255.0);
    assert!(bytes.contains(&255));
    for (&x, &code) in input.iter().zip(&bytes) {
        assert!(
            (code as f32 * scale - x).abs() <= 0.5 * scale * (1.0 + 1e-5),
            "{x} -> {code}"
        );
        assert!(x != 0.0 || code == 0, "{x} -> {code}");
    }
    let (mut high, mut low) = (vec![0i8; input.len()], vec![0i8; input.len()]);
    assert_eq!(
        ops::quantize_bytes_split(&input, &mut high, &mut low),
        scale
    );
    for ((&h, &l), &code) in high.iter().zip(&low).zip(&bytes) {
        assert!((0..=1).contains(&h) && (0..=127).contains(&l));
        assert_eq!(h as i32 * 128 + l as i32, code as i32);
    }
    for (name, kernels) in backends() {
        for form in [NarrowForm::Bytes, NarrowForm::Digits] {
            let mut found = vec![0i8; 2 * input.len()];
            let mut expected = vec![0i8; 2 * input.len()];
            let found_scale = kernels.quantize_narrow(&input, &mut found, form);
            let expected_scale = ops::quantize_narrow(&input, &mut expected, form);
            assert_eq!(
                found_scale.to_bits(),
                expected_scale.to_bits(),
                "{name} {form:?}"
            );
            assert_eq!(found, expected, "{name} {form:?}");
        }
    }
    let mut zeros = [1u8; 3];
    assert_eq!(ops::quantize_bytes(&[0.0; 3], &mut zeros), 1.0);
    assert_eq!(zeros, [0; 3]);
    let mut codes = [1u8; 2];
    assert!(ops::quantize_bytes(&[1.0, f32::NAN], &mut codes).is_nan());
    assert!(ops::quantize_bytes(&[f32::INFINITY, 1.0], &mut codes).is_nan());
    assert_eq!(codes, [0, 0]);
}

/// The largest products the int8 kernels can meet: activations all 127 against weights all
/// +127, all -127, +127/-127 pairs, or all -128 (no tool writes it, a file may hold it).
/// `vpmaddubsw` would saturate a pair sum beyond -32768..=32767; here each is ±32258 or
/// -32512 and must stay exact. Expected values are the
/// integers written out (a 1x1 kernel, unit scales, so the f32 result is exact).
#[test]
fn int8_convolution_is_exact_at_the_extremes() {
    let in_channels = 512;
    let out_channels = 48;
    let shape = ConvShape::square((3, 5, in_channels), out_channels, 1, 1, 0);
    for pattern in 0..4 {
        // Output channel o: +127 everywhere, -127 everywhere, or pairs (+, +, -, -) giving
        // +32258 and -32258 pair sums that cancel; by pattern and channel parity.
        let weight_of = |input: usize, output: usize| -> i8 {
            match (pattern + output) % 4 {
                0 => 127,
                1 => -127,
                2 if input % 4 < 2 => 127,
                2 => -127,
                _ => -128,
            }
        };
        let mut weight = vec![0i8; shape.weight_len()];
        for input in 0..in_channels {
            for output in 0..out_channels {
                weight[input * out_channels + output] = weight_of(input, output);
            }
        }
        let problem = Int8Case {
            shape,
            values: vec![16383; shape.input_len()],
            scale: 1.0,
            nonnegative: true,
            weight,
            weight_scales: vec![1.0; out_channels],
            bias: vec![0.0; out_channels],
        };
        // 16383 x 127 x 512 = 2,080,641 x 2^9 and 16383 x 128 x 512 = 16383 x 2^16: a
        // mantissa under 2^24 and a power of two, so exact in f32.
        let full = (16383 * 127 * in_channels) as f32;
        let lowest = -((16383 * 128 * in_channels) as f32);
        for (name, kernels) in backends() {
            let found = problem.run(
                kernels,
                Accumulate::Overwrite,
                &vec![0.0; shape.output_len()],
            );
            for (index, &value) in found.iter().enumerate() {
                let expected = match (pattern + index % out_channels) % 4 {
                    0 => full,
                    1 => -full,
                    2 => 0.0,
                    _ => lowest,
                };
                assert_eq!(value, expected, "{name} pattern {pattern} output {index}");
            }
        }
    }
}

/// A digit plane's sums run over the whole kernel and only their exact combination
/// `128 high + low` leaves i32: codes 16383 (both digits 127) against weights all 127 or
/// all -128 over a 3x3 kernel of 512 channels, up to 4.5 times what i32 holds, on every
/// backend (the AMX tiles included), borders and all, against the f32 rounding of the
/// exact sum.
#[test]
fn int8_convolution_is_exact_over_the_whole_kernel() {
    // 512 channels: 4,608 products, past what i32 holds (the sums combine in f64); 112: 1,008
    // products, just inside (AMX combines them in i32, up to 2.11e9 here, and its last
    // 64-channel step is partial).
    for in_channels in [512, 112] {
        whole_kernel_sums_are_exact(in_channels);
    }
}

fn whole_kernel_sums_are_exact(in_channels: usize) {
    let out_channels = 32;
    let shape = ConvShape::square((6, 7, in_channels), out_channels, 3, 1, 1);
    for weight_value in [i8::MAX, i8::MIN] {
        let problem = Int8Case {
            shape,
            values: vec![16383; shape.input_len()],
            scale: 1.0,
            nonnegative: true,
            weight: vec![weight_value; shape.weight_len()],
            weight_scales: vec![1.0; out_channels],
            bias: vec![0.0; out_channels],
        };
        for (name, kernels) in backends() {
            let found = problem.run(
                kernels,
                Accumulate::Overwrite,
                &vec![0.0; shape.output_len()],
            );
            for y in 0..6i64 {
                for x in 0..7i64 {
                    let rows = 3 - i64::from(y == 0) - i64::from(y == 5);
                    let columns = 3 - i64::from(x == 0) - i64::from(x == 6);
                    let exact = rows * columns * 16383 * weight_value as i64 * in_channels as i64;
                    let at = (y * 7 + x) as usize * out_channels;
                    for &value in &found[at..at + out_channels] {
                        assert_eq!(value, exact as f32, "{name} {weight_value} at ({y}, {x})");
                    }
                }
            }
        }
    }
}

#[test]
fn quantizing_reports_whether_every_value_is_nonnegative() {
    use scdp_engine::kernels::QuantizeScratch;
    let mut rng = Lcg(31);
    let (rows, row_len) = (6, 20);
    let relu: Vec<f32> = rng.vec(rows * row_len).iter().map(|x| x.max(0.0)).collect();
    let mut signed = relu.clone();
    signed[77] = -0.5;
    // Rounds to zero next to the largest value: still nonnegative once quantized.
    let mut tiny_negative = relu.clone();
    tiny_negative[3] = -1e-6;
    for (name, kernels) in backends() {
        for (input, expected) in [(&relu, true), (&signed, false), (&tiny_negative, true)] {
            let mut values = vec![0i8; 2 * input.len()];
            let mut scratch = QuantizeScratch {
                values: &mut values,
            };
            let digits = scratch.quantize(kernels, input);
            assert_eq!(digits.nonnegative, expected, "{name}");
            assert_eq!(
                digits.nonnegative,
                digits.high.iter().all(|&q| q >= 0),
                "{name}"
            );
            assert!(digits.low.iter().all(|&q| q >= 0), "{name}");
        }
    }
}

/// The element-wise methods (activation quantization, GroupNorm with each activation, the
/// residual add) are the portable code compiled for each backend's vectors: the same bits
/// as the scalar reference, on the trunk's and the U-Net's shapes, lengths off the vector
/// widths, negative values, zero rows and non-finite values.
#[test]
fn elementwise_operations_are_bit_identical_on_every_backend() {
    use scdp_engine::kernels::ops::Activation;
    let mut rng = Lcg(37);
    let backends = backends();
    // (positions, channels, groups): trunk layers (16 channels a group), U-Net blocks (8
    // groups), and odd sizes.
    let shapes = [
        (60 * 80, 64, 4),
        (15 * 20, 256, 16),
        (8 * 10, 512, 32),
        (16, 384, 8),
        (4, 256, 8),
        (7, 24, 3),
        (1, 5, 1),
    ];
    for (case, &(positions, channels, groups)) in shapes.iter().enumerate() {
        let data: Vec<f32> = rng
            .vec(positions * channels)
            .iter()
            .map(|x| x * 3.0 + 0.25)
            .collect();
        let gamma = rng.vec(channels);
        let beta = rng.vec(channels);
        let mut relu: Vec<f32> = data.iter().map(|x| x.max(0.0)).collect();
        relu[..channels.min(8)].fill(0.0);
        let mut non_finite = data.clone();
        non_finite[channels / 2] = f32::NAN;
        if positions > 1 {
            non_finite[channels + channels / 3] = f32::INFINITY;
        }
        for (name, kernels) in &backends {
            let what = format!("{name} case {case}");
            for activation in [Activation::None, Activation::Relu, Activation::Mish] {
                let mut expected = data.clone();
                Scalar.group_norm(&mut expected, channels, groups, (&gamma, &beta), activation);
                let mut found = data.clone();
                kernels.group_norm(&mut found, channels, groups, (&gamma, &beta), activation);
                assert_same_bits(
                    &found,
                    &expected,
                    &format!("{what} group_norm {activation:?}"),
                );

                let mut expected = data.clone();
                Scalar.add_activate(&mut expected, &relu, activation);
                let mut found = data.clone();
                kernels.add_activate(&mut found, &relu, activation);
                assert_same_bits(&found, &expected, &format!("{what} add {activation:?}"));
            }
            for input in [&data, &relu, &non_finite] {
                let quantize = |kernels: &dyn Kernels| {
                    let mut values = vec![0i8; 2 * input.len()];
                    let (high, low) = values.split_at_mut(input.len());
                    let (scale, nonnegative) = kernels.quantize_digits(input, (high, low));
                    (values, scale, nonnegative)
                };
                let (values, scale, nonnegative) = quantize(*kernels);
                let (expected_values, expected_scale, expected_nonnegative) = quantize(&Scalar);
                assert_eq!(values, expected_values, "{what} quantized values");
                assert_same_bits(&[scale], &[expected_scale], &format!("{what} scale"));
                assert_eq!(nonnegative, expected_nonnegative, "{what} nonnegative");
            }
        }
    }
}

/// The stem's 3x3 / 2 max pool is compiled for each backend's vectors too: the same bits as
/// the scalar reference on the pooled stem shapes and odd ones (a border pixel's window is
/// cut by the padding), with negative values and a NaN.
#[test]
fn max_pool_is_bit_identical_on_every_backend() {
    use scdp_engine::config::conv_output;
    let mut rng = Lcg(41);
    // (height, width, channels): the panda and metaworld stems, then odd sizes.
    let shapes = [
        (120, 160, 64),
        (64, 64, 64),
        (7, 5, 24),
        (2, 3, 16),
        (1, 1, 5),
    ];
    for &(height, width, channels) in &shapes {
        let mut input: Vec<f32> = rng
            .vec(height * width * channels)
            .iter()
            .map(|x| x * 3.0 - 1.0)
            .collect();
        input[channels / 2] = f32::NAN;
        let pooled = conv_output(height, 3, 2, 1) * conv_output(width, 3, 2, 1) * channels;
        let mut expected = vec![0.0; pooled];
        Scalar.max_pool_3x3_stride_2(&input, (height, width, channels), &mut expected);
        for (name, kernels) in &backends() {
            let mut found = vec![0.0; pooled];
            kernels.max_pool_3x3_stride_2(&input, (height, width, channels), &mut found);
            let what = format!("{name} max pool {height}x{width}x{channels}");
            assert_same_bits(&found, &expected, &what);
        }
    }
}

/// The stem's GroupNorm taken apart: per-channel moments added band by band, then the
/// normalization applied inside the max pool. On every backend, over bands of a few rows
/// (whole blocks of `MOMENT_BLOCK` pixels, or the whole map where its rows are too narrow
/// for a few to make one), it must give the scalar reference's GroupNorm followed by its
/// max pool, bit for bit (the moments are the same f64 additions in the same order), on
/// the stem shapes and odd ones. The values lie far from zero against their spread, so that
/// the moments' f64 sums, added in another order, would round differently and show it.
#[test]
fn banded_moments_and_normalizing_pool_equal_group_norm_then_pool() {
    use scdp_engine::config::conv_output;
    use scdp_engine::kernels::ops::{self, Activation};
    let mut rng = Lcg(43);
    // (height, width, channels, groups, band rows)
    let shapes = [
        (120, 160, 64, 4, 10),
        (64, 64, 64, 4, 7),
        (9, 32, 24, 3, 4),
        (7, 5, 24, 3, 7),
        (3, 2, 40, 5, 3),
        (1, 1, 8, 2, 1),
    ];
    for &(height, width, channels, groups, band_rows) in &shapes {
        let data: Vec<f32> = rng
            .vec(height * width * channels)
            .iter()
            .map(|x| x * 0.25 + 3000.0)
            .collect();
        let gamma = rng.vec(channels);
        let beta = rng.vec(channels);
        let pooled = conv_output(height, 3, 2, 1) * conv_output(width, 3, 2, 1) * channels;
        let mut normalized = data.clone();
        Scalar.group_norm(
            &mut normalized,
            channels,
            groups,
            (&gamma, &beta),
            Activation::Relu,
        );
        let mut expected = vec![0.0; pooled];
        Scalar.max_pool_3x3_stride_2(&normalized, (height, width, channels), &mut expected);
        for (name, kernels) in &backends() {
            let (mut sums, mut squares) = (vec![0.0f64; channels], vec![0.0f64; channels]);
            for band in data.chunks(band_rows * width * channels) {
                kernels.add_channel_moments(band, channels, (&mut sums, &mut squares));
            }
            let (mut scale, mut shift) = (vec![0.0f32; channels], vec![0.0f32; channels]);
            ops::group_scale_shift(
                (&sums, &squares),
                height * width,
                groups,
                (&gamma, &beta),
                (&mut scale, &mut shift),
            );
            let mut found = vec![0.0; pooled];
            kernels.normalize_max_pool(
                &data,
                (height, width, channels),
                (&scale, &shift),
                Activation::Relu,
                &mut found,
                0,
            );
            let what = format!("{name} banded group norm + pool {height}x{width}x{channels}");
            assert_same_bits(&found, &expected, &what);
        }
    }
}

/// `conv_pixel` and `conv_int8_pixel` must give, bit for bit, what the same backend's dense
/// kernel writes at that pixel (the pyramid evaluates large projections only at the cells
/// the anchors sample). Every pixel of random 2-D shapes, borders and tiles included, with
/// widths that leave partial tiles.
#[test]
fn single_pixel_convolution_equals_the_dense_kernel_bit_for_bit() {
    for (name, kernels) in backends() {
        let mut rng = Lcg(31);
        for case in 0..40 {
            let kernel = [1, 3, 5][rng.below(3)];
            let stride = 1 + rng.below(2);
            let padding = rng.below(kernel / 2 + 1);
            // Some wide inputs: a channel block's weights over 96 KB are walked one kernel
            // row at a time by the f32 tiles, the partial sums waiting in the output.
            let in_channels = if case % 10 == 8 {
                [96, 192, 264][rng.below(3)]
            } else if case % 3 == 0 {
                1 + rng.below(24)
            } else {
                4 * (1 + rng.below(8))
            };
            let out_channels = if case % 2 == 0 {
                16 * (1 + rng.below(4))
            } else {
                1 + rng.below(40)
            };
            let shape = ConvShape::square(
                // 2-D maps: at least two rows (the method's contract).
                (
                    kernel.max(2) + rng.below(9),
                    kernel + rng.below(9),
                    in_channels,
                ),
                out_channels,
                kernel,
                stride,
                padding,
            );
            let input = rng.vec(shape.input_len());
            let weight = rng.vec(shape.weight_len());
            let bias = rng.vec(out_channels);
            let mut dense = vec![f32::NAN; shape.output_len()];
            kernels.conv(
                &shape,
                &input,
                &weight,
                &bias,
                &mut dense,
                Accumulate::Overwrite,
            );
            // ReLU-like inputs, flagged, so the SIMD int8 tiles run.
            let planes = digit_planes(&random_codes(&mut rng, shape.input_len(), true));
            let scale = 0.01 + rng.next().abs();
            let quantized = DigitRows::from_planes(&planes, scale, true);
            let weight_int8 = random_i8(&mut rng, shape.int8_weight_len());
            let weight_scales: Vec<f32> = (0..out_channels)
                .map(|_| 0.001 + rng.next().abs() * 0.01)
                .collect();
            let mut dense_int8 = vec![f32::NAN; shape.output_len()];
            kernels.conv_int8(
                &shape,
                &quantized,
                &weight_int8,
                &weight_scales,
                &bias,
                &mut dense_int8,
                Accumulate::Overwrite,
            );
            for y in 0..shape.out_height() {
                for x in 0..shape.out_width() {
                    let at = (y * shape.out_width() + x) * out_channels;
                    let mut pixel = vec![f32::NAN; out_channels];
                    kernels.conv_pixel(&shape, &input, &weight, &bias, (y, x), &mut pixel);
                    let same = |a: &[f32], b: &[f32]| {
                        a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits())
                    };
                    assert!(
                        same(&pixel, &dense[at..at + out_channels]),
                        "{name} case {case} f32 pixel ({y}, {x}) of {shape:?}"
                    );
                    kernels.conv_int8_pixel(
                        &shape,
                        &quantized,
                        &weight_int8,
                        &weight_scales,
                        &bias,
                        (y, x),
                        &mut pixel,
                    );
                    assert!(
                        same(&pixel, &dense_int8[at..at + out_channels]),
                        "{name} case {case} int8 pixel ({y}, {x}) of {shape:?}"
                    );
                }
            }
            // The same pixels asked for in batches (every third, then the rest), into a map
            // where nothing else may be written.
            let all: Vec<(usize, usize)> = (0..shape.out_height())
                .flat_map(|y| (0..shape.out_width()).map(move |x| (y, x)))
                .collect();
            let (first, rest): (Vec<_>, Vec<_>) = all
                .iter()
                .enumerate()
                .partition(|(index, _)| index % 3 == 0);
            let mut batched = vec![f32::NAN; shape.output_len()];
            for batch in [first, rest] {
                let pixels: Vec<(usize, usize)> = batch.into_iter().map(|(_, &p)| p).collect();
                kernels.conv_int8_pixels(
                    &shape,
                    &quantized,
                    &weight_int8,
                    &weight_scales,
                    &bias,
                    &pixels,
                    &mut batched,
                );
            }
            assert_same_bits(
                &batched,
                &dense_int8,
                &format!("{name} case {case} int8 batches"),
            );
        }
    }
}

/// The AMX tiles' batches of output pixels (the projections evaluated at the anchors'
/// cells), 8 a pass with each pixel's patch gathered per tap: bit for bit the scalar
/// reference's single pixels, on maps with borders and padding, strides 1 and 2, 1x1 and
/// 3x3 kernels, several 64-channel steps and blocks, batches with repeated pixels and of
/// every size up to 50. Only the asked pixels are written. Each batch is checked to run on
/// the tiles.
#[cfg(target_arch = "x86_64")]
#[test]
fn amx_pixel_batches_are_bit_identical_to_the_scalar_reference() {
    // Fails here when CI requires the amx backend and it cannot run.
    backends();
    let Some(amx) = Amx::detect() else {
        eprintln!("no AMX on this machine: the pixel batches cannot run on tiles here");
        return;
    };
    let mut rng = Lcg(37);
    for case in 0..24 {
        let (kernel, stride) = [(3, 1), (3, 1), (3, 2), (1, 1)][case % 4];
        let in_channels = 64 * (1 + rng.below(4));
        let out_channels = 64 * (1 + rng.below(2));
        let shape = ConvShape::square(
            (2 + rng.below(14), 2 + rng.below(18), in_channels),
            out_channels,
            kernel,
            stride,
            kernel / 2,
        );
        let planes = digit_planes(&random_codes(&mut rng, shape.input_len(), true));
        let input = DigitRows::from_planes(&planes, 0.01 + rng.next().abs(), true);
        let weight = random_i8(&mut rng, shape.int8_weight_len());
        let weight_scales: Vec<f32> = (0..out_channels)
            .map(|_| 0.001 + rng.next().abs() * 0.01)
            .collect();
        let bias = rng.vec(out_channels);
        let count = 1 + rng.below(50);
        let pixels: Vec<(usize, usize)> = (0..count)
            .map(|_| (rng.below(shape.out_height()), rng.below(shape.out_width())))
            .collect();
        let mut expected = vec![f32::NAN; shape.output_len()];
        for &(y, x) in &pixels {
            let at = (y * shape.out_width() + x) * out_channels;
            Scalar.conv_int8_pixel(
                &shape,
                &input,
                &weight,
                &weight_scales,
                &bias,
                (y, x),
                &mut expected[at..at + out_channels],
            );
        }
        let mut found = vec![f32::NAN; shape.output_len()];
        let parameters = (&weight[..], &weight_scales[..], &bias[..]);
        let taken = amx.conv_int8_pixels_on_tiles(&shape, &input, parameters, &pixels, &mut found);
        assert!(taken, "case {case}: the tiles did not take {shape:?}");
        assert_same_bits(&found, &expected, &format!("case {case} {shape:?}"));
    }
}

/// A matrix-vector product over an input of no values is the base, on every backend, for
/// f32 and int8 weights (rows of zero columns; `chunks_exact(0)` would panic).
#[test]
fn matrix_vector_product_of_an_empty_input_is_the_base() {
    let base = [1.5f32, -2.0, 0.25];
    for (name, kernels) in backends() {
        let mut output = [f32::NAN; 3];
        kernels.matvec(&[], &[], &base, &mut output);
        assert_eq!(output, base, "{name} f32");
        let mut output = [f32::NAN; 3];
        let codes = CodeRows {
            codes: &[],
            scale: 1.0,
        };
        kernels.matvec_int8_codes(&[], &[0.5; 3], &codes, &base, &mut output);
        assert_eq!(output, base, "{name} int8");
    }
}

/// The trunk's activation codes: two int8 digits `high * 128 + low` whose value is within
/// half a step (`scale / 2`, scale = max |x| / 16383) of the input, low digits in 0..=127,
/// high digits nonnegative exactly for nonnegative rows; zero rows get scale 1 and zero
/// digits, non-finite rows a NaN scale (so the NaN reaches the result).
#[test]
fn split_activation_digits_reconstruct_the_input() {
    let mut rng = Lcg(41);
    let row = rng.vec(300);
    let (mut high, mut low) = (vec![0i8; row.len()], vec![0i8; row.len()]);
    let (scale, nonnegative) = ops::quantize_split_signs(&row, &mut high, &mut low);
    let largest = row.iter().fold(0.0f32, |m, x| m.max(x.abs()));
    assert_eq!(scale, largest / 16383.0);
    assert!(!nonnegative);
    for ((&x, &h), &l) in row.iter().zip(&high).zip(&low) {
        assert!((0..=127).contains(&l), "low digit {l}");
        let value = (h as f32 * 128.0 + l as f32) * scale;
        assert!(
            (value - x).abs() <= scale * 0.5001,
            "{x} -> {value} (scale {scale})"
        );
    }
    let relu: Vec<f32> = row.iter().map(|x| x.max(0.0)).collect();
    let (_, nonnegative) = ops::quantize_split_signs(&relu, &mut high, &mut low);
    assert!(nonnegative && high.iter().all(|&h| (0..=127).contains(&h)));
    assert_eq!(
        ops::quantize_split_signs(&[0.0; 3], &mut [1; 3], &mut [1; 3]),
        (1.0, true)
    );
    let (mut high, mut low) = ([1i8; 2], [1i8; 2]);
    let (scale, _) = ops::quantize_split_signs(&[1.0, f32::NAN], &mut high, &mut low);
    assert!(scale.is_nan() && high == [0, 0] && low == [0, 0]);
}

/// The int8 kernel layouts: the quads the tool writes and every backend reads, and the
/// pairs (eight inputs a group) a file may add for I8MM's operands. In each, every weight
/// has its own place inside the packed length; within a block of 64 output channels a
/// channel's next group is `int8_quad_stride` (quads) or twice that (pairs) further, what
/// the SIMD tiles step by, its channels side by side; packing puts each weight there and
/// zeros in the padding. Output counts around the block width, including a narrow last
/// block.
#[test]
fn int8_layouts_place_every_weight_once_and_step_groups_within_a_block() {
    use scdp_engine::kernels::{
        INT8_CHANNEL_BLOCK, PAIR, QUAD, int8_pair_index, int8_quad_index, int8_quad_stride,
        pack_int8_pairs, pack_int8_quads,
    };
    type Index = fn(usize, usize, usize, (usize, usize, usize)) -> usize;
    type Pack = fn(&[i8], usize, usize, &mut [i8]);
    let layouts: [(usize, Index, Pack); 2] = [
        (QUAD, int8_quad_index, pack_int8_quads),
        (PAIR, int8_pair_index, pack_int8_pairs),
    ];
    for (taps, in_channels, out_channels) in [
        (1usize, 4usize, 1usize),
        (9, 3, 64),
        (49, 3, 10),
        (5, 13, 63),
        (3, 8, 65),
        (9, 20, 130),
        (1, 196, 200),
        (5, 12, 384),
    ] {
        let shape = (taps, in_channels, out_channels);
        let mut rng = Lcg(taps as u64 * 1000 + in_channels as u64);
        let weight = random_i8(&mut rng, taps * in_channels * out_channels);
        for (group, index, pack) in layouts {
            let what = format!("{shape:?} in groups of {group}");
            let index = |at| index(taps, in_channels, out_channels, at);
            let groups = in_channels.div_ceil(group);
            let len = taps * groups * group * out_channels;
            let mut seen = vec![false; len];
            let mut packed = vec![1i8; len];
            pack(&weight, in_channels, out_channels, &mut packed);
            for tap in 0..taps {
                for input in 0..groups * group {
                    for output in 0..out_channels {
                        let at = index((tap, input, output));
                        assert!(at < len, "{what}: {at} >= {len}");
                        assert!(
                            !seen[at],
                            "{what}: ({tap}, {input}, {output}) on a used place"
                        );
                        seen[at] = true;
                        let expected = match input < in_channels {
                            true => weight[(tap * in_channels + input) * out_channels + output],
                            false => 0,
                        };
                        assert_eq!(packed[at], expected, "{what}: ({tap}, {input}, {output})");
                        let block_start = output / INT8_CHANNEL_BLOCK * INT8_CHANNEL_BLOCK;
                        let width = (out_channels - block_start).min(INT8_CHANNEL_BLOCK);
                        assert_eq!(int8_quad_stride(out_channels, output), width * QUAD);
                        if input % group == 0 && input + group < groups * group {
                            let step = index((tap, input + group, output)) - at;
                            assert_eq!(
                                step,
                                width * group,
                                "{what}: step of ({tap}, {input}, {output})"
                            );
                        }
                        if output > block_start {
                            let before = index((tap, input, output - 1));
                            assert_eq!(at - before, group, "{what}: channels side by side");
                        }
                    }
                }
            }
            assert!(seen.iter().all(|&s| s), "{what}: a gap");
        }
    }
}

/// Symmetric int8 per output channel (the last axis) to nearest: the values and scales.
fn quantize_per_output(weight: &[f32], out_channels: usize) -> (Vec<i8>, Vec<f32>) {
    let mut largest = vec![0.0f32; out_channels];
    for (index, value) in weight.iter().enumerate() {
        let channel = index % out_channels;
        largest[channel] = largest[channel].max(value.abs());
    }
    let scales: Vec<f32> = largest.iter().map(|m| m / 127.0).collect();
    let values = weight
        .iter()
        .enumerate()
        .map(|(index, value)| (value / scales[index % out_channels]).round() as i8)
        .collect();
    (values, scales)
}

/// A refined layer (its second weight plane the first plane's rounding error quantized
/// again) through `layer::convolve` on the trunk's codes: every backend gives the scalar
/// reference's bits, and the error from the f32 weights is at most 1/16 of the one-plane
/// layer's. The residual's step is about 1/254 of the first plane's, so the weights' own
/// error falls about 127x and what is left is mostly the 15-bit activation codes'; a
/// residual plane skipped or scaled wrongly leaves the ratio near 1.
#[test]
fn a_refined_layer_adds_its_residual_plane() {
    let mut rng = Lcg(0x5eed_2026);
    let shape = ConvShape::square((6, 7, 32), 24, 3, 1, 1);
    let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
    let weight: Vec<f32> = rng.vec(shape.weight_len());
    let bias = rng.vec(out_channels);
    let input: Vec<f32> = (0..shape.input_len()).map(|_| rng.next().abs()).collect();
    // `[taps, in, out]` in f64, from the f32 weights: what both layers approximate.
    let mut reference = vec![0.0f64; shape.output_len()];
    for y in 0..shape.out_height() {
        for x in 0..shape.out_width() {
            for o in 0..out_channels {
                let mut sum = f64::from(bias[o]);
                for ky in 0..3 {
                    for kx in 0..3 {
                        let (iy, ix) = ((y + ky) as isize - 1, (x + kx) as isize - 1);
                        if iy < 0 || ix < 0 || iy >= 6 || ix >= 7 {
                            continue;
                        }
                        for i in 0..in_channels {
                            let value = input[(iy as usize * 7 + ix as usize) * in_channels + i];
                            let w = weight[((ky * 3 + kx) * in_channels + i) * out_channels + o];
                            sum += f64::from(value) * f64::from(w);
                        }
                    }
                }
                reference[(y * shape.out_width() + x) * out_channels + o] = sum;
            }
        }
    }
    let (first, scales) = quantize_per_output(&weight, out_channels);
    let left: Vec<f32> = weight
        .iter()
        .zip(&first)
        .enumerate()
        .map(|(index, (w, q))| w - f32::from(*q) * scales[index % out_channels])
        .collect();
    let (second, residual_scales) = quantize_per_output(&left, out_channels);
    let pack = |values: &[i8]| {
        let mut packed = vec![0i8; shape.int8_weight_len()];
        scdp_engine::kernels::pack_int8_quads(values, in_channels, out_channels, &mut packed);
        packed
    };
    let (first, second) = (pack(&first), pack(&second));
    let run = |kernels: &dyn Kernels, refined: bool| {
        let weight = Weight::Int8 {
            values: &first,
            scales: &scales,
            activations: ActivationCodes::Wide,
            residual: refined.then_some(scdp_engine::weights::Residual {
                values: &second,
                scales: &residual_scales,
                pairs: None,
            }),
            pairs: None,
        };
        let mut scratch = vec![0i8; 4 * shape.input_len() + 4096];
        let mut quantize = QuantizeScratch {
            values: &mut scratch,
        };
        let mut output = vec![0.0; shape.output_len()];
        layer::convolve(
            kernels,
            &shape,
            &input,
            &weight,
            &bias,
            &mut output,
            Accumulate::Overwrite,
            layer::Activations::Digits(&mut quantize),
        );
        output
    };
    let largest_error = |found: &[f32]| {
        found
            .iter()
            .zip(&reference)
            .map(|(f, r)| (f64::from(*f) - r).abs())
            .fold(0.0, f64::max)
    };
    let one_plane = largest_error(&run(&Scalar, false));
    let expected = run(&Scalar, true);
    let refined = largest_error(&expected);
    assert!(
        refined <= one_plane / 16.0,
        "refined error {refined:.3e}, one plane {one_plane:.3e}"
    );
    for (name, kernels) in backends() {
        assert_same_bits(
            &run(kernels, true),
            &expected,
            &format!("refined on {name}"),
        );
    }
}

/// Workers that run the pieces backwards on the calling thread, counting the calls cut.
struct Backwards {
    count: usize,
    calls: std::sync::atomic::AtomicUsize,
}

impl Backwards {
    fn new(count: usize) -> Self {
        Backwards {
            count,
            calls: Default::default(),
        }
    }
}

impl Workers for Backwards {
    fn count(&self) -> usize {
        self.count
    }

    fn run(&self, pieces: usize, work: &(dyn Fn(usize) + Sync)) {
        self.calls
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        (0..pieces).rev().for_each(work)
    }
}

/// A convolution writing its output through the kernels it is given.
type BlockConv<'a> = dyn Fn(&dyn Kernels, &mut [f32]) + 'a;

/// A U-Net convolution block's epilogue (GroupNorm, Mish, FiLM from int8 or f32 rows), run
/// by `Split` on each block of whole groups as the convolution's pieces compute it, gives the
/// bits of the whole convolution followed by the whole epilogue on the same backend, for 2,
/// 3 and 5 workers, pieces run in any order; and where blocks of whole groups give every
/// worker a piece, the convolution and its epilogue took one hand-out (not a second one for
/// FiLM's product).
#[test]
fn epilogues_run_on_each_block_of_groups_with_the_whole_blocks_bits_on_every_backend() {
    let mut rng = Lcg(43);
    // Groups of 16, 32 and 48 channels (the U-Net's three levels with 8 groups): blocks of
    // whole groups are 64, 64 and 192 channels.
    let shapes = [
        ConvShape::sequence(16, 40, 128, 5, 1, 2),
        ConvShape::sequence(8, 128, 256, 5, 1, 2),
        ConvShape::sequence(4, 96, 384, 5, 1, 2),
    ];
    let groups = 8;
    let cols = 37;
    for shape in &shapes {
        let channels = shape.out_channels;
        let gamma = rng.vec(channels);
        let beta = rng.vec(channels);
        let base = rng.vec(2 * channels);
        let film_f32 = rng.vec(2 * channels * cols);
        let cond = rng.vec(cols);
        let film_int8: Vec<i8> = (0..2 * channels * cols)
            .map(|_| (rng.below(255) as i32 - 127) as i8)
            .collect();
        let row_scales: Vec<f32> = (0..2 * channels)
            .map(|_| 0.001 + rng.next().abs())
            .collect();
        let cond_codes = padded_codes(
            &random_codes(&mut rng, cols, false)
                .into_iter()
                .map(|code| if rng.below(2) == 0 { -code } else { code })
                .collect::<Vec<_>>(),
            cols,
        );
        let code_case = CodeCase::random(&mut rng, *shape);
        let codes = padded_codes(&code_case.codes, shape.in_channels);
        let input = rng.vec(shape.input_len());
        let weight = rng.vec(shape.weight_len());
        let bias = rng.vec(channels);
        let films = [
            None,
            Some(FilmWeights::F32 {
                weight: &film_f32,
                input: &cond,
            }),
            Some(FilmWeights::Int8 {
                weight: &film_int8,
                row_scales: &row_scales,
                input: CodeRows {
                    codes: &cond_codes,
                    scale: 0.02,
                },
            }),
        ];
        for film in films {
            let epilogue = Epilogue {
                groups,
                affine: (&gamma, &beta),
                activation: Activation::Mish,
                film: film.map(|weights| Film {
                    weights,
                    base: &base,
                }),
            };
            let int8 = |kernels: &dyn Kernels, output: &mut [f32]| {
                let input = CodeRows {
                    codes: &codes,
                    scale: code_case.scale,
                };
                let parameters = (&code_case.weight_scales, &code_case.bias);
                let (scales, bias) = parameters;
                let packed = &code_case.packed;
                kernels.conv_int8_codes(
                    shape,
                    &input,
                    packed,
                    scales,
                    bias,
                    output,
                    Accumulate::Overwrite,
                )
            };
            let f32_conv = |kernels: &dyn Kernels, output: &mut [f32]| {
                kernels.conv(shape, &input, &weight, &bias, output, Accumulate::Overwrite)
            };
            for (name, kernels) in backends() {
                let whole = |conv: &BlockConv<'_>| {
                    let mut output = vec![0.0; shape.output_len()];
                    let mut film = vec![0.0; 2 * channels];
                    conv(kernels, &mut output);
                    epilogue.apply(kernels, channels, &mut output, &mut film);
                    output
                };
                let expected = [whole(&int8), whole(&f32_conv)];
                for count in [2, 3, 5] {
                    let workers = Backwards::new(count);
                    let mut scratch = vec![0.0f32; 16 * 1024];
                    let split = Split::new(kernels, &workers, &mut scratch).cutting_every_call();
                    let what = format!("{name}, {count} workers, {shape:?}, film {film:?}");
                    let convs: [&BlockConv<'_>; 2] = [&int8, &f32_conv];
                    let mut int8_calls = 0;
                    for (conv, expected) in convs.into_iter().zip(&expected) {
                        let mut output = vec![f32::NAN; shape.output_len()];
                        let mut film = vec![f32::NAN; 2 * channels];
                        let mut conv =
                            |kernels: &dyn Kernels, output: &mut [f32]| conv(kernels, output);
                        workers.calls.store(0, std::sync::atomic::Ordering::Relaxed);
                        scdp_engine::kernels::conv_then(
                            &split,
                            &mut output,
                            channels,
                            &epilogue,
                            &mut film,
                            &mut conv,
                        );
                        assert_same_bits(&output, expected, &what);
                        if int8_calls == 0 {
                            int8_calls = workers.calls.load(std::sync::atomic::Ordering::Relaxed);
                        }
                    }
                    // Blocks of whole groups (one a worker at most) give as many pieces as
                    // blocks of 64 channels, but for 48-channel groups on 3 and 5 workers (2
                    // blocks of 192): there FiLM's product is a hand-out of its own.
                    let fused = channels != 384 || count == 2;
                    let expected_calls = if film.is_some() && !fused { 2 } else { 1 };
                    assert_eq!(int8_calls, expected_calls, "{what}: hand-outs");
                }
            }
        }
    }
}

/// A projection evaluated at chosen cells (`conv_pixels`), cut into runs of pixels over 2,
/// 3 and 5 workers, writes each cell's dense value (the bits of the whole map's call) and
/// nothing else; a list that repeats a cell is not cut (each piece writes its own cells'
/// values), and gives the same values.
#[test]
fn cells_cut_over_workers_give_the_dense_bits_on_every_backend() {
    let mut rng = Lcg(43);
    let shape = ConvShape::square((9, 7, 48), 64, 3, 1, 1);
    let input = rng.vec(shape.input_len());
    let weight = rng.vec(shape.weight_len());
    let bias = rng.vec(shape.out_channels);
    let cells: Vec<(usize, usize)> = (0..23).map(|i| ((i * 5) % 9, (i * 3) % 7)).collect();
    let repeated: Vec<(usize, usize)> = cells.iter().chain(&cells[..3]).copied().collect();
    let channels = shape.out_channels;
    for (name, kernels) in backends() {
        let mut dense = vec![0.0; shape.output_len()];
        kernels.conv(
            &shape,
            &input,
            &weight,
            &bias,
            &mut dense,
            Accumulate::Overwrite,
        );
        for count in [2, 3, 5] {
            let workers = Backwards::new(count);
            let mut scratch = vec![0.0f32; 1024];
            let split = Split::new(kernels, &workers, &mut scratch).cutting_every_call();
            for (list, cut) in [(&cells, true), (&repeated, false)] {
                let what = format!("{name}, {count} workers, {} cells", list.len());
                let mut map = vec![f32::NAN; shape.output_len()];
                split.conv_pixels(&shape, &input, &weight, &bias, list, &mut map);
                let calls = workers.calls.swap(0, std::sync::atomic::Ordering::Relaxed);
                assert_eq!(calls > 0, cut, "{what}: cut");
                for (pixel, (found, expected)) in map
                    .chunks_exact(channels)
                    .zip(dense.chunks_exact(channels))
                    .enumerate()
                {
                    let cell = (pixel / shape.out_width(), pixel % shape.out_width());
                    if list.contains(&cell) {
                        assert_same_bits(found, expected, &format!("{what}, cell {cell:?}"));
                    } else {
                        assert!(found.iter().all(|v| v.is_nan()), "{what}: {cell:?} written");
                    }
                }
            }
        }
    }
}

/// Every call `Split` cuts (bands of output rows of 2-D convolutions, runs of pixels of
/// pointwise ones, blocks of output channels of 1-D ones, runs of matrix rows) gives the bits
/// of the whole call on the same backend, for 2, 3 and 5 workers (uneven and empty pieces),
/// whatever order the pieces run in, both accumulation modes; and it did cut each.
#[test]
fn calls_cut_over_workers_give_the_whole_calls_bits_on_every_backend() {
    let mut rng = Lcg(41);
    // 2-D: the trunk's kinds (7x7 stride 2 with padding 3, 3x3 strides 1 and 2, 1x1 stride
    // 2 shortcuts, the 3x3 projections), maps from 2 to 13 rows.
    let maps = [
        ConvShape::square((13, 11, 3), 16, 7, 2, 3),
        ConvShape::square((9, 7, 16), 32, 3, 1, 1),
        ConvShape::square((10, 6, 24), 40, 3, 2, 1),
        ConvShape::square((8, 8, 32), 64, 1, 2, 0),
        ConvShape::square((4, 5, 12), 16, 3, 1, 1),
        ConvShape::square((1, 37, 196), 64, 1, 1, 0),
        // Weights over 4x the input (the trunk's last stages): blocks of output channels on
        // the SIMD backends, whole blocks of 64 and a last one of 32.
        ConvShape::square((4, 4, 64), 128, 3, 1, 1),
        ConvShape::square((8, 6, 32), 96, 3, 2, 1),
    ];
    // 1-D: the U-Net's (blocks of 64 output channels, a partial last one, Add).
    let sequences = [
        ConvShape::sequence(16, 10, 128, 5, 1, 2),
        ConvShape::sequence(8, 128, 256, 5, 1, 2),
        ConvShape::sequence(4, 96, 320, 3, 1, 1),
        ConvShape::sequence(16, 64, 200, 1, 1, 0),
    ];
    for (name, kernels) in backends() {
        for count in [2, 3, 5] {
            let workers = Backwards::new(count);
            let mut scratch = vec![0.0f32; 16 * 1024];
            let split = Split::new(kernels, &workers, &mut scratch).cutting_every_call();
            let cut = |what: &str| {
                let calls = workers.calls.swap(0, std::sync::atomic::Ordering::Relaxed);
                assert!(calls > 0, "{name}, {count} workers: {what} was not cut");
            };
            for shape in maps.iter().chain(&sequences) {
                let what = format!("{name}, {count} workers, {shape:?}");
                let input = rng.vec(shape.input_len());
                let weight = rng.vec(shape.weight_len());
                let bias = rng.vec(shape.out_channels);
                let initial = rng.vec(shape.output_len());
                for accumulate in [Accumulate::Overwrite, Accumulate::Add] {
                    let run = |kernels: &dyn Kernels| {
                        let mut output = initial.clone();
                        kernels.conv(shape, &input, &weight, &bias, &mut output, accumulate);
                        output
                    };
                    let found = run(&split);
                    assert_same_bits(&found, &run(kernels), &format!("f32 {what} {accumulate:?}"));
                    // Scalar f32 sequences have no channel form, and runs of positions
                    // would change the SIMD sequences' order: they run whole.
                    if shape.in_height > 1 || name != "scalar" && shape.in_width <= 16 {
                        cut("f32 conv");
                    }
                    // The SIMD tiles cover output channels in whole vectors of 32 or 16.
                    let map_by_channels = shape.in_height > 1
                        && shape.weight_len() > 4 * shape.input_len()
                        && shape.out_channels.is_multiple_of(32)
                        && name != "scalar";
                    if map_by_channels {
                        let asked = kernels.conv_channels(
                            shape,
                            &input,
                            &weight,
                            &bias,
                            0..0,
                            &mut [],
                            accumulate,
                        );
                        assert!(asked, "{what}: no channel form for a 2-D map");
                    }
                }
                let problem = Int8Case::random(&mut rng, *shape, true);
                let mut code_case = CodeCase::random(&mut rng, *shape);
                for accumulate in [Accumulate::Overwrite, Accumulate::Add] {
                    let what = format!("int8 {what} {accumulate:?}");
                    if shape.in_height > 1
                        || shape.is_pointwise()
                            && shape.kernel_width == 1
                            && shape.in_channels == 196
                    {
                        let found = problem.run(&split, accumulate, &initial);
                        assert_same_bits(
                            &found,
                            &problem.run(kernels, accumulate, &initial),
                            &what,
                        );
                        cut("int8 conv");
                        let bytes: Vec<u8> =
                            problem.values.iter().map(|&v| (v & 255) as u8).collect();
                        let (packed, _) = problem.packed();
                        let mut pairs = vec![0i8; shape.int8_pair_weight_len()];
                        let (inputs, outputs) = (shape.in_channels, shape.out_channels);
                        let weight = &problem.weight;
                        scdp_engine::kernels::pack_int8_pairs(weight, inputs, outputs, &mut pairs);
                        let byte_run = |kernels: &dyn Kernels, paired: bool| {
                            let input = ByteRows {
                                bytes: &bytes,
                                scale: problem.scale,
                            };
                            let mut output = initial.clone();
                            let (scales, bias) = (&problem.weight_scales, &problem.bias);
                            match paired {
                                true => kernels.conv_int8_bytes_paired(
                                    shape,
                                    &input,
                                    &packed,
                                    &pairs,
                                    scales,
                                    bias,
                                    &mut output,
                                    accumulate,
                                ),
                                false => kernels.conv_int8_bytes(
                                    shape,
                                    &input,
                                    &packed,
                                    scales,
                                    bias,
                                    &mut output,
                                    accumulate,
                                ),
                            }
                            output
                        };
                        let whole = byte_run(kernels, false);
                        assert_same_bits(
                            &byte_run(&split, false),
                            &whole,
                            &format!("bytes {what}"),
                        );
                        cut("byte conv");
                        let found = byte_run(&split, true);
                        assert_same_bits(&found, &whole, &format!("paired bytes {what}"));
                        cut("paired byte conv");
                    } else {
                        let found = code_case.run(&split, accumulate, &initial);
                        assert_same_bits(
                            &found,
                            &code_case.run(kernels, accumulate, &initial),
                            &what,
                        );
                        cut("code conv");
                        let wide = std::mem::take(&mut code_case.codes);
                        code_case.codes = wide.iter().map(|code| code % 128).collect();
                        let found = code_case.run_signed_bytes(&split, accumulate, &initial);
                        let whole = code_case.run_signed_bytes(kernels, accumulate, &initial);
                        assert_same_bits(&found, &whole, &format!("signed bytes {what}"));
                        cut("signed byte conv");
                        let found = code_case.run_signed_bytes_paired(&split, accumulate, &initial);
                        let what = format!("paired signed bytes {what}");
                        assert_same_bits(&found, &whole, &what);
                        cut("paired signed byte conv");
                        code_case.codes = wide;
                    }
                }
            }
            // The FiLM products.
            let (rows, cols) = (200, 72);
            let weight = rng.vec(rows * cols);
            let input = rng.vec(cols);
            let base = rng.vec(rows);
            let matvec = |kernels: &dyn Kernels| {
                let mut output = vec![0.0; rows];
                kernels.matvec(&weight, &input, &base, &mut output);
                output
            };
            assert_same_bits(&matvec(&split), &matvec(kernels), &format!("{name} matvec"));
            cut("matvec");
            let weight = random_i8(&mut rng, rows * cols);
            let codes = padded_codes(&random_codes(&mut rng, cols, false), cols);
            let scales = rng.vec(rows);
            let int8_matvec = |kernels: &dyn Kernels| {
                let input = CodeRows {
                    codes: &codes,
                    scale: 0.02,
                };
                let mut output = vec![0.0; rows];
                kernels.matvec_int8_codes(&weight, &scales, &input, &base, &mut output);
                output
            };
            assert_same_bits(
                &int8_matvec(&split),
                &int8_matvec(kernels),
                &format!("{name} int8 matvec"),
            );
            cut("int8 matvec");
        }
    }
}

/// The byte convolutions take at most `MAX_DIGIT_CHANNELS` inputs on every backend, as the
/// digit ones do: the SIMD tiles read a padded pixel's zeros from a row that long, so a
/// wider padded input would read past it. Such a call panics (the weights loader never
/// makes one: `int8_fits`) instead of summing whatever lies beyond.
#[test]
fn byte_convolutions_refuse_more_inputs_than_the_zero_row_holds() {
    use scdp_engine::kernels::MAX_DIGIT_CHANNELS;
    let inputs = 2 * MAX_DIGIT_CHANNELS + 16;
    let shape = ConvShape::square((2, 2, inputs), 4, 3, 1, 1);
    let bytes = vec![1u8; shape.input_len()];
    let weight = vec![1i8; shape.int8_weight_len()];
    let (scales, bias) = (vec![1.0f32; 4], vec![0.0f32; 4]);
    for (name, kernels) in backends() {
        let call = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            let input = ByteRows {
                bytes: &bytes,
                scale: 1.0,
            };
            let mut output = vec![0.0f32; shape.output_len()];
            let overwrite = Accumulate::Overwrite;
            kernels.conv_int8_bytes(
                &shape,
                &input,
                &weight,
                &scales,
                &bias,
                &mut output,
                overwrite,
            );
        }));
        assert!(
            call.is_err(),
            "{name} ran a byte convolution over {inputs} inputs"
        );
    }
}

/// The trunk's passes over a whole map, cut over workers (`Split`): GroupNorm (each block of
/// pixels' moments apart, added in order, then the scales and shifts applied by runs), the
/// quantizations of a layer's input (the largest magnitude of each run, then each run's
/// codes from the whole input's), and the residual add. On every backend, 2, 3 and 5
/// workers running the pieces in reverse order: the whole call's bits, its scale and its
/// sign flag; maps of a partial last block, of one block (run whole), of signed and of
/// nonnegative values, and inputs that are all zero, hold a NaN or an infinity.
#[test]
fn map_passes_cut_over_workers_give_the_whole_calls_bits_on_every_backend() {
    let mut rng = Lcg(47);
    // (positions, channels, groups)
    let maps: [(usize, usize, usize); 4] =
        [(300, 64, 32), (129, 128, 32), (64, 40, 5), (1000, 16, 4)];
    for (name, kernels) in backends() {
        for count in [2, 3, 5] {
            let workers = Backwards::new(count);
            // GroupNorm keeps f64 moments in the scratch: one on 8-byte boundaries.
            let mut scratch = vec![0.0f64; 32 * 1024];
            let scratch: &mut [f32] = bytemuck::cast_slice_mut(&mut scratch);
            let split = Split::new(kernels, &workers, scratch).cutting_every_call();
            let cut = |what: &str, expected: bool| {
                let calls = workers.calls.swap(0, std::sync::atomic::Ordering::Relaxed);
                assert_eq!(calls > 0, expected, "{name}, {count} workers: {what} cut");
            };
            for &(positions, channels, groups) in &maps {
                let what = format!("{name}, {count} workers, {positions}x{channels}");
                let blocks = positions.div_ceil(ops::MOMENT_BLOCK);
                // Far from zero against their spread, so that the moments' f64 sums round
                // differently in another order and the outputs show it.
                let data: Vec<f32> = rng
                    .vec(positions * channels)
                    .iter()
                    .map(|x| x * 0.25 + 3000.0)
                    .collect();
                let (gamma, beta) = (rng.vec(channels), rng.vec(channels));
                for activation in [Activation::Relu, Activation::None] {
                    let norm = |kernels: &dyn Kernels| {
                        let mut values = data.clone();
                        let affine = (&gamma[..], &beta[..]);
                        kernels.group_norm(&mut values, channels, groups, affine, activation);
                        values
                    };
                    let found = norm(&split);
                    cut("group norm", blocks > 1);
                    assert_same_bits(&found, &norm(kernels), &format!("{what} group norm"));
                }
                let source = rng.vec(data.len());
                let add = |kernels: &dyn Kernels| {
                    let mut values = data.clone();
                    kernels.add_activate(&mut values, &source, Activation::Relu);
                    values
                };
                let found = add(&split);
                cut("residual add", true);
                assert_same_bits(&found, &add(kernels), &format!("{what} add"));
                // Added to moments already running (a band after the first, the stem's).
                let moments = |kernels: &dyn Kernels| {
                    let (mut sums, mut squares) = (vec![0.125f64; channels], vec![2.5; channels]);
                    kernels.add_channel_moments(&data, channels, (&mut sums, &mut squares));
                    let bits = |values: &[f64]| values.iter().map(|v| v.to_bits()).collect();
                    (bits(&sums), bits(&squares)) as (Vec<u64>, Vec<u64>)
                };
                let found = moments(&split);
                cut("moments", blocks > 1);
                assert_eq!(found, moments(kernels), "{what} moments");
            }
            // The stem's normalize-and-pool by bands of pooled rows, from the top or from a
            // later row, odd and even sizes.
            for (height, width, channels, first_row) in
                [(12, 9, 64, 0), (11, 16, 16, 0), (13, 7, 64, 2)]
            {
                let what = format!("{name}, {count} workers, {height}x{width}x{channels} pool");
                let map = rng.vec(height * width * channels);
                let (scale, shift) = (rng.vec(channels), rng.vec(channels));
                let (pooled_height, pooled_width) = (height.div_ceil(2), width.div_ceil(2));
                let len = (pooled_height - first_row) * pooled_width * channels;
                let pool = |kernels: &dyn Kernels| {
                    let mut pooled = vec![7.0f32; len];
                    let (dims, affine) = ((height, width, channels), (&scale[..], &shift[..]));
                    kernels.normalize_max_pool(
                        &map,
                        dims,
                        affine,
                        Activation::Relu,
                        &mut pooled,
                        first_row,
                    );
                    pooled
                };
                let found = pool(&split);
                cut("normalize and pool", true);
                let whole = pool(kernels);
                assert_same_bits(&found, &whole, &what);
                // And the whole pool's rows from `first_row`: the band is the pool's.
                let mut all = vec![0.0f32; pooled_height * pooled_width * channels];
                let dims = (height, width, channels);
                kernels.normalize_max_pool(
                    &map,
                    dims,
                    (&scale, &shift),
                    Activation::Relu,
                    &mut all,
                    0,
                );
                assert_same_bits(&whole, &all[first_row * pooled_width * channels..], &what);
            }
            let mut inputs: Vec<Vec<f32>> = vec![rng.vec(777), vec![0.0; 300]];
            let nonnegative: Vec<f32> = rng.vec(1025).iter().map(|x| x.abs()).collect();
            inputs.push(nonnegative);
            for special in [f32::NAN, f32::INFINITY] {
                let mut values = rng.vec(500);
                values[321] = special;
                inputs.push(values);
            }
            for input in &inputs {
                let len = input.len();
                let what = format!("{name}, {count} workers, {len} values");
                let digits = |kernels: &dyn Kernels| {
                    let (mut high, mut low) = (vec![7i8; len], vec![7i8; len]);
                    let (scale, nonnegative) =
                        kernels.quantize_digits(input, (&mut high, &mut low));
                    (scale.to_bits(), nonnegative, high, low)
                };
                let found = digits(&split);
                cut("quantize digits", true);
                assert_eq!(found, digits(kernels), "{what}: digits");
                for form in [NarrowForm::Bytes, NarrowForm::Digits] {
                    let narrow = |kernels: &dyn Kernels| {
                        let mut codes = vec![7i8; 2 * len + 3];
                        let scale = kernels.quantize_narrow(input, &mut codes, form);
                        (scale.to_bits(), codes)
                    };
                    let found = narrow(&split);
                    cut("quantize narrow", true);
                    assert_eq!(found, narrow(kernels), "{what}: narrow {form:?}");
                }
            }
        }
    }
}

/// A part of an input quantized for the whole input's largest magnitude: values outside
/// it (a caller's mistake) take the nearest end instead of overflowing a code, on every
/// backend; inside it, the part's codes are the whole input's.
#[test]
fn quantizing_a_part_for_a_given_largest_keeps_codes_in_range() {
    let input = [0.5f32, -3.0, 9.0, f32::NAN, -0.25, 2.0];
    for (name, kernels) in backends() {
        let (mut high, mut low) = (vec![0i8; 6], vec![0i8; 6]);
        let (scale, _) = kernels.quantize_digits_within(&input, 2.0, (&mut high, &mut low));
        assert_eq!(scale, 2.0 / ops::SPLIT_CODE_LIMIT, "{name}");
        let codes: Vec<i32> = high
            .iter()
            .zip(&low)
            .map(|(&h, &l)| 128 * h as i32 + l as i32)
            .collect();
        assert_eq!(
            codes,
            [4096, -16383, 16383, -16383, -2048, 16383],
            "{name}: digits"
        );
        let mut bytes = vec![0i8; 6];
        kernels.quantize_narrow_within(&input, 2.0, (&mut bytes, &mut []), NarrowForm::Bytes);
        let bytes: Vec<u8> = bytes.iter().map(|&b| b as u8).collect();
        assert_eq!(bytes, [64, 0, 255, 0, 0, 255], "{name}: bytes");
        // Inside the range, the part's codes are what quantizing the whole gives there.
        let whole = [0.5f32, -1.0, 2.0, 0.125];
        let (mut high, mut low) = (vec![0i8; 4], vec![0i8; 4]);
        let expected = kernels.quantize_digits(&whole, (&mut high, &mut low));
        let (mut part_high, mut part_low) = (vec![0i8; 2], vec![0i8; 2]);
        let largest = kernels.largest_magnitude(&whole);
        let found =
            kernels.quantize_digits_within(&whole[2..], largest, (&mut part_high, &mut part_low));
        assert_eq!(found.0.to_bits(), expected.0.to_bits(), "{name}: scale");
        assert_eq!(
            (&part_high[..], &part_low[..]),
            (&high[2..], &low[2..]),
            "{name}: part"
        );
    }
}
