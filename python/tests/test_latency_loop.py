"""The closed loop with inference latency (`scdp.metaworld.run_episode`), on a fake scene and
a fake runtime: which actions run, which are given as the committed prefix and the planned
rows, and the seam figures. No simulator, no engine."""

from __future__ import annotations

import numpy as np
import pytest
from scdp import metaworld

CFG = {"n_obs_steps": 2, "horizon": 16, "n_action_steps": 8, "action_dim": 2}


class FakeScene:
    """Records each executed action; solved after `steps` steps."""

    max_steps = 60

    def __init__(self, steps=1000):
        self.solve_at = steps
        self.executed = []

    def reset(self, seed):
        self.executed = []

    def camera_model(self):
        return np.eye(3, dtype=np.float32), np.eye(4, dtype=np.float32)

    def render(self):
        return np.zeros((4, 4, 3), np.uint8)

    def state(self):
        return np.full(3, len(self.executed), np.float32)

    def step(self, action):
        self.executed.append(np.array(action))
        return len(self.executed) >= self.solve_at


class FakeRuntime:
    """Chunk c's row r is (c, r); records what each inference was given."""

    def __init__(self):
        self.calls = []

    def reset(self, camera_k, camera_t):
        self.chunk = 0

    def push(self, image, state):
        pass

    def infer(self, noise, prefix=None, prefix_mode="replace", planned=None):
        self.calls.append((prefix, planned))
        rows = np.array([[self.chunk, row] for row in range(CFG["horizon"])], np.float32)
        self.chunk += 1
        return rows, np.zeros((1, 1, 2), np.float32)


@pytest.mark.parametrize("latency", [0, 2, 4])
def test_actions_run_and_prefixes_given(latency):
    scene, runtime = FakeScene(), FakeRuntime()
    _, steps, _, seams = metaworld.run_episode(scene, runtime, CFG, 7, latency=latency,
                                               prefix_mode="replace", planned=True)
    executed = np.array(scene.executed)
    assert steps == len(executed) == scene.max_steps
    first, count = CFG["n_obs_steps"] - 1, CFG["n_action_steps"]
    # Chunk 0 runs rows first.., the arm waiting for it; chunk c >= 1 runs rows first+latency..
    # after the old chunk's last `latency` rows ran during its inference.
    expected = [(0, first + row) for row in range(count)]
    chunk = 1
    while len(expected) < len(executed):
        expected += [(chunk, first + latency + row) for row in range(count)]
        chunk += 1
    np.testing.assert_array_equal(executed, np.array(expected[: len(executed)], np.float32))
    # Each later inference got, as its prefix, exactly the old chunk's actions that then ran,
    # and as planned rows the old chunk's rows after them.
    assert runtime.calls[0][0].shape == (0, CFG["action_dim"]) and runtime.calls[0][1] is None
    for c, (prefix, planned) in enumerate(runtime.calls[1:], start=1):
        old_first = first if c == 1 else first + latency
        assert prefix.shape == (latency, CFG["action_dim"])
        # Every chunk's plan runs `count` actions: chunk c - 1's end at c * count.
        np.testing.assert_array_equal(prefix, executed[c * count - latency: c * count])
        old_rest = CFG["horizon"] - (old_first + count)
        assert len(planned) == old_rest
        if old_rest:
            np.testing.assert_array_equal(planned[:, 0], c - 1)
            np.testing.assert_array_equal(planned[:, 1], np.arange(old_first + count, CFG["horizon"]))
    # One seam per hand-over: the old chunk's last action against the new one's first.
    assert len(runtime.calls) - 2 <= len(seams) <= len(runtime.calls) - 1
    old, new = seams[0]
    np.testing.assert_array_equal(old, (0, first + count - 1))
    np.testing.assert_array_equal(new[0], (1, first + latency))


def test_without_prefix_the_runtime_gets_none_and_the_stale_rows_are_dropped():
    scene, runtime = FakeScene(), FakeRuntime()
    metaworld.run_episode(scene, runtime, CFG, 7, latency=3)
    assert all(prefix is None and planned is None for prefix, planned in runtime.calls)
    # Chunk 0's 8 actions, then chunk 1's from row To-1+3: its rows for the 3 steps its
    # inference took are dropped.
    assert tuple(scene.executed[7]) == (0, 1 + 7)
    assert tuple(scene.executed[8]) == (1, 1 + 3)


def test_seam_figures():
    seams = [(np.array([0.0, 0.0]), np.array([[3.0, 4.0], [3.0, 5.0], [3.0, 7.0]])),
             (np.array([1.0, 0.0]), np.array([[1.0, 0.0], [1.0, 1.0]]))]
    figures = metaworld.seam_figures(seams)
    assert figures["handovers"] == 2
    assert figures["jump_mean"] == pytest.approx(2.5)
    assert figures["jump_max"] == pytest.approx(5.0)
    assert figures["early_step_max_mean"] == pytest.approx(1.5)
    assert metaworld.seam_figures([]) == {"handovers": 0}
