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

/// Writes `rows` (the prefix's rows of the sample: the committed ones, then the planned
/// ones) from `committed` and `planned` (in action units), each normalized as `x = a scale +
/// offset` per action dimension. The committed rows are held as `mode` says at `level`. A
/// planned row `j` of `m` only pulls the sample towards it, at the step's noise level and
/// with weight `(m - j) / (m + 1)`: `A <- w (sqrt(a_t) x + sqrt(1 - a_t) z) + (1 - w) A`,
/// and is left to the model after the last step. `initial` holds the initial sample's values
/// of those rows (`z`).
pub fn hold_prefix(
    mode: PrefixMode,
    level: PrefixLevel<'_>,
    (committed, planned): (&[f32], &[f32]),
    (scale, offset): (&[f32], &[f32]),
    initial: &[f32],
    rows: &mut [f32],
) {
    let action_dim = scale.len();
    let normalized = |action: f32, index: usize| {
        let dimension = index % action_dim;
        action * scale[dimension] + offset[dimension]
    };
    let (held, pulled) = rows.split_at_mut(committed.len());
    let (held_noise, pulled_noise) = initial.split_at(committed.len());
    for (index, ((value, &action), &noise)) in
        held.iter_mut().zip(committed).zip(held_noise).enumerate()
    {
        let target = normalized(action, index);
        *value = match (mode, level) {
            (PrefixMode::Noised, PrefixLevel::Step(coefficients)) => {
                coefficients[0] * target + coefficients[1] * noise
            }
            _ => target,
        };
    }
    let PrefixLevel::Step(coefficients) = level else {
        return;
    };
    let planned_rows = planned.len() / action_dim;
    for (index, ((value, &action), &noise)) in
        pulled.iter_mut().zip(planned).zip(pulled_noise).enumerate()
    {
        let weight = (planned_rows - index / action_dim) as f32 / (planned_rows + 1) as f32;
        let target = coefficients[0] * normalized(action, index) + coefficients[1] * noise;
        *value = weight * target + (1.0 - weight) * *value;
    }
}
