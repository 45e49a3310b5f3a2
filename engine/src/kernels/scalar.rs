//! The reference implementation of [`Kernels`]: plain loops, written for clarity. Faster
//! implementations are tested against it.

use super::{Accumulate, ConvShape, Kernels};

/// Portable scalar kernels (the compiler may still auto-vectorise the inner loops).
pub struct Scalar;

impl Kernels for Scalar {
    fn name(&self) -> &'static str {
        "scalar"
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
        let out_width = shape.out_width();
        let in_channels = shape.in_channels;
        let out_channels = shape.out_channels;
        assert_eq!(input.len(), shape.input_len());
        assert_eq!(weight.len(), shape.weight_len());
        assert_eq!(bias.len(), out_channels);
        assert_eq!(output.len(), shape.output_len());
        for (position, out) in output.chunks_exact_mut(out_channels).enumerate() {
            let out_y = position / out_width;
            let out_x = position % out_width;
            match accumulate {
                Accumulate::Overwrite => out.copy_from_slice(bias),
                Accumulate::Add => out.iter_mut().zip(bias).for_each(|(o, b)| *o += b),
            }
            for kernel_y in 0..shape.kernel_height {
                let Some(in_y) =
                    (out_y * shape.stride + kernel_y).checked_sub(shape.padding_height)
                else {
                    continue;
                };
                if in_y >= shape.in_height {
                    continue;
                }
                for kernel_x in 0..shape.kernel_width {
                    let Some(in_x) =
                        (out_x * shape.stride + kernel_x).checked_sub(shape.padding_width)
                    else {
                        continue;
                    };
                    if in_x >= shape.in_width {
                        continue;
                    }
                    let pixel =
                        &input[(in_y * shape.in_width + in_x) * in_channels..][..in_channels];
                    let taps = &weight
                        [(kernel_y * shape.kernel_width + kernel_x) * in_channels * out_channels..]
                        [..in_channels * out_channels];
                    for (&value, row) in pixel.iter().zip(taps.chunks_exact(out_channels)) {
                        for (o, &w) in out.iter_mut().zip(row) {
                            *o += value * w;
                        }
                    }
                }
            }
        }
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
        assert_eq!(input.len(), length * in_channels);
        assert_eq!(weight.len(), 4 * in_channels * out_channels);
        assert_eq!(bias.len(), out_channels);
        assert_eq!(output.len(), 2 * length * out_channels);
        for out in output.chunks_exact_mut(out_channels) {
            out.copy_from_slice(bias);
        }
        // Input step t feeds output steps 2t + j - 1 through tap j (stride 2, padding 1).
        for (step, values) in input.chunks_exact(in_channels).enumerate() {
            for tap in 0..4 {
                let Some(target) = (2 * step + tap).checked_sub(1) else {
                    continue;
                };
                if target >= 2 * length {
                    continue;
                }
                let out = &mut output[target * out_channels..][..out_channels];
                let taps =
                    &weight[tap * in_channels * out_channels..][..in_channels * out_channels];
                for (&value, row) in values.iter().zip(taps.chunks_exact(out_channels)) {
                    for (o, &w) in out.iter_mut().zip(row) {
                        *o += value * w;
                    }
                }
            }
        }
    }

    fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
        assert_eq!(weight.len(), output.len() * input.len());
        assert_eq!(base.len(), output.len());
        for ((out, row), &start) in output
            .iter_mut()
            .zip(weight.chunks_exact(input.len()))
            .zip(base)
        {
            *out = start + row.iter().zip(input).map(|(w, x)| w * x).sum::<f32>();
        }
    }
}
