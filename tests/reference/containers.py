"""Checkpoint containers for the weights tool, written by PyTorch (not by the project's code).

- workspace.ckpt          Diffusion Policy workspace-style torch.save payload
- state_dict_f16.pt       plain torch.save(state_dict) in float16
- weights_bf16.safetensors  safetensors in bfloat16

`TrainingRunInfo` is the "class the tool does not know" pickled into workspace.ckpt; it lives
in this module so the pickle refers to `containers.TrainingRunInfo`.
"""

from __future__ import annotations

import collections
import pickle

import numpy as np
import torch
from omegaconf import OmegaConf


class TrainingRunInfo:
    """Bookkeeping object a training script might pickle next to its weights."""

    def __init__(self, run_name: str, epoch: int, global_step: int, metrics: dict):
        self.run_name = run_name
        self.epoch = epoch
        self.global_step = global_step
        self.metrics = metrics

    def __eq__(self, other):
        return isinstance(other, TrainingRunInfo) and self.__dict__ == other.__dict__


def module_state_dict(policy_ctor, cfg: dict, weights: dict) -> "collections.OrderedDict[str, torch.Tensor]":
    """A real `nn.Module.state_dict()` (OrderedDict with its `_metadata` attribute) holding `weights`."""
    m = policy_ctor(cfg)
    m.load_weights(weights)
    return m.state_dict()


def workspace_payload(cfg_toml: dict, model_sd, ema_sd) -> dict:
    """Diffusion Policy's BaseWorkspace.save_checkpoint layout: cfg, state_dicts, pickles
    (+ one object of a class defined here).

    In ema_model, two tensors are stored as views so a reader must honour strides and storage
    offsets: `model.diffusion_step_encoder.1.weight` is the transpose of a contiguous buffer
    holding its transpose (strides (1, rows)), and `obs_encoder.proj.0.bias` /
    `obs_encoder.proj.1.bias` are two slices of one shared storage (offsets 0 and d)."""
    ema = collections.OrderedDict(ema_sd)
    ema._metadata = getattr(ema_sd, "_metadata", None)  # keep the state_dict's own metadata
    k = "model.diffusion_step_encoder.1.weight"
    buf = ema[k].t().contiguous()
    ema[k] = buf.t()
    assert not ema[k].is_contiguous() and ema[k].stride() == (1, buf.shape[1])
    b0, b1 = ema["obs_encoder.proj.0.bias"], ema["obs_encoder.proj.1.bias"]
    shared = torch.cat([b0, b1])
    ema["obs_encoder.proj.0.bias"] = shared[: b0.numel()]
    ema["obs_encoder.proj.1.bias"] = shared[b0.numel():]
    assert ema["obs_encoder.proj.1.bias"].storage_offset() == b0.numel()

    cfg = OmegaConf.create({
        "name": "train_scdp_unet_image",
        "_target_": "diffusion_policy.workspace.train_diffusion_unet_hybrid_workspace.TrainDiffusionUnetHybridWorkspace",
        "horizon": cfg_toml["horizon"],
        "n_obs_steps": cfg_toml["n_obs_steps"],
        "n_action_steps": cfg_toml["n_action_steps"],
        "policy": {
            "_target_": "scdp.policy.SpatiallyConditionedDiffusionPolicy",
            "down_dims": list(cfg_toml["down_dims"]),
            "diffusion_step_embed_dim": cfg_toml["diffusion_step_embed_dim"],
            "kernel_size": cfg_toml["kernel_size"],
            "n_groups": cfg_toml["n_groups"],
            "cond_predict_scale": True,
            "noise_scheduler": {
                "_target_": "diffusers.schedulers.scheduling_ddim.DDIMScheduler",
                "num_train_timesteps": cfg_toml["num_train_timesteps"],
                "beta_schedule": cfg_toml["beta_schedule"],
                "clip_sample": cfg_toml["clip_sample"],
                "set_alpha_to_one": True,
                "steps_offset": 0,
                "prediction_type": cfg_toml["prediction_type"],
            },
            "num_inference_steps": cfg_toml["num_inference_steps"],
        },
        "training": {"seed": 42, "num_epochs": 3000, "lr_scheduler": "cosine", "use_ema": True},
        "optimizer": {"_target_": "torch.optim.AdamW", "lr": 1.0e-4, "betas": [0.95, 0.999],
                      "eps": 1.0e-8, "weight_decay": 1.0e-6},
    })
    optimizer = {
        "state": {0: {"step": torch.tensor(12000.0), "exp_avg": torch.zeros(4), "exp_avg_sq": torch.zeros(4)}},
        "param_groups": [{"lr": 1.0e-4, "betas": (0.95, 0.999), "eps": 1e-8, "weight_decay": 1e-6,
                          "amsgrad": False, "initial_lr": 1.0e-4, "params": [0]}],
    }
    return {
        "cfg": cfg,
        "state_dicts": {"model": model_sd, "ema_model": ema, "optimizer": optimizer},
        "pickles": {"_output_dir": pickle.dumps("data/outputs/2024.05.17/12.00.00_train_scdp_unet_image")},
        "run_info": TrainingRunInfo("scdp_tiny_synthetic", epoch=150, global_step=12000,
                                    metrics={"train_loss": 0.0123, "val_loss": 0.0234}),
    }


def to_numpy_state(sd) -> dict[str, np.ndarray]:
    """Tensor state dict (any float dtype) -> numpy float32 values (exact widening) / int64."""
    out = {}
    for k, v in sd.items():
        if v.dtype.is_floating_point:
            out[k] = v.to(torch.float32).contiguous().numpy()
        else:
            out[k] = v.contiguous().numpy()
    return out
