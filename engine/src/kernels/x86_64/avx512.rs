//! AVX-512 kernels: the int8 convolution with VNNI's `vpdpbusd` (the shared body of
//! `int8` on ZMM vectors), the f32 2-D convolution of [`super::avx512_f32`] and the U-Net's
//! `sequence` kernels, all on ZMM vectors; the AVX2 ones where those do not apply.

use super::avx2::Avx2;
use super::{avx512_f32, int8, sequence};
use crate::kernels::ops::Activation;
use crate::kernels::scalar::{assert_conv_columns, assert_conv_lengths, assert_conv_pixel_lengths};
use crate::kernels::{
    Accumulate, ByteRows, CodeRows, ConvShape, DigitRows, Kernels, NarrowForm, SignedByteRows,
};

/// AVX-512 F/BW/VL + VNNI kernels (and AVX2 + FMA). Reachable only through
/// [`Avx512::detect`], which checks the CPU.
#[derive(Debug)]
pub struct Avx512 {
    /// The AVX2 kernels the methods this backend does not specialize use.
    avx2: &'static Avx2,
}

pub(super) static INSTANCE: Avx512 = Avx512 {
    avx2: &super::avx2::INSTANCE,
};

impl Avx512 {
    /// `None` unless the CPU and OS support AVX-512 F, BW, VL and VNNI, and AVX2 and FMA.
    pub fn detect() -> Option<&'static Avx512> {
        (super::has_avx512_vnni() && Avx2::detect().is_some()).then_some(&INSTANCE)
    }

    fn avx2(&self) -> &'static Avx2 {
        self.avx2
    }
}

impl Kernels for Avx512 {
    fn name(&self) -> &'static str {
        "avx512"
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
        // The sequence kernels sum the channels past their last whole vector unfused: where
        // ZMM's last whole vector would end before YMM's, AVX2 runs the layer, so that every
        // backend splits the channels as YMM (and NEON) do and gives their bits.
        if shape.out_channels % 16 >= 8 {
            return self
                .avx2()
                .conv(shape, input, weight, bias, output, accumulate);
        }
        // SAFETY: `self` exists only when AVX-512 F/BW/VL were detected.
        if unsafe { sequence::avx512::conv(shape, (input, weight, bias), output, accumulate) }
            .is_some()
        {
            return;
        }
        if !avx512_f32::covers(shape) {
            return self
                .avx2()
                .conv(shape, input, weight, bias, output, accumulate);
        }
        assert_conv_lengths(shape, (input, weight, bias), output.len());
        let columns = 0..shape.out_channels;
        // SAFETY: `self` exists only when AVX-512F was detected; `covers` holds and the
        // asserts fix the lengths.
        unsafe { avx512_f32::conv(shape, (input, weight, bias), columns, output, accumulate) }
    }

    fn conv_channels(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        channels: core::ops::Range<usize>,
        output: &mut [f32],
        accumulate: Accumulate,
    ) -> bool {
        // As `conv`: AVX2 runs the layers whose channels it splits otherwise.
        if shape.out_channels % 16 >= 8 {
            let avx2 = self.avx2();
            return avx2.conv_channels(shape, input, weight, bias, channels, output, accumulate);
        }
        if channels.end > bias.len() || channels.start > channels.end {
            return false;
        }
        if shape.in_height > 1 {
            if !avx512_f32::covers(shape) {
                let avx2 = self.avx2();
                return avx2
                    .conv_channels(shape, input, weight, bias, channels, output, accumulate);
            }
            let parameters = (input, weight, bias);
            assert_conv_columns(shape, parameters, &channels, output.len());
            // SAFETY: `self` exists only when AVX-512F was detected; `covers` holds and the
            // asserts fix the lengths and the columns.
            unsafe { avx512_f32::conv(shape, parameters, channels, output, accumulate) };
            return true;
        }
        let parameters = (input, weight, &bias[channels.clone()]);
        // SAFETY: `self` exists only when AVX-512 F/BW/VL were detected.
        unsafe { sequence::avx512::conv_channels(shape, parameters, channels, output, accumulate) }
            .is_some()
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
        if !avx512_f32::covers(shape) {
            return self
                .avx2()
                .conv_pixel(shape, input, weight, bias, pixel, output);
        }
        assert_conv_pixel_lengths(shape, (input, weight, bias), pixel, output.len());
        // SAFETY: as in `conv`, and the pixel is inside the output.
        unsafe { avx512_f32::conv_pixel(shape, (input, weight, bias), pixel, output) }
    }

    fn conv_int8_bytes(
        &self,
        shape: &ConvShape,
        input: &ByteRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let parameters = (weight, weight_scales, bias);
        // SAFETY: `self` exists only when AVX-512 F/BW/VL and VNNI were detected.
        unsafe { int8::checked_conv_bytes(shape, input, parameters, output, accumulate) }
    }

    fn conv_int8_signed_bytes(
        &self,
        shape: &ConvShape,
        input: &SignedByteRows<'_>,
        weight: &[i8],
        weight_scales: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    ) {
        let parameters = (weight, weight_scales, bias);
        // SAFETY: `self` exists only when AVX-512 F/BW/VL and VNNI were detected.
        unsafe { int8::checked_conv_signed_bytes(shape, input, parameters, output, accumulate) }
    }

    /// `vpdpbusd` multiplies whole bytes.
    fn narrow_form(&self) -> NarrowForm {
        NarrowForm::Bytes
    }

    shared_kernels!(avx512);
}
