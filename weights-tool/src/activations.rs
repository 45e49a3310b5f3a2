//! Which int8 layers quantize their input to narrow (8-bit) codes, measured: the residual
//! blocks' convolutions, the trunk's and the U-Net's, may read one byte a value instead of
//! 15-bit codes (half the integer products where whole bytes are multiplied,
//! docs/QUANTIZATION.md). What that costs depends on the weights, so the
//! tool measures it on the calibration scenes' actions, against the f32 model with the same
//! noise draws, and keeps the 15-bit codes only where they are needed to stay within a budget.

use std::collections::BTreeMap;

use anyhow::{Context, Result, ensure};
use scdp_engine::ModelConfig;
use scdp_engine::weights::{ActivationCodes, NarrowCodes};

use crate::run::{RunInputs, Runner};
use crate::writer::{Stored, tensor_specs, write_weights_file};

/// How much the 8-bit codes may cost, measured on the calibration scenes' predicted
/// actions against the f32 model's, in normalized action units (each action dimension times
/// the normalizer's scale, so 1 is the training data's half range). The mean difference is
/// the measure: the largest difference over a few hundred inferences is set by rare chunks
/// that flip with any rounding (on the trained Meta-World policy the 15-bit file's own max
/// over 256 inferences was 1.97e-2, and single layers' 1.6e-2 to 2.8e-2 in no order of their
/// sensitivity), while the mean ranks the layers as the closed loop does.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Budget {
    /// The mean difference may exceed the 15-bit file's by this fraction of it.
    pub mean_increase: f64,
    /// And may not exceed this (the project's fidelity floor for the mean).
    pub mean_cap: f64,
}

impl Budget {
    /// 5% more mean error than 15-bit codes everywhere, within the floor's mean of 0.005.
    pub const DEFAULT: Budget = Budget {
        mean_increase: 0.05,
        mean_cap: 0.005,
    };

    /// The default budget with another allowed increase.
    pub fn with_increase(mean_increase: f64) -> Budget {
        Budget {
            mean_increase,
            ..Budget::DEFAULT
        }
    }

    /// Whether `error` is within the budget of a file whose 15-bit codes everywhere give
    /// `wide`.
    pub fn holds(&self, error: &ActionError, wide: &ActionError) -> bool {
        error.mean <= wide.mean * (1.0 + self.mean_increase) && error.mean <= self.mean_cap
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
    /// In the order they were tried: least mean error alone first.
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

/// Noise draws each calibration scene is denoised from: the mean error the choice is made
/// on is taken over `scenes x NOISE_DRAWS` inferences (256 for 32 scenes), over which it
/// ranked the trained Meta-World policy's layers as its closed loop does
/// (docs/QUANTIZATION.md).
pub const NOISE_DRAWS: usize = 8;

/// The predicted actions of a weights file on every scene, for [`NOISE_DRAWS`] noise seeds
/// each (the same seeds for every file), the scenes shared out over `threads` threads in
/// runs (each thread its own policy), the results in scene order: the same values for any
/// number of threads.
fn actions(file: &[u8], scenes: &[RunInputs], threads: usize) -> Result<Vec<Vec<f32>>> {
    let threads = threads.clamp(1, scenes.len().max(1));
    let run = |first: usize, scenes: &[RunInputs]| -> Result<Vec<Vec<f32>>> {
        let mut runner = Runner::new(file)?;
        let mut all = Vec::with_capacity(scenes.len() * NOISE_DRAWS);
        for (offset, scene) in scenes.iter().enumerate() {
            let index = first + offset;
            let seeds: Vec<u64> = (0..NOISE_DRAWS)
                .map(|draw| (index * NOISE_DRAWS + draw) as u64)
                .collect();
            all.extend(runner.action_preds(scene, &seeds)?);
        }
        Ok(all)
    };
    if threads == 1 {
        return run(0, scenes);
    }
    let share = |thread: usize| scenes.len() * thread / threads;
    let parts: Vec<Result<Vec<Vec<f32>>>> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..threads)
            .map(|thread| {
                let (first, end) = (share(thread), share(thread + 1));
                scope.spawn(move || run(first, &scenes[first..end]))
            })
            .collect();
        handles
            .into_iter()
            .map(|handle| handle.join().expect("a measuring thread panicked"))
            .collect()
    });
    let mut all = Vec::with_capacity(scenes.len() * NOISE_DRAWS);
    for part in parts {
        all.extend(part?);
    }
    Ok(all)
}

/// The error of `found` against `reference`, each value times its dimension's `scale`.
pub(crate) fn action_error(
    found: &[Vec<f32>],
    reference: &[Vec<f32>],
    scale: &[f32],
) -> ActionError {
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

/// Measures int8 files' predicted actions on the calibration scenes against the f32 model's
/// ([`action_error`]), reporting each measured file to `progress` as (done, total).
pub(crate) struct ActionMeasure<'s, P> {
    config: &'s ModelConfig,
    scenes: &'s [RunInputs],
    reference: Vec<Vec<f32>>,
    scale: Vec<f32>,
    threads: usize,
    done: usize,
    total: usize,
    progress: P,
}

impl<'s, P: FnMut(usize, usize)> ActionMeasure<'s, P> {
    /// Runs the f32 model (`f32_file`) on `scenes`; `stored` gives the action scale, `total`
    /// the number of files that will be measured; every file runs on `threads` threads.
    pub(crate) fn new(
        config: &'s ModelConfig,
        stored: &BTreeMap<String, Stored>,
        (f32_file, scenes): (&[u8], &'s [RunInputs]),
        (total, threads): (usize, usize),
        progress: P,
    ) -> Result<Self> {
        ensure!(!scenes.is_empty(), "no calibration scenes to measure on");
        let scale = match stored.get("normalizer.action.scale") {
            Some(Stored::F32(values)) => values.clone(),
            _ => anyhow::bail!("internal: no f32 `normalizer.action.scale`"),
        };
        let reference = actions(f32_file, scenes, threads).context("the f32 model")?;
        Ok(ActionMeasure {
            config,
            scenes,
            reference,
            scale,
            threads,
            done: 0,
            total,
            progress,
        })
    }

    /// The error of the file `stored` makes.
    pub(crate) fn error(&mut self, stored: &BTreeMap<String, Stored>) -> Result<ActionError> {
        let file = write_weights_file(self.config, stored)?;
        let found = actions(&file, self.scenes, self.threads)?;
        let error = action_error(&found, &self.reference, &self.scale);
        self.done += 1;
        (self.progress)(self.done, self.total);
        Ok(error)
    }
}

/// Chooses the activation codes of every candidate layer of `stored` (int8, all wide on
/// entry) and sets them: the mean error of each layer narrow alone is measured, then layers
/// are made narrow in the order of that error, each kept narrow only if the file with it
/// and the ones kept before stays within `budget`; none if the file with 15-bit codes
/// everywhere is already over its cap. `f32_file` is the same model in f32, the
/// reference. `progress` is called after each measured file with (done, total). Each file
/// runs on `threads` threads (the same values for any number).
pub fn choose(
    config: &ModelConfig,
    stored: &mut BTreeMap<String, Stored>,
    f32_file: &[u8],
    scenes: &[RunInputs],
    budget: Budget,
    threads: usize,
    progress: impl FnMut(usize, usize),
) -> Result<WidthReport> {
    let candidates = narrow_candidates(config, stored)?;
    let total = 2 * candidates.len() + 1;
    let mut measure = ActionMeasure::new(
        config,
        stored,
        (f32_file, scenes),
        (total, threads),
        progress,
    )?;
    set_codes(stored, &candidates, ActivationCodes::Wide);
    let wide = measure.error(stored)?;
    let mut layers = Vec::with_capacity(candidates.len());
    for name in &candidates {
        let one = std::slice::from_ref(name);
        set_codes(stored, one, ActivationCodes::Narrow);
        let alone = measure.error(stored)?;
        set_codes(stored, one, ActivationCodes::Wide);
        layers.push(LayerChoice {
            name: name.clone(),
            alone,
            codes: ActivationCodes::Wide,
        });
    }
    layers.sort_by(|a, b| a.alone.mean.total_cmp(&b.alone.mean));
    let mut chosen = wide;
    // Over the cap with 15-bit codes everywhere, the file stays wide.
    let trials = if budget.holds(&wide, &wide) {
        &mut layers[..]
    } else {
        &mut []
    };
    for layer in trials {
        let one = std::slice::from_ref(&layer.name);
        set_codes(stored, one, ActivationCodes::Narrow);
        let error = measure.error(stored)?;
        if budget.holds(&error, &wide) {
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
        let wide = ActionError {
            max: 0.0,
            mean: 1e-3,
        };
        assert!(!Budget::DEFAULT.holds(&nan, &wide));
    }

    #[test]
    fn a_budget_bounds_the_mean_relative_to_wide_codes_and_caps_it() {
        let budget = Budget::with_increase(0.25);
        let wide = ActionError {
            max: 0.1,
            mean: 0.002,
        };
        let at = |mean| ActionError { max: 1.0, mean };
        assert!(budget.holds(&at(0.0025), &wide));
        assert!(!budget.holds(&at(0.00251), &wide));
        // The cap: a file whose 15-bit codes already reach 0.0045 may not pass 0.005.
        let wide = ActionError {
            max: 0.1,
            mean: 0.0045,
        };
        assert!(budget.holds(&at(0.005), &wide));
        assert!(!budget.holds(&at(0.0051), &wide));
    }
}
