//! A policy on a pool of worker threads creates no thread and allocates nothing per
//! inference (its own binary: the counting allocator and the thread count see the whole
//! process).

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use scdp_engine::{ArenaPlan, Model, Noise, Policy};
use scdp_tests::{Fixture, golden_fixtures, synthetic_narrow_weights_file};
use scdp_threads::ThreadPool;
use weights_tool::writer::AlignedBytes;

struct CountingAllocator;

static COUNTING: AtomicBool = AtomicBool::new(false);
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards every call unchanged to the system allocator; it only counts.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if COUNTING.load(Ordering::SeqCst) {
            ALLOCATIONS.fetch_add(1, Ordering::SeqCst);
        }
        // SAFETY: the caller's contract for `alloc` is passed on as is.
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System.alloc` with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if COUNTING.load(Ordering::SeqCst) {
            ALLOCATIONS.fetch_add(1, Ordering::SeqCst);
        }
        // SAFETY: the caller's contract for `realloc` is passed on as is.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

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
    ALLOCATIONS.store(0, Ordering::SeqCst);
    COUNTING.store(true, Ordering::SeqCst);
    drop(std::hint::black_box(vec![1u8; 16]));
    let sanity = ALLOCATIONS.swap(0, Ordering::SeqCst);
    for _ in 0..5 {
        actions.push(infer(&mut policy));
    }
    COUNTING.store(false, Ordering::SeqCst);
    let allocations = ALLOCATIONS.load(Ordering::SeqCst);
    assert!(sanity >= 1, "the allocation counter counts nothing");
    assert_eq!(allocations, 0, "five inferences on a pool allocated");
    assert_eq!(threads(), before, "inferences created threads");
    assert!(
        actions
            .iter()
            .all(|&action| action.to_bits() == first.to_bits())
    );
}
