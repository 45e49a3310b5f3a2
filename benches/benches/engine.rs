//! Per-stage and end-to-end latency of the engine, one thread, in the same run: f32 and int8
//! weights on the scalar reference kernels and on each SIMD backend this CPU can run (groups
//! `<precision>_<kernels>/<config>`): `cargo bench -p scdp-benches --bench engine`, or
//! `-- encode` for the trunk alone.
//!
//! - `encode`: one frame through preprocessing, the ResNet-18 trunk and the projections of
//!   the small levels (large levels are projected on demand, during inference);
//! - `denoise`: the whole 10-step loop (anchors, context, U-Net, DDIM) on a full history;
//! - `end_to_end`: every frame of the history encoded, then the loop (a cold start);
//! - `streaming`: the newest frame encoded, then the loop (steady state: older frames were
//!   encoded when they arrived). The older frame's on-demand cells are already cached from
//!   the previous iteration, as they are in a control loop when the anchors stay put.

use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use scdp_benches::Setup;
use scdp_engine::{Backend, Model, Noise, Policy};
use weights_tool::Quant;

fn bench_config(c: &mut Criterion, name: &'static str, quant: Quant, backend: Backend) {
    let mut setup = Setup::new_as(name, quant);
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

    let mut group = c.benchmark_group(format!("{quant}_{}/{}", policy.kernels_name(), setup.name));
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

fn benches(c: &mut Criterion) {
    let int8_backends = [
        Backend::Scalar,
        Backend::Avx2,
        Backend::Avx512,
        Backend::Amx,
    ];
    for (quant, backends) in [
        (
            Quant::F32,
            &[Backend::Scalar, Backend::Avx2, Backend::Avx512][..],
        ),
        (Quant::Int8, &int8_backends[..]),
    ] {
        for &backend in backends {
            if scdp_engine::kernels::select(backend).is_none() {
                continue;
            }
            for name in ["metaworld", "panda"] {
                bench_config(c, name, quant, backend);
            }
        }
    }
}

criterion_group!(engine, benches);
criterion_main!(engine);
