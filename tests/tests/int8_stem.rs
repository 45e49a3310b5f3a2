//! The int8 stem runs as a 1x1 convolution over image patches, a band of output rows at a
//! time (`pyramid::stem`). It must give, bit for bit, what the 7x7 stride-2 int8
//! convolution of the contract gives on the same input: the image bytes as codes with the
//! scale 1 / 255, zero padding, the weights as the tool stores them. The reference here is
//! that convolution on the scalar backend, then the backend's own GroupNorm + ReLU and the
//! max pool (the stem takes the norm's moments band by band and normalizes inside the pool;
//! the bits must not change).

use scdp_engine::config::ModelConfig;
use scdp_engine::frame::{PATCH_CHANNELS, STEM_KERNEL, STEM_PADDING, STEM_STRIDE};
use scdp_engine::kernels::ops::Activation;
use scdp_engine::kernels::scalar::Scalar;
use scdp_engine::kernels::{
    Accumulate, ConvShape, DigitRows, Kernels, QuantizeScratch, int8_quad_index,
};
use scdp_engine::pyramid;
use scdp_engine::rng::NoiseRng;
use scdp_engine::weights::{ActivationCodes, Conv, ConvNorm, Norm, Weight};
use scdp_tests::available_backends;

#[test]
fn int8_stem_over_patches_equals_the_7x7_convolution() {
    // Odd sizes: the last output column and row read the padding, and the last band is
    // shorter than the others.
    let config = ModelConfig {
        image_height: 29,
        image_width: 31,
        imagenet_norm: false,
        ..ModelConfig::METAWORLD
    };
    let (height, width) = (config.image_height as usize, config.image_width as usize);
    let channels = config.stage_channels(0);
    let shape = ConvShape::square(
        (height, width, 3),
        channels,
        STEM_KERNEL,
        STEM_STRIDE,
        STEM_PADDING,
    );
    // The engine's own generator: the values only need to be varied and repeatable.
    let mut random = NoiseRng::new(7);
    // Every byte value, the extremes included, then random ones.
    let image: Vec<u8> = (0..height * width * 3)
        .map(|i| {
            if i < 256 {
                i as u8
            } else {
                random.next_u64() as u8
            }
        })
        .collect();

    // The weights as the tool stores a [7, 7, 3, out] kernel: one quad a tap, the fourth
    // input of each quad zero; the largest magnitudes included.
    let mut weight = vec![0i8; shape.int8_weight_len()];
    for tap in 0..STEM_KERNEL * STEM_KERNEL {
        for input in 0..3 {
            for output in 0..channels {
                let value = match (tap + input + output) % 17 {
                    0 => -128,
                    1 => 127,
                    _ => random.next_u64() as i8,
                };
                weight[int8_quad_index(
                    STEM_KERNEL * STEM_KERNEL,
                    3,
                    channels,
                    (tap, input, output),
                )] = value;
            }
        }
    }
    let scales: Vec<f32> = (0..channels)
        .map(|_| 1e-3 * (1.0 + (random.next_u64() % 1000) as f32 / 100.0))
        .collect();
    let signed = |random: &mut NoiseRng| (random.next_u64() % 2001) as f32 / 1000.0 - 1.0;
    let bias: Vec<f32> = (0..channels).map(|_| signed(&mut random)).collect();
    let gamma: Vec<f32> = (0..channels).map(|_| 1.0 + signed(&mut random)).collect();
    let beta: Vec<f32> = (0..channels).map(|_| signed(&mut random)).collect();
    let layer = ConvNorm {
        conv: Conv {
            weight: Weight::Int8 {
                values: &weight,
                scales: &scales,
                activations: ActivationCodes::Wide,
                residual: None,
                pairs: None,
            },
            bias: &bias,
        },
        norm: Some(Norm {
            gamma: &gamma,
            beta: &beta,
        }),
    };

    // The contract's convolution on the bytes as codes: 128 high + low.
    let high: Vec<i8> = image.iter().map(|&b| (b >> 7) as i8).collect();
    let low: Vec<i8> = image.iter().map(|&b| (b & 0x7f) as i8).collect();
    let codes = DigitRows {
        high: &high,
        low: &low,
        scale: 1.0 / 255.0,
        nonnegative: true,
    };
    let mut convolved = vec![0.0f32; shape.output_len()];
    Scalar.conv_int8(
        &shape,
        &codes,
        &weight,
        &scales,
        &bias,
        &mut convolved,
        Accumulate::Overwrite,
    );

    let out_width = shape.out_width();
    for backend in available_backends() {
        let kernels = scdp_engine::kernels::select(backend).unwrap();
        let mut expected = convolved.clone();
        kernels.group_norm(
            &mut expected,
            channels,
            ModelConfig::backbone_groups(channels),
            (&gamma, &beta),
            Activation::Relu,
        );
        let (pooled_height, pooled_width) = config.pyramid_size(0);
        let mut expected_pooled = vec![0.0f32; pooled_height * pooled_width * channels];
        Scalar.max_pool_3x3_stride_2(
            &expected,
            (shape.out_height(), out_width, channels),
            &mut expected_pooled,
        );
        // Output rows of 16 pixels: room for one row of patches holds less than a block of
        // GroupNorm's moments (the map is normalized whole); for 4 and 6 rows, bands of 4
        // (whole blocks) and a shorter last; for all, one band.
        for band_rows in [1, 4, 6, shape.out_height()] {
            let mut quantized = vec![0i8; band_rows * out_width * PATCH_CHANNELS + 5];
            // The pooled map's buffer first holds the padded image.
            let mut pooled = vec![f32::NAN; (4 * height * width).max(expected_pooled.len())];
            let mut map = vec![f32::NAN; shape.output_len()];
            pyramid::stem(
                kernels,
                &config,
                &layer,
                &image,
                (&mut pooled, &mut map),
                &mut QuantizeScratch {
                    values: &mut quantized,
                },
            );
            let differing = pooled[..expected_pooled.len()]
                .iter()
                .zip(&expected_pooled)
                .filter(|(a, b)| a.to_bits() != b.to_bits())
                .count();
            assert_eq!(
                differing,
                0,
                "{}: {differing} of {} pooled stem outputs differ from the 7x7 convolution's (bands of {band_rows} rows)",
                kernels.name(),
                expected_pooled.len()
            );
        }
    }
}
