//! The `weights-tool` binary: what a user sees.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn tool(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_weights-tool"))
        .args(args)
        .output()
        .expect("weights-tool runs")
}

fn repo_file(relative: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(relative)
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

#[test]
fn synth_writes_a_checkpoint_and_reports_its_checksum() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("tiny.safetensors");
    let config = repo_file("tests/configs/tiny.toml");
    let output = tool(&[
        "synth",
        "--config",
        config.to_str().unwrap(),
        "--seed",
        "1",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", text(&output.stderr));
    assert!(
        text(&output.stdout).contains(
            "weights_sha256 2e01e33705dbee9408bf9b96acde6f2a80a111b39e42a1ad8b2ed74d72f78a04"
        ),
        "{}",
        text(&output.stdout)
    );
    assert!(out.exists());
}

#[test]
fn convert_lists_every_key_problem() {
    let dir = tempfile::tempdir().unwrap();
    let checkpoint = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/workspace.ckpt");
    let config = repo_file("tests/configs/tiny.toml");
    let out = dir.path().join("tiny.scdp");
    let output = tool(&[
        "convert",
        checkpoint.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--key-prefix",
        "model.expanded.=model.widened.",
        // Moves a [4] tensor onto a [16] key: one mis-shaped, one missing.
        "--key-prefix",
        "model.final_conv.1.bias=model.final_conv.0.block.1.bias",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(!output.status.success());
    let stdout = text(&output.stdout);
    assert!(
        stdout.contains("(training checkpoint, state_dicts.ema_model): 7 tensors"),
        "{stdout}"
    );
    let stderr = text(&output.stderr);
    for expected in [
        "workspace.ckpt does not fit",
        "256 missing, 2 extra, 1 mis-shaped, 0 unreadable",
        "missing     model.final_conv.1.bias (expected shape [4])",
        "missing     obs_encoder.backbone.bn1.weight (expected shape [8])",
        "extra       model.counts (int32 tensor)",
        "extra       model.widened.bias (shape [3])",
        "mis-shaped  model.final_conv.0.block.1.bias: expected [16], found [4]",
    ] {
        assert!(stderr.contains(expected), "{expected:?} not in\n{stderr}");
    }
    assert!(!out.exists());
}

#[test]
fn bad_config_names_the_file_and_the_keys() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("bad.toml");
    let tiny = std::fs::read_to_string(repo_file("tests/configs/tiny.toml")).unwrap();
    std::fs::write(&config, tiny.replace("horizon = 8", "horizon = 18")).unwrap();
    let output = tool(&[
        "synth",
        "--config",
        config.to_str().unwrap(),
        "--seed",
        "1",
        "-o",
        dir.path().join("x.safetensors").to_str().unwrap(),
    ]);
    assert!(!output.status.success());
    let stderr = text(&output.stderr);
    assert!(stderr.contains("bad.toml: bad model config"), "{stderr}");
    assert!(
        stderr.contains("horizon must be a positive multiple of 4"),
        "{stderr}"
    );
}

/// `action_pred` of a run output file.
fn read_f32(path: &Path, name: &str) -> Vec<f64> {
    let bytes = std::fs::read(path).unwrap();
    let tensors = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let view = tensors.tensor(name).unwrap();
    match view.dtype() {
        safetensors::Dtype::F32 => view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()) as f64)
            .collect(),
        safetensors::Dtype::F64 => view
            .data()
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
            .collect(),
        other => panic!("{name}: {other:?}"),
    }
}

/// Max |found - expected| x action scale: the error in normalized action units, the unit of
/// the engine's 2e-4 bound (docs/FIXTURES.md).
fn normalized_error(found: &[f64], expected: &[f64], scale: &[f32]) -> f64 {
    assert_eq!(found.len(), expected.len());
    found
        .iter()
        .zip(expected)
        .enumerate()
        .map(|(i, (f, e))| (f - e).abs() * scale[i % scale.len()] as f64)
        .fold(0.0, f64::max)
}

/// The run output's `action_pred` is within the engine's bound (2e-4 in normalized action
/// units) of the float64 reference in `reference`; `checkpoint` supplies the action scale.
fn assert_action_pred_matches(result: &Path, reference: &Path, checkpoint: &Path) {
    let state = weights_tool::load_checkpoint(checkpoint).unwrap();
    let scale = &state
        .get("normalizer.params_dict.action.scale")
        .unwrap()
        .data;
    let error = normalized_error(
        &read_f32(result, "action_pred"),
        &read_f32(reference, "ref64.action_pred"),
        scale,
    );
    assert!(
        error <= 2e-4,
        "{}: action_pred error {error:e} > 2e-4",
        checkpoint.display()
    );
}

fn convert_and_run(checkpoint: &Path, config: &Path, inputs: &Path, dir: &Path) -> PathBuf {
    let model = dir.join("model.scdp");
    let output = tool(&[
        "convert",
        checkpoint.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "-o",
        model.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", text(&output.stderr));
    let result = dir.join("out.safetensors");
    let picture = dir.join("anchors.png");
    let output = tool(&[
        "run",
        model.to_str().unwrap(),
        "--inputs",
        inputs.to_str().unwrap(),
        "-o",
        result.to_str().unwrap(),
        "--viz",
        picture.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", text(&output.stderr));
    assert!(std::fs::metadata(&picture).unwrap().len() > 1000);
    result
}

#[test]
fn containers_written_by_pytorch_convert_and_run_to_the_reference_output() {
    let config = repo_file("tests/configs/tiny.toml");
    let inputs = repo_file("tests/fixtures/golden/tiny/basic.safetensors");
    for name in [
        "workspace.ckpt",
        "state_dict_f16.pt",
        "weights_bf16.safetensors",
    ] {
        let dir = tempfile::tempdir().unwrap();
        let container = repo_file(&format!("tests/fixtures/containers/{name}"));
        let stem = name.split('.').next().unwrap();
        let expected = repo_file(&format!(
            "tests/fixtures/containers/{stem}.expected.safetensors"
        ));
        let result = convert_and_run(&container, &config, &inputs, dir.path());
        assert_action_pred_matches(&result, &expected, &container);
    }
}

/// `weights-tool synth` of `config` at seed 1 (the golden fixtures' weights) into `dir`.
fn synth_seed_1(config: &Path, dir: &Path) -> PathBuf {
    let checkpoint = dir.join("synthetic.safetensors");
    let output = tool(&[
        "synth",
        "--config",
        config.to_str().unwrap(),
        "--seed",
        "1",
        "-o",
        checkpoint.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", text(&output.stderr));
    checkpoint
}

#[test]
fn run_reproduces_a_golden_fixture() {
    let dir = tempfile::tempdir().unwrap();
    let config = repo_file("tests/configs/metaworld.toml");
    let checkpoint = synth_seed_1(&config, dir.path());
    let inputs = repo_file("tests/fixtures/golden/metaworld/edge.safetensors");
    let result = convert_and_run(&checkpoint, &config, &inputs, dir.path());
    assert_action_pred_matches(&result, &inputs, &checkpoint);
    let anchors = read_f32(&result, "anchors_uv");
    let reference = read_f32(&inputs, "ref64.anchors_uv");
    assert_eq!(
        anchors.iter().map(|v| v.is_nan()).collect::<Vec<_>>(),
        reference.iter().map(|v| v.is_nan()).collect::<Vec<_>>(),
        "the same anchors are behind the camera"
    );
}

/// A run file with a committed prefix and planned rows (docs/SPEC.md section 5.1) is run
/// with them: the output is the prefix fixture's reference, not the plain chunk's.
#[test]
fn run_holds_a_run_files_prefix() {
    let dir = tempfile::tempdir().unwrap();
    let config = repo_file("tests/configs/tiny.toml");
    let checkpoint = synth_seed_1(&config, dir.path());
    for case in ["prefix-noised", "prefix-planned"] {
        let inputs = repo_file(&format!("tests/fixtures/golden/tiny/{case}.safetensors"));
        let result = convert_and_run(&checkpoint, &config, &inputs, dir.path());
        assert_action_pred_matches(&result, &inputs, &checkpoint);
    }
}

/// `run --threads 1,3 --bench N` checks that 3 workers give 1's bits and prints, for 3, each
/// stage's median against 1 thread's.
#[test]
fn run_benchmarks_each_thread_count_against_the_first() {
    let dir = tempfile::tempdir().unwrap();
    let config = repo_file("tests/configs/tiny.toml");
    let checkpoint = synth_seed_1(&config, dir.path());
    let inputs = repo_file("tests/fixtures/golden/tiny/basic.safetensors");
    let result = convert_and_run(&checkpoint, &config, &inputs, dir.path());
    let model = result.with_file_name("model.scdp");
    let output = tool(&[
        "run",
        model.to_str().unwrap(),
        "--inputs",
        inputs.to_str().unwrap(),
        "--threads",
        "1,3",
        "--bench",
        "3",
    ]);
    assert!(output.status.success(), "{}", text(&output.stderr));
    let stdout = text(&output.stdout);
    assert!(stdout.contains("threads: 3, the same bits"), "{stdout}");
    let (first, second) = stdout
        .split_once("3 runs after a warm-up, 3 threads:")
        .expect("a table for 3 threads");
    let rows_of = |table: &str| -> Vec<Vec<String>> {
        table
            .lines()
            .skip_while(|line| !line.trim_start().starts_with("stage"))
            .skip(1)
            .take(4)
            .map(|line| line.split_whitespace().map(String::from).collect())
            .collect()
    };
    let (one, three) = (rows_of(first), rows_of(second));
    assert!(
        second.lines().nth(1).unwrap().ends_with("x 1 thread"),
        "{stdout}"
    );
    assert_eq!((one.len(), three.len()), (4, 4), "{stdout}");
    for (one, three) in one.iter().zip(&three) {
        let number =
            |row: &[String], from_end: usize| -> f64 { row[row.len() - from_end].parse().unwrap() };
        // 1 thread's rows end with median and p99; 3 threads' with those and the ratio.
        let (median_three, median_one) = (number(three, 3), number(one, 2));
        let ratio = number(three, 1);
        assert!(ratio > 0.0 && ratio.is_finite(), "{stdout}");
        // The ratio is taken before the medians are rounded to 0.01 ms (each off by at most
        // 0.005, a relative 0.005 / median), and printed to 0.001.
        let expected = median_three / median_one;
        let bound = expected * (0.005 / median_three + 0.005 / median_one) * 1.1 + 5e-4;
        assert!((ratio - expected).abs() <= bound, "{stdout}");
    }
}

/// Runs the tool, expecting failure with exactly one line on stderr that contains `needle`.
fn assert_one_line_error(args: &[&str], needle: &str) {
    let output = tool(args);
    assert!(!output.status.success(), "{args:?} succeeded");
    let stderr = text(&output.stderr);
    let lines: Vec<&str> = stderr.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(
        lines.len(),
        1,
        "{args:?}: expected one error line, got:\n{stderr}"
    );
    assert!(
        lines[0].contains(needle),
        "{args:?}: {needle:?} not in {:?}",
        lines[0]
    );
}

#[test]
fn bad_inputs_give_one_clear_error_line() {
    let dir = tempfile::tempdir().unwrap();
    let tiny = repo_file("tests/configs/tiny.toml");
    let tiny = tiny.to_str().unwrap();
    let path = |name: &str| dir.path().join(name).to_str().unwrap().to_owned();

    // A training checkpoint cut in half.
    let ckpt = std::fs::read(repo_file("tests/fixtures/containers/workspace.ckpt")).unwrap();
    std::fs::write(path("cut.ckpt"), &ckpt[..ckpt.len() / 2]).unwrap();
    assert_one_line_error(
        &[
            "convert",
            &path("cut.ckpt"),
            "--config",
            tiny,
            "-o",
            &path("x.scdp"),
        ],
        "cut.ckpt",
    );

    // A full checkpoint in which one needed tensor has a dtype the tool does not read: the
    // key check reports it (a summary line, then one line per problem key).
    let config = weights_tool::parse_config(&std::fs::read_to_string(tiny).unwrap()).unwrap();
    let state = weights_tool::synth_state_dict(&config, 1);
    let encoded: Vec<(String, Vec<usize>, Vec<u8>, safetensors::Dtype)> = state
        .tensors
        .iter()
        .map(|(key, tensor)| {
            if key == "model.final_conv.1.bias" {
                (
                    key.clone(),
                    tensor.shape.clone(),
                    vec![0u8; tensor.numel() * 2],
                    safetensors::Dtype::I16,
                )
            } else {
                let bytes = tensor.data.iter().flat_map(|v| v.to_le_bytes()).collect();
                (
                    key.clone(),
                    tensor.shape.clone(),
                    bytes,
                    safetensors::Dtype::F32,
                )
            }
        })
        .collect();
    let views = encoded.iter().map(|(key, shape, bytes, dtype)| {
        (
            key.as_str(),
            safetensors::tensor::TensorView::new(*dtype, shape.clone(), bytes).unwrap(),
        )
    });
    safetensors::serialize_to_file(views, None, Path::new(&path("i16.safetensors"))).unwrap();
    let output = tool(&[
        "convert",
        &path("i16.safetensors"),
        "--config",
        tiny,
        "-o",
        &path("x.scdp"),
    ]);
    assert!(!output.status.success());
    let stderr = text(&output.stderr);
    assert!(
        stderr.contains("0 missing, 0 extra, 0 mis-shaped, 1 unreadable"),
        "{stderr}"
    );
    assert!(
        stderr
            .lines()
            .any(|l| l.contains("model.final_conv.1.bias") && l.contains("I16")),
        "{stderr}"
    );

    // A weights file with one flipped byte.
    let checkpoint = path("tiny.safetensors");
    assert!(
        tool(&["synth", "--config", tiny, "--seed", "1", "-o", &checkpoint])
            .status
            .success()
    );
    assert!(
        tool(&[
            "convert",
            &checkpoint,
            "--config",
            tiny,
            "-o",
            &path("tiny.scdp")
        ])
        .status
        .success()
    );
    let mut model = std::fs::read(path("tiny.scdp")).unwrap();
    let last = model.len() - 100;
    model[last] ^= 0x40;
    std::fs::write(path("flipped.scdp"), &model).unwrap();
    assert_one_line_error(&["inspect", &path("flipped.scdp")], "checksum");

    // Run inputs whose images do not fit the model.
    let inputs = repo_file("tests/fixtures/golden/metaworld/basic.safetensors");
    assert_one_line_error(
        &[
            "run",
            &path("tiny.scdp"),
            "--inputs",
            inputs.to_str().unwrap(),
        ],
        "`images`",
    );

    // A config the engine cannot run.
    let text = std::fs::read_to_string(tiny)
        .unwrap()
        .replace("horizon = 8", "horizon = 10");
    std::fs::write(path("bad.toml"), text).unwrap();
    assert_one_line_error(
        &[
            "convert",
            &checkpoint,
            "--config",
            &path("bad.toml"),
            "-o",
            &path("x.scdp"),
        ],
        "horizon must be a positive multiple of 4",
    );
}

/// `convert --quant int8` calibrated on recorded and synthetic scenes writes a weights file
/// the engine loads, says how it rounded and which activation codes each residual-block
/// layer got and which trunk layers were refined, and differs from round-to-nearest, which
/// is written only when asked for by name; without scenes `--quant int8` refuses and says
/// what to pass; calibration options that cannot apply are refused.
#[test]
fn convert_calibrates_int8_rounding_on_scenes() {
    let dir = tempfile::tempdir().unwrap();
    let path = |name: &str| dir.path().join(name).to_str().unwrap().to_owned();
    let tiny = repo_file("tests/configs/tiny.toml");
    let tiny = tiny.to_str().unwrap();
    let case = repo_file("tests/fixtures/golden/tiny/basic.safetensors");
    let case = case.to_str().unwrap();
    let synth = tool(&[
        "synth",
        "--config",
        tiny,
        "--seed",
        "1",
        "-o",
        &path("w.safetensors"),
    ]);
    assert!(synth.status.success(), "{}", text(&synth.stderr));
    let checkpoint = path("w.safetensors");
    let convert = |extra: &[&str], out: &str| {
        let mut args = vec!["convert", &checkpoint, "--config", tiny, "-o", out];
        args.extend_from_slice(extra);
        tool(&args)
    };
    let calibrated = path("gptq.scdp");
    let int8 = ["--quant", "int8"];
    let scenes = [
        "--calibrate",
        case,
        "--synthetic-scenes",
        "2",
        "--camera",
        case,
    ];
    let output = convert(&[&int8[..], &scenes[..]].concat(), &calibrated);
    assert!(output.status.success(), "{}", text(&output.stderr));
    // Every core by default; one thread, or three (scenes shared out unevenly), choose the
    // same and write the same bytes.
    let bytes = std::fs::read(&calibrated).unwrap();
    for threads in ["1", "3"] {
        let other = path(&format!("gptq-{threads}.scdp"));
        let threads_arg = ["--threads", threads];
        let run = convert(&[&int8[..], &scenes[..], &threads_arg[..]].concat(), &other);
        assert!(run.status.success(), "{}", text(&run.stderr));
        assert!(
            std::fs::read(&other).unwrap() == bytes,
            "--threads {threads} wrote other bytes"
        );
    }
    let stdout = text(&output.stdout);
    let refined_chosen = refinements_chosen(&stdout);
    assert!(
        stdout.contains("GPTQ, calibrated on 3 scenes (1 recorded, 2 synthetic)"),
        "{stdout}"
    );
    assert!(
        stdout.contains("activations    measured on 3 calibration scenes"),
        "{stdout}"
    );
    // Each stage that ran, in order, with its time.
    let took = stdout
        .lines()
        .find(|line| line.starts_with("  took"))
        .unwrap_or_else(|| panic!("{stdout}"));
    let stages: Vec<&str> = ["calibration", "rounding", "refinement", "activation widths"]
        .into_iter()
        .filter(|stage| took.contains(&format!("{stage} ")))
        .collect();
    assert_eq!(stages.len(), 4, "{took}");
    assert!(took.find("calibration").unwrap() < took.find("activation widths").unwrap());
    // The residual-block layers, each with its measured effect and choice: the activation
    // codes of the trunk's 19 and the U-Net's 24 (12 blocks of two convolutions), and the
    // refinement of the trunk's.
    let decided = |kinds: &[&str], part: &str| {
        stdout
            .lines()
            .filter(|line| kinds.iter().any(|kind| line.starts_with(kind)))
            .filter(|line| line.contains("alone: max") && line.contains(part))
            .count()
    };
    for (part, layers) in [("backbone.layer", 19), ("unet.", 24)] {
        assert_eq!(
            decided(&["  8-bit", "  15-bit"], part),
            layers,
            "{part}: {stdout}"
        );
    }
    let refinements = decided(&["  refined", "  one plane"], "backbone.layer");
    assert_eq!(refinements, 19, "{stdout}");

    // The chosen mix honours the budget it printed: its mean action error at most the
    // allowed fraction above the 15-bit file's, for the default budget and for none at all;
    // and `inspect` lists as many 8-bit layers as `convert` chose.
    for (budget, stdout) in [(0.05, stdout.clone()), (0.0, String::new())] {
        let stdout = if stdout.is_empty() {
            let strict = path("strict.scdp");
            let args = [&int8[..], &scenes[..], &["--action-budget", "0"]].concat();
            let output = convert(&args, &strict);
            assert!(output.status.success(), "{}", text(&output.stderr));
            text(&output.stdout)
        } else {
            stdout
        };
        let mean_after = |prefix: &str, containing: &str| -> f64 {
            let line = stdout
                .lines()
                .find(|line| line.trim_start().starts_with(prefix) && line.contains(containing));
            let line = line.unwrap_or_else(|| panic!("no `{prefix}` line: {stdout}"));
            line.rsplit("mean ").next().unwrap().trim().parse().unwrap()
        };
        // The printed means have three digits: 1% of slack for their rounding.
        let wide = mean_after("15-bit everywhere:", "");
        let chosen = mean_after("chosen,", "8-bit");
        assert!(chosen <= wide * (1.0 + budget) * (1.0 + 1e-2), "{stdout}");
        let all_refined = mean_after("every trunk layer refined:", "");
        let chosen = mean_after("chosen,", "refined");
        assert!(
            chosen <= all_refined * (1.0 + budget) * (1.0 + 1e-2),
            "{stdout}"
        );
    }

    let refused = convert(&int8, &path("refused.scdp"));
    assert!(!refused.status.success());
    let stderr = text(&refused.stderr);
    for hint in ["--calibrate", "--synthetic-scenes", "--rounding nearest"] {
        assert!(stderr.contains(hint), "{hint}: {stderr}");
    }
    assert!(!dir.path().join("refused.scdp").exists());

    let nearest = path("rtn.scdp");
    let output = convert(&[&int8[..], &["--rounding", "nearest"]].concat(), &nearest);
    assert!(output.status.success(), "{}", text(&output.stderr));
    let stdout = text(&output.stdout);
    assert!(stdout.contains("rounding       to nearest"), "{stdout}");
    assert!(
        stdout.contains("15-bit everywhere (no calibration scenes to measure on)"),
        "{stdout}"
    );
    let wide = path("wide.scdp");
    let one_plane = ["--activations", "wide", "--refine", "none"];
    let wide_args = [&int8[..], &scenes[..], &one_plane[..]].concat();
    assert!(convert(&wide_args, &wide).status.success());
    let calibrated = std::fs::read(&calibrated).unwrap();
    let nearest = std::fs::read(&nearest).unwrap();
    let wide = std::fs::read(&wide).unwrap();
    assert_eq!(wide.len(), nearest.len());
    assert_ne!(wide, nearest, "GPTQ changed no weight");
    let aligned = weights_tool::writer::aligned_copy(&calibrated);
    scdp_engine::Model::from_bytes(aligned.as_slice()).expect("calibrated file loads");

    // `inspect` lists the layers on 8-bit codes: none in the wide file, all 43 with
    // `--activations narrow`.
    let narrow = path("narrow.scdp");
    let narrow_args = [&int8[..], &scenes[..], &["--activations", "narrow"]].concat();
    let output = convert(&narrow_args, &narrow);
    assert!(output.status.success(), "{}", text(&output.stderr));
    for (file, eight_bit) in [(path("wide.scdp"), 0), (narrow.clone(), 43)] {
        assert_inspect_lists(
            &file,
            &format!("{eight_bit} on 8-bit codes"),
            "  8-bit",
            eight_bit,
        );
    }

    // The pair layout: `convert --weight-pairs` writes what `add-pairs` adds to the file
    // without it, one `.pairs` tensor for each 8-bit layer (all 43 are convolutions).
    let paired = path("paired.scdp");
    let paired_args = [&narrow_args[..], &["--weight-pairs"]].concat();
    let output = convert(&paired_args, &paired);
    assert!(output.status.success(), "{}", text(&output.stderr));
    let added = path("added.scdp");
    let output = tool(&["add-pairs", &narrow, "-o", &added]);
    assert!(output.status.success(), "{}", text(&output.stderr));
    assert!(text(&output.stdout).contains("43 8-bit layers with the pair layout"));
    let paired_bytes = std::fs::read(&paired).unwrap();
    assert!(
        std::fs::read(&added).unwrap() == paired_bytes,
        "add-pairs wrote other bytes"
    );
    assert!(paired_bytes.len() > std::fs::read(&narrow).unwrap().len());
    assert_inspect_lists(
        &paired,
        "read by `i8mm`): 43 of the 8-bit layers",
        "  8-bit",
        43,
    );
    let report = text(&tool(&["inspect", &paired]).stdout);
    assert_eq!(
        report
            .lines()
            .filter(|line| line.contains(".pairs "))
            .count(),
        43
    );
    let f32_paired = convert(&["--weight-pairs"], &path("z.scdp"));
    assert!(!f32_paired.status.success());
    assert!(text(&f32_paired.stderr).contains("only applies to --quant int8"));

    // `inspect` lists the refined layers: as many as `convert` chose, none with `--refine
    // none`, the trunk's 19 with `--refine trunk`.
    let trunk = path("trunk.scdp");
    let trunk_args = [&int8[..], &scenes[..], &["--refine", "trunk"]].concat();
    let output = convert(&trunk_args, &trunk);
    assert!(output.status.success(), "{}", text(&output.stderr));
    for (file, refined) in [
        (path("wide.scdp"), 0),
        (trunk, 19),
        (path("gptq.scdp"), refined_chosen),
    ] {
        assert_inspect_lists(
            &file,
            &format!("{refined} layers refined"),
            "  refined",
            refined,
        );
    }

    let no_camera = convert(
        &["--quant", "int8", "--synthetic-scenes", "2"],
        &path("x.scdp"),
    );
    assert!(!no_camera.status.success());
    assert!(
        text(&no_camera.stderr).contains("--camera"),
        "{}",
        text(&no_camera.stderr)
    );
    let f32_calibrated = convert(&["--calibrate", case], &path("y.scdp"));
    assert!(!f32_calibrated.status.success());
    assert!(text(&f32_calibrated.stderr).contains("only apply to --quant int8"));
}

/// The number `convert` printed in its "chosen, N of 19 trunk layers refined" line.
fn refinements_chosen(stdout: &str) -> usize {
    let line = stdout
        .lines()
        .find(|line| line.contains("trunk layers refined"))
        .unwrap_or_else(|| panic!("no refinement line: {stdout}"));
    let after = line.split("chosen, ").nth(1).unwrap();
    after.split(' ').next().unwrap().parse().unwrap()
}

/// `inspect FILE` prints `summary` and lists `count` layers on lines starting with `prefix`.
fn assert_inspect_lists(file: &str, summary: &str, prefix: &str, count: usize) {
    let report = text(&tool(&["inspect", file]).stdout);
    assert!(report.contains(summary), "{file}: {report}");
    let listed = report
        .lines()
        .filter(|line| line.starts_with(prefix))
        .count();
    assert_eq!(listed, count, "{file}: {report}");
}
