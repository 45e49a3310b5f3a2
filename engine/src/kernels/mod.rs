//! Compute kernels, apart from the model code that calls them.
//!
//! Each heavy kernel family is a method of [`Kernels`], the contract every implementation
//! meets; [`scalar::Scalar`] is the reference, always compiled, against which any faster
//! implementation is tested. Light element-wise operations live in [`ops`].

pub mod ops;
pub mod scalar;

/// Shape of a 2-D convolution over channels-last maps (`[H, W, C]`), weights packed
/// `[kernel_height, kernel_width, in_channels, out_channels]`. A 1-D convolution over
/// `[T, C]` is the same with height 1.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvShape {
    pub in_height: usize,
    pub in_width: usize,
    pub in_channels: usize,
    pub out_channels: usize,
    pub kernel_height: usize,
    pub kernel_width: usize,
    pub stride: usize,
    pub padding_height: usize,
    pub padding_width: usize,
}

impl ConvShape {
    /// A square 2-D convolution.
    pub const fn square(
        (in_height, in_width, in_channels): (usize, usize, usize),
        out_channels: usize,
        kernel: usize,
        stride: usize,
        padding: usize,
    ) -> Self {
        ConvShape {
            in_height,
            in_width,
            in_channels,
            out_channels,
            kernel_height: kernel,
            kernel_width: kernel,
            stride,
            padding_height: padding,
            padding_width: padding,
        }
    }

    /// A 1-D convolution over `[length, in_channels]`.
    pub const fn sequence(
        length: usize,
        in_channels: usize,
        out_channels: usize,
        kernel: usize,
        stride: usize,
        padding: usize,
    ) -> Self {
        ConvShape {
            in_height: 1,
            in_width: length,
            in_channels,
            out_channels,
            kernel_height: 1,
            kernel_width: kernel,
            stride,
            padding_height: 0,
            padding_width: padding,
        }
    }

    pub const fn out_height(&self) -> usize {
        crate::config::conv_output(
            self.in_height,
            self.kernel_height,
            self.stride,
            self.padding_height,
        )
    }

    pub const fn out_width(&self) -> usize {
        crate::config::conv_output(
            self.in_width,
            self.kernel_width,
            self.stride,
            self.padding_width,
        )
    }

    pub const fn input_len(&self) -> usize {
        self.in_height * self.in_width * self.in_channels
    }

    pub const fn output_len(&self) -> usize {
        self.out_height() * self.out_width() * self.out_channels
    }

    pub const fn weight_len(&self) -> usize {
        self.kernel_height * self.kernel_width * self.in_channels * self.out_channels
    }
}

/// Whether a convolution overwrites its output or adds to it (residual connections).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accumulate {
    Overwrite,
    Add,
}

/// The contract of a kernel implementation. Slices have exactly the lengths the shapes
/// imply (the model code guarantees it; implementations may assert it).
pub trait Kernels: Sync {
    /// Name used in benchmarks and to prove which backend ran.
    fn name(&self) -> &'static str;

    /// `output = conv(input) + bias` (or `+=` with [`Accumulate::Add`]); zero padding.
    fn conv(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        output: &mut [f32],
        accumulate: Accumulate,
    );

    /// PyTorch's ConvTranspose1d(kernel 4, stride 2, padding 1) over `[length, in]`,
    /// weights packed `[4, in, out]`, giving `[2 length, out]`.
    #[allow(clippy::too_many_arguments)]
    fn upsample_conv(
        &self,
        length: usize,
        in_channels: usize,
        out_channels: usize,
        input: &[f32],
        weight: &[f32],
        bias: &[f32],
        output: &mut [f32],
    );

    /// `output[r] = base[r] + sum_c weight[r, c] input[c]` for a row-major `[rows, cols]`.
    fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]);
}
