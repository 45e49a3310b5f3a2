"""The trained Meta-World policies that ship in tests/fixtures/trained/: the engine against
PyTorch on the torch rollouts' own recorded inputs, and the int8 policy in closed loop.

Each folder holds the training checkpoint (`checkpoint.ckpt`, the EMA weights in float16),
the int8 weights file made from it, the figures `eval` measured (`eval.json`) and recorded
observations (`observations/*.safetensors`: run files with the torch output). The f32
weights file is made here from the checkpoint by `weights-tool convert`, as a user would.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import scdp
from safetensors.numpy import load_file

ROOT = Path(__file__).resolve().parents[2]
TRAINED = sorted((ROOT / "tests" / "fixtures" / "trained").glob("metaworld-*"))
# Closed-loop smoke test: episodes of the int8 policy, on seeds far from the evaluation's.
SMOKE_EPISODES = 10
SMOKE_FIRST_SEED = 5000
# The agreement budget of an int8 file with PyTorch, normalized action units: the project's
# int8 fidelity floor.
INT8_AGREEMENT_MAX = 0.02
INT8_AGREEMENT_MEAN = 0.005


def task_of(folder: Path) -> str:
    return folder.name.removeprefix("metaworld-")


def evaluations(folder: Path) -> dict:
    return {entry["runtime"]: entry for entry in json.loads((folder / "eval.json").read_text())}


@pytest.fixture(scope="session")
def f32_weights(weights_tool: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[Path, Path]:
    out = {}
    for folder in TRAINED:
        target = tmp_path_factory.mktemp(folder.name) / "f32.scdp"
        subprocess.run(
            [str(weights_tool), "convert", str(folder / "checkpoint.ckpt"), "--config",
             str(folder / "model.toml"), "-o", str(target)],
            check=True, capture_output=True,
        )
        out[folder] = target
    return out


def test_a_trained_policy_ships():
    assert TRAINED, "no tests/fixtures/trained/metaworld-* folder"
    for folder in TRAINED:
        assert len(list((folder / "observations").glob("*.safetensors"))) >= 4


# Shipped int8 files whose largest error on their rollouts is over INT8_AGREEMENT_MAX, and
# why they ship: each is measured and stated in docs/METAWORLD.md, and still held to the
# mean budget and to PyTorch's success (test_engine_succeeds_as_often_as_torch).
OVER_THE_MAX = {
    # Max 0.095 in 69 of 4,506 chunks, 62 of them an episode's first three (the approach to
    # the puck); the most precise int8 file measured (every trunk layer refined, 15-bit
    # codes) still has 37; success paired with PyTorch +0.010 (-0.017 .. +0.037).
    "metaworld-push-v3",
}


@pytest.mark.parametrize("folder", TRAINED, ids=lambda f: f.name)
def test_shipped_int8_agreement_is_within_the_budget(folder):
    """The evaluation recorded beside each shipped int8 file (`eval --runtime torch
    --agreement`, every inference of its torch rollouts) is within the budget: a file
    converted or evaluated again must still meet it to ship. A file in OVER_THE_MAX is held
    to the mean only, and must still be over the max (else it belongs with the others)."""
    agreement = evaluations(folder)["torch"]["agreement"]["engine-int8"]
    assert agreement["inferences"] >= 500, agreement
    assert agreement["mean"] <= INT8_AGREEMENT_MEAN, agreement
    if folder.name in OVER_THE_MAX:
        assert agreement["max"] > INT8_AGREEMENT_MAX, agreement
    else:
        assert agreement["max"] <= INT8_AGREEMENT_MAX, agreement


@pytest.mark.parametrize("quant", ["f32", "int8"])
@pytest.mark.parametrize("folder", TRAINED, ids=lambda f: f.name)
def test_engine_reproduces_torch_on_recorded_observations(folder, quant, f32_weights):
    """Bounds: f32 within the product's 2e-4; int8 within the agreement budget the project
    states for it, max 0.02 (docs/METAWORLD.md), which the shipped files meet on every
    inference of the 100 torch rollouts (eval.json), so on these few recorded ones too."""
    bound = 2e-4 if quant == "f32" else INT8_AGREEMENT_MAX
    path = f32_weights[folder] if quant == "f32" else folder / "int8.scdp"
    model = scdp.Model(str(path))
    for backend in scdp.backends():
        policy = scdp.Policy(model, backend=backend)
        for file in sorted((folder / "observations").glob("*.safetensors")):
            run = load_file(str(file))
            policy.reset()
            policy.set_camera(run["camera_k"], run["camera_t"])
            for image, state in zip(run["images"], run["state"]):
                policy.push_observation(image, state)
            action_pred = policy.infer(noise=run["noise"], full=True)["action_pred"]
            # In normalized action units (x the normalizer's scale), as the golden tests.
            error = float((np.abs(action_pred - run["torch.action_pred"]) * run["action_scale"]).max())
            assert error <= bound, (file.name, backend, error, bound)


def test_threads_give_the_same_bits():
    """A policy on 2 or 3 threads gives exactly one thread's actions (the engine cuts each
    kernel call so that no sum changes order); 0 threads is refused."""
    folder = TRAINED[0]
    model = scdp.Model(str(folder / "int8.scdp"))
    run = load_file(str(sorted((folder / "observations").glob("*.safetensors"))[0]))
    results = {}
    for threads in (1, 2, 3):
        policy = scdp.Policy(model, threads=threads)
        assert policy.threads == threads
        policy.set_camera(run["camera_k"], run["camera_t"])
        for image, state in zip(run["images"], run["state"]):
            policy.push_observation(image, state)
        results[threads] = policy.infer(noise=run["noise"], full=True)["action_pred"]
    for threads in (2, 3):
        assert np.array_equal(results[threads].view(np.uint32), results[1].view(np.uint32))
    with pytest.raises(ValueError, match="threads"):
        scdp.Policy(model, threads=0)


@pytest.mark.parametrize("folder", TRAINED, ids=lambda f: f.name)
def test_engine_succeeds_as_often_as_torch(folder):
    """The shipped evaluation: engine f32 and int8 on the torch rollouts' seeds, the 95%
    interval of their paired difference to PyTorch's success holds zero and reaches no lower
    than -0.10 (a file converted or evaluated again must still meet it to ship)."""
    from scdp import metaworld

    results = evaluations(folder)
    for runtime in ("engine-f32", "engine-int8"):
        paired = metaworld.paired_difference_interval(results[runtime], results["torch"])
        low, high = paired["difference_95"]
        assert low <= 0 <= high and low > -0.10, (runtime, paired)


def test_int8_policy_in_closed_loop():
    """On the task whose episodes are shortest (CI's time): at least the measured int8
    success rate less a margin, the lower end of the 95% Wilson interval that SMOKE_EPISODES
    episodes at the measured rate would have, so a correct policy fails this rarely, and one
    that has lost its skill (the measured rate near 0 for a broken camera model or
    quantization) fails it."""
    from scdp import metaworld

    folder = min(TRAINED, key=lambda f: evaluations(f)["engine-int8"]["mean_steps"])
    measured = evaluations(folder)["engine-int8"]["success_rate"]
    floor, _ = metaworld.wilson_interval(round(measured * SMOKE_EPISODES), SMOKE_EPISODES)
    result = metaworld.evaluate(task_of(folder), folder, "engine-int8", SMOKE_EPISODES, SMOKE_FIRST_SEED,
                                threads=1)
    assert result["success_rate"] >= floor, (result, floor)
