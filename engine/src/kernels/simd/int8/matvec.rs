//! The FiLM layers' matrix-vector product on signed codes: each weight row widened to i16
//! and multiplied two codes a lane, the exact row sum formed in i64 from i32 segments.

use super::lanes::Int8Lanes;
use crate::kernels::scalar::{assert_matvec_codes_lengths, exact_row_sum, scaled_row_sum};
use crate::kernels::simd::prefetch_lines;
use crate::kernels::{CodeRows, MAX_DIGIT_CHANNELS};

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
