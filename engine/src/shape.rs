//! Plain shapes, below everything else in the engine: PyTorch's output-size rule, the shape
//! of a convolution, and where each weight of an int8 convolution kernel lives. The
//! configuration computes its map sizes with these, the weights file checks its tensors'
//! lengths with them, and the kernels read their weights by them; none of those needs the
//! others to do it.

/// The greatest common divisor of `a` and `b` (`a` when `b` is 0).
pub const fn gcd(mut a: usize, mut b: usize) -> usize {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// Output length of a convolution or pooling window (PyTorch's floor rule).
pub const fn conv_output(input: usize, kernel: usize, stride: usize, padding: usize) -> usize {
    (input + 2 * padding - kernel) / stride + 1
}

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
    /// Zero rows above the input (and, unless [`padding_bottom`](Self::padding_bottom) says
    /// otherwise, below it: PyTorch pads both sides alike).
    pub padding_height: usize,
    pub padding_width: usize,
    /// Zero rows below the input. Equal to `padding_height` in every layer of the model;
    /// a band of a layer's output rows (one worker's share) is the same convolution over
    /// the input rows it reads, padded only on the sides where the layer's map ends.
    pub padding_bottom: usize,
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
            padding_bottom: padding,
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
            padding_bottom: 0,
        }
    }

    /// A 1x1 convolution of stride 1 without padding: a matrix product over pixels.
    pub const fn is_pointwise(&self) -> bool {
        self.kernel_height == 1
            && self.kernel_width == 1
            && self.stride == 1
            && self.padding_height == 0
            && self.padding_bottom == 0
            && self.padding_width == 0
    }

    pub const fn out_height(&self) -> usize {
        (self.in_height + self.padding_height + self.padding_bottom - self.kernel_height)
            / self.stride
            + 1
    }

    /// The convolution computing only output rows `first .. first + rows` (inside
    /// [`out_height`](Self::out_height)), and the input rows it reads (`start .. start +
    /// its in_height`): every output pixel sees the same taps, in the same places, as in
    /// the whole convolution, so a kernel gives it the same bits.
    pub const fn row_band(&self, first: usize, rows: usize) -> (ConvShape, usize) {
        // Padded coordinates: input row `y` is padded row `y + padding_height`.
        let top = first * self.stride;
        let bottom = (first + rows - 1) * self.stride + self.kernel_height;
        let start = top.saturating_sub(self.padding_height);
        let end_padded = self.padding_height + self.in_height;
        let end = if bottom < end_padded {
            bottom - self.padding_height
        } else {
            self.in_height
        };
        let band = ConvShape {
            in_height: end - start,
            padding_height: (start + self.padding_height) - top,
            padding_bottom: bottom - (end + self.padding_height),
            ..*self
        };
        (band, start)
    }

    pub const fn out_width(&self) -> usize {
        conv_output(
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

    /// Where output pixel `(row, column)`'s `out_channels` values lie in the output map
    /// (`[out_height, out_width, out_channels]`).
    pub const fn pixel_values(&self, (row, column): (usize, usize)) -> core::ops::Range<usize> {
        let start = (row * self.out_width() + column) * self.out_channels;
        start..start + self.out_channels
    }

    pub const fn weight_len(&self) -> usize {
        self.kernel_height * self.kernel_width * self.in_channels * self.out_channels
    }

    /// Length of the kernel in the int8 layout: input channels in zero-padded quads, see
    /// [`int8_quad_index`].
    pub const fn int8_weight_len(&self) -> usize {
        self.kernel_height
            * self.kernel_width
            * int8_quads(self.in_channels)
            * QUAD
            * self.out_channels
    }

    /// Length of the kernel in the int8 pair layout: input channels in zero-padded groups
    /// of eight, see [`int8_pair_index`].
    pub const fn int8_pair_weight_len(&self) -> usize {
        self.kernel_height
            * self.kernel_width
            * int8_pairs(self.in_channels)
            * PAIR
            * self.out_channels
    }

    /// [`int8_quad_index`] of this convolution's `(tap, input, output)` weight.
    pub const fn int8_index(&self, tap: usize, input: usize, output: usize) -> usize {
        int8_quad_index(
            self.kernel_height * self.kernel_width,
            self.in_channels,
            self.out_channels,
            (tap, input, output),
        )
    }
}
/// Input channels grouped per output channel in the int8 kernels of 2-D convolutions.
pub const QUAD: usize = 4;

/// Quads covering `in_channels` (the last one zero-padded when `in_channels % 4 != 0`).
pub const fn int8_quads(in_channels: usize) -> usize {
    in_channels.div_ceil(QUAD)
}

/// Output channels whose quads an int8 kernel stores together: a whole block (the last
/// may be narrower) before the next, every tap and quad of it. A SIMD tile walks one block's
/// taps and quads in address order, so its weights stream from contiguous memory and spread
/// over every cache set; with the channels of a quad row side by side over all of
/// `out_channels`, the rows a tile read were `4 out_channels` bytes apart, a power of two
/// in ResNet, and crowded into a sixteenth of L1's and L2's sets.
pub const INT8_CHANNEL_BLOCK: usize = 64;

/// Where weight `(tap, input, output)` of a convolution of `taps` kernel taps lives in its
/// int8 kernel: the layout `[ceil(out / 64), taps, ceil(in / 4), block, 4]` ("input-channel
/// quads in blocks of output channels", `block` the width of the channel's
/// [`INT8_CHANNEL_BLOCK`]). For each tap, quad and output channel, four consecutive input
/// channels are adjacent, which is what the integer dot-product instructions (`vpdpbusd`,
/// `vpmaddubsw`) multiply and add at once; 16 output channels of one quad are one 64-byte
/// load, and a channel's next quad is [`int8_quad_stride`] bytes further.
pub const fn int8_quad_index(
    taps: usize,
    in_channels: usize,
    out_channels: usize,
    at: (usize, usize, usize),
) -> usize {
    int8_group_index(QUAD, taps, in_channels, out_channels, at)
}

/// [`int8_quad_index`] with input channels in groups of `group` (4: the quads, 8: the
/// pairs of [`int8_pair_index`]).
const fn int8_group_index(
    group: usize,
    taps: usize,
    in_channels: usize,
    out_channels: usize,
    (tap, input, output): (usize, usize, usize),
) -> usize {
    let groups = in_channels.div_ceil(group);
    let block_start = output / INT8_CHANNEL_BLOCK * INT8_CHANNEL_BLOCK;
    let width = int8_quad_stride(out_channels, output) / QUAD;
    block_start * taps * groups * group
        + ((tap * groups + input / group) * width + output - block_start) * group
        + input % group
}

/// Bytes from a quad of output channel `output` to its next quad in the int8 layout of
/// [`int8_quad_index`]: four times the width of the channel's block.
pub const fn int8_quad_stride(out_channels: usize, output: usize) -> usize {
    let block_start = output / INT8_CHANNEL_BLOCK * INT8_CHANNEL_BLOCK;
    let rest = out_channels - block_start;
    let width = if rest < INT8_CHANNEL_BLOCK {
        rest
    } else {
        INT8_CHANNEL_BLOCK
    };
    width * QUAD
}

/// Input channels grouped per output channel in the pair layout: two quads, the eight
/// bytes I8MM's matrix multiplies (`smmla`, `usmmla`) take for one row of an operand.
pub const PAIR: usize = 2 * QUAD;

/// Groups of eight covering `in_channels` (the last one zero-padded).
pub const fn int8_pairs(in_channels: usize) -> usize {
    in_channels.div_ceil(PAIR)
}

/// Where weight `(tap, input, output)` lives in the int8 pair layout, the quad layout of
/// [`int8_quad_index`] with eight inputs a group instead of four:
/// `[ceil(out / 64), taps, ceil(in / 8), block, 8]`. Two adjacent channels' groups are one
/// 16-byte operand of a matrix multiply. A file may hold it beside the quads (docs/FORMAT.md)
/// for the backends that multiply 2 x 8 matrices; a channel's next group is
/// `2 int8_quad_stride` bytes further.
pub const fn int8_pair_index(
    taps: usize,
    in_channels: usize,
    out_channels: usize,
    at: (usize, usize, usize),
) -> usize {
    int8_group_index(PAIR, taps, in_channels, out_channels, at)
}

/// An int8 tensor's dims read as a convolution kernel: `[kh, kw, in, out]` (2-D) or
/// `[k, in, out]` (1-D) give `(taps, in, out)`; any other rank (the FiLM matrices) is not a
/// convolution. `None` too when `kh kw` overflows (the dims may come from a file).
pub fn int8_convolution(dims: &[usize]) -> Option<(usize, usize, usize)> {
    match *dims {
        [height, width, inputs, outputs] => Some((height.checked_mul(width)?, inputs, outputs)),
        [taps, inputs, outputs] => Some((taps, inputs, outputs)),
        _ => None,
    }
}

/// Elements an int8 tensor of `dims` stores: a convolution kernel in input-channel quads
/// (`taps x 4 ceil(in / 4) x out`, [`int8_quad_index`]), anything else as its dims say.
/// `None` when that overflows.
pub fn int8_stored_elements(dims: &[usize]) -> Option<usize> {
    match int8_convolution(dims) {
        Some((taps, inputs, outputs)) => taps
            .checked_mul(int8_quads(inputs) * QUAD)?
            .checked_mul(outputs),
        None => dims
            .iter()
            .try_fold(1usize, |product, &dim| product.checked_mul(dim)),
    }
}

/// Elements the pair layout of a convolution kernel of `dims` stores
/// (`taps x 8 ceil(in / 8) x out`, [`int8_pair_index`]); `None` for a tensor that is not a
/// convolution kernel, or when that overflows.
pub fn int8_pair_stored_elements(dims: &[usize]) -> Option<usize> {
    let (taps, inputs, outputs) = int8_convolution(dims)?;
    taps.checked_mul(int8_pairs(inputs) * PAIR)?
        .checked_mul(outputs)
}

/// Packs `weight` (`[taps, in, out]`, the f32 layout) into the int8 quad layout `packed`
/// (`taps * ceil(in / 4) * 4 * out` values; the padding channels are written as 0).
pub fn pack_int8_quads(weight: &[i8], in_channels: usize, out_channels: usize, packed: &mut [i8]) {
    pack_int8_groups(QUAD, weight, (in_channels, out_channels), packed)
}

/// Packs `weight` (`[taps, in, out]`) into the int8 pair layout `packed` (`taps * ceil(in /
/// 8) * 8 * out` values; the padding channels are written as 0).
pub fn pack_int8_pairs(weight: &[i8], in_channels: usize, out_channels: usize, packed: &mut [i8]) {
    pack_int8_groups(PAIR, weight, (in_channels, out_channels), packed)
}

fn pack_int8_groups(
    group: usize,
    weight: &[i8],
    (in_channels, out_channels): (usize, usize),
    packed: &mut [i8],
) {
    let taps = weight.len() / (in_channels * out_channels).max(1);
    packed.fill(0);
    for tap in 0..taps {
        for input in 0..in_channels {
            for output in 0..out_channels {
                let at = (tap, input, output);
                packed[int8_group_index(group, taps, in_channels, out_channels, at)] =
                    weight[(tap * in_channels + input) * out_channels + output];
            }
        }
    }
}
