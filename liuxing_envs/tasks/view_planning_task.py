"""ViewPlanning's task: coverage of the object's observable surface, the view budget, the
reward terms, success, when the episode ends, and what ``info`` reports of it."""

from __future__ import annotations

import math

import numpy as np
from gymnasium import spaces

from liuxing_envs.envs.view_planning_settings import TaskSettings
from liuxing_envs.perception.coverage import CoverageTracker
from liuxing_envs.sim.object_stage import PlacedObject

VIEW_HISTORY_FEATURES = 5


class ViewPlanningTask:
    """Counts the views of an episode against the budget and pays for what they add.

    ``reward = coverage_reward_scale * coverage gain - motion_cost * joint path length -
    refusal_penalty * refused``; each term is in ``info``. Spending the budget terminates
    the episode (the observation counts it down, so no value lies beyond the last view);
    with ``terminate_on_success`` so does reaching ``success_coverage``.
    """

    def __init__(self, settings: TaskSettings) -> None:
        self.view_budget = settings.view_budget
        self.success_coverage = float(settings.success_coverage)
        self.terminate_on_success = bool(settings.terminate_on_success)
        self.coverage_reward_scale = float(settings.coverage_reward_scale)
        self.motion_cost = float(settings.motion_cost)
        self.refusal_penalty = float(settings.refusal_penalty)
        self.privileged = bool(settings.privileged)
        self.coverage: CoverageTracker | None = None
        self.views_used = 0
        self.history = np.zeros((self.view_budget, VIEW_HISTORY_FEATURES), dtype=np.float32)

    def reset(self, coverage: CoverageTracker) -> None:
        """A new episode, scanned by ``coverage`` (the placed variant's tracker)."""
        self.coverage = coverage
        self.coverage.reset()
        self.views_used = 0
        self.history[:] = 0.0

    def record_view(self, view, refused: bool, radii: tuple[float, float]) -> None:
        """One view of the budget used, as requested: cos and sin of its azimuth, elevation
        / 90°, radius normalised over ``radii``, +1 reached / -1 refused."""
        azimuth, elevation, radius = view
        self.history[self.views_used] = [
            math.cos(azimuth),
            math.sin(azimuth),
            elevation / (np.pi / 2),
            (radius - radii[0]) / max(radii[1] - radii[0], 1e-9),
            -1.0 if refused else 1.0,
        ]
        self.views_used += 1

    def reward_terms(self, gain: float, path_length: float, refused: bool) -> dict[str, float]:
        return {
            "reward_coverage": self.coverage_reward_scale * gain,
            "reward_motion": -self.motion_cost * path_length,
            "reward_refusal": -self.refusal_penalty * float(refused),
        }

    def preview_reward(self, gain: float, path_length: float) -> float:
        """What a reached view with this gain and path would earn."""
        return self.coverage_reward_scale * gain - self.motion_cost * path_length

    def info(
        self,
        gain: float,
        terms: dict,
        placed: PlacedObject,
        *,
        planned: bool,
        refused: bool,
        path: float,
        unstable: bool = False,
    ) -> dict:
        coverage = self.coverage.coverage
        return {
            **terms,
            "coverage": coverage,
            "coverage_gain": gain,
            "views_used": self.views_used,
            "reachable": planned,
            "refused": refused,
            "path_length": path,
            "is_success": coverage >= self.success_coverage,
            "object": placed.name,
            "scale": placed.scale,
            "sim_unstable": unstable,
        }

    def episode_end(self, info: dict, unstable: bool) -> tuple[bool, bool]:
        """(terminated, truncated) after a view."""
        # The budget is part of the task (the observation counts it down), so spending it
        # ends the episode as a terminal state: truncation would have learners bootstrap
        # from views that can never follow.
        terminated = self.views_used >= self.view_budget or (
            self.terminate_on_success and info["is_success"]
        )
        # A diverged simulation (dynamic motion only) was reset by MuJoCo: the episode's
        # state is gone, so it ends here; reset() starts a clean one.
        truncated = unstable and not terminated
        return terminated, truncated

    def observation_spaces(self) -> dict[str, spaces.Box]:
        found = {
            "view_history": spaces.Box(-1.0, 1.0, (self.history.size,), dtype=np.float32),
            "budget": spaces.Box(0.0, 1.0, (1,), dtype=np.float32),
        }
        if self.privileged:
            found["coverage"] = spaces.Box(0.0, 1.0, (1,), dtype=np.float32)
        return found

    def observation(self) -> dict[str, np.ndarray]:
        """The view history, the share of the budget left and, if privileged, coverage."""
        obs = {
            "view_history": self.history.flatten(),
            "budget": np.array([1.0 - self.views_used / self.view_budget], dtype=np.float32),
        }
        if self.privileged:
            obs["coverage"] = np.array([self.coverage.coverage], dtype=np.float32)
        return obs
