"""Writes the small checkpoint containers of weights-tool/tests/containers.rs.

They exercise the container readers, not a model: a handful of keys whose values come from
the synthetic generator (tests/reference/synthetic.py, docs/SYNTHETIC.md) at tiny.toml's
pos_scale, stored the awkward ways PyTorch can store them (transposed and Fortran-order
views, storage offsets, two tensors in one storage, float16 / bfloat16 / float64, int
buffers), inside the containers the tool reads. The Rust test regenerates the values with
`weights_tool::synth::synth_tensor` and compares.

Needs torch, numpy, omegaconf, safetensors and dill (Diffusion Policy saves its workspace
with `pickle_module=dill`). Run from the repository root; the outputs are committed:

    python weights-tool/tests/data/make_containers.py
"""

from __future__ import annotations

import collections
import os
import sys

import dill
import torch
from omegaconf import OmegaConf
from safetensors.torch import save_file

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "..", "tests", "reference"))
from synthetic import generate_tensor  # noqa: E402

POS_SCALE = 0.1  # tiny.toml

# key -> shape; the values are synth(key, seed).
KEYS = {
    "obs_encoder.backbone.conv1.weight": (8, 3, 7, 7),
    "model.diffusion_step_encoder.1.weight": (64, 16),
    "model.final_conv.1.bias": (4,),
    "model.final_conv.1.weight": (4, 16, 1),
    "normalizer.params_dict.action.scale": (4,),
    "obs_encoder.backbone.bn1.running_var": (8,),
}


def synth(key: str, seed: int) -> torch.Tensor:
    return torch.from_numpy(generate_tensor(key, KEYS[key], seed, POS_SCALE))


def awkward_state_dict(seed: int) -> collections.OrderedDict:
    """The KEYS at `seed`, each stored with a different memory layout."""
    sd = collections.OrderedDict()
    conv = synth("obs_encoder.backbone.conv1.weight", seed)
    # Fortran order: strides (1, 8, 24, 168).
    sd["obs_encoder.backbone.conv1.weight"] = conv.permute(3, 2, 1, 0).contiguous().permute(3, 2, 1, 0)
    linear = synth("model.diffusion_step_encoder.1.weight", seed)
    sd["model.diffusion_step_encoder.1.weight"] = linear.t().contiguous().t()  # strides (1, 64)
    # Two tensors in one storage, the second at offset 4.
    bias = synth("model.final_conv.1.bias", seed)
    weight = synth("model.final_conv.1.weight", seed)
    shared = torch.cat([bias, weight.reshape(-1)])
    sd["model.final_conv.1.bias"] = shared[:4]
    sd["model.final_conv.1.weight"] = shared[4:].view(4, 16, 1)
    # A row of a larger matrix: offset 3 * 4 + 0, stride (1,).
    scale = synth("normalizer.params_dict.action.scale", seed)
    rows = torch.zeros(5, 4)
    rows[3] = scale
    sd["normalizer.params_dict.action.scale"] = rows[3]
    sd["obs_encoder.backbone.bn1.running_var"] = synth("obs_encoder.backbone.bn1.running_var", seed)
    sd["obs_encoder.backbone.bn1.num_batches_tracked"] = torch.tensor(17)
    # Stride 0: three copies of one stored element.
    sd["model.expanded.bias"] = torch.tensor([1.5]).expand(3)
    sd["model.counts"] = torch.arange(3, dtype=torch.int32)
    sd._metadata = collections.OrderedDict({"": {"version": 1}})
    return sd


def plain_state_dict(seed: int, dtype: torch.dtype) -> collections.OrderedDict:
    sd = collections.OrderedDict((key, synth(key, seed).to(dtype)) for key in KEYS)
    sd["obs_encoder.backbone.bn1.num_batches_tracked"] = torch.tensor(17)
    return sd


class RunState:
    """A class the tool has never heard of, as a training run would pickle."""

    def __init__(self) -> None:
        self.tags = {"a", "b"}
        self.history = [(1, 0.5), (2, 0.25)]
        self.blob = b"\x00\xff" * 4


# dill pickles a class defined here by value, code objects included, and a code object names
# the file it came from: the absolute path of this script on the machine that ran it. The
# committed checkpoints record the path inside the repository instead.
RunState.__init__.__code__ = RunState.__init__.__code__.replace(
    co_filename="weights-tool/tests/data/make_containers.py"
)


def workspace_payload(with_ema: bool) -> dict:
    cfg = OmegaConf.create({
        "name": "train_scdp",
        "policy": {"horizon": 8, "down_dims": [16, 32, 48], "lr": 1.0e-4},
        "training": {"use_ema": with_ema, "seed": 42, "device": "cuda:0"},
        "checkpoint": None,
    })
    net = torch.nn.Linear(3, 2)
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-3)
    net(torch.ones(1, 3)).sum().backward()
    optimizer.step()
    state_dicts = {"model": awkward_state_dict(seed=2), "optimizer": optimizer.state_dict()}
    if with_ema:
        state_dicts["ema_model"] = awkward_state_dict(seed=1)
    return {
        "cfg": cfg,
        "state_dicts": state_dicts,
        "pickles": {
            "_output_dir": dill.dumps("/data/outputs/2024.01.01/train_scdp"),
            "global_step": dill.dumps(1000),
            "epoch": dill.dumps(10),
        },
        "run_state": RunState(),
    }


def main() -> None:
    out = HERE
    # Diffusion Policy's TrainWorkspace.save_checkpoint: torch.save(payload, f, pickle_module=dill).
    torch.save(workspace_payload(with_ema=True), os.path.join(out, "workspace.ckpt"), pickle_module=dill)
    torch.save(workspace_payload(with_ema=False), os.path.join(out, "workspace_no_ema.ckpt"),
               pickle_module=dill)
    # Protocol 4 brings FRAME, MEMOIZE, SHORT_BINUNICODE and STACK_GLOBAL.
    torch.save(plain_state_dict(seed=1, dtype=torch.float16), os.path.join(out, "state_dict_f16.pt"),
               pickle_protocol=4)
    torch.save(plain_state_dict(seed=1, dtype=torch.float64), os.path.join(out, "state_dict_f64.pt"))
    save_file({key: value.contiguous() for key, value in plain_state_dict(1, torch.bfloat16).items()},
              os.path.join(out, "state_dict_bf16.safetensors"))


if __name__ == "__main__":
    main()
