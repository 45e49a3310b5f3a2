//! Lowering a checked state dict into the engine's weights file (written by the lead).

use scdp_engine::ModelConfig;

use crate::quant::Quant;
use crate::state_dict::StateDict;

/// The bytes of the weights file for `config` holding `state_dict` at precision `quant`.
/// `state_dict` has passed [`crate::keys::check_keys`] for `config`.
pub fn lower_to_weights_file(
    config: &ModelConfig,
    state_dict: &StateDict,
    quant: Quant,
) -> anyhow::Result<Vec<u8>> {
    match quant {
        Quant::F32 => crate::lowering::weights_file(config, state_dict),
        Quant::Int8 => anyhow::bail!("--quant int8 is not implemented yet; use --quant f32"),
    }
}
