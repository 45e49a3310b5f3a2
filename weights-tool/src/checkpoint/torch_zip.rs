//! `torch.save` archives: a zip holding `<name>/data.pkl` (the pickled object, with tensor
//! storages replaced by persistent ids) and one raw entry `<name>/data/<key>` per storage.
//!
//! The pickled object is either a state dict or a Diffusion Policy training checkpoint, whose
//! `state_dicts` entry holds `ema_model` and/or `model` beside optimizer states, and whose
//! other entries (OmegaConf `cfg`, dill-pickled attributes) are never looked at.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::Path;

use anyhow::{Context as _, anyhow, bail};
use indicatif::ProgressBar;
use zip::ZipArchive;

use super::dtype::{ByteOrder, DType};
use super::pickle::{Node, Pickle, Value, unpickle};
use crate::state_dict::{Source, StateDict, Tensor, TrainingEntry};

/// Reads the state dict of a `torch.save` archive.
pub(super) fn read_torch_archive(path: &Path, progress: &ProgressBar) -> anyhow::Result<StateDict> {
    let file = File::open(path).context("cannot open")?;
    let zip = ZipArchive::new(BufReader::new(file))
        .map_err(|error| anyhow!("truncated or damaged zip archive ({error})"))?;
    let mut archive = Archive::new(zip)?;
    let pickle_bytes = archive.entry(&format!("{}data.pkl", archive.prefix))?;
    let pickle = unpickle(&pickle_bytes).context("data.pkl")?;
    let (state_dict_value, source) = locate_state_dict(&pickle)?;
    let items = pickle
        .dict_items(state_dict_value)
        .expect("locate_state_dict returns dicts");

    let mut state_dict = StateDict::new(source);
    progress.set_length(items.len() as u64);
    for (key, value) in items {
        let Value::Str(key) = key else {
            bail!("state dict has a non-string key ({})", pickle.describe(key));
        };
        progress.set_message(key.clone());
        match tensor_entry(&pickle, value) {
            Entry::Tensor(tensor) if tensor.dtype.float_size().is_some() => {
                let data = archive.read_tensor(&tensor).with_context(|| key.clone())?;
                state_dict.insert(key.clone(), Tensor::new(tensor.shape, data));
            }
            Entry::Tensor(tensor) => {
                state_dict
                    .skipped
                    .insert(key.clone(), format!("{} tensor", tensor.dtype));
            }
            Entry::Other(what) => {
                state_dict.skipped.insert(key.clone(), what);
            }
        }
        progress.inc(1);
    }
    Ok(state_dict)
}

/// Finds the state dict inside the pickled object and says which one it is.
fn locate_state_dict(pickle: &Pickle) -> anyhow::Result<(&Value, Source)> {
    let root = &pickle.root;
    if pickle.dict_items(root).is_none() {
        bail!(
            "data.pkl holds a {}, expected a state dict or a training checkpoint dict",
            pickle.describe(root)
        );
    }
    let Some(state_dicts) = pickle.dict_get(root, "state_dicts") else {
        return Ok((root, Source::TorchStateDict));
    };
    for entry in [TrainingEntry::EmaModel, TrainingEntry::Model] {
        if let Some(value) = pickle.dict_get(state_dicts, entry.key()) {
            if pickle.dict_items(value).is_none() {
                bail!(
                    "state_dicts.{} is a {}, expected a state dict",
                    entry.key(),
                    pickle.describe(value)
                );
            }
            return Ok((value, Source::TrainingCheckpoint(entry)));
        }
    }
    bail!(
        "training checkpoint has neither state_dicts.ema_model nor state_dicts.model (state_dicts holds: {})",
        pickle.dict_keys(state_dicts).join(", ")
    )
}

/// A tensor as the pickle describes it: a strided view of a storage.
#[derive(Debug, PartialEq)]
struct TensorRef {
    storage_key: String,
    dtype: DType,
    /// Elements of the storage according to the pickle.
    storage_numel: usize,
    /// In elements.
    offset: usize,
    shape: Vec<usize>,
    /// In elements.
    stride: Vec<usize>,
}

/// A state-dict value: a tensor, or a description of whatever else it is.
#[derive(Debug, PartialEq)]
enum Entry {
    Tensor(TensorRef),
    Other(String),
}

/// Wrappers (`Parameter`, tensor subclasses) nest one or two deep; a deeper chain is not a
/// tensor torch.save wrote, and following it could exhaust the stack.
const MAX_WRAPPING: usize = 8;

fn tensor_entry(pickle: &Pickle, value: &Value) -> Entry {
    wrapped_tensor_entry(pickle, value, 0)
}

fn wrapped_tensor_entry(pickle: &Pickle, value: &Value, depth: usize) -> Entry {
    match pickle.node(value) {
        Some(Node::Object(object)) => rebuild(pickle, &object.class, &object.args, depth),
        _ => Entry::Other(format!("not a tensor ({})", pickle.describe(value))),
    }
}

/// Interprets a call of one of torch's tensor rebuild functions.
fn rebuild(pickle: &Pickle, function: &Value, args: &Value, depth: usize) -> Entry {
    let Value::Global { module, name } = function else {
        return Entry::Other("not a tensor (object of an unnamed class)".into());
    };
    if depth > MAX_WRAPPING {
        return Entry::Other("tensor wrapped too deeply".into());
    }
    let args = pickle.tuple(args).unwrap_or_default();
    let parsed = match (module.as_str(), name.as_str()) {
        ("torch._utils", "_rebuild_tensor_v2") => rebuild_strided(pickle, args, None),
        // Newer dtypes: the storage is untyped and the dtype follows the hooks.
        ("torch._utils", "_rebuild_tensor_v3") => match args.get(6) {
            Some(Value::Global { module, name }) if module == "torch" => {
                rebuild_strided(pickle, args, Some(dtype_from_torch_name(name)))
            }
            _ => Err("_rebuild_tensor_v3 without a dtype".into()),
        },
        // nn.Parameter(data, ...) and tensor subclasses wrap a plain tensor.
        ("torch._utils", "_rebuild_parameter" | "_rebuild_parameter_with_state") => {
            return match args.first() {
                Some(data) => wrapped_tensor_entry(pickle, data, depth + 1),
                None => Entry::Other("_rebuild_parameter without data".into()),
            };
        }
        ("torch._tensor", "_rebuild_from_type_v2") => {
            return match args {
                [function, _type, args, ..] => rebuild(pickle, function, args, depth + 1),
                _ => Entry::Other("_rebuild_from_type_v2 with too few arguments".into()),
            };
        }
        ("torch._utils", other) if other.starts_with("_rebuild") => {
            Err(format!("unsupported kind of tensor (torch._utils.{other})"))
        }
        _ => Err(format!("not a tensor ({module}.{name} object)")),
    };
    parsed.map_or_else(Entry::Other, Entry::Tensor)
}

/// `(storage, storage_offset, size, stride, ...)`, the arguments of `_rebuild_tensor_v2/v3`.
fn rebuild_strided(
    pickle: &Pickle,
    args: &[Value],
    v3_dtype: Option<DType>,
) -> Result<TensorRef, String> {
    let [storage, offset, size, stride, ..] = args else {
        return Err("tensor rebuild with too few arguments".into());
    };
    let Some(Node::PersistentId(id)) = pickle.node(storage) else {
        return Err("tensor without a storage reference".into());
    };
    let [kind, storage_type, key, _location, numel] = pickle.tuple(id).unwrap_or_default() else {
        return Err("malformed storage reference".into());
    };
    let (
        Value::Str(kind),
        Value::Global {
            name: type_name, ..
        },
        Value::Str(key),
    ) = (kind, storage_type, key)
    else {
        return Err("malformed storage reference".into());
    };
    if kind != "storage" {
        return Err(format!(
            "persistent id of kind {kind:?}, expected \"storage\""
        ));
    }
    let dtype = v3_dtype.unwrap_or_else(|| dtype_from_storage_type(type_name));
    let numel = non_negative(numel).ok_or("storage size is not a non-negative integer")?;
    // An untyped storage (v3) counts bytes.
    let storage_numel = match (type_name.as_str(), dtype.float_size()) {
        ("UntypedStorage", Some(size)) => numel / size,
        _ => numel,
    };
    Ok(TensorRef {
        storage_key: key.clone(),
        dtype,
        storage_numel,
        offset: non_negative(offset).ok_or("storage offset is not a non-negative integer")?,
        shape: usize_tuple(pickle, size).ok_or("size is not a tuple of non-negative integers")?,
        stride: usize_tuple(pickle, stride)
            .ok_or("stride is not a tuple of non-negative integers")?,
    })
}

fn non_negative(value: &Value) -> Option<usize> {
    match value {
        Value::Int(value) => usize::try_from(*value).ok(),
        _ => None,
    }
}

fn usize_tuple(pickle: &Pickle, value: &Value) -> Option<Vec<usize>> {
    pickle.tuple(value)?.iter().map(non_negative).collect()
}

/// The legacy typed-storage classes torch.save still names (`torch.FloatStorage`, ...).
fn dtype_from_storage_type(name: &str) -> DType {
    match name {
        "FloatStorage" => DType::F32,
        "HalfStorage" => DType::F16,
        "BFloat16Storage" => DType::BF16,
        "DoubleStorage" => DType::F64,
        "LongStorage" => DType::Other("int64".into()),
        "IntStorage" => DType::Other("int32".into()),
        "ShortStorage" => DType::Other("int16".into()),
        "CharStorage" => DType::Other("int8".into()),
        "ByteStorage" => DType::Other("uint8".into()),
        "BoolStorage" => DType::Other("bool".into()),
        other => DType::Other(format!("torch.{other}")),
    }
}

/// `torch.float32` and friends, as `_rebuild_tensor_v3` names them.
fn dtype_from_torch_name(name: &str) -> DType {
    match name {
        "float32" | "float" => DType::F32,
        "float16" | "half" => DType::F16,
        "bfloat16" => DType::BF16,
        "float64" | "double" => DType::F64,
        other => DType::Other(other.into()),
    }
}

struct Archive {
    zip: ZipArchive<BufReader<File>>,
    /// The directory all entries are under (`archive/` or the file's stem), with the slash.
    prefix: String,
    order: ByteOrder,
    /// Storages read so far: several tensors may view one storage.
    storages: HashMap<String, Vec<u8>>,
}

impl Archive {
    fn new(zip: ZipArchive<BufReader<File>>) -> anyhow::Result<Self> {
        let prefix = zip
            .file_names()
            .filter_map(|name| name.strip_suffix("data.pkl"))
            .find(|prefix| {
                prefix.is_empty() || prefix.matches('/').count() == 1 && prefix.ends_with('/')
            })
            .map(str::to_owned)
            .ok_or_else(|| anyhow!("zip archive without data.pkl: not written by torch.save"))?;
        let mut archive = Archive {
            zip,
            prefix,
            order: ByteOrder::Little,
            storages: HashMap::new(),
        };
        // Archives from before PyTorch 1.10 have no byteorder entry and are little-endian.
        let byteorder_name = format!("{}byteorder", archive.prefix);
        if archive.zip.index_for_name(&byteorder_name).is_some() {
            archive.order = match archive.entry(&byteorder_name)?.as_slice() {
                b"little" => ByteOrder::Little,
                b"big" => ByteOrder::Big,
                other => bail!("byteorder entry says {:?}", String::from_utf8_lossy(other)),
            };
        }
        Ok(archive)
    }

    fn entry(&mut self, name: &str) -> anyhow::Result<Vec<u8>> {
        let mut file = self
            .zip
            .by_name(name)
            .with_context(|| format!("zip entry {name}"))?;
        let mut bytes = Vec::with_capacity(file.size().try_into().unwrap_or(0));
        file.read_to_end(&mut bytes)
            .with_context(|| format!("zip entry {name} is truncated or damaged"))?;
        Ok(bytes)
    }

    fn read_tensor(&mut self, tensor: &TensorRef) -> anyhow::Result<Vec<f32>> {
        let size = tensor
            .dtype
            .float_size()
            .expect("only float tensors are read");
        if !self.storages.contains_key(&tensor.storage_key) {
            let name = format!("{}data/{}", self.prefix, tensor.storage_key);
            let bytes = self.entry(&name)?;
            let expected = tensor.storage_numel.saturating_mul(size);
            if bytes.len() < expected {
                bail!(
                    "storage {name} holds {} bytes, expected {} {} values ({expected} bytes)",
                    bytes.len(),
                    tensor.storage_numel,
                    tensor.dtype
                );
            }
            self.storages.insert(tensor.storage_key.clone(), bytes);
        }
        let bytes = &self.storages[&tensor.storage_key];
        let view = StridedView {
            offset: tensor.offset,
            shape: &tensor.shape,
            stride: &tensor.stride,
        };
        view.gather(bytes, &tensor.dtype, self.order)
            .map_err(|message| anyhow!("storage data/{}: {message}", tensor.storage_key))
    }
}

/// Elements `offset + sum(index[i] * stride[i])` of a storage, in row-major index order.
struct StridedView<'a> {
    offset: usize,
    shape: &'a [usize],
    stride: &'a [usize],
}

impl StridedView<'_> {
    fn gather(&self, bytes: &[u8], dtype: &DType, order: ByteOrder) -> Result<Vec<f32>, String> {
        let size = dtype.float_size().expect("only float tensors are read");
        if self.shape.len() != self.stride.len() {
            return Err(format!(
                "size {:?} and stride {:?} differ in rank",
                self.shape, self.stride
            ));
        }
        let numel = self
            .shape
            .iter()
            .try_fold(1usize, |n, &dim| n.checked_mul(dim))
            .ok_or("element count overflows")?;
        if numel == 0 {
            return Ok(Vec::new());
        }
        let last = self
            .shape
            .iter()
            .zip(self.stride)
            .try_fold(self.offset, |end, (&dim, &stride)| {
                end.checked_add((dim - 1).checked_mul(stride)?)
            })
            .ok_or("view extent overflows")?;
        let available = bytes.len() / size;
        if last >= available {
            return Err(format!(
                "view (offset {}, size {:?}, stride {:?}) reaches element {last} but the storage has {available}",
                self.offset, self.shape, self.stride
            ));
        }
        let element = |index: usize| dtype.decode(&bytes[index * size..(index + 1) * size], order);
        if self.is_contiguous() {
            return Ok((self.offset..self.offset + numel).map(element).collect());
        }
        // Odometer over the multi-index, last dimension fastest.
        let mut data = Vec::with_capacity(numel);
        let mut index = vec![0usize; self.shape.len()];
        let mut position = self.offset;
        for _ in 0..numel {
            data.push(element(position));
            for axis in (0..self.shape.len()).rev() {
                index[axis] += 1;
                position += self.stride[axis];
                if index[axis] < self.shape[axis] {
                    break;
                }
                position -= self.stride[axis] * self.shape[axis];
                index[axis] = 0;
            }
        }
        Ok(data)
    }

    /// Row-major with no gaps (dimensions of size 1 may have any stride).
    fn is_contiguous(&self) -> bool {
        let mut expected = 1;
        for (&dim, &stride) in self.shape.iter().zip(self.stride).rev() {
            if dim != 1 && stride != expected {
                return false;
            }
            expected *= dim;
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn f32_bytes(values: impl IntoIterator<Item = f32>) -> Vec<u8> {
        values.into_iter().flat_map(f32::to_le_bytes).collect()
    }

    fn gather(
        offset: usize,
        shape: &[usize],
        stride: &[usize],
        bytes: &[u8],
    ) -> Result<Vec<f32>, String> {
        StridedView {
            offset,
            shape,
            stride,
        }
        .gather(bytes, &DType::F32, ByteOrder::Little)
    }

    #[test]
    fn contiguous_with_offset() {
        let bytes = f32_bytes((0..10).map(|v| v as f32));
        assert_eq!(
            gather(2, &[2, 3], &[3, 1], &bytes).unwrap(),
            [2., 3., 4., 5., 6., 7.]
        );
    }

    #[test]
    fn transposed_view() {
        // torch.arange(6.).reshape(2, 3).t(): size (3, 2), stride (1, 3).
        let bytes = f32_bytes((0..6).map(|v| v as f32));
        assert_eq!(
            gather(0, &[3, 2], &[1, 3], &bytes).unwrap(),
            [0., 3., 1., 4., 2., 5.]
        );
    }

    #[test]
    fn broadcast_and_scalar() {
        let bytes = f32_bytes([7.0, 8.0]);
        assert_eq!(gather(1, &[2, 2], &[0, 0], &bytes).unwrap(), [8.; 4]);
        assert_eq!(gather(1, &[], &[], &bytes).unwrap(), [8.]);
        assert_eq!(
            gather(0, &[0, 5], &[5, 1], &bytes).unwrap(),
            Vec::<f32>::new()
        );
    }

    #[test]
    fn views_past_the_storage_are_errors() {
        let bytes = f32_bytes([0.0; 6]);
        let error = gather(1, &[2, 3], &[3, 1], &bytes).unwrap_err();
        assert!(error.contains("reaches element 6"), "{error}");
    }

    #[test]
    fn storage_type_names() {
        assert_eq!(dtype_from_storage_type("BFloat16Storage"), DType::BF16);
        assert_eq!(
            dtype_from_storage_type("LongStorage"),
            DType::Other("int64".into())
        );
        assert_eq!(dtype_from_torch_name("float16"), DType::F16);
    }
}
