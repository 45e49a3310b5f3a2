//! The full tiny-model containers of tests/fixtures/containers (written by PyTorch in
//! tests/reference/generate.py): each holds synth(tiny, seed 1), in f32, f16 or bf16.

use std::path::{Path, PathBuf};

use half::{bf16, f16};
use safetensors::SafeTensors;
use scdp_engine::ModelConfig;
use weights_tool::keys::{check_keys, expected_keys};
use weights_tool::synth::{hex, synth_state_dict, weights_sha256};
use weights_tool::{Source, StateDict, TrainingEntry, load_checkpoint};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/fixtures/containers")
        .join(name)
}

/// Loads `name`, checks its keys against tiny.toml and its values against synth(tiny, 1)
/// rounded by `round`, and its checksum against the one its expected-output file records.
fn check_container(name: &str, expected_name: &str, round: impl Fn(f32) -> f32) -> StateDict {
    let state_dict = load_checkpoint(&fixture(name)).unwrap();
    check_keys(&state_dict, &expected_keys(&ModelConfig::TINY)).unwrap();
    let synth = synth_state_dict(&ModelConfig::TINY, 1);
    for (key, expected) in &synth.tensors {
        let found = &state_dict.tensors[key];
        let expected: Vec<u32> = expected.data.iter().map(|&v| round(v).to_bits()).collect();
        let found: Vec<u32> = found.data.iter().map(|v| v.to_bits()).collect();
        assert_eq!(found, expected, "{name}: {key}");
    }
    let bytes = std::fs::read(fixture(expected_name)).unwrap();
    let (_, metadata) = SafeTensors::read_metadata(&bytes).unwrap();
    let recorded = &metadata.metadata().as_ref().unwrap()["weights_sha256"];
    assert_eq!(&hex(&weights_sha256(&state_dict)), recorded, "{name}");
    state_dict
}

#[test]
fn workspace_checkpoint_reads_ema_model_exactly() {
    let state_dict = check_container("workspace.ckpt", "workspace.expected.safetensors", |v| v);
    assert_eq!(
        state_dict.source,
        Source::TrainingCheckpoint(TrainingEntry::EmaModel)
    );
}

#[test]
fn float16_state_dict_reads_within_rounding() {
    let state_dict = check_container(
        "state_dict_f16.pt",
        "state_dict_f16.expected.safetensors",
        |v| f16::from_f32(v).to_f32(),
    );
    assert_eq!(state_dict.source, Source::TorchStateDict);
}

#[test]
fn bfloat16_safetensors_reads_within_rounding() {
    let state_dict = check_container(
        "weights_bf16.safetensors",
        "weights_bf16.expected.safetensors",
        |v| bf16::from_f32(v).to_f32(),
    );
    assert_eq!(state_dict.source, Source::Safetensors);
}
