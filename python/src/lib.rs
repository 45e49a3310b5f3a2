//! `scdp._scdp`: the engine's public API for Python (PyO3, NumPy arrays in and out).
//!
//! The engine borrows everything: a `Model<'w>` reads the weights bytes in place and a
//! `Policy<'w, 'a>` borrows the model and its arena. A Python object cannot carry those
//! lifetimes, so each class owns what its engine value borrows, in memory that never moves
//! (anonymous mappings behind handles, an `Arc`), and holds the borrower with the lifetimes
//! widened to `'static`. The borrower is always declared before the owner, so it is dropped
//! before the memory it points into, and a widened reference only ever travels together with
//! (a clone of) its owner.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use memmap2::{Mmap, MmapMut, MmapOptions};
use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::buffer::PyBuffer;
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use scdp_engine::kernels;
use scdp_engine::{
    ArenaPlan, BackboneNorm, Backend, Camera, Model, ModelConfig, Noise, Policy, Prefix,
    PrefixMode, format::Quant,
};
use scdp_threads::ThreadPool;

create_exception!(
    scdp,
    EngineError,
    PyRuntimeError,
    "An error the SCDP engine reported; `str(err)` is the engine's message."
);

fn engine_error(error: scdp_engine::Error) -> PyErr {
    EngineError::new_err(error.to_string())
}

/// Zeroed bytes in an anonymous mapping: page aligned (the engine needs 64-byte alignment
/// for weights and arena) and, on Linux, in transparent huge pages where the kernel has
/// them, as `weights-tool` places its buffers: the U-Net reads all its weights at every
/// denoising step, and 4 KiB pages made that loop 12-15% slower (benches/README.md).
fn zeroed_mapping(len: usize) -> std::io::Result<MmapMut> {
    // A mapping of no bytes does not exist; the engine sees the requested length only.
    let map = MmapOptions::new().len(len.max(1)).map_anon()?;
    // Advice only, given before the first touch: without huge pages the buffer works the same.
    #[cfg(target_os = "linux")]
    let _ = map.advise(memmap2::Advice::HugePage);
    Ok(map)
}

/// A weights file's bytes and the engine's validated view of them.
struct Loaded {
    // Borrows `_bytes`: declared first so it is dropped first.
    model: Model<'static>,
    _bytes: Mmap,
}

impl Loaded {
    /// Validates `len` bytes at the start of `map`.
    fn new(map: MmapMut, len: usize) -> Result<Self, PyErr> {
        // Read-only from here on: the engine reads the weights in place for as long as the
        // model lives, so nothing may write them.
        let bytes = map.make_read_only()?;
        // SAFETY: the slice lies inside the mapping `bytes` (at least `len` bytes long), which
        // is never written (read-only) and stays mapped while `model` exists: `model` is
        // stored beside `bytes` and dropped before it (field order). `Model` is `Copy`, but
        // it is never copied out of this struct, and the one reference to it handed out (to
        // a `Policy`, in `PyPolicy::new`) travels with an `Arc` of this struct, so the
        // widened lifetime is never observed after the unmapping. Moving `bytes` moves the
        // handle, not the mapped pages.
        let view: &'static [u8] = unsafe { std::slice::from_raw_parts(bytes.as_ptr(), len) };
        let model = Model::from_bytes(view).map_err(engine_error)?;
        Ok(Loaded {
            model,
            _bytes: bytes,
        })
    }

    fn config(&self) -> &ModelConfig {
        self.model.config()
    }
}

/// Every field of `config` (docs/SPEC.md section 7's names), a new dict each call.
fn config_dict<'py>(py: Python<'py>, config: &ModelConfig) -> PyResult<Bound<'py, PyDict>> {
    // Exhaustive on purpose: a field added to ModelConfig fails to compile here until the
    // dict shows it.
    let ModelConfig {
        image_height,
        image_width,
        imagenet_norm,
        backbone_norm,
        backbone_width,
        feature_dim,
        n_obs_steps,
        horizon,
        n_action_steps,
        reconstruction_horizon,
        state_dim,
        action_dim,
        state_pos_index,
        action_pos_index,
        pos_scale,
        down_dims,
        diffusion_step_embed_dim,
        kernel_size,
        n_groups,
        num_train_timesteps,
        num_inference_steps,
        clip_sample,
    } = *config;
    let dict = PyDict::new(py);
    dict.set_item("image_height", image_height)?;
    dict.set_item("image_width", image_width)?;
    dict.set_item("imagenet_norm", imagenet_norm)?;
    // The config TOML's spelling.
    let norm = match backbone_norm {
        BackboneNorm::Group => "group",
        BackboneNorm::Batch => "batch",
    };
    dict.set_item("backbone_norm", norm)?;
    dict.set_item("backbone_width", backbone_width)?;
    dict.set_item("feature_dim", feature_dim)?;
    dict.set_item("n_obs_steps", n_obs_steps)?;
    dict.set_item("horizon", horizon)?;
    dict.set_item("n_action_steps", n_action_steps)?;
    dict.set_item("reconstruction_horizon", reconstruction_horizon)?;
    dict.set_item("state_dim", state_dim)?;
    dict.set_item("action_dim", action_dim)?;
    dict.set_item("state_pos_index", state_pos_index.to_vec())?;
    dict.set_item("action_pos_index", action_pos_index.to_vec())?;
    dict.set_item("pos_scale", pos_scale as f64)?;
    dict.set_item("down_dims", down_dims.to_vec())?;
    dict.set_item("diffusion_step_embed_dim", diffusion_step_embed_dim)?;
    dict.set_item("kernel_size", kernel_size)?;
    dict.set_item("n_groups", n_groups)?;
    dict.set_item("num_train_timesteps", num_train_timesteps)?;
    dict.set_item("num_inference_steps", num_inference_steps)?;
    dict.set_item("clip_sample", clip_sample)?;
    Ok(dict)
}

fn shape_text(shape: &[usize]) -> String {
    let dims: Vec<String> = shape.iter().map(usize::to_string).collect();
    match dims.len() {
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.join(", ")),
    }
}

/// What `object` is, for messages: an array's dtype or the Python type's name.
fn describe(object: &Bound<'_, PyAny>) -> String {
    match object.cast::<PyUntypedArray>() {
        Ok(array) => format!("an array of dtype {}", array.dtype()),
        Err(_) => match object.get_type().name() {
            Ok(name) => format!("a {name}"),
            Err(_) => "an object of unknown type".to_owned(),
        },
    }
}

/// Values of a float32 or float64 array in C order with its shape; another array-like (a
/// nested list) goes through `numpy.asarray(object, dtype=float64)` first. Arrays of other
/// dtypes are refused rather than converted: an integer or complex array where floats are
/// expected is more likely a mix-up than intended.
fn float_values(object: &Bound<'_, PyAny>, name: &str) -> PyResult<(Vec<usize>, Vec<f32>)> {
    let py = object.py();
    let array: Bound<'_, PyAny> = if object.cast::<PyUntypedArray>().is_ok() {
        object.clone()
    } else {
        py.import("numpy")?
            .call_method1("asarray", (object, "float64"))
            .map_err(|error| {
                PyValueError::new_err(format!(
                    "{name} must be a float32 or float64 array; got {} ({error})",
                    describe(object)
                ))
            })?
    };
    let shape = array.cast::<PyUntypedArray>()?.shape().to_vec();
    if let Ok(array) = array.cast::<PyArrayDyn<f32>>() {
        let array = array.try_readonly().map_err(borrow_error)?;
        return Ok((shape, c_order(array.as_array())));
    }
    if let Ok(array) = array.cast::<PyArrayDyn<f64>>() {
        let array = array.try_readonly().map_err(borrow_error)?;
        let values = array.as_array().iter().map(|&value| value as f32).collect();
        return Ok((shape, values));
    }
    Err(PyValueError::new_err(format!(
        "{name} must be a float32 or float64 array; got {}",
        describe(object)
    )))
}

/// The values in C order, whatever the layout. NumPy's own `as_slice` would also hand out a
/// Fortran-ordered array's memory as it lies, which is the transpose.
fn c_order<T: Copy>(view: numpy::ndarray::ArrayViewD<'_, T>) -> Vec<T> {
    match view.as_slice() {
        Some(slice) => slice.to_vec(),
        None => view.iter().copied().collect(),
    }
}

fn borrow_error(error: numpy::BorrowError) -> PyErr {
    PyValueError::new_err(format!("array cannot be read: {error}"))
}

fn require_shape(name: &str, found: &[usize], expected: &[usize], what: &str) -> PyResult<()> {
    if found == expected {
        Ok(())
    } else {
        Err(PyValueError::new_err(format!(
            "{name} must have shape {} {what}; got {}",
            shape_text(expected),
            shape_text(found)
        )))
    }
}

/// The names of the kernel backends this CPU can run (always including "scalar"), slowest
/// first: scalar, avx2, avx512, amx on x86-64; scalar, neon, dot, i8mm on aarch64.
/// `Policy(model, backend=name)` accepts each, and "auto".
#[pyfunction]
fn backends() -> Vec<&'static str> {
    Backend::ALL
        .into_iter()
        .filter(|&backend| backend != Backend::Auto)
        .filter_map(|backend| kernels::select(backend).map(|kernels| kernels.name()))
        .collect()
}

/// A validated SCDP weights file (written by `weights-tool convert`), held in memory.
///
/// `Model(path)` reads the file; `Model.from_bytes(data)` copies a bytes-like object. The
/// header, checksum and every tensor are checked once here; a bad file raises
/// `EngineError` with the engine's message. Immutable, and shareable by several policies
/// and threads.
#[pyclass(module = "scdp", name = "Model", frozen)]
struct PyModel {
    loaded: Arc<Loaded>,
}

#[pymethods]
impl PyModel {
    #[new]
    fn new(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let loaded = py.detach(|| -> PyResult<Loaded> {
            use std::io::Read;
            let mut file = std::fs::File::open(&path)?;
            let len = usize::try_from(file.metadata()?.len())
                .map_err(|_| PyValueError::new_err("weights file too large to map"))?;
            let mut map = zeroed_mapping(len)?;
            file.read_exact(&mut map[..len])?;
            Loaded::new(map, len)
        })?;
        Ok(PyModel {
            loaded: Arc::new(loaded),
        })
    }

    /// A model from the bytes of a weights file (`bytes`, `bytearray`, `memoryview`, ...),
    /// copied into aligned memory the model owns.
    #[staticmethod]
    fn from_bytes(py: Python<'_>, data: &Bound<'_, PyAny>) -> PyResult<Self> {
        let buffer = PyBuffer::<u8>::get(data)?;
        let len = buffer.item_count();
        let mut map = zeroed_mapping(len)?;
        buffer.copy_to_slice(py, &mut map[..len])?;
        drop(buffer);
        let loaded = py.detach(|| Loaded::new(map, len))?;
        Ok(PyModel {
            loaded: Arc::new(loaded),
        })
    }

    /// The model configuration the file records (docs/SPEC.md section 7's field names).
    #[getter]
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        config_dict(py, self.loaded.config())
    }

    /// Storage precision of the weight matrices and kernels: "f32" or "int8".
    #[getter]
    fn quant(&self) -> &'static str {
        match self.loaded.model.file().quant() {
            Quant::F32 => "f32",
            Quant::Int8 => "int8",
        }
    }

    /// Bytes of the arena a `Policy` of this model allocates.
    #[getter]
    fn arena_bytes(&self) -> usize {
        ArenaPlan::new(self.loaded.config()).arena_bytes
    }

    /// Bytes of the weights file.
    #[getter]
    fn file_bytes(&self) -> usize {
        self.loaded.model.file().len()
    }

    fn __repr__(&self) -> String {
        let config = self.loaded.config();
        format!(
            "scdp.Model({}x{} image, horizon {}, action_dim {}, {}, {} bytes)",
            config.image_height,
            config.image_width,
            config.horizon,
            config.action_dim,
            self.quant(),
            self.file_bytes()
        )
    }
}

/// One policy instance: a model, a camera and an observation history, in an arena of its
/// own (`Model.arena_bytes`).
///
/// `backend` is "auto" (the fastest this CPU runs) or a name from `scdp.backends()`;
/// one this CPU cannot run raises `EngineError`. `threads` workers run each call: the
/// calling thread and `threads - 1` threads the policy starts once and keeps; the results
/// are the same bits for any number. The policy keeps its model alive. Calls
/// release the GIL while the engine runs; one policy serves one call at a time (a
/// concurrent call from another thread raises `RuntimeError`), so give each thread its
/// own policy.
#[pyclass(module = "scdp", name = "Policy")]
struct PyPolicy {
    // Borrows `_arena`, `_model` and `_workers`: declared first so it is dropped first.
    policy: Policy<'static, 'static>,
    _arena: MmapMut,
    _model: Arc<Loaded>,
    /// The worker threads beyond the calling one, when `threads > 1`.
    _workers: Option<Box<ThreadPool>>,
    /// Seed of the next `infer()` given neither seed nor noise.
    next_seed: u64,
    push_observation_ms: Option<f64>,
    infer_ms: Option<f64>,
}

/// An inference's results, copied out of the arena before the GIL is taken back.
struct Inference {
    action: Vec<f32>,
    full: Option<(Vec<f32>, Vec<f32>)>,
    milliseconds: f64,
}

fn milliseconds(start: Instant) -> f64 {
    start.elapsed().as_secs_f64() * 1e3
}

#[pymethods]
impl PyPolicy {
    #[new]
    #[pyo3(signature = (model, backend = "auto", threads = 1))]
    fn new(model: &Bound<'_, PyModel>, backend: &str, threads: usize) -> PyResult<Self> {
        if threads == 0 {
            return Err(PyValueError::new_err("threads must be at least 1"));
        }
        let Some(backend) = Backend::from_name(backend) else {
            let names: Vec<&str> = Backend::ALL.iter().map(|backend| backend.name()).collect();
            return Err(PyValueError::new_err(format!(
                "backend must be one of {}; got {backend:?}",
                names.join(", ")
            )));
        };
        let loaded = Arc::clone(&model.get().loaded);
        let arena_bytes = ArenaPlan::new(loaded.config()).arena_bytes;
        let mut arena = zeroed_mapping(arena_bytes)?;
        // SAFETY: the reference is stored only in `policy`, beside `loaded`, an Arc this
        // struct keeps until after `policy` is dropped (field order); an Arc's contents
        // never move or change (Loaded has no interior mutability), so the model outlives
        // every use of the widened reference.
        let model: &'static Model<'static> = unsafe { &*(&loaded.model as *const Model<'static>) };
        // SAFETY: the slice lies inside the mapping `arena` (at least `arena_bytes` long),
        // which this struct owns, never reads, writes or remaps itself, and unmaps only when
        // dropped after `policy` (field order); so `policy`'s borrow is the only access to
        // those bytes while it exists. Moving the handle does not move the pages.
        let arena_view: &'static mut [u8] =
            unsafe { std::slice::from_raw_parts_mut(arena.as_mut_ptr(), arena_bytes) };
        let mut policy = Policy::with_backend(model, arena_view, backend).map_err(engine_error)?;
        let workers = if threads > 1 {
            let pool = ThreadPool::new(threads)
                .map_err(|error| PyRuntimeError::new_err(format!("worker threads: {error}")))?;
            Some(Box::new(pool))
        } else {
            None
        };
        if let Some(pool) = &workers {
            // SAFETY: the reference is stored only in `policy`; the pool is boxed (its
            // address does not move with this struct) and dropped after `policy` (field
            // order), so it outlives every use of the widened reference.
            let pool: &'static ThreadPool = unsafe { &*(&**pool as *const ThreadPool) };
            policy = policy.with_workers(pool);
        }
        Ok(PyPolicy {
            policy,
            _arena: arena,
            _model: loaded,
            _workers: workers,
            next_seed: 0,
            push_observation_ms: None,
            infer_ms: None,
        })
    }

    /// Sets or replaces the camera calibration: `K` the 3x3 pinhole intrinsics
    /// `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`, `T` the 4x4 rigid camera <- robot-base
    /// transform (`X_cam = R X_base + t`). float32 or float64. The engine's checks raise
    /// `EngineError` (non-positive focal length, a T that is not a finite rigid transform).
    // K and T as docs/SPEC.md section 3 names them, which are also the keyword names.
    #[pyo3(signature = (K, T))]
    #[allow(non_snake_case)]
    fn set_camera(&mut self, K: &Bound<'_, PyAny>, T: &Bound<'_, PyAny>) -> PyResult<()> {
        let (k_shape, k) = float_values(K, "K")?;
        require_shape("K", &k_shape, &[3, 3], "(intrinsics)")?;
        let (t_shape, t) = float_values(T, "T")?;
        require_shape("T", &t_shape, &[4, 4], "(extrinsics)")?;
        let intrinsics: [[f32; 3]; 3] =
            std::array::from_fn(|row| std::array::from_fn(|column| k[row * 3 + column]));
        let extrinsics: [[f32; 4]; 4] =
            std::array::from_fn(|row| std::array::from_fn(|column| t[row * 4 + column]));
        let camera = Camera::new(&intrinsics, &extrinsics).map_err(engine_error)?;
        self.policy.set_camera(camera);
        Ok(())
    }

    /// Encodes a frame and makes it the newest observation: `image` uint8 `[H, W, 3]` RGB
    /// (the config's image size), `state` the robot state `[state_dim]` (float32 or
    /// float64). The first observation after creation or `reset()` fills the whole
    /// history. A state of the wrong length or with NaN/inf raises `EngineError`.
    fn push_observation(
        &mut self,
        py: Python<'_>,
        image: &Bound<'_, PyAny>,
        state: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let config = *self.policy.config();
        let expected = [config.image_height as usize, config.image_width as usize, 3];
        let Ok(array) = image.cast::<PyArrayDyn<u8>>() else {
            return Err(PyValueError::new_err(format!(
                "image must be a uint8 array of shape {}; got {}",
                shape_text(&expected),
                describe(image)
            )));
        };
        require_shape("image", array.shape(), &expected, "(H, W, RGB)")?;
        // Inputs are copied while the GIL is held: once it is released, another Python
        // thread may write the caller's arrays.
        let image = c_order(array.try_readonly().map_err(borrow_error)?.as_array());

        let (state_shape, state) = float_values(state, "state")?;
        if state_shape.len() != 1 {
            return Err(PyValueError::new_err(format!(
                "state must be 1-D, [state_dim] = ({},); got shape {}",
                config.state_dim,
                shape_text(&state_shape)
            )));
        }

        let policy = &mut self.policy;
        let milliseconds = py.detach(|| {
            let start = Instant::now();
            policy.push_observation(&image, &state)?;
            Ok(milliseconds(start))
        });
        self.push_observation_ms = Some(milliseconds.map_err(engine_error)?);
        Ok(())
    }

    /// Runs the denoising loop (`num_inference_steps` DDIM steps) on the observations pushed.
    ///
    /// The initial noise comes from `seed` (the engine's portable Gaussian generator) or is
    /// `noise`, float32/float64 `[horizon, action_dim]`; giving both raises `ValueError`.
    /// Given neither, the seed is the policy's counter: 0 for the first such call after
    /// creation or `reset()`, then 1, 2, ...; so consecutive calls draw different noise
    /// and a reset policy repeats a new one's sequence. The counter advances only when such
    /// a call succeeds; explicit seeds and noise leave it alone.
    ///
    /// Returns the actions to execute, float32 `[n_action_steps, action_dim]`, unnormalized.
    /// With `full=True`, a dict: "action" (that array), "action_pred" (the whole chunk,
    /// `[horizon, action_dim]`) and "anchors_uv" (the anchor pixels of every step,
    /// `[num_inference_steps, reconstruction_horizon + 1, 2]`, NaN where a point is behind
    /// the camera). Raises `EngineError` before a camera is set or an observation pushed.
    ///
    /// `prefix`, float32/float64 `[k, action_dim]` in action units: the actions the robot
    /// will execute before this chunk takes over, for rows `n_obs_steps - 1 ..` of the
    /// chunk; the denoising holds them (`prefix_mode` "replace", Diffusion Policy's
    /// inpainting, or "noised", at each step's noise level) so the rest continues them.
    /// `planned`, `[m, action_dim]`: the previous chunk's plan for the rows after the prefix;
    /// the chunk is pulled towards it with weights falling from `m / (m + 1)` to
    /// `1 / (m + 1)`, so it leaves the old plan smoothly. More rows than `horizon -
    /// n_obs_steps + 1` in all, or NaN/inf, raise `EngineError`.
    #[pyo3(signature = (seed = None, noise = None, full = false, prefix = None, prefix_mode = "replace", planned = None))]
    #[allow(clippy::too_many_arguments)]
    fn infer<'py>(
        &mut self,
        py: Python<'py>,
        seed: Option<&Bound<'py, PyAny>>,
        noise: Option<&Bound<'py, PyAny>>,
        full: bool,
        prefix: Option<&Bound<'py, PyAny>>,
        prefix_mode: &str,
        planned: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let config = *self.policy.config();
        let (horizon, action_dim) = (config.horizon as usize, config.action_dim as usize);
        let mode = match prefix_mode {
            "replace" => PrefixMode::Replace,
            "noised" => PrefixMode::Noised,
            other => {
                return Err(PyValueError::new_err(format!(
                    "prefix_mode must be \"replace\" or \"noised\"; got {other:?}"
                )));
            }
        };
        let rows = |array: Option<&Bound<'py, PyAny>>, name: &str| -> PyResult<Vec<f32>> {
            let Some(array) = array else {
                return Ok(Vec::new());
            };
            let (shape, values) = float_values(array, name)?;
            if shape.len() != 2 || shape[1] != action_dim {
                return Err(PyValueError::new_err(format!(
                    "{name} must be 2-D, [k, action_dim] = (k, {action_dim}); got shape {}",
                    shape_text(&shape)
                )));
            }
            Ok(values)
        };
        let prefix = rows(prefix, "prefix")?;
        let planned = rows(planned, "planned")?;
        let counted = seed.is_none() && noise.is_none();
        let mut given = Vec::new();
        let seed = match (seed, noise) {
            (Some(_), Some(_)) => {
                return Err(PyValueError::new_err("give seed or noise, not both"));
            }
            (Some(seed), None) => Some(seed.extract::<u64>().map_err(|_| {
                PyValueError::new_err(format!(
                    "seed must be an integer in [0, 2**64); got {}",
                    seed.repr()
                        .map_or_else(|_| describe(seed), |r| r.to_string())
                ))
            })?),
            (None, Some(noise)) => {
                let (shape, values) = float_values(noise, "noise")?;
                require_shape(
                    "noise",
                    &shape,
                    &[horizon, action_dim],
                    "[horizon, action_dim]",
                )?;
                given = values;
                None
            }
            (None, None) => Some(self.next_seed),
        };

        let policy = &mut self.policy;
        let result = py.detach(|| -> Result<Inference, scdp_engine::Error> {
            let noise = match seed {
                Some(seed) => Noise::Seed(seed),
                None => Noise::Given(&given),
            };
            let start = Instant::now();
            let held = Prefix::new(&prefix, mode).with_planned(&planned);
            let actions = policy.infer_with(noise, held)?;
            let milliseconds = milliseconds(start);
            Ok(Inference {
                action: actions.action().to_vec(),
                full: full.then(|| {
                    (
                        actions.action_pred().to_vec(),
                        actions.anchors_uv().to_vec(),
                    )
                }),
                milliseconds,
            })
        });
        let inference = result.map_err(engine_error)?;
        self.infer_ms = Some(inference.milliseconds);
        if counted {
            self.next_seed = self.next_seed.wrapping_add(1);
        }

        let action = PyArray1::from_vec(py, inference.action)
            .reshape([config.n_action_steps as usize, action_dim])?;
        let Some((action_pred, anchors_uv)) = inference.full else {
            return Ok(action.into_any());
        };
        let action_pred = PyArray1::from_vec(py, action_pred).reshape([horizon, action_dim])?;
        let anchors_uv = PyArray1::from_vec(py, anchors_uv).reshape([
            config.num_inference_steps as usize,
            config.anchor_count(),
            2,
        ])?;
        let dict = PyDict::new(py);
        dict.set_item("action", action)?;
        dict.set_item("action_pred", action_pred)?;
        dict.set_item("anchors_uv", anchors_uv)?;
        Ok(dict.into_any())
    }

    /// Forgets the observation history and restarts the seed counter (see `infer`); the
    /// camera stays.
    fn reset(&mut self) {
        self.policy.reset();
        self.next_seed = 0;
    }

    /// The kernels in use: "scalar", "avx2", "avx512" or "amx" ("auto" resolved).
    #[getter]
    fn backend(&self) -> &'static str {
        self.policy.kernels_name()
    }

    /// Workers an inference runs on (the calling thread and `threads - 1` more).
    #[getter]
    fn threads(&self) -> usize {
        self.policy.workers()
    }

    /// Milliseconds of the engine's work in the last successful calls:
    /// "push_observation_ms" (encoding the frame) and "infer_ms" (the denoising loop),
    /// None before the first. Input conversion is not included.
    #[getter]
    fn timings<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let dict = PyDict::new(py);
        dict.set_item("push_observation_ms", self.push_observation_ms)?;
        dict.set_item("infer_ms", self.infer_ms)?;
        Ok(dict)
    }

    /// The model's configuration, as `Model.config`.
    #[getter]
    fn config<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        config_dict(py, self.policy.config())
    }

    fn __repr__(&self) -> String {
        format!(
            "scdp.Policy(backend={:?}, threads={})",
            self.policy.kernels_name(),
            self.policy.workers()
        )
    }
}

/// The compiled part of `scdp`: the engine's `Model` and `Policy`, `EngineError`,
/// `backends()`.
#[pymodule]
mod _scdp {
    #[pymodule_export]
    use super::{EngineError, PyModel, PyPolicy, backends};
}
