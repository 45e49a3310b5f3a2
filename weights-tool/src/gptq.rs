//! Error-compensating int8 rounding (GPTQ, Frantar et al. 2022) with the engine's scheme:
//! symmetric, one scale per output channel, `scale = max |w| / 127` as with plain rounding.
//! Only the rounding changes: the weights are rounded one input at a time, and each
//! rounding error is pushed onto the inputs not yet rounded, weighted by how those inputs
//! co-vary with it on calibration data, so that the layer's *output* error `(W - Q) x`
//! stays small on inputs like the calibration ones rather than each weight's own error.
//!
//! With `H = sum x x^T` over the calibration inputs (plus damping), the error of input `d`
//! is divided by `U[d, d]` and subtracted along row `d` of `U`, the upper Cholesky factor
//! of `H^-1` (`H^-1 = U^T U`). With `H = I` this is plain rounding.

use anyhow::{Context, Result, ensure};
use faer::linalg::matmul::matmul;
use faer::linalg::solvers::DenseSolveCore;
use faer::{Accum, Mat, Par, Side};

use crate::calibrate::InputMoment;
use crate::lowering::ChannelAxis;

/// Inputs rounded between two updates of the remaining ones by one matrix product.
const BLOCK: usize = 128;

/// Rounds `values` to int8 with the per-channel `scales`, GPTQ-style with the input moment
/// `moment` (`damping` times the mean of its diagonal is added to the diagonal). Returns
/// the int8 values in the layout of `values`.
pub fn quantize(
    values: &[f32],
    scales: &[f32],
    axis: ChannelAxis,
    moment: &InputMoment,
    damping: f64,
) -> Result<Vec<i8>> {
    let channels = scales.len();
    let inputs = values.len() / channels;
    ensure!(
        moment.second_moment.nrows() == inputs && moment.second_moment.ncols() == inputs,
        "moment is {}x{}, the weight has {inputs} inputs",
        moment.second_moment.nrows(),
        moment.second_moment.ncols()
    );
    let at = |channel: usize, input: usize| match axis {
        ChannelAxis::Last => input * channels + channel,
        ChannelAxis::First => channel * inputs + input,
    };
    // Column `d` of `weights` is input d's weights over all channels.
    let mut weights = Mat::from_fn(channels, inputs, |c, d| f64::from(values[at(c, d)]));
    let mut hessian = Mat::from_fn(inputs, inputs, |i, j| {
        f64::from(moment.second_moment[(i, j)])
    });
    for d in 0..inputs {
        // An input that was always zero: its weights cannot matter; keep H invertible.
        if hessian[(d, d)] == 0.0 {
            hessian[(d, d)] = 1.0;
        }
    }
    let mean_diagonal = (0..inputs).map(|d| hessian[(d, d)]).sum::<f64>() / inputs as f64;
    for d in 0..inputs {
        hessian[(d, d)] += damping * mean_diagonal;
    }
    let inverse = hessian
        .llt(Side::Lower)
        .ok()
        .context("calibration moment is not positive definite")?
        .inverse();
    let upper = inverse
        .llt(Side::Lower)
        .ok()
        .context("inverse calibration moment is not positive definite")?
        .L()
        .transpose()
        .to_owned();

    let scales64: Vec<f64> = scales.iter().map(|&s| f64::from(s)).collect();
    let mut quantized = vec![0i8; values.len()];
    let mut errors = Mat::<f64>::zeros(channels, BLOCK);
    for start in (0..inputs).step_by(BLOCK) {
        let end = (start + BLOCK).min(inputs);
        for d in start..end {
            let pivot = upper[(d, d)];
            for c in 0..channels {
                let w = weights[(c, d)];
                let q = (w / scales64[c]).round().clamp(-127.0, 127.0);
                quantized[at(c, d)] = q as i8;
                errors[(c, d - start)] = (w - q * scales64[c]) / pivot;
            }
            for j in d + 1..end {
                let factor = upper[(d, j)];
                for c in 0..channels {
                    weights[(c, j)] -= factor * errors[(c, d - start)];
                }
            }
        }
        if end < inputs {
            matmul(
                weights.subcols_mut(end, inputs - end),
                Accum::Add,
                errors.subcols(0, end - start),
                upper.submatrix(start, end, end - start, inputs - end),
                -1.0,
                Par::Seq,
            );
        }
    }
    Ok(quantized)
}
