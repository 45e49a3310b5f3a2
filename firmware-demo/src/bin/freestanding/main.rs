//! The engine linked as controller firmware would link it: no std, no C runtime, no
//! allocator. The weights are embedded in an aligned static, the arena is a static sized at
//! compile time from the engine's const plan, and the frames are rendered at compile time.
//!
//! It checks that the engine works there (same input and seed give the same bits, results are
//! finite, the first observation fills the history), then runs the shared control loop for a
//! few simulated seconds, and reports through stdout and its exit status:
//! 0 all checks passed, 1 a check failed, 2 the engine or the loop returned an error.
//!
//! Build and run (x86-64 or aarch64 Linux; `firmware-demo/freestanding.sh` also
//! cross-builds it for aarch64 and runs it under qemu):
//!   cargo build -p firmware-demo --bin firmware-freestanding --no-default-features \
//!       --features freestanding --profile firmware
//!   target/firmware/firmware-freestanding
#![no_std]
#![no_main]

#[cfg(feature = "host")]
compile_error!(
    "firmware-freestanding cannot link std: build it with --no-default-features --features freestanding"
);

mod mem;
mod sys;

use core::cell::UnsafeCell;
use core::fmt::{self, Write as _};
use core::sync::atomic::{AtomicBool, Ordering};

use firmware_demo::scene::{Blob, Calibration, draw_scene};
use firmware_demo::{ControlLoop, Dims, EnginePolicy, FRAME_SLOTS, SimRobot, Stopwatch, Timing};
use scdp_engine::{Aligned, Arena, ArenaPlan, Model, ModelConfig, Noise, Policy, PrefixMode};

const CONFIG: ModelConfig = ModelConfig::TINY;
const PLAN: ArenaPlan = ArenaPlan::new(&CONFIG);
const WIDTH: usize = CONFIG.image_width as usize;
const HEIGHT: usize = CONFIG.image_height as usize;
const FRAME_BYTES: usize = WIDTH * HEIGHT * 3;
const STATE_DIM: usize = CONFIG.state_dim as usize;
const CHUNK_VALUES: usize = (CONFIG.horizon * CONFIG.action_dim) as usize;
const _: () = assert!(CONFIG.validate().is_ok());

/// Simulated seconds of the control-loop run.
const LOOP_SECONDS: u64 = 3;
const SEED: u64 = 7;

static WEIGHTS: &Aligned<[u8]> = &Aligned(*include_bytes!(concat!(env!("OUT_DIR"), "/tiny.scdp")));

/// A static handed out once as `&'static mut`, which is all the synchronisation a
/// single-threaded firmware image needs.
struct Once<T> {
    taken: AtomicBool,
    value: UnsafeCell<T>,
}

// SAFETY: `take` hands out the only reference, at most once.
unsafe impl<T> Sync for Once<T> {}

impl<T> Once<T> {
    const fn new(value: T) -> Self {
        Once {
            taken: AtomicBool::new(false),
            value: UnsafeCell::new(value),
        }
    }

    #[allow(
        clippy::mut_from_ref,
        reason = "the atomic flag makes the returned reference unique"
    )]
    fn take(&'static self) -> Option<&'static mut T> {
        if self.taken.swap(true, Ordering::AcqRel) {
            None
        } else {
            // SAFETY: the flag guarantees this is the only reference ever created.
            Some(unsafe { &mut *self.value.get() })
        }
    }
}

/// Zero-initialised, so both land in .bss and cost no file size.
static ARENA: Once<Arena<{ PLAN.arena_bytes }>> = Once::new(Arena::new());
static LOOP_FRAMES: Once<[u8; FRAME_SLOTS * FRAME_BYTES]> =
    Once::new([0; FRAME_SLOTS * FRAME_BYTES]);

const fn frame(u: f32, v: f32) -> [u8; FRAME_BYTES] {
    let mut image = [0; FRAME_BYTES];
    draw_scene(&mut image, WIDTH, HEIGHT, Some(Blob { u, v, radius: 3.0 }));
    image
}

/// Two observations of the end effector moving right, computed by the compiler.
static FRAMES: [[u8; FRAME_BYTES]; 2] = [frame(20.0, 18.0), frame(26.0, 18.0)];
static STATES: [[f32; STATE_DIM]; 2] = [[0.5, 0.0, 0.2, 0.0, 0.0], [0.5, 0.05, 0.2, 0.0, 0.0]];

enum Failure {
    Engine(scdp_engine::Error),
    Check(&'static str),
}

impl From<scdp_engine::Error> for Failure {
    fn from(error: scdp_engine::Error) -> Self {
        Failure::Engine(error)
    }
}

fn check(condition: bool, what: &'static str) -> Result<(), Failure> {
    if condition {
        Ok(())
    } else {
        Err(Failure::Check(what))
    }
}

fn run() -> u8 {
    let mut out = sys::stdout();
    match checks_and_loop(&mut out) {
        Ok(()) => {
            let _ = writeln!(out, "firmware-freestanding: all checks passed");
            0
        }
        Err(Failure::Check(what)) => {
            let _ = writeln!(sys::stderr(), "firmware-freestanding: check failed: {what}");
            1
        }
        Err(Failure::Engine(error)) => {
            let _ = writeln!(
                sys::stderr(),
                "firmware-freestanding: engine error: {error}"
            );
            2
        }
    }
}

/// Resets the history, pushes `frames` and infers; returns the whole denoised chunk.
fn infer_from(
    policy: &mut Policy<'_, '_>,
    frames: &[usize],
    seed: u64,
) -> Result<[f32; CHUNK_VALUES], Failure> {
    policy.reset();
    for &index in frames {
        policy.push_observation(&FRAMES[index], &STATES[index])?;
    }
    let actions = policy.infer(Noise::Seed(seed))?;
    let mut chunk = [0.0; CHUNK_VALUES];
    chunk.copy_from_slice(actions.action_pred());
    check(
        actions.anchors_uv()[..2]
            .iter()
            .all(|value| value.is_finite()),
        "the end effector projects into the image",
    )?;
    Ok(chunk)
}

fn same_bits(a: &[f32], b: &[f32]) -> bool {
    a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
}

fn checks_and_loop(out: &mut sys::Output) -> Result<(), Failure> {
    let arena = ARENA.take().ok_or(Failure::Check("arena taken once"))?;
    let model = Model::from_bytes(&WEIGHTS.0)?;
    model.expect_config(&CONFIG)?;
    let calibration = Calibration::default_for(CONFIG.image_width, CONFIG.image_height);
    let _ = writeln!(
        out,
        "firmware-freestanding: tiny model, weights {} bytes (embedded), arena {} bytes (static)",
        WEIGHTS.0.len(),
        PLAN.arena_bytes
    );

    {
        let mut policy = Policy::new(&model, &mut arena.0)?;
        policy.set_camera(calibration.camera()?);
        let started = sys::monotonic_us();
        let first = infer_from(&mut policy, &[0, 1], SEED)?;
        let elapsed = sys::monotonic_us().saturating_sub(started);
        let again = infer_from(&mut policy, &[0, 1], SEED)?;
        check(
            same_bits(&first, &again),
            "same input and seed give the same bits",
        )?;
        check(
            first.iter().all(|value| value.is_finite()),
            "actions are finite",
        )?;
        let other_seed = infer_from(&mut policy, &[0, 1], SEED + 1)?;
        check(
            !same_bits(&first, &other_seed),
            "the noise seed changes the result",
        )?;
        let other_frames = infer_from(&mut policy, &[1, 0], SEED)?;
        check(
            !same_bits(&first, &other_frames),
            "the observations change the result",
        )?;
        let padded = infer_from(&mut policy, &[0], SEED)?;
        let repeated = infer_from(&mut policy, &[0, 0], SEED)?;
        check(
            same_bits(&padded, &repeated),
            "the first observation fills the whole history",
        )?;
        let _ = writeln!(
            out,
            "firmware-freestanding: 6 inferences checked, {elapsed} us for two encodes and one \
             inference, first action {}",
            Fixed(
                &first[(CONFIG.n_obs_steps as usize - 1) * CONFIG.action_dim as usize..]
                    [..CONFIG.action_dim as usize]
            ),
        );
    }

    let mut policy = Policy::new(&model, &mut arena.0)?;
    policy.set_camera(calibration.camera()?);
    let timing = Timing::panda(CONFIG.n_obs_steps as usize, CONFIG.n_action_steps as usize);
    let robot = SimRobot::new(&CONFIG, &timing, calibration)?;
    let dims = Dims {
        frame_bytes: FRAME_BYTES,
        state_dim: STATE_DIM,
        action_dim: CONFIG.action_dim as usize,
    };
    let frames = LOOP_FRAMES
        .take()
        .ok_or(Failure::Check("frames taken once"))?;
    let mut control = ControlLoop::new(
        timing,
        dims,
        EnginePolicy::new(policy, SEED, Some(PrefixMode::Replace), true),
        Monotonic,
        robot,
        frames,
    )
    .map_err(|_| Failure::Check("the loop accepts the tiny model's dimensions"))?;
    control.run_until(LOOP_SECONDS * 1_000_000)?;
    let stats = control.stats();
    let expected_inferences = (LOOP_SECONDS * 10).div_ceil(timing.steps_per_inference as u64);
    check(
        stats.inferences == expected_inferences,
        "the loop infers on every inference tick",
    )?;
    check(
        stats.deadline_misses == 0,
        "the tiny model meets every deadline",
    )?;
    let _ = writeln!(
        out,
        "firmware-freestanding: control loop {LOOP_SECONDS} s simulated: {} inferences, {} actions \
         run, {} stale dropped, {} replaced, {} deadline misses, latency p50 {} us max {} us",
        stats.inferences,
        stats.actions_executed,
        stats.stale_actions,
        stats.replaced_actions,
        stats.deadline_misses,
        stats.latency.percentile(500).unwrap_or(0),
        stats.latency.max(),
    );
    Ok(())
}

struct Monotonic;

impl Stopwatch for Monotonic {
    fn now_us(&mut self) -> u64 {
        sys::monotonic_us()
    }
}

/// Values with three decimals, without pulling in float formatting.
struct Fixed<'a>(&'a [f32]);

impl fmt::Display for Fixed<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("[")?;
        for (index, &value) in self.0.iter().enumerate() {
            let separator = if index == 0 { "" } else { ", " };
            let thousandths = (value * 1000.0) as i64;
            let sign = if thousandths < 0 { "-" } else { "" };
            let magnitude = thousandths.unsigned_abs();
            write!(
                f,
                "{separator}{sign}{}.{:03}",
                magnitude / 1000,
                magnitude % 1000
            )?;
        }
        f.write_str("]")
    }
}
