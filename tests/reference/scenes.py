"""Seeded synthetic scenes (images, robot state, camera, initial noise) for the golden fixtures.

Everything is drawn from NumPy `Generator(PCG64(seed))` streams, so a scene is a pure function
of (config, case parameters, seed).
"""

from __future__ import annotations

import numpy as np

from scdp_reference import RunInputs

# Per-config scene geometry (robot base frame, metres). "target" is where the camera looks,
# "ee" the end-effector reference point at the current frame (To-1).
GEOMETRY = {
    "panda": dict(focal=300.0, cam=(1.25, -0.35, 0.85), target=(0.5, 0.0, 0.15), ee=(0.47, 0.04, 0.22), roll=0.04),
    "metaworld": dict(focal=110.0, cam=(0.6, 0.0, 0.75), target=(0.0, 0.6, 0.1), ee=(0.02, 0.62, 0.18), roll=-0.03),
    "tiny": dict(focal=40.0, cam=(1.1, 0.3, 0.7), target=(0.45, 0.0, 0.1), ee=(0.5, -0.03, 0.2), roll=0.05),
}


def look_at(cam: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """Rotation camera <- base (rows: camera x right, y down, z forward; OpenCV), in float64."""
    z = target - cam
    z = z / np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    c, s = np.cos(roll), np.sin(roll)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R = Rz @ R
    # re-orthonormalise (polar decomposition) so R is orthonormal to f64 precision
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def camera_matrices(H: int, W: int, focal: float, R: np.ndarray, cam: np.ndarray):
    K = np.array([[focal, 0.0, (W - 1) / 2.0], [0.0, focal, (H - 1) / 2.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ cam
    return K.astype(np.float32), T.astype(np.float32)


def make_images(rng: np.random.Generator, To: int, H: int, W: int) -> np.ndarray:
    """Smooth gradients plus a few moving shapes (discs, rectangles, a ring), u8 [To,H,W,3]."""
    yy, xx = np.meshgrid(np.arange(H, dtype=np.float64) / H, np.arange(W, dtype=np.float64) / W, indexing="ij")
    base = np.empty((H, W, 3))
    for c in range(3):
        a, b = rng.uniform(-1, 1, size=2)
        ph, fr = rng.uniform(0, 2 * np.pi), rng.uniform(0.5, 2.0)
        base[..., c] = 0.45 + 0.25 * (a * xx + b * yy) + 0.12 * np.sin(2 * np.pi * fr * (xx * b - yy * a) + ph)
    shapes = []
    for _ in range(int(rng.integers(3, 6))):
        shapes.append(dict(kind=int(rng.integers(0, 3)), cx=rng.uniform(0.1, 0.9), cy=rng.uniform(0.1, 0.9),
                           r=rng.uniform(0.06, 0.2), col=rng.uniform(0, 1, 3),
                           vx=rng.uniform(-0.04, 0.04), vy=rng.uniform(-0.04, 0.04)))
    frames = []
    for j in range(To):
        img = base.copy()
        img *= 1.0 + 0.05 * (j - (To - 1))  # slight exposure change between frames
        aspect = W / H
        for s in shapes:
            cx, cy = s["cx"] + j * s["vx"], s["cy"] + j * s["vy"]
            dx, dy = (xx - cx) * aspect, yy - cy
            if s["kind"] == 0:
                m = dx * dx + dy * dy <= s["r"] ** 2
            elif s["kind"] == 1:
                m = (np.abs(dx) <= s["r"]) & (np.abs(dy) <= 0.6 * s["r"])
            else:
                rr = np.sqrt(dx * dx + dy * dy)
                m = (rr <= s["r"]) & (rr >= 0.6 * s["r"])
            img[m] = s["col"]
        frames.append(img)
    return np.clip(np.rint(np.stack(frames) * 255.0), 0, 255).astype(np.uint8)


def camera_rotation(geom_name: str) -> tuple[np.ndarray, np.ndarray]:
    g = GEOMETRY[geom_name]
    cam = np.array(g["cam"], dtype=np.float64)
    return look_at(cam, np.array(g["target"], dtype=np.float64), g["roll"]), cam


def make_inputs(cfg: dict, geom_name: str, seed: int, noise_scale: float = 1.0, *, image_seed: int | None = None,
                ee_cam: tuple[float, float, float] | None = None) -> tuple[RunInputs, dict]:
    """A full run input for the config's scene geometry.

    seed drives the state and the noise, image_seed (default: seed) the images. ee_cam, when
    given, places the end-effector point at these camera-frame coordinates instead of the
    geometry's "ee" (used by the edge case). Returns (inputs, info)."""
    g = GEOMETRY[geom_name]
    H, W = cfg["image_height"], cfg["image_width"]
    To, sd, ad = cfg["n_obs_steps"], cfg["state_dim"], cfg["action_dim"]
    image_seed = seed if image_seed is None else image_seed
    rng_img = np.random.Generator(np.random.PCG64(image_seed * 1000 + 1))
    rng_state = np.random.Generator(np.random.PCG64(seed * 1000 + 2))
    rng_noise = np.random.Generator(np.random.PCG64(seed * 1000 + 3))
    images = make_images(rng_img, To, H, W)
    R, cam = camera_rotation(geom_name)
    K, T = camera_matrices(H, W, g["focal"], R, cam)
    if ee_cam is None:
        ee = np.array(g["ee"], dtype=np.float64)
    else:
        ee = cam + R.T @ np.array(ee_cam, dtype=np.float64)
    state = rng_state.uniform(-1.0, 1.0, size=(To, sd))
    for j in range(To):
        # the end effector moved ~1 cm per frame towards "now"
        state[j, list(cfg["state_pos_index"])] = ee + (j - (To - 1)) * np.array([0.008, -0.005, 0.004])
    noise = rng_noise.standard_normal((cfg["horizon"], ad))
    noise32 = (noise * noise_scale).astype(np.float32)
    inp = RunInputs(images=images, state=state.astype(np.float32), noise=noise32, camera_k=K, camera_t=T)
    info = dict(R64_orthonormality=float(np.abs(T[:3, :3].astype(np.float64) @ T[:3, :3].astype(np.float64).T
                                                  - np.eye(3)).max()))
    return inp, info
