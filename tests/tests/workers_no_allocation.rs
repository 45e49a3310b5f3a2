//! A policy on a pool of worker threads creates no thread and allocates nothing per
//! inference (its own binary: the counting allocator and the thread count see the whole
//! process).

use scdp_engine::{ArenaPlan, Model, Noise, Policy};
use scdp_tests::{
    CountingAllocator, Fixture, allocations_during, golden_fixtures, synthetic_narrow_weights_file,
};
use scdp_threads::ThreadPool;
use weights_tool::writer::AlignedBytes;

#[global_allocator]
static ALLOCATOR: CountingAllocator = CountingAllocator;

/// Threads of this process, as the OS counts them.
fn threads() -> usize {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    let line = status
        .lines()
        .find(|line| line.starts_with("Threads:"))
        .unwrap();
    line["Threads:".len()..].trim().parse().unwrap()
}

#[test]
fn inferences_on_a_pool_create_no_thread_and_allocate_nothing() {
    let path = golden_fixtures()
        .into_iter()
        .find(|path| path.to_string_lossy().contains("metaworld"))
        .unwrap();
    let fixture = Fixture::load(&path).unwrap();
    let config = fixture.config;
    let weights = synthetic_narrow_weights_file(&config, fixture.seed).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
    let camera = fixture.camera().unwrap();
    let state = fixture.f32s("state");
    let noise = fixture.f32s("noise");
    let frames = config.n_obs_steps as usize;
    let frame_bytes = fixture.images.len() / frames;
    let state_dim = config.state_dim as usize;
    let pool = ThreadPool::new(3).unwrap();
    let model = Model::from_bytes(weights.as_slice()).unwrap();
    let mut policy = Policy::new(&model, arena.as_mut_slice())
        .unwrap()
        .with_workers(&pool);
    policy.set_camera(camera);
    let infer = |policy: &mut Policy<'_, '_>| {
        for frame in 0..frames {
            policy
                .push_observation(
                    &fixture.images[frame * frame_bytes..][..frame_bytes],
                    &state[frame * state_dim..][..state_dim],
                )
                .unwrap();
        }
        policy.infer(Noise::Given(&noise)).unwrap().action()[0]
    };
    // Sanity: the pool's threads exist, and the counter counts.
    let before = threads();
    assert!(before >= 3, "{before} threads with a pool of three workers");
    let first = infer(&mut policy);
    let mut actions = Vec::with_capacity(5);
    let sanity = allocations_during(|| drop(std::hint::black_box(vec![1u8; 16])));
    let allocations = allocations_during(|| {
        for _ in 0..5 {
            actions.push(infer(&mut policy));
        }
    });
    assert!(sanity >= 1, "the allocation counter counts nothing");
    assert_eq!(allocations, 0, "five inferences on a pool allocated");
    assert_eq!(threads(), before, "inferences created threads");
    assert!(
        actions
            .iter()
            .all(|&action| action.to_bits() == first.to_bits())
    );
}
