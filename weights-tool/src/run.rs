//! `weights-tool run`: the engine on the run files of docs/SPEC.md section 8, with an optional
//! picture of where the policy looked and an optional latency benchmark.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, ensure};
use safetensors::{Dtype, SafeTensors};
use scdp_engine::kernels::{self, Kernels};
use scdp_engine::{
    ArenaPlan, Backend, Camera, Model, ModelConfig, Noise, Policy, Prefix, PrefixMode,
};
use scdp_threads::ThreadPool;

use crate::writer::AlignedBytes;

/// The inputs of one inference (docs/SPEC.md section 8).
#[derive(Clone, Debug)]
pub struct RunInputs {
    /// `[To, H, W, 3]` RGB, oldest first.
    pub images: Vec<u8>,
    /// `[To, state_dim]`.
    pub state: Vec<f32>,
    /// `[horizon, action_dim]`; `None` to draw it from the engine's generator.
    pub noise: Option<Vec<f32>>,
    pub intrinsics: [[f32; 3]; 3],
    pub extrinsics: [[f32; 4]; 4],
    /// `[k, action_dim]` committed actions (docs/SPEC.md section 5.1), empty for none.
    pub prefix: Vec<f32>,
    /// `[m, action_dim]` planned actions after them, empty for none.
    pub planned: Vec<f32>,
    pub prefix_mode: PrefixMode,
}

impl RunInputs {
    /// The committed prefix and planned rows, as the engine takes them.
    pub fn held(&self) -> Prefix<'_> {
        Prefix::new(&self.prefix, self.prefix_mode).with_planned(&self.planned)
    }
}

/// An optional `[rows, action_dim]` f32 tensor, empty when absent.
fn optional_rows(
    tensors: &SafeTensors<'_>,
    name: &str,
    action_dim: usize,
    path: &Path,
) -> Result<Vec<f32>> {
    let Ok(view) = tensors.tensor(name) else {
        return Ok(Vec::new());
    };
    let rows = view.shape().first().copied().unwrap_or(0);
    tensor_f32(tensors, name, &[rows, action_dim], path)
}

fn tensor_f32(
    tensors: &SafeTensors<'_>,
    name: &str,
    shape: &[usize],
    path: &Path,
) -> Result<Vec<f32>> {
    let view = tensors
        .tensor(name)
        .with_context(|| format!("{}: no tensor `{name}`", path.display()))?;
    ensure!(
        view.dtype() == Dtype::F32,
        "{}: `{name}` is {:?}, expected F32",
        path.display(),
        view.dtype()
    );
    ensure!(
        view.shape() == shape,
        "{}: `{name}` has shape {:?}, expected {shape:?}",
        path.display(),
        view.shape()
    );
    Ok(view
        .data()
        .chunks_exact(4)
        .map(|bytes| f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]))
        .collect())
}

impl RunInputs {
    /// Reads and checks a run file against `config`.
    pub fn load(path: &Path, config: &ModelConfig) -> Result<Self> {
        let bytes =
            std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
        let tensors = SafeTensors::deserialize(&bytes)
            .with_context(|| format!("{}: not a safetensors file", path.display()))?;
        let frames = config.n_obs_steps as usize;
        let (height, width) = (config.image_height as usize, config.image_width as usize);
        let images = tensors
            .tensor("images")
            .with_context(|| format!("{}: no tensor `images`", path.display()))?;
        ensure!(
            images.dtype() == Dtype::U8 && images.shape() == [frames, height, width, 3],
            "{}: `images` is {:?} {:?}, expected U8 {:?}",
            path.display(),
            images.dtype(),
            images.shape(),
            [frames, height, width, 3]
        );
        let state = tensor_f32(
            &tensors,
            "state",
            &[frames, config.state_dim as usize],
            path,
        )?;
        let sequence = [config.horizon as usize, config.action_dim as usize];
        let noise = match tensors.tensor("noise") {
            Ok(_) => Some(tensor_f32(&tensors, "noise", &sequence, path)?),
            Err(_) => None,
        };
        let action_dim = config.action_dim as usize;
        let prefix = optional_rows(&tensors, "prefix", action_dim, path)?;
        let planned = optional_rows(&tensors, "planned", action_dim, path)?;
        let (_, metadata) = SafeTensors::read_metadata(&bytes)?;
        let prefix_mode = match metadata
            .metadata()
            .as_ref()
            .and_then(|entries| entries.get("prefix_mode"))
            .map(String::as_str)
        {
            None | Some("replace") => PrefixMode::Replace,
            Some("noised") => PrefixMode::Noised,
            Some(other) => anyhow::bail!(
                "{}: prefix_mode `{other}` is neither `replace` nor `noised`",
                path.display()
            ),
        };
        let k = tensor_f32(&tensors, "camera_k", &[3, 3], path)?;
        let t = tensor_f32(&tensors, "camera_t", &[4, 4], path)?;
        let mut intrinsics = [[0.0; 3]; 3];
        for (row, values) in intrinsics.iter_mut().zip(k.chunks_exact(3)) {
            row.copy_from_slice(values);
        }
        let mut extrinsics = [[0.0; 4]; 4];
        for (row, values) in extrinsics.iter_mut().zip(t.chunks_exact(4)) {
            row.copy_from_slice(values);
        }
        Ok(RunInputs {
            images: images.data().to_vec(),
            state,
            noise,
            intrinsics,
            extrinsics,
            prefix,
            planned,
            prefix_mode,
        })
    }
}

/// What one inference produced.
#[derive(Clone, Debug)]
pub struct RunOutputs {
    pub action_pred: Vec<f32>,
    pub action: Vec<f32>,
    /// `[steps, s + 1, 2]`, NaN where invalid.
    pub anchors_uv: Vec<f32>,
}

/// Wall-clock time of each stage of one inference.
#[derive(Clone, Copy, Debug, Default)]
pub struct StageTimes {
    /// Preprocessing, trunk and projections of each pushed frame, summed.
    pub encode_frames: Duration,
    /// The same for the newest frame only (the streaming latency's encoding part).
    pub encode_newest: Duration,
    /// The whole denoising loop (anchors, context, U-Net, DDIM for every step).
    pub denoise: Duration,
}

/// The kernel backends this CPU runs, fastest first: what `--kernels` accepts besides `auto`.
pub fn available_kernels() -> Vec<&'static str> {
    kernels::available().map(|kernels| kernels.name()).collect()
}

/// The kernels named `name` (`auto` for the fastest), or an error listing those this CPU
/// runs.
pub fn select_kernels(name: &str) -> Result<&'static dyn Kernels> {
    let available = available_kernels().join(", ");
    let backend = Backend::from_name(name)
        .with_context(|| format!("unknown kernels {name:?}; this CPU runs: auto, {available}"))?;
    kernels::select(backend).with_context(|| {
        format!("this CPU cannot run the {name} kernels; it runs: auto, {available}")
    })
}

/// A loaded model and an arena for it.
pub struct Runner {
    weights: AlignedBytes,
    arena: AlignedBytes,
    kernels: &'static dyn Kernels,
    /// Workers an inference runs on.
    threads: usize,
    /// A pool for each count of more than one thread asked for, kept (an idle pool's
    /// threads park), so switching counts starts no thread.
    pools: BTreeMap<usize, ThreadPool>,
}

impl Runner {
    /// The model on the fastest kernels this CPU runs.
    pub fn new(weights_file: &[u8]) -> Result<Self> {
        Self::with_kernels(weights_file, "auto")
    }

    /// The model on the kernels named `kernels` (`auto`, or a [`Backend`] name): an error
    /// naming the ones this CPU runs when it cannot run that one.
    pub fn with_kernels(weights_file: &[u8], kernels: &str) -> Result<Self> {
        let kernels = select_kernels(kernels)?;
        let weights = crate::writer::aligned_copy(weights_file);
        let model =
            Model::from_bytes(weights.as_slice()).map_err(|error| anyhow::anyhow!("{error}"))?;
        let arena = AlignedBytes::zeroed(ArenaPlan::new(model.config()).arena_bytes);
        Ok(Runner {
            weights,
            arena,
            kernels,
            threads: 1,
            pools: BTreeMap::new(),
        })
    }

    /// Runs each inference on `threads` workers (the calling thread and `threads - 1` more,
    /// started the first time this count is asked for).
    pub fn set_threads(&mut self, threads: usize) -> Result<()> {
        ensure!(threads > 0, "--threads needs at least one thread");
        if threads > 1 && !self.pools.contains_key(&threads) {
            let pool = ThreadPool::new(threads).context("starting the worker threads")?;
            self.pools.insert(threads, pool);
        }
        self.threads = threads;
        Ok(())
    }

    /// The name of the kernels that run.
    pub fn kernels_name(&self) -> &'static str {
        self.kernels.name()
    }

    /// Loads the model and a policy on the arena, its camera set to `inputs`', and hands the
    /// policy to `then`, with the pool it runs on (none for one thread).
    fn with_policy<R>(
        &mut self,
        inputs: &RunInputs,
        then: impl FnOnce(&mut Policy<'_, '_>, Option<&ThreadPool>) -> Result<R>,
    ) -> Result<R> {
        let model = Model::from_bytes(self.weights.as_slice())
            .map_err(|error| anyhow::anyhow!("{error}"))?;
        let mut policy = Policy::with_kernels(&model, self.arena.as_mut_slice(), self.kernels)
            .map_err(|error| anyhow::anyhow!("{error}"))?;
        let pool = self.pools.get(&self.threads);
        if let Some(pool) = pool {
            policy = policy.with_workers(pool);
        }
        let camera = Camera::new(&inputs.intrinsics, &inputs.extrinsics)
            .map_err(|error| anyhow::anyhow!("camera: {error}"))?;
        policy.set_camera(camera);
        then(&mut policy, pool)
    }

    /// [`with_policy`](Self::with_policy), every frame of `inputs` pushed first (oldest
    /// first; their encoding times into `times`).
    fn with_frames<R>(
        &mut self,
        inputs: &RunInputs,
        times: &mut StageTimes,
        then: impl FnOnce(&mut Policy<'_, '_>) -> Result<R>,
    ) -> Result<R> {
        self.with_policy(inputs, |policy, _| {
            push_frames(policy, inputs, times, &mut || ())?;
            then(policy)
        })
    }

    /// One inference: pushes every frame (oldest first), then denoises.
    pub fn run(&mut self, inputs: &RunInputs, seed: u64) -> Result<(RunOutputs, StageTimes)> {
        let mut times = StageTimes::default();
        let noise = match &inputs.noise {
            Some(values) => Noise::Given(values),
            None => Noise::Seed(seed),
        };
        let (outputs, denoise) = self.with_frames(inputs, &mut times, |policy| {
            let start = Instant::now();
            let actions = policy
                .infer_with(noise, inputs.held())
                .map_err(|error| anyhow::anyhow!("inference: {error}"))?;
            let denoise = start.elapsed();
            let outputs = RunOutputs {
                action_pred: actions.action_pred().to_vec(),
                action: actions.action().to_vec(),
                anchors_uv: actions.anchors_uv().to_vec(),
            };
            Ok((outputs, denoise))
        })?;
        times.denoise = denoise;
        Ok((outputs, times))
    }

    /// The predicted actions of `inputs` for each noise `seed`: the frames pushed once, then
    /// one inference per seed (what a controller's history gives every denoising run).
    pub fn action_preds(&mut self, inputs: &RunInputs, seeds: &[u64]) -> Result<Vec<Vec<f32>>> {
        self.with_frames(inputs, &mut StageTimes::default(), |policy| {
            seeds
                .iter()
                .map(|&seed| {
                    let actions = policy
                        .infer(Noise::Seed(seed))
                        .map_err(|error| anyhow::anyhow!("inference: {error}"))?;
                    Ok(actions.action_pred().to_vec())
                })
                .collect()
        })
    }
}

/// Pushes every frame of `inputs` (oldest first), adding their encoding times to `times`.
fn push_frames(
    policy: &mut Policy<'_, '_>,
    inputs: &RunInputs,
    times: &mut StageTimes,
    before_newest: &mut dyn FnMut(),
) -> Result<()> {
    let config = *policy.config();
    let frames = config.n_obs_steps as usize;
    let frame_bytes = inputs.images.len() / frames;
    let state_dim = config.state_dim as usize;
    for frame in 0..frames {
        if frame == frames - 1 {
            before_newest();
        }
        let start = Instant::now();
        policy
            .push_observation(
                &inputs.images[frame * frame_bytes..][..frame_bytes],
                &inputs.state[frame * state_dim..][..state_dim],
            )
            .map_err(|error| anyhow::anyhow!("frame {frame}: {error}"))?;
        let elapsed = start.elapsed();
        times.encode_frames += elapsed;
        times.encode_newest = elapsed;
    }
    Ok(())
}

/// Writes `action_pred`, `action` and `anchors_uv` as f32 safetensors.
pub fn write_outputs(path: &Path, config: &ModelConfig, outputs: &RunOutputs) -> Result<()> {
    let as_bytes = |values: &[f32]| {
        values
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<u8>>()
    };
    let action_dim = config.action_dim as usize;
    let entries = [
        (
            "action_pred",
            vec![config.horizon as usize, action_dim],
            as_bytes(&outputs.action_pred),
        ),
        (
            "action",
            vec![config.n_action_steps as usize, action_dim],
            as_bytes(&outputs.action),
        ),
        (
            "anchors_uv",
            vec![
                config.num_inference_steps as usize,
                config.anchor_count(),
                2,
            ],
            as_bytes(&outputs.anchors_uv),
        ),
    ];
    let views = entries
        .iter()
        .map(|(name, shape, data)| {
            Ok((
                *name,
                safetensors::tensor::TensorView::new(Dtype::F32, shape.clone(), data)?,
            ))
        })
        .collect::<Result<Vec<_>>>()?;
    let metadata: Option<std::collections::HashMap<String, String>> = None;
    safetensors::serialize_to_file(views, metadata, path)
        .with_context(|| format!("{}: cannot write", path.display()))
}

/// Median and 99th percentile of a set of durations.
pub fn percentiles(samples: &mut [Duration]) -> (Duration, Duration) {
    samples.sort();
    let at = |q: f64| samples[((samples.len() - 1) as f64 * q).round() as usize];
    (at(0.5), at(0.99))
}

/// The durations of each stage over a set of runs ([`bench`]).
#[derive(Clone, Debug, Default)]
pub struct StageSamples {
    encode: Vec<Duration>,
    denoise: Vec<Duration>,
    total: Vec<Duration>,
    streaming: Vec<Duration>,
    /// The calling thread's time in and between the pool's calls, each run: the older
    /// frames, then the newest frame and the loop.
    #[cfg(feature = "pool-timing")]
    calls: Vec<(scdp_threads::Timing, scdp_threads::Timing)>,
}

impl StageSamples {
    /// Median and 99th percentile of each stage over every run of `sets`.
    pub fn table(sets: &[StageSamples]) -> BTreeMap<&'static str, (Duration, Duration)> {
        let all = |stage: fn(&StageSamples) -> &Vec<Duration>| {
            let mut values: Vec<Duration> =
                sets.iter().flat_map(|set| stage(set).clone()).collect();
            percentiles(&mut values)
        };
        BTreeMap::from([
            ("1 encode one frame", all(|set| &set.encode)),
            ("2 denoise (all steps)", all(|set| &set.denoise)),
            ("3 end to end, all frames", all(|set| &set.total)),
            ("4 end to end, newest frame only", all(|set| &set.streaming)),
        ])
    }

    /// Medians over every run of `sets`, in ms, of the calling thread's time between the
    /// pool's calls, publishing them, running pieces and waiting, and the calls' count:
    /// end to end, then for the newest frame and the loop. `None` on one thread.
    #[cfg(feature = "pool-timing")]
    pub fn call_table(sets: &[StageSamples]) -> Option<[[f64; 5]; 2]> {
        use scdp_threads::Timing;
        let runs: Vec<_> = sets.iter().flat_map(|set| &set.calls).collect();
        if runs.iter().all(|(_, newest)| newest.calls == 0) {
            return None;
        }
        let row = |timings: Vec<Timing>| {
            let median = |part: fn(&Timing) -> Duration| {
                let mut values: Vec<Duration> = timings.iter().map(part).collect();
                percentiles(&mut values).0.as_secs_f64() * 1e3
            };
            let mut calls: Vec<usize> = timings.iter().map(|timing| timing.calls).collect();
            calls.sort_unstable();
            [
                median(|timing| timing.between),
                median(|timing| timing.publishing),
                median(|timing| timing.pieces),
                median(|timing| timing.waiting),
                calls[calls.len() / 2] as f64,
            ]
        };
        let whole = runs
            .iter()
            .map(|&&(older, newest)| older + newest)
            .collect();
        let newest = runs.iter().map(|&&(_, newest)| newest).collect();
        Some([row(whole), row(newest)])
    }
}

/// Per-stage latency over `iterations` runs after one warm-up run.
pub fn bench(runner: &mut Runner, inputs: &RunInputs, iterations: usize) -> Result<StageSamples> {
    ensure!(iterations > 0, "--bench needs at least one iteration");
    let noise = match &inputs.noise {
        Some(values) => Noise::Given(values),
        None => Noise::Seed(0),
    };
    let mut samples = StageSamples::default();
    // One model and one policy for every run, as a controller keeps them; each run starts
    // from an empty history. The first warms up.
    runner.with_policy(inputs, |policy, pool| {
        #[cfg(not(feature = "pool-timing"))]
        let _ = pool;
        #[cfg(feature = "pool-timing")]
        let take = || pool.map(ThreadPool::take_timing).unwrap_or_default();
        for iteration in 0..=iterations {
            policy.reset();
            let mut times = StageTimes::default();
            #[cfg(feature = "pool-timing")]
            let mut older = {
                take();
                scdp_threads::Timing::default()
            };
            #[cfg(feature = "pool-timing")]
            let mut before_newest = || older = take();
            #[cfg(not(feature = "pool-timing"))]
            let mut before_newest = || ();
            push_frames(policy, inputs, &mut times, &mut before_newest)?;
            let start = Instant::now();
            policy
                .infer_with(noise, inputs.held())
                .map_err(|error| anyhow::anyhow!("inference: {error}"))?;
            times.denoise = start.elapsed();
            #[cfg(feature = "pool-timing")]
            if iteration > 0 {
                samples.calls.push((older, take()));
            }
            if iteration > 0 {
                samples.encode.push(times.encode_newest);
                samples.denoise.push(times.denoise);
                samples.total.push(times.encode_frames + times.denoise);
                samples.streaming.push(times.encode_newest + times.denoise);
            }
        }
        Ok(())
    })?;
    Ok(samples)
}

/// Colour of denoising step `step` of `steps`: blue (noisiest) through green to red (final).
fn step_colour(step: usize, steps: usize) -> [u8; 3] {
    let t = if steps > 1 {
        step as f32 / (steps - 1) as f32
    } else {
        1.0
    };
    let ramp = |x: f32| (x.clamp(0.0, 1.0) * 255.0) as u8;
    [
        ramp(2.0 * t - 1.0),
        ramp(1.0 - (2.0 * t - 1.0).abs()),
        ramp(1.0 - 2.0 * t),
    ]
}

/// The newest frame, enlarged, with each step's anchors drawn as a polyline of dots
/// (colour by step), the SCDP paper's "visualization of spatial conditioning". Returns how
/// many anchors were in front of the camera (and so drawn, when inside the frame).
pub fn draw_anchors(
    config: &ModelConfig,
    inputs: &RunInputs,
    anchors_uv: &[f32],
    path: &Path,
) -> Result<usize> {
    let (height, width) = (config.image_height as usize, config.image_width as usize);
    let scale = (640 / width).max(1) as u32;
    let frames = config.n_obs_steps as usize;
    let newest = &inputs.images[(frames - 1) * height * width * 3..][..height * width * 3];
    let mut picture =
        image::RgbImage::from_fn(width as u32 * scale, height as u32 * scale, |x, y| {
            let at = ((y / scale) as usize * width + (x / scale) as usize) * 3;
            // Dim the frame so the anchors stand out.
            image::Rgb([
                newest[at] / 2 + 32,
                newest[at + 1] / 2 + 32,
                newest[at + 2] / 2 + 32,
            ])
        });
    let steps = config.num_inference_steps as usize;
    let points = config.anchor_count();
    let to_canvas = |u: f32, v: f32| ((u + 0.5) * scale as f32, (v + 0.5) * scale as f32);
    let plot = |picture: &mut image::RgbImage, x: f32, y: f32, colour: [u8; 3], radius: f32| {
        let r = radius.ceil() as i64;
        for dy in -r..=r {
            for dx in -r..=r {
                if (dx * dx + dy * dy) as f32 > radius * radius {
                    continue;
                }
                let (px, py) = (x as i64 + dx, y as i64 + dy);
                if px >= 0
                    && py >= 0
                    && (px as u32) < picture.width()
                    && (py as u32) < picture.height()
                {
                    picture.put_pixel(px as u32, py as u32, image::Rgb(colour));
                }
            }
        }
    };
    for step in 0..steps {
        let colour = step_colour(step, steps);
        let uv = &anchors_uv[step * points * 2..][..points * 2];
        let valid: Vec<(f32, f32)> = uv
            .chunks_exact(2)
            .filter(|p| p[0].is_finite() && p[1].is_finite())
            .map(|p| to_canvas(p[0], p[1]))
            .collect();
        for pair in valid.windows(2) {
            let ((x0, y0), (x1, y1)) = (pair[0], pair[1]);
            let length = ((x1 - x0).hypot(y1 - y0)).min(4.0 * picture.width() as f32);
            let samples = length.ceil().max(1.0) as usize;
            for i in 0..=samples {
                let t = i as f32 / samples as f32;
                plot(
                    &mut picture,
                    x0 + t * (x1 - x0),
                    y0 + t * (y1 - y0),
                    colour,
                    0.8,
                );
            }
        }
        let radius = if step + 1 == steps { 4.0 } else { 2.5 };
        for &(x, y) in &valid {
            plot(&mut picture, x, y, colour, radius);
        }
    }
    // Legend: a strip at the bottom going from the first step's colour to the last's.
    let (canvas_width, canvas_height) = (picture.width(), picture.height());
    for x in 0..canvas_width {
        let step = (x as usize * steps / canvas_width as usize).min(steps - 1);
        for y in canvas_height.saturating_sub(6)..canvas_height {
            picture.put_pixel(x, y, image::Rgb(step_colour(step, steps)));
        }
    }
    picture
        .save(path)
        .with_context(|| format!("{}: cannot write picture", path.display()))?;
    Ok(anchors_uv
        .chunks_exact(2)
        .filter(|p| p[0].is_finite())
        .count())
}
