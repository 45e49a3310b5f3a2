"""Independent PyTorch reference of SCDP inference (the contract is docs/SPEC.md).

Written from docs/SPEC.md, with Diffusion Policy's module layout (real-stanford/diffusion_policy:
ConditionalUnet1D, ConditionalResidualBlock1D, Conv1dBlock, SinusoidalPosEmb, Downsample1d,
Upsample1d) reproduced so that `state_dict()` keys are exactly the checkpoint keys of
docs/SPEC.md section 6. The ResNet-18 trunk is torchvision's own module (or torchvision's BasicBlock at a
scaled width for the `backbone_width` project extension).

Everything that is computed per inference is written out explicitly here: preprocessing,
pyramid taps and projections, anchor reconstruction and projection, bilinear sampling (our own,
not grid_sample), pooling, the global condition and the DDIM loop. The module runs in float64
(the truth) or float32; every input is cast to the run dtype first.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from torchvision.models import resnet18
from torchvision.models.resnet import BasicBlock, conv1x1

Z_MIN = 1e-3
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
# Diffusion Policy's final Conv1dBlock is built without n_groups, i.e. with the default 8
# groups, whatever the residual blocks use (docs/SPEC.md section 4: "Conv1dBlock ... GroupNorm(8)").
FINAL_CONV_GROUPS = 8
# Diffusion Policy's replace_bn_with_gn: GroupNorm(C // 16, C).
GN_FEATURES_PER_GROUP = 16


# --------------------------------------------------------------------------------------------
# config


def normalize_config(cfg: dict) -> dict:
    """Fill project defaults (backbone_width = 64) and check the fields this file relies on."""
    c = dict(cfg)
    c.setdefault("backbone_width", 64)
    c.setdefault("imagenet_norm", False)
    c.setdefault("backbone_norm", "group")
    assert c["backbone_norm"] in ("group", "batch"), c["backbone_norm"]
    assert c.get("prediction_type", "epsilon") == "epsilon"
    assert c.get("beta_schedule", "squaredcos_cap_v2") == "squaredcos_cap_v2"
    assert len(c["down_dims"]) == 3
    return c


# --------------------------------------------------------------------------------------------
# observation encoder


def _replace_bn_with_gn(module: nn.Module) -> None:
    """Swap every BatchNorm2d for GroupNorm(C // 16, C), as Diffusion Policy does."""
    for name, child in list(module.named_children()):
        if isinstance(child, nn.BatchNorm2d):
            c = child.num_features
            setattr(module, name, nn.GroupNorm(c // GN_FEATURES_PER_GROUP, c, eps=1e-5))
        else:
            _replace_bn_with_gn(child)


class ScaledResNet18Trunk(nn.Module):
    """torchvision's ResNet-18 structure (conv1/bn1/relu/maxpool/layer1..4 of BasicBlocks)
    with stage widths w, 2w, 4w, 8w. No avgpool/fc (the policy never uses them)."""

    def __init__(self, width: int):
        super().__init__()
        self.inplanes = width
        self.conv1 = nn.Conv2d(3, width, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._stage(width, 1)
        self.layer2 = self._stage(2 * width, 2)
        self.layer3 = self._stage(4 * width, 2)
        self.layer4 = self._stage(8 * width, 2)

    def _stage(self, planes: int, stride: int) -> nn.Sequential:
        downsample = None
        if stride != 1 or self.inplanes != planes:
            downsample = nn.Sequential(conv1x1(self.inplanes, planes, stride), nn.BatchNorm2d(planes))
        first = BasicBlock(self.inplanes, planes, stride, downsample)
        self.inplanes = planes
        return nn.Sequential(first, BasicBlock(planes, planes))


def build_trunk(width: int, norm: str, force_scaled: bool = False) -> nn.Module:
    if width == 64 and not force_scaled:
        trunk = resnet18(weights=None)
        del trunk.fc  # the policy's backbone has no classifier (Diffusion Policy sets fc = Identity)
        del trunk.avgpool
    else:
        trunk = ScaledResNet18Trunk(width)
    if norm == "group":
        _replace_bn_with_gn(trunk)
    return trunk


def trunk_taps(trunk: nn.Module, x: torch.Tensor) -> list[torch.Tensor]:
    """C1..C5 of docs/SPEC.md section 2.3. C1 = maxpool(relu(norm1(conv1 x)))."""
    h = trunk.maxpool(trunk.relu(trunk.bn1(trunk.conv1(x))))
    taps = [h]
    for layer in (trunk.layer1, trunk.layer2, trunk.layer3, trunk.layer4):
        h = layer(h)
        taps.append(h)
    return taps


class ObsEncoder(nn.Module):
    def __init__(self, cfg: dict):
        super().__init__()
        w = cfg["backbone_width"]
        d = cfg["feature_dim"]
        self.backbone = build_trunk(w, cfg["backbone_norm"])
        chans = [w, w, 2 * w, 4 * w, 8 * w]
        self.proj = nn.ModuleList([nn.Conv2d(c, d, kernel_size=3, padding=1, bias=True) for c in chans])


# --------------------------------------------------------------------------------------------
# ConditionalUnet1D (Diffusion Policy layout, FiLM conditioning)


def mish(x: torch.Tensor) -> torch.Tensor:
    # docs/SPEC.md section 4: Mish(x) = x tanh(softplus(x)), softplus as PyTorch (threshold 20).
    return x * torch.tanh(F.softplus(x))


class Mish(nn.Module):
    def forward(self, x):
        return mish(x)


class SinusoidalPosEmb(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        step = math.log(10000.0) / (half - 1)
        w = torch.exp(torch.arange(half, dtype=t.dtype) * (-step))
        arg = t.reshape(-1, 1) * w.reshape(1, -1)
        return torch.cat([torch.sin(arg), torch.cos(arg)], dim=-1)


class Conv1dBlock(nn.Module):
    def __init__(self, cin: int, cout: int, k: int, n_groups: int):
        super().__init__()
        self.block = nn.Sequential(
            nn.Conv1d(cin, cout, k, padding=k // 2),
            nn.GroupNorm(n_groups, cout, eps=1e-5),
            Mish(),
        )

    def forward(self, x):
        return self.block(x)


class ConditionalResidualBlock1D(nn.Module):
    def __init__(self, cin: int, cout: int, cond_dim: int, k: int, n_groups: int):
        super().__init__()
        self.out_channels = cout
        self.blocks = nn.ModuleList([Conv1dBlock(cin, cout, k, n_groups), Conv1dBlock(cout, cout, k, n_groups)])
        self.cond_encoder = nn.Sequential(Mish(), nn.Linear(cond_dim, 2 * cout))
        self.residual_conv = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        h = self.blocks[0](x)
        film = self.cond_encoder(cond)  # [B, 2 out]
        scale = film[:, : self.out_channels, None]
        bias = film[:, self.out_channels:, None]
        h = scale * h + bias
        h = self.blocks[1](h)
        return h + self.residual_conv(x)


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
    def __init__(self, input_dim: int, global_cond_dim: int, embed_dim: int, down_dims, k: int, n_groups: int):
        super().__init__()
        dims = [input_dim] + list(down_dims)
        pairs = list(zip(dims[:-1], dims[1:]))
        cond_dim = embed_dim + global_cond_dim
        self.diffusion_step_encoder = nn.Sequential(
            SinusoidalPosEmb(embed_dim),
            nn.Linear(embed_dim, 4 * embed_dim),
            Mish(),
            nn.Linear(4 * embed_dim, embed_dim),
        )
        self.down_modules = nn.ModuleList()
        for i, (cin, cout) in enumerate(pairs):
            last = i == len(pairs) - 1
            self.down_modules.append(nn.ModuleList([
                ConditionalResidualBlock1D(cin, cout, cond_dim, k, n_groups),
                ConditionalResidualBlock1D(cout, cout, cond_dim, k, n_groups),
                nn.Identity() if last else Downsample1d(cout),
            ]))
        mid = dims[-1]
        self.mid_modules = nn.ModuleList([
            ConditionalResidualBlock1D(mid, mid, cond_dim, k, n_groups),
            ConditionalResidualBlock1D(mid, mid, cond_dim, k, n_groups),
        ])
        self.up_modules = nn.ModuleList()
        for cin, cout in reversed(pairs[1:]):
            # Diffusion Policy: "is_last = ind >= len(in_out) - 1" is never true here, so both
            # up levels upsample.
            self.up_modules.append(nn.ModuleList([
                ConditionalResidualBlock1D(2 * cout, cin, cond_dim, k, n_groups),
                ConditionalResidualBlock1D(cin, cin, cond_dim, k, n_groups),
                Upsample1d(cin),
            ]))
        d0 = down_dims[0]
        self.final_conv = nn.Sequential(Conv1dBlock(d0, d0, k, FINAL_CONV_GROUPS), nn.Conv1d(d0, input_dim, 1))

    def forward(self, sample: torch.Tensor, t: torch.Tensor, global_cond: torch.Tensor) -> torch.Tensor:
        """sample [B, horizon, action_dim], t scalar tensor, global_cond [B, G] -> [B, horizon, action_dim]."""
        x = sample.transpose(1, 2)
        temb = self.diffusion_step_encoder(t.reshape(1).expand(x.shape[0]))
        cond = torch.cat([temb, global_cond], dim=-1)
        skips = []
        for res1, res2, down in self.down_modules:
            x = res2(res1(x, cond), cond)
            skips.append(x)
            x = down(x)
        for m in self.mid_modules:
            x = m(x, cond)
        for res1, res2, up in self.up_modules:
            x = torch.cat([x, skips.pop()], dim=1)
            x = res2(res1(x, cond), cond)
            x = up(x)
        x = self.final_conv(x)
        return x.transpose(1, 2)


# --------------------------------------------------------------------------------------------
# normalizer


class Normalizer(nn.Module):
    """Only the entries docs/SPEC.md section 6 reads: params_dict.{action,agent_pos}.{scale,offset}."""

    def __init__(self, action_dim: int, state_dim: int):
        super().__init__()

        def entry(n):
            return nn.ParameterDict({
                "scale": nn.Parameter(torch.ones(n), requires_grad=False),
                "offset": nn.Parameter(torch.zeros(n), requires_grad=False),
            })

        self.params_dict = nn.ParameterDict({"action": entry(action_dim), "agent_pos": entry(state_dim)})


# --------------------------------------------------------------------------------------------
# sampling helpers


def bilinear_sample(fmap: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Explicit bilinear sampling with zero padding.

    fmap [C, Hn, Wn]; x, y [P] continuous cell coordinates (cell centres at integers).
    Each of the four neighbouring cells contributes weight * value if it lies on the map and 0
    otherwise. Returns [P, C].
    """
    C, Hn, Wn = fmap.shape
    x0 = torch.floor(x)
    y0 = torch.floor(y)
    fx = x - x0
    fy = y - y0
    out = torch.zeros(x.shape[0], C, dtype=fmap.dtype)
    for dy, wy in ((0, 1.0 - fy), (1, fy)):
        for dx, wx in ((0, 1.0 - fx), (1, fx)):
            xi = x0 + dx
            yi = y0 + dy
            inside = (xi >= 0) & (xi <= Wn - 1) & (yi >= 0) & (yi <= Hn - 1)
            xc = torch.clamp(xi, 0, Wn - 1).to(torch.int64)
            yc = torch.clamp(yi, 0, Hn - 1).to(torch.int64)
            vals = fmap[:, yc, xc].T  # [P, C]
            w = torch.where(inside, wx * wy, torch.zeros_like(wx))
            out = out + w[:, None] * vals
    return out


def ddim_schedule(cfg: dict) -> tuple[np.ndarray, list[int], int]:
    """alphas_cumprod (float32, docs/SPEC.md section 5: betas in f64 stored f32, running product in f32),
    the "leading" timesteps and the step ratio."""
    T = cfg["num_train_timesteps"]
    steps = cfg["num_inference_steps"]

    def abar(x):
        return math.cos((x + 0.008) / 1.008 * math.pi / 2) ** 2

    betas = np.array([min(1 - abar((i + 1) / T) / abar(i / T), 0.999) for i in range(T)], dtype=np.float64)
    betas32 = betas.astype(np.float32)
    ac = np.empty(T, dtype=np.float32)
    p = np.float32(1.0)
    for i in range(T):
        p = np.float32(p * (np.float32(1.0) - betas32[i]))
        ac[i] = p
    ratio = T // steps
    timesteps = [ratio * i for i in range(steps - 1, -1, -1)]
    return ac, timesteps, ratio


def hold_prefix(A: torch.Tensor, prefix_norm: torch.Tensor, planned_norm: torch.Tensor, z: torch.Tensor,
                first: int, mode: str, a_t: float | None) -> torch.Tensor:
    """docs/SPEC.md section 5.1: rows first..first+k of A set to the normalized prefix, or (mode
    "noised", before a step at level a_t) to sqrt(a_t) prefix + sqrt(1 - a_t) z; before a step,
    the m planned rows after them pulled towards sqrt(a_t) planned + sqrt(1 - a_t) z with
    weights (m - j) / (m + 1)."""
    k, m = prefix_norm.shape[0], planned_norm.shape[0]
    if k + m == 0:
        return A
    A = A.clone()
    if a_t is not None:
        a = torch.tensor(a_t, dtype=A.dtype)
    if mode == "noised" and a_t is not None:
        A[first:first + k] = torch.sqrt(a) * prefix_norm + torch.sqrt(1 - a) * z[:k]
    else:
        A[first:first + k] = prefix_norm
    if m and a_t is not None:
        w = torch.tensor([(m - j) / (m + 1) for j in range(m)], dtype=A.dtype)[:, None]
        target = torch.sqrt(a) * planned_norm + torch.sqrt(1 - a) * z[k:]
        A[first + k:first + k + m] = w * target + (1 - w) * A[first + k:first + k + m]
    return A


def ddim_step(A: torch.Tensor, eps: torch.Tensor, t: int, ratio: int, ac: np.ndarray, clip: bool = True):
    """One DDIM (eta = 0) update in A's dtype. Returns (A_prev, x0_raw)."""
    dt = A.dtype
    a_t = torch.tensor(float(ac[t]), dtype=dt)
    a_prev = torch.tensor(float(ac[t - ratio]) if t - ratio >= 0 else 1.0, dtype=dt)
    x0_raw = (A - torch.sqrt(1 - a_t) * eps) / torch.sqrt(a_t)
    x0 = torch.clamp(x0_raw, -1.0, 1.0) if clip else x0_raw
    return torch.sqrt(a_prev) * x0 + torch.sqrt(1 - a_prev) * eps, x0_raw


# --------------------------------------------------------------------------------------------
# the policy


@dataclass
class RunInputs:
    images: np.ndarray  # u8 [To, H, W, 3]
    state: np.ndarray  # f32 [To, state_dim]
    noise: np.ndarray  # f32 [horizon, action_dim]
    camera_k: np.ndarray  # f32 [3, 3]
    camera_t: np.ndarray  # f32 [4, 4]
    prefix: np.ndarray | None = None  # f32 [k, action_dim], committed actions for rows To-1..
    prefix_mode: str = "replace"  # docs/SPEC.md section 5.1: "replace" or "noised"
    planned: np.ndarray | None = None  # f32 [m, action_dim], the old plan for the rows after the prefix


class SCDPPolicy(nn.Module):
    def __init__(self, cfg: dict):
        super().__init__()
        cfg = normalize_config(cfg)
        self.cfg = cfg
        To, d = cfg["n_obs_steps"], cfg["feature_dim"]
        gdim = To * (5 * d + cfg["state_dim"])
        self.obs_encoder = ObsEncoder(cfg)
        self.model = ConditionalUnet1D(cfg["action_dim"], gdim, cfg["diffusion_step_embed_dim"],
                                       cfg["down_dims"], cfg["kernel_size"], cfg["n_groups"])
        self.normalizer = Normalizer(cfg["action_dim"], cfg["state_dim"])
        self.eval()

    # ---- weights

    def load_weights(self, sd: dict) -> None:
        """Load a state dict of numpy arrays / tensors (all keys required, no extras)."""
        tsd = {k: torch.as_tensor(np.asarray(v)) if not torch.is_tensor(v) else v for k, v in sd.items()}
        own = self.state_dict()
        missing = set(own) - set(tsd)
        extra = set(tsd) - set(own)
        assert not missing and not extra, (sorted(missing)[:5], sorted(extra)[:5])
        for k, v in own.items():
            assert tuple(tsd[k].shape) == tuple(v.shape), (k, tsd[k].shape, v.shape)
            src = tsd[k]
            if v.dtype.is_floating_point:
                src = src.to(torch.float64).to(v.dtype)  # exact for f16/bf16/f32 -> f32/f64
            v.copy_(src)

    def as_dtype(self, dtype: torch.dtype) -> "SCDPPolicy":
        return copy.deepcopy(self).to(dtype)

    # ---- stages

    def features(self, images: torch.Tensor) -> list[torch.Tensor]:
        """images u8 [To,H,W,3] -> F_1..F_5, each [To, d, Hn, Wn], in the module's dtype."""
        dt = self.dtype
        x = images.to(dt) / 255.0
        x = x.permute(0, 3, 1, 2)
        if self.cfg["imagenet_norm"]:
            mean = torch.tensor(IMAGENET_MEAN, dtype=dt).reshape(1, 3, 1, 1)
            std = torch.tensor(IMAGENET_STD, dtype=dt).reshape(1, 3, 1, 1)
            x = (x - mean) / std
        taps = trunk_taps(self.obs_encoder.backbone, x)
        return [proj(c) for proj, c in zip(self.obs_encoder.proj, taps)]

    @property
    def dtype(self) -> torch.dtype:
        return self.obs_encoder.proj[0].weight.dtype

    def anchors(self, A: torch.Tensor, state: torch.Tensor, R: torch.Tensor, tvec: torch.Tensor):
        """docs/SPEC.md section 3.1-3.3. Returns (points_cam [s+1,3], valid [s+1] bool, uv [s+1,2] NaN where invalid)."""
        cfg = self.cfg
        To, s = cfg["n_obs_steps"], cfg["reconstruction_horizon"]
        nd = self.normalizer.params_dict["action"]
        a = (A - nd["offset"]) / nd["scale"]
        spi = list(cfg["state_pos_index"])
        api = list(cfg["action_pos_index"])
        pos_scale = torch.tensor(float(np.float32(cfg["pos_scale"])), dtype=A.dtype)
        P = [state[To - 1, spi]]
        for i in range(1, s + 1):
            P.append(P[-1] + pos_scale * a[To - 1 + i - 1, api])
        P = torch.stack(P)  # [s+1, 3]
        X = P @ R.T + tvec  # X = R P + t
        valid = torch.isfinite(X).all(dim=1) & (X[:, 2] > Z_MIN)
        return X, valid

    def project(self, X: torch.Tensor, valid: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        z = torch.where(valid, X[:, 2], torch.ones_like(X[:, 2]))
        u = fx * X[:, 0] / z + cx
        v = fy * X[:, 1] / z + cy
        uv = torch.stack([u, v], dim=1)
        nan = torch.full_like(uv, float("nan"))
        return torch.where(valid[:, None], uv, nan)

    def context(self, feats: list[torch.Tensor], uv: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """docs/SPEC.md section 3.4-3.5: [To, 5d] pooled contexts."""
        cfg = self.cfg
        H, W = cfg["image_height"], cfg["image_width"]
        npts = uv.shape[0]
        uu = torch.where(valid, uv[:, 0], torch.zeros_like(uv[:, 0]))
        vv = torch.where(valid, uv[:, 1], torch.zeros_like(uv[:, 1]))
        ctx = []
        for j in range(cfg["n_obs_steps"]):
            parts = []
            for fmap in feats:
                Hn, Wn = fmap.shape[-2:]
                x = (uu + 0.5) * Wn / W - 0.5
                y = (vv + 0.5) * Hn / H - 0.5
                smp = bilinear_sample(fmap[j], x, y)  # [P, d]
                smp = torch.where(valid[:, None], smp, torch.zeros_like(smp))
                parts.append(smp.sum(dim=0) / npts)
            ctx.append(torch.cat(parts))
        return torch.stack(ctx)

    # ---- full inference

    @torch.no_grad()
    def predict(self, inp: RunInputs, feats: list[torch.Tensor] | None = None,
                noise_override: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        dt = self.dtype
        To = cfg["n_obs_steps"]
        images = torch.as_tensor(inp.images)
        state = torch.as_tensor(inp.state).to(dt)
        noise = torch.as_tensor(inp.noise).to(dt) if noise_override is None else noise_override.to(dt)
        K = torch.as_tensor(inp.camera_k).to(dt)
        Tm = torch.as_tensor(inp.camera_t).to(dt)
        R, tvec = Tm[:3, :3], Tm[:3, 3]
        if feats is None:
            feats = self.features(images)
        sp = self.normalizer.params_dict["agent_pos"]
        nstate = state * sp["scale"] + sp["offset"]
        ac, timesteps, ratio = ddim_schedule(cfg)

        A = noise.clone()
        nd = self.normalizer.params_dict["action"]
        prefix = np.zeros((0, cfg["action_dim"]), np.float32) if inp.prefix is None else inp.prefix
        planned = np.zeros((0, cfg["action_dim"]), np.float32) if inp.planned is None else inp.planned
        prefix_norm = torch.as_tensor(prefix).to(dt) * nd["scale"] + nd["offset"]
        planned_norm = torch.as_tensor(planned).to(dt) * nd["scale"] + nd["offset"]
        z = noise[To - 1: To - 1 + prefix.shape[0] + planned.shape[0]].clone()
        rec = {k: [] for k in ("anchors_uv", "anchors_cam", "valid", "context", "eps", "sample", "x0_raw")}
        for t in timesteps:
            A = hold_prefix(A, prefix_norm, planned_norm, z, To - 1, inp.prefix_mode, float(ac[t]))
            X, valid = self.anchors(A, state, R, tvec)
            uv = self.project(X, valid, K)
            ctx = self.context(feats, uv, valid)
            g = torch.cat([torch.cat([ctx[j], nstate[j]]) for j in range(To)])[None]
            eps = self.model(A[None], torch.tensor(float(t), dtype=dt), g)[0]
            A, x0_raw = ddim_step(A, eps, t, ratio, ac, cfg.get("clip_sample", True))
            for k, v in (("anchors_uv", uv), ("anchors_cam", X), ("valid", valid), ("context", ctx),
                         ("eps", eps), ("sample", A), ("x0_raw", x0_raw)):
                rec[k].append(v)
        A = hold_prefix(A, prefix_norm, planned_norm, z, To - 1, inp.prefix_mode, None)
        action_pred = (A - nd["offset"]) / nd["scale"]
        out = {k: torch.stack(v) for k, v in rec.items()}
        out["action_pred"] = action_pred
        out["action"] = action_pred[To - 1: To - 1 + cfg["n_action_steps"]]
        out["nstate"] = nstate
        # [To, 5, 2, d]: per channel, mean and mean of squares over each map
        out["feature_digest"] = torch.stack(
            [torch.stack([f.mean(dim=(2, 3)), (f * f).mean(dim=(2, 3))], dim=1) for f in feats], dim=1)
        return out


def state_dict_spec(cfg: dict) -> dict:
    """key -> (shape, kind) of the policy's state dict, in module order."""
    m = SCDPPolicy(cfg)
    return {k: (tuple(v.shape), "float" if v.dtype.is_floating_point else "int") for k, v in m.state_dict().items()}
