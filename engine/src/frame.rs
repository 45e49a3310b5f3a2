//! Camera frame -> network input: `x / 255` in f32, optionally ImageNet-normalized,
//! kept channels-last `[H, W, 3]` (the trunk's layout).

use crate::config::ModelConfig;
use crate::error::Error;

const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// Bytes of one RGB frame for `config`.
pub const fn frame_bytes(config: &ModelConfig) -> usize {
    config.image_height as usize * config.image_width as usize * 3
}

/// Checks the frame's size; writes `H W 3` values to the front of `output`.
pub fn preprocess(config: &ModelConfig, image: &[u8], output: &mut [f32]) -> Result<(), Error> {
    let expected = frame_bytes(config);
    if image.len() != expected {
        return Err(Error::ImageSize {
            expected,
            found: image.len(),
        });
    }
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
    Ok(())
}
