"""Throughput and memory of InstrumentGrasp-v0 per observation mode.

Run: ``MUJOCO_GL=egl python -m benchmarks.instrument_grasp [--steps 2000 --repeats 3]``.
Each configuration runs in a fresh process (one core's worth of work: a single env made with
``gym.make``, so the 200-step TimeLimit and its resets are included), taking uniformly random
actions after a warm-up. Random actions keep the gripper near the instrument and the tray
about as often as a learning policy early in training. Prints a Markdown table: env steps/s
(median, min and max over repeats) and the process's peak resident memory.
Targets (issue 4): >= 1,500 steps/s with ``state``, >= 400 with ``depth`` at 64x64.
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

from benchmarks.isolated import random_action_throughput, run_in_fresh_process  # noqa: E402

CONFIGS = [  # (obs_mode, depth backend, resolution)
    ("state", "gl", 64),
    ("depth", "gl", 64),
    ("depth", "raycast", 64),
    ("rgbd", "gl", 64),
]


def measure(obs_mode: str, backend: str, resolution: int, steps: int, repeats: int) -> dict:
    import gymnasium as gym

    import liuxing_envs  # noqa: F401

    env = gym.make(
        "InstrumentGrasp-v0", obs_mode=obs_mode, depth_backend=backend, resolution=resolution
    )
    return random_action_throughput(env, steps, repeats, warmup=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--one", nargs=3, metavar=("OBS_MODE", "BACKEND", "RESOLUTION"))
    args = parser.parse_args()
    if args.one:
        obs_mode, backend, resolution = args.one
        print(json.dumps(measure(obs_mode, backend, int(resolution), args.steps, args.repeats)))
        return
    print(f"InstrumentGrasp-v0, random actions, {args.steps} steps x {args.repeats}\n")
    print("| obs_mode | depth backend | image | steps/s median | min | max | peak RSS MiB |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for obs_mode, backend, resolution in CONFIGS:
        r = run_in_fresh_process(
            "benchmarks.instrument_grasp",
            *("--steps", str(args.steps), "--repeats", str(args.repeats)),
            *("--one", obs_mode, backend, str(resolution)),
        )
        image = "-" if obs_mode == "state" else f"{resolution}x{resolution}"
        print(
            f"| {obs_mode} | {backend if obs_mode != 'state' else '-'} | {image} | "
            f"{r['median']:.0f} | {r['min']:.0f} | {r['max']:.0f} | {r['mib']:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
