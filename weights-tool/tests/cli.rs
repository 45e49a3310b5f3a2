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
