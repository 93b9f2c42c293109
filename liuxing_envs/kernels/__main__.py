"""``python -m liuxing_envs.kernels``: compile every kernel into numba's disk cache now.

A kernel compiles at its first call in any process whose cache does not hold it yet: about
45 seconds for ViewPlanning's on one core, which the first training, evaluation or test
worker would otherwise pay. ``make install`` runs this once per checkout. It steps the envs
briefly in the settings that reach every kernel, so each one is compiled for exactly the
argument types the envs pass it. Numba recompiles a kernel by itself when its source
changes.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

#: name: (env id, keyword arguments). Between them they call every kernel.
WARM_UPS = {
    "ViewPlanning-v1": ("ViewPlanning-v1", {}),
    "ViewPlanning-v1 with free space, discrete": (
        "ViewPlanning-v1",
        {"observe_free_space": True, "privileged": True, "action_mode": "discrete"},
    ),
    "InstrumentGrasp-v1 state": ("InstrumentGrasp-v1", {}),
    "InstrumentGrasp-v1 depth": ("InstrumentGrasp-v1", {"obs_mode": "depth"}),
}
STEPS = 12


def warm_up(env_id: str, kwargs: dict, steps: int = STEPS) -> None:
    """Step ``env_id`` with seeded random actions (and preview a view, for ViewPlanning)."""
    import gymnasium as gym

    import liuxing_envs  # noqa: F401  (registers the ids)

    env = gym.make(env_id, **kwargs)
    env.action_space.seed(0)
    env.reset(seed=0)
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    if hasattr(env.unwrapped, "preview_view"):
        env.unwrapped.preview_view(0.0, 0.6, 0.4)
    env.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m liuxing_envs.kernels", description=__doc__.splitlines()[0]
    )
    parser.parse_args(argv)
    from liuxing_envs import kernels

    if not kernels.available():
        print("numba is not installed: the envs run their numpy and MuJoCo references")
        return
    if not kernels.disk_cache():
        print("no folder for numba's cache can be written: nothing to keep")
        return
    started = time.perf_counter()
    for name, (env_id, kwargs) in WARM_UPS.items():
        print(f"compiling the kernels {name} calls ...", flush=True)
        warm_up(env_id, kwargs)
    print(f"kernels compiled and cached in {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
