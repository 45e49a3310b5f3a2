//! The firmware-facing API: load, plan, set the camera, push observations, infer.

use crate::anchors::{self, Camera};
use crate::config::{MAX_OBS_STEPS, ModelConfig, PYRAMID_LEVELS};
use crate::context;
use crate::denoiser::{self, DenoiserScratch, Helpers};
use crate::error::Error;
use crate::format::WeightsFile;
use crate::frame;
use crate::kernels::ops::mish;
use crate::kernels::{self, Backend, Board, Kernels, QuantizeScratch, Sequential, Split, Workers};
use crate::plan::{ArenaPlan, Carver};
use crate::pyramid::{self, FrameStore, TrunkScratch};
use crate::rng::NoiseRng;
use crate::scheduler::{self, PrefixLevel, PrefixMode};
use crate::weights::{FileSource, ModelWeights, SCHEDULE_COLUMNS};

/// A validated weights file bound to the model it describes. Borrows the bytes: nothing is
/// copied, so they may live in flash.
#[derive(Clone, Copy, Debug)]
pub struct Model<'w> {
    file: WeightsFile<'w>,
    weights: ModelWeights<'w>,
}

impl<'w> Model<'w> {
    /// Checks the whole file once (header, checksum, every tensor's name, shape, bounds and
    /// alignment). `bytes` must start on a 64-byte boundary.
    pub fn from_bytes(bytes: &'w [u8]) -> Result<Self, Error> {
        let file = WeightsFile::parse(bytes)?;
        let mut source = FileSource::new(file);
        let weights = ModelWeights::bind(file.config(), &mut source)?;
        source.finish()?;
        Ok(Model { file, weights })
    }

    pub fn config(&self) -> &ModelConfig {
        self.file.config()
    }

    /// Fails unless these weights are for `config` (the one the arena was planned for).
    pub fn expect_config(&self, config: &ModelConfig) -> Result<(), Error> {
        if self.config() == config {
            Ok(())
        } else {
            Err(Error::ConfigMismatch)
        }
    }

    pub fn weights(&self) -> &ModelWeights<'w> {
        &self.weights
    }

    pub fn file(&self) -> &WeightsFile<'w> {
        &self.file
    }
}

/// Where the initial sample `A_K` comes from.
#[derive(Clone, Copy, Debug)]
pub enum Noise<'n> {
    /// The engine's portable Gaussian generator ([`NoiseRng`]) with this seed.
    Seed(u64),
    /// Given values, `[horizon, action_dim]` row-major (tests, replays).
    Given(&'n [f32]),
}

/// Actions the robot will execute before the new chunk takes over, which the chunk must
/// continue: `[k, action_dim]` row-major in action units, for horizon rows `To - 1 ..
/// To - 1 + k` (the rows [`Actions::action`] starts at). The denoising loop holds those
/// rows as [`PrefixMode`] says, so the rest of the chunk, and the anchors it is conditioned
/// on, are planned from them; `action_pred` returns them (round-tripped through the action
/// normalization). Optionally the previous chunk's plan for the rows after them
/// ([`with_planned`](Self::with_planned)), which the new chunk is pulled towards with
/// weights falling to zero, so it leaves the old plan smoothly (docs/SPEC.md section 5.1).
#[derive(Clone, Copy, Debug)]
pub struct Prefix<'p> {
    actions: &'p [f32],
    planned: &'p [f32],
    mode: PrefixMode,
}

impl<'p> Prefix<'p> {
    /// No committed actions: the plain inference, bit for bit.
    pub const NONE: Prefix<'static> = Prefix {
        actions: &[],
        planned: &[],
        mode: PrefixMode::Replace,
    };

    #[must_use]
    pub const fn new(actions: &'p [f32], mode: PrefixMode) -> Self {
        Prefix {
            actions,
            planned: &[],
            mode,
        }
    }

    /// The previous plan's actions for the rows after the committed ones, `[m, action_dim]`
    /// in action units: row `j` pulls the sample towards it with weight `(m - j) / (m + 1)`
    /// at each step's noise level.
    #[must_use]
    pub const fn with_planned(self, planned: &'p [f32]) -> Self {
        Prefix { planned, ..self }
    }

    #[must_use]
    pub const fn actions(&self) -> &'p [f32] {
        self.actions
    }

    #[must_use]
    pub const fn planned(&self) -> &'p [f32] {
        self.planned
    }

    #[must_use]
    pub const fn mode(&self) -> PrefixMode {
        self.mode
    }

    /// The most rows a prefix can have for `config`: the horizon from row `To - 1` on.
    #[must_use]
    pub const fn max_rows(config: &ModelConfig) -> usize {
        (config.horizon - config.n_obs_steps + 1) as usize
    }

    fn check(&self, config: &ModelConfig) -> Result<(), Error> {
        let action_dim = config.action_dim as usize;
        let max_rows = Self::max_rows(config);
        let found = self.actions.len() + self.planned.len();
        if !self.actions.len().is_multiple_of(action_dim)
            || !self.planned.len().is_multiple_of(action_dim)
            || found > max_rows * action_dim
        {
            return Err(Error::PrefixSize {
                max_rows,
                action_dim,
                found,
            });
        }
        if self
            .actions
            .iter()
            .chain(self.planned)
            .any(|value| !value.is_finite())
        {
            return Err(Error::NonFinitePrefix);
        }
        Ok(())
    }
}

/// Sees the intermediate values of an inference; for golden tests and debugging. Every
/// method has an empty default, so an observer implements only what it needs.
pub trait Observer {
    /// After step `step`: the anchors `[s + 1, 2]`, the global condition `g`, the noise
    /// prediction and the updated sample (both `[horizon, action_dim]`, normalized).
    fn step(
        &mut self,
        _step: usize,
        _anchors_uv: &[f32],
        _global_cond: &[f32],
        _eps: &[f32],
        _sample: &[f32],
    ) {
    }
}

/// Observes nothing.
pub struct NoObserver;
impl Observer for NoObserver {}

/// The arena's buffers for one call.
struct Buffers<'a> {
    features: &'a mut [f32],
    states: &'a mut [f32],
    anchors: &'a mut [f32],
    sample: &'a mut [f32],
    eps: &'a mut [f32],
    initial: &'a mut [f32],
    global_cond: &'a mut [f32],
    activated_cond: &'a mut [f32],
    film: &'a mut [f32],
    quantized: QuantizeScratch<'a>,
    cond_codes: QuantizeScratch<'a>,
    scratch: &'a mut [f32],
}

/// One policy instance: a model, a camera and an observation history in a borrowed arena.
pub struct Policy<'w, 'a> {
    model: &'w Model<'w>,
    plan: ArenaPlan,
    arena: &'a mut [f32],
    kernels: &'static dyn Kernels,
    /// Who runs the pieces of a kernel call ([`Split`]); one worker runs them whole.
    workers: &'w dyn Workers,
    camera: Option<Camera>,
    /// Ring slot of the newest frame; frames are pushed into `(newest + 1) % To`.
    newest: usize,
    /// Frames pushed since creation or [`reset`](Self::reset), at most `To`. Until there
    /// are `To`, the history frames older than the first are that first frame (Diffusion
    /// Policy pads by repeating it), read from its slot rather than copied into the others.
    observed: usize,
}

impl<'w, 'a> Policy<'w, 'a> {
    /// Checks `arena` (64-byte aligned, at least [`ArenaPlan::arena_bytes`]) for the model;
    /// runs the fastest kernels this CPU supports.
    pub fn new(model: &'w Model<'w>, arena: &'a mut [u8]) -> Result<Self, Error> {
        Self::with_backend(model, arena, Backend::Auto)
    }

    /// [`new`](Self::new) with a chosen kernel implementation (tests force each one);
    /// [`Error::BackendUnavailable`] if this CPU cannot run it.
    pub fn with_backend(
        model: &'w Model<'w>,
        arena: &'a mut [u8],
        backend: Backend,
    ) -> Result<Self, Error> {
        let kernels = kernels::select(backend).ok_or(Error::BackendUnavailable)?;
        Self::with_kernels(model, arena, kernels)
    }

    /// [`new`](Self::new) running `kernels`, an implementation of the kernel contract the
    /// caller supplies: the tool's calibration wraps a backend to see every layer's input.
    pub fn with_kernels(
        model: &'w Model<'w>,
        arena: &'a mut [u8],
        kernels: &'static dyn Kernels,
    ) -> Result<Self, Error> {
        let plan = ArenaPlan::new(model.config());
        if arena.len() < plan.arena_bytes {
            return Err(Error::ArenaTooSmall {
                needed: plan.arena_bytes,
                found: arena.len(),
            });
        }
        let arena = &mut arena[..plan.arena_bytes];
        let arena: &mut [f32] =
            bytemuck::try_cast_slice_mut(arena).map_err(|_| Error::MisalignedArena)?;
        if !(arena.as_ptr() as usize).is_multiple_of(crate::format::ALIGN) {
            return Err(Error::MisalignedArena);
        }
        Ok(Policy {
            model,
            plan,
            arena,
            kernels,
            workers: &Sequential,
            camera: None,
            newest: 0,
            observed: 0,
        })
    }

    /// Runs each inference on `workers` (cores given by the caller): the trunk's and the
    /// projections' convolutions cut into bands of output rows, the U-Net's int8
    /// convolutions into blocks of output channels and the FiLM products into runs of rows,
    /// one piece a worker ([`Split`]). The results are the same bits for any number of
    /// workers; one worker (the default) runs everything on the calling core.
    #[must_use]
    pub fn with_workers(mut self, workers: &'w dyn Workers) -> Self {
        self.workers = workers;
        self
    }

    /// How many workers run an inference.
    pub fn workers(&self) -> usize {
        self.workers.count()
    }

    pub fn config(&self) -> &ModelConfig {
        self.model.config()
    }

    /// The kernel implementation in use.
    pub fn kernels_name(&self) -> &'static str {
        self.kernels.name()
    }

    /// Sets or replaces the calibration; takes effect at the next inference.
    pub fn set_camera(&mut self, camera: Camera) {
        self.camera = Some(camera);
    }

    /// Forgets the observation history.
    pub fn reset(&mut self) {
        self.observed = 0;
    }

    /// The ring slot holding history frame `frame` (0 = oldest) of `frames`; there is at
    /// least one observation.
    fn history_slot(&self, frames: usize, frame: usize) -> usize {
        let age = (frames - 1 - frame).min(self.observed - 1);
        (self.newest + frames - age) % frames
    }

    fn buffers(&mut self) -> Buffers<'_> {
        let plan = &self.plan;
        let mut carver = Carver::new(self.arena);
        Buffers {
            features: carver.take(plan.features),
            states: carver.take(plan.states),
            anchors: carver.take(plan.anchors),
            sample: carver.take(plan.sample),
            eps: carver.take(plan.eps),
            initial: carver.take(plan.initial),
            global_cond: carver.take(plan.global_cond),
            activated_cond: carver.take(plan.activated_cond),
            film: carver.take(plan.film),
            quantized: QuantizeScratch {
                values: bytemuck::cast_slice_mut(carver.take(plan.quantized)),
            },
            cond_codes: QuantizeScratch {
                values: bytemuck::cast_slice_mut(carver.take(plan.cond_codes)),
            },
            scratch: carver.take(plan.scratch),
        }
    }

    /// Encodes a frame (`[H, W, 3]` RGB bytes) with its robot state and makes it the newest
    /// observation. The first observation after creation or [`reset`](Self::reset) fills the
    /// whole history (Diffusion Policy pads by repeating the first frame).
    pub fn push_observation(&mut self, image: &[u8], state: &[f32]) -> Result<(), Error> {
        let config = *self.config();
        let state_dim = config.state_dim as usize;
        if state.len() != state_dim {
            return Err(Error::StateSize {
                expected: state_dim,
                found: state.len(),
            });
        }
        if state.iter().any(|value| !value.is_finite()) {
            return Err(Error::NonFiniteState);
        }
        let frames = config.n_obs_steps as usize;
        let slot = if self.observed > 0 {
            (self.newest + 1) % frames
        } else {
            0
        };
        let frame_len = self.plan.frame.total;
        let (kernels, workers) = (self.kernels, self.workers);
        let weights = self.model.weights();
        let plan = self.plan;
        let buffers = self.buffers();
        // The trunk's calls are cut by rows; those of its small maps by output channels
        // where a band of rows would hold less than the kernels compute at once, with
        // their outputs at the end of the scratch.
        let (scratch, split_scratch) = buffers
            .scratch
            .split_at_mut(plan.scratch - plan.trunk_split);
        let split = Split::new(kernels, workers, split_scratch);
        let kernels: &dyn Kernels = if workers.count() > 1 { &split } else { kernels };
        let (first, rest) = scratch.split_at_mut(plan.trunk_activation);
        frame::check_size(&config, image)?;
        let mut store = FrameStore::new(
            &mut buffers.features[slot * frame_len..][..frame_len],
            &plan.frame,
        );
        let scratch = TrunkScratch {
            first,
            rest,
            activation_len: plan.trunk_activation,
            quantized: buffers.quantized,
        };
        pyramid::encode(
            kernels,
            &config,
            &weights.pyramid,
            image,
            scratch,
            &mut store,
        );
        buffers.states[slot * state_dim..][..state_dim].copy_from_slice(state);
        self.newest = slot;
        self.observed = (self.observed + 1).min(frames);
        Ok(())
    }

    /// Runs the denoising loop and returns the action chunk.
    pub fn infer(&mut self, noise: Noise<'_>) -> Result<Actions<'_>, Error> {
        self.infer_observed(noise, Prefix::NONE, &mut NoObserver)
    }

    /// [`infer`](Self::infer) for a chunk that continues `prefix`, the actions already
    /// committed to run before it takes over.
    pub fn infer_with(
        &mut self,
        noise: Noise<'_>,
        prefix: Prefix<'_>,
    ) -> Result<Actions<'_>, Error> {
        self.infer_observed(noise, prefix, &mut NoObserver)
    }

    /// [`infer_with`](Self::infer_with), showing each step's intermediates to `observer`.
    pub fn infer_observed(
        &mut self,
        noise: Noise<'_>,
        prefix: Prefix<'_>,
        observer: &mut impl Observer,
    ) -> Result<Actions<'_>, Error> {
        let config = *self.config();
        let camera = self.camera.ok_or(Error::NoCamera)?;
        if self.observed == 0 {
            return Err(Error::NoObservation);
        }
        prefix.check(&config)?;
        let sequence = config.horizon as usize * config.action_dim as usize;
        let frames = config.n_obs_steps as usize;
        let state_dim = config.state_dim as usize;
        let frame_len = self.plan.frame.total;
        let context_dim = config.context_dim();
        let anchor_values = config.anchor_count() * 2;
        let newest = self.newest;
        let slots: [usize; MAX_OBS_STEPS] =
            core::array::from_fn(|frame| self.history_slot(frames, frame.min(frames - 1)));
        let (kernels, workers) = (self.kernels, self.workers);
        let weights = self.model.weights();
        let plan = self.plan;
        let normalizer = weights.normalizer;
        let buffers = self.buffers();
        let (split_scratch, unet_scratch) = buffers.scratch.split_at_mut(plan.unet_split);
        let (films, unet_scratch) = unet_scratch.split_at_mut(plan.unet_films);
        let backend = kernels;
        // The anchors' projection cells cut over the workers; each denoising step runs on a
        // board of its own (below), which cuts the U-Net's calls and computes its FiLM
        // products in the background.
        let split = Split::new(kernels, workers, &mut []);
        let kernels: &dyn Kernels = if workers.count() > 1 { &split } else { kernels };

        let sample = &mut buffers.sample[..sequence];
        match noise {
            Noise::Seed(seed) => NoiseRng::new(seed).fill_normal(sample),
            Noise::Given(values) => {
                if values.len() != sequence {
                    return Err(Error::NoiseSize {
                        expected: sequence,
                        found: values.len(),
                    });
                }
                if values.iter().any(|value| !value.is_finite()) {
                    return Err(Error::NonFiniteNoise);
                }
                sample.copy_from_slice(values);
            }
        }
        // The prefix's rows of the sample, and of the initial sample that noises them.
        let action_dim = config.action_dim as usize;
        let held = prefix.actions.len() + prefix.planned.len();
        let prefix_rows = (frames - 1) * action_dim..(frames - 1) * action_dim + held;
        let initial = &mut buffers.initial[..held];
        initial.copy_from_slice(&sample[prefix_rows.clone()]);
        let normalization = (normalizer.action_scale, normalizer.action_offset);

        // The normalized states do not change during the loop: write them into g once.
        let cond_stride = context_dim + state_dim;
        for (frame_index, &slot) in slots[..frames].iter().enumerate() {
            context::normalize_state(
                &buffers.states[slot * state_dim..][..state_dim],
                normalizer.state_scale,
                normalizer.state_offset,
                &mut buffers.global_cond[frame_index * cond_stride + context_dim..][..state_dim],
            );
        }
        let current_state = &buffers.states[newest * state_dim..][..state_dim];
        let eps = &mut buffers.eps[..sequence];
        for step in 0..config.num_inference_steps as usize {
            let coefficients = &weights.schedule[step * SCHEDULE_COLUMNS..][..SCHEDULE_COLUMNS];
            scheduler::hold_prefix(
                prefix.mode,
                PrefixLevel::Step(coefficients),
                (prefix.actions, prefix.planned),
                normalization,
                initial,
                &mut sample[prefix_rows.clone()],
            );
            let anchors_uv = &mut buffers.anchors[step * anchor_values..][..anchor_values];
            anchors::project_anchors(
                &config,
                &camera,
                sample,
                normalizer.action_scale,
                normalizer.action_offset,
                current_state,
                anchors_uv,
            );
            // Each frame's cells and pooling on a worker of its own, where the frames are
            // distinct (one observation fills every slot of the history until the next).
            let distinct = (1..frames).all(|frame| !slots[..frame].contains(&slots[frame]));
            if workers.count() > 1 && distinct {
                let mut per_slot: heapless::Vec<Option<&mut [f32]>, MAX_OBS_STEPS> = buffers
                    .features
                    .chunks_exact_mut(frame_len.max(1))
                    .map(Some)
                    .collect();
                let contexts = buffers.global_cond.chunks_exact_mut(cond_stride.max(1));
                let mut pooled = heapless::Vec::<_, MAX_OBS_STEPS>::new();
                for (&slot, context) in slots[..frames].iter().zip(contexts) {
                    let store = per_slot.get_mut(slot).and_then(Option::take);
                    let store = store.map(|region| FrameStore::new(region, &plan.frame));
                    let _ = pooled.push((store, &mut context[..context_dim]));
                }
                let projections = &weights.pyramid.projections;
                kernels::run_each(workers, &mut pooled, &|(store, context)| {
                    if let Some(store) = store {
                        context::pool_context(
                            backend,
                            &config,
                            projections,
                            store,
                            anchors_uv,
                            context,
                        );
                    }
                });
            } else {
                for (frame_index, &slot) in slots[..frames].iter().enumerate() {
                    let mut store = FrameStore::new(
                        &mut buffers.features[slot * frame_len..][..frame_len],
                        &plan.frame,
                    );
                    context::pool_context(
                        kernels,
                        &config,
                        &weights.pyramid.projections,
                        &mut store,
                        anchors_uv,
                        &mut buffers.global_cond[frame_index * cond_stride..][..context_dim],
                    );
                }
            }
            let global_cond = &buffers.global_cond[..config.global_cond_dim()];
            let activated = &mut buffers.activated_cond[..global_cond.len()];
            for (out, &value) in activated.iter_mut().zip(global_cond) {
                *out = mish(value);
            }
            let mut carver = Carver::new(&mut *unet_scratch);
            let work = [
                carver.take(plan.unet_work),
                carver.take(plan.unet_work),
                carver.take(plan.unet_work),
                carver.take(plan.unet_work),
            ];
            let skips = [
                carver.take(plan.unet_skips[0]),
                carver.take(plan.unet_skips[1]),
            ];
            let scratch = DenoiserScratch {
                work,
                skips,
                film: &mut *buffers.film,
                quantized: QuantizeScratch {
                    values: &mut *buffers.quantized.values,
                },
                cond_codes: QuantizeScratch {
                    values: &mut *buffers.cond_codes.values,
                },
            };
            let denoiser = &weights.denoiser;
            if workers.count() > 1 {
                let split_scratch = &mut *split_scratch;
                let films = &mut *films;
                let activated = &*activated;
                let sample = &*sample;
                let eps = &mut *eps;
                Board::lead(workers, |board| {
                    let split = Split::new(backend, board, split_scratch);
                    let helpers = Helpers {
                        board,
                        kernels: backend,
                        films,
                    };
                    let helpers = Some(helpers);
                    denoiser::predict_noise(
                        &split, &config, denoiser, step, sample, activated, scratch, helpers, eps,
                    );
                });
            } else {
                denoiser::predict_noise(
                    backend, &config, denoiser, step, sample, activated, scratch, None, eps,
                );
            }
            if eps.iter().any(|value| !value.is_finite()) {
                return Err(Error::NonFiniteResult { step });
            }
            scheduler::ddim_step(coefficients, config.clip_sample, sample, eps);
            if sample.iter().any(|value| !value.is_finite()) {
                return Err(Error::NonFiniteResult { step });
            }
            observer.step(step, anchors_uv, global_cond, eps, sample);
        }

        scheduler::hold_prefix(
            prefix.mode,
            PrefixLevel::Final,
            (prefix.actions, prefix.planned),
            normalization,
            initial,
            &mut sample[prefix_rows],
        );
        for row in sample.chunks_exact_mut(action_dim) {
            for ((value, &scale), &offset) in row
                .iter_mut()
                .zip(normalizer.action_scale)
                .zip(normalizer.action_offset)
            {
                *value = (*value - offset) / scale;
            }
        }
        if sample.iter().any(|value| !value.is_finite()) {
            return Err(Error::NonFiniteResult {
                step: config.num_inference_steps as usize,
            });
        }
        Ok(Actions {
            config,
            action_pred: sample,
            anchors: &buffers.anchors[..config.num_inference_steps as usize * anchor_values],
        })
    }

    /// Projected map F(level + 1) of history frame `frame` (0 = oldest), `[H_n, W_n, d]`.
    /// Cells that inferences have not needed yet are computed first, so this is the whole
    /// dense map.
    pub fn feature_map(&mut self, frame: usize, level: usize) -> Option<&[f32]> {
        let config = *self.config();
        let frames = config.n_obs_steps as usize;
        if self.observed == 0 || frame >= frames || level >= PYRAMID_LEVELS {
            return None;
        }
        let slot = self.history_slot(frames, frame);
        let (kernels, weights, layout) = (self.kernels, self.model.weights(), self.plan.frame);
        let split = Split::new(kernels, self.workers, &mut []);
        let kernels: &dyn Kernels = if self.workers.count() > 1 {
            &split
        } else {
            kernels
        };
        // The frames are the arena's first buffer (see `buffers`).
        let region = &mut self.arena[slot * layout.total..][..layout.total];
        let mut store = FrameStore::new(region, &layout);
        store.complete(kernels, &config, &weights.pyramid.projections[level], level);
        Some(store.into_map(&config, level))
    }
}

/// The result of one inference, borrowed from the arena until the next call.
#[derive(Debug)]
pub struct Actions<'a> {
    config: ModelConfig,
    action_pred: &'a [f32],
    anchors: &'a [f32],
}

impl<'a> Actions<'a> {
    /// The whole denoised chunk, unnormalized: `[horizon, action_dim]`.
    pub fn action_pred(&self) -> &'a [f32] {
        self.action_pred
    }

    /// The part to execute: rows `To - 1 .. To - 1 + n_action_steps`.
    pub fn action(&self) -> &'a [f32] {
        let action_dim = self.config.action_dim as usize;
        let start = (self.config.n_obs_steps as usize - 1) * action_dim;
        &self.action_pred[start..start + self.config.n_action_steps as usize * action_dim]
    }

    /// Anchor pixels of every step, `[steps, s + 1, 2]`, NaN where invalid.
    pub fn anchors_uv(&self) -> &'a [f32] {
        self.anchors
    }
}
