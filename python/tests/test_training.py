"""Training with a committed prefix (`SCDPPolicy.loss(prefix_rows=K)`): the held rows reach
the denoiser clean, as the engine's "replace" rule holds them at every step, and only the
other rows are in the loss. Needs PyTorch (the training side), so skipped where it is absent
(CI); run in the training environment."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from scdp.torch_policy import SCDPPolicy  # noqa: E402

CFG = {
    "image_height": 32, "image_width": 32, "imagenet_norm": False, "backbone_norm": "group",
    "feature_dim": 8, "n_obs_steps": 2, "horizon": 16, "n_action_steps": 8,
    "reconstruction_horizon": 8, "state_dim": 9, "action_dim": 4, "state_pos_index": [0, 1, 2],
    "action_pos_index": [0, 1, 2], "pos_scale": 0.01, "down_dims": [16, 32], "diffusion_step_embed_dim": 16,
    "kernel_size": 5, "n_groups": 4, "num_train_timesteps": 100, "num_inference_steps": 10,
    "beta_schedule": "squaredcos_cap_v2", "clip_sample": True, "prediction_type": "epsilon",
}


def batch(size=64):
    generator = torch.Generator().manual_seed(3)
    images = torch.randint(0, 256, (size, 2, 32, 32, 3), dtype=torch.uint8, generator=generator)
    state = torch.rand(size, 2, 9, generator=generator)
    actions = torch.rand(size, 16, 4, generator=generator) * 2 - 1
    camera_k = torch.tensor([[30.0, 0, 16], [0, 30.0, 16], [0, 0, 1]]).expand(size, 3, 3)
    camera_t = torch.eye(4).expand(size, 4, 4).clone()
    camera_t[:, 2, 3] = 1.0
    return images, state, actions, camera_k, camera_t


def observed_loss(prefix_rows):
    """The loss, the denoiser's input sample and the noise it was asked to predict, with the
    denoiser replaced by one that returns zeros (so the loss is the mean square of the noise
    over the rows in it)."""
    torch.manual_seed(0)
    policy = SCDPPolicy(CFG)
    images, state, actions, camera_k, camera_t = batch()
    policy.normalizer.fit("action", actions.flatten(0, 1).numpy())
    policy.normalizer.fit("agent_pos", state.flatten(0, 1).numpy())
    seen = {}

    def denoiser(sample, timesteps, cond):
        seen["sample"] = sample.detach().clone()
        return torch.zeros_like(sample)

    policy.model.forward = denoiser
    original = torch.randn_like

    def noise_like(x):
        seen["noise"] = original(x)
        return seen["noise"]

    torch.randn_like = noise_like
    try:
        loss = policy.loss(images, state, actions, camera_k, camera_t, prefix_rows)
    finally:
        torch.randn_like = original
    return loss, seen["sample"], seen["noise"], policy.normalizer.normalize("action", actions)


def test_without_a_prefix_every_row_is_noised_and_in_the_loss():
    loss, sample, noise, target = observed_loss(0)
    assert not torch.isclose(sample, target).all(dim=-1).any()
    assert torch.isclose(loss, noise.square().mean())


def test_a_prefix_reaches_the_denoiser_clean_and_stays_out_of_the_loss():
    loss, sample, noise, target = observed_loss(7)
    clean = torch.isclose(sample, target).all(dim=-1)  # [B, horizon]
    held = clean.sum(dim=1)
    # Row 0 (before To - 1) is never held; the held rows run from To - 1 without a gap.
    assert not clean[:, 0].any()
    for row_mask, count in zip(clean, held):
        assert row_mask[1 : 1 + count].all() and not row_mask[1 + count :].any()
    # About half the windows hold a prefix, of 1..7 rows.
    assert 16 <= int((held > 0).sum()) <= 48
    assert int(held.max()) <= 7 and set(held[held > 0].tolist()) - set(range(1, 8)) == set()
    free = ~clean[:, :, None].expand_as(noise)
    assert torch.isclose(loss, noise[free].square().mean())
    assert not torch.isclose(loss, noise.square().mean())
