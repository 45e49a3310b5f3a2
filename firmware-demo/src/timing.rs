//! The clocks of the control loop, all in integer microseconds so that the schedule is exact
//! and the same on every machine.

use core::fmt;

use crate::queue::MAX_CHUNK;

pub const MICROS_PER_SECOND: u64 = 1_000_000;

/// The rates of the loop and how the policy's chunks map onto control ticks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Timing {
    /// `dt`: one action per control tick; also the spacing of the observation history.
    pub control_period_us: u64,
    /// The robot's state stream.
    pub state_period_us: u64,
    pub camera_fps: u64,
    /// `To` of the model: how many frames, `dt` apart, one inference looks at.
    pub n_obs_steps: usize,
    /// Actions per chunk (`n_action_steps` of the model).
    pub n_action_steps: usize,
    /// Control ticks between two inferences.
    pub steps_per_inference: usize,
}

impl Timing {
    /// The Panda setup: a 10 Hz policy, a 1 kHz state stream, a 30 fps camera.
    pub const fn panda(n_obs_steps: usize, n_action_steps: usize) -> Timing {
        Timing {
            control_period_us: 100_000,
            state_period_us: 1_000,
            camera_fps: 30,
            n_obs_steps,
            n_action_steps,
            steps_per_inference: Timing::default_steps_per_inference(n_action_steps),
        }
    }

    /// Action 0 of a chunk is for the observation's own time, so it has always passed when
    /// the chunk arrives; one more action is the latency budget (one control period for the
    /// newest frame's encoding plus the inference). The rest run before the next chunk is
    /// due. Diffusion Policy's real-robot runner makes the same choice: 6 of 8.
    pub const fn default_steps_per_inference(n_action_steps: usize) -> usize {
        if n_action_steps > 2 {
            n_action_steps - 2
        } else {
            1
        }
    }

    pub fn validate(&self) -> Result<(), TimingError> {
        if self.control_period_us == 0 || self.state_period_us == 0 || self.camera_fps == 0 {
            return Err(TimingError::ZeroRate);
        }
        // Every control tick must also be a state sample and a camera frame, so an
        // observation is stamped exactly on the control grid.
        if !self.control_period_us.is_multiple_of(self.state_period_us) {
            return Err(TimingError::StateNotOnControlGrid);
        }
        if !(self.control_period_us * self.camera_fps).is_multiple_of(MICROS_PER_SECOND) {
            return Err(TimingError::CameraNotOnControlGrid);
        }
        if self.n_obs_steps == 0 {
            return Err(TimingError::NoObservationSteps);
        }
        if self.n_action_steps == 0 || self.n_action_steps > MAX_CHUNK {
            return Err(TimingError::ChunkLength);
        }
        if self.steps_per_inference == 0 || self.steps_per_inference > self.n_action_steps {
            return Err(TimingError::StepsPerInference);
        }
        Ok(())
    }

    /// Capture time of camera frame `index`.
    pub const fn frame_time_us(&self, index: u64) -> u64 {
        index * MICROS_PER_SECOND / self.camera_fps
    }

    pub const fn tick_time_us(&self, tick: u64) -> u64 {
        tick * self.control_period_us
    }

    /// The control tick a time falls on, if it falls on one.
    pub const fn tick_at(&self, time_us: u64) -> Option<u64> {
        if time_us.is_multiple_of(self.control_period_us) {
            Some(time_us / self.control_period_us)
        } else {
            None
        }
    }

    pub const fn is_inference_tick(&self, tick: u64) -> bool {
        tick.is_multiple_of(self.steps_per_inference as u64)
    }

    /// Whether the frame captured at control tick `tick` is in the history of some inference:
    /// inference `k` (at tick `k S`) sees ticks `k S - (To - 1) ..= k S`. Only those frames are
    /// encoded; the others are never looked at.
    pub const fn frame_is_used(&self, tick: u64) -> bool {
        let period = self.steps_per_inference as u64;
        let next_inference_tick = tick.div_ceil(period) * period;
        next_inference_tick - tick < self.n_obs_steps as u64
    }
}

/// A [`Timing`] the loop cannot run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TimingError {
    ZeroRate,
    StateNotOnControlGrid,
    CameraNotOnControlGrid,
    NoObservationSteps,
    ChunkLength,
    StepsPerInference,
}

impl fmt::Display for TimingError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::ZeroRate => "control period, state period and camera rate must be positive",
            Self::StateNotOnControlGrid => {
                "the control period must be a whole number of state periods"
            }
            Self::CameraNotOnControlGrid => {
                "the control period must be a whole number of camera frames"
            }
            Self::NoObservationSteps => "n_obs_steps must be positive",
            Self::ChunkLength => "n_action_steps must be in 1..=32",
            Self::StepsPerInference => "steps per inference must be in 1..=n_action_steps",
        })
    }
}

impl core::error::Error for TimingError {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn panda_rates_are_consistent() {
        let timing = Timing::panda(2, 8);
        assert_eq!(timing.validate(), Ok(()));
        assert_eq!(timing.steps_per_inference, 6);
        // Every third frame of a 30 fps camera lands exactly on a 10 Hz tick.
        assert_eq!(timing.frame_time_us(3), timing.tick_time_us(1));
        assert_eq!(timing.frame_time_us(1), 33_333);
        assert_eq!(timing.tick_at(timing.frame_time_us(1)), None);
    }

    #[test]
    fn used_frames_are_each_inference_history() {
        let timing = Timing {
            steps_per_inference: 6,
            ..Timing::panda(2, 8)
        };
        let used: heapless::Vec<u64, 16> = (0..14).filter(|&t| timing.frame_is_used(t)).collect();
        assert_eq!(used.as_slice(), &[0, 5, 6, 11, 12]);
        let every_tick = Timing {
            steps_per_inference: 1,
            ..Timing::panda(3, 8)
        };
        assert!((0..10).all(|tick| every_tick.frame_is_used(tick)));
    }

    #[test]
    fn rejects_a_camera_off_the_control_grid() {
        let timing = Timing {
            camera_fps: 25,
            control_period_us: 30_000,
            ..Timing::panda(2, 8)
        };
        assert_eq!(timing.validate(), Err(TimingError::CameraNotOnControlGrid));
        let too_sparse = Timing {
            steps_per_inference: 9,
            ..Timing::panda(2, 8)
        };
        assert_eq!(too_sparse.validate(), Err(TimingError::StepsPerInference));
    }
}
