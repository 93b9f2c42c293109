"""Arm controllers: how the arm part of an action moves the arm's joint set-points.

Each takes its settings part (:class:`~liuxing_envs.envs.instrument_grasp_settings.ArmControl`)
and drives a :class:`~liuxing_envs.sim.grasp_world.GraspWorld` through its named queries."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from liuxing_envs import kernels
from liuxing_envs.sim.arm_ik import IK_LIMIT_SLACK
from liuxing_envs.sim.grasp_world import tool_down
from liuxing_envs.sim.gripper import TCP_SITE

if TYPE_CHECKING:
    from liuxing_envs.envs.instrument_grasp_settings import ArmControl
    from liuxing_envs.safety.approach_guard import ApproachGuard
    from liuxing_envs.sim.grasp_world import GraspWorld

#: Largest joint set-point change (rad) an ee_delta step may ask for. A step's own moves need
#: a few tenths at most; switching to another IK configuration needs about pi.
MAX_SETPOINT_JUMP = 1.0


class ArmMove:
    """What an arm step left for the approach guard's finger brake: the pads it watches this
    step (``(pad, direction, gap)`` each; none when it is off) and their leads at the new
    set-point (None where the set-point did not change), and whether the guard slowed it."""

    __slots__ = ("leads", "near", "slowed")

    def __init__(self, near: list | None = None, leads: list | None = None, slowed=False):
        self.near, self.leads, self.slowed = near or [], leads, slowed


class JointDeltaController:
    """``controller="joint_delta"``: the action moves each arm joint's set-point by up to
    ``max_joint_delta`` rad, within the joint limits."""

    action_size: ClassVar[int] = 6

    def __init__(self, settings: ArmControl) -> None:
        self.max_joint_delta = settings.max_joint_delta

    def apply(self, world: GraspWorld, arm_action: np.ndarray, guard: ApproachGuard) -> ArmMove:
        ctrl = world.arm_ctrl() + self.max_joint_delta * arm_action
        world.set_arm_ctrl(np.clip(ctrl, world.arm.lower, world.arm.upper))
        return ArmMove()


class EndEffectorDeltaController:
    """``controller="ee_delta"``: the action moves the tool centre by up to
    ``max_translation`` m per axis and turns it by up to ``max_yaw`` rad about world z, from
    where it is now, the tool pointing down. The target is clipped to the workspace above the
    tray and solved with the arm's closed-form IK; a target it cannot reach, or reaches only
    by switching arm configuration (a joint jumping by more than MAX_SETPOINT_JUMP), leaves
    the set-point where it was. The approach guard may shorten the move."""

    action_size: ClassVar[int] = 4

    def __init__(self, settings: ArmControl) -> None:
        self.max_translation, self.max_yaw = settings.max_translation, settings.max_yaw

    def apply(self, world: GraspWorld, arm_action: np.ndarray, guard: ApproachGuard) -> ArmMove:
        qpos = self.set_point(world, arm_action)
        move = ArmMove()
        if guard.active:
            move.near = guard.near_pads(world)
            if qpos is not None:
                qpos, move.leads, move.slowed = guard.limit_set_point(
                    world, arm_action, qpos, move.near, self.set_point
                )
        if qpos is not None:
            world.set_arm_ctrl(qpos)
        return move

    def set_point(
        self, world: GraspWorld, arm_action: np.ndarray, scale: float = 1.0
    ) -> np.ndarray | None:
        """The arm joint set-point ``arm_action`` asks for, its move (after the workspace clip)
        times ``scale``, or None where it is refused."""
        # Displacements are from the actual pose (not the last target), so a zero action holds
        # the arm where it is and pushing against the tray cannot wind its servos up.
        reference = world.arm_ctrl()
        if world.compiled:
            one_pose_ik = kernels.module("one_pose_ik")
            dgemm = kernels.numpy_dgemm()
            data, arm = world.data, world.arm
            move = (arm_action, self.max_translation, self.max_yaw, scale)
            workspace = (world.workspace_lower, world.workspace_upper)
            if dgemm is not None:  # the whole set-point in one call
                base_inverse, flange_in_site = arm.ik.flange_frames(TCP_SITE)
                qpos = one_pose_ik.ee_delta_set_point(
                    data.site_xpos, data.site_xmat, world.tcp_site, *move, *workspace,
                    base_inverse, flange_in_site, dgemm, reference, arm.lower, arm.upper,
                    IK_LIMIT_SLACK, one_pose_ik.CONSTANTS, MAX_SETPOINT_JUMP,
                )  # fmt: skip
                return qpos if len(qpos) else None
            pose = one_pose_ik.tool_target_pose(
                data.site_xpos, data.site_xmat, world.tcp_site, *move, *workspace
            )
            qpos = arm.closed_form_nearest_pose(pose, reference, site=TCP_SITE)
        else:
            qpos = world.arm.closed_form_nearest(
                *self._target(world, arm_action, scale), reference, site=TCP_SITE
            )
        # Near a joint limit the nearest solution can be another arm configuration (elbow or
        # wrist flipped), which a servo would swing to across the workspace: refused, as an
        # unreachable target is.
        if qpos is not None and np.abs(qpos - reference).max() <= MAX_SETPOINT_JUMP:
            return qpos
        return None

    def _target(
        self, world: GraspWorld, arm_action: np.ndarray, scale: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The tool-centre position and rotation ``arm_action`` asks for (the reference of
        :func:`~liuxing_envs.kernels.one_pose_ik.tool_target_pose`)."""
        # np.minimum and np.maximum clip as np.clip does, at half its cost.
        tcp = world.tcp_position()
        lower, upper = world.workspace_lower, world.workspace_upper
        target = np.minimum(np.maximum(tcp + self.max_translation * arm_action[:3], lower), upper)
        yaw_change = self.max_yaw * float(arm_action[3])
        if scale != 1.0:
            start = np.minimum(np.maximum(tcp, lower), upper)  # a zero action's target
            target = start + scale * (target - start)
            yaw_change *= scale
        yaw = world.tcp_yaw() + yaw_change
        yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
        return target, tool_down(yaw)


ARM_CONTROLLERS = {"ee_delta": EndEffectorDeltaController, "joint_delta": JointDeltaController}


def arm_controller(settings: ArmControl) -> EndEffectorDeltaController | JointDeltaController:
    """The controller ``settings.controller`` names."""
    return ARM_CONTROLLERS[settings.controller](settings)
