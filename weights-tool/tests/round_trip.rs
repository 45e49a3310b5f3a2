//! synth -> .safetensors -> load_checkpoint gives back the same state dict.

use std::collections::BTreeMap;

use scdp_engine::ModelConfig;
use weights_tool::keys::{check_keys, expected_keys};
use weights_tool::synth::synth_state_dict;
use weights_tool::{Source, load_checkpoint, write_state_dict_safetensors};

#[test]
fn synth_safetensors_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tiny.safetensors");
    let written = synth_state_dict(&ModelConfig::TINY, 1);
    let metadata = BTreeMap::from([("seed".to_owned(), "1".to_owned())]);
    write_state_dict_safetensors(&written, &metadata, &path).unwrap();

    let read = load_checkpoint(&path).unwrap();
    assert_eq!(read.source, Source::Safetensors);
    assert!(read.skipped.is_empty());
    assert_eq!(read.tensors, written.tensors);
    assert_eq!(
        check_keys(&read, &expected_keys(&ModelConfig::TINY)),
        Ok(())
    );
}
