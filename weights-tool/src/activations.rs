//! Which int8 layers quantize their input to narrow (8-bit) codes, measured: the residual
//! blocks' convolutions may read one byte a value instead of 15-bit codes (half the trunk's
//! integer products, docs/QUANTIZATION.md). What that costs depends on the weights, so the
//! tool measures it on the calibration scenes' actions, against the f32 model with the same
//! noise, and keeps the 15-bit codes only where they are needed to stay within a budget.

use std::collections::BTreeMap;

use anyhow::{Context, Result, ensure};
use scdp_engine::ModelConfig;
use scdp_engine::weights::{ActivationCodes, NarrowCodes};

use crate::run::{RunInputs, Runner};
use crate::writer::{Stored, tensor_specs, write_weights_file};

/// How far an int8 file's actions may move from the f32 model's on the calibration scenes,
/// in normalized action units (each action dimension times the normalizer's scale, so 1
/// is the training data's half range): the largest difference of any predicted action
/// value, and the mean of all of them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Budget {
    pub max: f64,
    pub mean: f64,
}

impl Budget {
    /// The project's int8 fidelity floor (docs/QUANTIZATION.md): max 0.02, mean 0.005.
    pub const DEFAULT: Budget = Budget {
        max: 0.02,
        mean: 0.005,
    };

    /// A budget of `max`, its mean in the floor's proportion (a quarter).
    pub fn with_max(max: f64) -> Budget {
        Budget {
            max,
            mean: max * Budget::DEFAULT.mean / Budget::DEFAULT.max,
        }
    }

    pub fn holds(&self, error: &ActionError) -> bool {
        error.max <= self.max && error.mean <= self.mean
    }
}

/// Differences between an int8 file's predicted actions and the f32 model's over the
/// calibration scenes, in normalized action units.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ActionError {
    pub max: f64,
    pub mean: f64,
}

impl std::fmt::Display for ActionError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "max {:.2e}, mean {:.2e}", self.max, self.mean)
    }
}

/// One layer that may read narrow codes, and what was found for it.
#[derive(Clone, Debug)]
pub struct LayerChoice {
    /// The weight tensor's name.
    pub name: String,
    /// The actions' error with only this layer narrow.
    pub alone: ActionError,
    pub codes: ActivationCodes,
}

/// What [`choose`] measured and chose.
#[derive(Clone, Debug)]
pub struct WidthReport {
    pub budget: Budget,
    pub scenes: usize,
    /// Every layer on 15-bit codes.
    pub wide: ActionError,
    /// The chosen mix.
    pub chosen: ActionError,
    /// In the order they were tried: least costly alone first.
    pub layers: Vec<LayerChoice>,
}

/// The int8 tensors of `stored` whose layers may read narrow codes, in file order.
pub fn narrow_candidates(
    config: &ModelConfig,
    stored: &BTreeMap<String, Stored>,
) -> Result<Vec<String>> {
    Ok(tensor_specs(config)?
        .into_iter()
        .filter(|spec| spec.narrow == NarrowCodes::Allowed)
        .filter(|spec| matches!(stored.get(&spec.name), Some(Stored::Int8 { .. })))
        .map(|spec| spec.name)
        .collect())
}

/// Sets the activation codes of the int8 tensors `names` (others keep theirs).
pub fn set_codes(stored: &mut BTreeMap<String, Stored>, names: &[String], codes: ActivationCodes) {
    for name in names {
        if let Some(Stored::Int8 { activations, .. }) = stored.get_mut(name) {
            *activations = codes;
        }
    }
}

/// Every candidate layer narrow ([`narrow_candidates`]); returns their names.
pub fn set_all_narrow(
    config: &ModelConfig,
    stored: &mut BTreeMap<String, Stored>,
) -> Result<Vec<String>> {
    let names = narrow_candidates(config, stored)?;
    set_codes(stored, &names, ActivationCodes::Narrow);
    Ok(names)
}

/// The predicted actions of a weights file on every scene, each with its own noise (the
/// scene's, or the engine's generator seeded with the scene's index).
fn actions(file: &[u8], scenes: &[RunInputs]) -> Result<Vec<Vec<f32>>> {
    let mut runner = Runner::new(file)?;
    scenes
        .iter()
        .enumerate()
        .map(|(index, scene)| Ok(runner.run(scene, index as u64)?.0.action_pred))
        .collect()
}

/// The error of `found` against `reference`, each value times its dimension's `scale`.
fn action_error(found: &[Vec<f32>], reference: &[Vec<f32>], scale: &[f32]) -> ActionError {
    let (mut max, mut sum, mut count) = (0.0f64, 0.0f64, 0usize);
    for (found, reference) in found.iter().zip(reference) {
        for (index, (a, b)) in found.iter().zip(reference).enumerate() {
            let difference = f64::from((a - b).abs() * scale[index % scale.len()]);
            // A NaN difference must not pass for a small one.
            max = if difference.is_nan() {
                f64::INFINITY
            } else {
                max.max(difference)
            };
            sum += difference;
            count += 1;
        }
    }
    ActionError {
        max,
        mean: if count == 0 { 0.0 } else { sum / count as f64 },
    }
}

/// Chooses the activation codes of every candidate layer of `stored` (int8, all wide on
/// entry) and sets them: the error of each layer narrow alone is measured, then layers are
/// made narrow in the order of that error, each kept narrow only if the file with it and
/// the ones kept before stays within `budget`. `f32_file` is the same model in f32, the
/// reference. `progress` is called after each measured file with (done, total).
pub fn choose(
    config: &ModelConfig,
    stored: &mut BTreeMap<String, Stored>,
    f32_file: &[u8],
    scenes: &[RunInputs],
    budget: Budget,
    mut progress: impl FnMut(usize, usize),
) -> Result<WidthReport> {
    ensure!(!scenes.is_empty(), "no calibration scenes to measure on");
    let scale = match stored.get("normalizer.action.scale") {
        Some(Stored::F32(values)) => values.clone(),
        _ => anyhow::bail!("internal: no f32 `normalizer.action.scale`"),
    };
    let candidates = narrow_candidates(config, stored)?;
    let total = 2 * candidates.len() + 1;
    let mut done = 0;
    let reference = actions(f32_file, scenes).context("the f32 model")?;
    let mut measure = |stored: &BTreeMap<String, Stored>| -> Result<ActionError> {
        let file = write_weights_file(config, stored)?;
        let error = action_error(&actions(&file, scenes)?, &reference, &scale);
        done += 1;
        progress(done, total);
        Ok(error)
    };
    set_codes(stored, &candidates, ActivationCodes::Wide);
    let wide = measure(stored)?;
    let mut layers = Vec::with_capacity(candidates.len());
    for name in &candidates {
        let one = std::slice::from_ref(name);
        set_codes(stored, one, ActivationCodes::Narrow);
        let alone = measure(stored)?;
        set_codes(stored, one, ActivationCodes::Wide);
        layers.push(LayerChoice {
            name: name.clone(),
            alone,
            codes: ActivationCodes::Wide,
        });
    }
    layers.sort_by(|a, b| a.alone.max.total_cmp(&b.alone.max));
    let mut chosen = wide;
    for layer in &mut layers {
        let one = std::slice::from_ref(&layer.name);
        set_codes(stored, one, ActivationCodes::Narrow);
        let error = measure(stored)?;
        if budget.holds(&error) {
            layer.codes = ActivationCodes::Narrow;
            chosen = error;
        } else {
            set_codes(stored, one, ActivationCodes::Wide);
        }
    }
    Ok(WidthReport {
        budget,
        scenes: scenes.len(),
        wide,
        chosen,
        layers,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn action_error_scales_each_dimension_and_refuses_nan() {
        let reference = vec![vec![0.0, 0.0, 1.0, 1.0]];
        let found = vec![vec![0.5, 0.0, 1.0, 3.0]];
        let error = action_error(&found, &reference, &[2.0, 10.0]);
        // Dimension 0 scaled by 2, dimension 1 by 10: differences 1.0, 0, 0, 20.
        assert_eq!(error.max, 20.0);
        assert_eq!(error.mean, 21.0 / 4.0);
        let nan = action_error(&[vec![f32::NAN]], &[vec![0.0]], &[1.0]);
        assert!(!Budget::DEFAULT.holds(&nan));
    }

    #[test]
    fn a_budget_holds_on_both_figures() {
        let budget = Budget::with_max(0.04);
        assert_eq!(budget.mean, 0.01);
        assert!(budget.holds(&ActionError {
            max: 0.04,
            mean: 0.01
        }));
        assert!(!budget.holds(&ActionError {
            max: 0.041,
            mean: 0.0
        }));
        assert!(!budget.holds(&ActionError {
            max: 0.0,
            mean: 0.011
        }));
    }
}
