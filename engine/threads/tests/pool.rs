//! The pool's contract under load: every piece of every call runs exactly once and its
//! writes are seen by the caller when `run` returns, with more threads than cores (threads
//! taken off their cores mid-call, late to calls, or never showing up for one); a panicking
//! piece panics the call without breaking the pool.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

use scdp_threads::{ThreadPool, Workers};

#[test]
fn every_piece_runs_once_a_call_with_more_threads_than_cores() {
    let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
    let pool = ThreadPool::new(4 * cores).unwrap();
    let runs: Vec<AtomicUsize> = (0..64).map(|_| AtomicUsize::new(0)).collect();
    // Written last by each piece: `run` must not return before every piece has.
    let values: Vec<AtomicU64> = (0..64).map(|_| AtomicU64::new(0)).collect();
    for call in 0..3000usize {
        let pieces = 2 + call % 63;
        pool.run(pieces, &|piece| {
            runs[piece].fetch_add(1, Ordering::Relaxed);
            // Some pieces long enough for the others to be claimed meanwhile.
            if piece % 7 == 0 {
                std::hint::black_box((0..2000).sum::<u64>());
            }
            values[piece].store((call * 64 + piece) as u64, Ordering::Relaxed);
        });
        for (piece, count) in runs.iter().enumerate() {
            let expected = usize::from(piece < pieces);
            assert_eq!(
                count.swap(0, Ordering::Relaxed),
                expected,
                "call {call}, piece {piece}"
            );
        }
        for (piece, value) in values[..pieces].iter().enumerate() {
            assert_eq!(
                value.load(Ordering::Relaxed),
                (call * 64 + piece) as u64,
                "call {call}, piece {piece}"
            );
        }
    }
}

#[test]
fn a_panicking_piece_panics_the_call_and_the_pool_goes_on() {
    let pool = ThreadPool::new(3).unwrap();
    let done = AtomicUsize::new(0);
    let call = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        pool.run(6, &|piece| {
            assert!(piece != 4, "piece 4 fails");
            done.fetch_add(1, Ordering::Relaxed);
        })
    }));
    assert!(call.is_err(), "the call did not panic");
    // Every other piece still ran before the call returned.
    assert_eq!(done.swap(0, Ordering::Relaxed), 5);
    pool.run(6, &|_| {
        done.fetch_add(1, Ordering::Relaxed);
    });
    assert_eq!(done.load(Ordering::Relaxed), 6);
}

/// Busy for at least `duration`: a piece or the caller's own work between calls.
#[cfg(feature = "timing")]
fn busy(duration: std::time::Duration) {
    let start = std::time::Instant::now();
    while start.elapsed() < duration {
        std::hint::spin_loop();
    }
}

#[cfg(feature = "timing")]
#[test]
fn timing_counts_each_call_and_splits_the_time_between_takes() {
    use std::time::{Duration, Instant};
    let pool = ThreadPool::new(2).unwrap();
    let piece = Duration::from_micros(200);
    let outside = Duration::from_micros(300);
    let start = Instant::now();
    pool.take_timing();
    for _ in 0..10 {
        busy(outside);
        pool.run(2, &|_| busy(piece));
    }
    busy(outside);
    let timing = pool.take_timing();
    let elapsed = start.elapsed();
    assert_eq!(timing.calls, 10);
    // The caller ran at least one piece a call, and did its own work outside every call.
    assert!(timing.pieces >= 10 * piece, "{timing:?}");
    assert!(timing.between >= 11 * outside, "{timing:?}");
    let parts = timing.between + timing.publishing + timing.pieces + timing.waiting;
    assert!(parts <= elapsed, "{timing:?} in {elapsed:?}");
    // A call of one piece runs on the caller without the pool: not a call, its time between.
    pool.run(1, &|_| busy(piece));
    let timing = pool.take_timing();
    assert_eq!(timing.calls, 0);
    assert!(timing.between >= piece, "{timing:?}");
}
