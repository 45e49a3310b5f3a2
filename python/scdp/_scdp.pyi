"""The compiled part of `scdp` (PyO3): the engine's `Model` and `Policy`, `EngineError`,
`backends()`."""

from os import PathLike
from typing import Literal, Self, TypeAlias, TypedDict, final, overload, type_check_only

import numpy as np
import numpy.typing as npt
from typing_extensions import Buffer

_BackendName: TypeAlias = Literal[
    "auto", "scalar", "avx2", "avx512", "amx", "neon", "dot", "i8mm"
]
_PrefixMode: TypeAlias = Literal["replace", "noised"]

@type_check_only
class ModelConfig(TypedDict):
    """The model configuration a weights file records (docs/SPEC.md section 7's field names)."""

    image_height: int
    image_width: int
    imagenet_norm: bool
    backbone_norm: Literal["group", "batch"]
    backbone_width: int
    feature_dim: int
    n_obs_steps: int
    horizon: int
    n_action_steps: int
    reconstruction_horizon: int
    state_dim: int
    action_dim: int
    state_pos_index: list[int]
    action_pos_index: list[int]
    pos_scale: float
    down_dims: list[int]
    diffusion_step_embed_dim: int
    kernel_size: int
    n_groups: int
    num_train_timesteps: int
    num_inference_steps: int
    clip_sample: bool

@type_check_only
class Timings(TypedDict):
    """Milliseconds of the engine's work in the last successful calls, None before the
    first."""

    push_observation_ms: float | None
    infer_ms: float | None

@type_check_only
class FullInference(TypedDict):
    """`Policy.infer(full=True)`'s result."""

    action: npt.NDArray[np.float32]
    """`[n_action_steps, action_dim]`, the rows to execute."""
    action_pred: npt.NDArray[np.float32]
    """`[horizon, action_dim]`, the whole denoised chunk, unnormalized."""
    anchors_uv: npt.NDArray[np.float32]
    """`[num_inference_steps, reconstruction_horizon + 1, 2]` anchor pixels of every step,
    NaN where a point is behind the camera."""

class EngineError(RuntimeError):
    """An error the SCDP engine reported; `str(err)` is the engine's message."""

def backends() -> list[str]:
    """The names of the kernel backends this CPU can run (always including "scalar"),
    slowest first: scalar, avx2, avx512, amx on x86-64, scalar, neon, dot, i8mm on
    aarch64; `Policy(model, backend=name)` accepts each, and "auto"."""

@final
class Model:
    """A validated SCDP weights file (written by `weights-tool convert`), held in memory.

    `Model(path)` reads the file; `Model.from_bytes(data)` copies a bytes-like object. The
    header, checksum and every tensor are checked once here; a bad file raises
    `EngineError` with the engine's message. Immutable, and shareable by several policies
    and threads.
    """

    def __new__(cls, path: str | PathLike[str]) -> Self: ...
    @staticmethod
    def from_bytes(data: Buffer) -> Model:
        """A model from the bytes of a weights file (`bytes`, `bytearray`, `memoryview`,
        ...), copied into aligned memory the model owns."""
    @property
    def config(self) -> ModelConfig:
        """The model configuration the file records (docs/SPEC.md section 7's field names)."""
    @property
    def quant(self) -> Literal["f32", "int8"]:
        """Storage precision of the weight matrices and kernels."""
    @property
    def arena_bytes(self) -> int:
        """Bytes of the arena a `Policy` of this model allocates."""
    @property
    def file_bytes(self) -> int:
        """Bytes of the weights file."""

@final
class Policy:
    """One policy instance: a model, a camera and an observation history, in an arena of
    its own (`Model.arena_bytes`).

    `backend` is "auto" (the fastest this CPU runs) or a name from `scdp.backends()`; one
    this CPU cannot run raises `EngineError`. `threads` workers run each call: the calling
    thread and `threads - 1` threads the policy starts once and keeps; the results are the
    same bits for any number. The policy keeps its model alive. Calls release the GIL
    while the engine runs; one policy serves one call at a time (a
    concurrent call from another thread raises `RuntimeError`), so give each thread its
    own policy.
    """

    def __new__(
        cls, model: Model, backend: _BackendName | str = "auto", threads: int = 1
    ) -> Self: ...
    def set_camera(self, K: npt.ArrayLike, T: npt.ArrayLike) -> None:
        """Sets or replaces the camera calibration: `K` the 3x3 pinhole intrinsics
        `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`, `T` the 4x4 rigid camera <- robot-base
        transform (`X_cam = R X_base + t`). float32 or float64. The engine's checks raise
        `EngineError` (non-positive focal length, a T that is not a finite rigid
        transform)."""
    def push_observation(self, image: npt.NDArray[np.uint8], state: npt.ArrayLike) -> None:
        """Encodes a frame and makes it the newest observation: `image` uint8 `[H, W, 3]`
        RGB (the config's image size), `state` the robot state `[state_dim]` (float32 or
        float64). The first observation after creation or `reset()` fills the whole
        history. A state of the wrong length or with NaN/inf raises `EngineError`."""
    @overload
    def infer(
        self,
        seed: int | None = None,
        noise: npt.ArrayLike | None = None,
        full: Literal[False] = False,
        prefix: npt.ArrayLike | None = None,
        prefix_mode: _PrefixMode = "replace",
        planned: npt.ArrayLike | None = None,
    ) -> npt.NDArray[np.float32]: ...
    @overload
    def infer(
        self,
        seed: int | None = None,
        noise: npt.ArrayLike | None = None,
        *,
        full: Literal[True],
        prefix: npt.ArrayLike | None = None,
        prefix_mode: _PrefixMode = "replace",
        planned: npt.ArrayLike | None = None,
    ) -> FullInference: ...
    @overload
    def infer(
        self,
        seed: int | None = None,
        noise: npt.ArrayLike | None = None,
        full: bool = False,
        prefix: npt.ArrayLike | None = None,
        prefix_mode: _PrefixMode = "replace",
        planned: npt.ArrayLike | None = None,
    ) -> npt.NDArray[np.float32] | FullInference:
        """Runs the denoising loop (`num_inference_steps` DDIM steps) on the observations
        pushed.

        The initial noise comes from `seed` (the engine's portable Gaussian generator) or
        is `noise`, float32/float64 `[horizon, action_dim]`; giving both raises
        `ValueError`. Given neither, the seed is the policy's counter: 0 for the first such
        call after creation or `reset()`, then 1, 2, ...; so consecutive calls draw
        different noise and a reset policy repeats a new one's sequence. The counter
        advances only when such a call succeeds; explicit seeds and noise leave it alone.

        Returns the actions to execute, float32 `[n_action_steps, action_dim]`,
        unnormalized. With `full=True`, a dict: "action" (that array), "action_pred" (the
        whole chunk, `[horizon, action_dim]`) and "anchors_uv" (the anchor pixels of every
        step, `[num_inference_steps, reconstruction_horizon + 1, 2]`, NaN where a point is
        behind the camera). Raises `EngineError` before a camera is set or an observation
        pushed.

        `prefix`, float32/float64 `[k, action_dim]` in action units: the actions the robot
        will execute before this chunk takes over, for rows `n_obs_steps - 1 ..` of the
        chunk; the denoising holds them ("replace": Diffusion Policy's inpainting;
        "noised": at each step's noise level) so the rest of the chunk continues them.
        `planned`, `[m, action_dim]`: the previous chunk's plan for the rows after the
        prefix, which the chunk is pulled towards with weights falling from `m / (m + 1)`
        to `1 / (m + 1)`. More than `horizon - n_obs_steps + 1` rows in all, or NaN/inf,
        raise `EngineError`.
        """
    def reset(self) -> None:
        """Forgets the observation history and restarts the seed counter (see `infer`);
        the camera stays."""
    @property
    def backend(self) -> str:
        """The kernels in use: "scalar", "avx2", "avx512" or "amx" ("auto" resolved)."""
    @property
    def threads(self) -> int:
        """Workers an inference runs on (the calling thread and `threads - 1` more)."""
    @property
    def timings(self) -> Timings:
        """Milliseconds of the engine's work in the last successful calls:
        "push_observation_ms" (encoding the frame) and "infer_ms" (the denoising loop),
        None before the first. Input conversion is not included."""
    @property
    def config(self) -> ModelConfig:
        """The model's configuration, as `Model.config`."""

__all__ = ["EngineError", "Model", "Policy", "backends"]
