"""Meta-World as SCDP's paper uses it: the `corner` camera, the gripper's tool centre point as
the reference point, the scripted expert policies for demonstrations.

Frames are rendered off-screen (MuJoCo's OSMesa back-end unless `MUJOCO_GL` says otherwise).
The corner camera is mounted rolled by half a turn, so its raw image shows the scene upside
down; `Scene.render` turns it by 180 degrees, and `Scene.camera_model` describes that
upright image (a half turn about the optical axis is still a rigid camera), so the policy,
its camera model and every picture see the same upright frame.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np  # noqa: E402

CAMERA = "corner"
IMAGE_SIZE = 128
# Robot state, 9 values: the tool centre point (the anchors' origin), then the right and
# left finger pads, all in the world frame (metres), which is the "robot base" frame here.
STATE_DIM = 9


def camera_model(model, data, camera: str, width: int, height: int, turned: bool = False):
    """K and T (camera <- world, OpenCV axes) of a fixed MuJoCo camera for its
    `height x width` image with pixel centres at integer coordinates; with `turned`, for
    that image turned by 180 degrees (`image[::-1, ::-1]`).

    MuJoCo's camera looks down its -z axis with y up; OpenCV's looks down +z with y down, so
    the two frames differ by a half turn about x. The vertical field of view spans the
    image's full height (pixel edges), so f = (height / 2) / tan(fovy / 2) and the centre is
    ((width - 1) / 2, (height - 1) / 2).
    """
    import mujoco

    camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if camera_id < 0:
        raise ValueError(f"no camera named {camera!r}")
    fovy = np.deg2rad(model.cam_fovy[camera_id])
    focal = (height / 2) / np.tan(fovy / 2)
    k = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]])
    # cam_xmat's columns are the camera's axes in the world frame.
    camera_to_world = data.cam_xmat[camera_id].reshape(3, 3)
    rotation = np.diag([1.0, -1.0, -1.0]) @ camera_to_world.T
    if turned:
        # u -> (W - 1) - u and v -> (H - 1) - v: a half turn about the optical axis.
        rotation = np.diag([-1.0, -1.0, 1.0]) @ rotation
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = -rotation @ data.cam_xpos[camera_id]
    return k.astype(np.float32), t.astype(np.float32)


class Scene:
    """One Meta-World task with the goal observable, reset to a seeded random configuration."""

    def __init__(self, task: str, image_size: int = IMAGE_SIZE, camera: str = CAMERA):
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS
        from metaworld.policies import ENV_POLICY_MAP

        if task not in ALL_V3_ENVIRONMENTS:
            raise ValueError(f"unknown Meta-World task {task!r}")
        env = ALL_V3_ENVIRONMENTS[task](
            render_mode="rgb_array", camera_name=camera, width=image_size, height=image_size
        )
        # What Meta-World's goal-observable variants set up, with the per-episode random
        # configuration drawn from the episode's seed instead of a global generator.
        env._partially_observable = False
        # The observation space is cached from the partially observable default, and every
        # step clips the observation to it, which zeroes the goal that the goal-seeking
        # experts (push, pick-place, ...) steer by: drop it, as those variants do.
        env.__dict__.pop("sawyer_observation_space", None)
        env._set_task_called = True
        env._freeze_rand_vec = False
        env.seeded_rand_vec = True
        self.env = env
        self.task = task
        self.camera = camera
        self.image_size = image_size
        self.expert = ENV_POLICY_MAP[task]()
        self.observation = None

    @property
    def max_steps(self) -> int:
        return self.env.max_path_length

    def reset(self, seed: int) -> None:
        self.env.seed(seed)
        self.observation, _ = self.env.reset()

    def step(self, action: np.ndarray) -> bool:
        """Applies one action (clipped to [-1, 1] as the environment expects); True once the
        task is solved."""
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self.observation, _, _, _, info = self.env.step(action)
        return bool(info["success"])

    def expert_action(self) -> np.ndarray:
        return np.clip(self.expert.get_action(self.observation), -1.0, 1.0).astype(np.float32)

    def render(self) -> np.ndarray:
        """The camera's upright image, uint8 [H, W, 3]."""
        return np.ascontiguousarray(self.env.render()[::-1, ::-1])

    def state(self) -> np.ndarray:
        env = self.env
        return np.concatenate(
            [env.tcp_center, env.data.body("rightpad").xpos, env.data.body("leftpad").xpos]
        ).astype(np.float32)

    def camera_model(self) -> tuple[np.ndarray, np.ndarray]:
        size = self.image_size
        return camera_model(self.env.model, self.env.data, self.camera, size, size, turned=True)

    def segmentation(self) -> np.ndarray:
        """Geom id per pixel of the upright image (-1 where nothing), [H, W]."""
        import mujoco

        renderer = mujoco.Renderer(self.env.model, self.image_size, self.image_size)
        try:
            renderer.enable_segmentation_rendering()
            renderer.update_scene(self.env.data, camera=self.camera)
            ids = renderer.render()[..., 0]
        finally:
            renderer.close()
        return np.ascontiguousarray(ids[::-1, ::-1])

    def geom_ids(self, body_names) -> list[int]:
        model = self.env.model
        bodies = {model.body(name).id for name in body_names}
        return [g for g in range(model.ngeom) if model.geom_bodyid[g] in bodies]
