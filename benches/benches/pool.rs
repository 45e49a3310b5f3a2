//! What handing work to the other threads costs: one `ThreadPool::run` call of pieces that
//! do nothing, on 2 threads (the calling one and one spinning for the call), as the engine
//! makes some 500 of an inference: `cargo bench -p scdp-benches --bench pool`.

use criterion::{Criterion, criterion_group, criterion_main};
use scdp_threads::{ThreadPool, Workers};

fn pool(criterion: &mut Criterion) {
    let pool = ThreadPool::new(2).expect("a thread");
    criterion.bench_function("pool/2 threads, 2 empty pieces", |bench| {
        bench.iter(|| {
            pool.run(2, &|piece| {
                std::hint::black_box(piece);
            });
        });
    });
}

criterion_group!(benches, pool);
criterion_main!(benches);
