"""Acceptance run of the scripted view-planning baselines on held-out objects.

Run: ``MUJOCO_GL=egl python -m benchmarks.view_planning_baselines [--episodes 50]``.
Every baseline sees the same seeded episodes (object, scale, pose). Prints a Markdown table
of final coverage (mean, 95% bootstrap CI) and the mean number of refused views.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from agents.statistics import bootstrap_ci, interval_text  # noqa: E402
from agents.view_baselines import BASELINES  # noqa: E402
from liuxing_envs.envs.view_planning import OBJECT_SET_NAMES, ViewPlanningEnv  # noqa: E402


def run(baseline: str, episodes: int, object_set: str, budget: int) -> dict:
    env = ViewPlanningEnv(action_mode="discrete", object_set=object_set, view_budget=budget)
    policy = BASELINES[baseline](env)
    finals, refused = [], []
    start = time.perf_counter()
    for seed in range(episodes):
        obs, info = env.reset(seed=seed)
        policy.reset(seed=seed)
        refusals, done = 0, False
        while not done:
            action, _ = policy.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            refusals += info["refused"]
            done = terminated or truncated
        finals.append(info["coverage"])
        refused.append(refusals)
    env.close()
    finals = np.array(finals)
    return {
        "mean": float(finals.mean()),
        "ci": bootstrap_ci(finals),
        "refused": float(np.mean(refused)),
        "seconds": time.perf_counter() - start,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--object-set", choices=OBJECT_SET_NAMES, default="held_out")
    parser.add_argument("--budget", type=int, default=4)
    args = parser.parse_args()
    if args.episodes < 1 or not 1 <= args.budget <= 64:
        parser.error(
            f"--episodes must be at least 1 and --budget within [1, 64] views, got "
            f"{args.episodes} and {args.budget}"
        )
    print(
        f"ViewPlanning-v1, {args.object_set} objects, {args.budget} views, discrete actions, "
        f"{args.episodes} episodes (seeds 0-{args.episodes - 1}), default kwargs\n"
    )
    print("| baseline | final coverage | 95% CI | refused views / episode | wall s |")
    print("| --- | --- | --- | --- | --- |")
    for name in BASELINES:
        result = run(name, args.episodes, args.object_set, args.budget)
        print(
            f"| {name} | {result['mean']:.3f} | {interval_text(result['ci'])} | "
            f"{result['refused']:.2f} | {result['seconds']:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
