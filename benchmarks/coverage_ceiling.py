"""How much of ViewPlanning-v1's observable surface an arm-bound camera can cover at all.

Coverage counts the samples that some view of the env's view space sees, judged by ray
casting from view positions around the object's middle, with no arm, field of view or pixel
grid. This measures what that leaves out, for the default continuous action space. Per
episode, every view of the same set (at both ends of ``radius_range``: 24 azimuths on each of
four elevation rings across ``elevation_range_deg`` and the top view, 194 views in all)
around the env's estimated centre is tried from home: IK seeded there, a collision-checked
path, and, where both exist, a depth image fused into the episode's coverage (noise-free
unless the env given to :func:`measure_episode` has depth noise).
It reports:

* ``covered``: the coverage after every view reachable from home (what a policy with any
  budget can reach with these views; from another start a few more or fewer views are
  reachable);
* ``seen_from_reachable``: the share of the observable samples that the reachable views see
  by the same ray cast as the observable set (what the arm's reach alone costs);
* ``seen_from_all``: the same from all the views around the estimated centre (what aiming at
  the estimate instead of the true middle costs).

::

    python -m benchmarks.coverage_ceiling --object-set held_out --episodes 30
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import liuxing_envs  # noqa: F401  (registers the envs)
from liuxing_envs.sim.objects import (
    DEFAULT_OBSERVATION_AZIMUTH_COUNT,
    OBJECT_SETS,
    observable_mask,
    observable_samples,
    observation_viewpoints,
)

DEFAULT_SEED = 20_000


def measure_episode(env, seed: int) -> dict:
    """Take every reachable view of one episode (``env``: the unwrapped env) from home."""
    env.reset(seed=seed)
    placed, tracker, arm = env.placed, env.coverage, env.arm
    home = arm.qpos.copy()
    radii, elevations = env.actions.observation_views
    # The views that decide the env's observable set, around its estimated centre.
    eyes = observation_viewpoints(radii, center=env.center, elevations_deg=elevations)
    reachable = np.zeros(len(eyes), dtype=bool)
    for k, eye in enumerate(eyes):
        arm.set_qpos(home)
        plan = env.arm_motion.plan(arm, eye, env.center)
        if plan is None:
            continue
        reachable[k] = True
        arm.set_qpos(plan.waypoints[-1])
        tracker.update(placed.to_object(env.sensor.preview_points(env.scene)))
    mesh = env.scene.stage.meshes[placed.name]
    samples = observable_samples(
        mesh, placed.scale, env.coverage_samples, radii=radii, elevations_deg=elevations
    )
    observable = tracker.observable  # what the env counts
    mesh = mesh.scaled(placed.scale)

    def seen(view_positions: np.ndarray) -> float:
        if len(view_positions) == 0:
            return 0.0
        eyes_object = placed.to_object(view_positions)
        mask = observable_mask(mesh, samples.points, samples.normals, eyes_object)
        return float((mask & observable).sum() / observable.sum())

    return {
        "object": placed.name,
        "scale": placed.scale,
        "views": len(eyes),
        "reachable_views": int(reachable.sum()),
        "covered": float(tracker.coverage),
        "seen_from_reachable": seen(eyes[reachable]),
        "seen_from_all": seen(eyes),
    }


def measure(object_set: str, episodes: int, seed: int = DEFAULT_SEED) -> list[dict]:
    env = gym.make("ViewPlanning-v1", object_set=object_set, depth_backend="raycast")
    try:
        return [measure_episode(env.unwrapped, seed + k) for k in range(episodes)]
    finally:
        env.close()


def _summary(rows: list[dict]) -> str:
    keys = ("covered", "seen_from_reachable", "seen_from_all")
    lines = [
        "| object | episodes | reachable views | covered | seen from reachable | seen from all |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for name in sorted({row["object"] for row in rows}) + ["all"]:
        group = [row for row in rows if name in ("all", row["object"])]
        views = [row["reachable_views"] for row in group]
        cells = [
            f"{np.mean([r[k] for r in group]):.4f} (min {min(r[k] for r in group):.4f})"
            for k in keys
        ]
        lines.append(
            f"| {name} | {len(group)} | {min(views)}-{max(views)} of {group[0]['views']} | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--object-set", choices=sorted(OBJECT_SETS), default="held_out")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    rows = measure(args.object_set, args.episodes, args.seed)
    print(
        f"ViewPlanning-v1 ({args.object_set}, seeds {args.seed}-{args.seed + args.episodes - 1}, "
        f"continuous view space, {DEFAULT_OBSERVATION_AZIMUTH_COUNT} azimuths per ring)"
    )
    print(_summary(rows))


if __name__ == "__main__":
    main()
