//! Anchors + feature pyramid -> global condition (SPEC section 3, steps 4-6): each frame's
//! maps bilinearly sampled at the anchors and averaged, then interleaved with the
//! normalized states.

use crate::config::{ModelConfig, PYRAMID_LEVELS};

/// Adds `weight x F(x, y)` over the four cells around `(x, y)` to `sum`; cells outside the
/// map add nothing (grid_sample's zero padding, align_corners = False).
fn add_bilinear(
    map: &[f32],
    (height, width, channels): (usize, usize, usize),
    x: f32,
    y: f32,
    sum: &mut [f32],
) {
    // Also rejects NaN and points so far out that no neighbour is inside.
    if !(x > -1.0 && y > -1.0 && x < width as f32 && y < height as f32) {
        return;
    }
    let left = libm::floorf(x);
    let top = libm::floorf(y);
    let fx = x - left;
    let fy = y - top;
    let (left, top) = (left as isize, top as isize);
    let corners = [
        (top, left, (1.0 - fx) * (1.0 - fy)),
        (top, left + 1, fx * (1.0 - fy)),
        (top + 1, left, (1.0 - fx) * fy),
        (top + 1, left + 1, fx * fy),
    ];
    for (row, column, weight) in corners {
        if row < 0 || column < 0 || row as usize >= height || column as usize >= width {
            continue;
        }
        let cell = &map[(row as usize * width + column as usize) * channels..][..channels];
        for (s, &f) in sum.iter_mut().zip(cell) {
            *s += weight * f;
        }
    }
}

/// One frame's pooled context `[fbar_1 .. fbar_5]` (`5 d` values) at the anchors of one step.
/// `features` is that frame's five maps back to back; invalid (NaN) anchors count as zeros.
pub fn pool_context(
    config: &ModelConfig,
    features: &[f32],
    anchors_uv: &[f32],
    context: &mut [f32],
) {
    let feature_dim = config.feature_dim as usize;
    let image_width = config.image_width as f32;
    let image_height = config.image_height as f32;
    let inverse_count = 1.0 / config.anchor_count() as f32;
    let mut maps = features;
    for level in 0..PYRAMID_LEVELS {
        let (height, width) = config.pyramid_size(level);
        let (map, rest) = maps.split_at(height * width * feature_dim);
        maps = rest;
        let sum = &mut context[level * feature_dim..][..feature_dim];
        sum.fill(0.0);
        for uv in anchors_uv.chunks_exact(2) {
            let x = (uv[0] + 0.5) * width as f32 / image_width - 0.5;
            let y = (uv[1] + 0.5) * height as f32 / image_height - 0.5;
            add_bilinear(map, (height, width, feature_dim), x, y, sum);
        }
        sum.iter_mut().for_each(|value| *value *= inverse_count);
    }
}

/// `nstate = state * scale + offset` for one frame.
pub fn normalize_state(state: &[f32], scale: &[f32], offset: &[f32], output: &mut [f32]) {
    for ((out, &value), (&s, &o)) in output.iter_mut().zip(state).zip(scale.iter().zip(offset)) {
        *out = value * s + o;
    }
}
