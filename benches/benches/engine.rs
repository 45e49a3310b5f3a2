//! Per-stage and end-to-end latency of the f32 engine, one thread, on the scalar reference
//! kernels and on the fastest this CPU supports, in the same run:
//! `cargo bench -p scdp-benches --bench engine`.
//!
//! - `encode`: one frame through preprocessing, the ResNet-18 trunk and the projections;
//! - `denoise`: the whole 10-step loop (anchors, context, U-Net, DDIM) on a full history
//!   (also with an int8 weights file: the U-Net's weight-only int8 kernels);
//! - `end_to_end`: every frame of the history encoded, then the loop (a cold start);
//! - `streaming`: the newest frame encoded, then the loop (steady state: older frames were
//!   encoded when they arrived).

use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use scdp_benches::Setup;
use scdp_engine::{Backend, Model, Noise, Policy};
use scdp_tests::synthetic_weights_file_as;
use weights_tool::Quant;

fn bench_config(c: &mut Criterion, name: &'static str, backend: Backend) {
    let mut setup = Setup::new(name);
    let model = Model::from_bytes(setup.weights.as_slice()).expect("model");
    let frames = setup.config.n_obs_steps as usize;
    let camera = setup.camera;
    let (images, state, noise) = (
        setup.images.clone(),
        setup.state.clone(),
        setup.noise.clone(),
    );
    let config = setup.config;
    let frame_bytes = images.len() / frames;
    let state_dim = config.state_dim as usize;
    let frame = |i: usize| &images[i * frame_bytes..][..frame_bytes];
    let state_of = |i: usize| &state[i * state_dim..][..state_dim];
    let mut policy =
        Policy::with_backend(&model, setup.arena.as_mut_slice(), backend).expect("backend");
    policy.set_camera(camera);
    for i in 0..frames {
        policy
            .push_observation(frame(i), state_of(i))
            .expect("frame");
    }

    let mut group = c.benchmark_group(format!("f32_{}/{}", policy.kernels_name(), setup.name));
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(5));
    group.bench_function("encode", |b| {
        b.iter(|| {
            policy
                .push_observation(black_box(frame(frames - 1)), state_of(frames - 1))
                .unwrap()
        })
    });
    group.bench_function("denoise", |b| {
        b.iter(|| black_box(policy.infer(Noise::Given(&noise)).unwrap().action()[0]))
    });
    group.bench_function("streaming", |b| {
        b.iter(|| {
            policy
                .push_observation(black_box(frame(frames - 1)), state_of(frames - 1))
                .unwrap();
            black_box(policy.infer(Noise::Given(&noise)).unwrap().action()[0])
        })
    });
    group.bench_function("end_to_end", |b| {
        b.iter(|| {
            policy.reset();
            for i in 0..frames {
                policy
                    .push_observation(black_box(frame(i)), state_of(i))
                    .unwrap();
            }
            black_box(policy.infer(Noise::Given(&noise)).unwrap().action()[0])
        })
    });
    group.finish();
}

/// The denoising loop with weight-only int8 U-Net weights (the same inputs as the f32 group).
fn bench_int8_denoise(c: &mut Criterion, name: &'static str, backend: Backend) {
    let Setup {
        config,
        mut arena,
        camera,
        images,
        state,
        noise,
        ..
    } = Setup::new(name);
    let weights = synthetic_weights_file_as(&config, 0, Quant::Int8).expect("int8 weights");
    let model = Model::from_bytes(weights.as_slice()).expect("model");
    let mut policy = Policy::with_backend(&model, arena.as_mut_slice(), backend).expect("backend");
    policy.set_camera(camera);
    let frames = config.n_obs_steps as usize;
    let state_dim = config.state_dim as usize;
    for (frame, state) in images
        .chunks_exact(images.len() / frames)
        .zip(state.chunks_exact(state_dim))
    {
        policy.push_observation(frame, state).expect("frame");
    }
    let mut group = c.benchmark_group(format!("int8_{}/{name}", policy.kernels_name()));
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(5));
    group.bench_function("denoise", |b| {
        b.iter(|| black_box(policy.infer(Noise::Given(&noise)).unwrap().action()[0]))
    });
    group.finish();
}

fn benches(c: &mut Criterion) {
    for backend in [Backend::Scalar, Backend::Auto] {
        for name in ["metaworld", "panda"] {
            bench_config(c, name, backend);
            bench_int8_denoise(c, name, backend);
        }
    }
}

criterion_group!(engine, benches);
criterion_main!(engine);
