//! Replays every file of the committed fuzz corpus (`fuzz/corpus/<target>/`: the seeds,
//! and the inputs that once crashed a target, kept as regressions) through the code the
//! fuzz targets run, `fuzz/src/harness.rs`, so that CI checks them with a stable toolchain
//! and no libFuzzer. The harness panics when the engine breaks a promise; it also installs
//! the counting allocator that checks every engine call allocates nothing.

#[allow(dead_code)]
#[path = "../../fuzz/src/alloc_guard.rs"]
mod alloc_guard;
#[allow(dead_code)]
#[path = "../../fuzz/src/harness.rs"]
mod harness;

use std::path::PathBuf;

fn corpus(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = scdp_tests::tests_dir().join("../fuzz/corpus").join(target);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|error| panic!("{}: {error}", dir.display()))
        .map(|entry| entry.unwrap().path())
        .collect();
    files.sort();
    assert!(files.len() >= 5, "{}: corpus too small", dir.display());
    files
        .into_iter()
        .map(|path| {
            let bytes = std::fs::read(&path).unwrap();
            (path, bytes)
        })
        .collect()
}

fn replay(target: &str, run: fn(&[u8])) {
    for (path, bytes) in corpus(target) {
        let outcome = std::panic::catch_unwind(|| run(&bytes));
        assert!(outcome.is_ok(), "{target}: {} fails", path.display());
    }
}

#[test]
fn load_bytes_corpus() {
    replay("load_bytes", harness::fuzz_load_bytes);
}

#[test]
fn load_mutated_corpus() {
    replay("load_mutated", harness::fuzz_load_mutated);
}

#[test]
fn inference_corpus() {
    replay("inference", harness::fuzz_inference);
}

/// The harness's tools work: edits are applied and re-checksummed, allocations are caught.
#[test]
fn the_harness_detects_broken_promises() {
    // The mutation helper really applies edits and fixes the checksum.
    let base = harness::micro_weights(weights_tool::Quant::F32);
    let mut out = vec![0u8; base.len() + 512];
    let edit = [0u8, 8, 0, 0, 0, 3, b'X', b'X', b'X', b'X'];
    let (len, run) = harness::mutate_file(base, &edit, &mut out);
    assert_eq!((len, run), (base.len(), false));
    assert_eq!(&out[8..12], b"XXXX");
    assert_ne!(&out[24..32], &base[24..32], "checksum recomputed");
    // The allocation check fails on an allocation.
    let caught = std::panic::catch_unwind(|| {
        alloc_guard::no_alloc(|| std::hint::black_box(vec![0u8; 8]));
    });
    assert!(caught.is_err(), "no_alloc must fail on an allocation");
}
