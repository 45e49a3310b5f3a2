"""SCDP in Meta-World: collect expert demonstrations, train, evaluate in closed loop.

    python -m scdp.metaworld collect --task TASK --model-dir DIR [--episodes 20 --first-seed 0]
    python -m scdp.metaworld train   --model-dir DIR [--steps 5000]
    python -m scdp.metaworld eval    --task TASK --model-dir DIR --runtime RUNTIME \
                                     --episodes N --first-seed S

`collect` and `train` need PyTorch only for training; `eval --runtime engine-f32|engine-int8`
needs only this package and Meta-World. The last line `eval` prints is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

from . import sim

DEMOS = "demos.npz"
CONFIG = "model.toml"
CHECKPOINT = "checkpoint.ckpt"
CAMERA = "camera.safetensors"
TRAINING = "training"
# Evaluation seeds start here by default, far from the demonstrations' 0..19.
DEFAULT_EVAL_SEED = 1000


# --------------------------------------------------------------------------------------------
# collect


def collect(task: str, model_dir: Path, episodes: int, first_seed: int) -> None:
    scene = sim.Scene(task)
    images, states, actions, ends, seeds = [], [], [], [], []
    seed = first_seed
    while len(seeds) < episodes:
        scene.reset(seed)
        episode = ([], [], [])
        solved = False
        for _ in range(scene.max_steps):
            episode[0].append(scene.render())
            episode[1].append(scene.state())
            action = scene.expert_action()
            episode[2].append(action)
            if scene.step(action):
                solved = True
                break
        if solved:
            for store, values in zip((images, states, actions), episode):
                store.extend(values)
            ends.append(len(images))
            seeds.append(seed)
            print(f"seed {seed}: {len(episode[0])} steps", file=sys.stderr)
        else:
            print(f"seed {seed}: the expert did not succeed; skipped", file=sys.stderr)
        seed += 1
    camera_k, camera_t = scene.camera_model()
    model_dir.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        model_dir / DEMOS, images=np.stack(images), state=np.stack(states), action=np.stack(actions),
        episode_ends=np.array(ends), seeds=np.array(seeds), camera_k=camera_k, camera_t=camera_t,
        task=np.array(task),
    )
    write_camera(model_dir / CAMERA, camera_k, camera_t)
    print(json.dumps({"task": task, "episodes": len(seeds), "seeds": seeds, "frames": len(images)}))


def write_camera(path: Path, camera_k: np.ndarray, camera_t: np.ndarray) -> None:
    from safetensors.numpy import save_file

    save_file({"camera_k": camera_k.astype(np.float32), "camera_t": camera_t.astype(np.float32)}, str(path))


def write_calibration(model_dir: Path, count: int) -> None:
    """Run files (`weights-tool convert --calibrate`) of `count` training windows spread evenly
    over the demonstrations: the int8 rounding is fitted on frames the policy was trained on,
    never on evaluation episodes."""
    from safetensors.numpy import save_file

    cfg = load_config(model_dir)
    demos = dict(np.load(model_dir / DEMOS))
    sequences = Sequences(demos, cfg)
    folder = model_dir / "calibration"
    folder.mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    for number, row in enumerate(np.linspace(0, len(sequences.windows) - 1, count).round().astype(int)):
        observed = sequences.windows[row][: cfg["n_obs_steps"]]
        save_file({
            "images": np.ascontiguousarray(demos["images"][observed]),
            "state": np.ascontiguousarray(demos["state"][observed]),
            "noise": rng.standard_normal((cfg["horizon"], cfg["action_dim"])).astype(np.float32),
            "camera_k": demos["camera_k"], "camera_t": demos["camera_t"],
        }, str(folder / f"{number:03d}.safetensors"))
    print(f"{count} calibration run files in {folder}", file=sys.stderr)


# --------------------------------------------------------------------------------------------
# train


def load_config(model_dir: Path) -> dict:
    with open(model_dir / CONFIG, "rb") as f:
        return tomllib.load(f)


class Sequences:
    """Diffusion Policy's SequenceSampler: windows of `horizon` steps whose first `To` are the
    observations, starting up to To - 1 steps before an episode and ending up to
    n_action_steps - 1 steps after it, padded with the episode's first / last values."""

    def __init__(self, demos, cfg: dict):
        self.images, self.state, self.action = demos["images"], demos["state"], demos["action"]
        self.frames, self.horizon = cfg["n_obs_steps"], cfg["horizon"]
        windows = []
        start = 0
        for end in demos["episode_ends"]:
            length = end - start
            for first in range(-(self.frames - 1), length - self.horizon + cfg["n_action_steps"]):
                windows.append(start + np.clip(first + np.arange(self.horizon), 0, length - 1))
            start = end
        self.windows = np.stack(windows)

    def batch(self, rng: np.random.Generator, size: int):
        rows = self.windows[rng.integers(0, len(self.windows), size)]
        observed = rows[:, : self.frames]
        return self.images[observed], self.state[observed], self.action[rows]


def workspace_checkpoint(cfg: dict, model, ema, optimizer, scheduler, step: int, total_steps: int,
                         rng_state, half: bool, warmup: int = 500) -> dict:
    """Diffusion Policy's BaseWorkspace.save_checkpoint layout: cfg (OmegaConf), state_dicts,
    pickles. With `half`, only the EMA weights, as float16: what ships."""
    from omegaconf import OmegaConf

    workspace_cfg = OmegaConf.create({
        "name": "train_scdp_metaworld",
        "task_name": cfg.get("task", ""),
        "horizon": cfg["horizon"], "n_obs_steps": cfg["n_obs_steps"], "n_action_steps": cfg["n_action_steps"],
        "policy": {k: v for k, v in cfg.items() if k != "task"},
        "training": {"num_steps": total_steps, "lr_scheduler": "cosine", "lr_warmup_steps": warmup,
                     "use_ema": True, "batch_size": 32},
        "optimizer": {"_target_": "torch.optim.AdamW", "lr": 1.0e-4, "betas": [0.95, 0.999],
                      "eps": 1.0e-8, "weight_decay": 1.0e-6},
    })
    if half:
        state_dicts = {"ema_model": {k: v.half() if v.is_floating_point() else v
                                     for k, v in ema.averaged.state_dict().items()}}
    else:
        state_dicts = {"model": model.state_dict(), "ema_model": ema.averaged.state_dict(),
                       "optimizer": optimizer.state_dict(), "lr_scheduler": scheduler.state_dict()}
    pickles = {"global_step": pickle.dumps(step)}
    if not half:
        pickles["rng"] = pickle.dumps(rng_state)
        pickles["ema_optimization_step"] = pickle.dumps(ema.optimization_step)
    return {"cfg": workspace_cfg, "state_dicts": state_dicts, "pickles": pickles}


def train(model_dir: Path, total_steps: int, batch_size: int, checkpoint_every: int, threads: int,
          precision: str, prefix_rows: int = 0, init: Path | None = None, warmup: int = 500) -> None:
    """Trains from scratch, or with `init` from a shipped checkpoint's EMA weights (its
    normalizer included); with `prefix_rows`, half the windows hold a committed prefix of
    up to that many rows (`SCDPPolicy.loss`)."""
    import torch

    from .torch_policy import EMAModel, SCDPPolicy

    torch.set_num_threads(threads)
    cfg = load_config(model_dir)
    demos = dict(np.load(model_dir / DEMOS))
    sequences = Sequences(demos, cfg)
    camera_k = torch.as_tensor(demos["camera_k"]).expand(batch_size, 3, 3)
    camera_t = torch.as_tensor(demos["camera_t"]).expand(batch_size, 4, 4)
    torch.manual_seed(0)
    model = SCDPPolicy(cfg)
    if init is None:
        model.normalizer.fit("action", demos["action"])
        model.normalizer.fit("agent_pos", demos["state"])
    else:
        weights = torch.load(init, weights_only=False)["state_dicts"]["ema_model"]
        model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in weights.items()})
    ema = EMAModel(model)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4, betas=(0.95, 0.999), eps=1e-8, weight_decay=1e-6)

    def lr_factor(step):
        # diffusers' get_cosine_schedule_with_warmup
        if step < warmup:
            return step / max(1, warmup)
        progress = (step - warmup) / max(1, total_steps - warmup)
        return max(0.0, 0.5 * (1 + math.cos(math.pi * progress)))

    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lr_factor)
    rng = np.random.default_rng(0)
    step = 0
    work = model_dir / TRAINING
    work.mkdir(exist_ok=True)
    latest = work / "latest.ckpt"
    if latest.exists():
        payload = torch.load(latest, weights_only=False)
        model.load_state_dict(payload["state_dicts"]["model"])
        ema.averaged.load_state_dict(payload["state_dicts"]["ema_model"])
        optimizer.load_state_dict(payload["state_dicts"]["optimizer"])
        scheduler.load_state_dict(payload["state_dicts"]["lr_scheduler"])
        step = pickle.loads(payload["pickles"]["global_step"])
        ema.optimization_step = pickle.loads(payload["pickles"]["ema_optimization_step"])
        rng.bit_generator.state = pickle.loads(payload["pickles"]["rng"])
        torch.manual_seed(step)
        print(f"resumed at step {step}", file=sys.stderr)
    use_bf16 = precision == "bf16"
    log = open(work / "log.jsonl", "a")
    model.train()
    started = time.time()
    while step < total_steps:
        images, state, actions = sequences.batch(rng, batch_size)
        images, state, actions = (torch.as_tensor(x) for x in (images, state, actions))
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=use_bf16):
            loss = model.loss(images, state, actions, camera_k, camera_t, prefix_rows)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        ema.step(model)
        step += 1
        if step % 50 == 0:
            record = {"step": step, "loss": float(loss.detach()), "lr": scheduler.get_last_lr()[0],
                      "seconds": round(time.time() - started, 1)}
            log.write(json.dumps(record) + "\n")
            log.flush()
        if step % checkpoint_every == 0 or step == total_steps:
            payload = workspace_checkpoint(cfg, model, ema, optimizer, scheduler, step, total_steps,
                                           rng.bit_generator.state, half=False, warmup=warmup)
            torch.save(payload, work / "latest.tmp")
            (work / "latest.tmp").replace(latest)
            shipped = workspace_checkpoint(cfg, model, ema, optimizer, scheduler, step, total_steps, None,
                                           half=True, warmup=warmup)
            torch.save(shipped, work / f"step-{step:06d}.ckpt")
            print(f"step {step}: loss {float(loss.detach()):.4f}", file=sys.stderr)
    final = workspace_checkpoint(cfg, model, ema, optimizer, scheduler, step, total_steps, None, half=True,
                                 warmup=warmup)
    torch.save(final, model_dir / CHECKPOINT)


def training_cost(model_dir: Path, batches: int, batch_size: int, threads: int) -> None:
    """Seconds per training batch (forward, backward, AdamW step) in each autocast precision,
    measured in one process on the demonstrations; the first batch of each is a warm-up."""
    import torch

    from .torch_policy import SCDPPolicy

    torch.set_num_threads(threads)
    cfg = load_config(model_dir)
    demos = dict(np.load(model_dir / DEMOS))
    sequences = Sequences(demos, cfg)
    camera_k = torch.as_tensor(demos["camera_k"]).expand(batch_size, 3, 3)
    camera_t = torch.as_tensor(demos["camera_t"]).expand(batch_size, 4, 4)
    rng = np.random.default_rng(0)
    result = {"batch_size": batch_size, "threads": threads}
    for precision in ("f32", "bf16"):
        model = SCDPPolicy(cfg)
        optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
        seconds = []
        for _ in range(batches + 1):
            batch = [torch.as_tensor(x) for x in sequences.batch(rng, batch_size)]
            started = time.perf_counter()
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
                loss = model.loss(*batch, camera_k, camera_t)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            seconds.append(time.perf_counter() - started)
        result[f"{precision}_seconds_p50"] = float(np.median(seconds[1:]))
    print(json.dumps(result))


# --------------------------------------------------------------------------------------------
# runtimes: one interface over PyTorch and the engine


class TorchRuntime:
    """The trained checkpoint in PyTorch, float32: the reference the engine must match."""

    name = "torch"

    def __init__(self, model_dir: Path, threads: int):
        import torch

        from .torch_policy import SCDPPolicy

        torch.set_num_threads(threads)
        self.torch = torch
        self.cfg = load_config(model_dir)
        payload = torch.load(model_dir / CHECKPOINT, weights_only=False, map_location="cpu")
        weights = payload["state_dicts"]["ema_model"]
        self.policy = SCDPPolicy(self.cfg)
        self.policy.load_state_dict({k: v.float() for k, v in weights.items()})
        self.policy.eval()
        self.frames = []

    def reset(self, camera_k, camera_t):
        self.camera = (self.torch.as_tensor(camera_k)[None], self.torch.as_tensor(camera_t)[None])
        self.frames = []

    def push(self, image, state):
        self.frames = (self.frames + [(image, state)])[-self.cfg["n_obs_steps"]:]

    def history(self):
        """The last To observations, the first repeated until there are To (as the engine)."""
        frames = [self.frames[0]] * (self.cfg["n_obs_steps"] - len(self.frames)) + self.frames
        return np.stack([f[0] for f in frames]), np.stack([f[1] for f in frames])

    def infer(self, noise, prefix=None, prefix_mode="replace", planned=None):
        torch = self.torch
        images, state = self.history()
        held = None if prefix is None or len(prefix) == 0 else torch.as_tensor(prefix)[None]
        pulled = None if planned is None or len(planned) == 0 else torch.as_tensor(planned)[None]
        action_pred, anchors = self.policy.predict(
            torch.as_tensor(images)[None], torch.as_tensor(state)[None], *self.camera,
            torch.as_tensor(noise)[None], record_anchors=True, prefix=held, prefix_mode=prefix_mode,
            planned=pulled,
        )
        return action_pred[0].numpy(), anchors[:, 0].numpy()


class EngineRuntime:
    """The engine through this package's binding, on a weights file of `convert`."""

    def __init__(self, model_path: Path, name: str, backend: str = "auto", threads: int = 1):
        from . import Model, Policy

        if not model_path.exists():
            raise SystemExit(
                f"{model_path} does not exist; make it with weights-tool convert (docs/METAWORLD.md, Reproduce)"
            )
        self.name = name
        self.model = Model(str(model_path))
        self.policy = Policy(self.model, backend=backend, threads=threads)

    def reset(self, camera_k, camera_t):
        self.policy.reset()
        self.policy.set_camera(camera_k, camera_t)

    def push(self, image, state):
        self.policy.push_observation(image, state)

    def infer(self, noise, prefix=None, prefix_mode="replace", planned=None):
        result = self.policy.infer(noise=noise, full=True, prefix=prefix, prefix_mode=prefix_mode,
                                   planned=planned)
        return result["action_pred"], result["anchors_uv"]


def make_runtime(runtime: str, model_dir: Path, threads: int, backend: str = "auto"):
    if runtime == "torch":
        return TorchRuntime(model_dir, threads)
    if runtime == "engine-f32":
        return EngineRuntime(model_dir / "f32.scdp", runtime, backend, threads)
    if runtime == "engine-int8":
        return EngineRuntime(model_dir / "int8.scdp", runtime, backend, threads)
    raise SystemExit(f"unknown runtime {runtime!r}")


# --------------------------------------------------------------------------------------------
# closed loop


def episode_noise(seed: int, chunk: int, cfg: dict) -> np.ndarray:
    """The initial sample of chunk `chunk` of episode `seed`: the same for every runtime, so
    their rollouts differ only by their arithmetic."""
    rng = np.random.default_rng([seed, chunk])
    return rng.standard_normal((cfg["horizon"], cfg["action_dim"])).astype(np.float32)


# How many of a new chunk's first actions the seam measure looks at.
SEAM_WINDOW = 4


def run_episode(scene, runtime, cfg, seed, record=None, frames=None, latency=0, prefix_mode=None,
                planned=False, planned_rows=None, within=None):
    """Diffusion Policy's receding horizon with an inference that takes `latency` control
    steps. The first chunk is computed while the arm waits; it executes the n_action_steps
    actions from "now" (rows To-1 ..). Every later chunk is started from the observation
    taken when `latency` actions of the current one remain, and those actions keep running
    while it is computed: its rows To-1 .. To-1+latency are then in the past. They are
    dropped (`prefix_mode` None, the firmware demo's rule) or were given to the inference as
    its committed prefix (`prefix_mode` "replace" or "noised"), with `planned` also the old
    chunk's rows after them, which the new one is pulled towards; the chunk executes the
    n_action_steps rows after them. With latency 0 this is the loop where the simulation
    waits for the policy. Only the frames the policy sees are rendered (the last To before
    each inference). `record` (a list, torch runtime only) receives each inference's inputs
    and output; `frames` each executed step's frame with the anchors of its chunk; `within`
    the size of every step between two consecutive actions of one chunk's plan (the scale a
    seam's jump is judged against).

    Returns (solved, steps, inference milliseconds, seams): for each hand-over, the action
    executed last from the old chunk and the first SEAM_WINDOW + 1 of the new one."""
    scene.reset(seed)
    camera_k, camera_t = scene.camera_model()
    runtime.reset(camera_k, camera_t)
    first, count = cfg["n_obs_steps"] - 1, cfg["n_action_steps"]
    if first + latency + count > cfg["horizon"]:
        raise SystemExit(f"latency {latency} leaves fewer than n_action_steps rows of the horizon")
    steps, chunk, solved, latencies, seams = 0, 0, False, [], []
    plan, rest, anchors, last = [], [], None, None

    def execute(actions, push_before=None):
        """Steps the scene through `actions` (pushing the frame before action `push_before`
        to the policy); False once the episode is over."""
        nonlocal steps, solved, last
        for index, action in enumerate(actions):
            if frames is not None:
                frames.append((scene.render(), anchors))
            if index == push_before:
                runtime.push(scene.render(), scene.state())
            solved = scene.step(action)
            steps += 1
            last = action
            if solved or steps >= scene.max_steps:
                return False
        return True

    image, state = scene.render(), scene.state()
    while steps < scene.max_steps and not solved:
        # The observation: now, with `latency` actions of the plan still to run (none for the
        # first chunk, which the arm waits for).
        committed = np.array(plan[len(plan) - latency:] if chunk and latency else [], np.float32)
        committed = committed.reshape(-1, cfg["action_dim"])
        noise = episode_noise(seed, chunk, cfg)
        started = time.perf_counter()
        runtime.push(image, state)
        held = committed if prefix_mode else None
        pulled = None
        if prefix_mode and planned and chunk:
            pulled = np.array(rest[:planned_rows], np.float32).reshape(-1, cfg["action_dim"])
        action_pred, new_anchors = runtime.infer(noise, held, prefix_mode or "replace", pulled)
        latencies.append((time.perf_counter() - started) * 1e3)
        if record is not None:
            images, states = runtime.history()
            record.append({"images": images, "state": states, "noise": noise, "camera_k": camera_k,
                           "camera_t": camera_t, "action_pred": action_pred, "seed": seed, "chunk": chunk,
                           "prefix": held, "prefix_mode": prefix_mode, "planned": pulled})
        # While it computes, the old plan's last `latency` actions run.
        if not execute(committed):
            break
        skip = len(committed)
        plan = list(action_pred[first + skip : first + skip + count])
        if within is not None:
            within.extend(np.linalg.norm(np.diff(np.array(plan), axis=0), axis=1).tolist())
        rest = list(action_pred[first + skip + count :])
        anchors = new_anchors
        if last is not None:
            seams.append((last, np.array(plan[: SEAM_WINDOW + 1])))
        # Run the plan up to the next observation, which is taken with `latency` actions left
        # (the frame before it, too, when the policy looks at two).
        run_now = len(plan) - latency
        execute(plan[:run_now], run_now - 1 if cfg["n_obs_steps"] > 1 else None)
        image, state = scene.render(), scene.state()
        chunk += 1
    return solved, steps, latencies, seams


def seam_figures(seams, within=()):
    """At each hand-over, in action units (the Euclidean norm over the action's dimensions):
    the jump from the old chunk's last executed action to the new chunk's first, and the
    largest step-to-step change among the new chunk's first SEAM_WINDOW + 1 actions; their
    means, 95th percentiles and maxima over every hand-over. With `within` (run_episode's
    steps inside the chunks), their mean too, as `step_mean`."""
    if not seams:
        return {"handovers": 0}
    jumps = np.array([np.linalg.norm(new[0] - old) for old, new in seams])
    early = np.array([np.linalg.norm(np.diff(new, axis=0), axis=1).max() if len(new) > 1 else 0.0
                      for _, new in seams])
    figures = {"handovers": len(seams)}
    for name, values in (("jump", jumps), ("early_step_max", early)):
        figures[f"{name}_mean"] = round(float(values.mean()), 5)
        figures[f"{name}_p95"] = round(float(np.quantile(values, 0.95)), 5)
        figures[f"{name}_max"] = round(float(values.max()), 5)
    if len(within):
        figures["step_mean"] = round(float(np.mean(within)), 5)
        figures["step_count"] = len(within)
    return figures


def measured_latency_steps(runtime, cfg, scene, control_hz, seed):
    """The control steps one inference of `runtime` takes at `control_hz`: the median of 5
    inferences (after one warm-up) on the first observation of episode `seed`, rounded up."""
    scene.reset(seed)
    runtime.reset(*scene.camera_model())
    runtime.push(scene.render(), scene.state())
    noise = episode_noise(seed, 0, cfg)
    runtime.infer(noise)
    times = []
    for _ in range(5):
        started = time.perf_counter()
        runtime.infer(noise)
        times.append(time.perf_counter() - started)
    milliseconds = float(np.median(times)) * 1e3
    return max(1, math.ceil(milliseconds * control_hz / 1e3)), milliseconds


def evaluate(task, model_dir, runtime_name, episodes, first_seed, threads, backend="auto", gif=None,
             agreement=False, record_count=0, latency=0, prefix_mode=None, control_hz=None, planned=False,
             planned_rows=None):
    cfg = load_config(model_dir)
    demo_seeds = set()
    if (model_dir / DEMOS).exists():
        demo_seeds = set(np.load(model_dir / DEMOS)["seeds"].tolist())
    seeds = list(range(first_seed, first_seed + episodes))
    if demo_seeds & set(seeds):
        raise SystemExit(f"seeds {sorted(demo_seeds & set(seeds))} are demonstration seeds")
    # PyTorch first: its Triton brings an LLVM that crashes when loaded after the one MuJoCo's
    # OSMesa renderer has already loaded.
    runtime = make_runtime(runtime_name, model_dir, threads, backend)
    if agreement and runtime_name != "torch":
        raise SystemExit("--agreement compares the engine with the torch runtime's rollouts: use --runtime torch")
    scene = sim.Scene(task)
    record = [] if agreement else None
    measured_ms = None
    if control_hz is not None:
        latency, measured_ms = measured_latency_steps(runtime, cfg, scene, control_hz, seeds[0])
        print(f"one inference {measured_ms:.1f} ms: {latency} steps at {control_hz:g} Hz", file=sys.stderr)
    successes, steps_taken, latencies, seams, failed, within = 0, [], [], [], [], []
    for number, seed in enumerate(seeds):
        frames = [] if gif is not None and number == 0 else None
        solved, steps, times, episode_seams = run_episode(
            scene, runtime, cfg, seed, record=record, frames=frames, latency=latency, prefix_mode=prefix_mode,
            planned=planned, planned_rows=planned_rows, within=within)
        seams.extend(episode_seams)
        if frames is not None:
            write_rollout_gif(gif, frames)
        successes += solved
        if not solved:
            failed.append(seed)
        steps_taken.append(steps)
        latencies.extend(times)
        print(f"seed {seed}: {'success' if solved else 'failure'} after {steps} steps", file=sys.stderr)
    low, high = wilson_interval(successes, episodes)
    result = {
        "task": task, "runtime": runtime_name, "episodes": episodes, "successes": successes,
        "success_rate": successes / episodes, "success_rate_95": [round(low, 4), round(high, 4)],
        "policy": model_dir.resolve().name,
        "first_seed": first_seed, "mean_steps": float(np.mean(steps_taken)),
        "infer_ms_p50": float(np.median(latencies)),
        "backend": getattr(getattr(runtime, "policy", None), "backend", "torch"),
        "failed_seeds": failed,
        "latency_steps": latency, "prefix": prefix_mode, "planned": bool(prefix_mode and planned),
        "planned_rows": planned_rows if prefix_mode and planned else None,
        "seams": seam_figures(seams, within),
    }
    if control_hz is not None:
        result["control_hz"] = control_hz
        result["latency_measured_ms"] = round(measured_ms, 3)
    if record is not None:
        scale = runtime.policy.normalizer.params_dict["action"]["scale"].detach().numpy()
        result["agreement"] = {
            name: agreement_with(make_runtime(name, model_dir, threads, backend), record, scale)
            for name in ("engine-f32", "engine-int8")
        }
        if record_count:
            write_observations(model_dir / "observations", record, record_count, scale)
    print(json.dumps(result))
    return result


def agreement_with(runtime, record, action_scale):
    """The engine on the torch rollout's own inputs, with the same noise: max and mean of
    |engine - torch| x action scale (normalized action units) over every recorded chunk."""
    errors = inference_errors(runtime, record, action_scale)
    return agreement_figures(errors)


def inference_errors(runtime, record, action_scale) -> np.ndarray:
    """|runtime - torch| x action scale of every recorded inference, `[inferences, horizon,
    action_dim]`."""
    errors = []
    for entry in record:
        runtime.reset(entry["camera_k"], entry["camera_t"])
        for image, state in zip(entry["images"], entry["state"]):
            runtime.push(image, state)
        action_pred, _ = runtime.infer(entry["noise"], entry.get("prefix"), entry.get("prefix_mode") or "replace",
                                       entry.get("planned"))
        errors.append(np.abs(action_pred - entry["action_pred"]) * action_scale)
    return np.stack(errors)


def agreement_figures(errors: np.ndarray) -> dict:
    """Max, mean and the 99th percentile of a chunk's max of `inference_errors`."""
    return {"inferences": len(errors), "max": float(errors.max()), "mean": float(errors.mean()),
            "p99_chunk_max": float(np.quantile(errors.reshape(len(errors), -1).max(axis=1), 0.99))}


def recorded_agreement(weights: Path, folder: Path, budget: float = 0.02, worst: int = 5) -> dict:
    """A weights file on recorded inferences (`write_observations` files): its agreement
    with the recorded torch actions, the chunks whose largest error is over `budget`, and
    the `worst` chunks (file, seed, chunk, max)."""
    record, action_scale = read_observations(folder)
    errors = inference_errors(EngineRuntime(weights, weights.stem), record, action_scale)
    chunk_max = errors.reshape(len(errors), -1).max(axis=1)
    order = np.argsort(chunk_max)[::-1][:worst]
    return {"weights": str(weights), **agreement_figures(errors),
            "chunks_over_budget": int((chunk_max > budget).sum()), "budget": budget,
            "worst": [{"max": float(chunk_max[i]), "file": record[i]["file"], "seed": record[i]["seed"],
                       "chunk": record[i]["chunk"]} for i in order]}


def write_observations(folder: Path, record, count, action_scale):
    """`count` recorded inferences, spread over the rollouts, as run files with the torch
    output beside the inputs (`torch.action_pred`, and the `action_scale` that normalizes
    its errors)."""
    from safetensors.numpy import save_file

    folder.mkdir(exist_ok=True)
    for number, row in enumerate(np.linspace(0, len(record) - 1, count).round().astype(int)):
        entry = record[row]
        save_file({
            "images": np.ascontiguousarray(entry["images"]), "state": np.ascontiguousarray(entry["state"]),
            "noise": entry["noise"], "camera_k": entry["camera_k"], "camera_t": entry["camera_t"],
            "torch.action_pred": np.ascontiguousarray(entry["action_pred"], dtype=np.float32),
            "action_scale": np.ascontiguousarray(action_scale, dtype=np.float32),
        }, str(folder / f"{number:03d}.safetensors"),
            metadata={"seed": str(entry["seed"]), "chunk": str(entry["chunk"])})


def read_observations(folder: Path):
    """The files of `write_observations` as record entries (`action_pred` the torch output),
    with their `action_scale`."""
    from safetensors import safe_open

    record, action_scale = [], None
    for file in sorted(folder.glob("*.safetensors")):
        with safe_open(str(file), "np") as run:
            tensors = {name: run.get_tensor(name) for name in run.keys()}
            meta = run.metadata() or {}
        action_scale = tensors["action_scale"]
        record.append({**{k: tensors[k] for k in ("images", "state", "noise", "camera_k", "camera_t")},
                       "action_pred": tensors["torch.action_pred"], "file": file.name,
                       "seed": meta.get("seed"), "chunk": meta.get("chunk")})
    return record, action_scale


def wilson_interval(successes: int, trials: int, z: float = 1.959963984540054):
    """The Wilson score interval of a binomial proportion (95% by default)."""
    if trials == 0:
        return 0.0, 1.0
    p = successes / trials
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / (1 + z * z / trials)
    return max(0.0, centre - half), min(1.0, centre + half)


def difference_interval(successes_a: int, trials_a: int, successes_b: int, trials_b: int):
    """Newcombe's hybrid score interval (95%) of the difference a - b of two success rates,
    taken as independent (wider than a paired interval on the same seeds)."""
    pa, pb = successes_a / trials_a, successes_b / trials_b
    la, ua = wilson_interval(successes_a, trials_a)
    lb, ub = wilson_interval(successes_b, trials_b)
    difference = pa - pb
    return (difference - math.sqrt((pa - la) ** 2 + (ub - pb) ** 2),
            difference + math.sqrt((ua - pa) ** 2 + (pb - lb) ** 2))


def paired_difference_interval(a: dict, b: dict):
    """The difference a - b of two `eval` results' success rates on the same seeds, with
    Newcombe's score interval for paired proportions (95%, his method 10: each rate's Wilson
    interval, combined with the correlation of the pairs' outcomes)."""
    seeds = range(a["first_seed"], a["first_seed"] + a["episodes"])
    if (b["first_seed"], b["episodes"]) != (a["first_seed"], a["episodes"]):
        raise ValueError("a paired difference needs the same seeds")
    failed_a, failed_b = set(a["failed_seeds"]), set(b["failed_seeds"])
    both = sum(1 for s in seeds if s not in failed_a and s not in failed_b)
    only_a = sum(1 for s in seeds if s not in failed_a and s in failed_b)
    only_b = sum(1 for s in seeds if s in failed_a and s not in failed_b)
    neither = a["episodes"] - both - only_a - only_b
    n = a["episodes"]
    pa, pb = (both + only_a) / n, (both + only_b) / n
    la, ua = wilson_interval(both + only_a, n)
    lb, ub = wilson_interval(both + only_b, n)
    product = (both + only_a) * (only_b + neither) * (both + only_b) * (only_a + neither)
    cross = both * neither - only_a * only_b
    # Newcombe's continuity correction of the correlation where it is positive.
    phi = 0.0 if product == 0 else (max(cross - n / 2, 0) if cross > 0 else cross) / math.sqrt(product)
    lower = math.sqrt(max((pa - la) ** 2 - 2 * phi * (pa - la) * (ub - pb) + (ub - pb) ** 2, 0.0))
    upper = math.sqrt(max((ua - pa) ** 2 - 2 * phi * (ua - pa) * (pb - lb) + (pb - lb) ** 2, 0.0))
    difference = pa - pb
    return {"difference": difference, "difference_95": [difference - lower, difference + upper],
            "discordant": [only_a, only_b]}


def compare_table(path: Path) -> str:
    """A Markdown table of an `eval.json` (the runtimes' results on the same seeds): each
    runtime's success with its Wilson interval and its paired difference to PyTorch."""
    results = json.loads(path.read_text())
    torch_result = next(r for r in results if r["runtime"] == "torch")
    lines = ["| runtime | success (95%) | minus torch, paired (95%) | discordant seeds |",
             "|---|---|---|---|"]
    for r in results:
        low, high = r["success_rate_95"]
        row = f"| {r['runtime']} | {r['successes']}/{r['episodes']} ({low:.3f} - {high:.3f}) |"
        if r is torch_result:
            lines.append(row + " | |")
            continue
        paired = paired_difference_interval(r, torch_result)
        dl, dh = paired["difference_95"]
        only_r, only_torch = paired["discordant"]
        lines.append(row + f" {paired['difference']:+.3f} ({dl:+.3f} .. {dh:+.3f}) |"
                     f" {only_r} only {r['runtime']}, {only_torch} only torch |")
    return "\n".join(lines)


def handover_rule(result) -> str:
    """How an `eval` result's chunks took over: "drop", "prefix MODE", "prefix MODE +
    planned" (all the old plan's rows), "prefix MODE + M planned row(s)"."""
    if not result.get("prefix"):
        return "drop"
    rows = result.get("planned_rows")
    plan = "" if not result.get("planned") else " + planned" if rows is None else \
        f" + {rows} planned row" + ("s" if rows > 1 else "")
    return f"prefix {result['prefix']}{plan}"


def policy_label(result) -> str:
    """The task, and the policy's folder where it is not the task's shipped one
    (`metaworld-TASK`): results without a folder are the shipped policy's."""
    folder = result.get("policy", f"metaworld-{result['task']}")
    return result["task"] if folder == f"metaworld-{result['task']}" else f"{result['task']} ({folder})"


def pooled_results(results):
    """`eval` results of one setting (task, latency, hand-over rule) on adjacent seed ranges
    merged into one: successes, failed seeds (when every part lists them), the Wilson
    interval, and the seam means weighted by their counts (hand-overs; steps inside the
    chunks, when every part has them). 95th percentiles do not pool and are left out."""
    def setting(r):
        return (policy_label(r), r["latency_steps"], handover_rule(r))

    pooled = []
    for r in sorted(results, key=lambda r: (setting(r), r["first_seed"])):
        last = pooled[-1] if pooled else None
        if last is None or setting(last) != setting(r) or \
                last["first_seed"] + last["episodes"] != r["first_seed"]:
            pooled.append({**r, "seams": dict(r["seams"])})
            continue
        seams, more = last["seams"], r["seams"]
        handovers = seams["handovers"] + more["handovers"]
        for name in ("jump_mean", "early_step_max_mean"):
            seams[name] = (seams[name] * seams["handovers"] + more[name] * more["handovers"]) / handovers
        if "step_count" in seams and "step_count" in more:
            count = seams["step_count"] + more["step_count"]
            seams["step_mean"] = (seams["step_mean"] * seams["step_count"]
                                  + more["step_mean"] * more["step_count"]) / count
            seams["step_count"] = count
        else:
            seams.pop("step_mean", None)
            seams.pop("step_count", None)
        for name in ("jump_p95", "jump_max", "early_step_max_p95", "early_step_max_max"):
            seams.pop(name, None)
        seams["handovers"] = handovers
        episodes = last["episodes"] + r["episodes"]
        last["mean_steps"] = (last["mean_steps"] * last["episodes"] + r["mean_steps"] * r["episodes"]) / episodes
        last["episodes"] = episodes
        last["successes"] += r["successes"]
        last["success_rate"] = last["successes"] / episodes
        last["success_rate_95"] = list(wilson_interval(last["successes"], episodes))
        if "failed_seeds" in last and "failed_seeds" in r:
            last["failed_seeds"] = last["failed_seeds"] + r["failed_seeds"]
        else:
            last.pop("failed_seeds", None)
    return pooled


def latency_table(paths) -> str:
    """A Markdown table of `eval` results (JSON lines) with latency: per task, latency and
    seed range (a setting's results on adjacent seed ranges pooled), each hand-over rule's
    success, its difference to dropping the stale actions on the same seeds (pooled or not) (Newcombe's
    interval: paired where both results list their failed seeds, else for independent
    rates), and the seam figures against dropping's and against a step inside a chunk."""
    results = []
    for path in paths:
        for line in Path(path).read_text().splitlines():
            if line.strip():
                results.append(json.loads(line))
    return latency_table_of(results)


def latency_table_of(results) -> str:
    """`latency_table` of results already read."""
    parts, results = results, pooled_results(results)

    def rank(r):
        if not r.get("prefix"):
            return (0, 0)
        mode = ("replace", "noised").index(r["prefix"])
        if not r.get("planned"):
            return (1, mode)
        return (2 + (r.get("planned_rows") or 99), mode)

    def seeds(r):
        return f"{r['first_seed']}-{r['first_seed'] + r['episodes'] - 1}"

    results.sort(key=lambda r: (policy_label(r), r["latency_steps"], r["first_seed"], -r["episodes"], rank(r)))
    lines = ["| task | D | seeds | hand-over | success (95%) | minus drop (95%) | seam jump mean | "
             "jump / drop's | jump / step inside a chunk | largest early step mean | mean steps |",
             "|---|---:|---|---|---|---|---:|---:|---:|---:|---:|"]
    for r in results:
        # Dropping on the same seeds: pooled, or one of the parts when only these seeds ran.
        drop = next((d for d in results + parts if (policy_label(d), d["latency_steps"], seeds(d)) ==
                     (policy_label(r), r["latency_steps"], seeds(r)) and handover_rule(d) == "drop"), None)
        low, high = r["success_rate_95"]
        versus, ratio = "", ""
        if drop is not None and drop is not r:
            if "failed_seeds" in r and "failed_seeds" in drop:
                (a, b), kind = paired_difference_interval(r, drop)["difference_95"], " paired"
            else:
                (a, b), kind = difference_interval(r["successes"], r["episodes"], drop["successes"],
                                                   drop["episodes"]), ""
            versus = f"{r['success_rate'] - drop['success_rate']:+.3f} ({a:+.3f} .. {b:+.3f}){kind}"
            ratio = f"{r['seams']['jump_mean'] / drop['seams']['jump_mean']:.2f}x"
        seams = r["seams"]
        step = f"{seams['jump_mean'] / seams['step_mean']:.2f}x" if "step_mean" in seams else ""
        lines.append(
            f"| {policy_label(r)} | {r['latency_steps']} | {seeds(r)} | {handover_rule(r)} | "
            f"{r['successes']}/{r['episodes']} ({low:.3f} - {high:.3f}) | {versus} | {seams['jump_mean']:.3f} | "
            f"{ratio} | {step} | {seams['early_step_max_mean']:.3f} | {r['mean_steps']:.1f} |")
    return "\n".join(lines)


def write_rollout_gif(path, frames, scale=3):
    """Each executed step's frame with the anchors of every denoising step of the chunk that
    chose it, blue (noisiest) to red (final), as `weights-tool run --viz` draws them."""
    import imageio

    pictures = []
    for image, anchors in frames:
        picture = np.kron(image, np.ones((scale, scale, 1), dtype=np.uint8))
        steps = len(anchors)
        for step, points in enumerate(anchors):
            t = step / max(1, steps - 1)
            colour = np.array([255 * t, 0, 255 * (1 - t)], dtype=np.uint8)
            for u, v in points:
                if not (np.isfinite(u) and np.isfinite(v)):
                    continue
                x, y = int(round((u + 0.5) * scale - 0.5)), int(round((v + 0.5) * scale - 0.5))
                picture[max(0, y - 1) : y + 2, max(0, x - 1) : x + 2] = colour
        pictures.append(picture)
    imageio.mimsave(path, pictures, duration=0.05, loop=0)


# --------------------------------------------------------------------------------------------
# command line


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m scdp.metaworld", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("collect", help="record the scripted expert's demonstrations")
    p.add_argument("--task", required=True)
    p.add_argument("--model-dir", type=Path, required=True)
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--first-seed", type=int, default=0)
    p = commands.add_parser("calibration", help="run files of demonstration frames for int8 calibration")
    p.add_argument("--model-dir", type=Path, required=True)
    p.add_argument("--count", type=int, default=32)
    p = commands.add_parser("train", help="train SCDP on the demonstrations (PyTorch)")
    p.add_argument("--model-dir", type=Path, required=True)
    p.add_argument("--steps", type=int, default=5000)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--checkpoint-every", type=int, default=250)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--precision", choices=("bf16", "f32"), default="bf16",
                   help="autocast precision of the forward pass (weights and optimizer stay f32)")
    p.add_argument("--prefix-rows", type=int, default=0, metavar="K",
                   help="hold a committed prefix of 1..K rows in half the windows (inpainting training)")
    p.add_argument("--init", type=Path, metavar="CHECKPOINT",
                   help="start from this checkpoint's EMA weights (fine-tuning) instead of from scratch")
    p.add_argument("--warmup", type=int, default=500, help="learning-rate warm-up steps")
    p = commands.add_parser("train-cost", help="seconds per training batch, f32 and bf16 autocast")
    p.add_argument("--model-dir", type=Path, required=True)
    p.add_argument("--batches", type=int, default=5)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--threads", type=int, default=2)
    p = commands.add_parser("eval", help="closed-loop success of a runtime")
    p.add_argument("--task", required=True)
    p.add_argument("--model-dir", type=Path, required=True)
    p.add_argument("--runtime", choices=("torch", "engine-f32", "engine-int8"), required=True)
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--first-seed", type=int, default=DEFAULT_EVAL_SEED)
    p.add_argument("--threads", type=int, default=2,
                   help="PyTorch's threads (torch runtime), the engine's workers (engine runtimes: the same bits for any number)")
    p.add_argument("--backend", default="auto", help="engine kernels (engine runtimes)")
    p.add_argument("--gif", type=Path, help="write the first episode, anchors drawn, as an animated image")
    p.add_argument("--agreement", action="store_true",
                   help="torch runtime: also run engine f32 and int8 on every recorded inference")
    p.add_argument("--record", type=int, default=0, metavar="N",
                   help="with --agreement: keep N recorded inferences in MODEL_DIR/observations")
    p.add_argument("--latency-steps", type=int, default=0, metavar="D",
                   help="control steps one inference takes: the arm runs the old chunk meanwhile")
    p.add_argument("--control-hz", type=float, metavar="HZ",
                   help="take D from this runtime's measured inference time at this control rate")
    p.add_argument("--prefix", choices=("replace", "noised"),
                   help="give the actions run during the inference as the chunk's committed prefix "
                        "(default: drop the new chunk's actions whose time has passed)")
    p.add_argument("--planned", action="store_true",
                   help="with --prefix: also give the old chunk's plan after the prefix, which the "
                        "new chunk is pulled towards")
    p.add_argument("--planned-rows", type=int, metavar="M",
                   help="with --planned: give at most M of the old plan's rows (default: all)")
    p = commands.add_parser("agreement", help="a weights file on recorded inferences, against their torch actions")
    p.add_argument("--weights", type=Path, required=True, help="a weights file of convert")
    p.add_argument("--observations", type=Path, required=True,
                   help="a folder of eval --agreement --record N files")
    p.add_argument("--budget", type=float, default=0.02, help="count the chunks whose largest error is over this")
    p = commands.add_parser("compare", help="a Markdown table of an eval.json: success, paired difference to torch")
    p.add_argument("eval_json", type=Path, help="a JSON list of eval results on the same seeds")
    p = commands.add_parser("latency-table", help="a Markdown table of eval results with latency")
    p.add_argument("results", nargs="+", type=Path, help="files of eval's JSON lines")
    args = parser.parse_args(argv)
    if args.command == "agreement":
        print(json.dumps(recorded_agreement(args.weights, args.observations, args.budget)))
    elif args.command == "compare":
        print(compare_table(args.eval_json))
    elif args.command == "latency-table":
        print(latency_table(args.results))
    elif args.command == "collect":
        collect(args.task, args.model_dir, args.episodes, args.first_seed)
    elif args.command == "calibration":
        write_calibration(args.model_dir, args.count)
    elif args.command == "train":
        train(args.model_dir, args.steps, args.batch_size, args.checkpoint_every, args.threads, args.precision,
              args.prefix_rows, args.init, args.warmup)
    elif args.command == "train-cost":
        training_cost(args.model_dir, args.batches, args.batch_size, args.threads)
    elif args.command == "eval":
        evaluate(args.task, args.model_dir, args.runtime, args.episodes, args.first_seed, args.threads,
                 args.backend, args.gif, args.agreement, args.record, args.latency_steps, args.prefix,
                 args.control_hz, args.planned, args.planned_rows)


if __name__ == "__main__":
    main()
