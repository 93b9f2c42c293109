"""ViewPlanning's arm motion: to a camera pose looking at the centre, by a checked path."""

from __future__ import annotations

import numpy as np

from liuxing_envs.sim.arm import Arm, JointPath, MotionResult
from liuxing_envs.sim.viewpoints import look_at

#: Random IK restarts per requested view (after the current and home seeds). Unreachable
#: views cost every restart, so fewer than the Arm's default; roll-free IK rarely needs many.
VIEW_IK_RESTARTS = 4


class ViewMotion:
    """Moves the camera arm to a view: IK for the camera at the eye looking at the centre
    (any roll), within the joint limits; the straight joint path if it is free, else one
    through the home pose; then ``"kinematic"`` (set along the checked path) or
    ``"dynamic"`` (the servos follow it under physics, stopping at a contact or a waypoint
    not reached in time)."""

    def __init__(self, mode: str) -> None:
        self.mode = mode

    @staticmethod
    def plan(arm: Arm, eye: np.ndarray, center: np.ndarray) -> JointPath | None:
        """The arm's path to the camera at ``eye`` looking at ``center`` (any roll), or None
        when no IK solution or no collision-free path reaches it."""
        ik = arm.solve_ik(eye, look_at(eye, center), roll_free=True, restarts=VIEW_IK_RESTARTS)
        return arm.plan_path(ik.qpos) if ik.success else None

    def follow(self, arm: Arm, plan: JointPath) -> MotionResult:
        return arm.follow(plan, self.mode)
