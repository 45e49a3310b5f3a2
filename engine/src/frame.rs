//! Camera frame -> network input: `x / 255` in f32, optionally ImageNet-normalized,
//! kept channels-last `[H, W, 3]` (the trunk's layout); or, for an int8 stem, the bytes
//! themselves as the stem's patches.

use core::ops::Range;

use crate::config::ModelConfig;
use crate::error::Error;
use crate::shape::QUAD;

// The stem's geometry belongs to the configuration it constrains; re-exported here, where
// the patches are cut by it, under the path dependants know.
pub use crate::config::{STEM_KERNEL, STEM_PADDING, STEM_STRIDE};

/// Values of one stem patch: each of the 49 taps a quad (the pixel's three bytes and a
/// zero). An int8 kernel over three channels stores one quad a tap ([`int8_quad_index`]),
/// so the stem's int8 kernel, as stored, is also the weight matrix of a 1x1 convolution
/// over these patches, with no repacking.
///
/// [`int8_quad_index`]: crate::shape::int8_quad_index
pub const PATCH_CHANNELS: usize = STEM_KERNEL * STEM_KERNEL * QUAD;

/// `(rows, columns)` of the image with the stem's zero padding around it.
pub const fn padded_size(config: &ModelConfig) -> (usize, usize) {
    (
        config.image_height as usize + 2 * STEM_PADDING,
        config.image_width as usize + 2 * STEM_PADDING,
    )
}

/// Bytes of the padded image ([`pad_image`]).
pub const fn padded_image_bytes(config: &ModelConfig) -> usize {
    let (rows, columns) = padded_size(config);
    rows * columns * QUAD
}

const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// Bytes of one RGB frame for `config`.
pub const fn frame_bytes(config: &ModelConfig) -> usize {
    config.image_height as usize * config.image_width as usize * 3
}

/// Fails unless `image` is one RGB frame of `config`'s size.
pub fn check_size(config: &ModelConfig, image: &[u8]) -> Result<(), Error> {
    let expected = frame_bytes(config);
    if image.len() != expected {
        return Err(Error::ImageSize {
            expected,
            found: image.len(),
        });
    }
    Ok(())
}

/// Writes the network input of `image` (of the right size, [`check_size`]), `H W 3`
/// values, to the front of `output`.
pub fn normalize(config: &ModelConfig, image: &[u8], output: &mut [f32]) {
    let (mean, std) = if config.imagenet_norm {
        (IMAGENET_MEAN, IMAGENET_STD)
    } else {
        ([0.0; 3], [1.0; 3])
    };
    for (out, pixel) in output.chunks_exact_mut(3).zip(image.chunks_exact(3)) {
        for channel in 0..3 {
            // Same operation order as PyTorch: divide, subtract, divide.
            out[channel] = (pixel[channel] as f32 / 255.0 - mean[channel]) / std[channel];
        }
    }
}

/// The image bytes (of the right size, [`check_size`]), each pixel a quad (its colours
/// and a zero), with the stem's padding of zero pixels around them: `[rows, columns, 4]`
/// of [`padded_size`], at the front of `padded` (at least [`padded_image_bytes`] bytes).
/// Without ImageNet normalization a zero byte is the network's zero, so these codes with
/// the scale `1 / 255` are the stem's input exactly.
pub fn pad_image<'p>(config: &ModelConfig, image: &[u8], padded: &'p mut [u8]) -> &'p [u8] {
    let padded = &mut padded[..padded_image_bytes(config)];
    let (_, columns) = padded_size(config);
    let width = config.image_width as usize;
    debug_assert_eq!(image.len(), config.image_height as usize * width * 3);
    let line_bytes = columns * QUAD;
    let border = STEM_PADDING * QUAD;
    let padding_lines = STEM_PADDING * line_bytes;
    // Only the padding is zeroed: the image's quads are written whole below.
    let end = padded.len() - padding_lines;
    padded[..padding_lines].fill(0);
    padded[end..].fill(0);
    let lines = image.chunks_exact(width * 3);
    for (line, padded_line) in lines.zip(padded[padding_lines..].chunks_exact_mut(line_bytes)) {
        padded_line[..border].fill(0);
        padded_line[border + width * QUAD..].fill(0);
        let quads = padded_line[border..].chunks_exact_mut(QUAD);
        for (pixel, quad) in line.chunks_exact(3).zip(quads) {
            quad.copy_from_slice(&[pixel[0], pixel[1], pixel[2], 0]);
        }
    }
    padded
}

/// The stem's input patches of output rows `rows`, from the padded image of
/// [`pad_image`]: for each output pixel, [`PATCH_CHANNELS`] bytes, tap
/// `(kernel_y, kernel_x)`'s quad at `4 (7 kernel_y + kernel_x)`. A kernel row's seven
/// quads are adjacent in the padded image, so each is one copy.
pub fn patch_rows(config: &ModelConfig, padded: &[u8], rows: Range<usize>, patches: &mut [u8]) {
    let (_, columns) = padded_size(config);
    let (_, out_width) = config.stem_size();
    let row_bytes = STEM_KERNEL * QUAD;
    let mut pixels = patches.chunks_exact_mut(PATCH_CHANNELS);
    for out_y in rows {
        for out_x in 0..out_width {
            let Some(patch) = pixels.next() else { return };
            for (kernel_y, patch_row) in patch.chunks_exact_mut(row_bytes).enumerate() {
                let start =
                    ((out_y * STEM_STRIDE + kernel_y) * columns + out_x * STEM_STRIDE) * QUAD;
                patch_row.copy_from_slice(&padded[start..][..row_bytes]);
            }
        }
    }
}
