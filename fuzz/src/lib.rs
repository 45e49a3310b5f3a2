//! Fuzz targets of the SCDP engine (docs/ROBUSTNESS.md). The targets in `fuzz_targets/`
//! are one-line wrappers around [`harness`], which `tests/tests/fuzz_corpus.rs` also runs
//! on every committed corpus file.

pub mod alloc_guard;
pub mod harness;
