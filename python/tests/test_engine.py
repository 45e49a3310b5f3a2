"""The `scdp` binding against the golden fixtures and on every error path.

Needs the package installed (`pip install ./python[test]`) and a Rust toolchain: the weights
are made as tests/tests/golden.rs makes them, by the release `weights-tool` (built here if
needed; `SCDP_WEIGHTS_TOOL` names another binary): `synth` with each fixture's config and
seed, then `convert`.
"""

from __future__ import annotations

import gc
import os
import re
import subprocess
import sys
import threading
import tomllib
from pathlib import Path

import numpy as np
import pytest
import scdp
from safetensors import safe_open
from safetensors.numpy import load_file

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = ROOT / "tests" / "fixtures" / "golden"
FIXTURES = sorted(GOLDEN.glob("*/*.safetensors"))
# golden.rs's bound: action_pred within 2e-4 of the float64 truth in normalized action units,
# |engine - truth| x action scale.
ACTION_TOLERANCE = 2e-4
# golden.rs's bound for an intermediate stage (the anchors here): STAGE_FACTOR times float32
# PyTorch's deviation from the same truth, plus FLOOR relative to the stage's magnitude.
STAGE_FACTOR = 10.0
FLOOR = 1e-5


def fixture_id(path: Path) -> str:
    return f"{path.parent.name}/{path.stem}"


def fixture_metadata(path: Path) -> dict[str, str]:
    with safe_open(str(path), "np") as f:
        return f.metadata()


class Weights:
    """The converted weights of each (config, seed) the fixtures use, made once."""

    def __init__(self, tool: Path, folder: Path):
        self.tool = tool
        self.folder = folder
        self.made: dict[tuple[str, str], tuple[Path, np.ndarray]] = {}

    def for_fixture(self, path: Path) -> tuple[Path, np.ndarray]:
        """The weights file and the action scale (for normalized errors)."""
        metadata = fixture_metadata(path)
        key = (metadata["config"], metadata["seed"])
        if key not in self.made:
            name = f"{metadata['config_name']}-{metadata['seed']}"
            config = self.folder / f"{name}.toml"
            config.write_text(metadata["config"])
            checkpoint = self.folder / f"{name}.safetensors"
            model = self.folder / f"{name}.scdp"

            def run(*args):
                subprocess.run([str(self.tool), *map(str, args)], check=True, capture_output=True)

            run("synth", "--config", config, "--seed", metadata["seed"], "-o", checkpoint)
            # The weights the reference ran: the generator reproduces Python's bit for bit.
            assert fixture_metadata(checkpoint)["weights_sha256"] == metadata["weights_sha256"]
            run("convert", checkpoint, "--config", config, "-o", model)
            scale = load_file(str(checkpoint))["normalizer.params_dict.action.scale"]
            checkpoint.unlink()
            self.made[key] = (model, scale.astype(np.float64))
        return self.made[key]


@pytest.fixture(scope="session")
def weights(weights_tool: Path, tmp_path_factory: pytest.TempPathFactory) -> Weights:
    return Weights(weights_tool, tmp_path_factory.mktemp("weights"))


@pytest.fixture(scope="session")
def models(weights: Weights) -> dict[Path, scdp.Model]:
    """The loaded model of each fixture; fixtures of one config share it."""
    by_file: dict[Path, scdp.Model] = {}
    loaded: dict[Path, scdp.Model] = {}
    for path in FIXTURES:
        file = weights.for_fixture(path)[0]
        if file not in by_file:
            by_file[file] = scdp.Model(file)
        loaded[path] = by_file[file]
    return loaded


TINY = GOLDEN / "tiny" / "basic.safetensors"
TINY_EDGE = GOLDEN / "tiny" / "edge.safetensors"


@pytest.fixture(scope="session")
def tiny_model(models: dict[Path, scdp.Model]) -> scdp.Model:
    return models[TINY]


@pytest.fixture(scope="session")
def tiny() -> dict[str, np.ndarray]:
    return load_file(str(TINY))


def ready_policy(model: scdp.Model, case: dict[str, np.ndarray], backend: str = "auto"):
    policy = scdp.Policy(model, backend)
    policy.set_camera(case["camera_k"], case["camera_t"])
    for image, state in zip(case["images"], case["state"]):
        policy.push_observation(image, state)
    return policy


def max_error(engine: np.ndarray, truth: np.ndarray) -> float:
    """golden.rs's max_error: NaN in one but not the other is an infinite error."""
    engine = np.asarray(engine, np.float64)
    if not np.array_equal(np.isnan(engine), np.isnan(truth)):
        return float("inf")
    valid = ~np.isnan(truth)
    return float(np.abs(engine[valid] - truth[valid]).max(initial=0.0))


# --- (1) golden fixtures --------------------------------------------------------------------


@pytest.mark.parametrize("backend", scdp.backends())
@pytest.mark.parametrize("path", FIXTURES, ids=fixture_id)
def test_golden_fixture(path, backend, models, weights):
    case = load_file(str(path))
    _, scale = weights.for_fixture(path)
    policy = ready_policy(models[path], case, backend)
    assert policy.backend == backend
    prefix_mode = fixture_metadata(path).get("prefix_mode", "replace")
    result = policy.infer(noise=case["noise"], full=True, prefix=case.get("prefix"), prefix_mode=prefix_mode,
                          planned=case.get("planned"))

    truth = case["ref64.action_pred"]
    action_error = float((np.abs(result["action_pred"] - truth) * scale).max())
    assert action_error <= ACTION_TOLERANCE, f"action_pred error {action_error:.3e}"

    truth = case["ref64.anchors_uv"]
    deviation = max_error(case["ref32.anchors_uv"], truth)
    bound = STAGE_FACTOR * deviation + FLOOR * max(np.nanmax(np.abs(truth)), 1e-3)
    anchors_error = max_error(result["anchors_uv"], truth)
    assert anchors_error <= bound, f"anchors_uv error {anchors_error:.3e} > {bound:.3e}"

    config = policy.config
    first = config["n_obs_steps"] - 1
    executed = result["action_pred"][first : first + config["n_action_steps"]]
    np.testing.assert_array_equal(result["action"], executed)
    action_error = float((np.abs(result["action"] - case["ref64.action"]) * scale).max())
    assert action_error <= ACTION_TOLERANCE


def test_fixtures_are_there():
    assert len(FIXTURES) >= 15, FIXTURES
    assert sum("prefix" in load_file(str(path)) for path in FIXTURES) >= 9
    assert sum("planned" in load_file(str(path)) for path in FIXTURES) >= 3


# --- (2) errors -----------------------------------------------------------------------------


def engine_error(message: str):
    return pytest.raises(scdp.EngineError, match=f"^{re.escape(message)}$")


def test_engine_error_is_a_runtime_error():
    assert issubclass(scdp.EngineError, RuntimeError)


def test_bad_weights_bytes_raise_the_engines_message(tiny_model, weights):
    data = Path(weights.for_fixture(TINY)[0]).read_bytes()
    assert scdp.Model.from_bytes(data).config == tiny_model.config
    with engine_error("weights file is truncated"):
        scdp.Model.from_bytes(b"")
    with engine_error("weights file is truncated"):
        scdp.Model.from_bytes(data[:-64])
    with engine_error("not an SCDP weights file (bad magic)"):
        scdp.Model.from_bytes(b"\0" * 4096)
    corrupted = bytearray(data)
    corrupted[-1] ^= 1
    with engine_error("weights file checksum does not match"):
        scdp.Model.from_bytes(corrupted)
    version = int.from_bytes(data[8:12], "little")
    newer = bytearray(data)
    newer[8:12] = (version + 1).to_bytes(4, "little")
    with engine_error(
        f"weights file format version {version + 1}; this engine reads version {version}"
    ):
        scdp.Model.from_bytes(bytes(newer))


def test_bad_weights_file_raises_the_engines_message(tmp_path):
    path = tmp_path / "bad.scdp"
    path.write_bytes(b"SCDPWTS\0" + b"\0" * 8)
    with engine_error("weights file is truncated"):
        scdp.Model(path)
    with pytest.raises(FileNotFoundError):
        scdp.Model(tmp_path / "missing.scdp")


def test_unknown_backend_is_a_value_error(tiny_model):
    with pytest.raises(ValueError, match="backend must be one of auto, scalar, avx2"):
        scdp.Policy(tiny_model, "sve")


def test_unavailable_backend_is_an_engine_error(tiny_model):
    every = ("avx2", "avx512", "amx", "neon", "dot", "i8mm")
    missing = [b for b in every if b not in scdp.backends()]
    if not missing:
        pytest.skip("this CPU runs every backend")
    with engine_error("the requested kernel backend cannot run on this CPU"):
        scdp.Policy(tiny_model, missing[0])


def test_bad_images_are_value_errors(tiny_model, tiny):
    policy = scdp.Policy(tiny_model)
    image, state = tiny["images"][0], tiny["state"][0]
    with pytest.raises(
        ValueError,
        match=r"image must be a uint8 array of shape \(32, 48, 3\); got an array of dtype float32",
    ):
        policy.push_observation(image.astype(np.float32), state)
    with pytest.raises(ValueError, match="image must be a uint8 array .* got a list"):
        policy.push_observation(image.tolist(), state)
    bad_shapes = [image.transpose(1, 0, 2), image[..., :2], image[None], image.reshape(-1)]
    for bad in bad_shapes:
        expected = r"image must have shape \(32, 48, 3\) \(H, W, RGB\); got "
        with pytest.raises(ValueError, match=expected + re.escape(str(bad.shape))):
            policy.push_observation(bad, state)
    # Nothing was pushed.
    policy.set_camera(tiny["camera_k"], tiny["camera_t"])
    with engine_error("no observation has been pushed"):
        policy.infer(seed=0)


def test_bad_states(tiny_model, tiny):
    policy = scdp.Policy(tiny_model)
    policy.set_camera(tiny["camera_k"], tiny["camera_t"])
    image, state = tiny["images"][0], tiny["state"][0]
    with engine_error("state has 4 values; expected 5"):
        policy.push_observation(image, state[:4])
    with engine_error("state has 6 values; expected 5"):
        policy.push_observation(image, np.append(state, 0))
    for bad_value in (np.nan, np.inf):
        bad = state.copy()
        bad[2] = bad_value
        with engine_error("state contains NaN or infinity"):
            policy.push_observation(image, bad)
    with pytest.raises(
        ValueError, match=r"state must be 1-D, \[state_dim\] = \(5,\); got shape \(1, 5\)"
    ):
        policy.push_observation(image, state[None])
    with pytest.raises(
        ValueError, match="state must be a float32 or float64 array; got an array of dtype int64"
    ):
        policy.push_observation(image, state.astype(np.int64))
    with pytest.raises(ValueError, match="state must be a float32 or float64 array"):
        policy.push_observation(image, "not a state")
    # A failed call pushes nothing.
    with engine_error("no observation has been pushed"):
        policy.infer(seed=0)


def test_infer_before_camera_and_before_observation(tiny_model, tiny):
    policy = scdp.Policy(tiny_model)
    with engine_error("no camera calibration has been set"):
        policy.infer()
    policy.push_observation(tiny["images"][0], tiny["state"][0])
    with engine_error("no camera calibration has been set"):
        policy.infer(seed=3)
    policy.reset()
    policy.set_camera(tiny["camera_k"], tiny["camera_t"])
    with engine_error("no observation has been pushed"):
        policy.infer(noise=tiny["noise"])
    assert policy.timings["infer_ms"] is None


def test_bad_cameras(tiny_model, tiny):
    policy = scdp.Policy(tiny_model)
    k, t = tiny["camera_k"], tiny["camera_t"]
    for zero_focal in ((0, 0), (1, 1)):
        bad = k.copy()
        bad[zero_focal] = 0
        with engine_error("camera intrinsics are not a valid pinhole matrix"):
            policy.set_camera(bad, t)
    skewed = k.copy()
    skewed[0, 1] = 0.5
    with engine_error("camera intrinsics are not a valid pinhole matrix"):
        policy.set_camera(skewed, t)
    scaled = t.copy()
    scaled[:3, :3] *= 2  # not a rotation
    reflected = t.copy()
    reflected[0, :3] *= -1  # orthonormal, determinant -1
    bottom = t.copy()
    bottom[3, 0] = 1
    infinite = t.copy()
    infinite[0, 3] = np.inf
    for bad in (scaled, reflected, bottom, infinite):
        with engine_error("camera extrinsics are not a finite rigid transform"):
            policy.set_camera(k, bad)
    with pytest.raises(ValueError, match=r"K must have shape \(3, 3\) \(intrinsics\); got \(9,\)"):
        policy.set_camera(k.reshape(-1), t)
    with pytest.raises(
        ValueError, match=r"T must have shape \(4, 4\) \(extrinsics\); got \(3, 4\)"
    ):
        policy.set_camera(k, t[:3])
    with pytest.raises(
        ValueError, match="K must be a float32 or float64 array; got an array of dtype complex128"
    ):
        policy.set_camera(k.astype(np.complex128), t)
    # A rejected camera sets nothing.
    policy.push_observation(tiny["images"][0], tiny["state"][0])
    with engine_error("no camera calibration has been set"):
        policy.infer()


def test_bad_noise_and_seed(tiny_model, tiny):
    policy = ready_policy(tiny_model, tiny)
    noise = tiny["noise"]
    with pytest.raises(ValueError, match="give seed or noise, not both"):
        policy.infer(seed=1, noise=noise)
    with pytest.raises(
        ValueError, match=r"noise must have shape \(8, 4\) \[horizon, action_dim\]; got \(32,\)"
    ):
        policy.infer(noise=noise.reshape(-1))
    with pytest.raises(
        ValueError, match="noise must be a float32 or float64 array; got an array of dtype int32"
    ):
        policy.infer(noise=noise.astype(np.int32))
    bad = noise.copy()
    bad[3, 1] = np.nan
    with engine_error("noise contains NaN or infinity"):
        policy.infer(noise=bad)
    for seed in (-1, 2**64, 1.5, "7"):
        with pytest.raises(ValueError, match=r"seed must be an integer in \[0, 2\*\*64\)"):
            policy.infer(seed=seed)
    assert policy.infer(seed=2**64 - 1).shape == (4, 4)


def test_bad_prefixes(tiny_model, tiny):
    policy = ready_policy(tiny_model, tiny)
    with pytest.raises(ValueError, match=r"prefix_mode must be \"replace\" or \"noised\"; got \"soft\""):
        policy.infer(seed=1, prefix=np.zeros((2, 4)), prefix_mode="soft")
    with pytest.raises(ValueError, match=r"prefix must be 2-D, \[k, action_dim\] = \(k, 4\); got shape \(8,\)"):
        policy.infer(seed=1, prefix=np.zeros(8))
    # tiny: horizon 8, To 2, so at most 7 rows.
    with engine_error("prefix has 32 values; expected whole rows of 4, at most 7 rows with the planned ones"):
        policy.infer(seed=1, prefix=np.zeros((8, 4)))
    with engine_error("prefix has 32 values; expected whole rows of 4, at most 7 rows with the planned ones"):
        policy.infer(seed=1, prefix=np.zeros((5, 4)), planned=np.zeros((3, 4)))
    bad = np.zeros((2, 4))
    bad[1, 2] = np.inf
    with engine_error("prefix or planned actions contain NaN or infinity"):
        policy.infer(seed=1, prefix=bad, prefix_mode="noised")
    with engine_error("prefix or planned actions contain NaN or infinity"):
        policy.infer(seed=1, prefix=np.zeros((1, 4)), planned=bad)


@pytest.mark.parametrize("mode", ["replace", "noised"])
def test_prefix_rows_come_back_and_an_empty_one_changes_nothing(tiny_model, tiny, mode):
    policy = ready_policy(tiny_model, tiny)
    plain = policy.infer(seed=3, full=True)["action_pred"]
    empty = policy.infer(seed=3, full=True, prefix=np.zeros((0, 4)), prefix_mode=mode)["action_pred"]
    np.testing.assert_array_equal(empty, plain)
    prefix = plain[2:5] + 0.05
    held = policy.infer(seed=3, full=True, prefix=prefix, prefix_mode=mode)
    np.testing.assert_allclose(held["action_pred"][1:4], prefix, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(held["action"][:3], held["action_pred"][1:4])
    assert not np.array_equal(held["action_pred"][4:], plain[4:])


# --- (3) behaviour --------------------------------------------------------------------------


def test_seeds_are_deterministic(tiny_model, tiny):
    policy = ready_policy(tiny_model, tiny)
    first = policy.infer(seed=11)
    np.testing.assert_array_equal(policy.infer(seed=11), first)
    np.testing.assert_array_equal(ready_policy(tiny_model, tiny).infer(seed=11), first)
    assert not np.array_equal(policy.infer(seed=12), first)


def test_seed_counter(tiny_model, tiny):
    policy = ready_policy(tiny_model, tiny)
    by_seed = [policy.infer(seed=seed) for seed in range(3)]
    counted = [policy.infer() for _ in range(3)]
    for expected, found in zip(by_seed, counted):
        np.testing.assert_array_equal(found, expected)
    assert not np.array_equal(counted[0], counted[1])
    # Reset restarts the counter; explicit seeds leave it alone.
    policy.reset()
    for image, state in zip(tiny["images"], tiny["state"]):
        policy.push_observation(image, state)
    policy.infer(seed=5)
    np.testing.assert_array_equal(policy.infer(), by_seed[0])


def test_reset_forgets_the_history_and_keeps_the_camera(tiny_model, tiny):
    fresh = ready_policy(tiny_model, tiny).infer(noise=tiny["noise"], full=True)
    policy = ready_policy(tiny_model, tiny)
    # Another episode first: frames in the other order.
    policy.reset()
    for image, state in zip(tiny["images"][::-1], tiny["state"][::-1]):
        policy.push_observation(image, state)
    other = policy.infer(noise=tiny["noise"])
    assert not np.array_equal(other, fresh["action"])
    policy.reset()
    with engine_error("no observation has been pushed"):
        policy.infer(seed=0)
    for image, state in zip(tiny["images"], tiny["state"]):
        policy.push_observation(image, state)
    again = policy.infer(noise=tiny["noise"], full=True)
    for key in fresh:
        np.testing.assert_array_equal(again[key], fresh[key])


def test_first_observation_fills_the_history(tiny_model, tiny):
    image, state = tiny["images"][0], tiny["state"][0]
    once = scdp.Policy(tiny_model)
    once.set_camera(tiny["camera_k"], tiny["camera_t"])
    once.push_observation(image, state)
    twice = scdp.Policy(tiny_model)
    twice.set_camera(tiny["camera_k"], tiny["camera_t"])
    twice.push_observation(image, state)
    twice.push_observation(image, state)
    np.testing.assert_array_equal(once.infer(seed=4), twice.infer(seed=4))


def test_full_result_shapes(models):
    case = load_file(str(TINY_EDGE))
    policy = ready_policy(models[TINY_EDGE], case)
    config = policy.config
    horizon, action_dim = config["horizon"], config["action_dim"]
    steps, anchors = config["num_inference_steps"], config["reconstruction_horizon"] + 1
    action = policy.infer(seed=0)
    assert action.dtype == np.float32 and action.shape == (config["n_action_steps"], action_dim)
    np.testing.assert_array_equal(policy.infer(seed=0, full=True)["action"], action)
    full = policy.infer(noise=case["noise"], full=True)
    assert set(full) == {"action", "action_pred", "anchors_uv"}
    assert full["action_pred"].shape == (horizon, action_dim)
    assert full["anchors_uv"].shape == (steps, anchors, 2)
    for value in full.values():
        assert value.dtype == np.float32 and value.flags.c_contiguous and value.flags.writeable
    # The edge case puts points behind the camera: NaN in both coordinates.
    uv = full["anchors_uv"]
    assert np.isnan(uv).any() and np.array_equal(np.isnan(uv[..., 0]), np.isnan(uv[..., 1]))
    assert np.isfinite(full["action_pred"]).all()


def test_timings(tiny_model, tiny):
    policy = scdp.Policy(tiny_model)
    assert policy.timings == {"push_observation_ms": None, "infer_ms": None}
    policy.set_camera(tiny["camera_k"], tiny["camera_t"])
    policy.push_observation(tiny["images"][0], tiny["state"][0])
    assert policy.timings["infer_ms"] is None
    policy.infer()
    timings = policy.timings
    assert set(timings) == {"push_observation_ms", "infer_ms"}
    assert all(isinstance(v, float) and v > 0 for v in timings.values())


def test_required_backends_run():
    # As the Rust tests read it (CI sets it from /proc/cpuinfo): a backend this CPU has but
    # the engine failed to detect would otherwise be skipped silently.
    required = [n for n in os.environ.get("SCDP_REQUIRE_BACKENDS", "").split(",") if n]
    for name in required:
        assert name in scdp.backends(), f"backend {name} is required but not available"


def test_backends(tiny_model):
    names = scdp.backends()
    assert names[0] == "scalar"
    assert set(names) <= {"scalar", "avx2", "avx512", "amx", "neon", "dot", "i8mm"}
    # "auto" takes the fastest, the last listed.
    assert scdp.Policy(tiny_model).backend == names[-1]
    for name in names:
        assert scdp.Policy(tiny_model, backend=name).backend == name


def test_config_matches_the_toml(models):
    for path in FIXTURES:
        # The one optional key of the config TOML (docs/SPEC.md section 7 has no such field).
        toml = {"backbone_width": 64, **tomllib.loads(fixture_metadata(path)["config"])}
        config = models[path].config
        assert config == scdp.Policy(models[path]).config
        assert config["backbone_norm"] in ("group", "batch")
        for key, value in config.items():
            if isinstance(value, float):
                # Stored as f32.
                assert value == pytest.approx(toml[key], rel=1e-7), key
            else:
                assert value == toml[key], key


def test_model_properties(tiny_model, weights):
    path = weights.for_fixture(TINY)[0]
    assert tiny_model.quant == "f32"
    assert tiny_model.file_bytes == path.stat().st_size
    assert tiny_model.arena_bytes > 0 and tiny_model.arena_bytes % 64 == 0
    assert "32x48" in repr(tiny_model)


def test_float64_and_strided_inputs_match_float32(tiny_model, tiny):
    expected = ready_policy(tiny_model, tiny).infer(noise=tiny["noise"], full=True)
    policy = scdp.Policy(tiny_model)
    policy.set_camera(tiny["camera_k"].astype(np.float64), tiny["camera_t"].T.copy().T)
    for image, state in zip(tiny["images"], tiny["state"]):
        # Strided and Fortran-ordered views: copied, not refused.
        mirrored = np.ascontiguousarray(image[:, ::-1])[:, ::-1]
        strided_state = np.repeat(state.astype(np.float64), 2)[::2]
        policy.push_observation(np.asfortranarray(mirrored), strided_state)
    widened = np.repeat(tiny["noise"].astype(np.float64), 2, axis=0)[::2]
    found = policy.infer(noise=widened, full=True)
    for key in expected:
        np.testing.assert_array_equal(found[key], expected[key])
    # Nested lists for the camera (converted as float64) work too.
    policy.set_camera(tiny["camera_k"].tolist(), tiny["camera_t"].tolist())
    np.testing.assert_array_equal(policy.infer(noise=tiny["noise"]), expected["action"])


def test_policy_keeps_its_model_alive(weights, tiny):
    model = scdp.Model(weights.for_fixture(TINY)[0])
    expected = ready_policy(model, tiny).infer(seed=9)
    policy = ready_policy(model, tiny)
    del model
    gc.collect()
    np.testing.assert_array_equal(policy.infer(seed=9), expected)


def test_policies_in_threads(tiny_model, tiny):
    expected = ready_policy(tiny_model, tiny).infer(seed=21)
    results: list[np.ndarray] = []

    def run():
        policy = ready_policy(tiny_model, tiny)
        for _ in range(5):
            results.append(policy.infer(seed=21))

    threads = [threading.Thread(target=run) for _ in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(results) == 15
    for result in results:
        np.testing.assert_array_equal(result, expected)


def test_import_loads_neither_torch_nor_metaworld():
    heavy = "('torch', 'metaworld', 'mujoco')"
    code = f"import sys, scdp; print(sorted(m for m in {heavy} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    assert out.stdout.strip() == "[]"
