//! Intel AMX: the int8 convolution of the trunk on the tile matrix unit (`tdpbusd`), every
//! other kernel from [`Avx512`].
//!
//! One `tdpbusd` multiplies a 16 x 64 tile of u8 activations (16 output pixels, 64 input
//! channels) by a 16 x 64 tile of i8 weights (16 input-channel quads, 16 output channels)
//! into 16 x 16 exact i32 sums: 16,384 products where `vpdpbusd` does 64. A block is 16
//! pixels x 32 channels: the two activation tiles are the pixels' high and low digits, the
//! two weight tiles 16 channels each, and the four sum tiles one per digit and weight tile,
//! all eight tile registers. The contract sums exactly per kernel tap and scales each tap
//! by its input pixel's scale, so the sum tiles cannot run across taps: per tap they are
//! stored, each pixel's `128 high + low` formed, and added to f32 totals with AVX-512, in
//! kernel order, exactly as the scalar reference does (same bits, tested on every backend).
//!
//! Channel blocks are the outer loop; inside one, a group of 128 pixels keeps its f32
//! totals on the stack while the taps go by, and each tap's weights for the block are
//! copied once into tile order ([`PackedTap`], at most 16 KB) for the group's eight blocks:
//! read in place, a weight tile's rows lie `4 out_channels` bytes apart, a power of two
//! that puts them all in two L1 sets. The kernel uses about 40 KB of stack.
//!
//! An activation tile is loaded straight from the input when its 16 pixels read input rows
//! equally spaced (`tileloadd` takes a row stride: the inside of a map, stride 1 or 2);
//! otherwise (padding, a tile wrapping onto the next output row, the short last tile) its
//! rows are gathered into a scratch tile, zero where a pixel reads nothing, and the sums of
//! those pixels are skipped as the reference skips them.
//!
//! Linux hands out the tile registers on request only (`arch_prctl(ARCH_REQ_XCOMP_PERM)`);
//! without an OS (`target_os = "none"`) the firmware that set XCR0 has enabled them.

use core::arch::asm;
use core::arch::x86_64::{
    __m512, _mm512_add_epi32, _mm512_add_ps, _mm512_cvtepi32_ps, _mm512_load_si512,
    _mm512_loadu_ps, _mm512_loadu_si512, _mm512_mul_ps, _mm512_set1_ps, _mm512_setzero_ps,
    _mm512_setzero_si512, _mm512_slli_epi32, _mm512_store_si512, _mm512_storeu_ps,
};

use super::avx512::Avx512;
use super::int8::PixelTile;
use crate::kernels::ops::Activation;
use crate::kernels::scalar::assert_int8_lengths;
use crate::kernels::{Accumulate, CodeRows, ConvShape, DigitRows, Kernels, QUAD, int8_quad_index};

/// Rows of every tile: pixels of an activation tile, quads of a weight tile, pixels of a
/// sum tile.
const ROWS: usize = 16;
/// Bytes of every tile row: 64 activations, 16 weight quads, 16 i32 sums.
const ROW_BYTES: usize = 64;
/// Input channels one `tdpbusd` consumes.
const CHANNELS_PER_STEP: usize = ROW_BYTES;
/// Output channels of a sum tile.
const SUM_COLUMNS: usize = ROW_BYTES / 4;
/// Pixels and output channels of a block.
const BLOCK_PIXELS: usize = ROWS;
const BLOCK_CHANNELS: usize = 2 * SUM_COLUMNS;

/// AMX-TILE and AMX-INT8 kernels (and AVX-512, AVX2). Reachable only through
/// [`Amx::detect`], which checks the CPU, the OS and the permission.
#[derive(Debug)]
pub struct Amx {
    /// The kernels the methods this backend does not specialize use.
    avx512: &'static Avx512,
}

static INSTANCE: Amx = Amx {
    avx512: &super::avx512::INSTANCE,
};

impl Amx {
    /// Whether [`Kernels::conv_int8`] runs on the tiles here: activations readable as u8,
    /// whole 64-channel steps up to [`MAX_IN_CHANNELS`], whole 32-channel blocks (other
    /// shapes go to [`Avx512`]). Every int8 layer of the model qualifies.
    pub fn covers(shape: &ConvShape, input: &DigitRows<'_>) -> bool {
        input.nonnegative()
            && shape.in_channels.is_multiple_of(CHANNELS_PER_STEP)
            && shape.in_channels <= MAX_IN_CHANNELS
            && shape.out_channels.is_multiple_of(BLOCK_CHANNELS)
    }

    /// [`Kernels::conv_int8`] on the tiles; `false`, with nothing written, when they do not
    /// apply ([`Amx::covers`]). Tests call it to know the tiles ran.
    #[allow(clippy::too_many_arguments)]
    pub fn conv_int8_on_tiles(
        &self,
        shape: &ConvShape,
        input: &DigitRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) -> bool {
        if !Self::covers(shape, input) {
            return false;
        }
        let parameters = (weight, weight_scales, bias);
        assert_int8_lengths(shape, input, parameters, output.len());
        // SAFETY: `self` exists only once AMX, AVX-512 and the permission were detected;
        // the lengths were asserted and `covers` checked just above.
        unsafe { conv(shape, input, parameters, output, accumulate) };
        true
    }

    /// `None` unless the CPU supports AMX-TILE and AMX-INT8 as well as everything
    /// [`Avx512::detect`] asks for, the OS saves the tile state, and this process may use it.
    pub fn detect() -> Option<&'static Amx> {
        let avx512 = Avx512::detect().is_some();
        (avx512 && super::has_amx_int8() && tile_data_permitted()).then_some(&INSTANCE)
    }
}

#[cfg(target_os = "linux")]
fn tile_data_permitted() -> bool {
    use core::sync::atomic::{AtomicU8, Ordering};
    const UNKNOWN: u8 = 0;
    const GRANTED: u8 = 1;
    const REFUSED: u8 = 2;
    static PERMISSION: AtomicU8 = AtomicU8::new(UNKNOWN);
    match PERMISSION.load(Ordering::Relaxed) {
        GRANTED => true,
        REFUSED => false,
        _ => {
            // Asking twice (two threads racing here) is harmless: the kernel grants the
            // same permission again.
            let granted = request_tile_data();
            let state = if granted { GRANTED } else { REFUSED };
            PERMISSION.store(state, Ordering::Relaxed);
            granted
        }
    }
}

/// `arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`: until a process asks, Linux
/// traps its first tile instruction and kills it. A raw system call, as the engine links
/// no C library.
#[cfg(target_os = "linux")]
fn request_tile_data() -> bool {
    const SYS_ARCH_PRCTL: isize = 158;
    const ARCH_REQ_XCOMP_PERM: usize = 0x1023;
    const XFEATURE_XTILEDATA: usize = 18;
    let result: isize;
    // SAFETY: the system call only changes which register state this process may use; it
    // reads and writes no memory of ours, and `syscall` clobbers only rcx and r11 (declared).
    unsafe {
        asm!(
            "syscall",
            inlateout("rax") SYS_ARCH_PRCTL => result,
            in("rdi") ARCH_REQ_XCOMP_PERM,
            in("rsi") XFEATURE_XTILEDATA,
            lateout("rcx") _,
            lateout("r11") _,
            options(nostack),
        );
    }
    result == 0
}

/// No OS: XCR0, which [`super::has_amx_int8`] read, is the whole story.
#[cfg(target_os = "none")]
fn tile_data_permitted() -> bool {
    true
}

/// Another OS may trap tile instructions in ways this code does not know to ask about.
#[cfg(not(any(target_os = "linux", target_os = "none")))]
fn tile_data_permitted() -> bool {
    false
}

/// `ldtilecfg`'s operand: palette 1, all eight tiles 16 rows of 64 bytes.
#[repr(C, align(64))]
struct TileConfig([u8; 64]);

static TILE_CONFIG: TileConfig = {
    let mut bytes = [0u8; 64];
    bytes[0] = 1;
    let mut tile = 0;
    while tile < 8 {
        bytes[16 + 2 * tile] = ROW_BYTES as u8;
        bytes[48 + tile] = ROWS as u8;
        tile += 1;
    }
    TileConfig(bytes)
};

/// One tile's worth of bytes, aligned for `tileloadd` / `tilestored` and ZMM moves.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct TileBuffer([u8; ROWS * ROW_BYTES]);

/// Input channels the packed weights of one tap hold at most (the widest ResNet-18 layer).
const MAX_IN_CHANNELS: usize = 512;
/// Pixels whose f32 totals stay on the stack while the taps go by: the weights of one tap
/// are packed once for all of them.
const GROUP_PIXELS: usize = 8 * BLOCK_PIXELS;

/// The input row each of a block's pixels (`origins`, the first `count` used) reads at a
/// kernel tap, `None` in the padding or past the last pixel.
fn tap_rows(
    shape: &ConvShape,
    origins: &[(isize, isize)],
    count: usize,
    (kernel_y, kernel_x): (usize, usize),
) -> [Option<usize>; BLOCK_PIXELS] {
    let mut rows = [None; BLOCK_PIXELS];
    for (row, &(top, left)) in rows.iter_mut().zip(origins).take(count) {
        let in_y = top + kernel_y as isize;
        let in_x = left + kernel_x as isize;
        let inside = (0..shape.in_height as isize).contains(&in_y)
            && (0..shape.in_width as isize).contains(&in_x);
        *row = inside.then(|| in_y as usize * shape.in_width + in_x as usize);
    }
    rows
}

/// Where an activation tile comes from at one tap: straight from the input (first row and
/// row step, in input rows) when its 16 pixels read equally spaced rows, else gathered.
fn direct_source(rows: &[Option<usize>]) -> Option<(usize, usize)> {
    let first = rows[0]?;
    let second = rows[1]?;
    let step = second.checked_sub(first)?;
    rows.iter()
        .enumerate()
        .all(|(index, row)| *row == Some(first + index * step))
        .then_some((first, step))
}

/// One tap's weights for one block of 32 output channels, as the weight tiles read them:
/// per 64-channel step, two tiles of 16 quads x 16 channels, each 1 KB contiguous, so they
/// stay in L1 across the pixel blocks that reuse them.
#[repr(C, align(64))]
struct PackedTap([u8; MAX_IN_CHANNELS * BLOCK_CHANNELS]);

/// The whole convolution on tiles.
///
/// # Safety
/// The CPU supports AVX-512F, AMX-TILE and AMX-INT8 and this thread may use the tile
/// state; the slice lengths are those [`assert_int8_lengths`] checks; [`Amx::covers`] holds.
#[target_feature(enable = "avx512f")]
unsafe fn conv(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    (weight, weight_scales, bias): (&[i8], &[f32], &[f32]),
    output: &mut [f32],
    accumulate: Accumulate,
) {
    let (in_channels, out_channels) = (shape.in_channels, shape.out_channels);
    let positions = shape.out_height() * shape.out_width();
    let mut packed = PackedTap([0; MAX_IN_CHANNELS * BLOCK_CHANNELS]);
    let mut gathered = [TileBuffer([0; ROWS * ROW_BYTES]); 2];
    let mut sums = [TileBuffer([0; ROWS * ROW_BYTES]); 4];
    // SAFETY: the caller vouches for AMX and the permission; the configuration is a valid
    // palette-1 layout (64 aligned bytes).
    unsafe { asm!("ldtilecfg [{}]", in(reg) TILE_CONFIG.0.as_ptr(), options(nostack)) };
    for channel in (0..out_channels).step_by(BLOCK_CHANNELS) {
        for group in (0..positions).step_by(GROUP_PIXELS) {
            let group_count = (positions - group).min(GROUP_PIXELS);
            let mut totals = [[_mm512_setzero_ps(); 2]; GROUP_PIXELS];
            // Worked out once per group, not once per tap (a division per pixel).
            let origins = PixelTile::<GROUP_PIXELS>::new(shape, group, group_count).origins;
            for kernel_y in 0..shape.kernel_height {
                for kernel_x in 0..shape.kernel_width {
                    let tap = kernel_y * shape.kernel_width + kernel_x;
                    let first_quad = int8_quad_index(in_channels, out_channels, tap, 0, channel);
                    // SAFETY: AVX-512F; the tap's quads of the block's 32 channels are inside
                    // `weight` (lengths asserted by the caller).
                    unsafe { pack_tap(shape, &weight[first_quad..], &mut packed) };
                    for block in (0..group_count).step_by(BLOCK_PIXELS) {
                        let count = (group_count - block).min(BLOCK_PIXELS);
                        let rows = tap_rows(shape, &origins[block..], count, (kernel_y, kernel_x));
                        if rows.iter().all(Option::is_none) {
                            continue;
                        }
                        let totals = &mut totals.as_chunks_mut().0[block / BLOCK_PIXELS];
                        // SAFETY: the caller's promises; `rows` are inside the input.
                        unsafe {
                            tap_sums(shape, input, &packed, &rows, &mut gathered, &mut sums);
                            add_tap(&rows, input.scales(), &sums, totals);
                        }
                    }
                }
            }
            let out = &mut output[group * out_channels + channel..];
            let parameters = (&weight_scales[channel..], &bias[channel..]);
            // SAFETY: AVX-512F; the block's channels are inside the output and parameters.
            unsafe {
                store(
                    &totals,
                    group_count,
                    parameters,
                    out,
                    out_channels,
                    accumulate,
                )
            };
        }
    }
    // SAFETY: as for `ldtilecfg`; releasing lets the OS skip saving 8 KB of tile data.
    unsafe { asm!("tilerelease", options(nostack, nomem)) };
}

/// Copies one tap's quads of 32 channels (`weights` from quad 0 of the block's first
/// channel) into the tile order of [`PackedTap`].
///
/// # Safety
/// AVX-512F; `weights` holds the tap's `in_channels / 4` quads of the block's channels,
/// `4 out_channels` bytes apart.
#[inline(always)]
unsafe fn pack_tap(shape: &ConvShape, weights: &[i8], packed: &mut PackedTap) {
    let quad_stride = shape.out_channels * QUAD;
    for quad in 0..shape.in_channels / QUAD {
        let (step, row) = (quad / ROWS, quad % ROWS);
        for tile in 0..2 {
            let from = quad * quad_stride + tile * SUM_COLUMNS * QUAD;
            let to = ((2 * step + tile) * ROWS + row) * ROW_BYTES;
            // SAFETY: the caller's promise for `from`; `to` is a 64-byte row of `packed`,
            // which holds `2 in_channels / 64` tiles.
            unsafe {
                let bytes = _mm512_loadu_si512(weights[from..][..ROW_BYTES].as_ptr().cast());
                _mm512_store_si512(packed.0[to..][..ROW_BYTES].as_mut_ptr().cast(), bytes);
            }
        }
    }
}

/// One tap's exact i32 sums of the block: `sums[vector]` holds the high digits' sums for
/// channels `16 vector..` of the block, `sums[2 + vector]` the low digits'.
///
/// # Safety
/// As for [`conv`]; every `Some` row is an input row; `packed` holds the tap's weights.
#[inline(always)]
unsafe fn tap_sums(
    shape: &ConvShape,
    input: &DigitRows<'_>,
    packed: &PackedTap,
    rows: &[Option<usize>; BLOCK_PIXELS],
    gathered: &mut [TileBuffer; 2],
    sums: &mut [TileBuffer; 4],
) {
    let in_channels = shape.in_channels;
    let planes = [input.high.values, input.low.values];
    let direct = direct_source(rows);
    // SAFETY: tiles are configured (caller).
    unsafe {
        asm!(
            "tilezero tmm0",
            "tilezero tmm1",
            "tilezero tmm2",
            "tilezero tmm3",
            options(nostack, nomem)
        )
    };
    for step in 0..in_channels / CHANNELS_PER_STEP {
        let first_channel = step * CHANNELS_PER_STEP;
        let mut sources = [(core::ptr::null::<i8>(), 0usize); 2];
        for (digit, plane) in planes.iter().enumerate() {
            sources[digit] = match direct {
                Some((row, row_step)) => (
                    plane[row * in_channels + first_channel..].as_ptr(),
                    row_step * in_channels,
                ),
                None => {
                    let buffer = &mut gathered[digit];
                    // SAFETY: AVX-512F; each `Some` row holds `in_channels` values, so its
                    // 64 from `first_channel` are readable; the buffer holds 16 rows of 64.
                    unsafe { gather(plane, in_channels, first_channel, rows, buffer) };
                    (buffer.0.as_ptr().cast::<i8>(), ROW_BYTES)
                }
            };
        }
        let weights = packed.0[2 * step * ROWS * ROW_BYTES..][..2 * ROWS * ROW_BYTES].as_ptr();
        // SAFETY: the activation sources cover 16 rows of 64 bytes at their strides (direct
        // rows are input rows; the gathered buffers are 16 x 64); the step's two weight
        // tiles are the 2 KB of `packed` from `weights`.
        unsafe {
            asm!(
                "tileloadd tmm4, [{high} + {high_stride}]",
                "tileloadd tmm5, [{low} + {low_stride}]",
                "tileloadd tmm6, [{b0} + {sb}]",
                "tileloadd tmm7, [{b1} + {sb}]",
                "tdpbusd tmm0, tmm4, tmm6",
                "tdpbusd tmm1, tmm4, tmm7",
                "tdpbusd tmm2, tmm5, tmm6",
                "tdpbusd tmm3, tmm5, tmm7",
                high = in(reg) sources[0].0,
                high_stride = in(reg) sources[0].1,
                low = in(reg) sources[1].0,
                low_stride = in(reg) sources[1].1,
                b0 = in(reg) weights,
                b1 = in(reg) weights.add(ROWS * ROW_BYTES),
                sb = in(reg) ROW_BYTES,
                options(nostack, readonly, preserves_flags)
            );
        }
    }
    let [s0, s1, s2, s3] = sums;
    // SAFETY: each buffer is 16 rows of 64 bytes.
    unsafe {
        asm!(
            "tilestored [{s0} + {stride}], tmm0",
            "tilestored [{s1} + {stride}], tmm1",
            "tilestored [{s2} + {stride}], tmm2",
            "tilestored [{s3} + {stride}], tmm3",
            s0 = in(reg) s0.0.as_mut_ptr(),
            s1 = in(reg) s1.0.as_mut_ptr(),
            s2 = in(reg) s2.0.as_mut_ptr(),
            s3 = in(reg) s3.0.as_mut_ptr(),
            stride = in(reg) ROW_BYTES,
            options(nostack, preserves_flags)
        );
    }
}

/// Copies 64 activations from `step` of each pixel's row into `buffer`, zeros where the
/// pixel reads nothing.
///
/// # Safety
/// AVX-512F; each `Some` row has `in_channels` values in `values`, `step + 64` of them.
#[inline(always)]
unsafe fn gather(
    values: &[i8],
    in_channels: usize,
    step: usize,
    rows: &[Option<usize>],
    buffer: &mut TileBuffer,
) {
    for (pixel, row) in rows.iter().enumerate() {
        // SAFETY: the caller's promise for the row; the buffer row is 64 aligned bytes.
        unsafe {
            let bytes = match row {
                Some(row) => _mm512_loadu_si512(values[row * in_channels + step..].as_ptr().cast()),
                None => _mm512_setzero_si512(),
            };
            _mm512_store_si512(buffer.0[pixel * ROW_BYTES..].as_mut_ptr().cast(), bytes);
        }
    }
}

/// `totals[pixel] += (code sums as f32) * scale of the pixel's row`, a product then a sum,
/// for the pixels that read a row at this tap; the code sum is `128 high + low`, wrapping
/// as the scalar reference does (exact: the result fits i32).
///
/// # Safety
/// AVX-512F; `scales` holds every `Some` row.
#[inline(always)]
unsafe fn add_tap(
    rows: &[Option<usize>; BLOCK_PIXELS],
    scales: &[f32],
    sums: &[TileBuffer; 4],
    totals: &mut [[__m512; 2]; BLOCK_PIXELS],
) {
    for (pixel, row) in rows.iter().enumerate() {
        let Some(row) = *row else { continue };
        let at = pixel * ROW_BYTES;
        // SAFETY: AVX-512F; each sum buffer row is 64 aligned bytes.
        unsafe {
            let scale = _mm512_set1_ps(scales[row]);
            for vector in 0..2 {
                let high = _mm512_load_si512(sums[vector].0[at..].as_ptr().cast());
                let low = _mm512_load_si512(sums[2 + vector].0[at..].as_ptr().cast());
                let sum = _mm512_add_epi32(_mm512_slli_epi32::<7>(high), low);
                let scaled = _mm512_mul_ps(_mm512_cvtepi32_ps(sum), scale);
                totals[pixel][vector] = _mm512_add_ps(totals[pixel][vector], scaled);
            }
        }
    }
}

/// `out (+)= totals * weight_scales + bias` for the block's `count` pixels, `stride` apart
/// in `out`, unfused as the scalar reference does it.
///
/// # Safety
/// AVX-512F; `weight_scales` and `bias` hold the block's 32 channels; `out` holds them for
/// each of the `count` pixels.
#[inline(always)]
unsafe fn store(
    totals: &[[__m512; 2]],
    count: usize,
    (weight_scales, bias): (&[f32], &[f32]),
    out: &mut [f32],
    stride: usize,
    accumulate: Accumulate,
) {
    let (weight_scales, bias) = (&weight_scales[..BLOCK_CHANNELS], &bias[..BLOCK_CHANNELS]);
    for (pixel, total) in totals.iter().enumerate().take(count) {
        let out = &mut out[pixel * stride..][..BLOCK_CHANNELS];
        for (vector, &total) in total.iter().enumerate() {
            let at = vector * SUM_COLUMNS;
            // SAFETY: AVX-512F; 16 floats from `at` in each slice.
            unsafe {
                let scaled = _mm512_mul_ps(total, _mm512_loadu_ps(weight_scales[at..].as_ptr()));
                let mut value = _mm512_add_ps(scaled, _mm512_loadu_ps(bias[at..].as_ptr()));
                if accumulate == Accumulate::Add {
                    value = _mm512_add_ps(_mm512_loadu_ps(out[at..].as_ptr()), value);
                }
                _mm512_storeu_ps(out[at..].as_mut_ptr(), value);
            }
        }
    }
}

impl Kernels for Amx {
    fn name(&self) -> &'static str {
        "amx"
    }

    fn conv(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        self.avx512
            .conv(shape, input, weight, bias, output, accumulate)
    }

    fn conv_pixel(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        pixel: (usize, usize),
        output: &mut [f32],
    ) {
        self.avx512
            .conv_pixel(shape, input, weight, bias, pixel, output)
    }

    fn conv_int8_pixel(
        &self,
        shape: &ConvShape,
        input: &DigitRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        pixel: (usize, usize),
        output: &mut [f32],
    ) {
        // One pixel is one row of a tile: the VNNI path is as fast, with the same bits.
        self.avx512
            .conv_int8_pixel(shape, input, weight, weight_scales, bias, pixel, output)
    }

    fn upsample_conv(
        &self,
        length: usize,
        in_channels: usize,
        out_channels: usize,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        output: &mut [f32],
    ) {
        self.avx512.upsample_conv(
            length,
            in_channels,
            out_channels,
            input,
            weight,
            bias,
            output,
        )
    }

    fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
        self.avx512.matvec(weight, input, base, output)
    }

    fn conv_int8(
        &self,
        shape: &ConvShape,
        input: &DigitRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        if !self.conv_int8_on_tiles(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        ) {
            self.avx512.conv_int8(
                shape,
                input,
                weight,
                weight_scales,
                bias,
                output,
                accumulate,
            )
        }
    }

    fn conv_int8_codes(
        &self,
        shape: &ConvShape,
        input: &CodeRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        self.avx512.conv_int8_codes(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        )
    }

    fn matvec_weight_int8(
        &self,
        weight: &[i8],
        row_scales: &[f32],
        input: &[f32],
        base: &[f32],
        output: &mut [f32],
    ) {
        self.avx512
            .matvec_weight_int8(weight, row_scales, input, base, output)
    }

    fn quantize_rows(
        &self,
        input: &[f32],
        row_len: usize,
        digits: (&mut [i8], &mut [i8]),
        scales: &mut [f32],
    ) -> bool {
        self.avx512.quantize_rows(input, row_len, digits, scales)
    }

    fn quantize_codes(&self, input: &[f32], row_len: usize, codes: &mut [i16], scales: &mut [f32]) {
        self.avx512.quantize_codes(input, row_len, codes, scales)
    }

    fn group_norm(
        &self,
        data: &mut [f32],
        channels: usize,
        groups: usize,
        affine: (&[f32], &[f32]),
        activation: Activation,
    ) {
        self.avx512
            .group_norm(data, channels, groups, affine, activation)
    }

    fn add_activate(&self, target: &mut [f32], source: &[f32], activation: Activation) {
        self.avx512.add_activate(target, source, activation)
    }
}
