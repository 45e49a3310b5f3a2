"""Single-thread latency of the SCDP policy in PyTorch eager and in ONNX Runtime, next to the
Rust engine, on the same seeded synthetic weights and the same inputs (the golden fixture
`tests/fixtures/golden/<config>/basic.safetensors`). Not run in CI.

    python benches/peer/peer.py                      # PyTorch and ORT, metaworld and panda
    python benches/peer/peer.py --engine             # also `weights-tool run --bench`, and ratios
    python benches/peer/peer.py --flops              # PyTorch's FLOP counter per stage (see macs.rs)
    python benches/peer/peer.py --engine --int8 --ort-int8 --threads 1,2 --no-torch
                                                     # every runtime on 1 and 2 threads

Models are the PyTorch reference of `tests/reference/` (imported, not copied), built as
`generate.py` builds them: synthetic seed-1 weights for the config, float32.

- PyTorch eager: `SCDPPolicy.predict` as the reference runs it (2 frames encoded, then the 10
  DDIM steps with its explicit anchor projection and bilinear sampling), plus its two parts
  timed alone: encoding both frames, and one U-Net evaluation.
- ONNX Runtime: the trunk + projections exported as one graph (both frames as a batch) and one
  U-Net evaluation as another; anchors, bilinear pooling and DDIM in NumPy around ORT.
  Its result is checked against the PyTorch reference before timing.
- ONNX Runtime int8 (`--ort-int8`): both graphs quantized statically (QDQ, int8 weights per
  output channel, uint8 activations calibrated on the fixture's frames and on the U-Net inputs
  of its own f32 denoising loop), its error against PyTorch printed beside its times.
- Engine (`--engine`): `weights-tool synth` + `convert` (f32, and with `--int8` the fast int8 file: 8-bit
  activations in every residual-block layer, rounded to nearest) + `run
  --bench N` on the same fixture; its action_pred is checked against PyTorch too.

`--threads N[,N...]` (default 1) runs everything on each count in turn: torch.set_num_threads(N),
ORT intra_op_num_threads = N (inter_op 1, sequential execution), the engine `--threads N`. Times
are medians of `--runs` runs after warm-up.
"""

from __future__ import annotations

import argparse
import gc
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib

import numpy as np
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, os.path.join(ROOT, "tests", "reference"))
import synthetic  # noqa: E402
from scdp_reference import Z_MIN, RunInputs, SCDPPolicy, ddim_schedule, state_dict_spec  # noqa: E402

WEIGHT_SEED = 1  # the seed of the golden fixtures (generate.py)


def load_cfg(name: str) -> dict:
    with open(os.path.join(ROOT, "tests", "configs", f"{name}.toml"), "rb") as f:
        return tomllib.load(f)


def fixture_path(name: str) -> str:
    return os.path.join(ROOT, "tests", "fixtures", "golden", name, "basic.safetensors")


def load_inputs(name: str) -> RunInputs:
    from safetensors.numpy import load_file

    t = load_file(fixture_path(name))
    return RunInputs(images=t["images"], state=t["state"], noise=t["noise"], camera_k=t["camera_k"],
                     camera_t=t["camera_t"])


def build_policy(cfg: dict) -> SCDPPolicy:
    policy = SCDPPolicy(cfg)
    policy.load_weights(synthetic.generate_state_dict(state_dict_spec(cfg), WEIGHT_SEED, cfg["pos_scale"]))
    return policy


def median_ms(fn, runs: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3


# ------------------------------------------------------------------------------------ FLOPs


def flop_counts(cfg: dict, policy: SCDPPolicy, inp: RunInputs) -> dict[str, int]:
    """torch.utils.flop_counter over one frame's encoding and one U-Net evaluation, per
    top-level stage. FLOPs = 2 x MACs for convolutions and matrix products; transposed
    convolutions are counted over their input positions; nothing else is counted."""
    from torch.utils.flop_counter import FlopCounterMode

    out = {}
    frame = torch.as_tensor(inp.images[:1])
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        policy.features(frame)
    out["encode_frame"] = counter.get_total_flops()
    # Per stage: the trunk's modules called one at a time (features() calls them directly, so
    # the counter cannot name them); their sum is checked against the whole.
    trunk = policy.obs_encoder.backbone
    stages = [("trunk.stem", lambda x: trunk.maxpool(trunk.relu(trunk.bn1(trunk.conv1(x)))))]
    stages += [(f"trunk.layer{i}", getattr(trunk, f"layer{i}")) for i in range(1, 5)]
    x = frame.to(torch.float32).permute(0, 3, 1, 2) / 255.0
    taps = []
    with torch.no_grad():
        for name, stage in stages:
            with FlopCounterMode(display=False) as counter:
                x = stage(x)
            out[name] = counter.get_total_flops()
            taps.append(x)
        with FlopCounterMode(display=False) as counter:
            for proj, tap in zip(policy.obs_encoder.proj, taps):
                proj(tap)
        out["projections"] = counter.get_total_flops()
    assert sum(v for k, v in out.items() if k != "encode_frame") == out["encode_frame"]

    G = cfg["n_obs_steps"] * (5 * cfg["feature_dim"] + cfg["state_dim"])
    sample = torch.as_tensor(inp.noise)[None]
    g = torch.zeros(1, G)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        policy.model(sample, torch.tensor(90.0), g)
    per_module = counter.get_flop_counts()
    out["unet_step"] = counter.get_total_flops()
    # ModuleLists are never called, so their members are the top-level entries.
    patterns = {"diffusion_step_encoder": r"diffusion_step_encoder", "down_modules": r"down_modules\.\d+\.\d+",
                "mid_modules": r"mid_modules\.\d+", "up_modules": r"up_modules\.\d+\.\d+",
                "final_conv": r"final_conv"}
    for name, pattern in patterns.items():
        out[f"unet.{name}"] = sum(sum(counts.values()) for key, counts in per_module.items()
                                  if re.fullmatch(rf"ConditionalUnet1D\.{pattern}", key))
    assert sum(v for k, v in out.items() if k.startswith("unet.")) == out["unet_step"]
    out["unet.film (cond_encoder)"] = sum(sum(counts.values()) for key, counts in per_module.items()
                                          if key.endswith(".cond_encoder"))
    return out


# ------------------------------------------------------------------------------------ ORT


class EncoderGraph(torch.nn.Module):
    """u8 frames [N, H, W, 3] -> the five projected maps [N, d, Hn, Wn]."""

    def __init__(self, policy: SCDPPolicy):
        super().__init__()
        self.policy = policy

    def forward(self, images):
        return tuple(self.policy.features(images))


class UnetGraph(torch.nn.Module):
    """(sample [1, horizon, action_dim], t [1] f32, global_cond [1, G]) -> eps."""

    def __init__(self, policy: SCDPPolicy):
        super().__init__()
        self.unet = policy.model

    def forward(self, sample, t, global_cond):
        return self.unet(sample, t, global_cond)


def export_onnx(policy: SCDPPolicy, cfg: dict, inp: RunInputs, folder: str) -> tuple[str, str]:
    enc_path = os.path.join(folder, "encoder.onnx")
    unet_path = os.path.join(folder, "unet.onnx")
    G = cfg["n_obs_steps"] * (5 * cfg["feature_dim"] + cfg["state_dim"])
    with torch.no_grad():
        torch.onnx.export(EncoderGraph(policy), (torch.as_tensor(inp.images),), enc_path,
                          input_names=["images"], output_names=[f"f{i}" for i in range(1, 6)],
                          opset_version=17, dynamo=False)
        torch.onnx.export(UnetGraph(policy), (torch.as_tensor(inp.noise)[None], torch.tensor([90.0]),
                                              torch.zeros(1, G)), unet_path,
                          input_names=["sample", "t", "global_cond"], output_names=["eps"],
                          opset_version=17, dynamo=False)
    return enc_path, unet_path


def ort_session(path: str, threads: int = 1):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])


class OrtPolicy:
    """The policy around two ORT sessions; anchors, pooling and DDIM in NumPy (float32)."""

    def __init__(self, cfg: dict, policy: SCDPPolicy, enc_path: str, unet_path: str, threads: int = 1):
        self.cfg = cfg
        self.encoder = ort_session(enc_path, threads)
        self.unet = ort_session(unet_path, threads)
        self.unet_inputs = None  # set to a list to record the U-Net's inputs
        nd = policy.normalizer.params_dict
        self.action_scale = nd["action"]["scale"].detach().numpy()
        self.action_offset = nd["action"]["offset"].detach().numpy()
        self.state_scale = nd["agent_pos"]["scale"].detach().numpy()
        self.state_offset = nd["agent_pos"]["offset"].detach().numpy()
        self.ac, self.timesteps, self.ratio = ddim_schedule(cfg)

    def encode(self, images: np.ndarray) -> list[np.ndarray]:
        # [N, d, Hn, Wn] -> [N, Hn, Wn, d] once, so a bilinear tap reads d contiguous values.
        return [np.ascontiguousarray(f.transpose(0, 2, 3, 1)) for f in self.encoder.run(None, {"images": images})]

    def anchors_uv(self, A: np.ndarray, state: np.ndarray, K: np.ndarray, T: np.ndarray):
        cfg = self.cfg
        To, s = cfg["n_obs_steps"], cfg["reconstruction_horizon"]
        a = (A - self.action_offset) / self.action_scale
        steps = a[To - 1:To - 1 + s][:, list(cfg["action_pos_index"])] * np.float32(cfg["pos_scale"])
        start = state[To - 1, list(cfg["state_pos_index"])]
        P = np.concatenate([start[None], start[None] + np.cumsum(steps, axis=0, dtype=np.float32)])
        X = P @ T[:3, :3].T + T[:3, 3]
        valid = np.isfinite(X).all(axis=1) & (X[:, 2] > Z_MIN)
        z = np.where(valid, X[:, 2], 1.0)
        u = np.where(valid, K[0, 0] * X[:, 0] / z + K[0, 2], 0.0)
        v = np.where(valid, K[1, 1] * X[:, 1] / z + K[1, 2], 0.0)
        return u, v, valid

    def context(self, feats: list[np.ndarray], u, v, valid) -> np.ndarray:
        cfg = self.cfg
        H, W = cfg["image_height"], cfg["image_width"]
        npts = u.shape[0]
        parts = []
        for fmap in feats:  # [To, Hn, Wn, d]
            _, Hn, Wn, d = fmap.shape
            x = (u + 0.5) * Wn / W - 0.5
            y = (v + 0.5) * Hn / H - 0.5
            x0, y0 = np.floor(x), np.floor(y)
            fx, fy = x - x0, y - y0
            acc = np.zeros((fmap.shape[0], d), dtype=np.float32)
            for dy, wy in ((0, 1 - fy), (1, fy)):
                for dx, wx in ((0, 1 - fx), (1, fx)):
                    xi, yi = x0 + dx, y0 + dy
                    inside = valid & (xi >= 0) & (xi <= Wn - 1) & (yi >= 0) & (yi <= Hn - 1)
                    w = np.where(inside, wx * wy, 0.0).astype(np.float32)
                    xc = np.clip(xi, 0, Wn - 1).astype(np.int64)
                    yc = np.clip(yi, 0, Hn - 1).astype(np.int64)
                    acc += np.einsum("p,jpc->jc", w, fmap[:, yc, xc, :])
            parts.append(acc / npts)
        return np.concatenate(parts, axis=1)  # [To, 5d]

    def denoise(self, feats, inp: RunInputs) -> np.ndarray:
        cfg = self.cfg
        To = cfg["n_obs_steps"]
        state = inp.state.astype(np.float32)
        K, T = inp.camera_k.astype(np.float32), inp.camera_t.astype(np.float32)
        nstate = state * self.state_scale + self.state_offset
        A = inp.noise.astype(np.float32).copy()
        for t in self.timesteps:
            u, v, valid = self.anchors_uv(A, state, K, T)
            ctx = self.context(feats, u, v, valid)
            g = np.concatenate([np.concatenate([ctx[j], nstate[j]]) for j in range(To)])[None].astype(np.float32)
            feed = {"sample": A[None], "t": np.array([t], dtype=np.float32), "global_cond": g}
            if self.unet_inputs is not None:
                self.unet_inputs.append({key: value.copy() for key, value in feed.items()})
            eps = self.unet.run(None, feed)[0][0]
            a_t = np.float32(self.ac[t])
            a_prev = np.float32(self.ac[t - self.ratio]) if t - self.ratio >= 0 else np.float32(1.0)
            x0 = (A - np.sqrt(1 - a_t) * eps) / np.sqrt(a_t)
            if cfg.get("clip_sample", True):
                x0 = np.clip(x0, -1.0, 1.0)
            A = (np.sqrt(a_prev) * x0 + np.sqrt(1 - a_prev) * eps).astype(np.float32)
        return (A - self.action_offset) / self.action_scale

    def predict(self, inp: RunInputs) -> np.ndarray:
        return self.denoise(self.encode(inp.images), inp)


def quantize_int8(enc_path: str, unet_path: str, ort_f32: "OrtPolicy", inp: RunInputs, folder: str):
    """Static QDQ quantization of both graphs (per-channel int8 weights, uint8 activations),
    calibrated on the fixture's frames and on the U-Net inputs of the f32 loop."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    class Reader(CalibrationDataReader):
        def __init__(self, feeds):
            self.feeds = iter(feeds)

        def get_next(self):
            return next(self.feeds, None)

    ort_f32.unet_inputs = []
    feats = ort_f32.encode(inp.images)
    ort_f32.denoise(feats, inp)
    unet_feeds, ort_f32.unet_inputs = ort_f32.unet_inputs, None
    paths = []
    for path, feeds in ((enc_path, [{"images": inp.images}]), (unet_path, unet_feeds)):
        out = path.replace(".onnx", ".int8.onnx")
        quantize_static(path, out, Reader(feeds), quant_format=QuantFormat.QDQ, per_channel=True,
                        weight_type=QuantType.QInt8, activation_type=QuantType.QUInt8)
        paths.append(out)
    return paths


# ------------------------------------------------------------------------------------ engine


def cargo_weights_tool() -> list[str]:
    subprocess.run(["cargo", "build", "--release", "-q", "-p", "weights-tool"], cwd=ROOT, check=True)
    return [os.path.join(ROOT, "target", "release", "weights-tool")]


def engine_bench(tool: list[str], name: str, folder: str, runs: int, quant: str, threads: int = 1) -> dict:
    config = os.path.join(ROOT, "tests", "configs", f"{name}.toml")
    ckpt = os.path.join(folder, f"{name}.safetensors")
    model = os.path.join(folder, f"{name}.{quant}.scdp")
    out = os.path.join(folder, f"{name}.{quant}.out.safetensors")
    if not os.path.exists(ckpt):
        subprocess.run(tool + ["synth", "--config", config, "--seed", str(WEIGHT_SEED), "-o", ckpt], check=True,
                       capture_output=True)
    # The fast int8 file: 8-bit activations in every residual-block layer. Its rounding does
    # not change its speed, so it is rounded to nearest (no calibration scenes needed).
    int8 = ["--rounding", "nearest", "--activations", "narrow"] if quant == "int8" else []
    if not os.path.exists(model):
        subprocess.run(tool + ["convert", ckpt, "--config", config, "--quant", quant, *int8, "-o", model],
                       check=True, capture_output=True)
    text = subprocess.run(tool + ["run", model, "--inputs", fixture_path(name), "-o", out, "--bench", str(runs),
                                  "--threads", str(threads)],
                          check=True, capture_output=True, text=True).stdout
    stages = {}
    for line in text.splitlines():
        m = re.match(r"\s+(.+?)\s{2,}([0-9.]+)\s+([0-9.]+)$", line)
        if m:
            stages[m.group(1)] = float(m.group(2))
    from safetensors.numpy import load_file

    return {"encode_frame": stages["encode one frame"], "denoise": stages["denoise (all steps)"],
            "full": stages["end to end, all frames"], "action_pred": load_file(out)["action_pred"]}


# ------------------------------------------------------------------------------------ main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--configs", nargs="+", default=["metaworld", "panda"])
    ap.add_argument("--runs", type=int, default=15, help="timed runs per measurement (median)")
    ap.add_argument("--engine", action="store_true", help="also time the Rust engine (weights-tool run --bench)")
    ap.add_argument("--int8", action="store_true", help="with --engine, also the int8 weights file")
    ap.add_argument("--ort-int8", action="store_true", help="also ONNX Runtime on statically quantized graphs")
    ap.add_argument("--no-torch", action="store_true", help="skip PyTorch eager")
    ap.add_argument("--threads", default="1", help="thread counts, comma-separated (each runtime on each)")
    ap.add_argument("--weights-tool", help="weights-tool binary (default: cargo build --release)")
    ap.add_argument("--flops", action="store_true", help="print PyTorch's FLOP counts and exit")
    args = ap.parse_args()
    counts = [int(count) for count in args.threads.split(",")]

    torch.set_num_threads(1)
    torch.set_num_interop_threads(1)
    tool = None
    if args.engine:
        tool = [args.weights_tool] if args.weights_tool else cargo_weights_tool()

    rows = []
    with tempfile.TemporaryDirectory(prefix="scdp-peer-") as folder:
        for name in args.configs:
            cfg = load_cfg(name)
            policy = build_policy(cfg)
            inp = load_inputs(name)
            if args.flops:
                for key, value in flop_counts(cfg, policy, inp).items():
                    print(f"{name:<10} {key:<28} {value:>14} FLOPs = {value // 2:>13} MACs")
                continue
            reference = policy.predict(inp)["action_pred"].numpy()
            images = torch.as_tensor(inp.images)
            G = cfg["n_obs_steps"] * (5 * cfg["feature_dim"] + cfg["state_dim"])
            sample, g = torch.as_tensor(inp.noise)[None], torch.zeros(1, G)
            enc_path, unet_path = export_onnx(policy, cfg, inp, folder)
            graphs = [("ONNX Runtime", enc_path, unet_path)]
            if args.ort_int8:
                graphs.append(("ORT int8", *quantize_int8(enc_path, unet_path, OrtPolicy(cfg, policy, enc_path,
                                                                                          unet_path), inp, folder)))
            frames = cfg["n_obs_steps"]
            steps = cfg["num_inference_steps"]
            for threads in counts:
                torch.set_num_threads(threads)
                if not args.no_torch:
                    with torch.no_grad():
                        torch_full = median_ms(lambda: policy.predict(inp), args.runs)
                        torch_encode = median_ms(lambda: policy.features(images), args.runs)
                        torch_unet = median_ms(lambda: policy.model(sample, torch.tensor(90.0), g), args.runs)
                    rows.append((name, threads, "PyTorch eager", torch_encode, torch_unet, None, torch_full, 0.0))
                ort_fulls = {}
                for label, encoder, unet in graphs:
                    ort_policy = OrtPolicy(cfg, policy, encoder, unet, threads)
                    ort_pred = ort_policy.predict(inp)
                    ort_error = float(np.abs(ort_pred - reference).max())
                    if label == "ONNX Runtime":
                        assert ort_error < 1e-2, f"{name}: ORT disagrees with the PyTorch reference by {ort_error}"
                    feats = ort_policy.encode(inp.images)
                    ort_full = median_ms(lambda: ort_policy.predict(inp), args.runs)
                    ort_encode = median_ms(lambda: ort_policy.encode(inp.images), args.runs)
                    ort_unet = median_ms(lambda: ort_policy.unet.run(None, {
                        "sample": inp.noise[None].astype(np.float32), "t": np.array([90.0], dtype=np.float32),
                        "global_cond": np.zeros((1, G), dtype=np.float32)}), args.runs)
                    ort_denoise = median_ms(lambda: ort_policy.denoise(feats, inp), args.runs)
                    rows.append((name, threads, label, ort_encode, ort_unet, ort_denoise, ort_full, ort_error))
                    ort_fulls[label] = ort_full
                    # Its sessions' pool threads spin for a while after a run: gone before the
                    # next runtime starts, so they do not share its cores.
                    del ort_policy, feats
                    gc.collect()
                engines = [("f32", "engine f32")] + ([("int8", "engine int8")] if args.int8 else [])
                for quant, label in engines if args.engine else []:
                    e = engine_bench(tool, name, folder, args.runs, quant, threads)
                    err = float(np.abs(e["action_pred"] - reference).max())
                    rows.append((name, threads, label, frames * e["encode_frame"], None, e["denoise"], e["full"], err))
                    for peer, full in ort_fulls.items():
                        print(f"{name}, {threads} thread(s): {label} / {peer} = {e['full'] / full:.3f} "
                              f"(end to end, {frames} frames + {steps} steps)", flush=True)
            print(f"{name}: done", file=sys.stderr, flush=True)

    if args.flops:
        return
    print(f"\nmedian of {args.runs} runs; ms. encode = {frames} frames; "
          f"U-Net = one evaluation; denoise = {steps} steps incl. anchors, pooling, DDIM")
    print(f"{'config':<10} {'threads':>7} {'runtime':<14} {'encode':>9} {'U-Net':>9} {'denoise':>9} {'full':>9}"
          f" {'max|d action_pred| vs PyTorch':>30}")
    fmt = lambda x: f"{x:>9.2f}" if x is not None else f"{'-':>9}"  # noqa: E731
    for name, threads, label, enc, unet, den, full, err in rows:
        print(f"{name:<10} {threads:>7} {label:<14} {fmt(enc)} {fmt(unet)} {fmt(den)} {fmt(full)} {err:>30.2e}")


if __name__ == "__main__":
    main()
