//! Peak rates of one core: MAC throughput of each SIMD family with operands in registers, and
//! read bandwidth from a buffer that fits in L3 and from one far larger than L3:
//! `cargo bench -p scdp-benches --bench peak`.
//!
//! Every figure is the median of `REPEATS` timed calls and the best of them, each call long
//! enough (~5 ms) that timer and call overheads vanish. On a shared machine the median
//! includes time the scheduler gave to other processes; the best call, short enough to
//! often run undisturbed, is the better estimate of the ceiling. MAC/cycle divides the best
//! rate by the best clock estimate. Runs on the calling thread only.

use std::time::{Duration, Instant};

use scdp_benches::peak::{Throughput, available, bandwidth_loops, dependent_adds, expected_sum};

const REPEATS: usize = 41;
const TARGET: Duration = Duration::from_millis(5);

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Repeats `run` and returns (median, best) of `work / seconds`.
fn rates(work: f64, mut run: impl FnMut()) -> (f64, f64) {
    run();
    let mut rates: Vec<f64> = (0..REPEATS)
        .map(|_| {
            let start = Instant::now();
            run();
            work / start.elapsed().as_secs_f64()
        })
        .collect();
    let best = rates.iter().copied().fold(0.0, f64::max);
    (median(&mut rates), best)
}

/// Iterations of `run` that take about [`TARGET`].
fn calibrate(run: impl Fn(u64)) -> u64 {
    let mut iterations = 1 << 10;
    loop {
        let start = Instant::now();
        run(iterations);
        let elapsed = start.elapsed();
        if elapsed >= TARGET / 4 {
            let scale = TARGET.as_secs_f64() / elapsed.as_secs_f64();
            return ((iterations as f64 * scale) as u64).max(1);
        }
        iterations *= 4;
    }
}

/// (median, best) additions per second of a dependent chain: the clock, if undisturbed.
fn clock_hz() -> Option<(f64, f64)> {
    dependent_adds(1)?;
    let iterations = calibrate(|n| {
        std::hint::black_box(dependent_adds(n));
    });
    Some(rates(8.0 * iterations as f64, || {
        std::hint::black_box(dependent_adds(iterations));
    }))
}

/// (median, best) GMAC/s of one loop.
fn throughput(loop_: &Throughput) -> (f64, f64) {
    let iterations = calibrate(|n| {
        std::hint::black_box((loop_.run)(n));
    });
    let macs = (loop_.macs_per_iteration * iterations) as f64;
    let (median, best) = rates(macs, || {
        let sum = (loop_.run)(iterations);
        assert_eq!(sum, expected_sum(loop_, iterations), "{}", loop_.name);
    });
    (median / 1e9, best / 1e9)
}

/// Read bandwidth of a `bytes` buffer in plain pages (a `Vec`) or, with `huge_pages`, in
/// the transparent huge pages the engine's buffers get on Linux (`AlignedBytes`).
fn bandwidth(label: &str, bytes: usize, huge_pages: bool) {
    let mut mapped = weights_tool::writer::AlignedBytes::zeroed(if huge_pages { bytes } else { 0 });
    let mut owned: Vec<u32> = Vec::new();
    let values: &mut [u32] = if huge_pages {
        bytemuck::cast_slice_mut(mapped.as_mut_slice())
    } else {
        owned.resize(bytes / 4, 0);
        &mut owned
    };
    values
        .iter_mut()
        .zip(0u32..)
        .for_each(|(value, index)| *value = index);
    let values: &[u32] = values;
    let label = format!(
        "{label}, {}",
        if huge_pages {
            "2 MiB pages"
        } else {
            "4 KiB pages"
        }
    );
    let expected = values.iter().fold(0u32, |s, &v| s.wrapping_add(v));
    // Small buffers are read several times per timed call.
    let passes = (256 << 20) / bytes.min(256 << 20);
    for loop_ in bandwidth_loops() {
        let (median, best) = rates((passes * bytes) as f64, || {
            for _ in 0..passes {
                assert_eq!((loop_.run)(std::hint::black_box(values)), expected);
            }
        });
        println!(
            "| read {label}, {} | {:.1} | {:.1} |",
            loop_.name,
            median / 1e9,
            best / 1e9
        );
    }
}

fn main() {
    // `cargo bench` passes `--bench`; a name filter is not supported (the whole run is short).
    // The clock is measured next to every loop: other processes only ever lower a measured
    // rate, so the highest estimate of the run is the closest to the true clock.
    let mut clock: Option<f64> = None;
    let mut rows = Vec::new();
    for loop_ in available() {
        if let Some((_, best)) = clock_hz() {
            clock = Some(clock.map_or(best, |c: f64| c.max(best)));
        }
        rows.push((loop_.name, throughput(&loop_)));
    }
    match clock {
        Some(hz) => println!(
            "core clock estimate (best of dependent integer add chains): {:.2} GHz",
            hz / 1e9
        ),
        None => println!("core clock estimate: not on this architecture"),
    }
    println!("\nmedian and best of {REPEATS} calls of ~{TARGET:?}, one thread");
    println!("| loop | median GMAC/s | best GMAC/s | MAC/cycle (best) |");
    println!("|---|---:|---:|---:|");
    for (name, (median, best)) in rows {
        let per_cycle = clock.map_or("-".to_owned(), |hz| format!("{:.1}", best * 1e9 / hz));
        println!("| {name} | {median:.1} | {best:.1} | {per_cycle} |");
    }
    println!("\n| buffer | median GB/s | best GB/s |");
    println!("|---|---:|---:|");
    for huge_pages in [false, true] {
        bandwidth("16 MiB (fits L3)", 16 << 20, huge_pages);
        bandwidth("256 MiB (> L3)", 256 << 20, huge_pages);
    }
}
