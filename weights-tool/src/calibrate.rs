//! Calibration for error-compensating int8 rounding ([`crate::gptq`]): the f32 model runs
//! on calibration scenes, and for every weight that may be stored as int8 the second moment
//! of what it multiplies, `H = sum x x^T`, is accumulated (`x` = one output position's
//! input patch of a convolution, or the input vector of a FiLM matrix).
//!
//! The engine is not modified for this: its kernel contract is the one place every layer's
//! input passes through, so a [`Recorder`] implementing [`Kernels`] records the inputs and
//! hands the work to the fastest real backend. Layers are told apart by the address of
//! their weights in the loaded file.

use std::collections::{BTreeMap, HashMap};
use std::sync::Mutex;

use anyhow::{Context, Result, anyhow, ensure};
use faer::{Accum, Mat, Par};
use indicatif::{ProgressBar, ProgressStyle};
use scdp_engine::format::WeightsFile;
use scdp_engine::kernels::ops::Activation;
use scdp_engine::kernels::{self, Accumulate, Backend, CodeRows, ConvShape, DigitRows, Kernels};
use scdp_engine::{ArenaPlan, Camera, Model, ModelConfig, Noise, Policy};

use crate::run::RunInputs;
use crate::writer::AlignedBytes;

/// Input second moments of the weights that may be stored as int8, by engine name.
pub type Moments = BTreeMap<String, InputMoment>;

/// `sum x x^T` over the `samples` input vectors a weight multiplied, in the order of the
/// weight's reduction axis (`tap * in_channels + channel` for convolutions, the column for
/// FiLM matrices).
pub struct InputMoment {
    pub second_moment: Mat<f32>,
    pub samples: usize,
}

/// Input patches of one output position are recorded for at most this many positions per
/// call, spread over the map and rotated between calls: the large early maps have far more
/// positions than their patch length needs, and every patch costs `D^2` to accumulate.
const POSITIONS_PER_CALL: usize = 256;

/// Patches gathered before one `H += X^T X` product.
const BATCH_ROWS: usize = 256;

struct Layer {
    name: String,
    dim: usize,
    moment: Mat<f32>,
    samples: usize,
    pending: Vec<f32>,
    calls: usize,
}

impl Layer {
    fn flush(&mut self) {
        let rows = self.pending.len() / self.dim;
        if rows == 0 {
            return;
        }
        let patches = faer::MatRef::from_row_major_slice(&self.pending, rows, self.dim);
        faer::linalg::matmul::matmul(
            self.moment.as_mut(),
            Accum::Add,
            patches.transpose(),
            patches,
            1.0f32,
            Par::Seq,
        );
        self.samples += rows;
        self.pending.clear();
    }

    fn push(&mut self, patch: impl FnOnce(&mut [f32])) {
        let start = self.pending.len();
        self.pending.resize(start + self.dim, 0.0);
        patch(&mut self.pending[start..]);
        if self.pending.len() >= BATCH_ROWS * self.dim {
            self.flush();
        }
    }
}

/// Writes the input patch of output position `(out_y, out_x)` (`[tap, channel]`, zeros
/// where the kernel reads padding).
fn gather_patch(
    shape: &ConvShape,
    input: &[f32],
    (out_y, out_x): (usize, usize),
    patch: &mut [f32],
) {
    let channels = shape.in_channels;
    for ky in 0..shape.kernel_height {
        for kx in 0..shape.kernel_width {
            let tap = ky * shape.kernel_width + kx;
            let target = &mut patch[tap * channels..][..channels];
            let y = (out_y * shape.stride + ky).checked_sub(shape.padding_height);
            let x = (out_x * shape.stride + kx).checked_sub(shape.padding_width);
            match (y, x) {
                (Some(y), Some(x)) if y < shape.in_height && x < shape.in_width => {
                    target
                        .copy_from_slice(&input[(y * shape.in_width + x) * channels..][..channels]);
                }
                _ => target.fill(0.0),
            }
        }
    }
}

/// A [`Kernels`] implementation that records the input of every tracked weight and runs
/// `inner`.
pub struct Recorder {
    inner: &'static dyn Kernels,
    by_address: HashMap<usize, usize>,
    layers: Mutex<Vec<Layer>>,
}

impl Recorder {
    fn layer_of(&self, weight: &[f32]) -> Option<usize> {
        self.by_address.get(&(weight.as_ptr() as usize)).copied()
    }

    fn record_conv(
        &self,
        shape: &ConvShape,
        input: &[f32],
        weight: &[f32],
        pixels: Option<(usize, usize)>,
    ) {
        let Some(index) = self.layer_of(weight) else {
            return;
        };
        let mut layers = self.layers.lock().expect("recorder lock");
        let layer = &mut layers[index];
        if let Some(pixel) = pixels {
            layer.push(|patch| gather_patch(shape, input, pixel, patch));
            return;
        }
        let (height, width) = (shape.out_height(), shape.out_width());
        let positions = height * width;
        let stride = positions.div_ceil(POSITIONS_PER_CALL).max(1);
        let phase = layer.calls % stride;
        layer.calls += 1;
        for position in (phase..positions).step_by(stride) {
            layer.push(|patch| {
                gather_patch(shape, input, (position / width, position % width), patch)
            });
        }
    }
}

impl Kernels for Recorder {
    fn name(&self) -> &'static str {
        self.inner.name()
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
        self.record_conv(shape, input, weight, None);
        self.inner
            .conv(shape, input, weight, bias, output, accumulate);
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
        self.record_conv(shape, input, weight, Some(pixel));
        self.inner
            .conv_pixel(shape, input, weight, bias, pixel, output);
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
        self.inner
            .conv_int8_pixel(shape, input, weight, weight_scales, bias, pixel, output);
    }

    fn matvec(&self, weight: &[f32], input: &[f32], base: &[f32], output: &mut [f32]) {
        if let Some(index) = self.layer_of(weight) {
            let mut layers = self.layers.lock().expect("recorder lock");
            layers[index].push(|patch| patch.copy_from_slice(input));
        }
        self.inner.matvec(weight, input, base, output);
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
        self.inner.conv_int8(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        );
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
        self.inner.conv_int8_codes(
            shape,
            input,
            weight,
            weight_scales,
            bias,
            output,
            accumulate,
        );
    }

    fn matvec_int8_codes(
        &self,
        weight: &[i8],
        row_scales: &[f32],
        input: &CodeRows<'_>,
        base: &[f32],
        output: &mut [f32],
    ) {
        self.inner
            .matvec_int8_codes(weight, row_scales, input, base, output)
    }

    fn quantize_digits(&self, input: &[f32], digits: (&mut [i8], &mut [i8])) -> (f32, bool) {
        self.inner.quantize_digits(input, digits)
    }

    fn group_norm(
        &self,
        data: &mut [f32],
        channels: usize,
        groups: usize,
        affine: (&[f32], &[f32]),
        activation: Activation,
    ) {
        self.inner
            .group_norm(data, channels, groups, affine, activation);
    }

    fn add_activate(&self, target: &mut [f32], source: &[f32], activation: Activation) {
        self.inner.add_activate(target, source, activation);
    }
}

/// Runs the f32 weights file `f32_file` on every scene and returns the input moments of
/// the weights that may be stored as int8 (the tensors of `int8_names`, with the length of
/// their reduction axis).
pub fn input_moments(
    f32_file: &[u8],
    int8_names: &[(String, usize)],
    scenes: &[RunInputs],
    progress: bool,
) -> Result<Moments> {
    let weights = crate::writer::aligned_copy(f32_file);
    let file = WeightsFile::parse(weights.as_slice()).map_err(|error| anyhow!("{error}"))?;
    let mut by_address = HashMap::new();
    let mut layers = Vec::new();
    for index in 0..file.tensor_count() {
        let entry = file.entry(index).map_err(|error| anyhow!("{error}"))?;
        if let Some((name, dim)) = int8_names.iter().find(|(name, _)| name == entry.name) {
            by_address.insert(file.data(&entry).as_ptr() as usize, layers.len());
            layers.push(Layer {
                name: name.clone(),
                dim: *dim,
                moment: Mat::zeros(*dim, *dim),
                samples: 0,
                pending: Vec::new(),
                calls: 0,
            });
        }
    }
    ensure!(
        layers.len() == int8_names.len(),
        "internal: {} of {} int8 tensors found in the f32 file",
        layers.len(),
        int8_names.len()
    );
    let inner = kernels::select(Backend::Auto).context("no kernel backend")?;
    // The engine holds its kernels for 'static; one small recorder per calibration leaks
    // (its layers are taken back out below).
    let recorder: &'static Recorder = Box::leak(Box::new(Recorder {
        inner,
        by_address,
        layers: Mutex::new(layers),
    }));
    let model = Model::from_bytes(weights.as_slice()).map_err(|error| anyhow!("{error}"))?;
    let config: ModelConfig = *model.config();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
    let bar = if progress {
        ProgressBar::new(scenes.len() as u64).with_style(
            ProgressStyle::with_template("calibrating {bar:30} {pos}/{len} scenes ({eta})")
                .expect("progress template"),
        )
    } else {
        ProgressBar::hidden()
    };
    for (index, scene) in scenes.iter().enumerate() {
        let mut policy = Policy::with_kernels(&model, arena.as_mut_slice(), recorder)
            .map_err(|error| anyhow!("{error}"))?;
        let camera = Camera::new(&scene.intrinsics, &scene.extrinsics)
            .map_err(|error| anyhow!("calibration scene {index}: camera: {error}"))?;
        policy.set_camera(camera);
        let frames = config.n_obs_steps as usize;
        let frame_bytes = scene.images.len() / frames;
        let state_dim = config.state_dim as usize;
        for frame in 0..frames {
            policy
                .push_observation(
                    &scene.images[frame * frame_bytes..][..frame_bytes],
                    &scene.state[frame * state_dim..][..state_dim],
                )
                .map_err(|error| anyhow!("calibration scene {index}: {error}"))?;
        }
        let noise = match &scene.noise {
            Some(values) => Noise::Given(values),
            None => Noise::Seed(0x5eed_0000 + index as u64),
        };
        policy
            .infer(noise)
            .map_err(|error| anyhow!("calibration scene {index}: {error}"))?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    let mut layers = std::mem::take(&mut *recorder.layers.lock().expect("recorder lock"));
    let mut moments = Moments::new();
    for layer in &mut layers {
        layer.flush();
    }
    for layer in layers {
        moments.insert(
            layer.name,
            InputMoment {
                second_moment: layer.moment,
                samples: layer.samples,
            },
        );
    }
    Ok(moments)
}
