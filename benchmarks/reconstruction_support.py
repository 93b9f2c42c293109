"""How far from the scan a reconstruction may reach: metrics of ViewPlanning-v1 scans meshed
with the support trim at several multiples of the cloud's point spacing.

``reconstruct`` removes mesh vertices farther than ``support_distance`` from every cleaned
point (default ``DEFAULT_SUPPORT_SPACINGS`` times the cloud's median point spacing). This
scans objects with the four-view baseline and the greedy oracle and reports Chamfer
distance, precision, recall and F-score at each multiple, 0 meaning no trim, and with the
default (which takes Poisson's cell instead where that is larger). The default was
chosen on the train objects with the command below::

    MUJOCO_GL=egl python -m benchmarks.reconstruction_support --object-set train --episodes 8
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
from scipy.spatial import cKDTree

import liuxing_envs  # noqa: F401  (registers the envs)
from agents.view_baselines import FourViewpointBaseline, GreedyOracle
from liuxing_envs.sim.objects import OBJECT_SETS

DEFAULT_SPACINGS = (0.0, 1.5, 2.0, 3.0, 4.0, 6.0)
DEFAULT_SEED = 5000


def median_spacing(cloud_points: np.ndarray) -> float:
    """Median distance from each point to its nearest other point."""
    distance, _ = cKDTree(cloud_points).query(cloud_points, k=2)
    return float(np.median(distance[:, 1]))


def measure(object_set: str, episodes: int, spacings, seed: int = DEFAULT_SEED) -> dict:
    """Mean metrics per multiple of the spacing over ``episodes`` scans per baseline."""
    env = gym.make("ViewPlanning-v1", object_set=object_set, action_mode="continuous")
    rows = {k: [] for k in (*spacings, "default")}
    spacing_mm = []
    for policy in (FourViewpointBaseline(env), GreedyOracle(env)):
        for episode in range(episodes):
            obs, _ = env.reset(seed=seed + episode)
            policy.reset(seed=seed + episode)
            done = False
            while not done:
                action, _ = policy.predict(obs, deterministic=True)
                obs, _, terminated, truncated, _ = env.step(action)
                done = terminated or truncated
            untrimmed, _ = env.unwrapped.reconstruct(support_distance=0.0)
            spacing = median_spacing(np.asarray(untrimmed.cloud.points))
            spacing_mm.append(1000 * spacing)
            for k in rows:
                distance = None if k == "default" else k * spacing
                _, metrics = env.unwrapped.reconstruct(support_distance=distance)
                rows[k].append(
                    [1000 * metrics["chamfer"], metrics["precision"], metrics["recall"]]
                    + [metrics["fscore"]]
                )
    env.close()
    return {
        "median_spacing_mm": float(np.mean(spacing_mm)),
        "scans": len(spacing_mm),
        "rows": {k: np.mean(v, axis=0).tolist() for k, v in rows.items()},
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--object-set", default="train", choices=sorted(OBJECT_SETS))
    parser.add_argument("--episodes", type=int, default=8, help="scans per baseline")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help="first episode seed")
    parser.add_argument(
        "--spacings", type=float, nargs="+", default=DEFAULT_SPACINGS, help="0: no trim"
    )
    args = parser.parse_args(argv)
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    if any(not np.isfinite(k) or k < 0 for k in args.spacings):
        parser.error(f"--spacings must be finite and >= 0, got {args.spacings}")
    result = measure(args.object_set, args.episodes, args.spacings, args.seed)
    print(
        f"{result['scans']} scans of {args.object_set} objects (four-view and greedy-oracle, "
        f"seeds {args.seed}-{args.seed + args.episodes - 1}); median point spacing "
        f"{result['median_spacing_mm']:.2f} mm"
    )
    print("| spacings | Chamfer mm | precision | recall | F-score |")
    print("| --- | --- | --- | --- | --- |")
    for k, (chamfer, precision, recall, fscore) in result["rows"].items():
        label = {0: "no trim", "default": "the default"}.get(k, f"{k:g}")
        print(f"| {label} | {chamfer:.2f} | {precision:.3f} | {recall:.3f} | {fscore:.3f} |")


if __name__ == "__main__":
    main()
