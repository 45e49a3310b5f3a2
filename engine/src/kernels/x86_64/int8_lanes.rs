//! The x86-64 integer dot products of the int8 kernels: AVX2 `vpmaddubsw` and `vpmaddwd`
//! on YMM, AVX-512 VNNI `vpdpbusd` and `vpdpwssd` on ZMM.

use core::arch::x86_64::{
    __m256, __m256d, __m256i, __m512, __m512d, __m512i, _mm_loadu_si128, _mm256_add_epi32,
    _mm256_add_pd, _mm256_add_ps, _mm256_castps_pd, _mm256_castsi256_si128, _mm256_cvtepi8_epi16,
    _mm256_cvtepi32_pd, _mm256_cvtpd_ps, _mm256_extracti128_si256, _mm256_hadd_epi32,
    _mm256_loadu_ps, _mm256_loadu_si256, _mm256_madd_epi16, _mm256_maddubs_epi16, _mm256_mul_pd,
    _mm256_mul_ps, _mm256_permute4x64_epi64, _mm256_set_m128, _mm256_set1_epi16, _mm256_set1_epi32,
    _mm256_set1_epi64x, _mm256_set1_pd, _mm256_set1_ps, _mm256_setzero_pd, _mm256_setzero_ps,
    _mm256_setzero_si256, _mm256_storeu_ps, _mm256_storeu_si256, _mm512_add_epi32, _mm512_add_pd,
    _mm512_add_ps, _mm512_castpd_ps, _mm512_castpd256_pd512, _mm512_castsi512_si256,
    _mm512_cvtepi8_epi16, _mm512_cvtepi32_pd, _mm512_cvtepi32_ps, _mm512_cvtpd_ps,
    _mm512_dpbusd_epi32, _mm512_dpwssd_epi32, _mm512_extracti64x4_epi64, _mm512_insertf64x4,
    _mm512_loadu_ps, _mm512_loadu_si512, _mm512_mul_pd, _mm512_mul_ps, _mm512_permutex2var_epi32,
    _mm512_set1_epi8, _mm512_set1_epi32, _mm512_set1_epi64, _mm512_set1_pd, _mm512_set1_ps,
    _mm512_setr_epi32, _mm512_setzero_pd, _mm512_setzero_ps, _mm512_setzero_si512,
    _mm512_storeu_ps, _mm512_storeu_si512, _mm512_xor_si512,
};

use crate::kernels::ops;
use crate::kernels::simd::int8::{Int8Lanes, SignedByteLanes, WholeByteLanes};

/// AVX2: eight channels a YMM vector. `vpmaddubsw` multiplies the quad's four activations
/// (u8) by the four weights (i8) and adds adjacent pairs into i16 lanes, `vpmaddwd` by ones
/// adds the two pairs into an i32 lane, `vpaddd` accumulates. `vpmaddubsw` saturates its
/// i16 pair sums; with activations in 0..=127 and weights in -127..=127 (the tool's range)
/// a pair sum lies within ±2 x 127 x 127 = ±32258, and even a weight of -128 (which no tool
/// writes, but a file may hold) gives at most 2 x 127 x 128 = 32512: inside i16's
/// -32768..=32767, so nothing saturates and the sums are exact. (An activation of -1 as i8
/// reads as 255 as u8 and could reach 2 x 255 x 127 = 64770: why negative rows never come
/// here.) The i32 sum of a tap cannot overflow either: 127 x 127 x in_channels < 2^31 up to
/// 133,000 input channels.
pub(crate) struct PairSumsYmm;

/// AVX-512 VNNI: sixteen channels a ZMM vector. `vpdpbusd` multiplies four u8 activations
/// by four i8 weights and adds them into an i32 lane in one instruction, without
/// intermediate saturation (exact for any activation in 0..=255, here 0..=127).
pub(crate) struct VnniZmm;

// SAFETY: each method is the intrinsic sequence its documentation names; the trait's
// contract passes the CPU and pointer requirements on to the caller.
unsafe impl Int8Lanes for PairSumsYmm {
    type Integers = __m256i;
    type Floats = __m256;
    type Exact = (__m256d, __m256d);
    const WIDTH: usize = 8;
    // A pair of 255 x 127 products saturates `vpmaddubsw`'s i16 lane.
    #[inline(always)]
    unsafe fn zero_integers() -> __m256i {
        // SAFETY: the caller runs on AVX2 (trait contract).
        unsafe { _mm256_setzero_si256() }
    }
    #[inline(always)]
    unsafe fn zero_floats() -> __m256 {
        // SAFETY: the caller runs on AVX2 (trait contract).
        unsafe { _mm256_setzero_ps() }
    }
    #[inline(always)]
    unsafe fn zero_exact() -> (__m256d, __m256d) {
        // SAFETY: the caller runs on AVX2 (trait contract).
        unsafe { (_mm256_setzero_pd(), _mm256_setzero_pd()) }
    }
    #[inline(always)]
    unsafe fn load_weights(from: *const i8) -> __m256i {
        // SAFETY: AVX2, and 32 bytes readable (trait contract).
        unsafe { _mm256_loadu_si256(from.cast()) }
    }
    #[inline(always)]
    unsafe fn broadcast_quad(from: *const i8) -> __m256i {
        // SAFETY: AVX2, and 4 bytes readable (trait contract).
        unsafe { _mm256_set1_epi32(from.cast::<i32>().read_unaligned()) }
    }
    #[inline(always)]
    unsafe fn dot_quads(sum: __m256i, activations: __m256i, weights: __m256i) -> __m256i {
        // SAFETY: the caller runs on AVX2 (trait contract).
        unsafe {
            let pairs = _mm256_maddubs_epi16(activations, weights);
            _mm256_add_epi32(sum, _mm256_madd_epi16(pairs, _mm256_set1_epi16(1)))
        }
    }
    #[inline(always)]
    unsafe fn widen_quads(from: *const i8) -> __m256i {
        // SAFETY: AVX2, and 16 bytes readable (trait contract).
        unsafe { _mm256_cvtepi8_epi16(_mm_loadu_si128(from.cast())) }
    }
    #[inline(always)]
    unsafe fn broadcast_codes(from: *const i16) -> __m256i {
        // SAFETY: AVX2, and 8 bytes readable (trait contract).
        unsafe { _mm256_set1_epi64x(from.cast::<i64>().read_unaligned()) }
    }
    #[inline(always)]
    unsafe fn dot_code_pairs(sum: __m256i, codes: __m256i, weights: __m256i) -> __m256i {
        // SAFETY: the caller runs on AVX2 (trait contract). `vpmaddwd` saturates only
        // for two products of -32768 x -32768, which 15-bit codes cannot make.
        unsafe { _mm256_add_epi32(sum, _mm256_madd_epi16(codes, weights)) }
    }
    #[inline(always)]
    unsafe fn load_codes(from: *const i16) -> __m256i {
        // SAFETY: AVX2, and 32 bytes readable (trait contract).
        unsafe { _mm256_loadu_si256(from.cast()) }
    }
    #[inline(always)]
    unsafe fn add_integers(a: __m256i, b: __m256i) -> __m256i {
        // SAFETY: the caller runs on AVX2 (trait contract).
        unsafe { _mm256_add_epi32(a, b) }
    }
    #[inline(always)]
    unsafe fn lane_sum(sums: __m256i) -> i64 {
        let mut lanes = [0i32; 8];
        // SAFETY: AVX2 (trait contract); `lanes` holds 32 bytes.
        unsafe { _mm256_storeu_si256(lanes.as_mut_ptr().cast(), sums) };
        lanes.iter().map(|&lane| i64::from(lane)).sum()
    }
    #[inline(always)]
    unsafe fn add_lane_pairs(first: __m256i, second: __m256i) -> __m256i {
        // SAFETY: the caller runs on AVX2 (trait contract). `vphaddd` adds pairs within
        // each 128-bit half, giving the 64-bit groups (0 1)(4 5)(2 3)(6 7) of channels:
        // the permute puts them in order.
        unsafe { _mm256_permute4x64_epi64::<0b11_01_10_00>(_mm256_hadd_epi32(first, second)) }
    }
    #[inline(always)]
    unsafe fn add_exact(total: (__m256d, __m256d), sum: __m256i) -> (__m256d, __m256d) {
        // SAFETY: the caller runs on AVX2 (trait contract).
        unsafe {
            let (low, high) = widen_ymm(sum);
            (_mm256_add_pd(total.0, low), _mm256_add_pd(total.1, high))
        }
    }
    #[inline(always)]
    unsafe fn exact_digits(high: __m256i, low: __m256i) -> (__m256d, __m256d) {
        // SAFETY: the caller runs on AVX2 (trait contract). Times 128 and the sum are exact
        // for i32 digit sums in f64.
        unsafe {
            let base = _mm256_set1_pd(f64::from(ops::DIGIT_BASE));
            let (high, low) = (widen_ymm(high), widen_ymm(low));
            (
                _mm256_add_pd(_mm256_mul_pd(high.0, base), low.0),
                _mm256_add_pd(_mm256_mul_pd(high.1, base), low.1),
            )
        }
    }
    #[inline(always)]
    unsafe fn round_scaled(total: (__m256d, __m256d), scale: f32) -> __m256 {
        // SAFETY: the caller runs on AVX2 (trait contract). `vcvtpd2ps` rounds as MXCSR
        // says, to nearest unless the caller changed it (Rust code never does).
        unsafe {
            let rounded = _mm256_set_m128(_mm256_cvtpd_ps(total.1), _mm256_cvtpd_ps(total.0));
            _mm256_mul_ps(rounded, _mm256_set1_ps(scale))
        }
    }
    #[inline(always)]
    unsafe fn load(from: *const f32) -> __m256 {
        // SAFETY: AVX2, and 8 floats readable (trait contract).
        unsafe { _mm256_loadu_ps(from) }
    }
    #[inline(always)]
    unsafe fn store(to: *mut f32, value: __m256) {
        // SAFETY: AVX2, and 8 floats writable (trait contract).
        unsafe { _mm256_storeu_ps(to, value) }
    }
    #[inline(always)]
    unsafe fn mul(a: __m256, b: __m256) -> __m256 {
        // SAFETY: the caller runs on AVX2 (trait contract).
        unsafe { _mm256_mul_ps(a, b) }
    }
    #[inline(always)]
    unsafe fn add(a: __m256, b: __m256) -> __m256 {
        // SAFETY: the caller runs on AVX2 (trait contract).
        unsafe { _mm256_add_ps(a, b) }
    }
}

// SAFETY: as for `PairSumsYmm`, with AVX-512 F/BW/VNNI.
unsafe impl Int8Lanes for VnniZmm {
    type Integers = __m512i;
    type Floats = __m512;
    type Exact = (__m512d, __m512d);
    const WIDTH: usize = 16;
    #[inline(always)]
    unsafe fn zero_integers() -> __m512i {
        // SAFETY: the caller runs on AVX-512F (trait contract).
        unsafe { _mm512_setzero_si512() }
    }
    #[inline(always)]
    unsafe fn zero_floats() -> __m512 {
        // SAFETY: the caller runs on AVX-512F (trait contract).
        unsafe { _mm512_setzero_ps() }
    }
    #[inline(always)]
    unsafe fn zero_exact() -> (__m512d, __m512d) {
        // SAFETY: the caller runs on AVX-512F (trait contract).
        unsafe { (_mm512_setzero_pd(), _mm512_setzero_pd()) }
    }
    #[inline(always)]
    unsafe fn load_weights(from: *const i8) -> __m512i {
        // SAFETY: AVX-512F, and 64 bytes readable (trait contract).
        unsafe { _mm512_loadu_si512(from.cast()) }
    }
    #[inline(always)]
    unsafe fn broadcast_quad(from: *const i8) -> __m512i {
        // SAFETY: AVX-512F, and 4 bytes readable (trait contract).
        unsafe { _mm512_set1_epi32(from.cast::<i32>().read_unaligned()) }
    }
    #[inline(always)]
    unsafe fn dot_quads(sum: __m512i, activations: __m512i, weights: __m512i) -> __m512i {
        // SAFETY: the caller runs on AVX-512 VNNI (trait contract).
        unsafe { _mm512_dpbusd_epi32(sum, activations, weights) }
    }
    #[inline(always)]
    unsafe fn widen_quads(from: *const i8) -> __m512i {
        // SAFETY: AVX-512BW, and 32 bytes readable (trait contract).
        unsafe { _mm512_cvtepi8_epi16(_mm256_loadu_si256(from.cast())) }
    }
    #[inline(always)]
    unsafe fn broadcast_codes(from: *const i16) -> __m512i {
        // SAFETY: AVX-512F, and 8 bytes readable (trait contract).
        unsafe { _mm512_set1_epi64(from.cast::<i64>().read_unaligned()) }
    }
    #[inline(always)]
    unsafe fn dot_code_pairs(sum: __m512i, codes: __m512i, weights: __m512i) -> __m512i {
        // SAFETY: the caller runs on AVX-512 VNNI (trait contract). `vpdpwssd` wraps, and
        // the sums it makes here fit (`MAX_DIGIT_CHANNELS`).
        unsafe { _mm512_dpwssd_epi32(sum, codes, weights) }
    }
    #[inline(always)]
    unsafe fn load_codes(from: *const i16) -> __m512i {
        // SAFETY: AVX-512F, and 64 bytes readable (trait contract).
        unsafe { _mm512_loadu_si512(from.cast()) }
    }
    #[inline(always)]
    unsafe fn add_integers(a: __m512i, b: __m512i) -> __m512i {
        // SAFETY: the caller runs on AVX-512F (trait contract).
        unsafe { _mm512_add_epi32(a, b) }
    }
    #[inline(always)]
    unsafe fn lane_sum(sums: __m512i) -> i64 {
        let mut lanes = [0i32; 16];
        // SAFETY: AVX-512F (trait contract); `lanes` holds 64 bytes.
        unsafe { _mm512_storeu_si512(lanes.as_mut_ptr().cast(), sums) };
        lanes.iter().map(|&lane| i64::from(lane)).sum()
    }
    #[inline(always)]
    unsafe fn add_lane_pairs(first: __m512i, second: __m512i) -> __m512i {
        // SAFETY: the caller runs on AVX-512F (trait contract). Index `i` of a two-source
        // permute reads lane `i % 16` of `first` below 16 and of `second` from 16 on.
        unsafe {
            let even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
            let odd = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
            _mm512_add_epi32(
                _mm512_permutex2var_epi32(first, even, second),
                _mm512_permutex2var_epi32(first, odd, second),
            )
        }
    }
    #[inline(always)]
    unsafe fn add_exact(total: (__m512d, __m512d), sum: __m512i) -> (__m512d, __m512d) {
        // SAFETY: the caller runs on AVX-512F (trait contract).
        unsafe {
            let (low, high) = widen_zmm(sum);
            (_mm512_add_pd(total.0, low), _mm512_add_pd(total.1, high))
        }
    }
    #[inline(always)]
    unsafe fn exact_digits(high: __m512i, low: __m512i) -> (__m512d, __m512d) {
        // SAFETY: the caller runs on AVX-512F (trait contract). `vcvtdq2ps` rounds as MXCSR
        // says: to nearest.
        unsafe { exact_digits_zmm(high, low) }
    }
    #[inline(always)]
    unsafe fn round_scaled(total: (__m512d, __m512d), scale: f32) -> __m512 {
        // SAFETY: the caller runs on AVX-512F (trait contract). `vcvtdq2ps` rounds as MXCSR
        // says: to nearest.
        unsafe { _mm512_mul_ps(round_zmm(total), _mm512_set1_ps(scale)) }
    }
    #[inline(always)]
    unsafe fn load(from: *const f32) -> __m512 {
        // SAFETY: AVX-512F, and 16 floats readable (trait contract).
        unsafe { _mm512_loadu_ps(from) }
    }
    #[inline(always)]
    unsafe fn store(to: *mut f32, value: __m512) {
        // SAFETY: AVX-512F, and 16 floats writable (trait contract).
        unsafe { _mm512_storeu_ps(to, value) }
    }
    #[inline(always)]
    unsafe fn mul(a: __m512, b: __m512) -> __m512 {
        // SAFETY: the caller runs on AVX-512F (trait contract).
        unsafe { _mm512_mul_ps(a, b) }
    }
    #[inline(always)]
    unsafe fn add(a: __m512, b: __m512) -> __m512 {
        // SAFETY: the caller runs on AVX-512F (trait contract).
        unsafe { _mm512_add_ps(a, b) }
    }
}

// SAFETY: as for its `Int8Lanes`; the weights offset by 128 are the unsigned side.
unsafe impl SignedByteLanes for VnniZmm {
    const WEIGHT_OFFSET: i32 = 128;
    #[inline(always)]
    unsafe fn offset_bytes(bytes: __m512i) -> __m512i {
        // SAFETY: the caller runs on AVX-512F (trait contract).
        unsafe { _mm512_xor_si512(bytes, _mm512_set1_epi8(i8::MIN)) }
    }
    #[inline(always)]
    unsafe fn splat_integers(value: i32) -> __m512i {
        // SAFETY: the caller runs on AVX-512F (trait contract).
        unsafe { _mm512_set1_epi32(value) }
    }
    #[inline(always)]
    unsafe fn integers_scaled(sums: __m512i, scale: f32) -> __m512 {
        // SAFETY: the caller runs on AVX-512F (trait contract). `vcvtdq2ps` rounds as MXCSR
        // says: to nearest.
        unsafe { _mm512_mul_ps(_mm512_cvtepi32_ps(sums), _mm512_set1_ps(scale)) }
    }
}

// SAFETY: `vpdpbusd` adds its four u8 x i8 products into the i32 lane exactly.
unsafe impl WholeByteLanes for VnniZmm {}

/// The eight i32 lanes as f64, low four then high four (exact).
///
/// # Safety
/// AVX2.
#[inline(always)]
unsafe fn widen_ymm(sum: __m256i) -> (__m256d, __m256d) {
    // SAFETY: the caller runs on AVX2.
    unsafe {
        (
            _mm256_cvtepi32_pd(_mm256_castsi256_si128(sum)),
            _mm256_cvtepi32_pd(_mm256_extracti128_si256::<1>(sum)),
        )
    }
}

/// The sixteen i32 lanes as f64, low eight then high eight (exact).
///
/// # Safety
/// AVX-512F.
#[inline(always)]
unsafe fn widen_zmm(sum: __m512i) -> (__m512d, __m512d) {
    // SAFETY: the caller runs on AVX-512F.
    unsafe {
        (
            _mm512_cvtepi32_pd(_mm512_castsi512_si256(sum)),
            _mm512_cvtepi32_pd(_mm512_extracti64x4_epi64::<1>(sum)),
        )
    }
}

/// `128 high + low` per lane of i32 digit sums, exact in f64 (the AMX kernel's too).
///
/// # Safety
/// AVX-512F.
#[inline(always)]
pub(crate) unsafe fn exact_digits_zmm(high: __m512i, low: __m512i) -> (__m512d, __m512d) {
    // SAFETY: the caller runs on AVX-512F.
    unsafe {
        let base = _mm512_set1_pd(f64::from(ops::DIGIT_BASE));
        let (high, low) = (widen_zmm(high), widen_zmm(low));
        (
            _mm512_add_pd(_mm512_mul_pd(high.0, base), low.0),
            _mm512_add_pd(_mm512_mul_pd(high.1, base), low.1),
        )
    }
}

/// Sixteen exact integers in f64 lanes rounded to f32 (to nearest, as MXCSR says; Rust code
/// never changes it), in lane order.
///
/// # Safety
/// AVX-512F.
#[inline(always)]
pub(crate) unsafe fn round_zmm((low, high): (__m512d, __m512d)) -> __m512 {
    // SAFETY: the caller runs on AVX-512F.
    unsafe {
        let low = _mm512_castpd256_pd512(_mm256_castps_pd(_mm512_cvtpd_ps(low)));
        let high = _mm256_castps_pd(_mm512_cvtpd_ps(high));
        _mm512_castpd_ps(_mm512_insertf64x4::<1>(low, high))
    }
}
