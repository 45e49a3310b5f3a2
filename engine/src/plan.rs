//! The memory plan: every buffer of one inference as a slice of a single arena, computed
//! by `const fn` so firmware can size a `static` at compile time:
//!
//! ```
//! use scdp_engine::{Arena, ArenaPlan, ModelConfig};
//! const CONFIG: ModelConfig = ModelConfig::TINY;
//! const PLAN: ArenaPlan = ArenaPlan::new(&CONFIG);
//! // In firmware: `static mut ARENA: Arena<{ PLAN.arena_bytes }> = Arena::new();`
//! let arena = Arena::<{ PLAN.arena_bytes }>::new();
//! assert_eq!(arena.0.len(), PLAN.arena_bytes);
//! ```
//!
//! Buffers whose lifetimes do not overlap share memory: the feature maps and the small
//! per-inference state persist; the ResNet trunk's scratch (used while a frame is encoded)
//! and the U-Net's scratch (used while denoising) are the same bytes, and inside the trunk
//! four rotating activation buffers serve every residual block. Every buffer starts on a
//! 64-byte boundary.

use crate::config::{ModelConfig, PYRAMID_LEVELS, UNET_LEVELS};
use crate::error::ConfigError;
use crate::format::ALIGN;
use crate::frame;
use crate::kernels::{CodeRows, ops};

const FLOATS_PER_LINE: usize = ALIGN / 4;

/// The trunk maps whose convolutions may be cut by output channels ([`ArenaPlan::trunk_split`]):
/// at most four of AMX's 16-pixel tiles, so two workers' bands of rows would hold two tiles
/// or fewer, and five workers' less than one.
pub const SMALL_MAP_PIXELS: usize = 64;

/// Lengths, in f32 values, of every buffer. The arena is carved in the order of the fields.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ArenaPlan {
    /// Bytes the arena must have.
    pub arena_bytes: usize,
    /// Bytes the same buffers would take with no reuse at all (every activation its own).
    pub without_reuse_bytes: usize,

    // Persistent between calls.
    /// `To` frames, each laid out as [`FrameLayout`] says.
    pub features: usize,
    /// One frame's part of `features`.
    pub frame: FrameLayout,
    /// `To` raw state vectors.
    pub states: usize,
    /// `[steps, s + 1, 2]` anchor pixels of the last inference (NaN where invalid).
    pub anchors: usize,
    /// `[horizon, action_dim]`: the sample being denoised, then the unnormalized result.
    pub sample: usize,
    /// `[horizon, action_dim]`: the U-Net's noise prediction.
    pub eps: usize,
    /// `[horizon, action_dim]`: the initial sample, which a prefix held at each step's noise
    /// level is noised with.
    pub initial: usize,
    /// The global condition `g`, and `Mish(g)` which the FiLM layers read.
    pub global_cond: usize,
    pub activated_cond: usize,
    /// FiLM scale and bias of the residual block being run.
    pub film: usize,
    /// Int8 weights only: a layer's input quantized, a trunk layer's to two digit planes
    /// (twice the bytes of the largest trunk activation, in f32 units), a U-Net layer's to
    /// i16 codes (`kernels::QuantizeScratch`).
    pub quantized: usize,
    /// Int8 weights only: `Mish(g)` as one row of i16 codes, which every FiLM layer of a
    /// denoising step reads.
    pub cond_codes: usize,

    /// Shared scratch: the larger of the two phases below.
    pub scratch: usize,
    /// Trunk phase: four activation buffers, the first of which also holds the input image;
    /// the stem's output overlaps the other three (they are not live yet).
    pub trunk_activation: usize,
    pub trunk_stem: usize,
    /// Trunk phase too, for a call cut over several workers: the outputs of a convolution
    /// of a small map (at most [`SMALL_MAP_PIXELS`]) cut by output channels, where bands
    /// of its rows would hold fewer pixels than the kernels compute at once
    /// ([`crate::kernels::Kernels::int8_pixel_block`]); or a GroupNorm's moments (the stem's too), each
    /// block of [`crate::kernels::ops::MOMENT_BLOCK`] pixels' apart, and its scales and
    /// shifts.
    pub trunk_split: usize,
    /// Denoising phase: four work buffers and the two skips the up path reads.
    pub unet_work: usize,
    pub unet_skips: [usize; UNET_LEVELS - 1],
    /// Denoising phase too: the outputs of a U-Net convolution cut by output channels over
    /// several workers ([`crate::kernels::Split`]), one work buffer's length.
    pub unet_split: usize,
    /// Denoising phase too, with several workers: every residual block's FiLM values of a
    /// step (`2 out` each), which the workers compute in the background
    /// ([`crate::kernels::Board`]).
    pub unet_films: usize,
}

impl ArenaPlan {
    /// The plan of `config`. Every length is computed in `u64`, so a legal config whose
    /// buffers exceed a 32-bit address space cannot wrap around: its `arena_bytes` saturates
    /// at `usize::MAX`, which no arena can satisfy (`Policy::new` returns `ArenaTooSmall`),
    /// and [`ModelConfig::validate`] refuses it in the first place.
    pub const fn new(config: &ModelConfig) -> ArenaPlan {
        let plan = Lengths::new(config);
        ArenaPlan {
            arena_bytes: saturate(plan.arena_bytes),
            without_reuse_bytes: saturate(plan.without_reuse_bytes),
            features: saturate(plan.features),
            frame: FrameLayout {
                maps: saturate(plan.frame.maps),
                taps: saturate(plan.frame.taps),
                tap_scales: saturate(plan.frame.tap_scales),
                computed: saturate(plan.frame.computed),
                total: saturate(plan.frame.total),
            },
            states: saturate(plan.states),
            anchors: saturate(plan.anchors),
            sample: saturate(plan.sample),
            eps: saturate(plan.eps),
            initial: saturate(plan.initial),
            global_cond: saturate(plan.global_cond),
            activated_cond: saturate(plan.activated_cond),
            film: saturate(plan.film),
            quantized: saturate(plan.quantized),
            cond_codes: saturate(plan.cond_codes),
            scratch: saturate(plan.scratch),
            trunk_activation: saturate(plan.trunk_activation),
            trunk_stem: saturate(plan.trunk_stem),
            trunk_split: saturate(plan.trunk_split),
            unet_work: saturate(plan.unet_work),
            unet_skips: [saturate(plan.unet_skips[0]), saturate(plan.unet_skips[1])],
            unet_split: saturate(plan.unet_split),
            unet_films: saturate(plan.unet_films),
        }
    }

    /// Bytes of the arena `config` needs, exactly, whatever the width of `usize`.
    const fn arena_bytes_u64(config: &ModelConfig) -> u64 {
        Lengths::new(config).arena_bytes
    }
}

impl ModelConfig {
    /// Checks every rule the engine and the weights tool rely on: the fields'
    /// ([`ModelConfig::validate_fields`]) and that one inference's buffers fit the address
    /// space. `const` so a firmware build can reject a bad configuration at compile time.
    pub const fn validate(&self) -> Result<(), ConfigError> {
        if let Err(error) = self.validate_fields() {
            return Err(error);
        }
        // Legal sizes can still ask for more memory than a 32-bit target can address (8
        // frames of 4096x4096 pyramids); refused here so no length ever wraps around.
        if ArenaPlan::arena_bytes_u64(self) > isize::MAX as u64 {
            return Err(ConfigError::ArenaTooLarge);
        }
        Ok(())
    }
}

/// One history frame's persistent buffers, in f32 units, back to back in this order:
/// - `maps`: the five projected maps `[H_n, W_n, d]`, levels back to back. A level whose
///   projection runs on demand ([`ModelConfig::projection_on_demand`]) holds only the cells
///   computed so far;
/// - `taps`: for those levels, the projection's input C(level + 1), `[H_n, W_n, C_n]`, in
///   f32, or in int8 (bytes, same element offsets) for int8 weights;
/// - `tap_scales`: for int8 weights, the scale of each level's quantized tap and whether
///   its digits are all nonnegative (1 or 0; two values per level);
/// - `computed`: one bit per cell of those levels (u32 words), set once the cell is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameLayout {
    pub maps: usize,
    pub taps: usize,
    pub tap_scales: usize,
    pub computed: usize,
    pub total: usize,
}

struct FrameLengths {
    maps: u64,
    taps: u64,
    tap_scales: u64,
    computed: u64,
    total: u64,
}

impl FrameLengths {
    const fn new(config: &ModelConfig) -> FrameLengths {
        let mut cells = 0;
        let mut on_demand_words = 0;
        let mut taps = 0;
        let mut level = 0;
        while level < PYRAMID_LEVELS {
            let (height, width) = config.pyramid_size(level);
            let level_cells = height as u64 * width as u64;
            cells += level_cells;
            if config.projection_on_demand(level) {
                on_demand_words += level_cells.div_ceil(32);
                taps += level_cells * config.pyramid_channels(level) as u64;
            }
            level += 1;
        }
        let maps = aligned(cells * config.feature_dim as u64);
        let taps = aligned(taps);
        let tap_scales = aligned(2 * PYRAMID_LEVELS as u64);
        let computed = aligned(on_demand_words);
        FrameLengths {
            maps,
            taps,
            tap_scales,
            computed,
            total: maps + taps + tap_scales + computed,
        }
    }
}

const fn saturate(value: u64) -> usize {
    if value > usize::MAX as u64 {
        usize::MAX
    } else {
        value as usize
    }
}

/// `len` f32 values rounded up to whole 64-byte lines, in `u64`.
const fn aligned(len: u64) -> u64 {
    len.div_ceil(FLOATS_PER_LINE as u64) * FLOATS_PER_LINE as u64
}

const fn max(a: u64, b: u64) -> u64 {
    if a > b { a } else { b }
}

/// [`ArenaPlan`]'s lengths in `u64`. The config's own size helpers return `usize`; only
/// those bounded far below 2^32 by `validate`'s limits (map sides, channel counts, the
/// condition's length) are used, every product is formed here.
struct Lengths {
    arena_bytes: u64,
    without_reuse_bytes: u64,
    features: u64,
    frame: FrameLengths,
    states: u64,
    anchors: u64,
    sample: u64,
    eps: u64,
    initial: u64,
    global_cond: u64,
    activated_cond: u64,
    film: u64,
    quantized: u64,
    cond_codes: u64,
    scratch: u64,
    trunk_activation: u64,
    trunk_stem: u64,
    trunk_split: u64,
    unet_work: u64,
    unet_skips: [u64; UNET_LEVELS - 1],
    unet_split: u64,
    unet_films: u64,
}

impl Lengths {
    const fn new(config: &ModelConfig) -> Lengths {
        let frames = config.n_obs_steps as u64;
        let steps = config.num_inference_steps as u64;
        let horizon = config.horizon as u64;
        let action_dim = config.action_dim as u64;
        let sequence = horizon * action_dim;

        let frame = FrameLengths::new(config);
        let features = frames * frame.total;
        let states = aligned(frames * config.state_dim as u64);
        let anchors = aligned(steps * config.anchor_count() as u64 * 2);
        let sample = aligned(sequence);
        let eps = aligned(sequence);
        let initial = aligned(sequence);
        let global_cond = aligned(config.global_cond_dim() as u64);
        let activated_cond = global_cond;
        let mut widest = 0;
        let mut level = 0;
        while level < UNET_LEVELS {
            widest = max(widest, config.down_dims[level] as u64);
            level += 1;
        }
        let film = aligned(2 * widest);

        // Trunk: the image and every stage's activation fit in one activation buffer.
        let pixels = config.image_height as u64 * config.image_width as u64;
        let image = pixels * 3;
        let (stem_height, stem_width) = config.stem_size();
        let stem = stem_height as u64 * stem_width as u64 * config.stage_channels(0) as u64;
        let mut largest_activation = image;
        let mut trunk_naive = image + stem;
        let mut small_map = 0;
        let mut stage = 0;
        while stage < 4 {
            let (height, width) = config.pyramid_size(stage + 1);
            let activation = height as u64 * width as u64 * config.stage_channels(stage) as u64;
            largest_activation = max(largest_activation, activation);
            if height as u64 * width as u64 <= SMALL_MAP_PIXELS as u64 {
                small_map = max(small_map, activation);
            }
            // A GroupNorm cut over workers keeps each block of pixels' moments apart (two
            // f64 a channel) and the channels' scales and shifts.
            let channels = config.stage_channels(stage) as u64;
            let blocks = (height as u64 * width as u64).div_ceil(ops::MOMENT_BLOCK as u64);
            small_map = max(small_map, 4 * channels * blocks + 2 * channels);
            // Without reuse: each block's two convolutions (+ shortcut for the first block
            // of stages 2-4) and the max pool output have buffers of their own.
            let per_stage = if stage == 0 { 5 } else { 6 };
            trunk_naive += per_stage * activation;
            stage += 1;
        }
        // The stem's GroupNorm moments, each block's apart, when cut over workers.
        let stem_blocks =
            (stem_height as u64 * stem_width as u64).div_ceil(ops::MOMENT_BLOCK as u64);
        small_map = max(small_map, 4 * config.stage_channels(0) as u64 * stem_blocks);
        let (c1_height, c1_width) = config.pyramid_size(0);
        let maxpool = c1_height as u64 * c1_width as u64 * config.stage_channels(0) as u64;
        largest_activation = max(largest_activation, maxpool);
        // An int8 stem reads the padded image bytes instead.
        let padded_image = (frame::padded_image_bytes(config) as u64).div_ceil(4);
        largest_activation = max(largest_activation, padded_image);
        let trunk_activation = aligned(largest_activation);
        let trunk_stem = aligned(stem);
        let trunk_split = aligned(small_map);
        let trunk = trunk_activation + max(trunk_stem, 3 * trunk_activation) + trunk_split;

        // Denoiser: the widest activation is an up block's concatenated input.
        let unet_work = aligned(horizon * 2 * widest);
        let unet_skips = [
            aligned((horizon / 2) * config.down_dims[1] as u64),
            aligned((horizon / 4) * config.down_dims[2] as u64),
        ];
        let unet_split = unet_work;
        // Two residual blocks a level down, two in the middle (the deepest width), two a
        // level up (the width of the level below), each `2 out` FiLM values.
        let mut block_channels = 2 * config.down_dims[UNET_LEVELS - 1] as u64;
        let mut level = 0;
        while level < UNET_LEVELS {
            block_channels += 2 * config.down_dims[level] as u64;
            if level + 1 < UNET_LEVELS {
                block_channels += 2 * config.down_dims[level] as u64;
            }
            level += 1;
        }
        let unet_films = aligned(2 * block_channels);
        let unet = unet_split + unet_films + 4 * unet_work + unet_skips[0] + unet_skips[1];
        // Without reuse: every block output and intermediate of one U-Net pass (two
        // convolutions per block, 12 blocks, plus the resampling layers and the head).
        let unet_naive = 3 * 12 * horizon * 2 * widest + 6 * horizon * widest + unet_split;

        // Int8 layer inputs, quantized one layer at a time: the trunk's fit one activation
        // buffer as two digit planes; the U-Net's are at most `horizon` rows of an up
        // block's concatenated input (or the sample, the first block's), as i16 codes
        // padded to whole quads; an int8 stem's patches go a band of output rows at a time
        // (at least one row).
        let unet_codes = 2 * horizon * 4 * max(2 * widest, action_dim).div_ceil(4);
        let stem_patch_row = stem_width as u64 * frame::PATCH_CHANNELS as u64;
        let quantized_bytes = max(max(2 * trunk_activation, unet_codes), stem_patch_row);
        let quantized = aligned(quantized_bytes.div_ceil(4));
        // The FiLM layers' input, the activated global condition, as one row of codes.
        let cond_codes =
            aligned((2 * CodeRows::row_stride(config.global_cond_dim()) as u64).div_ceil(4));
        let persistent = features
            + states
            + anchors
            + sample
            + eps
            + initial
            + global_cond
            + activated_cond
            + film
            + quantized
            + cond_codes;
        let scratch = max(trunk, unet);
        Lengths {
            arena_bytes: 4 * (persistent + scratch),
            without_reuse_bytes: 4 * (persistent + trunk_naive + unet_naive),
            features,
            frame,
            states,
            anchors,
            sample,
            eps,
            initial,
            global_cond,
            activated_cond,
            film,
            quantized,
            cond_codes,
            scratch,
            trunk_activation,
            trunk_stem,
            trunk_split,
            unet_work,
            unet_skips,
            unet_split,
            unet_films,
        }
    }
}

/// A 64-byte aligned byte array, for the arena (`static mut ARENA: Arena<N>`) and for
/// embedded weights.
#[repr(C, align(64))]
pub struct Arena<const N: usize>(pub [u8; N]);

impl<const N: usize> Arena<N> {
    pub const fn new() -> Self {
        Arena([0; N])
    }
}

impl<const N: usize> Default for Arena<N> {
    fn default() -> Self {
        Self::new()
    }
}

/// Bytes with 64-byte alignment: `static WEIGHTS: &Aligned<[u8]> = &Aligned(*include_bytes!(..));`
#[repr(C, align(64))]
pub struct Aligned<T: ?Sized>(pub T);

/// Splits successive 64-byte aligned buffers off the front of an arena.
pub(crate) struct Carver<'a> {
    rest: &'a mut [f32],
}

impl<'a> Carver<'a> {
    pub(crate) fn new(rest: &'a mut [f32]) -> Self {
        Carver { rest }
    }

    /// The next buffer of `len` values (`len` is a plan length, already aligned).
    /// The caller has checked the arena against the plan, so this never runs short.
    pub(crate) fn take(&mut self, len: usize) -> &'a mut [f32] {
        let rest = core::mem::take(&mut self.rest);
        let (head, tail) = rest.split_at_mut(len.min(rest.len()));
        self.rest = tail;
        head
    }
}

/// Panics at compile time if a plan for the largest supported shapes overflows.
const _: () = {
    let plan = ArenaPlan::new(&ModelConfig::PANDA);
    assert!(plan.arena_bytes < plan.without_reuse_bytes);
    assert!(PYRAMID_LEVELS == 5);
};
