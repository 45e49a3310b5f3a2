"""SCDP: the Spatially Conditioned Diffusion Policy's Rust inference engine, from Python.

A thin binding over the engine (`scdp-engine`): the same code, kernels and numbers as the
firmware's, with NumPy arrays in and float32 arrays out::

    import scdp

    model = scdp.Model("metaworld.scdp")      # written by `weights-tool convert`
    policy = scdp.Policy(model)               # backend="auto": the fastest this CPU runs
    policy.set_camera(K, T)                   # 3x3 intrinsics, 4x4 camera <- base transform
    policy.push_observation(rgb, state)       # uint8 [H, W, 3], [state_dim]
    actions = policy.infer(seed=0)            # float32 [n_action_steps, action_dim]

`scdp.backends()` lists the kernel backends this CPU can run; every error the engine
reports is raised as `scdp.EngineError` (a `RuntimeError`) with the engine's message, bad
arguments (dtypes, shapes) as `ValueError`.

Importing `scdp` loads only the compiled extension and NumPy; the PyTorch and Meta-World
modules of this package are imported on their own (`scdp.torch_policy`, `scdp.metaworld`).
"""

from scdp._scdp import EngineError, Model, Policy, backends

__all__ = ["EngineError", "Model", "Policy", "backends"]
