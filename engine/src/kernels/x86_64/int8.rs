//! The int8 convolution ([`Kernels::conv_int8`](crate::kernels::Kernels) and its
//! single-pixel form) both x86-64 backends run: one generic body over an integer dot
//! product ([`Int8Lanes`]: AVX2 `vpmaddubsw` on YMM, AVX-512 VNNI `vpdpbusd` on ZMM),
//! instantiated inside each backend's thin `#[target_feature]` wrapper, as
//! [`super::f32_tile`] is for f32.
//!
//! A tile is `P` consecutive output positions (row-major over the output map, so a tile may
//! wrap onto the next row, and maps of one or two pixels still use it) times `V` vectors of
//! output channels. The tile's exact i32 sums of one digit plane are accumulated in
//! registers over every kernel tap and input-channel quad (the contract's sums run over the
//! whole kernel and the input has one scale), then the two planes' sums combined exactly,
//! rounded and scaled once. A pixel whose tap falls in the padding reads a row of zero
//! codes ([`ZERO_ROW`]), as the convolution defines it, so border pixels need no separate
//! path, and every output value is the same whichever tile (or the single-pixel path)
//! computes it.
//!
//! Channel blocks are the outer loop and pixel tiles the inner one, so a block's weights
//! (up to 295 KB, ResNet layer4 at 64 channels) stay in the L2 cache while every pixel
//! reads them; the other order streamed the whole kernel from L3 once per pixel tile. The
//! weight layout keeps each 64-channel block's quads in one stretch, in the order a tile
//! reads them ([`int8_quad_index`](crate::kernels::int8_quad_index)), so they spread over
//! every cache set.
//!
//! The unsigned-by-signed byte products need activations in 0..=127, which every trunk input
//! is (a ReLU output); [`DigitRows::nonnegative`] says so, and any other input goes to the
//! scalar reference.
//!
//! The U-Net's inputs have both signs: [`Kernels::conv_int8_codes`] reads whole signed codes
//! ([`CodeRows`], i16) and multiplies them by the weights widened to i16, two products a
//! lane (AVX-512 VNNI `vpdpwssd`, AVX2 `vpmaddwd`): the same tiles, the same exact sums.
//! A quad's four weights of one output channel, widened, fill two lanes, which meet the
//! same quad's codes broadcast as (c0, c1), (c2, c3); the two lanes of each channel are
//! added once per tap, and the taps' i32 sums added exactly in f64 (a whole kernel's can
//! exceed i32).
//!
//! [`DigitRows::nonnegative`]: crate::kernels::DigitRows::nonnegative
//! [`Kernels::conv_int8_codes`]: crate::kernels::Kernels::conv_int8_codes

use core::arch::x86_64::{
    __m256, __m256d, __m256i, __m512, __m512d, __m512i, _mm_loadu_si128, _mm256_add_epi32,
    _mm256_add_pd, _mm256_add_ps, _mm256_castps_pd, _mm256_castsi256_si128, _mm256_cvtepi8_epi16,
    _mm256_cvtepi32_pd, _mm256_cvtpd_ps, _mm256_extracti128_si256, _mm256_hadd_epi32,
    _mm256_loadu_ps, _mm256_loadu_si256, _mm256_madd_epi16, _mm256_maddubs_epi16, _mm256_mul_pd,
    _mm256_mul_ps, _mm256_permute4x64_epi64, _mm256_set_m128, _mm256_set1_epi16, _mm256_set1_epi32,
    _mm256_set1_epi64x, _mm256_set1_pd, _mm256_set1_ps, _mm256_setzero_pd, _mm256_setzero_ps,
    _mm256_setzero_si256, _mm256_storeu_ps, _mm256_storeu_si256, _mm512_add_epi32, _mm512_add_pd,
    _mm512_add_ps, _mm512_castpd_ps, _mm512_castpd256_pd512, _mm512_castsi512_si256,
    _mm512_cvtepi8_epi16, _mm512_cvtepi32_pd, _mm512_cvtpd_ps, _mm512_dpbusd_epi32,
    _mm512_dpwssd_epi32, _mm512_extracti64x4_epi64, _mm512_insertf64x4, _mm512_loadu_ps,
    _mm512_loadu_si512, _mm512_mul_pd, _mm512_mul_ps, _mm512_permutex2var_epi32, _mm512_set1_epi32,
    _mm512_set1_epi64, _mm512_set1_pd, _mm512_set1_ps, _mm512_setr_epi32, _mm512_setzero_pd,
    _mm512_setzero_ps, _mm512_setzero_si512, _mm512_storeu_ps, _mm512_storeu_si512,
};

use super::{prefetch_lines, prefetch_lines_into_l2};
use crate::kernels::scalar::{
    CodeSums, assert_code_lengths, assert_int8_lengths, assert_int8_pixel_lengths,
    assert_matvec_codes_lengths, conv_int8_pixel, conv_int8_pixels, exact_row_sum, scaled_row_sum,
};
use crate::kernels::{
    Accumulate, CodeRows, ConvShape, DigitRows, INT8_CHANNEL_BLOCK, MAX_DIGIT_CHANNELS, QUAD,
    int8_quad_stride, ops,
};

/// An integer dot product over input-channel quads, `WIDTH` output channels a vector, and
/// the f32 arithmetic around it.
///
/// # Safety
/// Every method requires the CPU to support the vector's instructions (AVX2 for
/// [`PairSumsYmm`], AVX-512 F/BW/VNNI for [`VnniZmm`]); pointers must cover what each
/// method reads or writes.
pub(crate) unsafe trait Int8Lanes {
    /// `WIDTH` i32 lanes: sums, and the bytes of `WIDTH` weight quads or a broadcast quad.
    type Integers: Copy;
    /// `WIDTH` f32 lanes.
    type Floats: Copy;
    /// `WIDTH` integers held exactly in two vectors of f64 lanes: sums over a whole kernel
    /// that i32 lanes cannot hold.
    type Exact: Copy;
    const WIDTH: usize;
    unsafe fn zero_integers() -> Self::Integers;
    unsafe fn zero_floats() -> Self::Floats;
    unsafe fn zero_exact() -> Self::Exact;
    /// The quads of `WIDTH` output channels (`4 WIDTH` bytes).
    unsafe fn load_weights(from: *const i8) -> Self::Integers;
    /// Four activations, repeated in every lane.
    unsafe fn broadcast_quad(from: *const i8) -> Self::Integers;
    /// `sum + activations . weights` per lane: four u8 x i8 products, exact for
    /// activations in 0..=127.
    unsafe fn dot_quads(
        sum: Self::Integers,
        activations: Self::Integers,
        weights: Self::Integers,
    ) -> Self::Integers;
    /// `2 WIDTH` consecutive weights widened to i16, two a lane. For a convolution these are
    /// the quads of `WIDTH / 2` output channels: lanes `2k` and `2k + 1` hold weights (0, 1)
    /// and (2, 3) of the `k`-th channel; for a FiLM row, `2 WIDTH` of its columns.
    unsafe fn widen_quads(from: *const i8) -> Self::Integers;
    /// Four i16 codes (one quad) as lane pairs: (c0, c1), (c2, c3), repeated.
    unsafe fn broadcast_codes(from: *const i16) -> Self::Integers;
    /// `sum + codes . weights` per lane: two i16 x i16 products, exact for codes and
    /// weights in the scheme's range (|product| <= 16383 x 128).
    unsafe fn dot_code_pairs(
        sum: Self::Integers,
        codes: Self::Integers,
        weights: Self::Integers,
    ) -> Self::Integers;
    /// `2 WIDTH` consecutive i16 codes, two a lane.
    unsafe fn load_codes(from: *const i16) -> Self::Integers;
    /// `a + b` per i32 lane (wrapping).
    unsafe fn add_integers(a: Self::Integers, b: Self::Integers) -> Self::Integers;
    /// The sum of every i32 lane, exact.
    unsafe fn lane_sum(sums: Self::Integers) -> i64;
    /// The sums of adjacent lane pairs: those of `first` (channels 0 .. WIDTH/2), then those
    /// of `second`, in channel order.
    unsafe fn add_lane_pairs(first: Self::Integers, second: Self::Integers) -> Self::Integers;
    /// `total + sum` per lane, exact (integers in f64 lanes, below 2^53).
    unsafe fn add_exact(total: Self::Exact, sum: Self::Integers) -> Self::Exact;
    /// `128 high + low` per lane, exact.
    unsafe fn exact_digits(high: Self::Integers, low: Self::Integers) -> Self::Exact;
    /// The exact integers rounded to f32 (to nearest), times `scale`: two roundings.
    unsafe fn round_scaled(total: Self::Exact, scale: f32) -> Self::Floats;
    unsafe fn load(from: *const f32) -> Self::Floats;
    unsafe fn store(to: *mut f32, value: Self::Floats);
    unsafe fn mul(a: Self::Floats, b: Self::Floats) -> Self::Floats;
    unsafe fn add(a: Self::Floats, b: Self::Floats) -> Self::Floats;
}

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
        // SAFETY: the caller runs on AVX-512F (trait contract). As for AVX2.
        unsafe { exact_digits_zmm(high, low) }
    }
    #[inline(always)]
    unsafe fn round_scaled(total: (__m512d, __m512d), scale: f32) -> __m512 {
        // SAFETY: the caller runs on AVX-512F (trait contract). As for AVX2.
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

/// Zero codes that a pixel whose kernel tap falls in the padding reads instead of an input
/// row (as digits: 2,048 zero bytes): a row of the widest input the kernels take.
static ZERO_ROW: [i16; MAX_DIGIT_CHANNELS] = [0; MAX_DIGIT_CHANNELS];

/// The pixels of one tile: how many there are (`count <= P`; the last tile of a map may be
/// short) and where they read.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PixelTile<const P: usize> {
    count: usize,
    /// Input coordinates of kernel tap (0, 0) per pixel, negative inside the padding.
    pub(crate) origins: [(isize, isize); P],
}

impl<const P: usize> PixelTile<P> {
    pub(crate) fn new(shape: &ConvShape, first: usize, count: usize) -> Self {
        let out_width = shape.out_width();
        let origins = core::array::from_fn(|pixel| {
            let position = first + pixel;
            (
                ((position / out_width) * shape.stride) as isize - shape.padding_height as isize,
                ((position % out_width) * shape.stride) as isize - shape.padding_width as isize,
            )
        });
        PixelTile { count, origins }
    }

    /// The input row (pixel) each pixel of the tile reads at kernel tap `(kernel_y,
    /// kernel_x)`, or `None` where the tap lies in the padding or the pixel is past `count`.
    fn rows(&self, shape: &ConvShape, kernel_y: usize, kernel_x: usize) -> [Option<usize>; P] {
        tap_rows(shape, &self.origins, self.count, (kernel_y, kernel_x))
    }
}

/// The input row (pixel) each of the first `count` pixels whose tap (0, 0) lies at
/// `origins` reads at kernel tap `(kernel_y, kernel_x)`: `None` in the padding and past
/// `count` (the AMX kernel's blocks too).
pub(crate) fn tap_rows<const P: usize>(
    shape: &ConvShape,
    origins: &[(isize, isize)],
    count: usize,
    (kernel_y, kernel_x): (usize, usize),
) -> [Option<usize>; P] {
    let mut rows = [None; P];
    for (row, &(top, left)) in rows.iter_mut().zip(origins).take(count) {
        let in_y = top + kernel_y as isize;
        let in_x = left + kernel_x as isize;
        let inside = (0..shape.in_height as isize).contains(&in_y)
            && (0..shape.in_width as isize).contains(&in_x);
        *row = inside.then(|| in_y as usize * shape.in_width + in_x as usize);
    }
    rows
}

/// Whether the SIMD int8 tiles apply: both digits readable as u8, and whole input-channel
/// quads in each row (so a 4-byte activation load stays inside its pixel). The int8 layers
/// of the model all qualify; the stem's 7x7 kernel over 3 channels would not, which is why it
/// runs over patches (`pyramid::stem`).
pub(crate) fn tiles_apply(shape: &ConvShape, input: &DigitRows<'_>) -> bool {
    input.nonnegative && shape.in_channels.is_multiple_of(QUAD)
}

/// `sums +` the exact i32 products of one kernel tap, both digit planes (high, then low):
/// `P` pixels (their activation rows in each plane) x `V` vectors of channels, over every
/// input-channel quad. The sums stay in registers for the whole quad loop, and each quad's
/// weights, loaded once, serve both planes: a loop per plane loaded them twice, the second
/// time from L1 (in-process A/B, encode 0.93-0.955x on AVX-512 VNNI, 0.90-1.01x on AVX2).
///
/// # Safety
/// The CPU supports `L`; each pointer in `activations` starts a row of `4 quads` readable
/// bytes; `weights` points at quad 0 of the tap's first channel of the block, with `quads`
/// quads, `quad_stride` bytes apart, of `V WIDTH` channels readable from there.
#[inline(always)]
unsafe fn add_digit_products<L: Int8Lanes, const P: usize, const V: usize>(
    mut sums: [[[L::Integers; V]; P]; 2],
    activations: [[*const i8; P]; 2],
    weights: *const i8,
    quads: usize,
    quad_stride: usize,
) -> [[[L::Integers; V]; P]; 2] {
    for quad in 0..quads {
        // SAFETY: quad `quad` of the block's channels and of each row is inside what the
        // caller vouched for.
        unsafe {
            let row = weights.add(quad * quad_stride);
            let vectors: [L::Integers; V] =
                core::array::from_fn(|vector| L::load_weights(row.add(vector * L::WIDTH * QUAD)));
            for pixel in 0..P {
                for plane in 0..2 {
                    let broadcast = L::broadcast_quad(activations[plane][pixel].add(quad * QUAD));
                    for vector in 0..V {
                        sums[plane][pixel][vector] =
                            L::dot_quads(sums[plane][pixel][vector], broadcast, vectors[vector]);
                    }
                }
            }
        }
    }
    sums
}

/// Quantized activations as the SIMD tiles read them: the exact code sums of a tile over
/// the whole kernel, rounded and scaled, and (through [`CodeSums`]) the reference's reading
/// for what the tiles leave.
pub(crate) trait TileInput: CodeSums {
    /// `round(S) * scale` for `P` pixels x `V` vectors of channels from `channel`, `S` the
    /// exact code sums over every tap and input channel.
    ///
    /// # Safety
    /// The CPU supports `L`; the slices have the lengths `shape` implies; [`tiles_apply`]
    /// holds for digit planes; `pixels` is a tile of this output; the block's `V WIDTH`
    /// channels from `channel` are inside the output channels.
    unsafe fn tile_totals<L: Int8Lanes, const P: usize, const V: usize>(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        pixels: &PixelTile<P>,
        channel: usize,
    ) -> [[L::Floats; V]; P];
}

/// Where each of a tile's pixels reads at one kernel tap: its input row of `row_stride`
/// elements in `values`, or [`ZERO_ROW`] in the padding. `None` when no pixel reads the
/// input at this tap (nothing to add).
#[inline(always)]
fn tap_sources<T: Copy, const P: usize>(
    rows: [Option<usize>; P],
    values: &[T],
    row_stride: usize,
) -> Option<[*const T; P]> {
    rows.iter().any(Option::is_some).then(|| {
        rows.map(|row| match row {
            Some(row) => values[row * row_stride..][..row_stride].as_ptr(),
            None => ZERO_ROW.as_ptr().cast(),
        })
    })
}

/// Both digit planes' exact i32 sums over the whole kernel for a tile (exact:
/// [`MAX_DIGIT_TERMS`]), high then low. Each quad's weights serve both planes as they are
/// loaded; the tile is sized so both sets of sums stay in registers.
///
/// # Safety
/// As for [`TileInput::tile_totals`].
#[inline(always)]
unsafe fn digit_sums<L: Int8Lanes, const P: usize, const V: usize>(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    weight: &[i8],
    pixels: &PixelTile<P>,
    channel: usize,
) -> [[[L::Integers; V]; P]; 2] {
    let in_channels = shape.in_channels;
    let quad_stride = int8_quad_stride(shape.out_channels, channel);
    // SAFETY: the caller runs on `L`'s CPU.
    let mut sums = [[[unsafe { L::zero_integers() }; V]; P]; 2];
    for kernel_y in 0..shape.kernel_height {
        for kernel_x in 0..shape.kernel_width {
            let rows = pixels.rows(shape, kernel_y, kernel_x);
            let (Some(high), Some(low)) = (
                tap_sources(rows, input.high, in_channels),
                tap_sources(rows, input.low, in_channels),
            ) else {
                continue;
            };
            let tap = kernel_y * shape.kernel_width + kernel_x;
            let weights = weight[shape.int8_index(tap, 0, channel)..].as_ptr();
            let quads = in_channels / QUAD;
            // SAFETY: every source is an input row of `in_channels` = 4 quads values
            // (`tiles_apply`) or the zero row, as long; the tap's quads of the block's
            // channels are inside `weight` (the caller's promise).
            unsafe {
                sums =
                    add_digit_products::<L, P, V>(sums, [high, low], weights, quads, quad_stride);
            }
        }
    }
    sums
}

impl TileInput for DigitRows<'_> {
    /// Each digit plane summed over the whole kernel in i32 (exact: [`MAX_DIGIT_TERMS`]),
    /// the two combined exactly.
    #[inline(always)]
    unsafe fn tile_totals<L: Int8Lanes, const P: usize, const V: usize>(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        pixels: &PixelTile<P>,
        channel: usize,
    ) -> [[L::Floats; V]; P] {
        // SAFETY: the caller's promises, passed on.
        let [high, low] = unsafe { digit_sums::<L, P, V>(shape, self, weight, pixels, channel) };
        // Loops, not `array::from_fn`: a closure does not inherit the caller's target
        // features, and its intrinsics would become calls.
        // SAFETY: the caller runs on `L`'s CPU.
        let mut totals = [[unsafe { L::zero_floats() }; V]; P];
        for pixel in 0..P {
            for vector in 0..V {
                // SAFETY: the caller runs on `L`'s CPU.
                totals[pixel][vector] = unsafe {
                    let exact = L::exact_digits(high[pixel][vector], low[pixel][vector]);
                    L::round_scaled(exact, self.scale)
                };
            }
        }
        totals
    }
}

/// Quad rows of weights [`CodeRows`]' tiles ask L2 for ahead of the one they read (64: 16
/// KB for the AVX-512 tile; with 16 rows into L1 the int8 denoising loop took
/// 1.17-1.19x as long on Zen 4, session 16).
const PREFETCH_QUADS: usize = 64;

impl TileInput for CodeRows<'_> {
    /// The codes times the widened weights, two lanes a channel, added up per tap in i32
    /// (exact: [`MAX_DIGIT_CHANNELS`]), the taps' sums in f64 (exact).
    #[inline(always)]
    unsafe fn tile_totals<L: Int8Lanes, const P: usize, const V: usize>(
        &self,
        shape: &ConvShape,
        weight: &[i8],
        pixels: &PixelTile<P>,
        channel: usize,
    ) -> [[L::Floats; V]; P] {
        let row_stride = CodeRows::row_stride(shape.in_channels);
        let quads = row_stride / QUAD;
        let quad_stride = int8_quad_stride(shape.out_channels, channel);
        // SAFETY: the caller runs on `L`'s CPU.
        let mut totals = [[unsafe { L::zero_exact() }; V]; P];
        for kernel_y in 0..shape.kernel_height {
            for kernel_x in 0..shape.kernel_width {
                let rows = pixels.rows(shape, kernel_y, kernel_x);
                let Some(codes) = tap_sources(rows, self.codes, row_stride) else {
                    continue;
                };
                let tap = kernel_y * shape.kernel_width + kernel_x;
                let weights = weight[shape.int8_index(tap, 0, channel)..].as_ptr();
                // SAFETY: every source holds `quads` whole quads of codes (padded rows,
                // `CodeRows`, or the zero row, at least as long); the tap's (zero-padded)
                // quads of the block are readable: the caller's promises.
                unsafe {
                    // Per pixel and vector: the halves of its channels (lane pairs).
                    let mut sums = [[(L::zero_integers(), L::zero_integers()); V]; P];
                    for quad in 0..quads {
                        let row = weights.add(quad * quad_stride);
                        // The U-Net's weights come from L3 once per step, a quad row's
                        // `V WIDTH` channels (one or two cache lines) `quad_stride` bytes
                        // apart: ask L2 for the lines `PREFETCH_QUADS` rows ahead. A hint only
                        // (it never faults), hence the wrapping address.
                        let ahead = row.wrapping_add(PREFETCH_QUADS * quad_stride);
                        prefetch_lines_into_l2(ahead, V * L::WIDTH * QUAD);
                        let halves: [(L::Integers, L::Integers); V] =
                            core::array::from_fn(|vector| {
                                let first = row.add(vector * L::WIDTH * QUAD);
                                (
                                    L::widen_quads(first),
                                    L::widen_quads(first.add(L::WIDTH * QUAD / 2)),
                                )
                            });
                        for pixel in 0..P {
                            let broadcast = L::broadcast_codes(codes[pixel].add(quad * QUAD));
                            for vector in 0..V {
                                let (low, high) = &mut sums[pixel][vector];
                                *low = L::dot_code_pairs(*low, broadcast, halves[vector].0);
                                *high = L::dot_code_pairs(*high, broadcast, halves[vector].1);
                            }
                        }
                    }
                    for pixel in 0..P {
                        for vector in 0..V {
                            let (low, high) = sums[pixel][vector];
                            let total = &mut totals[pixel][vector];
                            *total = L::add_exact(*total, L::add_lane_pairs(low, high));
                        }
                    }
                }
            }
        }
        // SAFETY: the caller runs on `L`'s CPU.
        let mut rounded = [[unsafe { L::zero_floats() }; V]; P];
        for pixel in 0..P {
            for vector in 0..V {
                // SAFETY: the caller runs on `L`'s CPU.
                rounded[pixel][vector] =
                    unsafe { L::round_scaled(totals[pixel][vector], self.scale) };
            }
        }
        rounded
    }
}

/// `out (+)= totals * weight_scales + bias` for `count` pixels whose channel blocks start
/// at `out[pixel * stride]`, unfused as the scalar reference does it.
///
/// # Safety
/// The CPU supports `L`; `weight_scales` and `bias` hold `V WIDTH` floats; `out` holds the
/// `V WIDTH` channels of each of the `count` pixels, `stride` apart.
#[inline(always)]
unsafe fn store<L: Int8Lanes, const P: usize, const V: usize>(
    totals: &[[L::Floats; V]; P],
    count: usize,
    (weight_scales, bias): (&[f32], &[f32]),
    out: &mut [f32],
    stride: usize,
    accumulate: Accumulate,
) {
    for (pixel, total) in totals.iter().enumerate().take(count) {
        let out = &mut out[pixel * stride..][..V * L::WIDTH];
        for (vector, &total) in total.iter().enumerate() {
            let at = vector * L::WIDTH;
            // SAFETY: `out`, `weight_scales` and `bias` hold `V WIDTH` floats; each access
            // covers WIDTH from `at`; the caller runs on `L`'s CPU.
            unsafe {
                let scaled = L::mul(total, L::load(weight_scales.as_ptr().add(at)));
                let mut value = L::add(scaled, L::load(bias.as_ptr().add(at)));
                if accumulate == Accumulate::Add {
                    value = L::add(L::load(out.as_ptr().add(at)), value);
                }
                L::store(out.as_mut_ptr().add(at), value);
            }
        }
    }
}

/// The channel blocks of `V WIDTH` channels from `*channel` while they fit, each over
/// every pixel tile of the output; advances `*channel` past them.
///
/// # Safety
/// As for [`conv`].
#[inline(always)]
unsafe fn channel_blocks<L: Int8Lanes, I: TileInput, const P: usize, const V: usize>(
    shape: &ConvShape,
    input: &I,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
    channel: &mut usize,
) {
    // A block reads its quads `quad_stride` apart, which holds inside one block of the
    // weight layout: blocks from a multiple of their width never straddle one.
    const { assert!(INT8_CHANNEL_BLOCK.is_multiple_of(V * L::WIDTH)) };
    let out_channels = shape.out_channels;
    let positions = shape.out_height() * shape.out_width();
    let width = V * L::WIDTH;
    while *channel + width <= out_channels {
        let block = *channel..*channel + width;
        for first in (0..positions).step_by(P) {
            let pixels = PixelTile::<P>::new(shape, first, (positions - first).min(P));
            // SAFETY: the caller's promises; the block and the tile are inside the output.
            unsafe {
                let totals = input.tile_totals::<L, P, V>(shape, weight, &pixels, *channel);
                let out = &mut output[first * out_channels + *channel..];
                let parameters = (&weight_scales[block.clone()], &bias[block.clone()]);
                store::<L, P, V>(
                    &totals,
                    pixels.count,
                    parameters,
                    out,
                    out_channels,
                    accumulate,
                );
            }
        }
        *channel += width;
    }
}

/// The whole int8 convolution: blocks of `V` vectors of channels, then single vectors, the
/// channels left over on the scalar reference.
///
/// # Safety
/// The CPU supports `L`; the slice lengths are those
/// [`assert_int8_lengths`](crate::kernels::scalar::assert_int8_lengths) (or, for codes,
/// `assert_code_lengths`) checks; [`tiles_apply`] holds for digit planes.
#[inline(always)]
pub(crate) unsafe fn conv<L: Int8Lanes, I: TileInput, const P: usize, const V: usize>(
    shape: &ConvShape,
    input: &I,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let mut channel = 0;
    // SAFETY: this function's contract is theirs.
    unsafe {
        channel_blocks::<L, I, P, V>(shape, input, parameters, output, accumulate, &mut channel);
        channel_blocks::<L, I, P, 1>(shape, input, parameters, output, accumulate, &mut channel);
    }
    if channel < shape.out_channels {
        let positions = shape.out_height() * shape.out_width();
        conv_int8_pixels(
            shape,
            input,
            parameters,
            output,
            accumulate,
            0..positions,
            channel..shape.out_channels,
        );
    }
}

/// Output pixel `(out_y, out_x)` of [`conv`] (overwriting) into `output` (its
/// `out_channels` values): the one-pixel tile, so the same bits.
///
/// # Safety
/// As for [`conv`]; the pixel is in the output and `output` holds its channels.
#[inline(always)]
pub(crate) unsafe fn conv_pixel<L: Int8Lanes, const V: usize>(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    (out_y, out_x): (usize, usize),
    output: &mut [f32],
) {
    let pixels = PixelTile::<1>::new(shape, out_y * shape.out_width() + out_x, 1);
    let out_channels = shape.out_channels;
    let overwrite = Accumulate::Overwrite;
    let mut channel = 0;
    while channel < out_channels {
        let block = channel..out_channels;
        let parameters = (&weight_scales[block.clone()], &bias[block.clone()]);
        let out = &mut output[channel..];
        // SAFETY: the caller's promises; each block is inside `out_channels`.
        unsafe {
            if channel + V * L::WIDTH <= out_channels {
                let totals = input.tile_totals::<L, 1, V>(shape, weight, &pixels, channel);
                store::<L, 1, V>(&totals, 1, parameters, out, 0, overwrite);
                channel += V * L::WIDTH;
            } else if channel + L::WIDTH <= out_channels {
                let totals = input.tile_totals::<L, 1, 1>(shape, weight, &pixels, channel);
                store::<L, 1, 1>(&totals, 1, parameters, out, 0, overwrite);
                channel += L::WIDTH;
            } else {
                break;
            }
        }
    }
    if channel < out_channels {
        conv_int8_pixel(
            shape,
            input,
            (weight, weight_scales, bias),
            output,
            overwrite,
            (out_y, out_x),
            channel..out_channels,
        );
    }
}

/// Columns of a row summed in i32 lanes before the lanes are added up in i64: each lane then
/// holds at most `MAX_DIGIT_CHANNELS / WIDTH` products of `|code| <= 16383` and
/// `|q_w| <= 128`, far inside i32, and so does the sum of a segment.
const MATVEC_SEGMENT: usize = MAX_DIGIT_CHANNELS;

/// Bytes ahead of the weights being read that [`segment_sum`] asks the caches for. The FiLM
/// rows are one contiguous stream from L3, yet the hardware prefetchers alone kept the
/// product at the rate of the f32 version; 4 KB ahead cut its share of the loop's samples
/// by about a quarter (perf, 1-16 KB tried).
const MATVEC_PREFETCH: usize = 4096;

/// [`Kernels::matvec_int8_codes`]: each row's weights widened to i16 and multiplied by the
/// codes two a lane (`vpdpwssd`, `vpmaddwd`), the row's exact sum formed in i64 from
/// segments of [`MATVEC_SEGMENT`] columns, the columns past the last whole vector on the
/// scalar path (integer sums are exact in any order).
///
/// # Safety
/// The CPU supports `L`.
///
/// [`Kernels::matvec_int8_codes`]: crate::kernels::Kernels::matvec_int8_codes
#[inline(always)]
pub(crate) unsafe fn matvec_codes<L: Int8Lanes>(
    weight: &[i8],
    row_scales: &[f32],
    input: &CodeRows<'_>,
    base: &[f32],
    output: &mut [f32],
) {
    let cols = assert_matvec_codes_lengths(weight, row_scales, input, base, output.len());
    let step = 2 * L::WIDTH;
    let vector_cols = cols - cols % step;
    let codes = &input.codes[..cols];
    for (r, out) in output.iter_mut().enumerate() {
        let row = &weight[r * cols..][..cols];
        let mut sum = 0i64;
        for start in (0..vector_cols).step_by(MATVEC_SEGMENT) {
            let end = (start + MATVEC_SEGMENT).min(vector_cols);
            // SAFETY: `start..end` lies within `vector_cols <= cols`, the length of `row`
            // and `codes`, in whole steps; the caller runs on `L`'s CPU.
            sum += unsafe { segment_sum::<L>(row.as_ptr(), codes.as_ptr(), start..end) };
        }
        sum += exact_row_sum(&row[vector_cols..], &codes[vector_cols..]);
        *out = scaled_row_sum(sum, input.scale, row_scales[r], base[r]);
    }
}

/// `sum_c code[c] w[c]` over `columns`, exact.
///
/// # Safety
/// The CPU supports `L`; `columns` starts and ends at multiples of `2 WIDTH`, spans at most
/// [`MATVEC_SEGMENT`], and both pointers are readable up to its end.
#[inline(always)]
unsafe fn segment_sum<L: Int8Lanes>(
    weights: *const i8,
    codes: *const i16,
    columns: core::ops::Range<usize>,
) -> i64 {
    let step = 2 * L::WIDTH;
    // Four independent sums hide the latency of the products.
    // SAFETY: the caller runs on `L`'s CPU.
    let mut sums = [unsafe { L::zero_integers() }; 4];
    let mut column = columns.start;
    // SAFETY (both loops): every read is `2 WIDTH` elements from a column below
    // `columns.end`, in whole steps: inside what the caller vouched for.
    while column + 4 * step <= columns.end {
        prefetch_lines(weights.wrapping_add(column + MATVEC_PREFETCH), 4 * step);
        for (k, sum) in sums.iter_mut().enumerate() {
            let at = column + k * step;
            *sum = unsafe {
                L::dot_code_pairs(
                    *sum,
                    L::load_codes(codes.add(at)),
                    L::widen_quads(weights.add(at)),
                )
            };
        }
        column += 4 * step;
    }
    while column < columns.end {
        sums[0] = unsafe {
            L::dot_code_pairs(
                sums[0],
                L::load_codes(codes.add(column)),
                L::widen_quads(weights.add(column)),
            )
        };
        column += step;
    }
    // SAFETY: the caller runs on `L`'s CPU; the lanes' sums fit i32 (`MATVEC_SEGMENT`).
    unsafe {
        let pairs = (
            L::add_integers(sums[0], sums[1]),
            L::add_integers(sums[2], sums[3]),
        );
        L::lane_sum(L::add_integers(pairs.0, pairs.1))
    }
}

/// Pixels and channel vectors of a tile, per backend, both digit planes' sums held across
/// the kernel: AVX2 has 16 YMM registers (8 sums, 4 weight vectors, the broadcast, the ones
/// and a product); AVX-512 has 32 ZMM registers (16 sums, 4 weight vectors, the
/// broadcast). Session 7 took (2, 2) and (3, 4), half the pixels of session 5's one-plane
/// tiles; since both planes share one quad loop, the in-process A/B of whole encodes put
/// (1, 4) at 0.91-0.97x of (2, 2) on AVX2 ((1, 8) spills: 0.95-1.17x) and (2, 4) at
/// 0.98-0.986x of (3, 4) on AVX-512 ((6, 2) 1.09-1.13x, (1, 4) 1.23-1.35x).
const AVX2_TILE: (usize, usize) = (1, 4);
const VNNI_TILE: (usize, usize) = (2, 4);

/// The same for signed codes, whose vectors of channels take two sums each: (2, 2) on AVX2
/// (8 sums, 4 widened weight halves; the denoising loop 0.92-0.99x of (4, 1)'s, in-process),
/// (4, 2) on AVX-512 (16 sums, 4 widened weight halves, 4 broadcasts; (2, 4) 1.07-1.11x,
/// (4, 1) 1.18-1.21x), the U-Net's shortest sequence being 4 positions.
const AVX2_CODES_TILE: (usize, usize) = (2, 2);
const VNNI_CODES_TILE: (usize, usize) = (4, 2);

/// [`conv`] and [`conv_pixel`] compiled for one backend: the thin `#[target_feature]`
/// wrappers of the shared body.
macro_rules! backend {
    ($module:ident, $lanes:ty, $tile:expr, $codes_tile:expr, $features:literal) => {
        pub(crate) mod $module {
            use crate::kernels::{Accumulate, CodeRows, ConvShape, DigitRows};

            const TILE: (usize, usize) = $tile;
            const CODES_TILE: (usize, usize) = $codes_tile;

            /// [`matvec_codes`](super::matvec_codes) on this backend.
            ///
            /// # Safety
            /// The CPU supports the backend's features.
            #[target_feature(enable = $features)]
            pub(crate) unsafe fn matvec_codes(
                weight: &[i8],
                row_scales: &[f32],
                input: &CodeRows<'_>,
                base: &[f32],
                output: &mut [f32],
            ) {
                // SAFETY: this function's contract is the body's.
                unsafe { super::matvec_codes::<$lanes>(weight, row_scales, input, base, output) }
            }

            /// [`conv`](super::conv) of signed codes on this backend.
            ///
            /// # Safety
            /// The CPU supports the backend's features; otherwise as for the body.
            #[target_feature(enable = $features)]
            pub(crate) unsafe fn conv_codes(
                shape: &ConvShape,
                input: &CodeRows<'_>,
                parameters: (&[i8], &[f32], &[f32]),
                output: &mut [f32],
                accumulate: Accumulate,
            ) {
                // SAFETY: this function's contract is the body's.
                unsafe {
                    super::conv::<$lanes, CodeRows<'_>, { CODES_TILE.0 }, { CODES_TILE.1 }>(
                        shape, input, parameters, output, accumulate,
                    )
                }
            }

            /// [`conv`](super::conv) on this backend.
            ///
            /// # Safety
            /// The CPU supports the backend's features; otherwise as for the body.
            #[target_feature(enable = $features)]
            pub(crate) unsafe fn conv(
                shape: &ConvShape,
                input: &DigitRows<'_>,
                parameters: (&[i8], &[f32], &[f32]),
                output: &mut [f32],
                accumulate: Accumulate,
            ) {
                // SAFETY: this function's contract is the body's.
                unsafe {
                    super::conv::<$lanes, DigitRows<'_>, { TILE.0 }, { TILE.1 }>(
                        shape, input, parameters, output, accumulate,
                    )
                }
            }

            /// [`conv_pixel`](super::conv_pixel) on this backend.
            ///
            /// # Safety
            /// As for [`conv`]; the pixel is in the output and `output` holds its channels.
            #[target_feature(enable = $features)]
            pub(crate) unsafe fn conv_pixel(
                shape: &ConvShape,
                input: &DigitRows<'_>,
                parameters: (&[i8], &[f32], &[f32]),
                pixel: (usize, usize),
                output: &mut [f32],
            ) {
                // SAFETY: this function's contract is the body's.
                unsafe {
                    super::conv_pixel::<$lanes, { TILE.1 }>(shape, input, parameters, pixel, output)
                }
            }
        }
    };
}

backend!(
    avx2,
    super::PairSumsYmm,
    super::AVX2_TILE,
    super::AVX2_CODES_TILE,
    "avx2,fma"
);
backend!(
    avx512,
    super::VnniZmm,
    super::VNNI_TILE,
    super::VNNI_CODES_TILE,
    "avx512f,avx512bw,avx512vl,avx512vnni"
);

/// A backend's [`conv`] wrapper.
pub(crate) type ConvKernel =
    unsafe fn(&ConvShape, &DigitRows<'_>, (&[i8], &[f32], &[f32]), &mut [f32], Accumulate);

/// A backend's [`conv`] wrapper for signed codes.
pub(crate) type CodesKernel =
    unsafe fn(&ConvShape, &CodeRows<'_>, (&[i8], &[f32], &[f32]), &mut [f32], Accumulate);

/// A backend's [`conv_pixel`] wrapper.
pub(crate) type PixelKernel =
    unsafe fn(&ConvShape, &DigitRows<'_>, (&[i8], &[f32], &[f32]), (usize, usize), &mut [f32]);

/// [`Kernels::conv_int8`](crate::kernels::Kernels::conv_int8) on `kernel`: the lengths
/// checked, inputs the tiles do not take ([`tiles_apply`]) on the scalar reference.
///
/// # Safety
/// The CPU supports what `kernel` requires.
pub(crate) unsafe fn checked_conv(
    kernel: ConvKernel,
    shape: &ConvShape,
    input: &DigitRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    assert_int8_lengths(shape, input, (weight, weight_scales, bias), output.len());
    if !tiles_apply(shape, input) {
        let positions = shape.out_height() * shape.out_width();
        let parameters = (weight, weight_scales, bias);
        let channels = 0..shape.out_channels;
        return conv_int8_pixels(
            shape,
            input,
            parameters,
            output,
            accumulate,
            0..positions,
            channels,
        );
    }
    // SAFETY: the caller vouches for the CPU; the lengths were asserted and `tiles_apply`
    // checked just above.
    unsafe {
        kernel(
            shape,
            input,
            (weight, weight_scales, bias),
            output,
            accumulate,
        )
    }
}

/// [`Kernels::conv_int8_pixel`](crate::kernels::Kernels::conv_int8_pixel) on `kernel`, as
/// [`checked_conv`] is for the whole map.
///
/// # Safety
/// The CPU supports what `kernel` requires.
pub(crate) unsafe fn checked_conv_pixel(
    kernel: PixelKernel,
    shape: &ConvShape,
    input: &DigitRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    (out_y, out_x): (usize, usize),
    output: &mut [f32],
) {
    let parameters = (weight, weight_scales, bias);
    assert_int8_pixel_lengths(shape, input, parameters, (out_y, out_x), output.len());
    if !tiles_apply(shape, input) {
        let (channels, pixel) = (0..shape.out_channels, (out_y, out_x));
        let overwrite = Accumulate::Overwrite;
        return conv_int8_pixel(shape, input, parameters, output, overwrite, pixel, channels);
    }
    // SAFETY: the caller vouches for the CPU; the lengths and the pixel were asserted and
    // `tiles_apply` checked just above.
    unsafe { kernel(shape, input, parameters, (out_y, out_x), output) }
}

/// [`Kernels::conv_int8_codes`](crate::kernels::Kernels::conv_int8_codes) on `kernel`, the
/// lengths checked (every input of whole codes suits the tiles).
///
/// # Safety
/// The CPU supports what `kernel` requires.
pub(crate) unsafe fn checked_conv_codes(
    kernel: CodesKernel,
    shape: &ConvShape,
    input: &CodeRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    assert_code_lengths(shape, input, parameters, output.len());
    // SAFETY: the caller vouches for the CPU; the lengths were asserted just above.
    unsafe { kernel(shape, input, parameters, output, accumulate) }
}
