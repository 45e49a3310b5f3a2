//! The state-dict keys of docs/SPEC.md section 6 with their PyTorch shapes, and the check that a
//! loaded state dict has exactly those.

use std::collections::BTreeSet;
use std::fmt;

use scdp_engine::{BackboneNorm, ModelConfig};

use crate::state_dict::StateDict;

/// A key and the shape PyTorch gives it.
pub type ExpectedKey = (String, Vec<usize>);

/// Counted as a BatchNorm buffer in PyTorch but carries nothing inference needs.
const IGNORED_SUFFIX: &str = ".num_batches_tracked";

/// Other normalizer entries (`input_stats`, other observation keys) exist in Diffusion Policy
/// checkpoints but do not enter the model (docs/SPEC.md section 6).
const IGNORED_PREFIX: &str = "normalizer.";

/// Every key of docs/SPEC.md section 6 for `config`, in PyTorch's `state_dict()` order within each
/// module, with its shape. `num_batches_tracked` is not listed.
pub fn expected_keys(config: &ModelConfig) -> Vec<ExpectedKey> {
    let mut keys = KeyList::default();
    backbone_keys(config, &mut keys);
    projection_keys(config, &mut keys);
    unet_keys(config, &mut keys);
    normalizer_keys(config, &mut keys);
    keys.0
}

#[derive(Default)]
struct KeyList(Vec<ExpectedKey>);

impl KeyList {
    fn push(&mut self, key: String, shape: &[usize]) {
        self.0.push((key, shape.to_vec()));
    }

    /// `weight` and `bias` of a layer with a bias.
    fn layer(&mut self, prefix: &str, weight: &[usize], bias: usize) {
        self.push(format!("{prefix}.weight"), weight);
        self.push(format!("{prefix}.bias"), &[bias]);
    }

    /// GroupNorm: weight and bias. BatchNorm additionally has its running statistics.
    fn norm(&mut self, prefix: &str, channels: usize, kind: BackboneNorm) {
        self.layer(prefix, &[channels], channels);
        if kind == BackboneNorm::Batch {
            self.push(format!("{prefix}.running_mean"), &[channels]);
            self.push(format!("{prefix}.running_var"), &[channels]);
        }
    }
}

/// torchvision's resnet18 without `fc` (Diffusion Policy replaces it with Identity). Its
/// convolutions have no bias.
fn backbone_keys(config: &ModelConfig, keys: &mut KeyList) {
    let norm = config.backbone_norm;
    let p = "obs_encoder.backbone";
    let width = config.stage_channels(0);
    keys.push(format!("{p}.conv1.weight"), &[width, 3, 7, 7]);
    keys.norm(&format!("{p}.bn1"), width, norm);
    let mut in_channels = width;
    for stage in 0..4 {
        let out = config.stage_channels(stage);
        for block in 0..2 {
            let b = format!("{p}.layer{}.{block}", stage + 1);
            let block_in = if block == 0 { in_channels } else { out };
            keys.push(format!("{b}.conv1.weight"), &[out, block_in, 3, 3]);
            keys.norm(&format!("{b}.bn1"), out, norm);
            keys.push(format!("{b}.conv2.weight"), &[out, out, 3, 3]);
            keys.norm(&format!("{b}.bn2"), out, norm);
            // Stages 2..4 halve the resolution and widen in their first block.
            if block == 0 && stage > 0 {
                keys.push(format!("{b}.downsample.0.weight"), &[out, block_in, 1, 1]);
                keys.norm(&format!("{b}.downsample.1"), out, norm);
            }
        }
        in_channels = out;
    }
}

/// The five 3x3 projections C_n -> d; C1 (after the stem) and C2 both have the first stage's
/// width.
fn projection_keys(config: &ModelConfig, keys: &mut KeyList) {
    let d = config.feature_dim as usize;
    let inputs = [0, 0, 1, 2, 3].map(|stage| config.stage_channels(stage));
    for (level, c) in inputs.into_iter().enumerate() {
        keys.layer(&format!("obs_encoder.proj.{level}"), &[d, c, 3, 3], d);
    }
}

/// Diffusion Policy's ConditionalUnet1D with FiLM scale and bias (`cond_predict_scale`).
fn unet_keys(config: &ModelConfig, keys: &mut KeyList) {
    let e = config.diffusion_step_embed_dim as usize;
    let [d0, d1, d2] = config.down_dims.map(|d| d as usize);
    let action_dim = config.action_dim as usize;
    let k = config.kernel_size as usize;
    let block = |keys: &mut KeyList, prefix: &str, dim_in: usize, dim_out: usize| {
        residual_block_keys(config, keys, prefix, dim_in, dim_out);
    };

    keys.layer("model.diffusion_step_encoder.1", &[4 * e, e], 4 * e);
    keys.layer("model.diffusion_step_encoder.3", &[e, 4 * e], e);

    let down = [(action_dim, d0), (d0, d1), (d1, d2)];
    for (level, (dim_in, dim_out)) in down.into_iter().enumerate() {
        let p = format!("model.down_modules.{level}");
        block(keys, &format!("{p}.0"), dim_in, dim_out);
        block(keys, &format!("{p}.1"), dim_out, dim_out);
        // Downsample1d after every level but the last.
        if level + 1 < down.len() {
            keys.layer(&format!("{p}.2.conv"), &[dim_out, dim_out, 3], dim_out);
        }
    }

    block(keys, "model.mid_modules.0", d2, d2);
    block(keys, "model.mid_modules.1", d2, d2);

    // Both up levels upsample; ConvTranspose1d's weight is [in, out, k].
    for (level, (skip_and_in, dim_out)) in [(d2, d1), (d1, d0)].into_iter().enumerate() {
        let p = format!("model.up_modules.{level}");
        block(keys, &format!("{p}.0"), 2 * skip_and_in, dim_out);
        block(keys, &format!("{p}.1"), dim_out, dim_out);
        keys.layer(&format!("{p}.2.conv"), &[dim_out, dim_out, 4], dim_out);
    }

    keys.layer("model.final_conv.0.block.0", &[d0, d0, k], d0);
    keys.layer("model.final_conv.0.block.1", &[d0], d0);
    keys.layer("model.final_conv.1", &[action_dim, d0, 1], action_dim);
}

/// ConditionalResidualBlock1D: two Conv1dBlocks (Conv1d, GroupNorm), the FiLM encoder
/// `Linear(cond_dim, 2 out)` and a 1x1 residual conv when the width changes.
fn residual_block_keys(
    config: &ModelConfig,
    keys: &mut KeyList,
    prefix: &str,
    dim_in: usize,
    dim_out: usize,
) {
    let k = config.kernel_size as usize;
    keys.layer(
        &format!("{prefix}.blocks.0.block.0"),
        &[dim_out, dim_in, k],
        dim_out,
    );
    keys.layer(&format!("{prefix}.blocks.0.block.1"), &[dim_out], dim_out);
    keys.layer(
        &format!("{prefix}.blocks.1.block.0"),
        &[dim_out, dim_out, k],
        dim_out,
    );
    keys.layer(&format!("{prefix}.blocks.1.block.1"), &[dim_out], dim_out);
    keys.layer(
        &format!("{prefix}.cond_encoder.1"),
        &[2 * dim_out, config.cond_dim()],
        2 * dim_out,
    );
    if dim_in != dim_out {
        keys.layer(
            &format!("{prefix}.residual_conv"),
            &[dim_out, dim_in, 1],
            dim_out,
        );
    }
}

fn normalizer_keys(config: &ModelConfig, keys: &mut KeyList) {
    let p = "normalizer.params_dict";
    for (field, dim) in [
        ("action", config.action_dim),
        ("agent_pos", config.state_dim),
    ] {
        keys.push(format!("{p}.{field}.scale"), &[dim as usize]);
        keys.push(format!("{p}.{field}.offset"), &[dim as usize]);
    }
}

/// Everything wrong with a state dict's keys, all at once.
#[derive(Debug, Default, PartialEq, Eq, thiserror::Error)]
pub struct KeyMismatch {
    /// Expected keys the state dict lacks, with their expected shapes.
    pub missing: Vec<ExpectedKey>,
    /// Keys the model has no use for, with what they hold (`shape [..]`, `int32 tensor`).
    pub extra: Vec<(String, String)>,
    /// `(key, expected shape, found shape)`.
    pub misshaped: Vec<(String, Vec<usize>, Vec<usize>)>,
    /// Expected keys present only as something other than a float tensor: `(key, what)`.
    pub unreadable: Vec<(String, String)>,
}

impl fmt::Display for KeyMismatch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "state dict does not match the config: {} missing, {} extra, {} mis-shaped, {} unreadable",
            self.missing.len(),
            self.extra.len(),
            self.misshaped.len(),
            self.unreadable.len()
        )?;
        for (key, shape) in &self.missing {
            write!(f, "\n  missing     {key} (expected shape {shape:?})")?;
        }
        for (key, what) in &self.extra {
            write!(f, "\n  extra       {key} ({what})")?;
        }
        for (key, expected, found) in &self.misshaped {
            write!(
                f,
                "\n  mis-shaped  {key}: expected {expected:?}, found {found:?}"
            )?;
        }
        for (key, what) in &self.unreadable {
            write!(
                f,
                "\n  unreadable  {key}: {what}, expected a float32, float16, bfloat16 or float64 tensor"
            )?;
        }
        Ok(())
    }
}

/// Checks that `state_dict` has exactly the `expected` keys with the expected shapes.
/// `num_batches_tracked` and normalizer entries other than the expected ones are ignored.
pub fn check_keys(state_dict: &StateDict, expected: &[ExpectedKey]) -> Result<(), KeyMismatch> {
    let mut mismatch = KeyMismatch::default();
    for (key, shape) in expected {
        match state_dict.get(key) {
            Some(tensor) if tensor.shape != *shape => {
                mismatch
                    .misshaped
                    .push((key.clone(), shape.clone(), tensor.shape.clone()));
            }
            Some(_) => {}
            None => match state_dict.skipped.get(key) {
                Some(what) => mismatch.unreadable.push((key.clone(), what.clone())),
                None => mismatch.missing.push((key.clone(), shape.clone())),
            },
        }
    }
    let expected_names: BTreeSet<&str> = expected.iter().map(|(key, _)| key.as_str()).collect();
    let unexpected = |key: &String| {
        !expected_names.contains(key.as_str())
            && !key.ends_with(IGNORED_SUFFIX)
            && !key.starts_with(IGNORED_PREFIX)
    };
    let tensors = state_dict
        .tensors
        .iter()
        .map(|(key, tensor)| (key, format!("shape {:?}", tensor.shape)));
    let others = state_dict
        .skipped
        .iter()
        .map(|(key, what)| (key, what.clone()));
    mismatch.extra = tensors
        .chain(others)
        .filter(|(key, _)| unexpected(key))
        .map(|(key, what)| (key.clone(), what))
        .collect();
    mismatch.extra.sort();
    if mismatch == KeyMismatch::default() {
        Ok(())
    } else {
        Err(mismatch)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::state_dict::{Source, Tensor};

    fn shape_of(keys: &[ExpectedKey], key: &str) -> Vec<usize> {
        keys.iter()
            .find(|(name, _)| name == key)
            .unwrap_or_else(|| panic!("{key} not expected"))
            .1
            .clone()
    }

    #[test]
    fn keys_are_unique() {
        let keys = expected_keys(&ModelConfig::PANDA);
        let mut names: Vec<_> = keys.iter().map(|(name, _)| name.as_str()).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), keys.len());
    }

    #[test]
    fn panda_shapes_match_diffusion_policy() {
        let keys = expected_keys(&ModelConfig::PANDA);
        // To (5 d + state_dim) + e = 2 (320 + 8) + 128.
        let cond_dim = 784;
        assert_eq!(
            shape_of(&keys, "model.down_modules.0.0.cond_encoder.1.weight"),
            [256, cond_dim]
        );
        assert_eq!(
            shape_of(&keys, "model.down_modules.0.0.residual_conv.weight"),
            [128, 10, 1]
        );
        assert_eq!(
            shape_of(&keys, "model.down_modules.1.2.conv.weight"),
            [256, 256, 3]
        );
        assert_eq!(
            shape_of(&keys, "model.up_modules.0.0.blocks.0.block.0.weight"),
            [256, 768, 5]
        );
        assert_eq!(
            shape_of(&keys, "model.up_modules.1.2.conv.weight"),
            [128, 128, 4]
        );
        assert_eq!(shape_of(&keys, "model.final_conv.1.weight"), [10, 128, 1]);
        assert_eq!(
            shape_of(&keys, "obs_encoder.backbone.layer4.0.downsample.0.weight"),
            [512, 256, 1, 1]
        );
        assert_eq!(
            shape_of(&keys, "obs_encoder.proj.4.weight"),
            [64, 512, 3, 3]
        );
        assert_eq!(shape_of(&keys, "obs_encoder.proj.1.weight"), [64, 64, 3, 3]);
        assert_eq!(
            shape_of(&keys, "normalizer.params_dict.agent_pos.scale"),
            [8]
        );
        // No Downsample1d after the last level, no residual conv when widths agree.
        let names: Vec<_> = keys.iter().map(|(name, _)| name.as_str()).collect();
        assert!(!names.contains(&"model.down_modules.2.2.conv.weight"));
        assert!(!names.contains(&"model.mid_modules.0.residual_conv.weight"));
        assert!(!names.iter().any(|name| name.contains("running_mean")));
    }

    #[test]
    fn panda_parameter_count() {
        // 11.17 M for the resnet18 trunk without fc, the rest hand-summed from the shapes.
        let keys = expected_keys(&ModelConfig::PANDA);
        let trunk: usize = keys
            .iter()
            .filter(|(name, _)| name.starts_with("obs_encoder.backbone."))
            .map(|(_, shape)| shape.iter().product::<usize>())
            .sum();
        // torchvision resnet18 has 11_689_512 parameters, fc has 512 * 1000 + 1000 of them.
        assert_eq!(trunk, 11_689_512 - 513_000);
    }

    #[test]
    fn batch_norm_has_running_statistics() {
        let keys = expected_keys(&ModelConfig::TINY);
        assert_eq!(
            shape_of(
                &keys,
                "obs_encoder.backbone.layer2.0.downsample.1.running_var"
            ),
            [16]
        );
        assert_eq!(
            shape_of(&keys, "obs_encoder.backbone.conv1.weight"),
            [8, 3, 7, 7]
        );
    }

    fn tiny_state_dict() -> (Vec<ExpectedKey>, StateDict) {
        let expected = expected_keys(&ModelConfig::TINY);
        let mut state_dict = StateDict::new(Source::Safetensors);
        for (key, shape) in &expected {
            let numel = shape.iter().product();
            state_dict.insert(key.clone(), Tensor::new(shape.clone(), vec![0.0; numel]));
        }
        (expected, state_dict)
    }

    #[test]
    fn complete_state_dict_passes_and_ignores_extras_that_do_not_matter() {
        let (expected, mut state_dict) = tiny_state_dict();
        state_dict.insert(
            "normalizer.params_dict.action.input_stats.min".into(),
            Tensor::new(vec![4], vec![0.0; 4]),
        );
        state_dict.insert(
            "obs_encoder.backbone.bn1.num_batches_tracked".into(),
            Tensor::new(vec![], vec![0.0]),
        );
        assert_eq!(check_keys(&state_dict, &expected), Ok(()));
    }

    #[test]
    fn every_problem_is_listed() {
        let (expected, mut state_dict) = tiny_state_dict();
        state_dict.tensors.remove("model.final_conv.1.bias");
        state_dict.tensors.remove("obs_encoder.proj.3.weight");
        state_dict.insert(
            "model.extra.weight".into(),
            Tensor::new(vec![2], vec![0.0; 2]),
        );
        state_dict.insert(
            "obs_encoder.backbone.conv1.weight".into(),
            Tensor::new(vec![8, 3, 3, 3], vec![0.0; 216]),
        );
        state_dict.tensors.remove("model.final_conv.1.weight");
        state_dict
            .skipped
            .insert("model.final_conv.1.weight".into(), "int32 tensor".into());
        let error = check_keys(&state_dict, &expected).unwrap_err();
        assert_eq!(
            error.missing,
            [
                ("obs_encoder.proj.3.weight".to_string(), vec![8, 32, 3, 3]),
                ("model.final_conv.1.bias".to_string(), vec![4]),
            ]
        );
        assert_eq!(
            error.extra,
            [("model.extra.weight".to_string(), "shape [2]".to_string())]
        );
        assert_eq!(
            error.misshaped,
            [(
                "obs_encoder.backbone.conv1.weight".to_string(),
                vec![8, 3, 7, 7],
                vec![8, 3, 3, 3]
            )]
        );
        assert_eq!(
            error.unreadable,
            [(
                "model.final_conv.1.weight".to_string(),
                "int32 tensor".to_string()
            )]
        );
        let message = error.to_string();
        for line in [
            "1 extra",
            "missing     obs_encoder.proj.3.weight (expected shape [8, 32, 3, 3])",
            "missing     model.final_conv.1.bias (expected shape [4])",
            "extra       model.extra.weight (shape [2])",
            "mis-shaped  obs_encoder.backbone.conv1.weight: expected [8, 3, 7, 7], found [8, 3, 3, 3]",
            "unreadable  model.final_conv.1.weight: int32 tensor",
        ] {
            assert!(message.contains(line), "{line:?} not in\n{message}");
        }
    }
}
