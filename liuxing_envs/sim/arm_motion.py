"""Motion of the live arm along a straight joint path or a planned one.

Two ways to move, both collision-checked and reporting the same :class:`MotionResult`:

``kinematic``
    The configuration is set directly along the straight joint-space path. The path is checked
    waypoint by waypoint first; if it would collide, the arm stops at the last collision-free
    waypoint (like a protective stop) and reports the contact. Fast; no dynamics.
``dynamic``
    The position actuators track a set-point that moves along the same path at a bounded joint
    speed, under full physics (gravity compensation, torque limits), until the arm settles
    within tolerance of the target or a timeout. A contact between the arm and anything halts
    the set-point where the arm is (a protective stop).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from liuxing_envs.sim.arm_collisions import Contact, JointPath, arm_contacts
from liuxing_envs.sim.arm_model import ArmPart
from liuxing_envs.sim.stability import diverged_since, divergence_count
from liuxing_envs.validation import require_number

if TYPE_CHECKING:
    from liuxing_envs.sim.arm import Arm
    from liuxing_envs.sim.arm_collisions import ArmCollisions

MOTION_MODES = ("kinematic", "dynamic")

#: Dynamic moves last ``max|Δq| / max_joint_speed``: the set-point's mean speed on the
#: joint that moves most. Its cubic ease peaks at 1.5 times that (1.5 rad/s), still well
#: under the UR5e's 3.14 rad/s.
DYNAMIC_MAX_JOINT_SPEED = 1.0  # rad/s
DYNAMIC_CONTROL_PERIOD = 0.01  # s between set-point updates and contact checks
DYNAMIC_SETTLE_TOLERANCE = 1e-3  # rad, every joint
DYNAMIC_SETTLE_SPEED = 0.02  # rad/s, every joint
DYNAMIC_TIMEOUT = 8.0  # s of simulated time


@dataclass(frozen=True)
class MotionResult:
    """Outcome of :meth:`ArmMotion.move_to` and :meth:`ArmMotion.follow`.

    ``path_length`` is the joint-space distance actually travelled (sum of the Euclidean norms
    of the joint increments, radians). ``sim_time`` is the simulated time the motion took
    (0 for kinematic motion). ``unstable`` means the physics diverged during a dynamic
    motion (see :mod:`liuxing_envs.sim.stability`): MuJoCo reset the data, so the motion
    stopped there and the live state is no longer the episode's.
    """

    reached: bool
    qpos: np.ndarray
    path_length: float
    collided: bool
    contacts: tuple[Contact, ...]
    sim_time: float
    mode: str
    unstable: bool = False


class ArmMotion(ArmPart):
    """Moves an :class:`~liuxing_envs.sim.arm.Arm` (its live data), kinematically or under
    physics, stopping at contacts found by ``collisions``."""

    def __init__(self, arm: Arm, collisions: ArmCollisions) -> None:
        super().__init__(arm)
        self._collisions = collisions

    def move_to(
        self,
        qpos: np.ndarray,
        mode: str = "kinematic",
        *,
        max_joint_speed: float = DYNAMIC_MAX_JOINT_SPEED,
        timeout: float = DYNAMIC_TIMEOUT,
        settle_tolerance: float = DYNAMIC_SETTLE_TOLERANCE,
    ) -> MotionResult:
        """Move the live arm to joint configuration ``qpos`` along the straight joint path
        (see the module docstring)."""
        target = self._arm.checked_qpos(qpos)
        _check_mode(mode)
        _check_dynamic_settings(max_joint_speed, timeout, settle_tolerance)
        if mode == "kinematic":
            return self._move_kinematic(target)
        return self._move_dynamic(target, max_joint_speed, timeout, settle_tolerance)

    def follow(
        self,
        path: JointPath,
        mode: str = "kinematic",
        *,
        max_joint_speed: float = DYNAMIC_MAX_JOINT_SPEED,
        timeout: float = DYNAMIC_TIMEOUT,
        settle_tolerance: float = DYNAMIC_SETTLE_TOLERANCE,
    ) -> MotionResult:
        """Execute a path from :meth:`~liuxing_envs.sim.arm_collisions.ArmCollisions.plan_path`,
        which must start at the current configuration.

        Kinematic motion trusts the plan's collision checks and jumps to the goal; dynamic
        motion drives the servos through every waypoint under physics (``timeout`` applies
        to each segment) and stops at the first contact or missed waypoint.
        """
        _check_mode(mode)
        _check_dynamic_settings(max_joint_speed, timeout, settle_tolerance)
        now = self._arm.qpos
        # np.allclose(path.start, now, atol=1e-9) spelled out: it is hot and costs 10 us.
        if not (np.abs(path.start - now) <= 1e-9 + 1e-5 * np.abs(now)).all():
            raise ValueError("the path does not start at the arm's current configuration")
        if mode == "kinematic":
            self._arm.set_qpos(path.waypoints[-1])
            return MotionResult(True, path.waypoints[-1].copy(), path.length, False, (), 0.0, mode)
        travelled, sim_time = 0.0, 0.0
        for waypoint in path.waypoints:
            result = self._move_dynamic(waypoint, max_joint_speed, timeout, settle_tolerance)
            travelled += result.path_length
            sim_time += result.sim_time
            if not result.reached:
                break
        return MotionResult(
            result.reached,
            result.qpos,
            travelled,
            result.collided,
            result.contacts,
            sim_time,
            mode,
            result.unstable,
        )

    def _move_kinematic(self, target: np.ndarray) -> MotionResult:
        start = self._arm.qpos
        check = self._collisions.check_path(start, target)
        final = target if check.free else check.last_free_qpos
        self._arm.set_qpos(final)
        return MotionResult(
            reached=check.free,
            qpos=final.copy(),
            path_length=float(np.linalg.norm(final - start)),
            collided=not check.free,
            contacts=check.contacts,
            sim_time=0.0,
            mode="kinematic",
        )

    def _move_dynamic(self, target, max_joint_speed, timeout, settle_tolerance) -> MotionResult:
        arm = self._arm
        m, d = arm.model, arm.data
        actuator_ids = arm.actuator_ids
        live_scene = self._collisions.live_scene
        start = arm.qpos
        delta = target - start
        duration = float(np.max(np.abs(delta))) / max_joint_speed
        substeps = max(1, round(DYNAMIC_CONTROL_PERIOD / m.opt.timestep))
        period = substeps * m.opt.timestep
        t = 0.0
        previous = start
        path_length = 0.0
        divergences = divergence_count(d)
        while t < timeout:
            progress = min(1.0, t / duration) if duration > 0 else 1.0
            d.ctrl[actuator_ids] = start + _smoothstep(progress) * delta
            mujoco.mj_step(m, d, nstep=substeps)
            t += period
            if diverged_since(d, divergences):
                return MotionResult(
                    False, arm.qpos, path_length, False, (), t, "dynamic", unstable=True
                )
            q = arm.qpos
            path_length += float(np.linalg.norm(q - previous))
            previous = q
            contacts = arm_contacts(d, live_scene)
            if contacts:
                d.ctrl[actuator_ids] = q
                return MotionResult(False, q, path_length, True, contacts, t, "dynamic")
            settled = (
                progress >= 1.0
                and np.max(np.abs(q - target)) <= settle_tolerance
                and np.max(np.abs(arm.qvel)) <= DYNAMIC_SETTLE_SPEED
            )
            if settled:
                return MotionResult(True, q, path_length, False, (), t, "dynamic")
        return MotionResult(False, arm.qpos, path_length, False, (), t, "dynamic")


def _check_mode(mode: str) -> None:
    if mode not in MOTION_MODES:
        raise ValueError(f"unknown motion mode {mode!r}; allowed: {MOTION_MODES}")


def _check_dynamic_settings(max_joint_speed, timeout, settle_tolerance) -> None:
    # A speed of 0 divided by zero; a negative or NaN one skipped the ramp and stepped the
    # servos to the goal at once.
    require_number("max_joint_speed", max_joint_speed, 1e-6, math.inf)
    require_number("timeout", timeout, 1e-6, math.inf)
    require_number("settle_tolerance", settle_tolerance, 1e-9, math.inf)


def _smoothstep(s: float) -> float:
    """Zero-velocity start and end for the dynamic set-point (cubic ease)."""
    return s * s * (3.0 - 2.0 * s)
