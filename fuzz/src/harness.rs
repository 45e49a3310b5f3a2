//! What the fuzz targets run, shared with `tests/tests/fuzz_corpus.rs` (which includes this
//! file with `#[path]`) so that a plain `cargo test` replays every corpus file through the
//! same code, without a nightly toolchain.
//!
//! Each `fuzz_*` function takes the fuzzer's bytes and panics exactly when the engine breaks
//! its promise (docs/ROBUSTNESS.md): a panic inside the engine, an allocation during an
//! engine call, an error other than the one the inputs call for, a non-finite action, an
//! `Ok` for bad inputs, or two identical calls giving different bits.
//!
//! Everything runs on [`MICRO`], a deliberately tiny model (16x16 frames, two denoising
//! steps) so that millions of executions are cheap; its weights, f32 and int8, are
//! generated once per process by the weights tool from the seeded synthetic state dict.
//! Inputs choose the storage and the kernel backend (the CPU's fastest, or the scalar
//! reference).

use std::cell::RefCell;
use std::sync::OnceLock;

use scdp_engine::format::CHECKSUM_RANGE;
use scdp_engine::{
    ArenaPlan, BackboneNorm, Backend, Camera, Error, Model, ModelConfig, Noise, Policy, Prefix,
    PrefixMode, format,
};
use weights_tool::Quant;
use weights_tool::writer::{AlignedBytes, aligned_copy};

use crate::alloc_guard::no_alloc;

/// The fuzzing model: every feature of a real one (BatchNorm folding, ImageNet
/// normalization, two history frames, three U-Net levels) on 16x16 frames with 2 steps.
pub const MICRO: ModelConfig = ModelConfig {
    image_height: 16,
    image_width: 16,
    imagenet_norm: true,
    backbone_norm: BackboneNorm::Batch,
    backbone_width: 8,
    feature_dim: 8,
    n_obs_steps: 2,
    horizon: 8,
    n_action_steps: 4,
    reconstruction_horizon: 4,
    state_dim: 4,
    action_dim: 3,
    state_pos_index: [0, 1, 2],
    action_pos_index: [0, 1, 2],
    pos_scale: 0.1,
    down_dims: [8, 8, 8],
    diffusion_step_embed_dim: 8,
    kernel_size: 3,
    n_groups: 4,
    num_train_timesteps: 100,
    num_inference_steps: 2,
    clip_sample: true,
};

/// Seed of the synthetic weights (docs/SYNTHETIC.md) of [`MICRO`].
pub const MICRO_SEED: u64 = 8;

/// The weights file of [`MICRO`] stored as `quant`, 64-byte aligned, generated on first use.
pub fn micro_weights(quant: Quant) -> &'static [u8] {
    static FILES: [OnceLock<AlignedBytes>; 2] = [OnceLock::new(), OnceLock::new()];
    FILES[quant as usize]
        .get_or_init(|| {
            MICRO.validate().expect("MICRO is a valid config");
            let state = weights_tool::synth::synth_state_dict(&MICRO, MICRO_SEED);
            let bytes = weights_tool::lowering::lower_to_weights_file(&MICRO, &state, quant)
                .expect("MICRO lowers");
            aligned_copy(&bytes)
        })
        .as_slice()
}

/// [`micro_weights`], loaded.
pub fn micro_model(quant: Quant) -> &'static Model<'static> {
    static MODELS: [OnceLock<Model<'static>>; 2] = [OnceLock::new(), OnceLock::new()];
    MODELS[quant as usize]
        .get_or_init(|| Model::from_bytes(micro_weights(quant)).expect("MICRO loads"))
}

/// Storage and backend from an input's bits: `quant_bit` set is int8, `scalar_bit` set
/// forces the scalar kernels (else the CPU's fastest).
fn choices(flags: u8, quant_bit: u8, scalar_bit: u8) -> (Quant, Backend) {
    let quant = if flags & quant_bit != 0 {
        Quant::Int8
    } else {
        Quant::F32
    };
    let backend = if flags & scalar_bit != 0 {
        Backend::Scalar
    } else {
        Backend::Auto
    };
    (quant, backend)
}

/// Writes the checksum of `file` into its header (docs/FORMAT.md: bytes 24..32), so that
/// a deliberately altered file reaches the checks behind the checksum.
pub fn fix_checksum(file: &mut [u8]) {
    if file.len() >= CHECKSUM_RANGE.end {
        let checksum = format::checksum(file);
        file[CHECKSUM_RANGE].copy_from_slice(&checksum.to_le_bytes());
    }
}

/// The fuzzer's bytes, read front to back; zeros once they run out.
pub struct Input<'a>(&'a [u8]);

impl<'a> Input<'a> {
    pub fn new(data: &'a [u8]) -> Self {
        Input(data)
    }

    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    pub fn byte(&mut self) -> u8 {
        match self.0.split_first() {
            Some((&byte, rest)) => {
                self.0 = rest;
                byte
            }
            None => 0,
        }
    }

    pub fn array<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0; N];
        out.iter_mut().for_each(|byte| *byte = self.byte());
        out
    }

    pub fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.array())
    }

    pub fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.array())
    }

    pub fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.array())
    }

    /// Any f32 bit pattern: NaN, infinities, subnormals, huge values.
    pub fn any_f32(&mut self) -> f32 {
        f32::from_bits(self.u32())
    }

    /// A modest finite value, in [-8, 8) by steps of 1/16.
    pub fn small_f32(&mut self) -> f32 {
        self.byte() as i8 as f32 / 16.0
    }

    /// Up to `len` bytes (fewer when the input runs out).
    pub fn take(&mut self, len: usize) -> &'a [u8] {
        let (head, rest) = self.0.split_at(len.min(self.0.len()));
        self.0 = rest;
        head
    }
}

// ---------------------------------------------------------------------------------------
// Weights loader.

/// Target `load_bytes`: `Model::from_bytes` on arbitrary bytes in a 64-byte aligned buffer.
pub fn fuzz_load_bytes(data: &[u8]) {
    let buffer = aligned_copy(data);
    check_load(buffer.as_slice(), true);
}

/// Target `load_mutated`: a valid [`MICRO`] file with the input's edits applied, its length
/// field and checksum then fixed (unless the input's flags say not to), so that mutations
/// reach the checks behind the checksum.
///
/// Input: a flags byte (bit 0: resize, bit 1: keep the stale length field, bit 2: keep
/// the stale checksum, bit 3: run an inference if the file loads, bit 4: start from the
/// int8 file), with bit 0 a u32 giving the new length modulo `len + 512`, then edits
/// `(u32 offset modulo len, u8 n, the next (n % 8) + 1 bytes)` until the input ends.
pub fn fuzz_load_mutated(data: &[u8]) {
    thread_local! {
        // The file is ~1 MB: a fresh buffer per execution would cost more than the rest.
        static BUFFER: RefCell<Option<AlignedBytes>> = const { RefCell::new(None) };
    }
    let (quant, _) = choices(data.first().copied().unwrap_or(0), 16, 0);
    let base = micro_weights(quant);
    BUFFER.with_borrow_mut(|buffer| {
        let capacity = micro_weights(Quant::F32)
            .len()
            .max(micro_weights(Quant::Int8).len());
        let buffer = buffer.get_or_insert_with(|| AlignedBytes::zeroed(capacity + 512));
        let (len, run) = mutate_file(base, data, buffer.as_mut_slice());
        check_load(&buffer.as_slice()[..len], run);
    });
}

/// Writes `base` with the edits of [`fuzz_load_mutated`] applied to the front of `out`
/// (at least `base.len() + 512` bytes); returns the mutated file's length and whether to
/// run it.
pub fn mutate_file(base: &[u8], data: &[u8], out: &mut [u8]) -> (usize, bool) {
    let mut input = Input::new(data);
    let flags = input.byte();
    let len = if flags & 1 != 0 {
        input.u32() as usize % (base.len() + 512)
    } else {
        base.len()
    };
    let file = &mut out[..len];
    let kept = len.min(base.len());
    file[..kept].copy_from_slice(&base[..kept]);
    file[kept..].fill(0);
    while !input.is_empty() && len > 0 {
        let at = input.u32() as usize % len;
        let count = (input.byte() % 8) as usize + 1;
        let patch = input.take(count);
        let end = (at + patch.len()).min(len);
        file[at..end].copy_from_slice(&patch[..end - at]);
    }
    if flags & 2 == 0 && len >= 24 {
        file[16..24].copy_from_slice(&(len as u64).to_le_bytes());
    }
    if flags & 4 == 0 {
        fix_checksum(file);
    }
    (len, flags & 8 != 0)
}

/// Loads `bytes`; a file that loads must then (if `run`) run: on plain inputs the policy
/// returns finite actions or `NonFiniteResult`, nothing else, on the scalar kernels and on
/// the CPU's fastest, whose feature maps must agree with the scalar ones up to rounding.
fn check_load(bytes: &[u8], run: bool) {
    let loaded = no_alloc(|| Model::from_bytes(bytes));
    let model = match loaded {
        Ok(model) => model,
        Err(error) => {
            // Every error has a message (and formatting it does not panic).
            assert!(!error.to_string().is_empty());
            return;
        }
    };
    let config = *model.config();
    assert_eq!(
        config.validate(),
        Ok(()),
        "a loaded model has a valid config"
    );
    assert_eq!(model.expect_config(&config), Ok(()));
    let plan = ArenaPlan::new(&config);
    // A legal config may need a large arena (e.g. a mutated 4096 x 4096 image size); the
    // loader has done its job, running it would only make the fuzzer slow.
    if !run || plan.arena_bytes > 8 << 20 {
        return;
    }
    let scalar = run_plain(&model, Backend::Scalar);
    let fast = scdp_engine::kernels::select(Backend::Auto).expect("Auto always runs");
    if fast.name()
        != scdp_engine::kernels::select(Backend::Scalar)
            .unwrap()
            .name()
    {
        let fast = run_plain(&model, Backend::Auto);
        for (level, (a, b)) in scalar.iter().zip(&fast).enumerate() {
            assert_close(a, b, level);
        }
    }
}

/// Feature maps of two backends agree up to rounding (compared when finite and moderate:
/// near overflow, a fused multiply-add may overflow where two roundings do not).
fn assert_close(scalar: &[f32], fast: &[f32], level: usize) {
    assert_eq!(scalar.len(), fast.len());
    let finite = |map: &[f32]| map.iter().all(|v| v.is_finite());
    if !finite(scalar) || !finite(fast) {
        return;
    }
    let magnitude = scalar.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    if magnitude > 1e30 {
        return;
    }
    let tolerance = 1e-3 * magnitude;
    for (index, (a, b)) in scalar.iter().zip(fast).enumerate() {
        assert!(
            (a - b).abs() <= tolerance,
            "level {level} value {index}: scalar {a}, fast {b} (largest {magnitude})"
        );
    }
}

/// Plain inputs (a fixed image pattern, small state, a centred camera) through `model` on
/// `backend`: the checks above; returns the oldest frame's five feature maps.
fn run_plain(model: &Model<'_>, backend: Backend) -> Vec<Vec<f32>> {
    let config = *model.config();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
    let (height, width) = (config.image_height as usize, config.image_width as usize);
    let image: Vec<u8> = (0..height * width * 3)
        .map(|i| (i * 7 % 251) as u8)
        .collect();
    let state = vec![0.05f32; config.state_dim as usize];
    let camera = centred_camera(&config);
    let frames = config.n_obs_steps as usize;
    let mut policy = no_alloc(|| Policy::with_backend(model, arena.as_mut_slice(), backend))
        .expect("planned arena, available backend");
    no_alloc(|| {
        policy.set_camera(camera);
        for _ in 0..frames {
            policy
                .push_observation(&image, &state)
                .expect("valid observation");
        }
    });
    let maps = (0..5)
        .map(|level| policy.feature_map(0, level).expect("pushed").to_vec())
        .collect();
    let result = no_alloc(|| {
        policy.infer(Noise::Seed(1)).map(|actions| {
            let finite = actions.action_pred().iter().all(|v| v.is_finite());
            (finite, actions.action_pred().len())
        })
    });
    match result {
        Ok((finite, len)) => {
            assert!(finite, "Ok with non-finite actions");
            assert_eq!(len, (config.horizon * config.action_dim) as usize);
        }
        Err(Error::NonFiniteResult { step }) => {
            assert!(step <= config.num_inference_steps as usize);
        }
        Err(other) => panic!("plain inputs on a loaded model gave {other:?}"),
    }
    maps
}

/// A camera one metre behind the base origin looking along +z, centred on the image.
pub fn centred_camera(config: &ModelConfig) -> Camera {
    let (height, width) = (config.image_height as f32, config.image_width as f32);
    let k = [
        [width, 0.0, (width - 1.0) / 2.0],
        [0.0, width, (height - 1.0) / 2.0],
        [0.0, 0.0, 1.0],
    ];
    let t = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 1.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    Camera::new(&k, &t).expect("a valid camera")
}

// ---------------------------------------------------------------------------------------
// Inference inputs.

/// Whether an independent reading of docs/SPEC.md section 1 accepts `k` as pinhole intrinsics.
fn intrinsics_valid(k: &[[f32; 3]; 3]) -> bool {
    let [[fx, skew, cx], [zero, fy, cy], bottom] = *k;
    [fx, fy, cx, cy].iter().all(|v| v.is_finite())
        && fx > 0.0
        && fy > 0.0
        && skew == 0.0
        && zero == 0.0
        && bottom == [0.0, 0.0, 1.0]
}

/// Rotation matrix of the unit quaternion `(w, x, y, z)`.
fn rotation(q: [f32; 4]) -> [[f32; 3]; 3] {
    let [w, x, y, z] = q;
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// What the camera operation expects of `Camera::new`.
enum CameraOracle {
    /// A valid calibration: must be accepted.
    Accept,
    /// Exactly this error.
    Reject(Error),
    /// A rotation perturbed by an unknown amount: accepted or `BadExtrinsics`.
    Either,
}

/// Decodes a calibration: raw bit patterns (mode 0), a valid one (1), a valid one with one
/// entry replaced (2), or one with a degenerate focal length (3).
fn decode_camera(input: &mut Input<'_>) -> ([[f32; 3]; 3], [[f32; 4]; 4], Option<CameraOracle>) {
    let mode = input.byte() % 4;
    if mode == 0 {
        let mut k = [[0.0; 3]; 3];
        let mut t = [[0.0; 4]; 4];
        k.iter_mut().flatten().for_each(|v| *v = input.any_f32());
        t.iter_mut().flatten().for_each(|v| *v = input.any_f32());
        return (k, t, None);
    }
    let fx = 1.0 + input.byte() as f32;
    let fy = 1.0 + input.byte() as f32;
    let cx = input.small_f32() * 2.0 + 7.5;
    let cy = input.small_f32() * 2.0 + 7.5;
    let mut q = [0.0f32; 4];
    q.iter_mut().for_each(|v| *v = input.small_f32());
    let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    let q = if norm < 0.25 {
        [1.0, 0.0, 0.0, 0.0]
    } else {
        q.map(|v| v / norm)
    };
    let r = rotation(q);
    let translation = [
        input.small_f32() / 8.0,
        input.small_f32() / 8.0,
        input.small_f32() / 4.0 + 1.0,
    ];
    let mut k = [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]];
    let mut t = [[0.0; 4]; 4];
    for row in 0..3 {
        t[row][..3].copy_from_slice(&r[row]);
        t[row][3] = translation[row];
    }
    t[3] = [0.0, 0.0, 0.0, 1.0];
    let oracle = match mode {
        1 => CameraOracle::Accept,
        2 => {
            let index = input.byte() as usize % 25;
            let value = if input.byte() & 1 == 0 {
                input.any_f32()
            } else {
                input.small_f32()
            };
            if index < 9 {
                k[index / 3][index % 3] = value;
            } else {
                let index = index - 9;
                t[index / 4][index % 4] = value;
            }
            if !intrinsics_valid(&k) {
                CameraOracle::Reject(Error::BadIntrinsics)
            } else if !value.is_finite() || t[3] != [0.0, 0.0, 0.0, 1.0] {
                CameraOracle::Reject(Error::BadExtrinsics)
            } else if index >= 9 && (index - 9) % 4 == 3 {
                // A different (finite) translation is still a rigid transform.
                CameraOracle::Accept
            } else if index >= 9 {
                CameraOracle::Either
            } else {
                CameraOracle::Accept
            }
        }
        _ => {
            k[0][0] = -(input.byte() as f32);
            CameraOracle::Reject(Error::BadIntrinsics)
        }
    };
    (k, t, Some(oracle))
}

/// One engine call and the errors the inputs call for (empty: it must succeed).
fn expect_one_of(result: Result<(), Error>, allowed: &[Error], what: &str) {
    match result {
        Ok(()) => assert!(
            allowed.is_empty(),
            "{what}: Ok, expected one of {allowed:?}"
        ),
        Err(error) => assert!(
            allowed.contains(&error),
            "{what}: {error:?}, expected one of {allowed:?}"
        ),
    }
}

/// An inference's committed prefix and planned rows as the input gives them, and the
/// errors they call for.
struct DecodedPrefix {
    committed: Vec<f32>,
    planned: Vec<f32>,
    mode: PrefixMode,
    /// Modest values in whole rows that fit: an inference that succeeds returns them.
    returned: bool,
    errors: Vec<Error>,
}

/// The prefix byte: bits 0-1 none (the plain `infer`), whole rows of modest values, whole
/// rows of any bit patterns, or any lengths; bit 2 the `Noised` mode. Row counts may add
/// up to one more than the horizon holds.
fn decode_prefix(input: &mut Input<'_>, config: &ModelConfig) -> Option<DecodedPrefix> {
    let flags = input.byte();
    let action_dim = config.action_dim as usize;
    let max_rows = Prefix::max_rows(config);
    let (committed_len, planned_len) = match flags % 4 {
        0 => return None,
        1 | 2 => {
            let rows = input.byte() as usize % (max_rows + 1);
            let planned = input.byte() as usize % (max_rows + 2 - rows);
            (rows * action_dim, planned * action_dim)
        }
        _ => (
            input.byte() as usize % (2 * max_rows * action_dim + 1),
            input.byte() as usize % (max_rows * action_dim + 1),
        ),
    };
    let raw = flags % 4 == 2;
    let mut values = |len: usize| -> Vec<f32> {
        (0..len)
            .map(|_| {
                if raw {
                    input.any_f32()
                } else {
                    input.small_f32() / 2.0
                }
            })
            .collect()
    };
    let committed = values(committed_len);
    let planned = values(planned_len);
    let found = committed.len() + planned.len();
    let whole_rows = committed.len().is_multiple_of(action_dim)
        && planned.len().is_multiple_of(action_dim)
        && found <= max_rows * action_dim;
    let mut errors = Vec::new();
    if !whole_rows {
        errors.push(Error::PrefixSize {
            max_rows,
            action_dim,
            found,
        });
    } else if committed.iter().chain(&planned).any(|v| !v.is_finite()) {
        errors.push(Error::NonFinitePrefix);
    }
    let mode = if flags & 4 != 0 {
        PrefixMode::Noised
    } else {
        PrefixMode::Replace
    };
    Some(DecodedPrefix {
        returned: !raw && errors.is_empty(),
        committed,
        planned,
        mode,
        errors,
    })
}

/// Target `inference`: a setup byte (bit 0: the int8 file, bit 1: scalar kernels), then up
/// to 12 operations on a fresh [`MICRO`] policy: set a camera (any of the four calibration
/// modes), push an observation (image of any length and bytes, state of any length and
/// values), infer (seeded, given noise of any values or length; then a committed prefix
/// and planned rows of any values or lengths, or none), reset. Every result is checked
/// against what the inputs call for; every successful inference is repeated and must give
/// the same bits.
pub fn fuzz_inference(data: &[u8]) {
    let mut input = Input::new(data);
    let (quant, backend) = choices(input.byte(), 1, 2);
    let model = micro_model(quant);
    let config = *model.config();
    let frame_bytes = (config.image_height * config.image_width * 3) as usize;
    let state_dim = config.state_dim as usize;
    let sequence = (config.horizon * config.action_dim) as usize;
    let anchors_len = config.num_inference_steps as usize * config.anchor_count() * 2;
    let action_start = (config.n_obs_steps as usize - 1) * config.action_dim as usize;
    let action_len = (config.n_action_steps * config.action_dim) as usize;

    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
    let mut policy = no_alloc(|| Policy::with_backend(model, arena.as_mut_slice(), backend))
        .expect("planned arena, available backend");
    let mut has_camera = false;
    let mut has_observation = false;
    let mut inferences = 0;
    for _ in 0..12 {
        if input.is_empty() {
            break;
        }
        match input.byte() % 4 {
            0 => {
                let (k, t, oracle) = decode_camera(&mut input);
                let result = no_alloc(|| Camera::new(&k, &t));
                let expected_k = intrinsics_valid(&k);
                match (&result, oracle) {
                    (Ok(_), Some(CameraOracle::Accept | CameraOracle::Either)) => {}
                    (Err(Error::BadExtrinsics), Some(CameraOracle::Either)) => {}
                    (Err(error), Some(CameraOracle::Reject(expected))) => {
                        assert_eq!(*error, expected, "camera {k:?} {t:?}")
                    }
                    (_, None) => {
                        // Raw bit patterns: at least the intrinsics verdict is exact.
                        if !expected_k {
                            assert_eq!(result, Err(Error::BadIntrinsics), "camera {k:?}");
                        } else if t.iter().flatten().any(|v| !v.is_finite()) {
                            assert_eq!(result, Err(Error::BadExtrinsics), "camera {t:?}");
                        }
                    }
                    (result, _) => panic!("camera {k:?} {t:?}: unexpected {result:?}"),
                }
                if let Ok(camera) = result {
                    no_alloc(|| policy.set_camera(camera));
                    has_camera = true;
                }
            }
            1 => {
                let image_mode = input.byte();
                let image_len = if image_mode == 0xff {
                    input.u16() as usize % (2 * frame_bytes + 1)
                } else {
                    frame_bytes
                };
                let mut image = vec![image_mode; image_len];
                let given = input.take(image_len);
                image[..given.len()].copy_from_slice(given);
                let state_mode = input.byte();
                let state_len = if state_mode == 0xfe {
                    input.byte() as usize % (2 * state_dim + 1)
                } else {
                    state_dim
                };
                let state: Vec<f32> = (0..state_len)
                    .map(|_| {
                        if state_mode & 1 == 0 {
                            input.small_f32() / 4.0
                        } else {
                            input.any_f32()
                        }
                    })
                    .collect();
                let mut allowed = Vec::new();
                if state_len != state_dim {
                    allowed.push(Error::StateSize {
                        expected: state_dim,
                        found: state_len,
                    });
                }
                if state.iter().any(|v| !v.is_finite()) {
                    allowed.push(Error::NonFiniteState);
                }
                if image_len != frame_bytes {
                    allowed.push(Error::ImageSize {
                        expected: frame_bytes,
                        found: image_len,
                    });
                }
                let result = no_alloc(|| policy.push_observation(&image, &state));
                expect_one_of(result, &allowed, "push_observation");
                has_observation |= result.is_ok();
            }
            2 if inferences < 3 => {
                inferences += 1;
                let noise_mode = input.byte() % 4;
                let seed = if noise_mode == 0 { input.u64() } else { 0 };
                let noise_len = match noise_mode {
                    0 => 0,
                    3 => input.u16() as usize % (2 * sequence + 1),
                    _ => sequence,
                };
                let values: Vec<f32> = (0..noise_len)
                    .map(|_| {
                        if noise_mode == 2 {
                            input.any_f32()
                        } else {
                            input.small_f32() / 2.0
                        }
                    })
                    .collect();
                let noise = if noise_mode == 0 {
                    Noise::Seed(seed)
                } else {
                    Noise::Given(&values)
                };
                let decoded = decode_prefix(&mut input, &config);
                let prefix = decoded.as_ref().map(|decoded| {
                    Prefix::new(&decoded.committed, decoded.mode).with_planned(&decoded.planned)
                });
                let mut allowed = Vec::new();
                if let Some(decoded) = &decoded {
                    allowed.extend_from_slice(&decoded.errors);
                }
                if !has_camera {
                    allowed.push(Error::NoCamera);
                }
                if !has_observation {
                    allowed.push(Error::NoObservation);
                }
                if noise_mode != 0 && noise_len != sequence {
                    allowed.push(Error::NoiseSize {
                        expected: sequence,
                        found: noise_len,
                    });
                }
                if noise_mode != 0 && values.iter().any(|v| !v.is_finite()) {
                    allowed.push(Error::NonFiniteNoise);
                }
                let first = run_inference(&mut policy, noise, prefix);
                match &first {
                    Ok((action_pred, action, anchors)) => {
                        assert!(allowed.is_empty(), "Ok, expected one of {allowed:?}");
                        assert_eq!(action_pred.len(), sequence);
                        assert!(action_pred.iter().all(|v| v.is_finite()), "{action_pred:?}");
                        assert_eq!(action, &action_pred[action_start..][..action_len]);
                        assert_eq!(anchors.len(), anchors_len);
                        for uv in anchors.chunks_exact(2) {
                            assert_eq!(uv[0].is_nan(), uv[1].is_nan(), "anchor {uv:?}");
                        }
                        // The committed rows come back, normalized and back: a few ulps
                        // (tests/tests/prefix.rs holds real actions to 1e-6; MICRO's
                        // synthetic normalization and values up to 4 get 1e-5).
                        let returned = decoded.as_ref().filter(|decoded| decoded.returned);
                        if let Some(decoded) = returned {
                            let rows = &action_pred[action_start..][..decoded.committed.len()];
                            for (got, want) in rows.iter().zip(&decoded.committed) {
                                assert!(
                                    (got - want).abs() <= 1e-5 * want.abs().max(1.0),
                                    "prefix row value {got} for {want}"
                                );
                            }
                        }
                    }
                    Err(Error::NonFiniteResult { step }) if allowed.is_empty() => {
                        assert!(*step <= config.num_inference_steps as usize);
                    }
                    Err(error) => assert!(
                        allowed.contains(error),
                        "infer: {error:?}, expected one of {allowed:?}"
                    ),
                }
                // Same state, same noise: same bits.
                let second = run_inference(&mut policy, noise, prefix);
                assert_eq!(
                    bits(&first),
                    bits(&second),
                    "inference is not deterministic"
                );
            }
            2 => {}
            _ => {
                no_alloc(|| policy.reset());
                has_observation = false;
            }
        }
    }
}

type Inference = Result<(Vec<f32>, Vec<f32>, Vec<f32>), Error>;

/// One inference (the plain `infer` without a prefix), checked to allocate nothing; the
/// results are copied out afterwards.
fn run_inference(
    policy: &mut Policy<'_, '_>,
    noise: Noise<'_>,
    prefix: Option<Prefix<'_>>,
) -> Inference {
    let actions = match prefix {
        Some(prefix) => no_alloc(|| policy.infer_with(noise, prefix))?,
        None => no_alloc(|| policy.infer(noise))?,
    };
    Ok((
        actions.action_pred().to_vec(),
        actions.action().to_vec(),
        actions.anchors_uv().to_vec(),
    ))
}

fn bits(result: &Inference) -> Result<Vec<u32>, Error> {
    result
        .as_ref()
        .map_err(|error| *error)
        .map(|(pred, _, anchors)| {
            pred.iter()
                .chain(anchors)
                .map(|value| value.to_bits())
                .collect()
        })
}
