//! Latency of every kernel backend this CPU runs, interleaved: one policy per backend on
//! the same weights and frames, each repetition running every backend once in turn, so a
//! shared machine's slow and fast spells fall on all of them alike and the ratios of the
//! medians stay meaningful where the absolute figures drift.
//!
//! `cargo run --release -p scdp-benches --bin latency -- CONFIG [f32|int8] [REPETITIONS]`
//! (CONFIG: `metaworld`, `panda` or `tiny`). With `int8`, two files take turns: every layer
//! on 15-bit activation codes (the precise scheme) and every residual-block layer on 8-bit
//! codes (the fast file). Per backend and file, medians in ms of:
//! - `encode`: one frame (`push_observation`);
//! - `denoise`: the 10-step loop with every on-demand projection cell already cached;
//! - `streaming`: the newest frame, then the loop (older frames encoded on arrival; cells
//!   of the new frame computed on demand);
//! - `end to end`: every history frame, then the loop (a cold start).

use std::time::Instant;

use scdp_benches::Setup;
use scdp_engine::{ArenaPlan, Backend, Model, Noise, Policy};
use weights_tool::Quant;
use weights_tool::writer::AlignedBytes;

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

fn main() {
    let arguments: Vec<String> = std::env::args().skip(1).collect();
    let name = match arguments.first().map(String::as_str) {
        Some("metaworld") => "metaworld",
        Some("tiny") => "tiny",
        _ => "panda",
    };
    let quant = match arguments.get(1).map(String::as_str) {
        Some("f32") => Quant::F32,
        _ => Quant::Int8,
    };
    let repetitions: usize = arguments.get(2).and_then(|r| r.parse().ok()).unwrap_or(15);
    let setup = Setup::new_as(name, quant);
    let narrow = (quant == Quant::Int8).then(|| Setup::new_narrow(name));
    let mut models = vec![(
        if quant == Quant::Int8 { " 15-bit" } else { "" },
        Model::from_bytes(setup.weights.as_slice()).expect("model"),
    )];
    if let Some(narrow) = &narrow {
        models.push((
            " 8-bit",
            Model::from_bytes(narrow.weights.as_slice()).expect("model"),
        ));
    }
    let frames = setup.config.n_obs_steps as usize;
    let backends: Vec<Backend> = [
        Backend::Scalar,
        Backend::Avx2,
        Backend::Avx512,
        Backend::Amx,
    ]
    .into_iter()
    .filter(|&backend| scdp_engine::kernels::select(backend).is_some())
    // The scalar reference is ten times slower: on the small model only.
    .filter(|&backend| backend != Backend::Scalar || name == "tiny")
    .collect();
    let plan = ArenaPlan::new(&setup.config);
    let runs: Vec<(&str, &Model, Backend)> = backends
        .iter()
        .flat_map(|&backend| {
            models
                .iter()
                .map(move |(label, model)| (*label, model, backend))
        })
        .collect();
    let mut arenas: Vec<AlignedBytes> = runs
        .iter()
        .map(|_| AlignedBytes::zeroed(plan.arena_bytes))
        .collect();
    let mut policies: Vec<(&str, Policy)> = arenas
        .iter_mut()
        .zip(&runs)
        .map(|(arena, &(label, model, backend))| {
            let mut policy =
                Policy::with_backend(model, arena.as_mut_slice(), backend).expect("backend");
            policy.set_camera(setup.camera);
            (label, policy)
        })
        .collect();
    // Per run: encode, denoise, streaming, end to end.
    let mut times = vec![[vec![], vec![], vec![], vec![]]; runs.len()];
    let milliseconds = |start: Instant| start.elapsed().as_secs_f64() * 1e3;
    for repetition in 0..=repetitions {
        for ((_, policy), times) in policies.iter_mut().zip(&mut times) {
            policy.reset();
            let start = Instant::now();
            for frame in 0..frames {
                policy
                    .push_observation(setup.frame(frame), setup.state(frame))
                    .expect("frame");
            }
            std::hint::black_box(policy.infer(Noise::Given(&setup.noise)).expect("infer"));
            let end_to_end = milliseconds(start);
            let start = Instant::now();
            std::hint::black_box(policy.infer(Noise::Given(&setup.noise)).expect("infer"));
            let denoise = milliseconds(start);
            let start = Instant::now();
            let newest = frames - 1;
            policy
                .push_observation(setup.frame(newest), setup.state(newest))
                .expect("frame");
            let encode = milliseconds(start);
            std::hint::black_box(policy.infer(Noise::Given(&setup.noise)).expect("infer"));
            let streaming = milliseconds(start);
            // The first repetition warms the caches and the tile state up.
            if repetition > 0 {
                for (series, value) in times
                    .iter_mut()
                    .zip([encode, denoise, streaming, end_to_end])
                {
                    series.push(value);
                }
            }
        }
    }
    println!(
        "{name}, {quant} weights, medians of {repetitions} interleaved repetitions, one thread, ms"
    );
    println!("| kernels | encode | denoise | streaming | end to end |");
    println!("|---|---:|---:|---:|---:|");
    for ((label, policy), times) in policies.iter().zip(&mut times) {
        let [encode, denoise, streaming, end_to_end] = times.each_mut().map(|s| median(s));
        println!(
            "| {}{label} | {encode:.2} | {denoise:.2} | {streaming:.2} | {end_to_end:.2} |",
            policy.kernels_name()
        );
    }
}
