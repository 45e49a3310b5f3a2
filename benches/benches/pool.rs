//! What handing work to the other threads costs, as the engine does it some 500 times an
//! inference: `cargo bench -p scdp-benches --bench pool`.
//! - one `ThreadPool::run` call of 2 pieces that do nothing, on 2 threads (the calling one
//!   and one spinning for the call);
//! - a layer's worth of data passed between cores: the calling thread writes a buffer (as
//!   GroupNorm or the quantization of a layer's input do, on the caller), then each of the
//!   2 threads sums its half (as a convolution's pieces read their input), against one
//!   thread writing it and summing all of it;
//! - weights streamed from L3, as the denoising loop's layers read theirs (14.9 MB a step
//!   for door-open's int8 file): a 16 MiB buffer that nobody writes, summed by one thread,
//!   against each of 2 threads summing its half.

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use scdp_threads::{ThreadPool, Workers};

/// Buffer sizes: a U-Net layer's input codes up to a trunk map's f32 values.
const SIZES_KB: [usize; 3] = [8, 32, 128];

// Integers, so that both loops run at the cores' vector speed (an f32 sum in order would
// not) and the cost measured is the data's.
fn write(buffer: &mut [u32], value: u32) {
    for (index, x) in buffer.iter_mut().enumerate() {
        *x = value.wrapping_add(index as u32);
    }
}

fn sum(values: &[u32]) -> u32 {
    values.iter().fold(0, |sum, &x| sum.wrapping_add(x))
}

fn pool(criterion: &mut Criterion) {
    let pool = ThreadPool::new(2).expect("a thread");
    criterion.bench_function("pool/2 threads, 2 empty pieces", |bench| {
        bench.iter(|| {
            pool.run(2, &|piece| {
                std::hint::black_box(piece);
            });
        });
    });
    let mut group = criterion.benchmark_group("pool/write then read, KB");
    for kb in SIZES_KB {
        let mut buffer = vec![0u32; kb * 256];
        let half = buffer.len() / 2;
        let mut round = 0u32;
        group.bench_with_input(BenchmarkId::new("1 thread", kb), &kb, |bench, _| {
            bench.iter(|| {
                round = round.wrapping_add(1);
                write(&mut buffer, round);
                std::hint::black_box(sum(&buffer));
            });
        });
        group.bench_with_input(BenchmarkId::new("2 threads", kb), &kb, |bench, _| {
            bench.iter(|| {
                round = round.wrapping_add(1);
                write(&mut buffer, round);
                let values = &buffer;
                pool.run(2, &|piece| {
                    std::hint::black_box(sum(&values[piece * half..][..half]));
                });
            });
        });
    }
    group.finish();
    let mut group = criterion.benchmark_group("pool/read once, MiB");
    let weights: Vec<u32> = (0..16 << 18).collect();
    let half = weights.len() / 2;
    group.bench_function("1 thread, 16", |bench| {
        bench.iter(|| std::hint::black_box(sum(&weights)));
    });
    group.bench_function("2 threads, 16", |bench| {
        bench.iter(|| {
            pool.run(2, &|piece| {
                std::hint::black_box(sum(&weights[piece * half..][..half]));
            });
        });
    });
    group.finish();
}

criterion_group!(benches, pool);
criterion_main!(benches);
