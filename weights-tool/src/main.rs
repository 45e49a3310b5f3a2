//! `weights-tool`: makes synthetic SCDP checkpoints and converts checkpoints into the
//! engine's weights file.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context as _;
use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};

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
}

#[derive(clap::Args)]
struct SynthArgs {
    /// Model config TOML (SPEC section 7).
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
    /// Model config TOML (SPEC section 7) the checkpoint was trained with.
    #[arg(long, value_name = "MODEL.toml")]
    config: PathBuf,
    /// Storage precision of the weights.
    #[arg(long, value_enum, default_value_t = QuantArg::F32)]
    quant: QuantArg,
    /// Rename keys starting with OLD to start with NEW before checking them (repeatable; the
    /// first matching rule applies).
    #[arg(long = "key-prefix", value_name = "OLD=NEW")]
    key_prefix: Vec<KeyPrefix>,
    /// Output weights file.
    #[arg(short, long, value_name = "MODEL.scdp")]
    output: PathBuf,
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
    let spinner = spinner(&format!("converting to {quant}"));
    let bytes = weights_tool::lower::lower_to_weights_file(&config, &state_dict, quant);
    spinner.finish_and_clear();
    let bytes = bytes.with_context(|| format!("converting {}", args.checkpoint.display()))?;
    std::fs::write(&args.output, &bytes)
        .with_context(|| format!("{}: cannot write", args.output.display()))?;
    println!(
        "wrote {} ({} bytes, {quant})",
        args.output.display(),
        bytes.len()
    );
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
fn spinner(message: &str) -> ProgressBar {
    let spinner = ProgressBar::new_spinner().with_message(message.to_owned());
    spinner.enable_steady_tick(Duration::from_millis(100));
    spinner
}
