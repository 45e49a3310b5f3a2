//! Action chunk -> anchors: the end-effector path the current sample implies, projected
//! into the image (docs/SPEC.md section 3, steps 1-3).

use glam::{Mat3, Vec3};

use crate::config::ModelConfig;
use crate::error::Error;

/// A point is in front of the camera only beyond this depth (metres).
pub const Z_MIN: f32 = 1e-3;

/// Pinhole intrinsics and the camera <- robot-base transform.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    focal: [f32; 2],
    centre: [f32; 2],
    rotation: Mat3,
    translation: Vec3,
}

/// How far from orthonormal a calibration's rotation may be (f32 round-off of a real
/// calibration is ~1e-7; anything near this bound is not a rotation).
const ROTATION_TOLERANCE: f32 = 1e-3;

impl Camera {
    /// `intrinsics` is the row-major 3x3 K (`[fx 0 cx; 0 fy cy; 0 0 1]`), `extrinsics` the
    /// row-major 4x4 T with `X_cam = R X_base + t`.
    pub fn new(intrinsics: &[[f32; 3]; 3], extrinsics: &[[f32; 4]; 4]) -> Result<Self, Error> {
        let [[fx, skew, cx], [zero_a, fy, cy], bottom] = *intrinsics;
        let intrinsics_ok = fx.is_finite()
            && fy.is_finite()
            && fx > 0.0
            && fy > 0.0
            && cx.is_finite()
            && cy.is_finite()
            && skew == 0.0
            && zero_a == 0.0
            && bottom == [0.0, 0.0, 1.0];
        if !intrinsics_ok {
            return Err(Error::BadIntrinsics);
        }
        if extrinsics.iter().flatten().any(|v| !v.is_finite())
            || extrinsics[3] != [0.0, 0.0, 0.0, 1.0]
        {
            return Err(Error::BadExtrinsics);
        }
        let row = |r: usize| Vec3::new(extrinsics[r][0], extrinsics[r][1], extrinsics[r][2]);
        let rotation = Mat3::from_cols(row(0), row(1), row(2)).transpose();
        let gram = rotation.transpose() * rotation;
        let orthonormal = (0..3).all(|i| {
            (0..3).all(|j| {
                let expected = if i == j { 1.0 } else { 0.0 };
                (gram.col(i)[j] - expected).abs() <= ROTATION_TOLERANCE
            })
        });
        if !orthonormal || rotation.determinant() <= 0.0 {
            return Err(Error::BadExtrinsics);
        }
        Ok(Camera {
            focal: [fx, fy],
            centre: [cx, cy],
            rotation,
            translation: Vec3::new(extrinsics[0][3], extrinsics[1][3], extrinsics[2][3]),
        })
    }

    /// Pixel `(u, v)` of a robot-base point, or `None` behind the camera (or non-finite).
    pub fn project(&self, point: Vec3) -> Option<[f32; 2]> {
        let camera = self.rotation * point + self.translation;
        if !camera.is_finite() || camera.z <= Z_MIN {
            return None;
        }
        Some([
            self.focal[0] * camera.x / camera.z + self.centre[0],
            self.focal[1] * camera.y / camera.z + self.centre[1],
        ])
    }
}

/// Writes the `s + 1` anchor pixels of one step into `anchors_uv` (`[s + 1, 2]`, NaN where
/// invalid). `sample` is the normalized chunk `[horizon, action_dim]`, `current_state` the
/// newest raw state.
pub fn project_anchors(
    config: &ModelConfig,
    camera: &Camera,
    sample: &[f32],
    action_scale: &[f32],
    action_offset: &[f32],
    current_state: &[f32],
    anchors_uv: &mut [f32],
) {
    let action_dim = config.action_dim as usize;
    let first_row = config.n_obs_steps as usize - 1;
    let state_at = |axis: usize| current_state[config.state_pos_index[axis] as usize];
    let mut point = Vec3::new(state_at(0), state_at(1), state_at(2));
    for (index, uv) in anchors_uv.chunks_exact_mut(2).enumerate() {
        if index > 0 {
            let row = &sample[(first_row + index - 1) * action_dim..][..action_dim];
            let step = |axis: usize| {
                let dim = config.action_pos_index[axis] as usize;
                (row[dim] - action_offset[dim]) / action_scale[dim]
            };
            point += config.pos_scale * Vec3::new(step(0), step(1), step(2));
        }
        let pixel = camera.project(point).unwrap_or([f32::NAN; 2]);
        uv.copy_from_slice(&pixel);
    }
}
