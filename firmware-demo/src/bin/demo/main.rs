//! The host control-loop demo: the SCDP engine in a simulated Panda-style loop (30 fps camera,
//! 1 kHz robot state, 10 Hz actions), in simulated time (see `firmware_demo::control`).
//!
//! `cargo run --release -p firmware-demo` runs 30 simulated seconds of the metaworld-sized
//! model with seeded synthetic weights generated in-process.

mod calibration_file;

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context as _, bail};
use clap::Parser;
use firmware_demo::timing::MICROS_PER_SECOND;
use firmware_demo::{
    Calibration, ControlLoop, Dims, EnginePolicy, FRAME_SLOTS, Histogram, LoopStats, SimRobot,
    Stopwatch, Timing,
};
use scdp_engine::{ArenaPlan, Model, ModelConfig, Policy, PrefixMode};
use weights_tool::writer::{AlignedBytes, aligned_copy};
use weights_tool::{Quant, load_config, synth_state_dict};

/// Runs the SCDP engine in a simulated robot control loop and reports its timing.
#[derive(Parser)]
#[command(name = "firmware-demo", version, about)]
struct Cli {
    /// Simulated seconds to run.
    #[arg(long, default_value_t = 30.0, value_name = "SECONDS")]
    duration: f64,
    /// Model config: a preset (panda, metaworld, tiny) or a TOML file. Defaults to metaworld,
    /// or to the config recorded in --weights.
    #[arg(long, value_name = "PRESET|FILE")]
    config: Option<String>,
    /// Weights file (weights-tool convert). Without it, seeded synthetic weights are
    /// generated in-process for the config.
    #[arg(long, value_name = "FILE")]
    weights: Option<PathBuf>,
    /// Seed of the synthetic weights and of the inferences' noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Camera calibration TOML (intrinsics and extrinsics). Defaults to a camera in front of
    /// the robot looking at the workspace.
    #[arg(long, value_name = "FILE")]
    camera: Option<PathBuf>,
    /// Control ticks between inferences. Defaults to n_action_steps - 2: action 0 of a chunk
    /// is always stale and one more step is the latency budget.
    #[arg(long, value_name = "N")]
    steps_per_inference: Option<usize>,
    /// Simulated seconds between status lines.
    #[arg(long, default_value_t = 2.0, value_name = "SECONDS")]
    status_every: f64,
    /// Print the camera calibration in use as a --camera file and exit.
    #[arg(long)]
    print_camera: bool,
    /// How an inference holds the actions that run before its chunk arrives (docs/SPEC.md
    /// section 5.1): "replace" or "noised" condition the chunk on them; "none" ignores them
    /// (the chunk's own actions for those ticks are dropped as stale).
    #[arg(long, default_value = "replace", value_name = "MODE")]
    prefix: PrefixArg,
    /// With a prefix: do not give the queued plan after it, which the new chunk is
    /// otherwise pulled towards.
    #[arg(long)]
    no_planned: bool,
    /// Workers an inference runs on: the control loop's thread and N - 1 threads started
    /// once (the same actions for any number).
    #[arg(long, default_value_t = 1, value_name = "N")]
    threads: usize,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum PrefixArg {
    None,
    Replace,
    Noised,
}

impl PrefixArg {
    fn mode(self) -> Option<PrefixMode> {
        match self {
            PrefixArg::None => None,
            PrefixArg::Replace => Some(PrefixMode::Replace),
            PrefixArg::Noised => Some(PrefixMode::Noised),
        }
    }
}

const DEFAULT_PRESET: &str = "metaworld";

fn preset(name: &str) -> Option<ModelConfig> {
    match name {
        "panda" => Some(ModelConfig::PANDA),
        "metaworld" => Some(ModelConfig::METAWORLD),
        "tiny" => Some(ModelConfig::TINY),
        _ => None,
    }
}

fn resolve_config(name: &str) -> anyhow::Result<ModelConfig> {
    match preset(name) {
        Some(config) => Ok(config),
        None => load_config(name.as_ref())
            .with_context(|| format!("--config {name} is not a preset (panda, metaworld, tiny)")),
    }
}

/// The weights bytes, 64-byte aligned, and where they came from: the --weights file, or
/// seeded synthetic weights for `config`.
fn load_weights(cli: &Cli, config: &ModelConfig) -> anyhow::Result<(AlignedBytes, String)> {
    if let Some(path) = &cli.weights {
        let bytes = std::fs::read(path)
            .with_context(|| format!("{}: cannot read the weights file", path.display()))?;
        return Ok((aligned_copy(&bytes), path.display().to_string()));
    }
    let started = Instant::now();
    let state_dict = synth_state_dict(config, cli.seed);
    let bytes = weights_tool::lowering::lower_to_weights_file(config, &state_dict, Quant::F32)?;
    let description = format!(
        "synthetic, seed {}, generated in {:.2} s",
        cli.seed,
        started.elapsed().as_secs_f64()
    );
    Ok((aligned_copy(&bytes), description))
}

fn calibration_for(cli: &Cli, config: &ModelConfig) -> anyhow::Result<Calibration> {
    match &cli.camera {
        Some(path) => calibration_file::load(path),
        None => Ok(Calibration::default_for(
            config.image_width,
            config.image_height,
        )),
    }
}

fn seconds_to_us(seconds: f64, what: &str) -> anyhow::Result<u64> {
    if !(seconds.is_finite() && seconds > 0.0) {
        bail!("{what} must be a positive number of seconds");
    }
    Ok((seconds * MICROS_PER_SECOND as f64).round() as u64)
}

struct WallClock(Instant);

impl Stopwatch for WallClock {
    fn now_us(&mut self) -> u64 {
        self.0.elapsed().as_micros() as u64
    }
}

fn milliseconds(micros: u64) -> String {
    format!("{:.1} ms", micros as f64 / 1000.0)
}

fn percentiles(histogram: &Histogram) -> String {
    match (histogram.percentile(500), histogram.percentile(990)) {
        (Some(p50), Some(p99)) => format!(
            "p50 {}  p99 {}  max {}",
            milliseconds(p50),
            milliseconds(p99),
            milliseconds(histogram.max())
        ),
        _ => "none".into(),
    }
}

fn run(cli: &Cli) -> anyhow::Result<()> {
    let duration_us = seconds_to_us(cli.duration, "--duration")?;
    let status_us = seconds_to_us(cli.status_every, "--status-every")?;
    let requested = cli.config.as_deref().map(resolve_config).transpose()?;
    let synthetic_config =
        requested.unwrap_or(preset(DEFAULT_PRESET).expect("the default is a preset"));
    if cli.print_camera && cli.weights.is_none() {
        print!(
            "{}",
            calibration_file::to_toml(&calibration_for(cli, &synthetic_config)?)
        );
        return Ok(());
    }
    let (weights, weights_source) = load_weights(cli, &synthetic_config)?;
    let model = Model::from_bytes(weights.as_slice()).context("weights")?;
    if let Some(requested) = &requested {
        // Only a --weights file can disagree: it records the config it was made for.
        model.expect_config(requested).context("--config")?;
    }
    let config = *model.config();
    let calibration = calibration_for(cli, &config)?;
    if cli.print_camera {
        print!("{}", calibration_file::to_toml(&calibration));
        return Ok(());
    }

    let mut timing = Timing::panda(config.n_obs_steps as usize, config.n_action_steps as usize);
    if let Some(steps) = cli.steps_per_inference {
        timing.steps_per_inference = steps;
    }
    timing.validate().context("timing")?;

    let plan = ArenaPlan::new(&config);
    let mut arena = AlignedBytes::zeroed(plan.arena_bytes);
    anyhow::ensure!(cli.threads > 0, "--threads needs at least one thread");
    let pool = scdp_threads::ThreadPool::new(cli.threads).context("worker threads")?;
    let mut policy = Policy::new(&model, arena.as_mut_slice())
        .context("policy")?
        .with_workers(&pool);
    policy.set_camera(calibration.camera().context("camera")?);
    let kernels = policy.kernels_name();
    let threads = policy.workers();
    let robot = SimRobot::new(&config, &timing, calibration).context("camera")?;
    let dims = Dims {
        frame_bytes: (config.image_height * config.image_width * 3) as usize,
        state_dim: config.state_dim as usize,
        action_dim: config.action_dim as usize,
    };
    let mut frames = vec![0u8; FRAME_SLOTS * dims.frame_bytes];
    let wall = Instant::now();
    let mut control = ControlLoop::new(
        timing,
        dims,
        EnginePolicy::new(policy, cli.seed, cli.prefix.mode(), !cli.no_planned),
        WallClock(wall),
        robot,
        &mut frames,
    )?;

    println!(
        "model: {}x{} images, To {}, horizon {}, {} actions per chunk, action_dim {}; weights {} \
         ({:.1} MB); arena {:.1} MB; kernels {kernels} on {threads} thread(s)",
        config.image_width,
        config.image_height,
        config.n_obs_steps,
        config.horizon,
        config.n_action_steps,
        config.action_dim,
        weights_source,
        weights.as_slice().len() as f64 / 1e6,
        plan.arena_bytes as f64 / 1e6,
    );
    println!(
        "loop: {} Hz control, {} Hz state stream, {} fps camera, inference every {} ticks; \
         {:.1} s simulated (the clock advances by measured compute time, nothing sleeps)",
        MICROS_PER_SECOND / timing.control_period_us,
        MICROS_PER_SECOND / timing.state_period_us,
        timing.camera_fps,
        timing.steps_per_inference,
        cli.duration,
    );

    let mut next_status = status_us.min(duration_us);
    loop {
        control.run_until(next_status).context("engine")?;
        print_status(&control);
        if next_status >= duration_us {
            break;
        }
        next_status = (next_status + status_us).min(duration_us);
    }
    print_summary(
        control.stats(),
        control.now_us(),
        wall.elapsed().as_secs_f64(),
    );
    Ok(())
}

fn print_status<C: Stopwatch>(control: &ControlLoop<'_, EnginePolicy<'_, '_>, C, SimRobot>) {
    let stats = control.stats();
    let [x, y, z] = control.plant().position();
    let looking_at = control
        .policy()
        .last_path()
        .map(|path| {
            format!(
                "  anchors ({:.0},{:.0})->({:.0},{:.0}) px",
                path.start[0], path.start[1], path.end[0], path.end[1]
            )
        })
        .unwrap_or_default();
    println!(
        "t {:5.1} s  ee ({x:.3}, {y:.3}, {z:.3}) m  chunks {:3}  queued {:2}  last latency {:>8}  \
         misses {}  stale {}  held {}{looking_at}",
        control.now_us() as f64 / MICROS_PER_SECOND as f64,
        stats.inferences,
        control.queue().len(),
        stats
            .last_latency_us
            .map(milliseconds)
            .unwrap_or_else(|| "-".into()),
        stats.deadline_misses,
        stats.stale_actions,
        stats.ticks_held,
    );
}

fn print_summary(stats: &LoopStats, simulated_us: u64, wall_seconds: f64) {
    let mean = |histogram: &Histogram| histogram.mean().map(milliseconds).unwrap_or("-".into());
    println!(
        "summary: {:.1} s simulated in {wall_seconds:.1} s wall",
        simulated_us as f64 / MICROS_PER_SECOND as f64
    );
    println!(
        "  inferences {} ({} skipped: processor busy); frames encoded {} of {} captured ({} dropped)",
        stats.inferences,
        stats.skipped_inferences,
        stats.frames_encoded,
        stats.frames_captured,
        stats.frames_dropped,
    );
    println!(
        "  latency, observation to actions: {}",
        percentiles(&stats.latency)
    );
    println!(
        "  compute per call: encode mean {}, infer mean {}",
        mean(&stats.encode_time),
        mean(&stats.infer_time),
    );
    println!(
        "  control ticks {}: {} actions run, {} held for want of an action",
        stats.control_ticks, stats.actions_executed, stats.ticks_held,
    );
    println!(
        "  deadline misses {}; stale actions dropped {}; queued actions replaced at hand-over {}",
        stats.deadline_misses, stats.stale_actions, stats.replaced_actions,
    );
    let seams = &stats.seams;
    let figure = |value: Option<f64>| value.map_or("-".into(), |v| format!("{v:.4}"));
    println!(
        "  seams over {} hand-overs ({} committed rows offered as prefixes): jump mean {} max {:.4}; \
         largest of the next {} steps mean {} max {:.4} (action units)",
        seams.count,
        stats.prefix_rows,
        figure(seams.jump_mean()),
        seams.jump_max,
        firmware_demo::SEAM_WINDOW,
        figure(seams.early_step_mean()),
        seams.early_step_max,
    );
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(&cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("firmware-demo: {error:#}");
            ExitCode::FAILURE
        }
    }
}
