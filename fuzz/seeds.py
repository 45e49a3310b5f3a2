#!/usr/bin/env python3
"""Writes the committed seed corpus, fuzz/corpus/<target>/seed-*, from scratch.

Run from anywhere: `python3 fuzz/seeds.py`. The inputs follow the layouts documented in
fuzz/src/harness.rs; the weights file layout is docs/FORMAT.md. Offsets into the MICRO
weights files (f32: 861824 bytes, 195 tensors; int8: 254144 bytes, 262 tensors) are those
`weights-tool inspect` prints for them.
"""

import struct
from pathlib import Path

CORPUS = Path(__file__).resolve().parent / "corpus"

# --- weights files (docs/FORMAT.md) -------------------------------------------------------

MASK = (1 << 64) - 1


def checksum(data: bytes) -> int:
    """FNV-1a over little-endian u64 words, the checksum word (bytes 24..32) read as 0."""
    h = 0xCBF29CE484222325
    for index in range(0, len(data), 8):
        word = data[index:index + 8].ljust(8, b"\0")
        value = 0 if index == 24 else int.from_bytes(word, "little")
        h = ((h ^ value) * 0x100000001B3) & MASK
    return h


def header(file_bytes: int, tensors: int) -> bytearray:
    out = bytearray(64)
    out[0:8] = b"SCDPWTS\0"
    struct.pack_into("<IIQ", out, 8, 4, 64, file_bytes)
    struct.pack_into("<IIIII", out, 32, 64, 256, 320, tensors, 0)
    return out


# The MICRO config of fuzz/src/harness.rs, in config-record slot order.
MICRO_SLOTS = [16, 16, 1, 1, 8, 8, 2, 8, 4, 4, 4, 3, 0, 1, 2, 0, 1, 2,
               struct.unpack("<I", struct.pack("<f", 0.1))[0], 8, 8, 8, 8, 3, 4, 100, 2, 1,
               0, 0, 3]


def config_record() -> bytes:
    return struct.pack("<64I", *(MICRO_SLOTS + [0] * (64 - len(MICRO_SLOTS))))


def entry(name: str, dims, offset: int) -> bytes:
    out = bytearray(96)
    out[:len(name)] = name.encode()
    struct.pack_into("<II", out, 56, 0, len(dims))
    struct.pack_into("<4I", out, 64, *(list(dims) + [0] * (4 - len(dims))))
    count = 1
    for d in dims:
        count *= d
    struct.pack_into("<QQ", out, 80, offset, 4 * count)
    return bytes(out)


def finish(data: bytearray) -> bytes:
    struct.pack_into("<Q", data, 24, checksum(bytes(data)))
    return bytes(data)


def load_bytes_seeds():
    yield "empty", b""
    yield "zeros-64", bytes(64)
    # A consistent header alone: the file ends where the config record should be.
    yield "header-only", finish(header(64, 0))
    # Header and config, no tensors: parses, then the model lacks tensor 0.
    data = header(320, 0) + config_record()
    yield "no-tensors", finish(data)
    # One real tensor (the stem convolution, zeros), then the model lacks tensor 1.
    dims = [7, 7, 3, 8]
    data = header(0, 1) + config_record() + entry("backbone.conv1.weight", dims, 448)
    data += bytes(448 - len(data)) + bytes(4 * 7 * 7 * 3 * 8)
    data += bytes(-len(data) % 64)
    struct.pack_into("<Q", data, 16, len(data))
    yield "one-tensor", finish(data)


# --- load_mutated: flags, [u32 length], then (u32 offset, u8 n, n % 8 + 1 bytes) edits ----

MICRO_LEN = 861824


def edit(offset: int, payload: bytes) -> bytes:
    assert 1 <= len(payload) <= 8
    return struct.pack("<IB", offset, len(payload) - 1) + payload


def f32(value: float) -> bytes:
    return struct.pack("<f", value)


def u32(value: int) -> bytes:
    return struct.pack("<I", value)


RUN = 8
INT8 = 16
INT8_LEN = 254144


def load_mutated_seeds():
    yield "unchanged", bytes([0])
    yield "unchanged-run", bytes([RUN])
    for length in (0, 63, 64, 320, 4096, MICRO_LEN - 64, MICRO_LEN + 64):
        yield f"resize-{length}", bytes([1 | RUN]) + u32(length)
    yield "resize-stale-length", bytes([1 | 2]) + u32(MICRO_LEN - 64)
    yield "stale-checksum", bytes([4]) + edit(100_000, b"\x01")
    yield "version-6", bytes([0]) + edit(8, u32(6))
    yield "header-bytes", bytes([0]) + edit(12, u32(65))
    yield "table-offset", bytes([0]) + edit(40, u32(64))
    yield "count-minus-one", bytes([0]) + edit(44, u32(194))
    yield "count-plus-one", bytes([0]) + edit(44, u32(196))
    yield "count-huge", bytes([0]) + edit(44, u32(100_000))
    yield "int8-storage", bytes([0]) + edit(48, u32(1))
    yield "config-bool", bytes([0]) + edit(64 + 2 * 4, u32(2))
    yield "config-horizon", bytes([0]) + edit(64 + 7 * 4, u32(12))
    yield "config-image-size", bytes([RUN]) + edit(64, u32(24) + u32(20))
    yield "config-pos-scale-nan", bytes([RUN]) + edit(64 + 18 * 4, f32(float("nan")))
    yield "config-unused-slot", bytes([0]) + edit(64 + 40 * 4, u32(1))
    table = 320
    yield "entry0-name", bytes([0]) + edit(table, b"X")
    yield "entry0-rank", bytes([0]) + edit(table + 60, u32(5))
    yield "entry0-dims", bytes([0]) + edit(table + 64, u32(3)) + edit(table + 72, u32(7))
    yield "entry0-offset-zero", bytes([0]) + edit(table + 80, struct.pack("<Q", 0))
    yield "entry3-offset-misaligned", bytes([0]) + edit(table + 3 * 96 + 80, b"\x04")
    yield "entry3-offset-beyond", bytes([0]) + edit(table + 3 * 96 + 84, u32(1))
    yield "entry3-len", bytes([0]) + edit(table + 3 * 96 + 88, b"\x00")
    yield "entry-dtype-i8", bytes([0]) + edit(table + 100 * 96 + 56, u32(1))
    # Tensor values the denoiser cannot survive, and ones it can.
    yield "ddim-nan", bytes([RUN]) + edit(861760, f32(float("nan")))
    yield "ddim-inf", bytes([RUN]) + edit(861760 + 4, f32(float("inf")))
    yield "final-bias-huge", bytes([RUN]) + edit(861440, f32(3e38) * 2)
    yield "action-scale-zero", bytes([RUN]) + edit(861504, f32(0.0) * 2)
    yield "state-scale-huge", bytes([RUN]) + edit(861632, f32(3e38) * 2)
    yield "state-offset-nan", bytes([RUN]) + edit(861696, f32(float("nan")))
    yield "stem-weight-huge", bytes([RUN]) + b"".join(
        edit(19072 + 4 * i, f32(3e38) * 2) for i in range(0, 64, 2))
    # The int8 file: int8 kernels with their per-channel scales.
    yield "int8-unchanged-run", bytes([INT8 | RUN])
    for length in (64, 320, INT8_LEN - 64):
        yield f"int8-resize-{length}", bytes([INT8 | 1 | RUN]) + u32(length)
    yield "int8-image-size", bytes([INT8 | RUN]) + edit(64, u32(19) + u32(37))
    layer1_scale = 30848
    for name, value in (("zero", 0.0), ("negative", -1.0), ("nan", float("nan")),
                        ("inf", float("inf")), ("huge", 3e38), ("tiny", 1e-45)):
        yield f"int8-scale-{name}", bytes([INT8 | RUN]) + edit(layer1_scale, f32(value))
    yield "int8-weight-minus-128", bytes([INT8 | RUN]) + edit(30272, b"\x80" * 8)
    yield "int8-film-scale-huge", bytes([INT8 | RUN]) + edit(221696, f32(3e38) * 2)
    yield "int8-dtype-f32", bytes([INT8]) + edit(320 + 10 * 96 + 56, u32(0))


# --- inference: operations (0 camera, 1 push, 2 infer, 3 reset) ---------------------------

FRAME = 16 * 16 * 3
STATE_DIM = 4
SEQUENCE = 8 * 3


def i8(value: float, scale: float = 16.0) -> int:
    return int(round(value * scale)) & 0xFF


def camera(fx=20, fy=20, cx=0.0, cy=0.0, q=(0, 0, 0, 0), t=(0.0, 0.0, 0.0), mode=1,
           perturb=None) -> bytes:
    """Mode 1/2/3 calibration: fx, fy are 1 + byte; cx, cy offsets from 7.5 (in units of
    2/16); q raw quaternion (zeros: identity); t offsets (x, y in 1/128 m, z from 1 m)."""
    out = bytes([0, mode, fx - 1, fy - 1, i8(cx / 2), i8(cy / 2)])
    out += bytes(i8(v) for v in q)
    out += bytes([i8(t[0] * 8), i8(t[1] * 8), i8(t[2] * 4)])
    if mode == 2:
        index, value = perturb
        out += bytes([index, 0]) + f32(value)
    elif mode == 3:
        out += bytes([0])
    return out


def raw_camera(k, t) -> bytes:
    return bytes([0, 0]) + b"".join(f32(v) for v in list(k) + list(t))


def push(image_byte=0x40, state=(0.0, 0.0, 0.0, 0.0), image_len=None, raw_state=False,
         state_len=None) -> bytes:
    out = bytes([1])
    if image_len is None:
        out += bytes([image_byte]) + bytes((image_byte + i) & 0xFF for i in range(FRAME))
    else:
        out += bytes([0xFF]) + struct.pack("<H", image_len) + bytes(image_len)
    if state_len is not None:
        return out + bytes([0xFE, state_len]) + bytes(i8(v, 64) for v in state[:state_len])
    if raw_state:
        return out + bytes([1]) + b"".join(f32(v) for v in state)
    return out + bytes([0]) + bytes(i8(v, 64) for v in state)


NO_PREFIX = bytes([0])
ACTION_DIM = 3
MAX_ROWS = 8 - 2 + 1  # horizon - n_obs_steps + 1


def prefix(rows=0, planned=0, values=None, noised=False, raw=False) -> bytes:
    """Whole rows (modest values, or raw bit patterns with raw=True) of a committed prefix
    then planned rows; values default to a ramp."""
    count = (rows + planned) * ACTION_DIM
    values = values if values is not None else [0.125 * ((i % 7) - 3) for i in range(count)]
    flags = (2 if raw else 1) | (4 if noised else 0)
    out = bytes([flags, rows, planned])
    if raw:
        return out + b"".join(f32(v) for v in values)
    return out + bytes(i8(v, 32) for v in values)


def prefix_lengths(committed, planned=0) -> bytes:
    """Any value counts (modest values): lengths that are not whole rows."""
    return bytes([3, committed, planned]) + bytes(i8(0.25, 32) for _ in range(committed + planned))


def infer_seed(seed=7, after=NO_PREFIX) -> bytes:
    return bytes([2, 0]) + struct.pack("<Q", seed) + after


def infer_given(values=None, raw=False, length=None) -> bytes:
    if length is not None:
        return bytes([2, 3]) + struct.pack("<H", length) + bytes(length) + NO_PREFIX
    values = values if values is not None else [0.25 * ((i % 5) - 2) for i in range(SEQUENCE)]
    if raw:
        return bytes([2, 2]) + b"".join(f32(v) for v in values) + NO_PREFIX
    return bytes([2, 1]) + bytes(i8(v, 32) for v in values) + NO_PREFIX


RESET = bytes([3])
IDENTITY_K = [20, 0, 7.5, 0, 20, 7.5, 0, 0, 1]
IDENTITY_T = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 1, 0, 0, 0, 1]


def inference_seeds():
    for setup, name in ((0, "f32"), (1, "int8"), (2, "f32-scalar"), (3, "int8-scalar")):
        for seed_name, data in plain_inference_seeds():
            if setup == 0 or seed_name in ("seeded", "history", "state-huge", "noise-huge",
                                           "prefix", "prefix-noised-planned"):
                yield f"{name}-{seed_name}", bytes([setup]) + data


def plain_inference_seeds():
    yield "seeded", camera() + push() + infer_seed()
    yield "given", camera() + push() + infer_given()
    yield "history", camera() + push(0x10) + push(0x80, (0.1, -0.1, 0.2, 0.0)) + push(
        0xC0) + infer_seed(1) + RESET + push(0x20) + infer_given()
    yield "rotated", camera(fx=30, fy=25, cx=1.0, cy=-1.0, q=(1, 0.5, -0.25, 0.25),
                            t=(0.1, -0.1, 0.5)) + push() + infer_seed(3)
    yield "behind-camera", camera(t=(0.0, 0.0, -1.5)) + push() + infer_seed(2)
    yield "outside-image", camera(cx=15.0, cy=15.0, fx=250, fy=250) + push(
        state=(1.5, 1.5, 0.0, 0.0)) + infer_seed(2)
    yield "no-camera", push() + infer_seed()
    yield "no-observation", camera() + infer_seed()
    yield "after-reset", camera() + push() + RESET + infer_seed()
    yield "raw-camera", raw_camera(IDENTITY_K, IDENTITY_T) + push() + infer_seed()
    yield "fx-zero", raw_camera([0] + IDENTITY_K[1:], IDENTITY_T) + push() + infer_seed()
    yield "camera-nan", raw_camera(IDENTITY_K, [float("nan")] + IDENTITY_T[1:])
    yield "not-rigid", camera(mode=2, perturb=(9, 2.0)) + push() + infer_seed()
    yield "bad-bottom-row", camera(mode=2, perturb=(21, 0.5)) + push() + infer_seed()
    yield "degenerate-focal", camera(mode=3) + push() + infer_seed()
    yield "image-short", camera() + push(image_len=FRAME - 1) + infer_seed()
    yield "image-two-frames", camera() + push(image_len=2 * FRAME) + infer_seed()
    yield "state-nan", camera() + push(state=(float("nan"), 0, 0, 0), raw_state=True)
    yield "state-inf", camera() + push(state=(0, float("inf"), 0, 0), raw_state=True)
    yield "state-huge", camera() + push(state=(3e38, -3e38, 3e38, 1e38),
                                        raw_state=True) + infer_seed()
    yield "state-short", camera() + push(state_len=3) + infer_seed()
    yield "noise-short", camera() + push() + infer_given(length=SEQUENCE - 1)
    yield "noise-nan", camera() + push() + infer_given(
        [float("nan")] + [0.0] * (SEQUENCE - 1), raw=True)
    yield "noise-huge", camera() + push() + infer_given([3e38] * SEQUENCE, raw=True)
    yield "prefix", camera() + push() + infer_seed(after=prefix(3))
    yield "prefix-noised-planned", camera() + push() + infer_seed(
        after=prefix(2, 3, noised=True))
    yield "prefix-no-rows", camera() + push() + infer_seed(after=prefix(0))
    yield "prefix-whole-horizon", camera() + push() + infer_seed(after=prefix(MAX_ROWS))
    yield "prefix-too-long", camera() + push() + infer_seed(after=prefix(MAX_ROWS, 1))
    yield "prefix-partial-row", camera() + push() + infer_seed(after=prefix_lengths(4))
    yield "prefix-planned-partial-row", camera() + push() + infer_seed(
        after=prefix_lengths(3, 2))
    yield "prefix-nan", camera() + push() + infer_seed(
        after=prefix(1, values=[float("nan"), 0.0, 0.0], raw=True))
    yield "prefix-planned-inf", camera() + push() + infer_seed(
        after=prefix(1, 1, values=[0.0] * 4 + [float("inf"), 0.0], raw=True))
    yield "prefix-huge", camera() + push() + infer_seed(after=prefix(2, values=[3e38] * 6, raw=True))
    yield "prefix-no-camera", push() + infer_seed(after=prefix(2))


def main():
    for target, seeds in (("load_bytes", load_bytes_seeds()),
                          ("load_mutated", load_mutated_seeds()),
                          ("inference", inference_seeds())):
        folder = CORPUS / target
        folder.mkdir(parents=True, exist_ok=True)
        for old in folder.glob("seed-*"):
            old.unlink()
        for name, data in seeds:
            (folder / f"seed-{name}").write_bytes(data)


if __name__ == "__main__":
    main()
