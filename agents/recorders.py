"""What an evaluation records of each episode, per environment.

A recorder sees the reset ``info`` (:meth:`begin`), every step's reward and ``info``
(:meth:`step`) and returns the episode's figures at its end (:meth:`end`), all JSON-ready.
``run_episodes`` in :mod:`agents.evaluation` drives it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from liuxing_envs.open3d_import import o3d

#: Coverage levels whose "views needed" the reports give.
COVERAGE_LEVELS = (0.90, 0.95)
TRACE_DIGITS = 4


def _first_reaching(values, level: float) -> int | None:
    reached = np.flatnonzero(np.asarray(values) >= level)
    return int(reached[0]) if reached.size else None


class ViewPlanningRecorder:
    """Per episode: the object and its pose, coverage after each view (index 0: the start view
    alone), views needed for each of :data:`COVERAGE_LEVELS` (``None``: not reached), refused
    views, joint path length and motion cost; for the first ``reconstruct_episodes`` episodes
    also the reconstruction's Chamfer distance, precision, completeness and F-score (open3d
    Poisson meshing, about a second each). The first ``save_episodes`` of those write their
    .ply/.pcd files and the observable ground-truth surface to ``save_dir/seed_<seed>/``."""

    def __init__(
        self,
        reconstruct_episodes: int = 0,
        save_dir: Path | None = None,
        save_episodes: int = 0,
    ) -> None:
        self.reconstruct_episodes = reconstruct_episodes
        self.save_dir = None if save_dir is None else Path(save_dir)
        self.save_episodes = save_episodes if save_dir is not None else 0

    def begin(self, env, info: dict) -> None:
        self.coverage = [float(info["coverage"])]
        self.refused = 0
        self.path_length = 0.0
        self.motion_cost = 0.0

    def step(self, env, reward: float, info: dict) -> None:
        self.coverage.append(float(info["coverage"]))
        self.refused += int(info["refused"])
        self.path_length += float(info["path_length"])
        self.motion_cost -= float(info.get("reward_motion", 0.0))

    def end(self, env, index: int, seed: int) -> dict:
        scene = env.unwrapped
        placed = scene.placed
        record = {
            "object": placed.name,
            "scale": float(placed.scale),
            "position": [round(float(v), 6) for v in placed.position],
            "yaw": round(float(placed.yaw), 6),
            "coverage_after_view": [round(c, TRACE_DIGITS + 2) for c in self.coverage],
            "refused_views": self.refused,
            "joint_path_length": self.path_length,
            "motion_cost": self.motion_cost,
        }
        for level in COVERAGE_LEVELS:
            record[f"views_to_{round(100 * level)}"] = _first_reaching(self.coverage, level)
        if index < self.reconstruct_episodes:
            save_dir = None
            if index < self.save_episodes:
                save_dir = self.save_dir / f"seed_{seed}"
                tracker = scene.coverage
                truth = placed.to_world(tracker.samples[tracker.observable])
                save_dir.mkdir(parents=True, exist_ok=True)
                cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(truth))
                o3d.io.write_point_cloud(str(save_dir / "ground_truth.ply"), cloud)
            reconstruction, metrics = scene.reconstruct(save_dir)
            record["has_mesh"] = bool(reconstruction.has_mesh)
            for key in ("chamfer", "precision", "completeness", "fscore"):
                value = float(metrics[key])
                # Nothing fused gives an infinite Chamfer distance: None keeps report.json
                # strict JSON, and the summaries count the episode as having none.
                record[key] = value if np.isfinite(value) else None
        return record


class GraspRecorder:
    """Per episode: the instrument and where it lay at the start (its grasp point's x, y and
    its handle's yaw, so that pairing checks the pose too), success, the episode's peak
    fingertip force, control steps over the force limit, whether the hard limit ended it, the
    highest lift, the time to first reach the target lift while grasped (``None``: never), and
    the per-step peak pad force."""

    def begin(self, env, info: dict) -> None:
        scene = env.unwrapped
        self.dt = scene.dt
        self.target_height = scene.target_height
        #: The env's limits and control period, for the report's figures.
        self.limits = {
            "force_limit": scene.force_limit,
            "hard_limit": scene.hard_limit,
            "dt": scene.dt,
        }
        self.forces: list[float] = []
        self.lift = 0.0
        self.time_to_lift = None
        world = scene.world
        axis = world.grasp_axis()
        self.start = {
            "start_position": [round(float(v), 6) for v in world.grasp_point()[:2]],
            "start_yaw": round(math.atan2(axis[1], axis[0]), 6),
        }

    def step(self, env, reward: float, info: dict) -> None:
        self.forces.append(round(float(info["step_peak_force"]), TRACE_DIGITS))
        self.lift = max(self.lift, float(info["lift_height"]))
        if (
            self.time_to_lift is None
            and info["grasped"]
            and info["lift_height"] >= self.target_height
        ):
            self.time_to_lift = len(self.forces) * self.dt

    def end(self, env, index: int, seed: int) -> dict:
        return {
            "instrument": env.unwrapped.world.name,
            **self.start,
            "max_lift": self.lift,
            "time_to_lift": self.time_to_lift,
            "force_trace": self.forces,
        }
