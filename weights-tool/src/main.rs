//! `weights-tool`: converts SCDP checkpoints into the engine's weights file, inspects and
//! runs weights files, and makes synthetic checkpoints.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::Context as _;
use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};

use weights_tool::inspect::WeightCounts;
use weights_tool::keys::{check_keys, expected_keys};
use weights_tool::synth::{hex, synth_state_dict, weights_sha256};
use weights_tool::{
    KeyPrefix, Quant, config_to_toml, load_checkpoint_with_progress, load_config, remap_keys,
    write_state_dict_safetensors,
};

#[derive(Parser)]
#[command(name = "weights-tool", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Generate the seeded synthetic weights of docs/SYNTHETIC.md as a .safetensors checkpoint.
    Synth(SynthArgs),
    /// Convert a checkpoint (training checkpoint, torch.save state dict or .safetensors) into
    /// the engine's weights file.
    Convert(ConvertArgs),
    /// Show a weights file's config, storage, arena plan and tensor table.
    Inspect(InspectArgs),
    /// Add the pair layout to an int8 file's 8-bit layers (as `convert --weight-pairs`
    /// writes it), for the `i8mm` backend; the same outputs, bit for bit.
    AddPairs(AddPairsArgs),
    /// Run the engine on a run file (docs/SPEC.md section 8): actions, anchors, optional picture and
    /// latency benchmark.
    Run(RunArgs),
}

#[derive(clap::Args)]
struct InspectArgs {
    /// Weights file written by `convert`.
    #[arg(value_name = "MODEL.scdp")]
    model: PathBuf,
}

#[derive(clap::Args)]
struct AddPairsArgs {
    /// Int8 weights file written by `convert`.
    #[arg(value_name = "MODEL.scdp")]
    model: PathBuf,
    /// The file with the pair layout.
    #[arg(short, long, value_name = "OUT.scdp")]
    output: PathBuf,
}

#[derive(clap::Args)]
struct RunArgs {
    /// Weights file written by `convert`.
    #[arg(value_name = "MODEL.scdp")]
    model: PathBuf,
    /// Inputs: `images` u8 [To,H,W,3], `state` f32 [To,state_dim], `camera_k` f32 [3,3],
    /// `camera_t` f32 [4,4], optional `noise` f32 [horizon,action_dim].
    #[arg(long, value_name = "IN.safetensors")]
    inputs: PathBuf,
    /// Outputs: `action_pred`, `action`, `anchors_uv` (NaN where invalid).
    #[arg(short, long, value_name = "OUT.safetensors")]
    output: Option<PathBuf>,
    /// Seed of the engine's noise generator, used when the inputs hold no `noise`.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Draw the newest frame with every denoising step's anchors (colour by step, blue to red).
    #[arg(long, value_name = "OUT.png")]
    viz: Option<PathBuf>,
    /// Run the inference N more times after a warm-up and print median and p99 per stage.
    #[arg(long, value_name = "N")]
    bench: Option<usize>,
    /// Kernel backend: `auto` (the fastest this CPU runs) or one by name (scalar, avx2,
    /// avx512, amx, neon, dot, i8mm); `inspect` lists this CPU's.
    #[arg(long, value_name = "NAME", default_value = "auto")]
    kernels: String,
    /// Workers an inference runs on: the calling thread and N - 1 more. A list (`1,2`)
    /// runs the inference on each, checks they give the same bits, and benchmarks each in
    /// turn with `--bench`.
    #[arg(
        long,
        value_name = "N[,N...]",
        value_delimiter = ',',
        default_value = "1"
    )]
    threads: Vec<usize>,
}

#[derive(clap::Args)]
struct SynthArgs {
    /// Model config TOML (docs/SPEC.md section 7).
    #[arg(long, value_name = "MODEL.toml")]
    config: PathBuf,
    /// Generator seed.
    #[arg(long, value_name = "N")]
    seed: u64,
    /// Output checkpoint.
    #[arg(short, long, value_name = "CKPT.safetensors")]
    output: PathBuf,
}

#[derive(clap::Args)]
struct ConvertArgs {
    /// Training checkpoint (.ckpt), torch.save state dict (.pt) or .safetensors file.
    #[arg(value_name = "CHECKPOINT")]
    checkpoint: PathBuf,
    /// Model config TOML (docs/SPEC.md section 7) the checkpoint was trained with.
    #[arg(long, value_name = "MODEL.toml")]
    config: PathBuf,
    /// Storage precision of the weights.
    #[arg(long, value_enum, default_value_t = QuantArg::F32)]
    quant: QuantArg,
    /// Rename keys starting with OLD to start with NEW before checking them (repeatable; the
    /// first matching rule applies).
    #[arg(long = "key-prefix", value_name = "OLD=NEW")]
    key_prefix: Vec<KeyPrefix>,
    /// With `--quant int8`: run files (the inputs `run` takes, e.g. observations recorded on
    /// the robot) on which the f32 model is run to calibrate GPTQ rounding.
    #[arg(long, value_name = "RUN.safetensors", num_args = 1..)]
    calibrate: Vec<PathBuf>,
    /// With `--quant int8`: also calibrate on N synthetic scenes seen through `--camera`.
    #[arg(long, value_name = "N", requires = "camera", default_value_t = 0)]
    synthetic_scenes: usize,
    /// Run file whose `camera_k` and `camera_t` the synthetic scenes are seen through.
    #[arg(long, value_name = "RUN.safetensors")]
    camera: Option<PathBuf>,
    /// With `--quant int8`: how weights are rounded. `gptq` needs calibration scenes;
    /// `nearest` is only for comparisons (it misses the fidelity floor, docs/QUANTIZATION.md).
    #[arg(long, value_enum, default_value_t = RoundingArg::Gptq)]
    rounding: RoundingArg,
    /// With `--quant int8`: the codes the residual blocks' layers quantize their input to.
    /// `measured`: 8-bit where the calibration scenes' actions stay within
    /// `--action-budget` of the f32 model's, 15-bit elsewhere; `wide`: 15-bit everywhere
    /// (the precise scheme); `narrow`: 8-bit everywhere they can be.
    #[arg(long, value_enum, default_value_t = ActivationsArg::Measured)]
    activations: ActivationsArg,
    /// With `--activations measured`: how much the 8-bit codes may raise the mean difference
    /// between the file's predicted actions and the f32 model's on the calibration scenes,
    /// as a fraction of the 15-bit file's (0.05: by 5%); never past the fidelity floor's
    /// mean, 0.005 normalized.
    #[arg(long, value_name = "FRACTION", default_value_t = weights_tool::activations::Budget::DEFAULT.mean_increase)]
    action_budget: f64,
    /// With `--quant int8`: which of the trunk's residual-block layers store their rounding
    /// error as a second int8 plane (about 15-bit weights, twice the layer's integer
    /// products). `measured`: only where the calibration scenes' actions would otherwise
    /// leave `--action-budget` of the file with every trunk layer refined; `none`; `trunk`:
    /// every one of them.
    #[arg(long, value_enum, default_value_t = RefineArg::Measured)]
    refine: RefineArg,
    /// Threads the measurements run on (the calibration scenes shared out among them); the
    /// same choices and the same file for any number. Default: every core.
    #[arg(long, value_name = "N", default_value_t = every_core())]
    threads: usize,
    /// With `--quant int8`: store the 8-bit layers' kernels a second time in eight-input
    /// groups, the operands of I8MM's matrix multiplies (the `i8mm` backend: Neoverse V1/V2,
    /// Graviton 3/4, Cortex-A710 on), so it need not pair them as it runs. The same
    /// outputs, bit for bit; the file grows by those layers' weights (docs/ARM.md).
    #[arg(long)]
    weight_pairs: bool,
    /// Output weights file.
    #[arg(short, long, value_name = "MODEL.scdp")]
    output: PathBuf,
}

/// The cores this process may run on.
fn every_core() -> usize {
    std::thread::available_parallelism().map_or(1, usize::from)
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum RoundingArg {
    /// GPTQ, calibrated on the scenes: each weight rounded so the layer's output error on
    /// inputs like them is small.
    Gptq,
    /// Each weight to the nearest step, no calibration.
    Nearest,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum RefineArg {
    /// Refined where the actions need it, measured on the calibration scenes.
    Measured,
    /// One int8 plane everywhere.
    None,
    /// Every residual-block layer of the trunk refined.
    Trunk,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum ActivationsArg {
    /// 8-bit codes where the actions stay within the budget, measured layer by layer.
    Measured,
    /// 15-bit codes everywhere.
    Wide,
    /// 8-bit codes in every residual-block layer.
    Narrow,
}

#[derive(Clone, Copy, ValueEnum)]
enum QuantArg {
    /// Every tensor as f32.
    F32,
    /// Weight matrices and kernels as int8 with scales.
    Int8,
}

impl From<QuantArg> for Quant {
    fn from(quant: QuantArg) -> Self {
        match quant {
            QuantArg::F32 => Quant::F32,
            QuantArg::Int8 => Quant::Int8,
        }
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Synth(args) => synth(&args),
        Command::Convert(args) => convert(&args),
        Command::Inspect(args) => inspect(&args),
        Command::AddPairs(args) => add_pairs(&args),
        Command::Run(args) => run(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            // `:#` puts the whole context chain (file, key, cause) on one line.
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}

fn synth(args: &SynthArgs) -> anyhow::Result<()> {
    let config = load_config(&args.config)?;
    let spinner = spinner("generating weights");
    let state_dict = synth_state_dict(&config, args.seed);
    let digest = hex(&weights_sha256(&state_dict));
    spinner.finish_and_clear();
    let metadata = BTreeMap::from([
        ("format".to_owned(), "pt".to_owned()),
        ("generator".to_owned(), "weights-tool synth".to_owned()),
        ("seed".to_owned(), args.seed.to_string()),
        ("weights_sha256".to_owned(), digest.clone()),
        ("config".to_owned(), config_to_toml(&config)),
    ]);
    write_state_dict_safetensors(&state_dict, &metadata, &args.output)?;
    println!(
        "wrote {}: {} tensors, {} values, weights_sha256 {digest}",
        args.output.display(),
        state_dict.len(),
        state_dict.numel()
    );
    Ok(())
}

/// Seed of `--synthetic-scenes`: the scenes are the same for every conversion.
const SYNTHETIC_SCENE_SEED: u64 = 7;

/// The recorded and synthetic calibration scenes `convert` was given.
fn calibration_scenes(
    args: &ConvertArgs,
    config: &scdp_engine::ModelConfig,
) -> anyhow::Result<Vec<weights_tool::run::RunInputs>> {
    let mut scenes = args
        .calibrate
        .iter()
        .map(|path| weights_tool::run::RunInputs::load(path, config))
        .collect::<anyhow::Result<Vec<_>>>()?;
    if let (Some(camera), count @ 1..) = (&args.camera, args.synthetic_scenes) {
        let seen_through = weights_tool::run::RunInputs::load(camera, config)?;
        scenes.extend(weights_tool::scenes::synthetic_scenes(
            config,
            seen_through.intrinsics,
            seen_through.extrinsics,
            count,
            SYNTHETIC_SCENE_SEED,
        ));
    }
    Ok(scenes)
}

/// What `--quant int8` needs before anything is computed: calibration scenes, unless
/// round-to-nearest was asked for by name.
const INT8_NEEDS_SCENES: &str = "--quant int8 rounds with GPTQ and measures the activation widths on calibration scenes: pass --calibrate RUN.safetensors... (observations recorded on the robot) and/or --synthetic-scenes N --camera RUN.safetensors, or --rounding nearest for an uncalibrated file (it misses the fidelity floor, docs/QUANTIZATION.md)";

/// An int8 weights file: rounded as asked, its refined layers and then its activation widths
/// as asked (measured on `scenes` by default); returns the file and what was measured.
fn int8_weights_file(
    args: &ConvertArgs,
    config: &scdp_engine::ModelConfig,
    state_dict: &weights_tool::StateDict,
    scenes: &[weights_tool::run::RunInputs],
) -> anyhow::Result<Int8File> {
    use weights_tool::activations::{self, Budget};
    use weights_tool::lowering::{self, Rounding};
    use weights_tool::refine;
    use weights_tool::writer::{add_weight_pairs, write_weights_file};
    anyhow::ensure!(
        !scenes.is_empty() || args.rounding == RoundingArg::Nearest,
        INT8_NEEDS_SCENES
    );
    anyhow::ensure!(
        args.action_budget.is_finite() && args.action_budget >= 0.0,
        "--action-budget must be a fraction, 0 or more"
    );
    let lowered = lowering::lower(config, state_dict)?;
    let f32_stored = lowering::store(config, lowered.clone(), Quant::F32, Rounding::Nearest)?;
    let f32_file = write_weights_file(config, &f32_stored)?;
    let mut stages = Vec::new();
    let started = Instant::now();
    let moments = match args.rounding {
        RoundingArg::Gptq => Some(weights_tool::calibrate::input_moments(
            &f32_file,
            &lowering::int8_tensors(config)?,
            scenes,
            true,
        )?),
        RoundingArg::Nearest => None,
    };
    if moments.is_some() {
        stages.push(("calibration", started.elapsed()));
    }
    let rounding = moments
        .as_ref()
        .map_or(Rounding::Nearest, Rounding::Calibrated);
    let started = Instant::now();
    let spinner = spinner(&on_threads("rounding", args.threads));
    let mut stored = lowering::store_on(config, lowered, (Quant::Int8, rounding), args.threads)?;
    spinner.finish_and_clear();
    stages.push(("rounding", started.elapsed()));
    let started = Instant::now();
    let budget = Budget::with_increase(args.action_budget);
    let refinement = match args.refine {
        RefineArg::None => None,
        RefineArg::Measured if scenes.is_empty() => None,
        RefineArg::Trunk => {
            let names = refine::candidates(&stored);
            refine::set_refined(&mut stored, &names, true);
            None
        }
        RefineArg::Measured => Some(with_progress(
            &on_threads("measuring weight refinement", args.threads),
            |progress| {
                refine::choose(
                    config,
                    &mut stored,
                    &f32_file,
                    scenes,
                    budget,
                    args.threads,
                    progress,
                )
            },
        )?),
    };
    if refinement.is_some() {
        stages.push(("refinement", started.elapsed()));
    }
    let started = Instant::now();
    let report = match args.activations {
        ActivationsArg::Wide => None,
        ActivationsArg::Measured if scenes.is_empty() => None,
        ActivationsArg::Narrow => {
            activations::set_all_narrow(config, &mut stored)?;
            None
        }
        ActivationsArg::Measured => Some(with_progress(
            &on_threads("measuring activation widths", args.threads),
            |progress| {
                activations::choose(
                    config,
                    &mut stored,
                    &f32_file,
                    scenes,
                    budget,
                    args.threads,
                    progress,
                )
            },
        )?),
    };
    if report.is_some() {
        stages.push(("activation widths", started.elapsed()));
    }
    Ok(Int8File {
        bytes: match args.weight_pairs {
            true => add_weight_pairs(&write_weights_file(config, &stored)?)?,
            false => write_weights_file(config, &stored)?,
        },
        widths: report,
        refinement,
        stages,
    })
}

/// A progress label saying how many threads do the work.
fn on_threads(label: &str, threads: usize) -> String {
    format!("{label} on {}", thread_count(threads))
}

/// "1 thread", "2 threads".
fn thread_count(threads: usize) -> String {
    let plural = if threads == 1 { "" } else { "s" };
    format!("{threads} thread{plural}")
}

/// An int8 weights file and what was measured to make it.
struct Int8File {
    bytes: Vec<u8>,
    widths: Option<weights_tool::activations::WidthReport>,
    refinement: Option<weights_tool::refine::RefineReport>,
    /// The int8 stages that ran, with how long each took.
    stages: Vec<(&'static str, Duration)>,
}

/// `convert`'s lines about an int8 file's refined layers.
fn print_refinement(
    args: &ConvertArgs,
    counts: &WeightCounts,
    report: Option<&weights_tool::refine::RefineReport>,
) {
    let Some(report) = report else {
        let refined = counts.refined;
        let why = match args.refine {
            RefineArg::None => "none (--refine none)",
            RefineArg::Trunk => "every trunk residual-block layer (--refine trunk)",
            RefineArg::Measured => "none (no calibration scenes to measure on)",
        };
        println!("  refined        {why}: {refined} layers");
        return;
    };
    println!(
        "  refined        measured on {} calibration scenes x {} noise draws against the f32 model (normalized actions); budget: mean at most {:.0}% over every trunk layer refined",
        report.scenes,
        weights_tool::activations::NOISE_DRAWS,
        100.0 * report.budget.mean_increase,
    );
    println!("                 none refined: {}", report.none);
    println!("                 every trunk layer refined: {}", report.all);
    let chosen = report.layers.iter().filter(|layer| layer.refined).count();
    println!(
        "                 chosen, {chosen} of {} trunk layers refined: {}",
        report.layers.len(),
        report.chosen
    );
    for layer in &report.layers {
        let (what, why) = if layer.refined {
            ("refined", "needed to stay within the budget")
        } else {
            ("one plane", "within the budget without it")
        };
        println!(
            "  {what:<9}      {:<40} alone: {}; {why}",
            layer.name, layer.alone
        );
    }
}

/// `convert`'s lines about an int8 file's activation codes.
fn print_activations(
    args: &ConvertArgs,
    counts: &WeightCounts,
    report: Option<&weights_tool::activations::WidthReport>,
) {
    let Some(report) = report else {
        let WeightCounts { wide, narrow, .. } = *counts;
        let why = match args.activations {
            ActivationsArg::Narrow => "8-bit in every residual-block layer (--activations narrow)",
            ActivationsArg::Wide => "15-bit everywhere (--activations wide)",
            ActivationsArg::Measured => "15-bit everywhere (no calibration scenes to measure on)",
        };
        println!("  activations    {why}: {narrow} layers 8-bit, {wide} 15-bit");
        return;
    };
    println!(
        "  activations    measured on {} calibration scenes x {} noise draws against the f32 model (normalized actions); budget: mean at most {:.0}% over 15-bit codes, capped at {:.1e}",
        report.scenes,
        weights_tool::activations::NOISE_DRAWS,
        100.0 * report.budget.mean_increase,
        report.budget.mean_cap
    );
    println!("                 15-bit everywhere: {}", report.wide);
    let within = report.budget.holds(&report.wide, &report.wide);
    if !within {
        println!(
            "                 over the cap already: every layer keeps 15-bit codes (--activations narrow forces 8-bit)"
        );
    }
    let chosen = report
        .layers
        .iter()
        .filter(|layer| layer.codes == scdp_engine::weights::ActivationCodes::Narrow)
        .count();
    println!(
        "                 chosen, {chosen} of {} residual-block layers 8-bit: {}",
        report.layers.len(),
        report.chosen
    );
    for layer in &report.layers {
        let (codes, why) = match layer.codes {
            scdp_engine::weights::ActivationCodes::Narrow => ("8-bit ", "within the budget"),
            scdp_engine::weights::ActivationCodes::Wide if within => {
                ("15-bit", "over the budget with the 8-bit layers before it")
            }
            scdp_engine::weights::ActivationCodes::Wide => ("15-bit", "not tried"),
        };
        println!(
            "  {codes}         {:<40} alone: {}; {why}",
            layer.name, layer.alone
        );
    }
}

fn convert(args: &ConvertArgs) -> anyhow::Result<()> {
    let config = load_config(&args.config)?;
    let state_dict = read_with_progress(&args.checkpoint)?;
    println!(
        "read {} ({}): {} tensors",
        args.checkpoint.display(),
        state_dict.source,
        state_dict.len()
    );
    let state_dict = remap_keys(state_dict, &args.key_prefix)
        .with_context(|| args.checkpoint.display().to_string())?;
    check_keys(&state_dict, &expected_keys(&config)).with_context(|| {
        format!(
            "{} does not fit {}",
            args.checkpoint.display(),
            args.config.display()
        )
    })?;
    let quant = Quant::from(args.quant);
    let scenes = calibration_scenes(args, &config)?;
    anyhow::ensure!(
        scenes.is_empty() || quant == Quant::Int8,
        "calibration scenes only apply to --quant int8"
    );
    anyhow::ensure!(
        !args.weight_pairs || quant == Quant::Int8,
        "--weight-pairs only applies to --quant int8 (f32 files have no 8-bit layers)"
    );
    let int8 = match quant {
        Quant::F32 => {
            let spinner = spinner("converting to f32");
            let bytes = weights_tool::lowering::lower_to_weights_file(&config, &state_dict, quant);
            spinner.finish_and_clear();
            bytes.map(|bytes| Int8File {
                bytes,
                widths: None,
                refinement: None,
                stages: Vec::new(),
            })
        }
        Quant::Int8 => int8_weights_file(args, &config, &state_dict, &scenes),
    };
    let Int8File {
        bytes,
        widths: report,
        refinement,
        stages,
    } = int8.with_context(|| format!("converting {}", args.checkpoint.display()))?;
    std::fs::write(&args.output, &bytes)
        .with_context(|| format!("{}: cannot write", args.output.display()))?;
    let plan = scdp_engine::ArenaPlan::new(&config);
    println!("wrote {}", args.output.display());
    println!("  weights used   {}", state_dict.source);
    println!("  storage        {quant}");
    if quant == Quant::Int8 {
        println!(
            "  int8 scheme    convolutions: int8 weights x 15-bit activations (one scale per layer input; two int8 digits in the trunk, i16 in the U-Net), or x 8-bit activations where chosen below (unsigned in the trunk, signed in the U-Net); FiLM: int8 weights x 15-bit activations (i16)"
        );
        match args.rounding {
            RoundingArg::Nearest => println!(
                "  rounding       to nearest (--rounding nearest: the fidelity floor of docs/QUANTIZATION.md needs GPTQ)"
            ),
            RoundingArg::Gptq => println!(
                "  rounding       GPTQ, calibrated on {} scenes ({} recorded, {} synthetic), damping {}",
                scenes.len(),
                args.calibrate.len(),
                args.synthetic_scenes,
                weights_tool::lowering::GPTQ_DAMPING
            ),
        }
        let counts = weights_tool::inspect::weight_counts(&bytes).unwrap_or_default();
        print_refinement(args, &counts, refinement.as_ref());
        print_activations(args, &counts, report.as_ref());
        for (name, why) in weights_tool::lowering::int8_kept_f32(&config) {
            println!("  kept f32       {name}: {why}");
        }
        let times: Vec<String> = stages
            .iter()
            .map(|(stage, took)| format!("{stage} {:.1} s", took.as_secs_f64()))
            .collect();
        println!(
            "  took           {} (on {})",
            times.join(", "),
            thread_count(args.threads)
        );
    }
    println!("  parameters     {}", state_dict.numel());
    println!(
        "  file           {} bytes ({:.1} MiB)",
        bytes.len(),
        bytes.len() as f64 / 1048576.0
    );
    println!(
        "  arena          {} bytes ({:.1} MiB), {:.1} MiB without buffer reuse",
        plan.arena_bytes,
        plan.arena_bytes as f64 / 1048576.0,
        plan.without_reuse_bytes as f64 / 1048576.0
    );
    println!(
        "  model          {}x{} frames x{}, horizon {}, {} DDIM steps",
        config.image_width,
        config.image_height,
        config.n_obs_steps,
        config.horizon,
        config.num_inference_steps
    );
    Ok(())
}

fn read_file(path: &Path) -> anyhow::Result<Vec<u8>> {
    std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))
}

fn inspect(args: &InspectArgs) -> anyhow::Result<()> {
    let bytes = read_file(&args.model)?;
    let report =
        weights_tool::inspect::report(&bytes).with_context(|| args.model.display().to_string())?;
    print!("{report}");
    Ok(())
}

fn add_pairs(args: &AddPairsArgs) -> anyhow::Result<()> {
    let bytes = read_file(&args.model)?;
    let paired = weights_tool::writer::add_weight_pairs(&bytes)
        .with_context(|| args.model.display().to_string())?;
    std::fs::write(&args.output, &paired)
        .with_context(|| format!("writing {}", args.output.display()))?;
    let counts = weights_tool::inspect::weight_counts(&paired)?;
    println!(
        "{}: {} 8-bit layers with the pair layout, {:.1} MB (was {:.1} MB)",
        args.output.display(),
        counts.paired,
        paired.len() as f64 / 1e6,
        bytes.len() as f64 / 1e6
    );
    Ok(())
}

fn milliseconds(duration: Duration) -> f64 {
    duration.as_secs_f64() * 1e3
}

fn run(args: &RunArgs) -> anyhow::Result<()> {
    use weights_tool::run::{RunInputs, Runner, bench, draw_anchors, write_outputs};
    let bytes = read_file(&args.model)?;
    let mut runner = Runner::with_kernels(&bytes, &args.kernels)
        .with_context(|| args.model.display().to_string())?;
    let config =
        *scdp_engine::Model::from_bytes(weights_tool::writer::aligned_copy(&bytes).as_slice())
            .map_err(|error| anyhow::anyhow!("{}: {error}", args.model.display()))?
            .config();
    let inputs = RunInputs::load(&args.inputs, &config)?;
    let counts = &args.threads;
    runner.set_threads(counts[0])?;
    let (outputs, times) = runner.run(&inputs, args.seed)?;
    let action_dim = config.action_dim as usize;
    println!("kernels: {}, threads: {}", runner.kernels_name(), counts[0]);
    for &threads in &counts[1..] {
        runner.set_threads(threads)?;
        let (other, _) = runner.run(&inputs, args.seed)?;
        let same = other
            .action_pred
            .iter()
            .map(|v| v.to_bits())
            .eq(outputs.action_pred.iter().map(|v| v.to_bits()));
        anyhow::ensure!(same, "{threads} threads give other bits than {}", counts[0]);
        println!("threads: {threads}, the same bits");
    }
    println!(
        "action ({} steps x {action_dim}), encode {:.1} ms for {} frames, denoise {:.1} ms:",
        config.n_action_steps,
        milliseconds(times.encode_frames),
        config.n_obs_steps,
        milliseconds(times.denoise)
    );
    for row in outputs.action.chunks_exact(action_dim) {
        let values: Vec<String> = row.iter().map(|v| format!("{v:+.5}")).collect();
        println!("  {}", values.join(" "));
    }
    if let Some(path) = &args.output {
        write_outputs(path, &config, &outputs)?;
        println!("wrote {}", path.display());
    }
    if let Some(path) = &args.viz {
        let drawn = draw_anchors(&config, &inputs, &outputs.anchors_uv, path)?;
        let total = outputs.anchors_uv.len() / 2;
        println!(
            "wrote {} ({drawn} of {total} anchors in front of the camera)",
            path.display()
        );
    }
    if let Some(iterations) = args.bench {
        // Each count in turn, a tenth of the runs at a time, so slow drifts of the machine
        // fall on every count alike.
        let rounds = iterations.clamp(1, 10);
        let mut samples: Vec<Vec<weights_tool::run::StageSamples>> = vec![Vec::new(); counts.len()];
        for round in 0..rounds {
            let runs = iterations * (round + 1) / rounds - iterations * round / rounds;
            for (index, &threads) in counts.iter().enumerate() {
                runner.set_threads(threads)?;
                samples[index].push(bench(&mut runner, &inputs, runs.max(1))?);
            }
        }
        let tables: Vec<_> = samples
            .iter()
            .map(|sets| weights_tool::run::StageSamples::table(sets))
            .collect();
        for (index, &threads) in counts.iter().enumerate() {
            println!(
                "{iterations} runs after a warm-up, {}:",
                thread_count(threads)
            );
            // Past the first count, each median against the first's, taken in the same run.
            let against = (index > 0).then(|| format!("x {}", thread_count(counts[0])));
            let header = format!(
                "  {:<36} {:>10} {:>10} {:>12}",
                "stage",
                "median ms",
                "p99 ms",
                against.as_deref().unwrap_or("")
            );
            println!("{}", header.trim_end());
            for (stage, &(median, p99)) in &tables[index] {
                let ratio = if index > 0 {
                    let first = tables[0][stage].0;
                    format!("{:.3}", median.as_secs_f64() / first.as_secs_f64())
                } else {
                    String::new()
                };
                let row = format!(
                    "  {:<36} {:>10.2} {:>10.2} {:>12}",
                    &stage[2..],
                    milliseconds(median),
                    milliseconds(p99),
                    ratio
                );
                println!("{}", row.trim_end());
            }
            #[cfg(feature = "pool-timing")]
            if let Some(rows) = weights_tool::run::StageSamples::call_table(&samples[index]) {
                println!(
                    "  calling thread, median ms     between calls publishing  pieces  waiting  calls"
                );
                for (stage, row) in ["end to end, all frames", "end to end, newest frame only"]
                    .iter()
                    .zip(rows)
                {
                    println!(
                        "  {stage:<29} {:>13.2} {:>10.2} {:>7.2} {:>8.2} {:>6}",
                        row[0], row[1], row[2], row[3], row[4]
                    );
                }
            }
        }
    }
    Ok(())
}

fn read_with_progress(path: &Path) -> anyhow::Result<weights_tool::StateDict> {
    let bar = ProgressBar::new(0).with_style(
        ProgressStyle::with_template("reading {prefix} [{bar:30}] {pos}/{len} {wide_msg}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_prefix(path.display().to_string());
    let result = load_checkpoint_with_progress(path, &bar);
    bar.finish_and_clear();
    result
}

/// A spinner for steps with no count to show; drawn only when stderr is a terminal.
/// Runs `measure` with a bar of the files it measured, `(done, total)` as it reports them.
fn with_progress<T>(
    what: &str,
    measure: impl FnOnce(&mut dyn FnMut(usize, usize)) -> anyhow::Result<T>,
) -> anyhow::Result<T> {
    let bar = ProgressBar::new(0).with_style(
        ProgressStyle::with_template(&format!("{what} [{{bar:30}}] {{pos}}/{{len}}"))
            .expect("valid template")
            .progress_chars("=> "),
    );
    let result = measure(&mut |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    result
}

fn spinner(message: &str) -> ProgressBar {
    let spinner = ProgressBar::new_spinner().with_message(message.to_owned());
    spinner.enable_steady_tick(Duration::from_millis(100));
    spinner
}
