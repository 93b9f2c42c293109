"""Throughput and memory of ViewPlanning-v0 per depth backend, motion mode and resolution.

Run: ``MUJOCO_GL=egl python -m benchmarks.view_planning [--steps 600 --repeats 3]``.
Each configuration runs in a fresh process (one core's worth of work: a single env), taking
uniformly random actions with resets included, after a warm-up episode. Prints a Markdown
table: env steps/s (median, min and max over repeats) and the process's peak resident memory.
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

from benchmarks.isolated import random_action_throughput, run_in_fresh_process  # noqa: E402

CONFIGS = [
    ("raycast", "kinematic", 64),
    ("gl", "kinematic", 64),
    ("raycast", "dynamic", 64),
    ("gl", "dynamic", 64),
    ("raycast", "kinematic", 128),
    ("gl", "kinematic", 128),
]


def measure(backend: str, motion: str, resolution: int, steps: int, repeats: int) -> dict:
    from liuxing_envs.envs.view_planning import ViewPlanningEnv

    env = ViewPlanningEnv(depth_backend=backend, motion=motion, resolution=resolution)
    return random_action_throughput(env, steps, repeats, warmup=env.view_budget)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--one", nargs=3, metavar=("BACKEND", "MOTION", "RESOLUTION"))
    args = parser.parse_args()
    if args.one:
        backend, motion, resolution = args.one
        print(json.dumps(measure(backend, motion, int(resolution), args.steps, args.repeats)))
        return
    print(f"ViewPlanning-v0 defaults, random actions, {args.steps} steps x {args.repeats}\n")
    print("| backend | motion | depth | steps/s median | min | max | peak RSS MiB |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for backend, motion, resolution in CONFIGS:
        r = run_in_fresh_process(
            "benchmarks.view_planning",
            *("--steps", str(args.steps), "--repeats", str(args.repeats)),
            *("--one", backend, motion, str(resolution)),
        )
        print(
            f"| {backend} | {motion} | {resolution}x{resolution} | {r['median']:.0f} | "
            f"{r['min']:.0f} | {r['max']:.0f} | {r['mib']:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
