//! The x86-64 int8 convolutions: the shared tiles (`simd::int8`) on AVX2's and AVX-512
//! VNNI's integer dot products (`int8_lanes`).

use super::int8_lanes::{PairSumsYmm, VnniZmm};
pub(crate) use super::int8_lanes::{exact_digits_zmm, round_zmm};
use crate::kernels::simd::int8;
use crate::kernels::{Accumulate, ByteRows, ConvShape, SignedByteRows};

/// Pixels and channel vectors of a tile, per backend, both digit planes' sums held across
/// the kernel: AVX2 has 16 YMM registers (8 sums, 4 weight vectors, the broadcast, the ones
/// and a product); AVX-512 has 32 ZMM registers (16 sums, 4 weight vectors, the
/// broadcast). With both planes in one quad loop, the in-process A/B of whole encodes put
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

crate::kernels::simd::int8::backend!(
    avx2,
    super::PairSumsYmm,
    super::AVX2_TILE,
    super::AVX2_CODES_TILE,
    "avx2,fma"
);
crate::kernels::simd::int8::backend!(
    avx512,
    super::VnniZmm,
    super::VNNI_TILE,
    super::VNNI_CODES_TILE,
    "avx512f,avx512bw,avx512vl,avx512vnni"
);

/// The tile of whole bytes on AVX-512 (one plane: 16 sums, 4 weight vectors, the
/// broadcast). Builds alternated on Zen 5 (the latency harness, panda with every
/// residual-block layer 8-bit, two rounds): (6, 4) encoded a frame in 1.01-1.04x the time,
/// (8, 2) in 1.07-1.09x.
const VNNI_BYTES_TILE: (usize, usize) = (4, 4);

/// `Kernels::conv_int8_bytes` with VNNI's `vpdpbusd` (exact for 0..=255; AVX2's
/// `vpmaddubsw` is not, so it has no such wrapper).
///
/// # Safety
/// The CPU supports AVX-512 F/BW/VL and VNNI.
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vnni")]
pub(crate) unsafe fn checked_conv_bytes(
    shape: &ConvShape,
    input: &ByteRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    const TILE: (usize, usize) = VNNI_BYTES_TILE;
    // SAFETY: the CPU runs VNNI (this function's contract).
    unsafe {
        int8::checked_conv_bytes::<VnniZmm, { TILE.0 }, { TILE.1 }>(
            shape, input, parameters, output, accumulate,
        )
    }
}

/// `Kernels::conv_int8_signed_bytes` with VNNI's `vpdpbusd` on the weights offset by 128
/// (the tile of whole bytes). AVX2 has no such wrapper: it takes the same codes as 16-bit
/// words ([`Kernels::multiplies_signed_bytes`]).
///
/// [`Kernels::multiplies_signed_bytes`]: crate::kernels::Kernels::multiplies_signed_bytes
///
/// # Safety
/// The CPU supports AVX-512 F/BW/VL and VNNI.
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vnni")]
pub(crate) unsafe fn checked_conv_signed_bytes(
    shape: &ConvShape,
    input: &SignedByteRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    const TILE: (usize, usize) = VNNI_BYTES_TILE;
    // SAFETY: the CPU runs VNNI (this function's contract).
    unsafe {
        int8::checked_conv_signed_bytes::<VnniZmm, { TILE.0 }, { TILE.1 }>(
            shape, input, parameters, output, accumulate,
        )
    }
}
