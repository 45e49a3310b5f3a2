"""The seeded synthetic-weight generator of docs/SYNTHETIC.md (Python side).

Counter-based splitmix64, vectorised with NumPy uint64 arithmetic (which wraps modulo 2^64).
The Rust implementation (`weights_tool::synth`) must agree bit for bit; `weights_sha256`
is the cross-check recorded in every fixture.

Usage as a script prints the cross-check record for a config and seed:

    python tests/reference/synthetic.py tests/configs/tiny.toml 1
"""

from __future__ import annotations

import hashlib
import math
import struct
import sys

import numpy as np

MASK64 = (1 << 64) - 1
FNV_OFFSET = 0xCBF29CE484222325
FNV_PRIME = 0x100000001B3
GOLDEN_GAMMA = 0x9E3779B97F4A7C15

# Gain table of docs/SYNTHETIC.md ("gain(K) is 1 for every key except those listed").
# Keep this dict and the table in the doc identical.
GAINS: dict[str, float] = {}


def fnv1a64(data: bytes) -> int:
    h = FNV_OFFSET
    for b in data:
        h = ((h ^ b) * FNV_PRIME) & MASK64
    return h


def mix64(z: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on a uint64 array (wrapping arithmetic)."""
    z = z.astype(np.uint64, copy=True)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def stream_r(key: str, seed: int, count: int) -> np.ndarray:
    """r_k in [-1, 1) (float64, exact) for elements k = 0..count-1 of tensor `key`."""
    base = (seed & MASK64) ^ fnv1a64(key.encode("utf-8"))
    k1 = np.arange(1, count + 1, dtype=np.uint64)  # k + 1
    with np.errstate(over="ignore"):
        z = np.uint64(base) + k1 * np.uint64(GOLDEN_GAMMA)
        z = mix64(z)
    u = (z >> np.uint64(40)).astype(np.float64) / float(1 << 24)
    return 2.0 * u - 1.0


def value_rule(key: str, shape: tuple[int, ...], r: np.ndarray, pos_scale_f32: float,
               gains: dict[str, float] | None = None) -> np.ndarray:
    """Apply the value table of docs/SYNTHETIC.md (first matching rule wins), in float64."""
    if key.endswith(".running_mean"):
        return 0.1 * r
    if key.endswith(".running_var"):
        return 1.0 + 0.25 * r
    if key == "normalizer.params_dict.action.scale":
        ps = float(np.float32(pos_scale_f32))
        return 25.0 * ps * (1.0 + 0.2 * r)  # evaluated left to right: (25*ps) * (1 + 0.2 r)
    if key == "normalizer.params_dict.agent_pos.scale":
        return 1.0 + 0.2 * r
    if key.startswith("normalizer.params_dict.") and key.endswith(".offset"):
        return 0.1 * r
    if key.endswith(".bias"):
        return 0.1 * r
    if key.endswith(".weight") and len(shape) == 1:
        return 1.0 + 0.1 * r
    if key.endswith(".weight") and len(shape) >= 2:
        fan_in = int(np.prod(shape[1:]))
        gain = (GAINS if gains is None else gains).get(key, 1.0)
        return (gain * r) / math.sqrt(fan_in)
    raise KeyError(f"no synthetic rule for key {key!r} with shape {shape}")


def generate_tensor(key: str, shape: tuple[int, ...], seed: int, pos_scale: float,
                    gains: dict[str, float] | None = None) -> np.ndarray:
    n = int(np.prod(shape)) if len(shape) else 1
    r = stream_r(key, seed, n)
    v = value_rule(key, tuple(shape), r, pos_scale, gains)
    return v.astype(np.float32).reshape(shape)


def generate_state_dict(spec: dict[str, tuple[tuple[int, ...], str]], seed: int, pos_scale: float,
                        gains: dict[str, float] | None = None) -> dict[str, np.ndarray]:
    """spec: key -> (shape, kind) with kind "float" or "int" (num_batches_tracked).

    gains: override of the gain table (None = GAINS, the documented table).
    Returns key -> numpy array (float32, or int64 zeros for num_batches_tracked), in spec order.
    """
    out: dict[str, np.ndarray] = {}
    for key, (shape, kind) in spec.items():
        if key.endswith(".num_batches_tracked"):
            out[key] = np.zeros(shape, dtype=np.int64)
            continue
        if kind != "float":
            raise KeyError(f"unexpected non-float key {key}")
        out[key] = generate_tensor(key, tuple(shape), seed, pos_scale, gains)
    return out


def weights_sha256(state: dict[str, np.ndarray]) -> str:
    """SHA-256 of docs/SYNTHETIC.md "Checksum" over float32 values."""
    h = hashlib.sha256()
    for key in sorted(state.keys(), key=lambda k: k.encode("utf-8")):
        if key.endswith(".num_batches_tracked"):
            continue
        v = np.asarray(state[key])
        if v.dtype != np.float32:
            raise TypeError(f"{key}: checksum is defined over float32 values, got {v.dtype}")
        h.update(key.encode("utf-8"))
        h.update(b"\x00")
        h.update(struct.pack("<Q", v.ndim))
        for d in v.shape:
            h.update(struct.pack("<Q", d))
        h.update(np.ascontiguousarray(v).astype("<f4").tobytes())
    return h.hexdigest()


def f32_hex(x: np.ndarray) -> list[str]:
    return [f"0x{int(b):08x}" for b in np.asarray(x, dtype=np.float32).view(np.uint32).ravel()]


def _main(argv: list[str]) -> None:
    import tomllib

    from scdp_reference import state_dict_spec

    cfg_path = argv[1] if len(argv) > 1 else "tests/configs/tiny.toml"
    seed = int(argv[2]) if len(argv) > 2 else 1
    with open(cfg_path, "rb") as f:
        cfg = tomllib.load(f)
    spec = state_dict_spec(cfg)
    sd = generate_state_dict(spec, seed, cfg["pos_scale"])
    w = sd["obs_encoder.backbone.conv1.weight"].ravel()[:4]
    print(f"config {cfg_path} seed {seed}: {len(sd)} keys, "
          f"{sum(v.size for k, v in sd.items() if v.dtype == np.float32)} float values")
    print("obs_encoder.backbone.conv1.weight[:4] =", [repr(float(x)) for x in w], f32_hex(w))
    print("weights_sha256 =", weights_sha256(sd))


if __name__ == "__main__":
    sys.path.insert(0, __import__("os").path.dirname(__file__))
    _main(sys.argv)
