//! Control-loop logic shared by the host demo and the freestanding build: no `std`, no
//! allocator, fixed-capacity queues, explicit microsecond timestamps.
//!
//! - [`timing`]: the rates (10 Hz control, 1 kHz state, 30 fps camera) and which frames an
//!   inference looks at;
//! - [`queue`]: time-stamped actions, stale-action dropping and the chunk hand-over rule;
//! - [`control`]: the loop itself, generic over the policy ([`control::PolicyPort`]), a
//!   stopwatch and the robot ([`control::Plant`]), so tests drive it with fakes;
//! - [`engine_port`]: the SCDP engine as a [`control::PolicyPort`];
//! - [`scene`]: the simulated robot and camera;
//! - [`stats`]: counters and latency percentiles.
#![no_std]

pub mod control;
pub mod engine_port;
pub mod queue;
pub mod scene;
pub mod stats;
pub mod timing;

pub use control::{ControlLoop, Dims, FRAME_SLOTS, Plant, PolicyPort, SetupError, Stopwatch};
pub use engine_port::{AnchorPath, EnginePolicy};
pub use queue::{ActionQueue, Due, HandOver, TimedAction};
pub use scene::{Calibration, SimRobot};
pub use stats::{Histogram, LoopStats, SEAM_WINDOW, Seams};
pub use timing::Timing;
