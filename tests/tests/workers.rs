//! An inference cut over several workers gives the bits of one worker: every golden config
//! (its synthetic f32 file, its int8 file on 15-bit codes and its int8 file on 8-bit codes),
//! on every kernel backend, for 2, 3 and 5 workers (so the pieces are uneven and some are
//! empty), the actions, every step's intermediates and every projected map.

use scdp_engine::Backend;
use scdp_engine::kernels::{Sequential, Workers};
use scdp_tests::{
    EngineRun, Fixture, available_backends, golden_fixtures, run_engine_on,
    synthetic_narrow_weights_file, synthetic_weights_file_as,
};
use scdp_threads::ThreadPool;
use weights_tool::Quant;

fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|value| value.to_bits()).collect()
}

/// Everything a run produced, as bits.
fn run_bits(run: &EngineRun) -> Vec<Vec<u32>> {
    let recorded = &run.recorded;
    let steps = [
        &recorded.anchors_uv,
        &recorded.global_cond,
        &recorded.eps,
        &recorded.sample,
    ];
    let maps = run.feature_maps.iter().flatten();
    [bits(&run.action_pred)]
        .into_iter()
        .chain(steps.into_iter().flatten().map(|values| bits(values)))
        .chain(maps.map(|map| bits(map)))
        .collect()
}

#[test]
fn any_number_of_workers_gives_the_bits_of_one() {
    let pools: Vec<ThreadPool> = [2, 3, 5]
        .into_iter()
        .map(|count| ThreadPool::new(count).unwrap())
        .collect();
    let mut checked = 0;
    for path in golden_fixtures() {
        let fixture = Fixture::load(&path).unwrap();
        // One case per config: the workers cut layers, whatever the inputs.
        if !path.ends_with("basic.safetensors") {
            continue;
        }
        let config = fixture.config;
        let files = [
            (
                "f32",
                synthetic_weights_file_as(&config, fixture.seed, Quant::F32),
            ),
            (
                "int8",
                synthetic_weights_file_as(&config, fixture.seed, Quant::Int8),
            ),
            (
                "int8 narrow",
                synthetic_narrow_weights_file(&config, fixture.seed),
            ),
        ];
        for (name, file) in files {
            let file = file.unwrap();
            for backend in available_backends() {
                // The scalar reference on panda takes most of a minute a file; its pieces
                // are cut by the same code as the SIMD backends' (`Split` wraps any).
                if backend == Backend::Scalar && config.image_height > 128 {
                    continue;
                }
                let one = run_engine_on(file.as_slice(), &fixture, backend, &Sequential).unwrap();
                let one = run_bits(&one);
                for pool in &pools {
                    let many = run_engine_on(file.as_slice(), &fixture, backend, pool).unwrap();
                    assert!(
                        run_bits(&many) == one,
                        "{}: {name} on {backend:?} with {} workers differs from one worker",
                        path.display(),
                        pool.count()
                    );
                    checked += 1;
                }
            }
        }
    }
    assert!(checked >= 3 * 3 * 3, "only {checked} cases ran");
}
