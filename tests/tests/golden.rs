//! The real path, pinned to the PyTorch reference: seeded weights regenerated in Rust (and
//! checked against the checksum the Python generator recorded), converted by the weights
//! tool, run by the engine on each golden fixture's inputs, compared stage by stage with
//! the float64 reference.
//!
//! Tolerances. The hard bound is the product's: `action_pred` within 2e-4 of the float64
//! truth in normalized action units (|error| x action scale). Each intermediate stage is
//! held to `STAGE_FACTOR` times the deviation of float32 PyTorch from the same truth
//! (recorded in the fixture), plus a floor of `FLOOR` relative to the stage's magnitude for
//! stages where float32 PyTorch happens to be exact: an f32 engine with a different
//! summation order is expected to land within a small multiple of another f32
//! implementation. The first stage outside its bound names where a bug is.

use scdp_tests::{
    EngineRun, Fixture, available_backends, golden_fixtures, run_engine_with,
    synthetic_weights_file,
};

const ACTION_TOLERANCE: f64 = 2e-4;
const STAGE_FACTOR: f64 = 10.0;
const FLOOR: f64 = 1e-5;

struct Comparison {
    stage: String,
    error: f64,
    tolerance: f64,
}

/// False for NaN errors too.
fn within(error: f64, bound: f64) -> bool {
    error <= bound
}

fn max_abs(values: &[f64]) -> f64 {
    values
        .iter()
        .filter(|v| v.is_finite())
        .fold(0.0, |m, v| m.max(v.abs()))
}

/// Max |a - b| where both are finite; a NaN in one but not the other is an infinite error.
fn max_error(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .fold(0.0, |m, (&x, &y)| match (x.is_nan(), y.is_nan()) {
            (true, true) => m,
            (false, false) => m.max((x - y).abs()),
            _ => f64::INFINITY,
        })
}

fn compare(stage: String, engine: &[f64], truth: &[f64], float32: &[f64]) -> Comparison {
    let deviation = max_error(float32, truth);
    Comparison {
        error: max_error(engine, truth),
        tolerance: STAGE_FACTOR * deviation + FLOOR * max_abs(truth).max(1e-3),
        stage,
    }
}

fn widen(values: &[f32]) -> Vec<f64> {
    values.iter().map(|&v| v as f64).collect()
}

/// Per channel: mean and mean of squares of a `[H, W, d]` map (the fixture's digest).
fn digest(map: &[f32], feature_dim: usize) -> Vec<f64> {
    let positions = (map.len() / feature_dim) as f64;
    let mut means = vec![0.0; feature_dim];
    let mut squares = vec![0.0; feature_dim];
    for cell in map.chunks_exact(feature_dim) {
        for (c, &v) in cell.iter().enumerate() {
            means[c] += v as f64 / positions;
            squares[c] += (v as f64) * (v as f64) / positions;
        }
    }
    means.extend(squares);
    means
}

fn stages(fixture: &Fixture, run: &EngineRun) -> Vec<Comparison> {
    let config = fixture.config;
    let frames = config.n_obs_steps as usize;
    let feature_dim = config.feature_dim as usize;
    let mut comparisons = Vec::new();
    let slice = |name: &str, start: usize, len: usize| {
        fixture.array(name).values[start..start + len].to_vec()
    };

    // Feature maps: digest [To, 5, 2, d].
    for frame in 0..frames {
        for level in 0..5 {
            let at = (frame * 5 + level) * 2 * feature_dim;
            comparisons.push(compare(
                format!("frame {frame} F{}", level + 1),
                &digest(&run.feature_maps[frame][level], feature_dim),
                &slice("ref64.feature_digest", at, 2 * feature_dim),
                &slice("ref32.feature_digest", at, 2 * feature_dim),
            ));
        }
    }
    let anchors = config.anchor_count() * 2;
    let context = config.context_dim();
    let state_dim = config.state_dim as usize;
    let sequence = (config.horizon * config.action_dim) as usize;
    for step in 0..config.num_inference_steps as usize {
        comparisons.push(compare(
            format!("step {step} anchors"),
            &widen(&run.recorded.anchors_uv[step]),
            &slice("ref64.anchors_uv", step * anchors, anchors),
            &slice("ref32.anchors_uv", step * anchors, anchors),
        ));
        for frame in 0..frames {
            let g = &run.recorded.global_cond[step][frame * (context + state_dim)..];
            comparisons.push(compare(
                format!("step {step} frame {frame} context"),
                &widen(&g[..context]),
                &slice("ref64.context", (step * frames + frame) * context, context),
                &slice("ref32.context", (step * frames + frame) * context, context),
            ));
            if step == 0 {
                comparisons.push(compare(
                    format!("frame {frame} normalized state"),
                    &widen(&g[context..context + state_dim]),
                    &slice("ref64.nstate", frame * state_dim, state_dim),
                    &slice("ref32.nstate", frame * state_dim, state_dim),
                ));
            }
        }
        comparisons.push(compare(
            format!("step {step} eps"),
            &widen(&run.recorded.eps[step]),
            &slice("ref64.eps", step * sequence, sequence),
            &slice("ref32.eps", step * sequence, sequence),
        ));
        comparisons.push(compare(
            format!("step {step} sample"),
            &widen(&run.recorded.sample[step]),
            &slice("ref64.sample", step * sequence, sequence),
            &slice("ref32.sample", step * sequence, sequence),
        ));
    }
    comparisons
}

/// |engine - truth| x action scale: the error in normalized action units.
fn normalized_action_error(fixture: &Fixture, engine: &[f32], truth: &[f64]) -> f64 {
    let scale = weights_tool::synth::synth_state_dict(&fixture.config, fixture.seed)
        .get("normalizer.params_dict.action.scale")
        .expect("synthetic weights have an action scale")
        .data
        .clone();
    engine
        .iter()
        .zip(truth)
        .enumerate()
        .map(|(i, (&e, &t))| (e as f64 - t).abs() * scale[i % scale.len()] as f64)
        .fold(0.0, f64::max)
}

#[test]
fn every_golden_fixture_matches_the_float64_reference() {
    let fixtures = golden_fixtures();
    assert!(
        fixtures.len() >= 6,
        "expected at least 6 golden fixtures, found {}",
        fixtures.len()
    );
    let mut failures = Vec::new();
    for path in fixtures {
        let fixture = Fixture::load(&path).unwrap();
        let name = path
            .strip_prefix(scdp_tests::tests_dir())
            .unwrap()
            .display()
            .to_string();
        let weights = synthetic_weights_file(&fixture.config, fixture.seed).unwrap();
        for backend in available_backends() {
            let name = format!("{name} [{backend:?}]");
            let run = run_engine_with(weights.as_slice(), &fixture, backend).unwrap();
            let comparisons = stages(&fixture, &run);
            let action_error = normalized_action_error(
                &fixture,
                &run.action_pred,
                &fixture.array("ref64.action_pred").values,
            );
            let float32_error = normalized_action_error(
                &fixture,
                &fixture.f32s("ref32.action_pred"),
                &fixture.array("ref64.action_pred").values,
            );
            let worst = comparisons
                .iter()
                .map(|c| c.error / c.tolerance)
                .fold(0.0, f64::max);
            println!(
                "{name}: action_pred error {action_error:.2e} (float32 PyTorch {float32_error:.2e}); worst stage at {worst:.2} of its bound"
            );
            if let Some(first) = comparisons.iter().find(|c| !within(c.error, c.tolerance)) {
                failures.push(format!(
                    "{name}: first diverging stage `{}`: error {:.3e} > tolerance {:.3e}",
                    first.stage, first.error, first.tolerance
                ));
            }
            if !within(action_error, ACTION_TOLERANCE) {
                failures.push(format!(
                    "{name}: action_pred error {action_error:.3e} > {ACTION_TOLERANCE:e}"
                ));
            }
            let action_rows = &fixture.array("ref64.action").values;
            let action_rows_error = max_error(&widen(&run.action), action_rows);
            if !within(action_rows_error, max_abs(action_rows) * 1e-2 + 1e-6) {
                failures.push(format!("{name}: executed action slice differs from the reference's ({action_rows_error:.3e})"));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn rust_generator_reproduces_the_python_weights() {
    let fixtures = golden_fixtures();
    assert!(!fixtures.is_empty());
    let mut checked = std::collections::BTreeSet::new();
    for path in fixtures {
        let fixture = Fixture::load(&path).unwrap();
        if !checked.insert((format!("{:?}", fixture.config), fixture.seed)) {
            continue;
        }
        let state = weights_tool::synth::synth_state_dict(&fixture.config, fixture.seed);
        let sha = weights_tool::synth::hex(&weights_tool::synth::weights_sha256(&state));
        assert_eq!(
            sha,
            fixture.weights_sha256,
            "{}: Rust generator differs from Python's",
            path.display()
        );
    }
}
