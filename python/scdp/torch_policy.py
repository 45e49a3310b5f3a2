"""SCDP in PyTorch, batched, for training and for the `torch` evaluation runtime.

The module tree (and so `state_dict()` keys) is Diffusion Policy's, the keys the weights tool
reads (docs/SPEC.md section 6): `obs_encoder.backbone.*` (torchvision ResNet-18 with every
BatchNorm replaced by GroupNorm(C/16, C)), `obs_encoder.proj.{0..4}`, `model.*`
(ConditionalUnet1D with FiLM) and `normalizer.params_dict.{action,agent_pos}.{scale,offset}`.

The math is docs/SPEC.md's: the anchors are reconstructed from the current (noisy) sample at
every denoising step, and bilinear sampling is `grid_sample(align_corners=False,
padding_mode="zeros")`, which docs/SPEC.md defines the engine's sampling by. This file imports
torch; nothing else in the package does at import time.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from torchvision.models import resnet18

Z_MIN = 1e-3
# Diffusion Policy's replace_bn_with_gn: GroupNorm(C // 16, C).
FEATURES_PER_GROUP = 16
# Diffusion Policy's final Conv1dBlock uses the default 8 groups whatever n_groups is.
FINAL_CONV_GROUPS = 8


def _replace_batch_norm(module: nn.Module) -> None:
    for name, child in list(module.named_children()):
        if isinstance(child, nn.BatchNorm2d):
            channels = child.num_features
            setattr(module, name, nn.GroupNorm(channels // FEATURES_PER_GROUP, channels))
        else:
            _replace_batch_norm(child)


class ObsEncoder(nn.Module):
    def __init__(self, feature_dim: int):
        super().__init__()
        backbone = resnet18(weights=None)
        del backbone.fc, backbone.avgpool
        _replace_batch_norm(backbone)
        self.backbone = backbone
        self.proj = nn.ModuleList(
            [nn.Conv2d(c, feature_dim, 3, padding=1) for c in (64, 64, 128, 256, 512)]
        )

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        """images float [N, 3, H, W] in [0, 1] -> F_1..F_5, each [N, d, H_n, W_n]."""
        b = self.backbone
        h = b.maxpool(b.relu(b.bn1(b.conv1(images))))
        taps = [h]
        for layer in (b.layer1, b.layer2, b.layer3, b.layer4):
            h = layer(h)
            taps.append(h)
        return [proj(tap) for proj, tap in zip(self.proj, taps)]


class Mish(nn.Module):
    def forward(self, x):
        return F.mish(x)


class SinusoidalPosEmb(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        frequencies = torch.exp(
            torch.arange(half, dtype=torch.float32, device=t.device) * (-math.log(10000.0) / (half - 1))
        )
        argument = t.float()[:, None] * frequencies[None]
        return torch.cat([argument.sin(), argument.cos()], dim=-1)


class Conv1dBlock(nn.Module):
    def __init__(self, cin: int, cout: int, kernel: int, groups: int):
        super().__init__()
        self.block = nn.Sequential(
            nn.Conv1d(cin, cout, kernel, padding=kernel // 2), nn.GroupNorm(groups, cout), Mish()
        )

    def forward(self, x):
        return self.block(x)


class ConditionalResidualBlock1D(nn.Module):
    def __init__(self, cin: int, cout: int, cond_dim: int, kernel: int, groups: int):
        super().__init__()
        self.out_channels = cout
        self.blocks = nn.ModuleList(
            [Conv1dBlock(cin, cout, kernel, groups), Conv1dBlock(cout, cout, kernel, groups)]
        )
        self.cond_encoder = nn.Sequential(Mish(), nn.Linear(cond_dim, 2 * cout))
        self.residual_conv = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x, cond):
        h = self.blocks[0](x)
        film = self.cond_encoder(cond)[:, :, None]
        h = film[:, : self.out_channels] * h + film[:, self.out_channels :]
        return self.blocks[1](h) + self.residual_conv(x)


class Downsample1d(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.conv = nn.Conv1d(dim, dim, 3, stride=2, padding=1)

    def forward(self, x):
        return self.conv(x)


class Upsample1d(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.conv = nn.ConvTranspose1d(dim, dim, 4, stride=2, padding=1)

    def forward(self, x):
        return self.conv(x)


class ConditionalUnet1D(nn.Module):
    def __init__(self, input_dim, global_cond_dim, embed_dim, down_dims, kernel, groups):
        super().__init__()
        dims = [input_dim, *down_dims]
        pairs = list(zip(dims[:-1], dims[1:]))
        cond_dim = embed_dim + global_cond_dim
        self.diffusion_step_encoder = nn.Sequential(
            SinusoidalPosEmb(embed_dim),
            nn.Linear(embed_dim, 4 * embed_dim),
            Mish(),
            nn.Linear(4 * embed_dim, embed_dim),
        )

        def block(cin, cout):
            return ConditionalResidualBlock1D(cin, cout, cond_dim, kernel, groups)

        self.down_modules = nn.ModuleList(
            nn.ModuleList(
                [
                    block(cin, cout),
                    block(cout, cout),
                    nn.Identity() if i == len(pairs) - 1 else Downsample1d(cout),
                ]
            )
            for i, (cin, cout) in enumerate(pairs)
        )
        self.mid_modules = nn.ModuleList([block(dims[-1], dims[-1]), block(dims[-1], dims[-1])])
        self.up_modules = nn.ModuleList(
            nn.ModuleList([block(2 * cout, cin), block(cin, cin), Upsample1d(cin)])
            for cin, cout in reversed(pairs[1:])
        )
        self.final_conv = nn.Sequential(
            Conv1dBlock(down_dims[0], down_dims[0], kernel, FINAL_CONV_GROUPS),
            nn.Conv1d(down_dims[0], input_dim, 1),
        )

    def forward(self, sample, timesteps, global_cond):
        """sample [B, horizon, action_dim], timesteps [B], global_cond [B, G]."""
        x = sample.transpose(1, 2)
        cond = torch.cat([self.diffusion_step_encoder(timesteps), global_cond], dim=-1)
        skips = []
        for first, second, down in self.down_modules:
            x = second(first(x, cond), cond)
            skips.append(x)
            x = down(x)
        for mid in self.mid_modules:
            x = mid(x, cond)
        for first, second, up in self.up_modules:
            x = torch.cat([x, skips.pop()], dim=1)
            x = up(second(first(x, cond), cond))
        return self.final_conv(x).transpose(1, 2)


class Normalizer(nn.Module):
    """Diffusion Policy's LinearNormalizer entries the engine reads: n = x * scale + offset."""

    def __init__(self, action_dim: int, state_dim: int):
        super().__init__()

        def entry(n):
            return nn.ParameterDict(
                {
                    "scale": nn.Parameter(torch.ones(n), requires_grad=False),
                    "offset": nn.Parameter(torch.zeros(n), requires_grad=False),
                }
            )

        self.params_dict = nn.ParameterDict({"action": entry(action_dim), "agent_pos": entry(state_dim)})

    def fit(self, key: str, values: np.ndarray) -> None:
        """Diffusion Policy's "limits" mode: [min, max] -> [-1, 1]; a constant dimension
        (range below 1e-4) is only shifted to 0."""
        low, high = values.min(axis=0), values.max(axis=0)
        span = high - low
        constant = span < 1e-4
        scale = np.where(constant, 1.0, 2.0 / np.where(constant, 1.0, span))
        offset = np.where(constant, -low, -1.0 - scale * low)
        self.params_dict[key]["scale"].data.copy_(torch.as_tensor(scale, dtype=torch.float32))
        self.params_dict[key]["offset"].data.copy_(torch.as_tensor(offset, dtype=torch.float32))

    def normalize(self, key, x):
        entry = self.params_dict[key]
        return x * entry["scale"] + entry["offset"]

    def unnormalize(self, key, x):
        entry = self.params_dict[key]
        return (x - entry["offset"]) / entry["scale"]


def alphas_cumprod(num_train_timesteps: int) -> torch.Tensor:
    """squaredcos_cap_v2 betas in float64, stored float32; running product in float32."""

    def abar(x):
        return math.cos((x + 0.008) / 1.008 * math.pi / 2) ** 2

    betas = np.array(
        [min(1 - abar((i + 1) / num_train_timesteps) / abar(i / num_train_timesteps), 0.999)
         for i in range(num_train_timesteps)],
        dtype=np.float64,
    ).astype(np.float32)
    product = np.cumprod(1.0 - betas, dtype=np.float32)
    return torch.as_tensor(product)


class SCDPPolicy(nn.Module):
    def __init__(self, cfg: dict):
        super().__init__()
        self.cfg = dict(cfg)
        assert cfg.get("backbone_norm", "group") == "group" and not cfg.get("imagenet_norm", False)
        frames, d = cfg["n_obs_steps"], cfg["feature_dim"]
        self.obs_encoder = ObsEncoder(d)
        self.model = ConditionalUnet1D(
            cfg["action_dim"], frames * (5 * d + cfg["state_dim"]), cfg["diffusion_step_embed_dim"],
            cfg["down_dims"], cfg["kernel_size"], cfg["n_groups"],
        )
        self.normalizer = Normalizer(cfg["action_dim"], cfg["state_dim"])
        self.register_buffer("alphas_cumprod", alphas_cumprod(cfg["num_train_timesteps"]), persistent=False)

    # ---- the stages

    def features(self, images: torch.Tensor) -> list[torch.Tensor]:
        """images uint8 [B, To, H, W, 3] -> per level [B, To, d, H_n, W_n]."""
        batch, frames = images.shape[:2]
        x = images.flatten(0, 1).permute(0, 3, 1, 2).float() / 255.0
        return [f.unflatten(0, (batch, frames)) for f in self.obs_encoder(x)]

    def anchors(self, sample, state, camera_k, camera_t):
        """docs/SPEC.md's anchors of the normalized sample [B, horizon, A]: pixel coordinates
        [B, s+1, 2] (zero where invalid) and validity [B, s+1]."""
        cfg = self.cfg
        frames, s = cfg["n_obs_steps"], cfg["reconstruction_horizon"]
        actions = self.normalizer.unnormalize("action", sample)
        steps = actions[:, frames - 1 : frames - 1 + s][:, :, cfg["action_pos_index"]]
        origin = state[:, frames - 1][:, cfg["state_pos_index"]]
        pos_scale = float(np.float32(cfg["pos_scale"]))
        points = torch.cat([origin[:, None], origin[:, None] + pos_scale * steps.cumsum(dim=1)], dim=1)
        rotation, translation = camera_t[:, :3, :3], camera_t[:, :3, 3]
        cam = torch.einsum("bij,bpj->bpi", rotation, points) + translation[:, None]
        valid = torch.isfinite(cam).all(dim=-1) & (cam[..., 2] > Z_MIN)
        depth = torch.where(valid, cam[..., 2], torch.ones_like(cam[..., 2]))
        u = camera_k[:, 0, 0, None] * cam[..., 0] / depth + camera_k[:, 0, 2, None]
        v = camera_k[:, 1, 1, None] * cam[..., 1] / depth + camera_k[:, 1, 2, None]
        uv = torch.stack([u, v], dim=-1)
        uv = torch.where(valid[..., None], uv, torch.zeros_like(uv))
        return uv, valid

    def context(self, features, uv, valid):
        """Pooled features at the anchors: [B, To, 5 d]."""
        cfg = self.cfg
        height, width = cfg["image_height"], cfg["image_width"]
        grid = torch.stack([(2 * uv[..., 0] + 1) / width - 1, (2 * uv[..., 1] + 1) / height - 1], dim=-1)
        weight = valid.to(uv.dtype)[:, None, None, :]
        pooled = []
        for level in features:
            batch, frames = level.shape[:2]
            level_grid = grid[:, None].expand(batch, frames, *grid.shape[1:]).flatten(0, 1)[:, None]
            sampled = F.grid_sample(
                level.flatten(0, 1), level_grid.to(level.dtype), mode="bilinear",
                padding_mode="zeros", align_corners=False,
            )  # [B To, d, 1, P]
            sampled = sampled.unflatten(0, (batch, frames))[:, :, :, 0]  # [B, To, d, P]
            pooled.append((sampled * weight.to(sampled.dtype)).mean(dim=-1))
        return torch.cat(pooled, dim=-1)

    def global_condition(self, features, sample, state, camera_k, camera_t):
        uv, valid = self.anchors(sample, state, camera_k, camera_t)
        context = self.context(features, uv, valid)
        nstate = self.normalizer.normalize("agent_pos", state)
        return torch.cat([context, nstate.to(context.dtype)], dim=-1).flatten(1), uv, valid

    # ---- training

    def loss(self, images, state, actions, camera_k, camera_t, prefix_rows: int = 0) -> torch.Tensor:
        """Epsilon-prediction MSE of one batch: images uint8 [B, To, H, W, 3], state
        [B, To, S], actions [B, horizon, A] (raw units), camera [B, 3, 3] / [B, 4, 4].

        With `prefix_rows` K > 0, half of the windows (drawn per window) hold a committed
        prefix of k rows, k uniform in 1..K, from row To-1 on: those rows are the clean
        actions in the noisy sample, as `predict`'s "replace" rule holds them at every step
        (Diffusion Policy's inpainting, its `condition_mask`), and are left out of the loss."""
        target = self.normalizer.normalize("action", actions)
        noise = torch.randn_like(target)
        timesteps = torch.randint(0, self.cfg["num_train_timesteps"], (target.shape[0],), device=target.device)
        abar = self.alphas_cumprod[timesteps][:, None, None]
        noisy = abar.sqrt() * target + (1 - abar).sqrt() * noise
        free = None
        if prefix_rows:
            batch, horizon = target.shape[:2]
            k = torch.randint(1, prefix_rows + 1, (batch,)) * (torch.rand(batch) < 0.5)
            row = torch.arange(horizon)[None, :] - (self.cfg["n_obs_steps"] - 1)
            held = ((row >= 0) & (row < k[:, None]))[:, :, None].expand_as(target)
            noisy = torch.where(held, target, noisy)
            free = ~held
        features = self.features(images)
        cond, _, _ = self.global_condition(features, noisy, state, camera_k, camera_t)
        eps = self.model(noisy, timesteps, cond)
        if free is None:
            return F.mse_loss(eps.float(), noise)
        return F.mse_loss(eps.float()[free], noise[free])

    # ---- inference (DDIM, eta 0, "leading" timesteps, set_alpha_to_one)

    @torch.no_grad()
    def predict(self, images, state, camera_k, camera_t, noise, record_anchors=False, prefix=None,
                prefix_mode="replace", planned=None):
        """One chunk per batch entry; noise [B, horizon, A] is the initial sample.
        Returns action_pred [B, horizon, A] (raw units) and, when asked, the anchors of
        each step [steps, B, s+1, 2] (NaN where invalid). `prefix` [B, k, A] (raw units):
        actions committed for rows To-1.., held as `prefix_mode` says ("replace": Diffusion
        Policy's inpainting; "noised": at each step's noise level; docs/SPEC.md 5.1); `planned`
        [B, m, A] (raw units): the old plan for the rows after them, which the sample is pulled
        towards with weights (m - j) / (m + 1) at each step's noise level."""
        cfg = self.cfg
        features = self.features(images)
        steps = cfg["num_inference_steps"]
        ratio = cfg["num_train_timesteps"] // steps
        sample = noise.float()
        first = cfg["n_obs_steps"] - 1
        k = 0 if prefix is None else prefix.shape[1]
        m = 0 if planned is None else planned.shape[1]
        rows = slice(first, first + k)
        pulled = slice(first + k, first + k + m)
        if k:
            held = self.normalizer.normalize("action", prefix.float())
            initial = sample[:, rows].clone()
        if m:
            guide = self.normalizer.normalize("action", planned.float())
            guide_noise = sample[:, pulled].clone()
            weight = torch.tensor([(m - j) / (m + 1) for j in range(m)])[None, :, None]
        anchors = []
        for t in range(ratio * (steps - 1), -1, -ratio):
            if k or m:
                a_t = self.alphas_cumprod[t]
                sample = sample.clone()
            if k:
                noised = prefix_mode == "noised"
                sample[:, rows] = a_t.sqrt() * held + (1 - a_t).sqrt() * initial if noised else held
            if m:
                target = a_t.sqrt() * guide + (1 - a_t).sqrt() * guide_noise
                sample[:, pulled] = weight * target + (1 - weight) * sample[:, pulled]
            cond, uv, valid = self.global_condition(features, sample, state, camera_k, camera_t)
            if record_anchors:
                anchors.append(torch.where(valid[..., None], uv, torch.full_like(uv, float("nan"))))
            timesteps = torch.full((sample.shape[0],), t, dtype=torch.long)
            eps = self.model(sample, timesteps, cond)
            a_t = self.alphas_cumprod[t]
            a_prev = self.alphas_cumprod[t - ratio] if t - ratio >= 0 else torch.tensor(1.0)
            x0 = (sample - (1 - a_t).sqrt() * eps) / a_t.sqrt()
            if cfg.get("clip_sample", True):
                x0 = x0.clamp(-1.0, 1.0)
            sample = a_prev.sqrt() * x0 + (1 - a_prev).sqrt() * eps
        if k:
            sample = sample.clone()
            sample[:, rows] = held
        action_pred = self.normalizer.unnormalize("action", sample)
        return (action_pred, torch.stack(anchors)) if record_anchors else action_pred


class EMAModel:
    """Diffusion Policy's EMAModel: decay = 1 - (1 + step / inv_gamma) ** -power, clamped to
    [min_value, max_value], 0 until update_after_step; BatchNorm layers are copied, not
    averaged (there are none here: the trunk uses GroupNorm)."""

    def __init__(self, model: nn.Module, power=0.75, inv_gamma=1.0, min_value=0.0, max_value=0.9999,
                 update_after_step=0):
        import copy

        self.averaged = copy.deepcopy(model).eval().requires_grad_(False)
        self.power, self.inv_gamma = power, inv_gamma
        self.min_value, self.max_value = min_value, max_value
        self.update_after_step = update_after_step
        self.optimization_step = 0

    def decay(self, step: int) -> float:
        step = max(0, step - self.update_after_step - 1)
        if step <= 0:
            return 0.0
        value = 1 - (1 + step / self.inv_gamma) ** -self.power
        return max(self.min_value, min(value, self.max_value))

    @torch.no_grad()
    def step(self, model: nn.Module) -> None:
        decay = self.decay(self.optimization_step)
        for averaged, current in zip(self.averaged.parameters(), model.parameters()):
            if current.requires_grad:
                averaged.mul_(decay).add_(current.detach(), alpha=1 - decay)
            else:
                averaged.copy_(current.detach())
        self.optimization_step += 1
