//! DDIM update (docs/SPEC.md section 5, eta = 0). The coefficients per step are precomputed by the
//! weights tool: `[sqrt(a_t), sqrt(1 - a_t), sqrt(a_prev), sqrt(1 - a_prev)]`.

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
