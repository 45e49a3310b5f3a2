"""Meta-World as the policy sees it: the camera model proven against MuJoCo's own renderer.

At step 0 of a chunk the anchor P0 is the current tool centre point, so its projection
through `Scene.camera_model()` must fall on the gripper in the frame the policy gets. The
segmentation render says which pixels show the gripper's geoms; it is turned like the RGB
frame (`Scene.render`), so both describe one image.
"""

from __future__ import annotations

import numpy as np
import pytest

from scdp import sim

TASK = "button-press-topdown-v3"
# The fingers, and the hand they hang from (from some poses the hand hides the pads).
GRIPPER_BODIES = ("hand", "rightclaw", "rightpad", "leftclaw", "leftpad")
# The tool centre point lies between the finger pads: with the gripper open it is up to about
# 4 pixels from the nearest pad pixel at 128x128. A camera model off by a flip, a turn or a
# transpose lands tens of pixels away.
MAX_DISTANCE_PX = 6.0


def project(camera_k, camera_t, point):
    x = camera_t[:3, :3] @ point + camera_t[:3, 3]
    return np.array([camera_k[0, 0] * x[0] / x[2] + camera_k[0, 2], camera_k[1, 1] * x[1] / x[2] + camera_k[1, 2]])


def distance_to_mask(mask, uv):
    rows, columns = np.nonzero(mask)
    return float(np.min(np.hypot(columns - uv[0], rows - uv[1])))


@pytest.fixture(scope="module")
def scene():
    return sim.Scene(TASK)


# (seed, expert steps taken first): the start, and two poses on the way down to the button
# (on the way up, the arm's own links hide the fingers from this camera).
POSES = [(1000, 0), (1001, 40), (1002, 55)]


@pytest.mark.parametrize("seed, steps", POSES)
def test_tool_centre_point_projects_onto_the_gripper(scene, seed, steps):
    scene.reset(seed)
    for _ in range(steps):
        scene.step(scene.expert_action())
    camera_k, camera_t = scene.camera_model()
    mask = np.isin(scene.segmentation(), scene.geom_ids(GRIPPER_BODIES))
    assert mask.sum() > 10, "the gripper is not in view"
    uv = project(camera_k, camera_t, scene.state()[:3])
    assert distance_to_mask(mask, uv) <= MAX_DISTANCE_PX, (uv, np.argwhere(mask).mean(axis=0)[::-1])
    rows, columns = np.nonzero(mask)
    assert columns.min() - 1 <= uv[0] <= columns.max() + 1, (uv, columns.min(), columns.max())
    # The untouched MuJoCo camera describes the raw, upside-down image instead: through it
    # the same point misses the turned frame's gripper, so the check above can fail.
    raw_k, raw_t = sim.camera_model(scene.env.model, scene.env.data, sim.CAMERA, 128, 128)
    assert distance_to_mask(mask, project(raw_k, raw_t, scene.state()[:3])) > 3 * MAX_DISTANCE_PX


def test_the_frame_is_the_camera_image_turned(scene):
    scene.reset(1000)
    raw = scene.env.render()
    frame = scene.render()
    assert frame.shape == (128, 128, 3) and frame.dtype == np.uint8
    np.testing.assert_array_equal(frame, raw[::-1, ::-1])
    # Upright: the table top is in the lower half of the frame, the button box above it.
    segmentation = scene.segmentation()
    table_rows = np.nonzero(np.isin(segmentation, scene.geom_ids(["tablelink"])))[0]
    box_rows = np.nonzero(np.isin(segmentation, scene.geom_ids(["buttonbox"])))[0]
    assert table_rows.mean() > 64 and box_rows.mean() < table_rows.mean()


def test_state_starts_with_the_tool_centre_point(scene):
    scene.reset(1000)
    state = scene.state()
    assert state.shape == (sim.STATE_DIM,) and state.dtype == np.float32
    np.testing.assert_allclose(state[:3], scene.env.tcp_center, rtol=0, atol=1e-6)


def test_the_goal_stays_observable_after_a_step():
    # Meta-World clips each step's observation to a space cached at construction; unless the
    # scene re-derives it, the goal (the last 3 values) reads zero from the first step on and
    # push's expert, which steers by it, pushes towards the origin.
    scene = sim.Scene("push-v3")
    scene.reset(3)
    goal = np.array(scene.env._target_pos)
    assert np.linalg.norm(goal) > 0.1
    scene.step(np.zeros(4))
    np.testing.assert_allclose(scene.observation[-3:], goal, atol=1e-9)
