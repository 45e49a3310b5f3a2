//! The trunk's convolutions alone, per layer shape of the panda trunk (320x240 frames), on
//! every SIMD backend this CPU runs: int8 (`conv_int8/...`) and f32 (`conv_f32/...`, the stem
//! and two 3x3 layers): `cargo bench -p scdp-benches --bench kernels`. Criterion reports the
//! throughput in MACs a second (elements = MACs, taps on the padding included as in
//! `--bin macs`), to set against the peak rates of `--bench peak`. Also the GroupNorm and
//! Mish after each of the U-Net's convolutions (`group_norm/...`, elements = values), which
//! run on the calling core between the split convolutions.

use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use scdp_engine::Backend;
use scdp_engine::kernels::ops::Activation;
use scdp_engine::kernels::{
    Accumulate, ByteRows, ConvShape, DigitRows, Kernels, pack_int8_quads, select,
};
use weights_tool::writer::AlignedBytes;

/// `(name, shape)` of the distinct int8 convolutions of one panda frame.
fn panda_trunk_layers() -> [(&'static str, ConvShape); 8] {
    [
        (
            "layer1 3x3 64",
            ConvShape::square((60, 80, 64), 64, 3, 1, 1),
        ),
        (
            "layer2 3x3/2 64-128",
            ConvShape::square((60, 80, 64), 128, 3, 2, 1),
        ),
        (
            "layer2 3x3 128",
            ConvShape::square((30, 40, 128), 128, 3, 1, 1),
        ),
        (
            "layer3 3x3 256",
            ConvShape::square((15, 20, 256), 256, 3, 1, 1),
        ),
        (
            "layer4 3x3 512",
            ConvShape::square((8, 10, 512), 512, 3, 1, 1),
        ),
        (
            "layer4 3x3/2 256-512",
            ConvShape::square((15, 20, 256), 512, 3, 2, 1),
        ),
        (
            "layer4 1x1/2 256-512",
            ConvShape::square((15, 20, 256), 512, 1, 2, 0),
        ),
        (
            "projection 3x3 512-256",
            ConvShape::square((8, 10, 512), 256, 3, 1, 1),
        ),
    ]
}

/// A small deterministic generator: the values only need to be in range.
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> u32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 33) as u32
    }
}

fn benches(c: &mut Criterion) {
    let mut rng = Lcg(7);
    for (name, shape) in panda_trunk_layers() {
        // Both digit planes, back to back, as the engine quantizes a ReLU output, 64-byte
        // aligned as the arena places them (a tile row across two cache lines loads several
        // times slower on AMX).
        let mut planes = AlignedBytes::zeroed(2 * shape.input_len());
        for value in planes.as_mut_slice() {
            *value = (rng.next() % 128) as u8;
        }
        let values: &[i8] = bytemuck::cast_slice(planes.as_slice());
        let weight: Vec<i8> = (0..shape.weight_len())
            .map(|_| ((rng.next() % 255) as i32 - 127) as i8)
            .collect();
        // Aligned too, as a weights file places every tensor.
        let mut packed_bytes = AlignedBytes::zeroed(shape.int8_weight_len());
        let packed: &mut [i8] = bytemuck::cast_slice_mut(packed_bytes.as_mut_slice());
        pack_int8_quads(&weight, shape.in_channels, shape.out_channels, packed);
        let packed: &[i8] = packed;
        let weight_scales = vec![1e-3f32; shape.out_channels];
        let bias = vec![0.5f32; shape.out_channels];
        let mut output = vec![0.0f32; shape.output_len()];
        let input = DigitRows::from_planes(values, 0.01, true);
        on_every_backend(c, format!("conv_int8/{name}"), macs(&shape), |kernels| {
            kernels.conv_int8(
                &shape,
                black_box(&input),
                packed,
                &weight_scales,
                &bias,
                &mut output,
                Accumulate::Overwrite,
            )
        });
        // The same layer on 8-bit codes, as the fast file's residual blocks read them (the
        // high plane stands in for a byte a value).
        let bytes = ByteRows {
            bytes: &planes.as_slice()[..shape.input_len()],
            scale: 0.01,
        };
        on_every_backend(
            c,
            format!("conv_int8_bytes/{name}"),
            macs(&shape),
            |kernels| {
                kernels.conv_int8_bytes(
                    &shape,
                    black_box(&bytes),
                    packed,
                    &weight_scales,
                    &bias,
                    &mut output,
                    Accumulate::Overwrite,
                )
            },
        );
    }
}

/// Times `run` on each SIMD backend this CPU has, as the group `name`, throughput in
/// `elements` (MACs for a convolution).
fn on_every_backend(
    c: &mut Criterion,
    name: String,
    elements: u64,
    mut run: impl FnMut(&dyn Kernels),
) {
    let mut group = c.benchmark_group(name);
    group
        .sample_size(20)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2))
        .throughput(Throughput::Elements(elements));
    for backend in [Backend::Avx2, Backend::Avx512, Backend::Amx] {
        let Some(kernels) = select(backend) else {
            continue;
        };
        group.bench_function(kernels.name(), |b| b.iter(|| run(kernels)));
    }
    group.finish();
}

fn f32_benches(c: &mut Criterion) {
    let mut rng = Lcg(11);
    let mut value = move || (rng.next() % 2001) as f32 * 1e-3 - 1.0;
    for (name, shape) in [
        (
            "stem 7x7/2 3-64",
            ConvShape::square((240, 320, 3), 64, 7, 2, 3),
        ),
        (
            "layer1 3x3 64",
            ConvShape::square((60, 80, 64), 64, 3, 1, 1),
        ),
        (
            "layer4 3x3 512",
            ConvShape::square((8, 10, 512), 512, 3, 1, 1),
        ),
    ] {
        // 64-byte aligned, as the arena and the weights file place them.
        let mut aligned = |len: usize| {
            let mut bytes = AlignedBytes::zeroed(len * size_of::<f32>());
            let values: &mut [f32] = bytemuck::cast_slice_mut(bytes.as_mut_slice());
            values.iter_mut().for_each(|v| *v = value());
            bytes
        };
        let (input, weight) = (aligned(shape.input_len()), aligned(shape.weight_len()));
        let input: &[f32] = bytemuck::cast_slice(input.as_slice());
        let weight: &[f32] = bytemuck::cast_slice(weight.as_slice());
        let bias = vec![0.5f32; shape.out_channels];
        let mut output = vec![0.0f32; shape.output_len()];
        on_every_backend(c, format!("conv_f32/{name}"), macs(&shape), |kernels| {
            kernels.conv(
                &shape,
                black_box(input),
                weight,
                &bias,
                &mut output,
                Accumulate::Overwrite,
            )
        });
    }
}

/// Multiply-accumulates of a convolution, padding taps included.
fn macs(shape: &ConvShape) -> u64 {
    (shape.out_height()
        * shape.out_width()
        * shape.kernel_height
        * shape.kernel_width
        * shape.in_channels
        * shape.out_channels) as u64
}

/// GroupNorm (8 groups) then Mish on the U-Net's activations: `[positions, channels]` of
/// metaworld's levels (horizon 16).
fn norm_benches(c: &mut Criterion) {
    let mut rng = Lcg(13);
    for (positions, channels) in [(16, 128), (8, 256), (4, 384)] {
        let values: Vec<f32> = (0..positions * channels)
            .map(|_| (rng.next() % 2001) as f32 / 1000.0 - 1.0)
            .collect();
        let gamma = vec![1.1f32; channels];
        let beta = vec![0.1f32; channels];
        let mut data = values.clone();
        let name = format!("group_norm/{positions}x{channels} mish");
        on_every_backend(c, name, values.len() as u64, |kernels| {
            data.copy_from_slice(&values);
            kernels.group_norm(
                black_box(&mut data),
                channels,
                8,
                (&gamma, &beta),
                Activation::Mish,
            )
        });
    }
}

criterion_group!(kernels, benches, f32_benches, norm_benches);
criterion_main!(kernels);
