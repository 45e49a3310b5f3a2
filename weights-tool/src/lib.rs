//! weights-tool library: checkpoint reading, synthetic weights, conversion.
//!
//! The pipeline of `weights-tool convert`: [`checkpoint::load_checkpoint`] ->
//! [`remap::remap_keys`] -> [`keys::check_keys`] against [`keys::expected_keys`] ->
//! [`lowering::lower_to_weights_file`].

pub mod activations;
#[cfg(feature = "gptq")]
pub mod calibrate;
pub mod checkpoint;
pub mod config;
#[cfg(feature = "gptq")]
pub mod gptq;
pub mod inspect;
pub mod keys;
pub mod lowering;
pub mod quant;
pub mod refine;
pub mod remap;
pub mod run;
pub mod safetensors_io;
pub mod scenes;
pub mod state_dict;
pub mod synth;
pub mod writer;

pub use checkpoint::{load_checkpoint, load_checkpoint_with_progress};
pub use config::{config_to_toml, load_config, parse_config};
pub use keys::{check_keys, expected_keys};
pub use quant::Quant;
pub use remap::{KeyPrefix, remap_keys};
pub use safetensors_io::write_state_dict_safetensors;
pub use state_dict::{Source, StateDict, Tensor, TrainingEntry};
pub use synth::{synth_state_dict, weights_sha256};
