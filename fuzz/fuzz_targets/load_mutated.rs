#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| scdp_fuzz::harness::fuzz_load_mutated(data));
