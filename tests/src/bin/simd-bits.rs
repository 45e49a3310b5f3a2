//! Prints one line per case and kernel backend: the case, the backend, and a digest of the
//! bits of every output (`action_pred`, the anchors). Every SIMD backend, on x86-64 and
//! aarch64, must print the same digest for a case (one weights file, one answer): CI runs
//! this natively and under emulation of each ARM level and compares the lines
//! (`.ci/aarch64`). The scalar reference is left out: its f32 parts sum in another order.
//!
//! Cases: every golden fixture with the round-to-nearest int8 weights of its checkpoint and
//! with its f32 weights, and every recorded observation of the trained Meta-World policies
//! with their int8 file, as shipped and with the pair layout added (`add-pairs`: the `i8mm`
//! backend reads it, the others the quads; one case, so one digest either way).
//!
//! `cargo run --release -p scdp-tests --bin simd-bits [-- [--quick] [--int8 | --f32]
//! [BACKEND...]]`: every backend this CPU runs, or only the BACKENDs named; `--quick` (CI
//! under emulation) takes the golden case `basic` of each config and the first observation
//! of each trained policy; `--int8` / `--f32` only the cases with those weights (the ARM
//! backends share one f32 code path, so CI runs f32 on one of them and int8 on all).

use anyhow::{Context, Result};
use scdp_engine::{Backend, Model};
use scdp_tests::{Fixture, golden_fixtures, run_engine_with, synthetic_weights_file_as, tests_dir};
use weights_tool::Quant;
use weights_tool::run::{RunInputs, Runner};

/// FNV-1a over the values' bits: any changed bit changes it (with overwhelming odds).
fn digest(values: &[f32]) -> u64 {
    values
        .iter()
        .flat_map(|value| value.to_bits().to_le_bytes())
        .fold(0xcbf2_9ce4_8422_2325, |hash, byte| {
            (hash ^ u64::from(byte)).wrapping_mul(0x0100_0000_01b3)
        })
}

fn main() -> Result<()> {
    let arguments: Vec<String> = std::env::args().skip(1).collect();
    let flag = |name: &str| arguments.iter().any(|argument| argument == name);
    let quick = flag("--quick");
    let (int8, f32) = match (flag("--int8"), flag("--f32")) {
        (false, false) => (true, true),
        chosen => chosen,
    };
    let named: Vec<&String> = arguments
        .iter()
        .filter(|argument| !argument.starts_with("--"))
        .collect();
    for name in &named {
        anyhow::ensure!(Backend::from_name(name).is_some(), "unknown backend {name}");
    }
    let backends: Vec<Backend> = Backend::ALL
        .into_iter()
        .filter(|&b| !matches!(b, Backend::Auto | Backend::Scalar))
        .filter(|&b| scdp_engine::kernels::select(b).is_some())
        .filter(|b| named.is_empty() || named.iter().any(|name| name.as_str() == b.name()))
        .collect();
    anyhow::ensure!(
        !backends.is_empty() && (named.is_empty() || backends.len() == named.len()),
        "a named backend is not a SIMD backend this CPU runs"
    );
    let root = tests_dir();
    let quick_cases = ["basic.safetensors"];
    for path in golden_fixtures() {
        let name = path
            .file_name()
            .and_then(|name| name.to_str())
            .unwrap_or_default();
        if quick && !quick_cases.contains(&name) {
            continue;
        }
        let fixture = Fixture::load(&path)?;
        let case = path
            .strip_prefix(root.join("fixtures/golden"))?
            .display()
            .to_string();
        let quants = [(Quant::Int8, "int8", int8), (Quant::F32, "f32", f32)];
        for (quant, label, _) in quants.into_iter().filter(|(_, _, chosen)| *chosen) {
            let file = synthetic_weights_file_as(&fixture.config, fixture.seed, quant)?;
            for &backend in &backends {
                let run = run_engine_with(file.as_slice(), &fixture, backend)?;
                let anchors: Vec<f32> = run.recorded.anchors_uv.concat();
                let bits = digest(&run.action_pred) ^ digest(&anchors).rotate_left(1);
                println!("{case}:{label} {} {bits:016x}", backend.name());
            }
        }
    }
    if !int8 {
        return Ok(());
    }
    let mut tasks: Vec<_> = std::fs::read_dir(root.join("fixtures/trained"))?
        .flatten()
        .map(|entry| entry.path())
        .collect();
    tasks.sort();
    for task in tasks {
        let weights =
            std::fs::read(task.join("int8.scdp")).with_context(|| format!("{}", task.display()))?;
        let config = *Model::from_bytes(weights_tool::writer::aligned_copy(&weights).as_slice())
            .map_err(|error| anyhow::anyhow!("{error}"))?
            .config();
        let mut observations: Vec<_> = std::fs::read_dir(task.join("observations"))?
            .flatten()
            .map(|entry| entry.path())
            .collect();
        observations.sort();
        if quick {
            observations.truncate(1);
        }
        let paired = weights_tool::writer::add_weight_pairs(&weights)?;
        for (&backend, weights) in backends.iter().flat_map(|b| [(b, &weights), (b, &paired)]) {
            let mut runner = Runner::with_kernels(weights, backend.name())?;
            for observation in &observations {
                let inputs = RunInputs::load(observation, &config)?;
                let (outputs, _) = runner.run(&inputs, 0)?;
                let bits =
                    digest(&outputs.action_pred) ^ digest(&outputs.anchors_uv).rotate_left(1);
                let case = observation.strip_prefix(&root)?.display().to_string();
                println!("{case} {} {bits:016x}", backend.name());
            }
        }
    }
    Ok(())
}
