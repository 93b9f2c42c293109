"""Acceptance run of the scripted grasping baselines on InstrumentGrasp-v1.

Run: ``MUJOCO_GL=egl python -m benchmarks.instrument_grasp_baselines [--episodes 50]``.
Every baseline sees the same seeded episodes (instrument, pose) of the registered env with
``obs_mode="rgbd"`` and default kwargs (episodes run the full 200 steps: a success must
survive the rest of the episode). Prints a Markdown table per instrument set: success rate
(95% Wilson interval), peak fingertip force (median and max), episodes ended by the hard
limit, and the mean number of control steps above the force limit.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

import liuxing_envs  # noqa: E402, F401
from agents.grasp_baselines import GRASP_BASELINES  # noqa: E402
from agents.statistics import wilson_interval  # noqa: E402
from liuxing_envs.sim.instruments import INSTRUMENT_SETS  # noqa: E402


def run(baseline: str, episodes: int, instrument_set: str) -> dict:
    env = gym.make("InstrumentGrasp-v1", obs_mode="rgbd", instrument_set=instrument_set)
    policy = GRASP_BASELINES[baseline](env)
    outcomes = []
    start = time.perf_counter()
    for seed in range(episodes):
        observation, info = env.reset(seed=seed)
        policy.reset(seed=seed)
        done = False
        while not done:
            action, _ = policy.predict(observation, deterministic=True)
            observation, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        outcomes.append(info)
    env.close()
    successes = sum(o["is_success"] for o in outcomes)
    peaks = np.array([o["peak_force"] for o in outcomes])
    return {
        "success": successes / episodes,
        "ci": wilson_interval(successes, episodes),
        "peak_median": float(np.median(peaks)),
        "peak_max": float(peaks.max()),
        "hard_limit": sum(o["hard_limit_exceeded"] for o in outcomes),
        "violations": float(np.mean([o["force_violations"] for o in outcomes])),
        "failures": sorted({o["instrument"] for o in outcomes if not o["is_success"]}),
        "seconds": time.perf_counter() - start,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument(
        "--sets", nargs="+", choices=list(INSTRUMENT_SETS), default=["train", "held_out"]
    )
    parser.add_argument(
        "--baselines", nargs="+", choices=list(GRASP_BASELINES), default=list(GRASP_BASELINES)
    )
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    for instrument_set in args.sets:
        print(
            f"\nInstrumentGrasp-v1, {instrument_set} instruments, obs_mode=rgbd, "
            f"{args.episodes} episodes (seeds 0-{args.episodes - 1})\n"
        )
        print(
            "| baseline | success | 95% CI | peak force median N | max N | hard-limit ends | "
            "steps above limit / ep | failed on | wall s |"
        )
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for name in args.baselines:
            r = run(name, args.episodes, instrument_set)
            low, high = r["ci"]
            print(
                f"| {name} | {r['success']:.2f} | [{low:.2f}, {high:.2f}] | "
                f"{r['peak_median']:.1f} | {r['peak_max']:.1f} | {r['hard_limit']} | "
                f"{r['violations']:.1f} | {', '.join(r['failures']) or '-'} | "
                f"{r['seconds']:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
