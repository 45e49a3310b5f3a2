//! A PyTorch-style state dict held as f32, whatever container and dtype it came from.

use std::collections::BTreeMap;
use std::fmt;

/// One tensor: PyTorch's shape and its values in row-major (C) order.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

impl Tensor {
    /// Panics when `data` does not hold exactly `shape.iter().product()` values: every caller
    /// builds both from the same source, so a mismatch is a bug, not bad input.
    pub fn new(shape: Vec<usize>, data: Vec<f32>) -> Self {
        assert_eq!(
            shape.iter().product::<usize>(),
            data.len(),
            "tensor data does not match its shape {shape:?}"
        );
        Tensor { shape, data }
    }

    pub fn numel(&self) -> usize {
        self.data.len()
    }
}

/// Which entry of a Diffusion Policy training checkpoint the weights came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrainingEntry {
    /// `state_dicts.ema_model`: the exponential moving average, preferred for inference.
    EmaModel,
    /// `state_dicts.model`: the raw trained weights, used when the run kept no EMA.
    Model,
}

impl TrainingEntry {
    /// The key under `state_dicts`.
    pub fn key(self) -> &'static str {
        match self {
            TrainingEntry::EmaModel => "ema_model",
            TrainingEntry::Model => "model",
        }
    }
}

/// Where a [`StateDict`] came from, for reports and for telling EMA from raw weights.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Source {
    /// Made by `synth` for this seed.
    Synthetic { seed: u64 },
    /// A `.safetensors` file.
    Safetensors,
    /// A `torch.save(state_dict)` archive.
    TorchStateDict,
    /// A Diffusion Policy training checkpoint (`torch.save` of a payload dict).
    TrainingCheckpoint(TrainingEntry),
}

impl fmt::Display for Source {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Source::Synthetic { seed } => write!(f, "synthetic weights, seed {seed}"),
            Source::Safetensors => f.write_str("safetensors file"),
            Source::TorchStateDict => f.write_str("torch.save state dict"),
            Source::TrainingCheckpoint(entry) => {
                write!(f, "training checkpoint, state_dicts.{}", entry.key())
            }
        }
    }
}

/// Keys mapped to f32 tensors, in bytewise key order.
#[derive(Clone, Debug, PartialEq)]
pub struct StateDict {
    pub tensors: BTreeMap<String, Tensor>,
    /// Entries the container holds but that are not floating-point tensors (key -> what they
    /// are, e.g. `int64` for `num_batches_tracked`). Kept so that a needed key with an
    /// unreadable dtype is reported as such rather than as missing.
    pub skipped: BTreeMap<String, String>,
    pub source: Source,
}

impl StateDict {
    pub fn new(source: Source) -> Self {
        StateDict {
            tensors: BTreeMap::new(),
            skipped: BTreeMap::new(),
            source,
        }
    }

    pub fn get(&self, key: &str) -> Option<&Tensor> {
        self.tensors.get(key)
    }

    pub fn insert(&mut self, key: String, tensor: Tensor) {
        self.tensors.insert(key, tensor);
    }

    pub fn len(&self) -> usize {
        self.tensors.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tensors.is_empty()
    }

    /// Total number of values over all tensors.
    pub fn numel(&self) -> usize {
        self.tensors.values().map(Tensor::numel).sum()
    }
}
