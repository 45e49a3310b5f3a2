//! The control loop as a discrete-event simulation over explicit microsecond timestamps.
//!
//! Four sources drive it: the robot's state stream, the camera, the control tick (one action
//! per `dt`) and the processor, which runs one engine call at a time. Simulated time does not
//! sleep: an engine call runs at once, and the processor counts as busy for the compute time
//! the [`Stopwatch`] measured, so latencies and deadline misses are those of the real engine
//! while a minute of robot time takes only as long as its computing. Meanwhile the robot and
//! the camera go on without the processor, as they would on a separate controller.
//!
//! At equal timestamps the order is: a finished engine call delivers, the state stream
//! advances, the control tick runs its action, the camera captures, the inference is
//! triggered, the processor starts its next job (waiting frames before a waiting inference,
//! up to one history's worth).
//! So a chunk arriving exactly at a tick is in time for it, and an inference runs on the
//! newest frames captured by the time the processor is free.
//!
//! The timing rules:
//! - start-up: the first inference runs as soon as the first frame is encoded, on a history
//!   the policy pads by repeating that frame; the ticks before the first chunk hold still;
//! - action `i` of a chunk whose newest frame was captured at `t_obs` is for `t_obs + i dt`;
//!   on arrival the actions whose time has passed are dropped as stale, and the chunk takes
//!   over the queue from its first valid timestamp ([`crate::queue`]);
//! - an inference is given, as its committed prefix, the actions that will have run from its
//!   observation time until it is expected to arrive (the previous inference's compute
//!   time from now): those already executed since the observation and those still queued,
//!   as long as they are one per tick; the policy conditions the rest of the chunk on them
//!   (or ignores them), and each hand-over's seam (the jump from the last old action to the
//!   first new one, the largest step among the next few) is counted;
//! - a later tick with no action holds still, and every inference outstanding at that tick
//!   misses its deadline (the first tick the queue could not serve);
//! - only the frames some inference looks at are encoded ([`Timing::frame_is_used`]); a
//!   frame that finds both slots waiting for a busy processor replaces the older one, and an
//!   inference tick that finds an inference still waiting is skipped.

use heapless::Deque;

use crate::queue::{ActionQueue, Due, MAX_ACTION_DIM, MAX_CHUNK, TimedAction};
use crate::stats::LoopStats;
use crate::timing::{Timing, TimingError};

/// Frames that may wait for the processor at once; when a newer used frame finds them all
/// taken, the oldest waiting one is dropped.
pub const FRAME_SLOTS: usize = 2;
/// Largest `state_dim` the loop stores inline.
pub const MAX_STATE_DIM: usize = 32;

/// The policy as the loop drives it.
pub trait PolicyPort {
    type Error;

    /// Encodes a frame and makes it the newest observation. The first call fills the whole
    /// history (the start-up padding of Diffusion Policy).
    fn push_observation(&mut self, image: &[u8], state: &[f32]) -> Result<(), Self::Error>;

    /// Writes the chunk to execute, `[n_action_steps, action_dim]`, into `chunk`. Action `i` is
    /// for the newest observation's time plus `i dt`. `prefix`, `[k, action_dim]` (`k` may
    /// be 0), holds the actions that run at the chunk's first `k` times whatever it says (the
    /// robot does not wait for it): a policy that can, continues them. `planned`, `[m,
    /// action_dim]`, the queued plan for the `m` times after those, which the chunk replaces:
    /// a policy that can, leaves it smoothly.
    fn infer(
        &mut self,
        prefix: &[f32],
        planned: &[f32],
        chunk: &mut [f32],
    ) -> Result<(), Self::Error>;
}

/// Measures real compute time.
pub trait Stopwatch {
    fn now_us(&mut self) -> u64;
}

/// The robot and its camera.
pub trait Plant {
    /// One sample of the state stream.
    fn robot_tick(&mut self, time_us: u64);

    /// The action to follow from `time_us` until the next control tick; `None` holds still.
    fn command(&mut self, time_us: u64, action: Option<&[f32]>);

    /// Renders the camera frame at `time_us` into `image` and writes the robot state of the
    /// same instant into `state`.
    fn capture(&mut self, time_us: u64, image: &mut [u8], state: &mut [f32]);
}

/// Sizes of the tensors crossing the loop.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dims {
    pub frame_bytes: usize,
    pub state_dim: usize,
    pub action_dim: usize,
}

/// Why a loop cannot be set up.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SetupError {
    Timing(TimingError),
    ActionDim,
    StateDim,
    FrameBuffer { needed: usize, found: usize },
}

impl core::fmt::Display for SetupError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Timing(error) => write!(f, "timing: {error}"),
            Self::ActionDim => write!(f, "action_dim must be in 1..={MAX_ACTION_DIM}"),
            Self::StateDim => write!(f, "state_dim must be in 1..={MAX_STATE_DIM}"),
            Self::FrameBuffer { needed, found } => {
                write!(f, "frame buffer has {found} bytes; {needed} needed")
            }
        }
    }
}

impl core::error::Error for SetupError {}

#[derive(Clone, Copy, Debug)]
enum Running {
    Encode,
    Infer { observed_us: u64, late: bool },
}

/// The loop's state. `'f` is the frame buffer, [`FRAME_SLOTS`] frames of `frame_bytes`.
pub struct ControlLoop<'f, P, C, W> {
    timing: Timing,
    dims: Dims,
    policy: P,
    stopwatch: C,
    plant: W,
    frames: &'f mut [u8],
    frame_states: [[f32; MAX_STATE_DIM]; FRAME_SLOTS],
    frame_times: [u64; FRAME_SLOTS],
    /// Captured frames waiting to be encoded, oldest first (their slots).
    waiting_frames: Deque<usize, FRAME_SLOTS>,
    /// An inference is due; `true` once a control tick held while it waited.
    waiting_inference: Option<bool>,
    /// Frames encoded ahead of the waiting inference.
    encodes_ahead: usize,
    /// The job on the processor and when it finishes.
    running: Option<(Running, u64)>,
    /// The chunk of the running inference, held until it is delivered.
    chunk: [f32; MAX_CHUNK * MAX_ACTION_DIM],
    /// The committed prefix and planned rows given to the running inference.
    prefix: [f32; MAX_CHUNK * MAX_ACTION_DIM],
    /// The actions run lately, oldest first: the part of a prefix already executed.
    executed: Deque<TimedAction, MAX_CHUNK>,
    /// Compute time of the last inference: how long the next one is expected to take.
    last_infer_us: u64,
    queue: ActionQueue,
    now_us: u64,
    next_state_us: u64,
    next_tick: u64,
    next_frame: u64,
    /// Capture time of the newest encoded frame: the observation time of the next inference.
    newest_observation_us: Option<u64>,
    stats: LoopStats,
}

impl<'f, P: PolicyPort, C: Stopwatch, W: Plant> ControlLoop<'f, P, C, W> {
    pub fn new(
        timing: Timing,
        dims: Dims,
        policy: P,
        stopwatch: C,
        plant: W,
        frames: &'f mut [u8],
    ) -> Result<Self, SetupError> {
        timing.validate().map_err(SetupError::Timing)?;
        if dims.action_dim == 0 || dims.action_dim > MAX_ACTION_DIM {
            return Err(SetupError::ActionDim);
        }
        if dims.state_dim == 0 || dims.state_dim > MAX_STATE_DIM {
            return Err(SetupError::StateDim);
        }
        let needed = FRAME_SLOTS * dims.frame_bytes;
        if frames.len() < needed {
            return Err(SetupError::FrameBuffer {
                needed,
                found: frames.len(),
            });
        }
        Ok(ControlLoop {
            timing,
            dims,
            policy,
            stopwatch,
            plant,
            frames,
            frame_states: [[0.0; MAX_STATE_DIM]; FRAME_SLOTS],
            frame_times: [0; FRAME_SLOTS],
            waiting_frames: Deque::new(),
            waiting_inference: None,
            encodes_ahead: 0,
            running: None,
            chunk: [0.0; MAX_CHUNK * MAX_ACTION_DIM],
            prefix: [0.0; MAX_CHUNK * MAX_ACTION_DIM],
            executed: Deque::new(),
            last_infer_us: 0,
            queue: ActionQueue::new(),
            now_us: 0,
            next_state_us: 0,
            next_tick: 0,
            next_frame: 0,
            newest_observation_us: None,
            stats: LoopStats::default(),
        })
    }

    pub fn now_us(&self) -> u64 {
        self.now_us
    }

    pub fn timing(&self) -> &Timing {
        &self.timing
    }

    pub fn stats(&self) -> &LoopStats {
        &self.stats
    }

    pub fn queue(&self) -> &ActionQueue {
        &self.queue
    }

    pub fn plant(&self) -> &W {
        &self.plant
    }

    pub fn policy(&self) -> &P {
        &self.policy
    }

    /// Processes every event before `end_us` and leaves the clock at `end_us`.
    pub fn run_until(&mut self, end_us: u64) -> Result<(), P::Error> {
        loop {
            let tick_us = self.timing.tick_time_us(self.next_tick);
            let frame_us = self.timing.frame_time_us(self.next_frame);
            let done_us = self.running.map_or(u64::MAX, |(_, done)| done);
            let now = done_us.min(self.next_state_us).min(tick_us).min(frame_us);
            if now >= end_us {
                break;
            }
            self.now_us = now;
            if done_us == now {
                self.finish_job(now);
            }
            if self.next_state_us == now {
                self.plant.robot_tick(now);
                self.next_state_us += self.timing.state_period_us;
            }
            let tick = (tick_us == now).then_some(self.next_tick);
            if let Some(tick) = tick {
                self.control_tick(now);
                self.next_tick = tick + 1;
            }
            if frame_us == now {
                self.camera_frame(now);
                self.next_frame += 1;
            }
            if tick.is_some_and(|tick| self.timing.is_inference_tick(tick)) {
                self.trigger_inference();
            }
            if self.running.is_none() {
                self.start_job(now)?;
            }
        }
        self.now_us = end_us;
        Ok(())
    }

    fn control_tick(&mut self, now: u64) {
        self.stats.control_ticks += 1;
        let (due, expired) = self.queue.take_due(now);
        self.stats.stale_actions += expired as u64;
        match due {
            Due::Run(action) => {
                self.stats.actions_executed += 1;
                if self.executed.is_full() {
                    self.executed.pop_front();
                }
                let _ = self.executed.push_back(action);
                self.plant.command(now, Some(action.values()));
            }
            Due::Hold => {
                self.plant.command(now, None);
                if self.stats.inferences == 0 {
                    // Nothing can be in time for the ticks before the first chunk.
                    self.stats.startup_ticks += 1;
                } else {
                    self.stats.ticks_held += 1;
                    self.mark_outstanding_inferences_late();
                }
            }
        }
    }

    fn mark_outstanding_inferences_late(&mut self) {
        if let Some(late) = &mut self.waiting_inference {
            *late = true;
        }
        if let Some((Running::Infer { late, .. }, _)) = &mut self.running {
            *late = true;
        }
    }

    fn camera_frame(&mut self, now: u64) {
        self.stats.frames_captured += 1;
        let Some(tick) = self.timing.tick_at(now) else {
            return;
        };
        if !self.timing.frame_is_used(tick) {
            return;
        }
        let slot = if self.waiting_frames.is_full() {
            self.stats.frames_dropped += 1;
            self.waiting_frames.pop_front()
        } else {
            (0..FRAME_SLOTS).find(|slot| !self.waiting_frames.iter().any(|waiting| waiting == slot))
        };
        // A slot is always found: FRAME_SLOTS slots, at most FRAME_SLOTS waiting.
        let Some(slot) = slot else { return };
        let image = &mut self.frames[slot * self.dims.frame_bytes..][..self.dims.frame_bytes];
        let state = &mut self.frame_states[slot][..self.dims.state_dim];
        self.plant.capture(now, image, state);
        self.frame_times[slot] = now;
        let _ = self.waiting_frames.push_back(slot);
    }

    fn trigger_inference(&mut self) {
        if self.waiting_inference.is_some() {
            self.stats.skipped_inferences += 1;
        } else {
            self.waiting_inference = Some(false);
        }
    }

    /// Frames go first: they are the inference's inputs, so a waiting inference runs on the
    /// newest frames captured by the time the processor is free. But at most `To` of them
    /// (one history) go ahead of it, so a processor too slow to encode every frame still
    /// infers.
    fn start_job(&mut self, now: u64) -> Result<(), P::Error> {
        let frame_first = self.waiting_inference.is_none()
            || self.encodes_ahead < self.timing.n_obs_steps
            || self.newest_observation_us.is_none();
        let frame = if frame_first {
            self.waiting_frames.pop_front()
        } else {
            None
        };
        let started = self.stopwatch.now_us();
        let running = if let Some(slot) = frame {
            if self.waiting_inference.is_some() {
                self.encodes_ahead += 1;
            }
            let image = &self.frames[slot * self.dims.frame_bytes..][..self.dims.frame_bytes];
            let state = &self.frame_states[slot][..self.dims.state_dim];
            self.policy.push_observation(image, state)?;
            self.newest_observation_us = Some(self.frame_times[slot]);
            Running::Encode
        } else if let Some(late) = self.waiting_inference {
            let Some(observed_us) = self.newest_observation_us else {
                // No frame encoded yet (every one dropped): the inference waits for one.
                return Ok(());
            };
            self.waiting_inference = None;
            self.encodes_ahead = 0;
            let length = self.timing.n_action_steps * self.dims.action_dim;
            let (rows, planned) = self.committed_prefix(observed_us, now + self.last_infer_us);
            self.stats.prefix_rows += rows as u64;
            let action_dim = self.dims.action_dim;
            let (prefix, rest) = self.prefix.split_at(rows * action_dim);
            let planned = &rest[..planned * action_dim];
            self.policy
                .infer(prefix, planned, &mut self.chunk[..length])?;
            Running::Infer { observed_us, late }
        } else {
            return Ok(());
        };
        let compute_us = self.stopwatch.now_us().saturating_sub(started);
        match running {
            Running::Encode => self.stats.encode_time.record(compute_us),
            Running::Infer { .. } => {
                self.stats.infer_time.record(compute_us);
                self.last_infer_us = compute_us;
            }
        }
        self.running = Some((running, now + compute_us));
        Ok(())
    }

    /// Writes into `self.prefix` the actions that run at `observed_us + i dt`, one per tick
    /// from those executed and those queued, stopping at the first tick with none and after
    /// `n_action_steps` rows: first the committed ones, for the ticks before `arrival_us` (at
    /// most `n_action_steps - 1`, so the chunk has one of its own), then the planned ones
    /// the chunk will replace. Returns how many of each.
    fn committed_prefix(&mut self, observed_us: u64, arrival_us: u64) -> (usize, usize) {
        let period = self.timing.control_period_us;
        let action_dim = self.dims.action_dim;
        let steps = self.timing.n_action_steps;
        let (mut committed, mut rows) = (0, 0);
        while rows < steps {
            let time = observed_us + rows as u64 * period;
            let found = self
                .executed
                .iter()
                .chain(self.queue.iter())
                .find(|action| action.time_us == time);
            let Some(action) = found else { break };
            self.prefix[rows * action_dim..][..action_dim].copy_from_slice(action.values());
            if time < arrival_us && committed == rows && rows + 1 < steps {
                committed += 1;
            }
            rows += 1;
        }
        (committed, rows - committed)
    }

    fn finish_job(&mut self, now: u64) {
        let Some((running, _)) = self.running.take() else {
            return;
        };
        match running {
            Running::Encode => self.stats.frames_encoded += 1,
            Running::Infer { observed_us, late } => {
                let length = self.timing.n_action_steps * self.dims.action_dim;
                let action_dim = self.dims.action_dim;
                let report = self.queue.hand_over(
                    &self.chunk[..length],
                    action_dim,
                    observed_us,
                    self.timing.control_period_us,
                    now,
                );
                if report.queued > 0 {
                    // The action before the take-over: the last old one still queued, or
                    // the last one run.
                    let takeover_us =
                        observed_us + report.stale as u64 * self.timing.control_period_us;
                    let before = self
                        .queue
                        .iter()
                        .take_while(|action| action.time_us < takeover_us)
                        .last()
                        .or(self.executed.back());
                    if let Some(before) = before {
                        let new = &self.chunk[report.stale * action_dim..length];
                        self.stats.seams.record(before.values(), new, action_dim);
                    }
                }
                debug_assert_eq!(report.overflowed, 0, "chunks are at most MAX_CHUNK long");
                self.stats.inferences += 1;
                self.stats.stale_actions += report.stale as u64;
                self.stats.replaced_actions += report.replaced as u64;
                self.stats.deadline_misses += u64::from(late);
                self.stats.latency.record(now - observed_us);
                self.stats.last_latency_us = Some(now - observed_us);
            }
        }
    }
}
