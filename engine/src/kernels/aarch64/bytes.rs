//! Whole bytes (the stem's patches, the trunk's 8-bit activations) on `sdot`, which
//! multiplies signed bytes only: the tiles read each byte centred and add the weights'
//! share back ([`CenteredBytes`]). The share, `128 sum w` per output channel, is summed here
//! once per call from the packed weights (the same work as one more output pixel).

use core::arch::aarch64::{
    vdupq_n_s8, vdupq_n_s32, vld1q_s8, vreinterpretq_s32_s8, vshlq_n_s32, vst1q_s32,
};

use super::int8;
use super::int8_lanes::sdot;
use crate::kernels::scalar::{assert_byte_lengths, conv_int8_bytes};
use crate::kernels::simd::int8::{CenteredBytes, byte_tiles_apply, conv};
use crate::kernels::{Accumulate, ByteRows, ConvShape, INT8_CHANNEL_BLOCK, QUAD, int8_quads};

/// Output channels whose shares fit the stack (4 KB); ResNet-18's widest layer has 512.
const MAX_CHANNELS: usize = 1024;

/// `shares[o] = 128 sum w[o]` over every tap and input channel of the packed kernel
/// (`[out/64, taps, in/4, block, 4]`), for `out_channels` a multiple of 4.
///
/// # Safety
/// The CPU has the dot-product extension; `weight` holds the packed kernel of `shape`.
#[target_feature(enable = "neon,dotprod")]
unsafe fn weight_shares(shape: &ConvShape, weight: &[i8], shares: &mut [i32]) {
    let taps = shape.kernel_height * shape.kernel_width;
    let rows = taps * int8_quads(shape.in_channels);
    let out_channels = shape.out_channels;
    // SAFETY: NEON; every load is 16 bytes of one row of a block, inside `weight` (the
    // packed length is blocks x rows x width x 4); the stores are 4 channels of `shares`.
    unsafe {
        let ones = vreinterpretq_s32_s8(vdupq_n_s8(1));
        for block_start in (0..out_channels).step_by(INT8_CHANNEL_BLOCK) {
            let width = (out_channels - block_start).min(INT8_CHANNEL_BLOCK);
            let block = &weight[block_start * rows * QUAD..][..rows * width * QUAD];
            for group in (0..width).step_by(4) {
                let mut sum = vdupq_n_s32(0);
                for row in 0..rows {
                    let at = block.as_ptr().add((row * width + group) * QUAD);
                    sum = sdot(sum, vreinterpretq_s32_s8(vld1q_s8(at)), ones);
                }
                // At most `MAX_BYTE_TERMS` weights of magnitude 128 or less: 128 times their
                // sum fits i32.
                let share = vshlq_n_s32::<7>(sum);
                vst1q_s32(shares[block_start + group..][..4].as_mut_ptr(), share);
            }
        }
    }
}

/// `Kernels::conv_int8_bytes` on `sdot`, the lengths checked; shapes the tiles do not take
/// (and layers wider than [`MAX_CHANNELS`] or of channels not in fours) on the scalar
/// reference.
///
/// # Safety
/// The CPU has the dot-product extension.
#[target_feature(enable = "neon,dotprod")]
pub(crate) unsafe fn checked_conv_bytes(
    shape: &ConvShape,
    input: &ByteRows<'_>,
    parameters: (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    assert_byte_lengths(shape, input, parameters, output.len());
    let out_channels = shape.out_channels;
    if !byte_tiles_apply(shape) || out_channels > MAX_CHANNELS || !out_channels.is_multiple_of(4) {
        return conv_int8_bytes(shape, input, parameters, output, accumulate);
    }
    let mut shares = [0i32; MAX_CHANNELS];
    let shares = &mut shares[..out_channels];
    const TILE: (usize, usize) = int8::BYTES_TILE;
    // SAFETY: the dot product (this function's contract); the lengths were asserted and the
    // quads checked just above.
    unsafe {
        weight_shares(shape, parameters.0, shares);
        let input = CenteredBytes {
            bytes: *input,
            weight_shares: shares,
        };
        conv::<int8::SignedBytes, CenteredBytes<'_>, { TILE.0 }, { TILE.1 }>(
            shape, &input, parameters, output, accumulate,
        )
    }
}
