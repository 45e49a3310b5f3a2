//! The U-Net's transposed convolutions, as the tool lowers them (2 taps, padding 1, twice
//! the output channels, one position more than the input), run through the engine's
//! convolution contract, give PyTorch's ConvTranspose1d(kernel 4, stride 2, padding 1),
//! written out from its definition.

use scdp_engine::kernels::scalar::Scalar;
use scdp_engine::kernels::{Accumulate, ConvShape, Kernels};
use scdp_engine::rng::NoiseRng;
use weights_tool::lowering::lower_upsample;

/// `len` standard normal values from the engine's seeded generator.
fn normal(rng: &mut NoiseRng, len: usize) -> Vec<f32> {
    let mut values = vec![0.0; len];
    rng.fill_normal(&mut values);
    values
}

#[test]
fn lowered_upsample_is_pytorch_conv_transpose() {
    let mut rng = NoiseRng::new(5);
    for (length, channels) in [(1, 1), (1, 3), (2, 5), (4, 16), (7, 9), (8, 24)] {
        // PyTorch's layout: input [channels, length], weight [in, out, 4].
        let input_ct = normal(&mut rng, channels * length);
        let weight = normal(&mut rng, channels * channels * 4);
        let bias = normal(&mut rng, channels);
        // y[o, t] = b[o] + sum over s, k with t = 2 s + k - 1 of x[i, s] w[i, o, k].
        let mut expected = vec![0.0f64; 2 * length * channels];
        let mut magnitude = vec![0.0f64; expected.len()];
        for t in 0..2 * length {
            for o in 0..channels {
                let (mut sum, mut abs) = (bias[o] as f64, bias[o].abs() as f64);
                for s in 0..length {
                    for k in 0..4 {
                        if 2 * s + k != t + 1 {
                            continue;
                        }
                        for i in 0..channels {
                            let term = input_ct[i * length + s] as f64
                                * weight[(i * channels + o) * 4 + k] as f64;
                            sum += term;
                            abs += term.abs();
                        }
                    }
                }
                expected[t * channels + o] = sum;
                magnitude[t * channels + o] = abs;
            }
        }

        let (lowered, wide_bias) = lower_upsample(&weight, &bias);
        let shape = ConvShape::sequence(length, channels, 2 * channels, 2, 1, 1);
        assert_eq!(lowered.len(), shape.weight_len());
        assert_eq!(shape.out_width(), length + 1);
        assert!(
            lowered.iter().all(|&value| value != 0.0),
            "every lowered weight is one of the transposed convolution's"
        );
        let input: Vec<f32> = (0..length * channels)
            .map(|index| input_ct[(index % channels) * length + index / channels])
            .collect();
        let mut output = vec![f32::NAN; shape.output_len()];
        Scalar.conv(
            &shape,
            &input,
            &lowered,
            &wide_bias,
            &mut output,
            Accumulate::Overwrite,
        );
        // Output `2 j` is the first half of position `j`, output `2 j + 1` the second half
        // of position `j + 1`. Each sums at most 2 channels + 1 terms; each product and
        // each addition rounds by at most eps/2 of the sum of magnitudes, so
        // (2 channels + 2) eps of it is twice that bound.
        for t in 0..2 * length {
            for o in 0..channels {
                let at = match t % 2 {
                    0 => (t / 2) * 2 * channels + o,
                    _ => (t / 2 + 1) * 2 * channels + channels + o,
                };
                let (found, exact) = (output[at], expected[t * channels + o]);
                let tolerance =
                    (2 * channels + 2) as f64 * f32::EPSILON as f64 * magnitude[t * channels + o];
                assert!(
                    (found as f64 - exact).abs() <= tolerance,
                    "({length}, {channels}) output ({t}, {o}): {found} vs {exact}"
                );
            }
        }
    }
}
