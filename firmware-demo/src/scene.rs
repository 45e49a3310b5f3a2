//! The simulated robot and camera: an end effector that follows the executed actions inside a
//! workspace box, seen by a pinhole camera as a ball over a table, so that the encoder sees
//! the scene change as the policy moves the robot.

use glam::Vec3;
use scdp_engine::{Camera, Error, ModelConfig};

use crate::control::Plant;
use crate::timing::{MICROS_PER_SECOND, Timing};

/// Where the end effector starts, in the robot base frame (metres): in front of the base,
/// above the table.
pub const HOME: [f32; 3] = [0.5, 0.0, 0.2];
/// The box the controller keeps the end effector in, as a real arm's safety limits would.
pub const WORKSPACE_MIN: [f32; 3] = [0.3, -0.25, 0.05];
pub const WORKSPACE_MAX: [f32; 3] = [0.7, 0.25, 0.35];
/// Radius of the ball drawn at the end effector (metres).
pub const BALL_RADIUS: f32 = 0.04;

/// A shaded disc in pixel coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Blob {
    pub u: f32,
    pub v: f32,
    pub radius: f32,
}

const WALL: [u8; 3] = [70, 90, 120];
const TABLE_LIGHT: [u8; 3] = [170, 150, 120];
const TABLE_DARK: [u8; 3] = [120, 100, 80];
const BALL: [u8; 3] = [240, 110, 30];

/// The static background: a wall over the top third, a checkered table below. `const` so the
/// freestanding build can embed frames computed at compile time.
const fn background(u: usize, v: usize, width: usize, height: usize) -> [u8; 3] {
    if v * 3 < height {
        let shade = (v * 40 / height) as u8;
        [WALL[0] + shade, WALL[1] + shade, WALL[2] + shade]
    } else {
        let cell = if width >= 8 { width / 8 } else { 1 };
        if (u / cell + v / cell).is_multiple_of(2) {
            TABLE_LIGHT
        } else {
            TABLE_DARK
        }
    }
}

/// Renders the scene into an `[height, width, 3]` RGB frame.
pub const fn draw_scene(image: &mut [u8], width: usize, height: usize, blob: Option<Blob>) {
    let mut v = 0;
    while v < height {
        let mut u = 0;
        while u < width {
            let mut colour = background(u, v, width, height);
            if let Some(blob) = blob {
                let du = u as f32 - blob.u;
                let dv = v as f32 - blob.v;
                let squared = du * du + dv * dv;
                let limit = blob.radius * blob.radius;
                if squared <= limit && limit > 0.0 {
                    // Brightest at the centre, so the ball reads as a sphere.
                    let weight = 1.0 - 0.5 * squared / limit;
                    let mut channel = 0;
                    while channel < 3 {
                        let mixed =
                            BALL[channel] as f32 * weight + colour[channel] as f32 * (1.0 - weight);
                        colour[channel] = mixed as u8;
                        channel += 1;
                    }
                }
            }
            let at = (v * width + u) * 3;
            image[at] = colour[0];
            image[at + 1] = colour[1];
            image[at + 2] = colour[2];
            u += 1;
        }
        v += 1;
    }
}

/// A camera calibration: row-major K of the model-input image and T (camera <- base).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Calibration {
    pub intrinsics: [[f32; 3]; 3],
    pub extrinsics: [[f32; 4]; 4],
}

impl Calibration {
    /// A camera in front of the robot, 1.4 m out and 0.6 m up, looking at the middle of the
    /// workspace with a 58 degree horizontal field of view.
    pub fn default_for(image_width: u32, image_height: u32) -> Calibration {
        let eye = Vec3::new(1.4, 0.0, 0.6);
        let target = Vec3::new(0.5, 0.0, 0.15);
        let forward = (target - eye).normalize();
        let right = forward.cross(Vec3::Z).normalize();
        let down = forward.cross(right);
        let translation = -Vec3::new(right.dot(eye), down.dot(eye), forward.dot(eye));
        let focal = 0.9 * image_width as f32;
        // `+ 0.0` turns the -0.0 of the cross products into 0.0 for a tidy calibration file.
        let row = |axis: Vec3, offset: f32| [axis.x, axis.y, axis.z, offset].map(|v| v + 0.0);
        Calibration {
            intrinsics: [
                [focal, 0.0, (image_width as f32 - 1.0) / 2.0],
                [0.0, focal, (image_height as f32 - 1.0) / 2.0],
                [0.0, 0.0, 1.0],
            ],
            extrinsics: [
                row(right, translation.x),
                row(down, translation.y),
                row(forward, translation.z),
                [0.0, 0.0, 0.0, 1.0],
            ],
        }
    }

    pub fn camera(&self) -> Result<Camera, Error> {
        Camera::new(&self.intrinsics, &self.extrinsics)
    }

    /// Depth of a base-frame point along the optical axis.
    fn depth(&self, point: Vec3) -> f32 {
        let [x, y, z, t] = self.extrinsics[2];
        x * point.x + y * point.y + z * point.z + t
    }
}

/// The simulated arm: the end effector integrates the commanded position deltas on the 1 kHz
/// state stream (action `a` moves it by `pos_scale * a[action_pos_index]` over one control
/// period, the anchor model of docs/SPEC.md), so the robot goes where the policy's anchors say.
pub struct SimRobot {
    calibration: Calibration,
    camera: Camera,
    width: usize,
    height: usize,
    state_pos_index: [usize; 3],
    action_pos_index: [usize; 3],
    pos_scale: f32,
    control_period_s: f32,
    state_period_s: f32,
    position: Vec3,
    velocity: Vec3,
}

impl SimRobot {
    pub fn new(
        config: &ModelConfig,
        timing: &Timing,
        calibration: Calibration,
    ) -> Result<SimRobot, Error> {
        let seconds = |micros: u64| micros as f32 / MICROS_PER_SECOND as f32;
        let index = |indices: [u32; 3]| indices.map(|index| index as usize);
        Ok(SimRobot {
            camera: calibration.camera()?,
            calibration,
            width: config.image_width as usize,
            height: config.image_height as usize,
            state_pos_index: index(config.state_pos_index),
            action_pos_index: index(config.action_pos_index),
            pos_scale: config.pos_scale,
            control_period_s: seconds(timing.control_period_us),
            state_period_s: seconds(timing.state_period_us),
            position: Vec3::from_array(HOME),
            velocity: Vec3::ZERO,
        })
    }

    pub fn position(&self) -> [f32; 3] {
        self.position.to_array()
    }

    /// The end effector's pixel and apparent size, if it is in front of the camera.
    pub fn blob(&self) -> Option<Blob> {
        let [u, v] = self.camera.project(self.position)?;
        let depth = self.calibration.depth(self.position);
        Some(Blob {
            u,
            v,
            radius: self.calibration.intrinsics[0][0] * BALL_RADIUS / depth,
        })
    }

    /// The state vector: the end effector position in its slots, zero elsewhere.
    pub fn write_state(&self, state: &mut [f32]) {
        state.fill(0.0);
        for (axis, &slot) in self.state_pos_index.iter().enumerate() {
            if let Some(value) = state.get_mut(slot) {
                *value = self.position[axis];
            }
        }
    }
}

impl Plant for SimRobot {
    fn robot_tick(&mut self, _time_us: u64) {
        let moved = self.position + self.velocity * self.state_period_s;
        self.position = moved.clamp(
            Vec3::from_array(WORKSPACE_MIN),
            Vec3::from_array(WORKSPACE_MAX),
        );
    }

    fn command(&mut self, _time_us: u64, action: Option<&[f32]>) {
        self.velocity = match action {
            Some(action) => {
                let delta = self.action_pos_index.map(|dim| action[dim]);
                Vec3::from_array(delta) * (self.pos_scale / self.control_period_s)
            }
            None => Vec3::ZERO,
        };
    }

    fn capture(&mut self, _time_us: u64, image: &mut [u8], state: &mut [f32]) {
        draw_scene(image, self.width, self.height, self.blob());
        self.write_state(state);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_camera_sees_the_whole_workspace() {
        let config = ModelConfig::METAWORLD;
        let calibration = Calibration::default_for(config.image_width, config.image_height);
        let camera = calibration.camera().expect("a rigid transform");
        for corner in 0..8 {
            let pick = |axis: usize| {
                if corner >> axis & 1 == 0 {
                    WORKSPACE_MIN[axis]
                } else {
                    WORKSPACE_MAX[axis]
                }
            };
            let point = Vec3::new(pick(0), pick(1), pick(2));
            let [u, v] = camera.project(point).expect("in front of the camera");
            assert!(
                (0.0..128.0).contains(&u) && (0.0..128.0).contains(&v),
                "{u} {v}"
            );
        }
        let [u, _] = camera.project(Vec3::from_array(HOME)).unwrap();
        assert!(
            (u - 63.5).abs() < 1e-3,
            "home is on the vertical centre line: {u}"
        );
    }

    #[test]
    fn robot_follows_commanded_deltas_within_the_workspace() {
        let config = ModelConfig::TINY;
        let timing = Timing::panda(2, 4);
        let calibration = Calibration::default_for(config.image_width, config.image_height);
        let mut robot = SimRobot::new(&config, &timing, calibration).unwrap();
        // One control period of action [1, 0, -1, 0] moves by pos_scale * (1, 0, -1).
        robot.command(0, Some(&[1.0, 0.0, -1.0, 5.0]));
        for tick in 0..100 {
            robot.robot_tick(tick * 1000);
        }
        let [x, y, z] = robot.position();
        assert!((x - 0.6).abs() < 1e-4 && y == 0.0 && (z - 0.1).abs() < 1e-4);
        robot.command(100_000, Some(&[10.0, 0.0, 0.0, 0.0]));
        for tick in 100..200 {
            robot.robot_tick(tick * 1000);
        }
        assert_eq!(robot.position()[0], WORKSPACE_MAX[0]);
        robot.command(200_000, None);
        robot.robot_tick(200_000);
        assert_eq!(robot.position()[0], WORKSPACE_MAX[0]);
    }

    #[test]
    fn frame_shows_the_ball_where_the_end_effector_projects() {
        let config = ModelConfig::METAWORLD;
        let timing = Timing::panda(2, 8);
        let calibration = Calibration::default_for(128, 128);
        let mut robot = SimRobot::new(&config, &timing, calibration).unwrap();
        let mut image = [0u8; 128 * 128 * 3];
        let mut state = [1.0f32; 9];
        robot.capture(0, &mut image, &mut state);
        assert_eq!(&state[..4], &[HOME[0], HOME[1], HOME[2], 0.0]);
        let blob = robot.blob().unwrap();
        assert!(blob.radius > 2.0, "{blob:?}");
        let at = ((blob.v.round() as usize) * 128 + blob.u.round() as usize) * 3;
        let mut empty = [0u8; 128 * 128 * 3];
        draw_scene(&mut empty, 128, 128, None);
        assert!(image[at] > empty[at] && image[at + 2] < empty[at + 2]);
        let changed = image.iter().zip(&empty).filter(|(a, b)| a != b).count();
        let disc = core::f32::consts::PI * blob.radius * blob.radius;
        assert!(
            (changed as f32) < 3.0 * 1.2 * disc,
            "only the ball differs: {changed}"
        );
    }
}
