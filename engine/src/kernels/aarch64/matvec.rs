//! `Kernels::matvec_int8_codes` (the FiLM rows) on `sdot`. The input's 15-bit codes are
//! split once into two digit planes (`code = 128 high + low`, as the trunk's), and each
//! weight row meets both planes sixteen columns at a time, four rows at once for eight
//! independent sums. The row sums are exact, so the bits are every backend's. The 16-bit
//! pair products of the shared `matvec_codes` (`smull`) run about a tenth as many products
//! a cycle.

use core::arch::aarch64::{int32x4_t, vaddlvq_s32, vdupq_n_s32, vld1q_s8, vreinterpretq_s32_s8};

use super::int8_lanes::sdot;
use crate::kernels::CodeRows;
use crate::kernels::scalar::{assert_matvec_codes_lengths, exact_row_sum, scaled_row_sum};

/// Columns whose digit planes are split on the stack (4 KB). A digit plane's lane sums are
/// exact in i32 up to 2^31 / (128 x 128) = 131,072 columns; wider rows (no model has them)
/// take the shared kernel.
pub(crate) const SPLIT_COLUMNS: usize = 2048;

/// Rows whose sums are held at once.
const ROWS: usize = 4;

/// `matvec_int8_codes` on `sdot` for rows of at most [`SPLIT_COLUMNS`] columns (`None`,
/// nothing done, for wider ones).
///
/// # Safety
/// The CPU has the dot-product extension.
///
/// # Panics
/// If the lengths disagree (the model code never passes such slices).
#[target_feature(enable = "neon,dotprod")]
pub(crate) unsafe fn matvec_codes(
    weight: &[i8],
    row_scales: &[f32],
    input: &CodeRows<'_>,
    base: &[f32],
    output: &mut [f32],
) -> Option<()> {
    let cols = assert_matvec_codes_lengths(weight, row_scales, input, base, output.len());
    let vector_cols = cols - cols % 16;
    if vector_cols > SPLIT_COLUMNS {
        return None;
    }
    let (mut high, mut low) = ([0i8; SPLIT_COLUMNS], [0i8; SPLIT_COLUMNS]);
    let codes = &input.codes[..cols];
    for ((high, low), &code) in high
        .iter_mut()
        .zip(low.iter_mut())
        .zip(&codes[..vector_cols])
    {
        // |code| <= 16383: the high digit fits i8, the low one is 0..=127.
        (*high, *low) = ((code >> 7) as i8, (code & 127) as i8);
    }
    let rows = output.len();
    let mut first = 0;
    while first < rows {
        let count = (rows - first).min(ROWS);
        let mut digit_sums = [[0i64; 2]; ROWS];
        // SAFETY: the rows `first .. first + count` have `cols` weights each (asserted);
        // every load reads 16 bytes at a column below `vector_cols`, inside a row and inside
        // the planes; the CPU has the dot product (this function's contract).
        unsafe {
            let zero = vdupq_n_s32(0);
            let mut sums: [[int32x4_t; 2]; ROWS] = [[zero; 2]; ROWS];
            for column in (0..vector_cols).step_by(16) {
                let h = vreinterpretq_s32_s8(vld1q_s8(high.as_ptr().add(column)));
                let l = vreinterpretq_s32_s8(vld1q_s8(low.as_ptr().add(column)));
                for (row, sums) in sums.iter_mut().enumerate().take(count) {
                    let at = weight.as_ptr().add((first + row) * cols + column);
                    let w = vreinterpretq_s32_s8(vld1q_s8(at));
                    sums[0] = sdot(sums[0], h, w);
                    sums[1] = sdot(sums[1], l, w);
                }
            }
            for (total, sums) in digit_sums.iter_mut().zip(&sums) {
                *total = [vaddlvq_s32(sums[0]), vaddlvq_s32(sums[1])];
            }
        }
        for (row, [high, low]) in digit_sums.iter().enumerate().take(count) {
            let r = first + row;
            let tail = &weight[r * cols + vector_cols..][..cols - vector_cols];
            let sum = 128 * high + low + exact_row_sum(tail, &codes[vector_cols..]);
            output[r] = scaled_row_sum(sum, input.scale, row_scales[r], base[r]);
        }
        first += count;
    }
    Some(())
}
