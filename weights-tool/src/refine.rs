//! Which int8 trunk layers get a second weight plane, measured: a residual-block
//! convolution of the trunk may store its rounding error quantized again
//! (`DType::I8Refined`, about 15-bit weights for twice the layer's integer products). The
//! trunk's weights set the rare large action differences of an int8 file (docs/METAWORLD.md:
//! with the trunk in f32 the door-open policy's largest difference fell 3.3x, with the
//! U-Net in f32 it did not move), and which layers matter depends on the weights, so the
//! tool measures the refinement on the calibration scenes' actions, against the f32 model
//! with the same noise draws, and keeps it only where it is needed to stay within a budget
//! of the file with every trunk layer refined.

use std::collections::BTreeMap;

use anyhow::Result;
use scdp_engine::ModelConfig;

use crate::activations::{ActionError, ActionMeasure, Budget};
use crate::run::RunInputs;
use crate::writer::Stored;

/// The layers that may be refined: those the lowering gave a residual plane (the trunk's
/// int8 residual-block convolutions).
pub fn candidates(stored: &BTreeMap<String, Stored>) -> Vec<String> {
    let has_residual = |tensor: &Stored| {
        matches!(
            tensor,
            Stored::Int8 {
                residual: Some(_),
                ..
            }
        )
    };
    stored
        .iter()
        .filter(|(_, tensor)| has_residual(tensor))
        .map(|(name, _)| name.clone())
        .collect()
}

/// Sets whether the int8 tensors `names` are written with their residual plane.
pub fn set_refined(stored: &mut BTreeMap<String, Stored>, names: &[String], value: bool) {
    for name in names {
        if let Some(Stored::Int8 {
            residual: Some(_),
            refined,
            ..
        }) = stored.get_mut(name)
        {
            *refined = value;
        }
    }
}

/// One candidate layer and what was found for it.
#[derive(Clone, Debug)]
pub struct LayerRefinement {
    pub name: String,
    /// The actions' error with only this layer refined.
    pub alone: ActionError,
    pub refined: bool,
}

/// What [`choose`] measured and chose.
#[derive(Clone, Debug)]
pub struct RefineReport {
    pub budget: Budget,
    pub scenes: usize,
    /// No layer refined.
    pub none: ActionError,
    /// Every candidate refined: the reference of the budget.
    pub all: ActionError,
    /// The chosen layers refined.
    pub chosen: ActionError,
    /// In the order their refinement was dropped or kept: least gain alone first.
    pub layers: Vec<LayerRefinement>,
}

/// Chooses which candidate layers of `stored` ([`candidates`]) are refined and sets them:
/// every candidate starts refined; in the order of what refining each alone gains on the
/// mean action difference (least first), a layer's refinement is dropped if the file without
/// it and the ones dropped before stays within `budget` of the file with every candidate
/// refined. Single layers gain little alone (the trunk's error comes from all of them), so
/// the choice is made on whole files, as [`crate::activations::choose`] makes its own.
/// `f32_file` is the same model in f32, the reference. `progress` is called after each
/// measured file with (done, total). Each file runs on `threads` threads (the same values
/// for any number).
pub fn choose(
    config: &ModelConfig,
    stored: &mut BTreeMap<String, Stored>,
    f32_file: &[u8],
    scenes: &[RunInputs],
    budget: Budget,
    threads: usize,
    progress: impl FnMut(usize, usize),
) -> Result<RefineReport> {
    let names = candidates(stored);
    let total = 2 * names.len() + 2;
    let mut measure = ActionMeasure::new(
        config,
        stored,
        (f32_file, scenes),
        (total, threads),
        progress,
    )?;
    set_refined(stored, &names, false);
    let none = measure.error(stored)?;
    let mut layers = Vec::with_capacity(names.len());
    for name in &names {
        let one = std::slice::from_ref(name);
        set_refined(stored, one, true);
        let alone = measure.error(stored)?;
        set_refined(stored, one, false);
        layers.push(LayerRefinement {
            name: name.clone(),
            alone,
            refined: true,
        });
    }
    layers.sort_by(|a, b| b.alone.mean.total_cmp(&a.alone.mean));
    set_refined(stored, &names, true);
    let all = measure.error(stored)?;
    let mut chosen = all;
    for layer in &mut layers {
        let one = std::slice::from_ref(&layer.name);
        set_refined(stored, one, false);
        let error = measure.error(stored)?;
        if budget.holds(&error, &all) {
            layer.refined = false;
            chosen = error;
        } else {
            set_refined(stored, one, true);
        }
    }
    Ok(RefineReport {
        budget,
        scenes: scenes.len(),
        none,
        all,
        chosen,
        layers,
    })
}
