//! The engine's `Board` on real threads: the first piece to start runs the chain, the others
//! take the pieces of its calls and its background chunks; every piece and every chunk runs
//! exactly once, each chunk's values are complete when the chain collects them, and any
//! `Workers` (one core running the pieces backwards included) runs it to the end.

use std::sync::atomic::{AtomicUsize, Ordering};

use scdp_engine::kernels::{Board, Workers};
use scdp_threads::ThreadPool;

/// One core running the pieces last first: the helpers start before the chain, and find it
/// done.
struct Backwards(usize);

impl Workers for Backwards {
    fn count(&self) -> usize {
        self.0
    }

    fn run(&self, pieces: usize, work: &(dyn Fn(usize) + Sync)) {
        (0..pieces).rev().for_each(work)
    }
}

/// A step like the denoiser's: chunks of background values posted, then calls cut into
/// pieces, each collecting the chunks it needs first. Returns the sum of the values the
/// chain read (each chunk's values are its index + 1) and how often each piece ran.
fn step(workers: &dyn Workers, calls: usize, chunks: usize) -> (f64, Vec<usize>) {
    let per_chunk = 7;
    let ranges: Vec<_> = (0..chunks)
        .map(|c| c * per_chunk..(c + 1) * per_chunk)
        .collect();
    let mut output = vec![0.0f32; chunks * per_chunk];
    let ran: Vec<AtomicUsize> = (0..calls * workers.count())
        .map(|_| AtomicUsize::new(0))
        .collect();
    let mut read = 0.0f64;
    Board::lead(workers, |board| {
        let work = |chunk: usize, values: &mut [f32]| {
            // A little work, so the helpers and the chain overlap.
            let value = (0..200).fold(chunk as f32, |acc, _| std::hint::black_box(acc)) + 1.0;
            values.fill(value);
        };
        board.with_background(&mut output, &ranges, &work, |board, collected| {
            for call in 0..calls {
                let wanted = (call * chunks / calls.max(1)).min(chunks - 1);
                let values = collected.complete(wanted);
                assert_eq!(values.len(), (wanted + 1) * per_chunk);
                read += values.iter().map(|&v| v as f64).sum::<f64>();
                let pieces = board.count();
                board.run(pieces, &|piece| {
                    ran[call * pieces + piece].fetch_add(1, Ordering::Relaxed);
                });
            }
        });
    });
    let expected_last: f32 = chunks as f32;
    assert!(
        output.iter().all(|&v| v >= 1.0 && v <= expected_last),
        "a chunk never ran"
    );
    (
        read,
        ran.iter().map(|r| r.load(Ordering::Relaxed)).collect(),
    )
}

/// What the chain should have read: the same sums on one core.
fn expected(calls: usize, chunks: usize) -> f64 {
    (0..calls)
        .map(|call| {
            let wanted = (call * chunks / calls.max(1)).min(chunks - 1);
            (0..=wanted).map(|c| 7.0 * (c + 1) as f64).sum::<f64>()
        })
        .sum()
}

#[test]
fn every_piece_and_chunk_runs_once_and_the_chain_reads_complete_chunks() {
    for threads in [2, 3, 5] {
        let pool = ThreadPool::new(threads).unwrap();
        for round in 0..300 {
            let (calls, chunks) = (1 + round % 40, 1 + round % 97);
            let (read, ran) = step(&pool, calls, chunks);
            assert_eq!(
                read,
                expected(calls, chunks),
                "{threads} threads, round {round}"
            );
            assert!(
                ran.iter().all(|&r| r == 1),
                "{threads} threads, round {round}: {ran:?}"
            );
        }
    }
}

#[test]
fn one_core_running_the_pieces_backwards_finishes() {
    for count in [2, 4] {
        let (read, ran) = step(&Backwards(count), 12, 30);
        assert_eq!(read, expected(12, 30));
        assert!(ran.iter().all(|&r| r == 1));
    }
}
