//! The AMX backend runs the int8 convolutions on its tiles only for the shapes they take
//! (`Amx::covers`, `Amx::covers_codes`); any other shape goes, silently and correctly, to
//! the AVX-512 kernels. The speed of the trunk and of the denoiser rests on every int8
//! layer of the product models being taken (the stem's patch bands included): this encodes
//! a frame of metaworld and panda and runs an inference through a kernel wrapper that
//! records every int8 convolution it is asked for, and checks each one.
#![cfg(target_arch = "x86_64")]

use std::sync::Mutex;

use scdp_engine::frame::PATCH_CHANNELS;
use scdp_engine::kernels::x86_64::amx::Amx;
use scdp_engine::kernels::{
    Accumulate, ByteRows, CodeRows, ConvShape, DigitRows, Kernels, scalar::Scalar,
};
use scdp_engine::{ArenaPlan, Camera, Model, ModelConfig, Noise, Policy};
use scdp_tests::synthetic_weights_file_as;
use weights_tool::Quant;
use weights_tool::writer::AlignedBytes;

/// The scalar reference, recording the shape of each int8 convolution and whether the
/// tiles would take it.
struct Recording {
    calls: Mutex<Vec<(ConvShape, bool)>>,
    /// The same for the U-Net's convolutions on signed codes.
    code_calls: Mutex<Vec<(ConvShape, bool)>>,
    /// The U-Net's convolutions the tiles take as short sequences.
    short_sequences: Mutex<Vec<ConvShape>>,
}

impl Kernels for Recording {
    fn name(&self) -> &'static str {
        "recording"
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
        Scalar.conv(shape, input, weight, bias, output, accumulate)
    }

    fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
        Scalar.matvec(weight, input, base, output)
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
        let covered = Amx::covers(shape, input);
        self.calls.lock().unwrap().push((*shape, covered));
        Scalar.conv_int8(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        )
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
        let covered = Amx::covers_bytes(shape, input);
        self.calls.lock().unwrap().push((*shape, covered));
        Scalar.conv_int8_bytes(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        )
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
        let covered = Amx::covers_codes(shape, input);
        self.code_calls.lock().unwrap().push((*shape, covered));
        if Amx::covers_short_sequence(shape, input) {
            self.short_sequences.lock().unwrap().push(*shape);
        }
        Scalar.conv_int8_codes(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        )
    }

    fn matvec_int8_codes(
        &self,
        weight: &[i8],
        row_scales: &[f32],
        input: &CodeRows<'_>,
        base: &[f32],
        output: &mut [f32],
    ) {
        Scalar.matvec_int8_codes(weight, row_scales, input, base, output)
    }
}

/// The int8 convolutions one frame and one inference ask for, each with whether the tiles
/// take it.
struct Recorded {
    /// The trunk's dense ones (digit planes).
    trunk: Vec<(ConvShape, bool)>,
    /// The U-Net's (codes).
    unet: Vec<(ConvShape, bool)>,
    /// Those of the U-Net's the tiles take as short sequences.
    short_sequences: Vec<ConvShape>,
}

fn int8_convolutions_of_one_inference(config: ModelConfig) -> Recorded {
    let weights = synthetic_weights_file_as(&config, 1, Quant::Int8).unwrap();
    let model = Model::from_bytes(weights.as_slice()).unwrap();
    let recording: &'static Recording = Box::leak(Box::new(Recording {
        calls: Mutex::new(Vec::new()),
        code_calls: Mutex::new(Vec::new()),
        short_sequences: Mutex::new(Vec::new()),
    }));
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
    let mut policy = Policy::with_kernels(&model, arena.as_mut_slice(), recording).unwrap();
    let pixels = (config.image_height * config.image_width) as usize;
    // A frame with structure (the values do not matter to which shapes run).
    let frame: Vec<u8> = (0..3 * pixels).map(|i| (i * 7 % 251) as u8).collect();
    let state = vec![0.1; config.state_dim as usize];
    policy.push_observation(&frame, &state).unwrap();
    let trunk = recording.calls.lock().unwrap().clone();
    let (width, height) = (config.image_width as f32, config.image_height as f32);
    let intrinsics = [
        [width, 0.0, width / 2.0],
        [0.0, width, height / 2.0],
        [0.0, 0.0, 1.0],
    ];
    let mut extrinsics = [[0.0; 4]; 4];
    for (axis, row) in extrinsics.iter_mut().enumerate() {
        row[axis] = 1.0;
    }
    extrinsics[2][3] = 1.0;
    policy.set_camera(Camera::new(&intrinsics, &extrinsics).unwrap());
    policy.infer(Noise::Seed(3)).unwrap();
    let unet = recording.code_calls.lock().unwrap().clone();
    let short = recording.short_sequences.lock().unwrap().clone();
    Recorded {
        trunk,
        unet,
        short_sequences: short,
    }
}

#[test]
fn amx_tiles_take_every_dense_int8_convolution_of_the_product_models() {
    for (name, config) in [
        ("metaworld", ModelConfig::METAWORLD),
        ("panda", ModelConfig::PANDA),
    ] {
        let calls = int8_convolutions_of_one_inference(config).trunk;
        let (stem, others): (Vec<_>, Vec<_>) = calls
            .iter()
            .partition(|(shape, _)| shape.in_channels == PATCH_CHANNELS);
        // The stem: 1x1 convolutions over its patches, a band of output rows each, all of
        // them together one output row per stem row.
        let (stem_height, stem_width) = config.stem_size();
        let stem_rows: usize = stem.iter().map(|(shape, _)| shape.in_height).sum();
        assert_eq!(stem_rows, stem_height, "{name}");
        for (shape, _) in &stem {
            assert_eq!(
                (shape.kernel_height, shape.in_width),
                (1, stem_width),
                "{name}"
            );
        }
        // ResNet-18's other 19 int8 convolutions (16 3x3, three 1x1 downsamples) and the
        // dense projections (the others run per cell, during inference).
        let dense_projections = (0..5)
            .filter(|&level| !config.projection_on_demand(level))
            .count();
        assert_eq!(others.len(), 19 + dense_projections, "{name}");
        for &(shape, covered) in &calls {
            assert!(covered, "{name}: the AMX tiles do not take {shape:?}");
        }
    }
}

#[test]
fn amx_tiles_take_every_int8_convolution_of_the_denoiser() {
    for (name, config) in [
        ("metaworld", ModelConfig::METAWORLD),
        ("panda", ModelConfig::PANDA),
    ] {
        let Recorded {
            unet: calls,
            short_sequences: short,
            ..
        } = int8_convolutions_of_one_inference(config);
        // Per step: two per residual block (12 of them), five 1x1 residuals where the width
        // changes, two downsamplings, the first upsampling and the final block's;
        // the head and the second upsampling are f32.
        let steps = config.num_inference_steps as usize;
        assert_eq!(calls.len(), steps * (2 * 12 + 5 + 2 + 1 + 1), "{name}");
        for &(shape, covered) in &calls {
            assert!(covered, "{name}: the AMX tiles do not take {shape:?}");
        }
        // Those at half and a quarter of the horizon (the ten blocks there, four of the
        // residuals, both downsamplings, the upsampling) take the one-pass kernel: all but
        // the five at the full horizon and the first block's residual on the sample.
        assert_eq!(short.len(), steps * (2 * 10 + 4 + 2 + 1), "{name}");
        for (shape, _) in &calls {
            if shape.out_width() <= (config.horizon / 2) as usize {
                assert!(
                    short.contains(shape),
                    "{name}: not a short sequence: {shape:?}"
                );
            }
        }
    }
}
