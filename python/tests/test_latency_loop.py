"""The closed loop with inference latency (`scdp.metaworld.run_episode`), on a fake scene and
a fake runtime: which actions run, which are given as the committed prefix and the planned
rows, the seam figures and their table. No simulator, no engine."""

from __future__ import annotations

from pathlib import Path

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
    assert "step_mean" not in figures
    assert metaworld.seam_figures(seams, [1.0, 2.0, 6.0])["step_mean"] == pytest.approx(3.0)
    assert metaworld.seam_figures([]) == {"handovers": 0}


def test_steps_within_chunks_leave_the_seams_out():
    scene, runtime = FakeScene(), FakeRuntime()
    within = []
    metaworld.run_episode(scene, runtime, CFG, 7, latency=2, within=within)
    # The fake chunks' rows are (chunk, row): a step inside a chunk moves one row (norm 1),
    # a hand-over changes the chunk too.
    count = CFG["n_action_steps"]
    # Every chunk whose plan ran (the last inference may come after the episode's end).
    assert len(within) in ((count - 1) * len(runtime.calls), (count - 1) * (len(runtime.calls) - 1))
    np.testing.assert_allclose(within, 1.0)


def test_planned_rows_limit_the_old_plan_given():
    scene, runtime = FakeScene(), FakeRuntime()
    metaworld.run_episode(scene, runtime, CFG, 7, latency=2, prefix_mode="replace", planned=True, planned_rows=1)
    assert all(len(planned) == 1 for _, planned in runtime.calls[1:])


def _result(first_seed, successes, failed, jump, handovers, step=None, steps_within=0, rule=("replace", True, 1)):
    prefix, planned, rows = rule
    seams = {"handovers": handovers, "jump_mean": jump, "jump_p95": 2 * jump, "jump_max": 3 * jump,
             "early_step_max_mean": jump, "early_step_max_p95": 1.0, "early_step_max_max": 1.0}
    if step is not None:
        seams.update(step_mean=step, step_count=steps_within)
    return {"task": "t", "latency_steps": 4, "first_seed": first_seed, "episodes": 100, "successes": successes,
            "success_rate": successes / 100, "success_rate_95": [0, 1], "failed_seeds": failed,
            "mean_steps": 10.0 * (1 + first_seed // 1100), "prefix": prefix, "planned": planned,
            "planned_rows": rows, "seams": seams}


def test_adjacent_seed_ranges_of_one_setting_pool():
    parts = [_result(1000, 90, [1003] * 10, 0.1, 100, 0.2, 300), _result(1100, 80, [1105] * 20, 0.4, 300, 0.1, 100),
             _result(1300, 70, [], 0.5, 10), _result(1000, 50, [], 0.9, 10, rule=(None, False, None))]
    pooled = {(r["first_seed"], r["episodes"], metaworld.handover_rule(r)): r
              for r in metaworld.pooled_results(parts)}
    whole = pooled[(1000, 200, "prefix replace + 1 planned row")]
    assert whole["successes"] == 170 and len(whole["failed_seeds"]) == 30
    assert whole["seams"]["handovers"] == 400
    assert whole["seams"]["jump_mean"] == pytest.approx((0.1 * 100 + 0.4 * 300) / 400)
    assert whole["seams"]["step_mean"] == pytest.approx((0.2 * 300 + 0.1 * 100) / 400)
    assert "jump_p95" not in whole["seams"]
    assert whole["mean_steps"] == pytest.approx(15.0)
    low, high = whole["success_rate_95"]
    assert low < 0.85 < high
    # Not adjacent (1200-1299 missing), or another rule: left alone.
    assert pooled[(1300, 100, "prefix replace + 1 planned row")]["successes"] == 70
    assert pooled[(1000, 100, "drop")]["successes"] == 50
    # The parts themselves are not changed.
    assert parts[0]["successes"] == 90 and parts[0]["seams"]["handovers"] == 100


def test_another_policy_of_a_task_is_its_own_setting():
    shipped = _result(1000, 90, [1003] * 10, 0.1, 100)
    retrained = {**_result(1100, 60, [1105] * 40, 0.4, 100), "policy": "prefix-trained"}
    drop = _result(1000, 50, [1001] * 50, 0.2, 100, rule=(None, False, None))
    # Adjacent seeds, same rule: pooled only if the policy is the same.
    assert len(metaworld.pooled_results([shipped, retrained])) == 2
    assert metaworld.policy_label({**shipped, "policy": "metaworld-t"}) == "t"
    retrained = {**retrained, "first_seed": 1000}
    table = metaworld.latency_table_of([shipped, retrained, drop])
    rows = [line for line in table.splitlines() if "prefix replace" in line]
    assert rows[0].startswith("| t | 4 | 1000-1099 |") and "paired" in rows[0]
    # The same seeds, but no dropping run of the retrained policy: it is not compared with
    # the shipped policy's.
    assert rows[1].startswith("| t (prefix-trained) | 4 | 1000-1099 |") and "paired" not in rows[1]


def test_the_documented_latency_table_is_the_shipped_results():
    root = Path(__file__).resolve().parents[2]
    table = metaworld.latency_table(sorted(root.glob("tests/fixtures/trained/**/latency.jsonl")))
    documented = (root / "docs" / "METAWORLD.md").read_text()
    assert table in documented


def test_the_documented_runtime_comparison_is_the_shipped_results():
    root = Path(__file__).resolve().parents[2]
    folder = root / "tests" / "fixtures" / "trained" / "metaworld-push-v3" / "prefix-trained"
    table = metaworld.compare_table(folder / "latency-runtimes.json")
    assert table in (root / "docs" / "METAWORLD.md").read_text()
