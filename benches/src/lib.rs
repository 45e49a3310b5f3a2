//! Benchmark set-up shared by the criterion benches: a model of a named configuration with
//! the seeded synthetic weights, loaded with its inputs from the golden fixture.

pub mod macs;
pub mod peak;

use scdp_engine::{ArenaPlan, Camera, ModelConfig};
use scdp_tests::{Fixture, synthetic_narrow_weights_file, synthetic_weights_file_as, tests_dir};
use weights_tool::Quant;
use weights_tool::writer::AlignedBytes;

/// Everything one benchmark needs, owned.
pub struct Setup {
    pub name: &'static str,
    pub config: ModelConfig,
    pub weights: AlignedBytes,
    pub arena: AlignedBytes,
    pub camera: Camera,
    pub images: Vec<u8>,
    pub state: Vec<f32>,
    pub noise: Vec<f32>,
}

impl Setup {
    /// `name` is a golden fixture folder: `tiny`, `metaworld` or `panda`; f32 weights.
    pub fn new(name: &'static str) -> Self {
        Self::new_as(name, Quant::F32)
    }

    /// [`Setup::new`] with weights stored at precision `quant`.
    pub fn new_as(name: &'static str, quant: Quant) -> Self {
        Self::with_weights(name, |config, seed| {
            synthetic_weights_file_as(config, seed, quant).expect("weights")
        })
    }

    /// [`Setup::new`] with int8 weights whose residual blocks read narrow (8-bit) codes.
    pub fn new_narrow(name: &'static str) -> Self {
        Self::with_weights(name, |config, seed| {
            synthetic_narrow_weights_file(config, seed).expect("weights")
        })
    }

    fn with_weights(
        name: &'static str,
        weights: impl FnOnce(&ModelConfig, u64) -> AlignedBytes,
    ) -> Self {
        let fixture =
            Fixture::load(&tests_dir().join(format!("fixtures/golden/{name}/basic.safetensors")))
                .expect("golden fixture");
        let config = fixture.config;
        Setup {
            name,
            config,
            weights: weights(&config, fixture.seed),
            arena: AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes),
            camera: fixture.camera().expect("camera"),
            images: fixture.images.clone(),
            state: fixture.f32s("state"),
            noise: fixture.f32s("noise"),
        }
    }

    pub fn frame(&self, index: usize) -> &[u8] {
        let frames = self.config.n_obs_steps as usize;
        let bytes = self.images.len() / frames;
        &self.images[index * bytes..][..bytes]
    }

    pub fn state(&self, index: usize) -> &[f32] {
        let dim = self.config.state_dim as usize;
        &self.state[index * dim..][..dim]
    }
}
