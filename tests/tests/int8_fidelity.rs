//! Fidelity of int8 weights, measured against the float64 PyTorch reference on every golden
//! case, side by side with the f32 engine (docs/QUANTIZATION.md).
//!
//! `cargo test -p scdp-tests --test int8_fidelity -- --nocapture` prints the report.
//!
//! What is asserted:
//! - the panda int8 weights file is at most 30 MB (the product's size floor);
//! - int8 `action_pred` stays within REGRESSION_MAX / REGRESSION_MEAN (normalized action
//!   units) on every golden case: the current scheme's measured worst case (max 0.054 and
//!   mean 0.0089 on panda/basic with the AVX2 f32 kernels; max 0.070, mean 0.0090 on the
//!   scalar backend: the max is that sensitive to 1e-6 differences elsewhere) with about 40%
//!   margin, so a change that makes int8 worse fails. The product's fidelity floor (max
//!   0.02, mean 0.005 on metaworld and panda) is NOT met: the report marks each case against
//!   it, and docs/QUANTIZATION.md has what was measured on the way (no storage-only mixed
//!   precision reaches it within 30 MB).

use scdp_engine::ArenaPlan;
use scdp_tests::{Fixture, golden_fixtures, run_engine, synthetic_weights_file_as};
use weights_tool::Quant;

/// The product's floor, reported per case.
const FLOOR_MAX: f64 = 0.02;
const FLOOR_MEAN: f64 = 0.005;
/// The asserted regression bounds (see the module comment).
const REGRESSION_MAX: f64 = 0.1;
const REGRESSION_MEAN: f64 = 0.0125;
const PANDA_INT8_FILE_BYTES: usize = 30_000_000;

/// Max and mean of |found - truth| x action scale (normalized action units).
fn action_errors(fixture: &Fixture, found: &[f32]) -> (f64, f64) {
    let scale = weights_tool::synth::synth_state_dict(&fixture.config, fixture.seed)
        .get("normalizer.params_dict.action.scale")
        .expect("action scale")
        .data
        .clone();
    let truth = &fixture.array("ref64.action_pred").values;
    let errors: Vec<f64> = found
        .iter()
        .zip(truth)
        .enumerate()
        .map(|(i, (&f, &t))| (f as f64 - t).abs() * scale[i % scale.len()] as f64)
        .collect();
    let max = errors.iter().copied().fold(0.0, f64::max);
    (max, errors.iter().sum::<f64>() / errors.len() as f64)
}

/// Largest pixel distance to the reference over anchors that both put inside the image
/// (points far outside sample zeros, where pixel distances say nothing).
fn anchor_error(fixture: &Fixture, anchors_per_step: &[Vec<f32>]) -> f64 {
    let (width, height) = (
        fixture.config.image_width as f64,
        fixture.config.image_height as f64,
    );
    let truth = &fixture.array("ref64.anchors_uv").values;
    let found: Vec<f32> = anchors_per_step.concat();
    let inside = |u: f64, v: f64| u > -1.0 && v > -1.0 && u < width && v < height;
    found
        .chunks_exact(2)
        .zip(truth.chunks_exact(2))
        .filter(|(f, t)| f[0].is_finite() && t[0].is_finite() && inside(t[0], t[1]))
        .map(|(f, t)| (f[0] as f64 - t[0]).hypot(f[1] as f64 - t[1]))
        .fold(0.0, f64::max)
}

#[test]
fn int8_fidelity_is_measured_and_does_not_regress() {
    let mut failures = Vec::new();
    println!(
        "{:<26} {:>11} {:>11} {:>9} {:>11} {:>11} {:>9}  floor (max {FLOOR_MAX}, mean {FLOOR_MEAN})",
        "case", "f32 max", "f32 mean", "f32 px", "int8 max", "int8 mean", "int8 px"
    );
    let mut sizes = std::collections::BTreeMap::new();
    for path in golden_fixtures() {
        let fixture = Fixture::load(&path).unwrap();
        let name = path
            .strip_prefix(scdp_tests::tests_dir().join("fixtures/golden"))
            .unwrap()
            .display()
            .to_string();
        let config_name = name.split('/').next().unwrap().to_owned();
        let mut row = Vec::new();
        for quant in [Quant::F32, Quant::Int8] {
            let weights = synthetic_weights_file_as(&fixture.config, fixture.seed, quant).unwrap();
            sizes.insert(
                (config_name.clone(), quant.name()),
                weights.as_slice().len(),
            );
            let run = run_engine(weights.as_slice(), &fixture).unwrap();
            let (max, mean) = action_errors(&fixture, &run.action_pred);
            row.push((max, mean, anchor_error(&fixture, &run.recorded.anchors_uv)));
        }
        let (max, mean, _) = row[1];
        let floor = if max <= FLOOR_MAX && mean <= FLOOR_MEAN {
            "met"
        } else {
            "not met"
        };
        println!(
            "{name:<26} {:>11.2e} {:>11.2e} {:>9.4} {:>11.2e} {:>11.2e} {:>9.4}  {floor}",
            row[0].0, row[0].1, row[0].2, row[1].0, row[1].1, row[1].2
        );
        if !(max <= REGRESSION_MAX && mean <= REGRESSION_MEAN) {
            failures.push(format!("{name}: int8 max {max:.3e} (bound {REGRESSION_MAX}), mean {mean:.3e} (bound {REGRESSION_MEAN})"));
        }
    }
    for ((config, quant), bytes) in &sizes {
        let path = scdp_tests::tests_dir().join(format!("configs/{config}.toml"));
        let model_config = weights_tool::load_config(&path).unwrap();
        println!(
            "{config:<10} {quant:<5} weights file {bytes:>11} bytes, arena {:>10} bytes",
            ArenaPlan::new(&model_config).arena_bytes
        );
    }
    let panda = sizes[&("panda".to_owned(), "int8")];
    if panda > PANDA_INT8_FILE_BYTES {
        failures.push(format!(
            "panda int8 weights file {panda} bytes > {PANDA_INT8_FILE_BYTES}"
        ));
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
