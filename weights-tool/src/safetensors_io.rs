//! Reading a state dict from `.safetensors` bytes and writing one as f32 `.safetensors`.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use anyhow::Context as _;
use indicatif::ProgressBar;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use crate::checkpoint::dtype::{ByteOrder, DType};
use crate::state_dict::{Source, StateDict, Tensor};

/// Parses a whole `.safetensors` file already in memory.
pub fn read_safetensors(bytes: &[u8], progress: &ProgressBar) -> anyhow::Result<StateDict> {
    let file = SafeTensors::deserialize(bytes)
        .map_err(|error| anyhow::anyhow!("not a valid safetensors file ({error})"))?;
    let mut state_dict = StateDict::new(Source::Safetensors);
    progress.set_length(file.len() as u64);
    for (key, view) in file.iter() {
        progress.set_message(key.to_owned());
        let dtype = dtype_of(view.dtype());
        match dtype.float_size() {
            Some(size) => {
                // The format guarantees row-major data of exactly shape x size bytes.
                let data = view
                    .data()
                    .chunks_exact(size)
                    .map(|element| dtype.decode(element, ByteOrder::Little))
                    .collect();
                state_dict.insert(key.to_owned(), Tensor::new(view.shape().to_vec(), data));
            }
            None => {
                state_dict
                    .skipped
                    .insert(key.to_owned(), format!("{dtype} tensor"));
            }
        }
        progress.inc(1);
    }
    Ok(state_dict)
}

fn dtype_of(dtype: Dtype) -> DType {
    match dtype {
        Dtype::F32 => DType::F32,
        Dtype::F16 => DType::F16,
        Dtype::BF16 => DType::BF16,
        Dtype::F64 => DType::F64,
        other => DType::Other(format!("{other:?}")),
    }
}

/// The `.safetensors` bytes of `state_dict`, all tensors f32, with `metadata` in the header's
/// `__metadata__`.
pub fn state_dict_to_safetensors(
    state_dict: &StateDict,
    metadata: &BTreeMap<String, String>,
) -> anyhow::Result<Vec<u8>> {
    let bytes: Vec<(&String, Vec<u8>)> = state_dict
        .tensors
        .iter()
        .map(|(key, tensor)| {
            (
                key,
                tensor.data.iter().flat_map(|v| v.to_le_bytes()).collect(),
            )
        })
        .collect();
    let views = bytes
        .iter()
        .zip(state_dict.tensors.values())
        .map(|((key, data), tensor)| {
            TensorView::new(Dtype::F32, tensor.shape.clone(), data)
                .map(|view| (key.as_str(), view))
                .with_context(|| format!("tensor {key}"))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let metadata: HashMap<String, String> = metadata.clone().into_iter().collect();
    safetensors::serialize(views, Some(metadata)).context("cannot serialize safetensors")
}

/// Writes `state_dict` to `path` as f32 `.safetensors`.
pub fn write_state_dict_safetensors(
    state_dict: &StateDict,
    metadata: &BTreeMap<String, String>,
    path: &Path,
) -> anyhow::Result<()> {
    let bytes = state_dict_to_safetensors(state_dict, metadata)?;
    std::fs::write(path, bytes).with_context(|| format!("{}: cannot write", path.display()))
}
