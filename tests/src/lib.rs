//! Shared helpers for the golden tests: reading the fixtures the PyTorch reference wrote
//! (tests/fixtures, format in docs/FIXTURES.md) and running the engine on them.

use std::alloc::{GlobalAlloc, Layout, System};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use anyhow::{Context, Result, bail};
use safetensors::{Dtype, SafeTensors};
use scdp_engine::{
    Backend, Camera, Model, ModelConfig, Noise, Observer, Policy, Prefix, PrefixMode,
};
use weights_tool::writer::AlignedBytes;

/// The repository's `tests/` folder.
pub fn tests_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).to_path_buf()
}

/// A tensor of a fixture, widened to f64 (u8 images are kept apart).
#[derive(Clone, Debug)]
pub struct Array {
    pub shape: Vec<usize>,
    pub values: Vec<f64>,
}

/// One golden case: metadata, inputs and reference outputs.
pub struct Fixture {
    pub path: PathBuf,
    pub config: ModelConfig,
    pub seed: u64,
    pub weights_sha256: String,
    /// How the fixture's `prefix` (committed actions, if it has one) is held.
    pub prefix_mode: PrefixMode,
    pub images: Vec<u8>,
    pub arrays: HashMap<String, Array>,
}

impl Fixture {
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let (_, metadata) = SafeTensors::read_metadata(&bytes)?;
        let metadata = metadata.metadata().clone().unwrap_or_default();
        let field = |name: &str| {
            metadata
                .get(name)
                .cloned()
                .with_context(|| format!("{}: metadata lacks `{name}`", path.display()))
        };
        let config = weights_tool::config::parse_config(&field("config")?)
            .map_err(|error| anyhow::anyhow!("{}: config: {error}", path.display()))?;
        let seed = field("seed")?.parse()?;
        let weights_sha256 = field("weights_sha256")?;
        let prefix_mode = match metadata.get("prefix_mode").map(String::as_str) {
            None | Some("replace") => PrefixMode::Replace,
            Some("noised") => PrefixMode::Noised,
            Some(other) => bail!("{}: unknown prefix_mode `{other}`", path.display()),
        };
        let tensors = SafeTensors::deserialize(&bytes)?;
        let mut images = Vec::new();
        let mut arrays = HashMap::new();
        for (name, view) in tensors.tensors() {
            let data = view.data();
            let values: Vec<f64> = match view.dtype() {
                Dtype::U8 => {
                    if name == "images" {
                        images = data.to_vec();
                    }
                    data.iter().map(|&b| b as f64).collect()
                }
                Dtype::F32 => data
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes(c.try_into().unwrap()) as f64)
                    .collect(),
                Dtype::F64 => data
                    .chunks_exact(8)
                    .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
                    .collect(),
                other => bail!("{}: `{name}` has dtype {other:?}", path.display()),
            };
            arrays.insert(
                name,
                Array {
                    shape: view.shape().to_vec(),
                    values,
                },
            );
        }
        Ok(Fixture {
            path: path.to_path_buf(),
            config,
            seed,
            weights_sha256,
            prefix_mode,
            images,
            arrays,
        })
    }

    pub fn array(&self, name: &str) -> &Array {
        self.arrays
            .get(name)
            .unwrap_or_else(|| panic!("{}: no tensor `{name}`", self.path.display()))
    }

    pub fn f32s(&self, name: &str) -> Vec<f32> {
        self.array(name).values.iter().map(|&v| v as f32).collect()
    }

    /// The committed actions of a prefix fixture, `[k, action_dim]` (none in the others).
    pub fn prefix_actions(&self) -> Vec<f32> {
        self.optional_f32s("prefix")
    }

    /// The planned actions after the prefix, `[m, action_dim]` (none where not given).
    pub fn planned_actions(&self) -> Vec<f32> {
        self.optional_f32s("planned")
    }

    fn optional_f32s(&self, name: &str) -> Vec<f32> {
        self.arrays
            .get(name)
            .map(|array| array.values.iter().map(|&v| v as f32).collect())
            .unwrap_or_default()
    }

    pub fn camera(&self) -> Result<Camera> {
        let k = self.f32s("camera_k");
        let t = self.f32s("camera_t");
        let intrinsics = [[k[0], k[1], k[2]], [k[3], k[4], k[5]], [k[6], k[7], k[8]]];
        let mut extrinsics = [[0.0; 4]; 4];
        for (row, chunk) in extrinsics.iter_mut().zip(t.chunks_exact(4)) {
            row.copy_from_slice(chunk);
        }
        Ok(Camera::new(&intrinsics, &extrinsics)?)
    }
}

/// A camera 0.8 m in front of the scene, looking along +z, focal length the image width:
/// the synthetic tests' view (anchors near the image centre).
pub fn frontal_camera(config: &ModelConfig) -> Camera {
    let (h, w) = (config.image_height as f32, config.image_width as f32);
    let k = [
        [w, 0.0, (w - 1.0) / 2.0],
        [0.0, w, (h - 1.0) / 2.0],
        [0.0, 0.0, 1.0],
    ];
    let t = [
        [1.0, 0.0, 0.0, 0.02],
        [0.0, 1.0, 0.0, -0.01],
        [0.0, 0.0, 1.0, 0.8],
        [0.0, 0.0, 0.0, 1.0],
    ];
    Camera::new(&k, &t).expect("a valid camera")
}

/// The kernel backends this CPU can run. `SCDP_REQUIRE_BACKENDS=avx2,avx512` (as CI sets it)
/// turns a missing backend into a failure instead of a silent skip. `SCDP_TEST_BACKENDS=dot`
/// keeps only the named ones: under emulation, where one run of the golden cases takes
/// minutes, CI runs the aarch64 f32 kernels (one body for `neon`, `dot` and `i8mm`) once.
pub fn available_backends() -> Vec<Backend> {
    let only = std::env::var("SCDP_TEST_BACKENDS").unwrap_or_default();
    let chosen = |backend: Backend| only.is_empty() || only.split(',').any(|n| n == backend.name());
    let mut found = Vec::new();
    for backend in Backend::ALL.into_iter().filter(|&b| b != Backend::Auto) {
        if scdp_engine::kernels::select(backend).is_some() && chosen(backend) {
            found.push(backend);
        }
    }
    let required = std::env::var("SCDP_REQUIRE_BACKENDS").unwrap_or_default();
    for name in required.split(',').filter(|n| !n.is_empty()) {
        assert!(
            found
                .iter()
                .any(|b| scdp_engine::kernels::select(*b).is_some_and(|k| k.name() == name)),
            "backend {name} is required but this CPU cannot run it"
        );
    }
    found
}

/// Every golden fixture, sorted, optionally only those of one config folder.
pub fn golden_fixtures() -> Vec<PathBuf> {
    let mut paths: Vec<PathBuf> = glob_safetensors(&tests_dir().join("fixtures/golden"));
    paths.sort();
    paths
}

fn glob_safetensors(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    if let Ok(entries) = std::fs::read_dir(dir) {
        for entry in entries.flatten() {
            let path = entry.path();
            if path.is_dir() {
                found.extend(glob_safetensors(&path));
            } else if path.extension().is_some_and(|e| e == "safetensors") {
                found.push(path);
            }
        }
    }
    found
}

/// Seeded synthetic weights, converted by the weights tool exactly as `convert` does.
pub fn synthetic_weights_file(config: &ModelConfig, seed: u64) -> Result<AlignedBytes> {
    synthetic_weights_file_as(config, seed, weights_tool::Quant::F32)
}

/// [`synthetic_weights_file`] at a chosen storage precision.
pub fn synthetic_weights_file_as(
    config: &ModelConfig,
    seed: u64,
    quant: weights_tool::Quant,
) -> Result<AlignedBytes> {
    let state = weights_tool::synth::synth_state_dict(config, seed);
    let bytes = weights_tool::lowering::lower_to_weights_file(config, &state, quant)?;
    Ok(weights_tool::writer::aligned_copy(&bytes))
}

/// [`synthetic_weights_file_as`] int8 (rounded to nearest) with every residual-block layer
/// on narrow (8-bit) activation codes: the fast file's speed, whatever its rounding.
pub fn synthetic_narrow_weights_file(config: &ModelConfig, seed: u64) -> Result<AlignedBytes> {
    use weights_tool::lowering::{self, Rounding};
    let state = weights_tool::synth::synth_state_dict(config, seed);
    let lowered = lowering::lower(config, &state)?;
    let mut stored = lowering::store(
        config,
        lowered,
        weights_tool::Quant::Int8,
        Rounding::Nearest,
    )?;
    weights_tool::activations::set_all_narrow(config, &mut stored)?;
    let bytes = weights_tool::writer::write_weights_file(config, &stored)?;
    Ok(weights_tool::writer::aligned_copy(&bytes))
}

/// Synthetic scenes the int8 fidelity is calibrated on (docs/QUANTIZATION.md: 8 were not
/// enough, 32 met the floor).
pub const CALIBRATION_SCENES: usize = 32;
/// Seed of those scenes: not a golden case's (the cases' inputs never calibrate).
pub const CALIBRATION_SEED: u64 = 7;

/// [`synthetic_weights_file`] as int8 with GPTQ rounding, calibrated on
/// [`CALIBRATION_SCENES`] synthetic scenes seen through `fixture`'s camera (a deployment
/// constant: the camera the policy runs with is the one it is calibrated with); the same
/// rounding written twice, with one weight plane and with the trunk refined.
///
/// With `SCDP_CALIBRATED_FILES` naming a folder, the two files are read from it where an
/// earlier run wrote them (named by the case's weights digest), else converted and written
/// there: under emulation, where GPTQ's calibration runs for hours, the fidelity test then
/// runs the engine on the files a native run converted (docs/ARM.md).
#[cfg(feature = "gptq")]
pub fn calibrated_int8_weights_files(fixture: &Fixture) -> Result<CalibratedFiles> {
    let Some(folder) = std::env::var_os("SCDP_CALIBRATED_FILES") else {
        return convert_calibrated(fixture);
    };
    let folder = PathBuf::from(folder);
    let stem = folder.join(&fixture.weights_sha256[..16]);
    let [plain, refined] =
        ["plain", "refined-trunk"].map(|name| stem.with_extension(format!("{name}.scdp")));
    if plain.exists() && refined.exists() {
        let read = |path: &Path| -> Result<AlignedBytes> {
            let bytes =
                std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
            Ok(weights_tool::writer::aligned_copy(&bytes))
        };
        return Ok(CalibratedFiles {
            plain: read(&plain)?,
            refined_trunk: read(&refined)?,
        });
    }
    let files = convert_calibrated(fixture)?;
    std::fs::create_dir_all(&folder)?;
    std::fs::write(&plain, files.plain.as_slice())?;
    std::fs::write(&refined, files.refined_trunk.as_slice())?;
    Ok(files)
}

#[cfg(feature = "gptq")]
fn convert_calibrated(fixture: &Fixture) -> Result<CalibratedFiles> {
    use weights_tool::lowering::{self, Rounding};
    let config = &fixture.config;
    let state = weights_tool::synth::synth_state_dict(config, fixture.seed);
    let lowered = lowering::lower(config, &state)?;
    let k = fixture.f32s("camera_k");
    let t = fixture.f32s("camera_t");
    let intrinsics = [[k[0], k[1], k[2]], [k[3], k[4], k[5]], [k[6], k[7], k[8]]];
    let mut extrinsics = [[0.0; 4]; 4];
    for (row, chunk) in extrinsics.iter_mut().zip(t.chunks_exact(4)) {
        row.copy_from_slice(chunk);
    }
    let scenes = weights_tool::scenes::synthetic_scenes(
        config,
        intrinsics,
        extrinsics,
        CALIBRATION_SCENES,
        CALIBRATION_SEED,
    );
    let moments = lowering::calibrate(config, &lowered, &scenes, false)?;
    let mut stored = lowering::store(
        config,
        lowered,
        weights_tool::Quant::Int8,
        Rounding::Calibrated(&moments),
    )?;
    let plain = weights_tool::writer::write_weights_file(config, &stored)?;
    let names = weights_tool::refine::candidates(&stored);
    weights_tool::refine::set_refined(&mut stored, &names, true);
    let refined = weights_tool::writer::write_weights_file(config, &stored)?;
    Ok(CalibratedFiles {
        plain: weights_tool::writer::aligned_copy(&plain),
        refined_trunk: weights_tool::writer::aligned_copy(&refined),
    })
}

/// The GPTQ-rounded int8 files of a golden case's weights.
pub struct CalibratedFiles {
    /// One int8 plane a weight, 15-bit activation codes everywhere.
    pub plain: AlignedBytes,
    /// The same, with every residual-block layer of the trunk refined by its second plane.
    pub refined_trunk: AlignedBytes,
}

/// Everything an inference showed its observer, step by step.
#[derive(Default, Debug)]
pub struct Recorded {
    pub anchors_uv: Vec<Vec<f32>>,
    pub global_cond: Vec<Vec<f32>>,
    pub eps: Vec<Vec<f32>>,
    pub sample: Vec<Vec<f32>>,
}

impl Observer for Recorded {
    fn step(
        &mut self,
        _step: usize,
        anchors_uv: &[f32],
        global_cond: &[f32],
        eps: &[f32],
        sample: &[f32],
    ) {
        self.anchors_uv.push(anchors_uv.to_vec());
        self.global_cond.push(global_cond.to_vec());
        self.eps.push(eps.to_vec());
        self.sample.push(sample.to_vec());
    }
}

/// The engine's results on a fixture's inputs.
pub struct EngineRun {
    pub recorded: Recorded,
    pub action_pred: Vec<f32>,
    pub action: Vec<f32>,
    /// `[frame][level]` -> the projected map `[H, W, d]`.
    pub feature_maps: Vec<Vec<Vec<f32>>>,
}

/// Runs a weights file on a fixture's inputs: frames pushed oldest first, the given noise,
/// the fastest kernels of this CPU.
pub fn run_engine(weights: &[u8], fixture: &Fixture) -> Result<EngineRun> {
    run_engine_with(weights, fixture, Backend::Auto)
}

/// [`run_engine`] on a chosen kernel backend; fails if another one ran.
pub fn run_engine_with(weights: &[u8], fixture: &Fixture, backend: Backend) -> Result<EngineRun> {
    run_engine_on(weights, fixture, backend, &scdp_engine::kernels::Sequential)
}

/// [`run_engine_with`], each inference on `workers`.
pub fn run_engine_on(
    weights: &[u8],
    fixture: &Fixture,
    backend: Backend,
    workers: &dyn scdp_engine::kernels::Workers,
) -> Result<EngineRun> {
    let model = Model::from_bytes(weights)?;
    model.expect_config(&fixture.config)?;
    let config = fixture.config;
    let plan = scdp_engine::ArenaPlan::new(&config);
    let mut arena = AlignedBytes::zeroed(plan.arena_bytes);
    let mut policy =
        Policy::with_backend(&model, arena.as_mut_slice(), backend)?.with_workers(workers);
    if let Some(expected) = scdp_engine::kernels::select(backend) {
        anyhow::ensure!(
            policy.kernels_name() == expected.name(),
            "{backend:?} did not run"
        );
    }
    policy.set_camera(fixture.camera()?);
    let frames = config.n_obs_steps as usize;
    let frame_bytes = fixture.images.len() / frames;
    let state = fixture.f32s("state");
    let state_dim = config.state_dim as usize;
    for frame in 0..frames {
        policy.push_observation(
            &fixture.images[frame * frame_bytes..][..frame_bytes],
            &state[frame * state_dim..][..state_dim],
        )?;
    }
    let feature_maps = (0..frames)
        .map(|frame| {
            (0..5)
                .map(|level| policy.feature_map(frame, level).unwrap().to_vec())
                .collect()
        })
        .collect();
    let noise = fixture.f32s("noise");
    let prefix_actions = fixture.prefix_actions();
    let planned_actions = fixture.planned_actions();
    let prefix = Prefix::new(&prefix_actions, fixture.prefix_mode).with_planned(&planned_actions);
    let mut recorded = Recorded::default();
    let actions = policy.infer_observed(Noise::Given(&noise), prefix, &mut recorded)?;
    Ok(EngineRun {
        action_pred: actions.action_pred().to_vec(),
        action: actions.action().to_vec(),
        recorded,
        feature_maps,
    })
}

/// A global allocator that counts the allocations made while [`allocations_during`] runs,
/// on any thread; each test binary that counts installs it:
/// `#[global_allocator] static ALLOCATOR: CountingAllocator = CountingAllocator;`.
pub struct CountingAllocator;

static COUNTING: AtomicBool = AtomicBool::new(false);
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards every call unchanged to the system allocator; it only counts.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if COUNTING.load(Ordering::SeqCst) {
            ALLOCATIONS.fetch_add(1, Ordering::SeqCst);
        }
        // SAFETY: the caller's contract for `alloc` is passed on as is.
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System.alloc` with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if COUNTING.load(Ordering::SeqCst) {
            ALLOCATIONS.fetch_add(1, Ordering::SeqCst);
        }
        // SAFETY: the caller's contract for `realloc` is passed on as is.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

/// Allocations made by any thread while `work` runs, where [`CountingAllocator`] is the
/// global allocator. One count at a time: a binary that counts runs one test.
pub fn allocations_during(work: impl FnOnce()) -> usize {
    ALLOCATIONS.store(0, Ordering::SeqCst);
    COUNTING.store(true, Ordering::SeqCst);
    work();
    COUNTING.store(false, Ordering::SeqCst);
    ALLOCATIONS.load(Ordering::SeqCst)
}
