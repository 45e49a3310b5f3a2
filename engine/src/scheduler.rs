//! DDIM update (docs/SPEC.md section 5, eta = 0) and the committed prefix held through it
//! (section 5.1). The coefficients per step are precomputed by the weights tool:
//! `[sqrt(a_t), sqrt(1 - a_t), sqrt(a_prev), sqrt(1 - a_prev)]`.

/// `x0 = clamp((A - sqrt(1 - a_t) eps) / sqrt(a_t))`, `A <- sqrt(a_prev) x0 + sqrt(1 - a_prev) eps`.
pub fn ddim_step(coefficients: &[f32], clip_sample: bool, sample: &mut [f32], eps: &[f32]) {
    let [
        sqrt_alpha,
        sqrt_one_minus_alpha,
        sqrt_alpha_prev,
        sqrt_one_minus_alpha_prev,
    ] = [
        coefficients[0],
        coefficients[1],
        coefficients[2],
        coefficients[3],
    ];
    for (value, &noise) in sample.iter_mut().zip(eps) {
        let mut original = (*value - sqrt_one_minus_alpha * noise) / sqrt_alpha;
        if clip_sample {
            original = original.clamp(-1.0, 1.0);
        }
        *value = sqrt_alpha_prev * original + sqrt_one_minus_alpha_prev * noise;
    }
}

/// How the rows of a committed prefix are held while the rest of the chunk is denoised.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[non_exhaustive]
pub enum PrefixMode {
    /// Diffusion Policy's inpainting (`condition_mask`): before every step the rows are
    /// overwritten with the given actions, normalized.
    #[default]
    Replace,
    /// Before every step the rows are the given actions noised to that step's level,
    /// `sqrt(a_t) x + sqrt(1 - a_t) z`, with `z` the initial sample's own rows: the sample
    /// the denoiser sees is at one noise level throughout.
    Noised,
}

/// The point of the loop the prefix is written for.
#[derive(Clone, Copy, Debug)]
pub enum PrefixLevel<'c> {
    /// Before the step with these DDIM coefficients.
    Step(&'c [f32]),
    /// After the last step: both modes write the given actions themselves.
    Final,
}

/// Writes `rows` (the prefix's rows of the sample) from `actions` (the same number of rows,
/// in action units): normalized as `x = a scale + offset` per action dimension, then held
/// as `mode` says at `level`. `initial` holds the initial sample's values of those rows.
pub fn hold_prefix(
    mode: PrefixMode,
    level: PrefixLevel<'_>,
    actions: &[f32],
    (scale, offset): (&[f32], &[f32]),
    initial: &[f32],
    rows: &mut [f32],
) {
    let action_dim = scale.len();
    for (index, ((value, &action), &noise)) in rows.iter_mut().zip(actions).zip(initial).enumerate()
    {
        let dimension = index % action_dim;
        let normalized = action * scale[dimension] + offset[dimension];
        *value = match (mode, level) {
            (PrefixMode::Noised, PrefixLevel::Step(coefficients)) => {
                coefficients[0] * normalized + coefficients[1] * noise
            }
            _ => normalized,
        };
    }
}
