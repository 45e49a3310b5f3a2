"""Non-degeneracy study for random (synthetic) weights: how often does the DDIM loop saturate?

For every config, seed-1 weights, and a grid of (gain on model.final_conv.1.weight, scale of
the initial noise), run the float64 reference on the `basic` scene and report:
  - eps RMS per step (min / max over the 10 steps),
  - the fraction of x0 entries clipped at each step (mean over steps),
  - the fraction of final normalized actions (A after the last step) with |value| >= 0.999.
Not part of fixture generation; it documents the choice recorded in docs/SYNTHETIC.md and
docs/FIXTURES.md.

    python tests/reference/saturation_study.py [--configs tiny,metaworld,panda] [--seeds 1,2,3]
"""

from __future__ import annotations

import argparse
import os
import sys
import tomllib

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import synthetic  # noqa: E402
from scdp_reference import SCDPPolicy, state_dict_spec  # noqa: E402
from scenes import make_inputs  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
KEY = "model.final_conv.1.weight"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--configs", default="tiny,metaworld,panda")
    ap.add_argument("--gains", default="1,0.5,0.25,0.125,0.0625")
    ap.add_argument("--noise", default="1,0.5,0.25")
    ap.add_argument("--scenes", default="11,12,13", help="scene seeds (noise/image/state draws)")
    args = ap.parse_args()
    torch.set_num_threads(2)
    gains = [float(g) for g in args.gains.split(",")]
    scales = [float(s) for s in args.noise.split(",")]
    print("config     gain    noise  epsRMS(min..max)  x0clip%  final|A|>=0.999 %   (mean over scene seeds; max in [])")
    for name in args.configs.split(","):
        with open(os.path.join(ROOT, "tests", "configs", f"{name}.toml"), "rb") as f:
            cfg = tomllib.load(f)
        spec = state_dict_spec(cfg)
        sd = synthetic.generate_state_dict(spec, 1, cfg["pos_scale"], gains={})
        pol = SCDPPolicy(cfg)
        pol.load_weights(sd)
        pol = pol.as_dtype(torch.float64)
        w0 = pol.model.final_conv[1].weight.detach().clone()
        scenes = []
        for ss in [int(x) for x in args.scenes.split(",")]:
            inp, _ = make_inputs(cfg, name, ss, 1.0)
            scenes.append((inp, pol.features(torch.as_tensor(inp.images))))
        for g in gains:
            with torch.no_grad():
                pol.model.final_conv[1].weight.copy_(w0 * g)  # g is a power of two: exact
            for s in scales:
                rms_lo, rms_hi, clip, sat = [], [], [], []
                for inp, feats in scenes:
                    noise = torch.as_tensor(inp.noise).to(torch.float64) * s
                    out = pol.predict(inp, feats=feats, noise_override=noise)
                    eps = out["eps"].numpy()
                    rms = np.sqrt((eps ** 2).mean(axis=(1, 2)))
                    rms_lo.append(rms.min())
                    rms_hi.append(rms.max())
                    clip.append((np.abs(out["x0_raw"].numpy()) > 1).mean())
                    sat.append((np.abs(out["sample"][-1].numpy()) >= 0.999).mean())
                print(f"{name:10s} {g:<7g} {s:<6g} {np.mean(rms_lo):6.3f}..{np.mean(rms_hi):6.3f}    "
                      f"{100 * np.mean(clip):5.1f}    {100 * np.mean(sat):5.1f} [{100 * np.max(sat):5.1f}]")


if __name__ == "__main__":
    main()
