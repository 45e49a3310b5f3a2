"""Self-checks of the reference against independent implementations. Fails loudly (AssertionError).

Run by generate.py before it writes anything; also runnable alone:

    python tests/reference/check_reference.py

Checks and tolerances (max absolute difference unless stated):
  1. synthetic stream: NumPy-vectorised splitmix64 vs a pure-Python scalar implementation
     (exact equality of the f32 bits), plus the cross-check record for tiny seed 1.
  2. DDIM: our loop vs diffusers DDIMScheduler(num_train_timesteps=100, squaredcos_cap_v2,
     clip_sample, set_alpha_to_one, steps_offset=0, epsilon), set_timesteps(10), step() on the
     same eps sequence. Timesteps must equal 90..0 and betas must be bit-identical.
     - with diffusers' own alphas_cumprod injected: float32 bit-identical (tolerance 0).
     - with docs/SPEC.md's float32 running product (differs from diffusers-on-CPU, whose
       torch.cumprod accumulates in double, by up to 5 ulp): float32 <= 5e-6,
       float64 run vs diffusers stepping a float64 sample <= 5e-6 (diffusers keeps its
       coefficients in float32 even for a float64 sample).
  3. ResNet taps: C1..C5 of our trunk vs forward hooks on torchvision's resnet18 (full width,
     GroupNorm built independently through torchvision's norm_layer argument, and eval-mode
     BatchNorm), and our scaled-width builder at width 64 vs torchvision. Relative to the
     tap's max |value|: float64 <= 1e-12, float32 <= 1e-5. Tap shapes for 240x320 must be
     60x80, 60x80, 30x40, 15x20, 8x10.
  4. Bilinear sampling: ours vs F.grid_sample(bilinear, zeros, align_corners=False) with grid
     ((2u+1)/W - 1, (2v+1)/H - 1), points inside, on the border and far outside the map, map
     sizes from 1x2 to 60x80. float64 <= 1e-12; float32 <= 5e-5 (both sides round the sample
     coordinate differently in f32: up to ~1 ulp of a coordinate ~80 times a feature slope).
"""

from __future__ import annotations

import math
import os
import sys
import tomllib

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import synthetic  # noqa: E402
from scdp_reference import (SCDPPolicy, bilinear_sample, build_trunk, ddim_schedule, ddim_step,  # noqa: E402
                            state_dict_spec, trunk_taps)

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TOL = dict(ddim_f32=5e-6, ddim_f64=5e-6, taps_f64=1e-12, taps_f32=1e-5, bilinear_f64=1e-12, bilinear_f32=5e-5)


def load_cfg(name: str) -> dict:
    with open(os.path.join(ROOT, "tests", "configs", f"{name}.toml"), "rb") as f:
        return tomllib.load(f)


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise AssertionError("reference self-check FAILED: " + msg)


# ------------------------------------------------------------------------------------ 1


def check_synthetic(report: dict) -> None:
    M = (1 << 64) - 1

    def scalar(key: str, seed: int, k: int) -> float:
        h = 0xCBF29CE484222325
        for b in key.encode():
            h = ((h ^ b) * 0x100000001B3) & M
        z = ((seed ^ h) + (k + 1) * 0x9E3779B97F4A7C15) & M
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & M
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & M
        z ^= z >> 31
        return 2.0 * ((z >> 40) / 2.0 ** 24) - 1.0

    for key, seed, n in (("obs_encoder.backbone.conv1.weight", 1, 300), ("model.final_conv.1.bias", 2, 40),
                         ("x", (1 << 64) - 1, 70)):
        vec = synthetic.stream_r(key, seed, n)
        ref = np.array([scalar(key, seed, k) for k in range(n)])
        _check(np.array_equal(vec, ref), f"vectorised stream differs from scalar for {key}")
    # the value rules, spot-checked against scalar formulas
    cfg = load_cfg("tiny")
    spec = state_dict_spec(cfg)
    sd = synthetic.generate_state_dict(spec, 1, cfg["pos_scale"])
    w = sd["obs_encoder.backbone.conv1.weight"]
    exp = np.float32(scalar("obs_encoder.backbone.conv1.weight", 1, 5) / math.sqrt(3 * 7 * 7))
    _check(w.ravel()[5] == exp, "conv1 weight rule")
    ps = float(np.float32(cfg["pos_scale"]))
    exp = np.float32(25.0 * ps * (1.0 + 0.2 * scalar("normalizer.params_dict.action.scale", 1, 2)))
    _check(sd["normalizer.params_dict.action.scale"][2] == exp, "action scale rule")
    _check(sd["obs_encoder.backbone.bn1.num_batches_tracked"].dtype == np.int64, "num_batches_tracked")
    first = w.ravel()[:4]
    report["synthetic"] = dict(tiny_seed1_conv1_first4=[repr(float(x)) for x in first],
                               tiny_seed1_conv1_first4_hex=synthetic.f32_hex(first),
                               tiny_seed1_weights_sha256=synthetic.weights_sha256(sd))


# ------------------------------------------------------------------------------------ 2


def check_ddim(report: dict) -> None:
    from diffusers import DDIMScheduler

    cfg = load_cfg("panda")
    ac, timesteps, ratio = ddim_schedule(cfg)

    def sched():
        s = DDIMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2", clip_sample=True,
                          set_alpha_to_one=True, steps_offset=0, prediction_type="epsilon")
        s.set_timesteps(10)
        return s

    s = sched()
    _check(s.timesteps.tolist() == list(range(90, -1, -10)) == timesteps, f"timesteps {s.timesteps.tolist()}")
    T = 100

    def abar(x):
        return math.cos((x + 0.008) / 1.008 * math.pi / 2) ** 2

    betas32 = np.array([min(1 - abar((i + 1) / T) / abar(i / T), 0.999) for i in range(T)]).astype(np.float32)
    _check(np.array_equal(betas32, s.betas.numpy()), "betas differ from diffusers")
    dac = s.alphas_cumprod.numpy()
    ulps = np.abs(ac.astype(np.float64) - dac) / np.spacing(dac)
    report["ddim_alphas_cumprod"] = dict(entries_differing_from_diffusers_cpu=int((ac != dac).sum()),
                                         max_ulp=float(ulps.max()),
                                         max_rel=float((np.abs(ac.astype(np.float64) / dac - 1)).max()))
    _check(ulps.max() <= 16, "alphas_cumprod far from diffusers")

    g = torch.Generator().manual_seed(1234)
    x_init = torch.randn(1, 16, 10, generator=g) * 1.5
    eps_seq = [torch.randn(1, 16, 10, generator=g) for _ in range(10)]

    res = {}
    for label, dtype, table in (("f32_diffusers_alphas", torch.float32, dac), ("f32_spec_alphas", torch.float32, ac),
                                ("f64_spec_alphas", torch.float64, ac)):
        s = sched()
        xd = x_init.to(dtype)
        xm = x_init.to(dtype)
        worst = 0.0
        for t, e in zip(timesteps, eps_seq):
            xd = s.step(e.to(dtype), t, xd).prev_sample
            xm, _ = ddim_step(xm, e.to(dtype), t, ratio, table)
            _check(xd.dtype == dtype, "diffusers changed dtype")
            worst = max(worst, float((xd.double() - xm.double()).abs().max()))
        res[label] = worst
    report["ddim_vs_diffusers_max_abs"] = res
    _check(res["f32_diffusers_alphas"] == 0.0, f"f32 DDIM with diffusers' alphas not bit-identical: {res}")
    _check(res["f32_spec_alphas"] <= TOL["ddim_f32"], f"f32 DDIM vs diffusers: {res}")
    _check(res["f64_spec_alphas"] <= TOL["ddim_f64"], f"f64 DDIM vs diffusers: {res}")


# ------------------------------------------------------------------------------------ 3


def check_taps(report: dict) -> None:
    from torchvision.models import resnet18

    out = {}
    rng = np.random.Generator(np.random.PCG64(7))
    for norm in ("group", "batch"):
        cfg = dict(load_cfg("panda"), backbone_norm=norm)
        spec = {k: v for k, v in state_dict_spec(cfg).items() if k.startswith("obs_encoder.backbone.")}
        sd = synthetic.generate_state_dict(spec, 3, 1.0)
        bsd = {k[len("obs_encoder.backbone."):]: torch.from_numpy(v) for k, v in sd.items()}

        if norm == "group":
            tv = resnet18(weights=None, norm_layer=lambda c: nn.GroupNorm(c // 16, c))
        else:
            tv = resnet18(weights=None)
        missing, unexpected = tv.load_state_dict(bsd, strict=False)
        _check(sorted(missing) == ["fc.bias", "fc.weight"] and not unexpected, f"torchvision keys {missing} {unexpected}")
        ours = build_trunk(64, norm)
        ours.load_state_dict(bsd, strict=True)
        scaled = build_trunk(64, norm, force_scaled=True)
        scaled.load_state_dict(bsd, strict=True)
        _check(list(ours.state_dict()) == list(scaled.state_dict()), "scaled builder key order")
        for m in (tv, ours, scaled):
            m.eval()

        for dtype in (torch.float64, torch.float32):
            H, W = (240, 320) if dtype == torch.float32 else (64, 96)
            x = torch.from_numpy(rng.uniform(-2, 2, size=(2, 3, H, W))).to(dtype)
            tvd, ourd, scd = (m.to(dtype) for m in (tv, ours, scaled))
            hooks, got = [], []
            for mod in (tvd.maxpool, tvd.layer1, tvd.layer2, tvd.layer3, tvd.layer4):
                hooks.append(mod.register_forward_hook(lambda m, i, o: got.append(o.detach().clone())))
            with torch.no_grad():
                tvd(x)
                a = trunk_taps(ourd, x)
                b = trunk_taps(scd, x)
            for h in hooks:
                h.remove()
            if dtype == torch.float32:
                sizes = [tuple(t.shape[-2:]) for t in a]
                _check(sizes == [(60, 80), (60, 80), (30, 40), (15, 20), (8, 10)], f"tap sizes {sizes}")
                _check([t.shape[1] for t in a] == [64, 64, 128, 256, 512], "tap channels")
            tol = TOL["taps_f64"] if dtype == torch.float64 else TOL["taps_f32"]
            worst = 0.0
            for n, (r, p, q) in enumerate(zip(got, a, b)):
                scale = float(r.abs().max())
                e = max(float((r - p).abs().max()), float((r - q).abs().max())) / scale
                worst = max(worst, e)
                _check(e <= tol, f"tap C{n + 1} {norm} {dtype}: rel err {e}")
            out[f"{norm}_{str(dtype)[6:]}_max_rel"] = worst
    report["taps_vs_torchvision"] = out


# ------------------------------------------------------------------------------------ 4


def check_bilinear(report: dict) -> None:
    rng = np.random.Generator(np.random.PCG64(11))
    cases = [((32, 48), (1, 2)), ((32, 48), (2, 3)), ((32, 48), (8, 12)), ((128, 128), (4, 4)),
             ((128, 128), (64, 64)), ((240, 320), (8, 10)), ((240, 320), (60, 80))]
    out = {}
    for dtype in (torch.float64, torch.float32):
        worst = 0.0
        for (H, W), (Hn, Wn) in cases:
            C = 5
            fmap = torch.from_numpy(rng.normal(size=(C, Hn, Wn))).to(dtype)
            n = 400
            u = rng.uniform(-0.25 * W - 3, 1.25 * W + 3, size=n)
            v = rng.uniform(-0.25 * H - 3, 1.25 * H + 3, size=n)
            special_u = [-0.5, 0.0, W - 1.0, W - 0.5, W - 0.25, -0.75, (W - 1) / 2, 3.0, -1e3, 1e4, W + 40.0]
            special_v = [-0.5, 0.0, H - 1.0, H - 0.5, -0.25, H - 0.75, (H - 1) / 2, 5.0, 2e3, -1e4, -30.0]
            u = np.concatenate([u, special_u, np.clip(special_u, 0, W - 1)])
            v = np.concatenate([v, special_v, special_v[::-1]])
            uu = torch.from_numpy(u).to(dtype)
            vv = torch.from_numpy(v).to(dtype)
            x = (uu + 0.5) * Wn / W - 0.5
            y = (vv + 0.5) * Hn / H - 0.5
            ours = bilinear_sample(fmap, x, y)
            grid = torch.stack([(2 * uu + 1) / W - 1, (2 * vv + 1) / H - 1], dim=-1).reshape(1, 1, -1, 2)
            ref = F.grid_sample(fmap[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)
            ref = ref[0, :, 0, :].T
            e = float((ours - ref).abs().max())
            worst = max(worst, e)
            tol = TOL["bilinear_f64"] if dtype == torch.float64 else TOL["bilinear_f32"]
            _check(e <= tol, f"bilinear {dtype} map {Hn}x{Wn} image {H}x{W}: {e}")
            # points far outside must give exactly zero
            far = (np.abs(u) > 5 * W) | (np.abs(v) > 5 * H)
            _check(bool((ours[torch.from_numpy(far)] == 0).all()), "far-outside points must sample 0")
        out[str(dtype)[6:]] = worst
    report["bilinear_vs_grid_sample_max_abs"] = out


# ------------------------------------------------------------------------------------ keys


def check_keys(report: dict) -> None:
    import re
    pats = [r"obs_encoder\.backbone\.(conv1\.weight|bn1\.\w+|layer[1-4]\.[01]\.(conv[12]\.weight|bn[12]\.\w+"
            r"|downsample\.0\.weight|downsample\.1\.\w+))",
            r"obs_encoder\.proj\.[0-4]\.(weight|bias)",
            r"model\.diffusion_step_encoder\.[13]\.(weight|bias)",
            r"model\.(down_modules\.[0-2]\.[01]|mid_modules\.[01]|up_modules\.[01]\.[01])\."
            r"(blocks\.[01]\.block\.[01]\.(weight|bias)|cond_encoder\.1\.(weight|bias)|residual_conv\.(weight|bias))",
            r"model\.down_modules\.[01]\.2\.conv\.(weight|bias)",
            r"model\.up_modules\.[01]\.2\.conv\.(weight|bias)",
            r"model\.final_conv\.0\.block\.[01]\.(weight|bias)",
            r"model\.final_conv\.1\.(weight|bias)",
            r"normalizer\.params_dict\.(action|agent_pos)\.(scale|offset)"]
    rx = re.compile("^(" + "|".join(pats) + ")$")
    counts = {}
    for name in ("tiny", "metaworld", "panda"):
        m = SCDPPolicy(load_cfg(name))
        sd = m.state_dict()
        bad = [k for k in sd if not rx.match(k)]
        _check(not bad, f"{name}: unexpected keys {bad[:5]}")
        _check("model.up_modules.0.2.conv.weight" in sd and "model.up_modules.1.2.conv.weight" in sd, "up convs")
        _check("model.down_modules.2.2.conv.weight" not in sd, "last down level must not downsample")
        _check(isinstance(m.model.up_modules[0][2].conv, nn.ConvTranspose1d), "ConvTranspose1d")
        _check(not any(k.startswith("obs_encoder.backbone.fc") for k in sd), "fc must be absent")
        counts[name] = len(sd)
    report["state_dict_key_counts"] = counts


def run_all(verbose: bool = True) -> dict:
    torch.set_num_threads(2)
    report: dict = {}
    check_synthetic(report)
    check_keys(report)
    check_ddim(report)
    check_bilinear(report)
    check_taps(report)
    if verbose:
        import json
        print("reference self-checks passed; tolerances:", json.dumps(TOL))
        print(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    run_all()
