//! The ceilings a kernel on this core can reach: multiply-accumulate throughput of each
//! SIMD instruction family with every operand in registers, and read bandwidth from L3 and
//! from DRAM (`cargo bench -p scdp-benches --bench peak`).
//!
//! Each throughput loop keeps [`CHAINS`] (AVX2) or [`CHAINS_AVX512`] independent
//! accumulators, more than the FMA or dot-product latency times the number of ports, so the loop is bound by issue rate, not by
//! a dependency. Operands go through `black_box` so the compiler cannot fold the
//! multiplications away, and every loop returns its accumulators, which the tests compare
//! with the exact expected sum: a loop that the optimiser emptied would fail them.
//!
//! All loops exist on x86-64 only; [`available`] lists the ones this CPU can run (std's
//! CPUID-backed `is_x86_feature_detected!`).

#[cfg(target_arch = "x86_64")]
use std::hint::black_box;

/// Independent accumulator registers per AVX2 loop (16 vector registers, some hold operands).
pub const CHAINS: usize = 12;

/// Independent accumulators per AVX-512 loop (32 vector registers): enough to cover a
/// latency of up to 12 cycles at two instructions per cycle.
pub const CHAINS_AVX512: usize = 24;

/// One throughput loop: `run(iterations)` returns the sum of its accumulators' lanes.
#[derive(Clone, Copy)]
pub struct Throughput {
    pub name: &'static str,
    /// MACs per iteration of the loop (all chains, all lanes).
    pub macs_per_iteration: u64,
    pub run: fn(u64) -> f64,
}

/// The throughput loops this CPU supports.
pub fn available() -> Vec<Throughput> {
    #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
    let mut loops = Vec::new();
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        if has!("avx2") && has!("fma") {
            loops.push(Throughput {
                name: "f32 FMA ymm (vfmadd231ps, 8 lanes)",
                macs_per_iteration: (CHAINS * 8) as u64,
                run: x86::fma_ymm,
            });
        }
        if has!("avx512f") {
            loops.push(Throughput {
                name: "f32 FMA zmm (vfmadd231ps, 16 lanes)",
                macs_per_iteration: (CHAINS_AVX512 * 16) as u64,
                run: x86::fma_zmm,
            });
        }
        if has!("avx2") {
            loops.push(Throughput {
                name: "int8 ymm vpmaddubsw + vpmaddwd + vpaddd (32 MAC)",
                macs_per_iteration: (CHAINS * 32) as u64,
                run: x86::maddubs_ymm,
            });
        }
        if has!("avx512vnni") && has!("avx512vl") {
            loops.push(Throughput {
                name: "int8 ymm VNNI vpdpbusd (32 MAC)",
                macs_per_iteration: (CHAINS_AVX512 * 32) as u64,
                run: x86::dpbusd_ymm,
            });
        }
        if has!("avx512vnni") {
            loops.push(Throughput {
                name: "int8 zmm VNNI vpdpbusd (64 MAC)",
                macs_per_iteration: (CHAINS_AVX512 * 64) as u64,
                run: x86::dpbusd_zmm,
            });
        }
        if has!("avx512vnni") {
            loops.push(Throughput {
                name: "int16 zmm VNNI vpdpwssd (32 MAC; the U-Net's code products)",
                macs_per_iteration: (CHAINS_AVX512 * 32) as u64,
                run: x86::dpwssd_zmm,
            });
        }
        // The engine's own detection: CPUID, XCR0 and, on Linux, the OS's permission.
        if scdp_engine::kernels::select(scdp_engine::Backend::Amx).is_some() {
            loops.push(Throughput {
                name: "int8 AMX tdpbusd (16 x 16 x 64 = 16384 MAC)",
                macs_per_iteration: (AMX_SUMS * 16 * 16 * 64) as u64,
                run: x86::tdpbusd_tiles,
            });
        }
    }
    loops
}

/// Independent sum tiles of the AMX loop: the 2 x 2 blocking of the engine's kernel (four
/// sum tiles, two activation and two weight tiles: all eight tile registers).
pub const AMX_SUMS: usize = 4;

/// The value every loop's result must equal after `iterations`: each MAC adds exactly 1
/// (operands are 1), summed over all chains and lanes.
pub fn expected_sum(throughput: &Throughput, iterations: u64) -> f64 {
    (throughput.macs_per_iteration * iterations) as f64
}

/// One read-bandwidth loop over a `u32` buffer: returns the wrapping sum of its values.
#[derive(Clone, Copy)]
pub struct Bandwidth {
    pub name: &'static str,
    pub run: fn(&[u32]) -> u32,
}

/// The bandwidth loops this CPU supports (the portable one always).
pub fn bandwidth_loops() -> Vec<Bandwidth> {
    #[cfg_attr(not(target_arch = "x86_64"), allow(unused_mut))]
    let mut loops = vec![Bandwidth {
        name: "portable (compiler's vectorisation)",
        run: portable_sum,
    }];
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        if has!("avx2") {
            loops.push(Bandwidth {
                name: "AVX2 ymm loads",
                run: x86::sum_ymm,
            });
        }
        if has!("avx512f") {
            loops.push(Bandwidth {
                name: "AVX-512 zmm loads",
                run: x86::sum_zmm,
            });
        }
    }
    loops
}

/// Reads every value once with independent partial sums.
pub fn portable_sum(values: &[u32]) -> u32 {
    let mut partial = [0u32; 16];
    let mut chunks = values.chunks_exact(16);
    for chunk in &mut chunks {
        for (sum, &value) in partial.iter_mut().zip(chunk) {
            *sum = sum.wrapping_add(value);
        }
    }
    let tail = chunks
        .remainder()
        .iter()
        .fold(0u32, |s, &v| s.wrapping_add(v));
    partial.iter().fold(tail, |s, &v| s.wrapping_add(v))
}

/// `8 x iterations` dependent one-cycle integer additions (returns their result), to
/// estimate the core clock: at one addition per cycle, additions per second are cycles per
/// second. The addend is a register, not an immediate: Golden Cove and its server kin
/// (Sapphire and Emerald Rapids) fold chains of immediate additions at rename, which read
/// as a 12 GHz clock. `None` off x86-64.
pub fn dependent_adds(iterations: u64) -> Option<u64> {
    #[cfg(target_arch = "x86_64")]
    {
        let mut value = 0u64;
        let one = black_box(1u64);
        for _ in 0..iterations {
            // SAFETY: register-only integer additions; no memory or stack access.
            unsafe {
                std::arch::asm!(
                    "add {v}, {one}", "add {v}, {one}", "add {v}, {one}", "add {v}, {one}",
                    "add {v}, {one}", "add {v}, {one}", "add {v}, {one}", "add {v}, {one}",
                    v = inout(reg) value,
                    one = in(reg) one,
                    options(nomem, nostack),
                );
            }
        }
        Some(value)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = iterations;
        None
    }
}

/// Operands for the throughput loops: ones the compiler cannot see.
#[cfg(target_arch = "x86_64")]
fn opaque_one_f32() -> f32 {
    black_box(1.0)
}

#[cfg(target_arch = "x86_64")]
fn opaque_one_i8() -> i8 {
    black_box(1)
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{CHAINS, CHAINS_AVX512, opaque_one_f32, opaque_one_i8};
    use std::arch::x86_64::*;

    /// Wraps a `#[target_feature]` loop for the table of [`super::Throughput`]s.
    macro_rules! checked {
        ($safe:ident, $unsafe_fn:ident, $($feature:tt),+) => {
            pub fn $safe(iterations: u64) -> f64 {
                assert!($(std::arch::is_x86_feature_detected!($feature))&&+);
                // SAFETY: the features the function is compiled for were just detected.
                unsafe { $unsafe_fn(iterations) }
            }
        };
    }

    checked!(fma_ymm, fma_ymm_loop, "avx2", "fma");
    checked!(fma_zmm, fma_zmm_loop, "avx512f");
    checked!(maddubs_ymm, maddubs_ymm_loop, "avx2");
    checked!(dpbusd_ymm, dpbusd_ymm_loop, "avx512vnni", "avx512vl");
    checked!(dpbusd_zmm, dpbusd_zmm_loop, "avx512vnni");
    checked!(dpwssd_zmm, dpwssd_zmm_loop, "avx512vnni");

    fn sum_f32(lanes: &[f32]) -> f64 {
        lanes.iter().map(|&v| v as f64).sum()
    }

    fn sum_i32(lanes: &[i32]) -> f64 {
        lanes.iter().map(|&v| v as f64).sum()
    }

    /// The sum of every i32 lane of the integer loops' `CHAINS_AVX512` zmm accumulators
    /// (callable without `unsafe` from the loops, which are compiled with AVX-512F).
    #[target_feature(enable = "avx512f")]
    fn sum_i32_zmm(acc: &[__m512i; CHAINS_AVX512]) -> f64 {
        let mut lanes = [0i32; CHAINS_AVX512 * 16];
        for (chain, out) in acc.iter().zip(lanes.chunks_exact_mut(16)) {
            // SAFETY: `out` holds exactly 16 i32 (64 bytes); storeu has no alignment
            // requirement.
            unsafe { _mm512_storeu_si512(out.as_mut_ptr().cast(), *chain) };
        }
        sum_i32(&lanes)
    }

    /// `acc = acc * 1 + 1` on `CHAINS` ymm registers.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    unsafe fn fma_ymm_loop(iterations: u64) -> f64 {
        let a = _mm256_set1_ps(opaque_one_f32());
        let b = _mm256_set1_ps(opaque_one_f32());
        let mut acc = [_mm256_setzero_ps(); CHAINS];
        for _ in 0..iterations {
            for chain in &mut acc {
                *chain = _mm256_fmadd_ps(*chain, a, b);
            }
        }
        let mut lanes = [0.0f32; CHAINS * 8];
        for (chain, out) in acc.iter().zip(lanes.chunks_exact_mut(8)) {
            // SAFETY: `out` holds exactly 8 f32; storeu has no alignment requirement.
            unsafe { _mm256_storeu_ps(out.as_mut_ptr(), *chain) };
        }
        sum_f32(&lanes)
    }

    /// `acc = acc * 1 + 1` on `CHAINS_AVX512` zmm registers.
    ///
    /// # Safety
    /// The CPU must support AVX-512F.
    #[target_feature(enable = "avx512f")]
    unsafe fn fma_zmm_loop(iterations: u64) -> f64 {
        let a = _mm512_set1_ps(opaque_one_f32());
        let b = _mm512_set1_ps(opaque_one_f32());
        let mut acc = [_mm512_setzero_ps(); CHAINS_AVX512];
        for _ in 0..iterations {
            for chain in &mut acc {
                *chain = _mm512_fmadd_ps(*chain, a, b);
            }
        }
        let mut lanes = [0.0f32; CHAINS_AVX512 * 16];
        for (chain, out) in acc.iter().zip(lanes.chunks_exact_mut(16)) {
            // SAFETY: `out` holds exactly 16 f32; storeu has no alignment requirement.
            unsafe { _mm512_storeu_ps(out.as_mut_ptr(), *chain) };
        }
        sum_f32(&lanes)
    }

    /// The AVX2 int8 dot product of the engine's kernels: u8 x i8 pairs to i16
    /// (vpmaddubsw), pairs of i16 to i32 (vpmaddwd by ones), accumulated (vpaddd).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    unsafe fn maddubs_ymm_loop(iterations: u64) -> f64 {
        let a = _mm256_set1_epi8(opaque_one_i8());
        let b = _mm256_set1_epi8(opaque_one_i8());
        let ones = _mm256_set1_epi16(opaque_one_i8() as i16);
        let mut acc = [_mm256_setzero_si256(); CHAINS];
        for _ in 0..iterations {
            for chain in &mut acc {
                // Written as assembly because with intrinsics the compiler hoists the two
                // products, which do not depend on the accumulator, out of the loop.
                // SAFETY: register-only AVX2 instructions (available: the function's target
                // feature); no memory or stack access.
                unsafe {
                    core::arch::asm!(
                        "vpmaddubsw {pairs}, {a}, {b}",
                        "vpmaddwd {pairs}, {pairs}, {ones}",
                        "vpaddd {acc}, {acc}, {pairs}",
                        acc = inout(ymm_reg) *chain,
                        a = in(ymm_reg) a,
                        b = in(ymm_reg) b,
                        ones = in(ymm_reg) ones,
                        pairs = out(ymm_reg) _,
                        options(nomem, nostack, preserves_flags),
                    );
                }
            }
        }
        let mut lanes = [0i32; CHAINS * 8];
        for (chain, out) in acc.iter().zip(lanes.chunks_exact_mut(8)) {
            // SAFETY: `out` holds exactly 8 i32 (32 bytes); storeu has no alignment requirement.
            unsafe { _mm256_storeu_si256(out.as_mut_ptr().cast(), *chain) };
        }
        sum_i32(&lanes)
    }

    /// `acc += dot4(u8, i8)` per i32 lane (vpdpbusd) on `CHAINS_AVX512` ymm registers (32 with VL).
    ///
    /// # Safety
    /// The CPU must support AVX-512 VNNI and VL.
    #[target_feature(enable = "avx512vnni,avx512vl")]
    unsafe fn dpbusd_ymm_loop(iterations: u64) -> f64 {
        let a = _mm256_set1_epi8(opaque_one_i8());
        let b = _mm256_set1_epi8(opaque_one_i8());
        let mut acc = [_mm256_setzero_si256(); CHAINS_AVX512];
        for _ in 0..iterations {
            for chain in &mut acc {
                *chain = _mm256_dpbusd_epi32(*chain, a, b);
            }
        }
        let mut lanes = [0i32; CHAINS_AVX512 * 8];
        for (chain, out) in acc.iter().zip(lanes.chunks_exact_mut(8)) {
            // SAFETY: `out` holds exactly 8 i32 (32 bytes); storeu has no alignment requirement.
            unsafe { _mm256_storeu_si256(out.as_mut_ptr().cast(), *chain) };
        }
        sum_i32(&lanes)
    }

    /// `acc += dot4(u8, i8)` per i32 lane (vpdpbusd) on `CHAINS_AVX512` zmm registers.
    ///
    /// # Safety
    /// The CPU must support AVX-512 VNNI (which implies AVX-512F).
    #[target_feature(enable = "avx512vnni")]
    unsafe fn dpbusd_zmm_loop(iterations: u64) -> f64 {
        let a = _mm512_set1_epi8(opaque_one_i8());
        let b = _mm512_set1_epi8(opaque_one_i8());
        let mut acc = [_mm512_setzero_si512(); CHAINS_AVX512];
        for _ in 0..iterations {
            for chain in &mut acc {
                *chain = _mm512_dpbusd_epi32(*chain, a, b);
            }
        }
        sum_i32_zmm(&acc)
    }

    /// `acc += dot2(i16, i16)` per i32 lane (vpdpwssd) on `CHAINS_AVX512` zmm registers.
    ///
    /// # Safety
    /// The CPU must support AVX-512 VNNI (which implies AVX-512F).
    #[target_feature(enable = "avx512vnni")]
    unsafe fn dpwssd_zmm_loop(iterations: u64) -> f64 {
        let a = _mm512_set1_epi16(i16::from(opaque_one_i8()));
        let b = _mm512_set1_epi16(i16::from(opaque_one_i8()));
        let mut acc = [_mm512_setzero_si512(); CHAINS_AVX512];
        for _ in 0..iterations {
            for chain in &mut acc {
                *chain = _mm512_dpwssd_epi32(*chain, a, b);
            }
        }
        sum_i32_zmm(&acc)
    }

    /// `tdpbusd` on [`AMX_SUMS`](super::AMX_SUMS) independent sum tiles from two
    /// activation and two weight tiles of ones, as the engine's block uses them.
    pub fn tdpbusd_tiles(iterations: u64) -> f64 {
        assert!(scdp_engine::kernels::select(scdp_engine::Backend::Amx).is_some());
        #[repr(C, align(64))]
        struct Tile([u8; 1024]);
        let mut config = Tile([0; 1024]);
        config.0[0] = 1;
        for tile in 0..8 {
            config.0[16 + 2 * tile] = 64;
            config.0[48 + tile] = 16;
        }
        let ones = Tile([opaque_one_i8() as u8; 1024]);
        let mut sums = [
            Tile([0; 1024]),
            Tile([0; 1024]),
            Tile([0; 1024]),
            Tile([0; 1024]),
        ];
        // SAFETY: the engine detected AMX and obtained the OS's permission (asserted above);
        // the configuration is palette 1 with eight tiles of 16 rows x 64 bytes; every tile
        // load and store covers one 1 KB buffer at a 64-byte stride; nothing else in this
        // function touches the tile registers between the configuration and the release.
        unsafe {
            core::arch::asm!("ldtilecfg [{}]", in(reg) config.0.as_ptr(), options(nostack));
            core::arch::asm!(
                "tilezero tmm0",
                "tilezero tmm1",
                "tilezero tmm2",
                "tilezero tmm3",
                "tileloadd tmm4, [{ones} + {stride}]",
                "tileloadd tmm5, [{ones} + {stride}]",
                "tileloadd tmm6, [{ones} + {stride}]",
                "tileloadd tmm7, [{ones} + {stride}]",
                ones = in(reg) ones.0.as_ptr(),
                stride = in(reg) 64usize,
                options(nostack, readonly, preserves_flags),
            );
            for _ in 0..iterations {
                core::arch::asm!(
                    "tdpbusd tmm0, tmm4, tmm6",
                    "tdpbusd tmm1, tmm4, tmm7",
                    "tdpbusd tmm2, tmm5, tmm6",
                    "tdpbusd tmm3, tmm5, tmm7",
                    options(nomem, nostack, preserves_flags),
                );
            }
            let [s0, s1, s2, s3] = &mut sums;
            core::arch::asm!(
                "tilestored [{s0} + {stride}], tmm0",
                "tilestored [{s1} + {stride}], tmm1",
                "tilestored [{s2} + {stride}], tmm2",
                "tilestored [{s3} + {stride}], tmm3",
                "tilerelease",
                s0 = in(reg) s0.0.as_mut_ptr(),
                s1 = in(reg) s1.0.as_mut_ptr(),
                s2 = in(reg) s2.0.as_mut_ptr(),
                s3 = in(reg) s3.0.as_mut_ptr(),
                stride = in(reg) 64usize,
                options(nostack, preserves_flags),
            );
        }
        sums.iter()
            .flat_map(|tile| tile.0.chunks_exact(4))
            .map(|sum| i32::from_le_bytes([sum[0], sum[1], sum[2], sum[3]]) as f64)
            .sum()
    }

    pub fn sum_ymm(values: &[u32]) -> u32 {
        assert!(std::arch::is_x86_feature_detected!("avx2"));
        // SAFETY: AVX2 was just detected.
        unsafe { sum_ymm_loop(values) }
    }

    pub fn sum_zmm(values: &[u32]) -> u32 {
        assert!(std::arch::is_x86_feature_detected!("avx512f"));
        // SAFETY: AVX-512F was just detected.
        unsafe { sum_zmm_loop(values) }
    }

    /// Four ymm loads per iteration into four partial sums.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    unsafe fn sum_ymm_loop(values: &[u32]) -> u32 {
        let mut acc = [_mm256_setzero_si256(); 4];
        let mut blocks = values.chunks_exact(32);
        for block in &mut blocks {
            for (index, sum) in acc.iter_mut().enumerate() {
                // SAFETY: `block` holds 32 u32, so 8 from `index * 8` are in bounds;
                // loadu has no alignment requirement.
                let v = unsafe { _mm256_loadu_si256(block.as_ptr().add(index * 8).cast()) };
                *sum = _mm256_add_epi32(*sum, v);
            }
        }
        let mut lanes = [0u32; 32];
        for (sum, out) in acc.iter().zip(lanes.chunks_exact_mut(8)) {
            // SAFETY: `out` holds exactly 8 u32; storeu has no alignment requirement.
            unsafe { _mm256_storeu_si256(out.as_mut_ptr().cast(), *sum) };
        }
        let tail = super::portable_sum(blocks.remainder());
        lanes.iter().fold(tail, |s, &v| s.wrapping_add(v))
    }

    /// Four zmm loads (one 256-byte block) per iteration into four partial sums.
    ///
    /// # Safety
    /// The CPU must support AVX-512F.
    #[target_feature(enable = "avx512f")]
    unsafe fn sum_zmm_loop(values: &[u32]) -> u32 {
        let mut acc = [_mm512_setzero_si512(); 4];
        let mut blocks = values.chunks_exact(64);
        for block in &mut blocks {
            for (index, sum) in acc.iter_mut().enumerate() {
                // SAFETY: `block` holds 64 u32, so 16 from `index * 16` are in bounds;
                // loadu has no alignment requirement.
                let v = unsafe { _mm512_loadu_si512(block.as_ptr().add(index * 16).cast()) };
                *sum = _mm512_add_epi32(*sum, v);
            }
        }
        let mut lanes = [0u32; 64];
        for (sum, out) in acc.iter().zip(lanes.chunks_exact_mut(16)) {
            // SAFETY: `out` holds exactly 16 u32; storeu has no alignment requirement.
            unsafe { _mm512_storeu_si512(out.as_mut_ptr().cast(), *sum) };
        }
        let tail = super::portable_sum(blocks.remainder());
        lanes.iter().fold(tail, |s, &v| s.wrapping_add(v))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_throughput_loop_computes_its_sum() {
        let loops = available();
        // An AVX-512 VNNI machine has six (seven with AMX); elsewhere at least the AVX2 ones.
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            assert!(loops.len() >= 2);
        }
        for throughput in loops {
            for iterations in [0, 1, 7, 1000] {
                assert_eq!(
                    (throughput.run)(iterations),
                    expected_sum(&throughput, iterations),
                    "{} x {iterations}",
                    throughput.name
                );
            }
        }
    }

    #[test]
    fn the_clock_loop_adds_eight_per_iteration() {
        #[cfg(target_arch = "x86_64")]
        assert_eq!(dependent_adds(1000), Some(8000));
    }

    #[test]
    fn every_bandwidth_loop_reads_every_value() {
        // Lengths around the block sizes, values whose wrapping sum is known independently.
        for len in [0usize, 1, 15, 16, 63, 64, 65, 1000, 4099] {
            let values: Vec<u32> = (0..len as u32)
                .map(|i| i.wrapping_mul(2_654_435_761))
                .collect();
            let mut expected = 0u64;
            for &v in &values {
                expected += v as u64;
            }
            for bandwidth in bandwidth_loops() {
                assert_eq!(
                    (bandwidth.run)(&values),
                    expected as u32,
                    "{} over {len}",
                    bandwidth.name
                );
            }
        }
    }
}
