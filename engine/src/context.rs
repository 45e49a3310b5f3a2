//! Anchors + feature pyramid -> global condition (docs/SPEC.md section 3, steps 4-6): each frame's
//! maps bilinearly sampled at the anchors and averaged, then interleaved with the
//! normalized states.

use crate::config::{ModelConfig, PYRAMID_LEVELS};
use crate::kernels::Kernels;
use crate::pyramid::FrameStore;
use crate::weights::Conv;

/// The four cells around `(x, y)` with their bilinear weights, or `None` when no
/// neighbour can be inside the map (this also rejects NaN).
fn corners((height, width): (usize, usize), x: f32, y: f32) -> Option<[(isize, isize, f32); 4]> {
    if !(x > -1.0 && y > -1.0 && x < width as f32 && y < height as f32) {
        return None;
    }
    let left = libm::floorf(x);
    let top = libm::floorf(y);
    let fx = x - left;
    let fy = y - top;
    let (left, top) = (left as isize, top as isize);
    Some([
        (top, left, (1.0 - fx) * (1.0 - fy)),
        (top, left + 1, fx * (1.0 - fy)),
        (top + 1, left, (1.0 - fx) * fy),
        (top + 1, left + 1, fx * fy),
    ])
}

/// Map coordinates of anchor pixel `uv` on a map of `height x width` cells.
fn map_point(config: &ModelConfig, (height, width): (usize, usize), uv: &[f32]) -> (f32, f32) {
    let x = (uv[0] + 0.5) * width as f32 / config.image_width as f32 - 0.5;
    let y = (uv[1] + 0.5) * height as f32 / config.image_height as f32 - 0.5;
    (x, y)
}

/// Adds `weight x F(x, y)` over the four cells around `(x, y)` to `sum`; cells outside the
/// map add nothing (grid_sample's zero padding, align_corners = False).
fn add_bilinear(
    map: &[f32],
    (height, width, channels): (usize, usize, usize),
    x: f32,
    y: f32,
    sum: &mut [f32],
) {
    let Some(corners) = corners((height, width), x, y) else {
        return;
    };
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

/// One frame's pooled context `[fbar_1 .. fbar_5]` (`5 d` values) at the anchors of one
/// step; invalid (NaN) anchors count as zeros. Cells of on-demand projections that the
/// anchors read are computed first (and stay cached in `frame`).
pub fn pool_context(
    kernels: &dyn Kernels,
    config: &ModelConfig,
    projections: &[Conv<'_>; PYRAMID_LEVELS],
    frame: &mut FrameStore<'_>,
    anchors_uv: &[f32],
    context: &mut [f32],
) {
    let feature_dim = config.feature_dim as usize;
    let inverse_count = 1.0 / config.anchor_count() as f32;
    for (level, projection) in projections.iter().enumerate() {
        let size = config.pyramid_size(level);
        let cells = anchors_uv.chunks_exact(2).flat_map(|uv| {
            let (x, y) = map_point(config, size, uv);
            corners(size, x, y)
                .into_iter()
                .flatten()
                .filter(|&(row, column, _)| row >= 0 && column >= 0)
                .map(|(row, column, _)| (row as usize, column as usize))
        });
        frame.ensure_cells(kernels, config, projection, level, cells);
        let (height, width) = size;
        let map = frame.map(config, level);
        let sum = &mut context[level * feature_dim..][..feature_dim];
        sum.fill(0.0);
        for uv in anchors_uv.chunks_exact(2) {
            let (x, y) = map_point(config, size, uv);
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
