//! Synthetic calibration scenes: observations a camera could plausibly see, for calibrating
//! int8 rounding when no recorded observations are at hand (and for the synthetic models of
//! the tests and demos, which have none).
//!
//! Each scene has smooth colour gradients with a few discs and rectangles that move between
//! frames, and an end-effector point inside the camera's view at about the distance of the
//! workspace origin, moving about 1 cm per frame; the other state entries are uniform in
//! [-1, 1]. The denoising noise is left to the engine's seeded generator.

use scdp_engine::ModelConfig;
use scdp_engine::rng::NoiseRng;

use crate::run::RunInputs;

struct Uniform(NoiseRng);

impl Uniform {
    /// Uniform in [low, high).
    fn next(&mut self, low: f64, high: f64) -> f64 {
        let unit = (self.0.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        low + (high - low) * unit
    }
}

struct Shape {
    centre: [f64; 2],
    velocity: [f64; 2],
    size: f64,
    colour: [f64; 3],
    disc: bool,
}

fn draw_frame(
    random_background: &([f64; 3], [f64; 3], [f64; 3]),
    shapes: &[Shape],
    time: f64,
    (height, width): (usize, usize),
    pixels: &mut [u8],
) {
    let (base, along_x, along_y) = random_background;
    for y in 0..height {
        for x in 0..width {
            let (u, v) = (x as f64 / width as f64, y as f64 / height as f64);
            let mut colour = [0.0; 3];
            for channel in 0..3 {
                colour[channel] = base[channel] + along_x[channel] * u + along_y[channel] * v;
            }
            for shape in shapes {
                let dx = x as f64 - (shape.centre[0] + shape.velocity[0] * time);
                let dy = y as f64 - (shape.centre[1] + shape.velocity[1] * time);
                let inside = if shape.disc {
                    dx * dx + dy * dy <= shape.size * shape.size
                } else {
                    dx.abs() <= shape.size && dy.abs() <= 0.6 * shape.size
                };
                if inside {
                    colour = shape.colour;
                }
            }
            let at = (y * width + x) * 3;
            for channel in 0..3 {
                pixels[at + channel] = (colour[channel] * 255.0).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
}

/// `count` scenes for `config` seen through the camera `(intrinsics, extrinsics)` (the
/// conventions of [`RunInputs`]), reproducible from `seed`.
pub fn synthetic_scenes(
    config: &ModelConfig,
    intrinsics: [[f32; 3]; 3],
    extrinsics: [[f32; 4]; 4],
    count: usize,
    seed: u64,
) -> Vec<RunInputs> {
    let mut random = Uniform(NoiseRng::new(seed));
    let frames = config.n_obs_steps as usize;
    let (height, width) = (config.image_height as usize, config.image_width as usize);
    let state_dim = config.state_dim as usize;
    let [[fx, _, cx], [_, fy, cy], _] = intrinsics.map(|row| row.map(f64::from));
    let rotation = |row: usize, column: usize| f64::from(extrinsics[row][column]);
    let translation = [0, 1, 2].map(|row| f64::from(extrinsics[row][3]));
    // The workspace origin's depth in the camera; the scenes' points are around it.
    let origin_depth = if translation[2] > 0.05 {
        translation[2]
    } else {
        1.0
    };
    (0..count)
        .map(|_| {
            let background = (
                [0, 1, 2].map(|_| random.next(0.1, 0.7)),
                [0, 1, 2].map(|_| random.next(-0.3, 0.3)),
                [0, 1, 2].map(|_| random.next(-0.3, 0.3)),
            );
            let shape_count = random.next(3.0, 6.0) as usize;
            let shapes: Vec<Shape> = (0..shape_count)
                .map(|_| Shape {
                    centre: [
                        random.next(0.0, width as f64),
                        random.next(0.0, height as f64),
                    ],
                    velocity: [random.next(-4.0, 4.0), random.next(-4.0, 4.0)],
                    size: random.next(0.04, 0.15) * width as f64,
                    colour: [0, 1, 2].map(|_| random.next(0.0, 1.0)),
                    disc: random.next(0.0, 1.0) < 0.5,
                })
                .collect();
            let mut images = vec![0u8; frames * height * width * 3];
            for (frame, pixels) in images.chunks_exact_mut(height * width * 3).enumerate() {
                draw_frame(&background, &shapes, frame as f64, (height, width), pixels);
            }
            // The newest frame's end-effector point: a pixel of the central 80 % of the
            // image, back-projected to a depth near the workspace's.
            let u = random.next(0.1, 0.9) * width as f64;
            let v = random.next(0.1, 0.9) * height as f64;
            let depth = origin_depth * random.next(0.7, 1.3);
            let in_camera = [depth * (u - cx) / fx, depth * (v - cy) / fy, depth];
            // X_base = R^T (X_cam - t)
            let newest: [f64; 3] = [0, 1, 2].map(|axis| {
                (0..3)
                    .map(|row| rotation(row, axis) * (in_camera[row] - translation[row]))
                    .sum()
            });
            let step = [0, 1, 2].map(|_| random.next(-0.01, 0.01));
            let mut state = vec![0.0f32; frames * state_dim];
            for frame in 0..frames {
                let behind = (frames - 1 - frame) as f64;
                let row = &mut state[frame * state_dim..][..state_dim];
                for value in row.iter_mut() {
                    *value = random.next(-1.0, 1.0) as f32;
                }
                for (axis, &index) in config.state_pos_index.iter().enumerate() {
                    row[index as usize] = (newest[axis] - behind * step[axis]) as f32;
                }
            }
            RunInputs {
                images,
                state,
                noise: None,
                intrinsics,
                extrinsics,
                prefix: Vec::new(),
                planned: Vec::new(),
                prefix_mode: scdp_engine::PrefixMode::Replace,
            }
        })
        .collect()
}
