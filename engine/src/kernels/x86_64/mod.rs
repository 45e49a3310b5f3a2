//! x86-64 kernels, chosen at run time from what the CPU reports (CPUID works without std).

pub mod avx2;
pub mod avx512;
pub mod avx512_f32;
mod int8;
pub mod sequence;

use core::arch::x86_64::{__cpuid, __cpuid_count, _xgetbv};

use crate::kernels::ConvShape;

/// Whether every kernel tap of output pixels `out_x .. out_x + pixels` of row `out_y` reads
/// inside the input (no padding involved).
pub(crate) fn interior(shape: &ConvShape, out_y: usize, out_x: usize, pixels: usize) -> bool {
    let top = out_y * shape.stride;
    let left = out_x * shape.stride;
    let right = (out_x + pixels - 1) * shape.stride + shape.kernel_width;
    top >= shape.padding_height
        && top + shape.kernel_height <= shape.in_height + shape.padding_height
        && left >= shape.padding_width
        && right <= shape.in_width + shape.padding_width
}

/// How an f32 convolution covers its output pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Run {
    /// This many consecutive pixels of the row (a full tile, or 1), all taps inside.
    Interior(usize),
    /// One pixel with taps in the padding (the scalar reference computes it).
    Border,
}

/// Visits every output pixel of `shape` once, row by row: tiles of `tile` interior pixels
/// where they fit, single interior pixels, single border pixels. Each interior pixel is
/// one FMA chain whichever run it is in, so a kernel's single-pixel path can reproduce it.
pub(crate) fn walk_pixels(
    shape: &ConvShape,
    tile: usize,
    mut visit: impl FnMut(usize, usize, Run),
) {
    let out_width = shape.out_width();
    for out_y in 0..shape.out_height() {
        let mut out_x = 0;
        while out_x < out_width {
            let run = if out_x + tile <= out_width && interior(shape, out_y, out_x, tile) {
                Run::Interior(tile)
            } else if interior(shape, out_y, out_x, 1) {
                Run::Interior(1)
            } else {
                Run::Border
            };
            visit(out_y, out_x, run);
            out_x += match run {
                Run::Interior(pixels) => pixels,
                Run::Border => 1,
            };
        }
    }
}

/// Reads XCR0. Only called once CPUID has reported OSXSAVE.
#[target_feature(enable = "xsave")]
fn os_enabled_state() -> u64 {
    // SAFETY: `xgetbv` is available: the caller checked CPUID's OSXSAVE bit, which the
    // target_feature contract of this function stands for.
    unsafe { _xgetbv(0) }
}

/// AVX2 and FMA are present and the OS saves the YMM registers.
pub fn has_avx2_fma() -> bool {
    // CPUID is safe on x86-64; leaf 1 exists on every such processor.
    let basic = __cpuid(1);
    let fma = basic.ecx & (1 << 12) != 0;
    let osxsave = basic.ecx & (1 << 27) != 0;
    let avx = basic.ecx & (1 << 28) != 0;
    if !(fma && osxsave && avx) {
        return false;
    }
    // SAFETY: OSXSAVE is set, so XGETBV may be executed.
    let state = unsafe { os_enabled_state() };
    if state & 0b110 != 0b110 {
        return false;
    }
    // Leaf 0 reports the highest leaf; leaf 7 (structured features) is read only if present.
    let highest = __cpuid(0).eax;
    highest >= 7 && __cpuid_count(7, 0).ebx & (1 << 5) != 0
}

/// AVX-512 F, BW, VL and VNNI are present and the OS saves the opmask and ZMM registers
/// (XCR0 bits 5 to 7) as well as the YMM ones (bits 1 and 2).
pub fn has_avx512_vnni() -> bool {
    // CPUID is safe on x86-64; leaf 1 exists on every such processor.
    let osxsave = __cpuid(1).ecx & (1 << 27) != 0;
    if !osxsave || __cpuid(0).eax < 7 {
        return false;
    }
    let features = __cpuid_count(7, 0);
    let foundation = features.ebx & (1 << 16) != 0;
    let byte_word = features.ebx & (1 << 30) != 0;
    let vector_length = features.ebx & (1 << 31) != 0;
    let vnni = features.ecx & (1 << 11) != 0;
    if !(foundation && byte_word && vector_length && vnni) {
        return false;
    }
    // SAFETY: OSXSAVE is set, so XGETBV may be executed.
    let state = unsafe { os_enabled_state() };
    state & 0b1110_0110 == 0b1110_0110
}
