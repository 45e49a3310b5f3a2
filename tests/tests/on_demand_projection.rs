//! "Don't compute what is never read": large 3x3 projections are evaluated only at
//! the cells the anchors sample, cached per frame. The actions must be exactly those of the
//! dense maps: a policy whose maps were completed before the inference (every cell, through
//! `Policy::feature_map`) and one that computed cells on demand give the same bits, on every
//! backend, for f32 and int8 weights. The golden tests check the completed maps against
//! PyTorch.

use scdp_engine::{ArenaPlan, Model, ModelConfig, Noise, Policy, config::PYRAMID_LEVELS};
use scdp_tests::{Fixture, available_backends, synthetic_weights_file_as, tests_dir};
use weights_tool::Quant;
use weights_tool::writer::AlignedBytes;

fn action_bits(
    fixture: &Fixture,
    weights: &[u8],
    backend: scdp_engine::Backend,
    complete_first: bool,
) -> Vec<u32> {
    let model = Model::from_bytes(weights).unwrap();
    let config = *model.config();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
    let mut policy = Policy::with_backend(&model, arena.as_mut_slice(), backend).unwrap();
    policy.set_camera(fixture.camera().unwrap());
    let frames = config.n_obs_steps as usize;
    let frame_bytes = fixture.images.len() / frames;
    let state = fixture.f32s("state");
    let state_dim = config.state_dim as usize;
    for frame in 0..frames {
        policy
            .push_observation(
                &fixture.images[frame * frame_bytes..][..frame_bytes],
                &state[frame * state_dim..][..state_dim],
            )
            .unwrap();
    }
    if complete_first {
        for frame in 0..frames {
            for level in 0..PYRAMID_LEVELS {
                assert!(policy.feature_map(frame, level).is_some());
            }
        }
    }
    let noise = fixture.f32s("noise");
    let actions = policy.infer(Noise::Given(&noise)).unwrap();
    actions.action_pred().iter().map(|v| v.to_bits()).collect()
}

#[test]
fn on_demand_projections_give_the_dense_maps_actions() {
    for name in ["metaworld", "panda"] {
        let path = tests_dir().join(format!("fixtures/golden/{name}/edge.safetensors"));
        let fixture = Fixture::load(&path).unwrap();
        let config: ModelConfig = fixture.config;
        // Otherwise this test would test nothing.
        assert!(
            (0..PYRAMID_LEVELS).any(|level| config.projection_on_demand(level)),
            "{name} has no on-demand level"
        );
        for quant in [Quant::F32, Quant::Int8] {
            let weights = synthetic_weights_file_as(&config, fixture.seed, quant).unwrap();
            for backend in available_backends() {
                let lazy = action_bits(&fixture, weights.as_slice(), backend, false);
                let dense = action_bits(&fixture, weights.as_slice(), backend, true);
                assert_eq!(lazy, dense, "{name} {quant:?} {backend:?}");
            }
        }
    }
}
