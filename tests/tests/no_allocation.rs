//! The engine never allocates: a counting global allocator sees zero allocations from
//! loading the weights to reading the actions (the weights file and the arena are prepared
//! before counting starts, as firmware would have them in flash and in a static).

use scdp_engine::{ArenaPlan, Model, ModelConfig, Noise, Policy, Prefix};
use scdp_tests::{
    CountingAllocator, Fixture, allocations_during, golden_fixtures, synthetic_weights_file,
};
use weights_tool::writer::AlignedBytes;

#[global_allocator]
static ALLOCATOR: CountingAllocator = CountingAllocator;

#[test]
fn load_and_inference_allocate_nothing() {
    // Sanity: the counter does count.
    assert!(allocations_during(|| drop(std::hint::black_box(vec![1u8; 16]))) >= 1);

    for path in golden_fixtures()
        .into_iter()
        .filter(|p| !p.to_string_lossy().contains("panda"))
    {
        let fixture = Fixture::load(&path).unwrap();
        let config: ModelConfig = fixture.config;
        let weights = synthetic_weights_file(&config, fixture.seed).unwrap();
        let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
        let camera = fixture.camera().unwrap();
        let noise = fixture.f32s("noise");
        let state = fixture.f32s("state");
        let frames = config.n_obs_steps as usize;
        let frame_bytes = fixture.images.len() / frames;
        let state_dim = config.state_dim as usize;
        let prefix = fixture.prefix_actions();
        let planned = fixture.planned_actions();
        let mut first_actions = [f32::NAN; 3];
        let count = allocations_during(|| {
            let model = Model::from_bytes(weights.as_slice()).unwrap();
            let mut policy = Policy::new(&model, arena.as_mut_slice()).unwrap();
            policy.set_camera(camera);
            for frame in 0..frames {
                policy
                    .push_observation(
                        &fixture.images[frame * frame_bytes..][..frame_bytes],
                        &state[frame * state_dim..][..state_dim],
                    )
                    .unwrap();
            }
            // Both noise sources: given values and the engine's own generator.
            first_actions[0] = policy.infer(Noise::Given(&noise)).unwrap().action()[0];
            first_actions[1] = policy.infer(Noise::Seed(5)).unwrap().action()[0];
            // With the fixture's committed prefix and planned rows, if it has them.
            let held = Prefix::new(&prefix, fixture.prefix_mode).with_planned(&planned);
            first_actions[2] = policy.infer_with(Noise::Seed(5), held).unwrap().action()[0];
        });
        assert!(first_actions.iter().all(|a| a.is_finite()));
        assert_eq!(
            count,
            0,
            "{}: {count} allocations during load and inference",
            path.display()
        );
    }
}
