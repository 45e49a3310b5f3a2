//! Reading the containers of tests/data (made by make_containers.py with PyTorch) and the
//! errors for damaged or foreign files.

use std::path::{Path, PathBuf};

use half::{bf16, f16};
use scdp_engine::ModelConfig;
use weights_tool::keys::check_keys;
use weights_tool::synth::synth_tensor;
use weights_tool::{Source, StateDict, TrainingEntry, load_checkpoint};

/// The keys make_containers.py stores, with their shapes.
const KEYS: [(&str, &[usize]); 6] = [
    ("obs_encoder.backbone.conv1.weight", &[8, 3, 7, 7]),
    ("model.diffusion_step_encoder.1.weight", &[64, 16]),
    ("model.final_conv.1.bias", &[4]),
    ("model.final_conv.1.weight", &[4, 16, 1]),
    ("normalizer.params_dict.action.scale", &[4]),
    ("obs_encoder.backbone.bn1.running_var", &[8]),
];

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// Asserts each of KEYS equals synth(tiny, seed) after `round` (the storage dtype's rounding).
fn assert_synth_values(state_dict: &StateDict, seed: u64, round: impl Fn(f32) -> f32) {
    for (key, shape) in KEYS {
        let expected = synth_tensor(&ModelConfig::TINY, seed, key, shape);
        let tensor = state_dict
            .get(key)
            .unwrap_or_else(|| panic!("{key} missing"));
        assert_eq!(tensor.shape, shape, "{key}");
        let expected: Vec<u32> = expected.data.iter().map(|&v| round(v).to_bits()).collect();
        let found: Vec<u32> = tensor.data.iter().map(|v| v.to_bits()).collect();
        assert_eq!(found, expected, "{key}");
    }
}

#[test]
fn training_checkpoint_prefers_ema_model_and_honours_strides() {
    let state_dict = load_checkpoint(&data("workspace.ckpt")).unwrap();
    assert_eq!(
        state_dict.source,
        Source::TrainingCheckpoint(TrainingEntry::EmaModel)
    );
    // ema_model holds seed 1, model seed 2.
    assert_synth_values(&state_dict, 1, |v| v);
    assert_eq!(
        state_dict.get("model.expanded.bias").unwrap().data,
        [1.5; 3]
    );
    assert_eq!(
        state_dict.skipped["obs_encoder.backbone.bn1.num_batches_tracked"],
        "int64 tensor"
    );
    assert_eq!(state_dict.skipped["model.counts"], "int32 tensor");
}

#[test]
fn training_checkpoint_without_ema_uses_model() {
    let state_dict = load_checkpoint(&data("workspace_no_ema.ckpt")).unwrap();
    assert_eq!(
        state_dict.source,
        Source::TrainingCheckpoint(TrainingEntry::Model)
    );
    assert_synth_values(&state_dict, 2, |v| v);
}

#[test]
fn float16_state_dict_in_pickle_protocol_4() {
    let state_dict = load_checkpoint(&data("state_dict_f16.pt")).unwrap();
    assert_eq!(state_dict.source, Source::TorchStateDict);
    assert_synth_values(&state_dict, 1, |v| f16::from_f32(v).to_f32());
}

#[test]
fn float64_state_dict() {
    let state_dict = load_checkpoint(&data("state_dict_f64.pt")).unwrap();
    assert_synth_values(&state_dict, 1, |v| v);
}

#[test]
fn bfloat16_safetensors() {
    let state_dict = load_checkpoint(&data("state_dict_bf16.safetensors")).unwrap();
    assert_eq!(state_dict.source, Source::Safetensors);
    assert_synth_values(&state_dict, 1, |v| bf16::from_f32(v).to_f32());
    assert_eq!(
        state_dict.skipped["obs_encoder.backbone.bn1.num_batches_tracked"],
        "I64 tensor"
    );
}

#[test]
fn needed_key_of_an_integer_dtype_is_reported_as_unreadable() {
    let state_dict = load_checkpoint(&data("workspace.ckpt")).unwrap();
    let expected = [("model.counts".to_string(), vec![3])];
    let error = check_keys(&state_dict, &expected).unwrap_err();
    assert_eq!(
        error.unreadable,
        [("model.counts".to_string(), "int32 tensor".to_string())]
    );
}

/// `{:#}`: the message as the CLI prints it, context chain on one line.
fn load_error(path: &Path) -> String {
    format!("{:#}", load_checkpoint(path).unwrap_err())
}

fn temp_copy(name: &str, edit: impl FnOnce(&mut Vec<u8>)) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    let mut bytes = std::fs::read(data(name)).unwrap_or_default();
    edit(&mut bytes);
    std::fs::write(&path, bytes).unwrap();
    (dir, path)
}

#[test]
fn truncated_zip_is_one_clear_line() {
    let (_dir, path) = temp_copy("workspace.ckpt", |bytes| bytes.truncate(bytes.len() / 2));
    let message = load_error(&path);
    assert!(
        message.starts_with(&path.display().to_string()),
        "{message}"
    );
    assert!(
        message.contains("truncated or damaged zip archive"),
        "{message}"
    );
    assert!(!message.contains('\n'), "{message}");
}

#[test]
fn damaged_storage_names_the_key() {
    let (_dir, path) = temp_copy("workspace.ckpt", |bytes| {
        let mut archive = zip::ZipArchive::new(std::io::Cursor::new(bytes.clone())).unwrap();
        let names: Vec<String> = archive.file_names().map(str::to_owned).collect();
        for name in names.iter().filter(|name| name.contains("/data/")) {
            let start = archive.by_name(name).unwrap().data_start() as usize;
            bytes[start] ^= 0xff;
        }
    });
    let message = load_error(&path);
    assert!(
        message.contains("obs_encoder.backbone.conv1.weight: zip entry workspace/data/"),
        "{message}"
    );
}

#[test]
fn truncated_safetensors_is_an_error() {
    let (_dir, path) = temp_copy("state_dict_bf16.safetensors", |bytes| {
        bytes.truncate(bytes.len() - 10)
    });
    let message = load_error(&path);
    assert!(
        message.contains("not a valid safetensors file"),
        "{message}"
    );
}

#[test]
fn foreign_files_are_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let cases: [(&str, &[u8], &str); 3] = [
        (
            "notes.txt",
            b"hello, this is text",
            "neither a torch.save zip archive nor a safetensors file",
        ),
        ("empty.pt", b"", "empty file"),
        (
            "legacy.pt",
            b"\x80\x02\x8a\x0a\x6c\xfc\x9c\x46\xf9\x20\x6a\xa8\x50\x19.",
            "before PyTorch 1.6",
        ),
    ];
    for (name, bytes, expected) in cases {
        let path = dir.path().join(name);
        std::fs::write(&path, bytes).unwrap();
        let message = load_error(&path);
        assert!(message.contains(expected), "{name}: {message}");
        assert!(message.contains(name), "{name}: {message}");
    }
    let message = load_error(&dir.path().join("absent.pt"));
    assert!(message.contains("absent.pt: cannot open"), "{message}");
}
