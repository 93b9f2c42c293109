"""The approach guard: slows an ``ee_delta`` step, and a closing finger, near the instrument.

For each pad between GUARD_MIN_GAP and ``approach_distance`` of the instrument, the arm's
set-point (its forward kinematics, the fingers as open as now) may lead the pad toward the
instrument's nearest point by at most ``approach_lead_limit`` + ``approach_lead_slope`` x the
pad's gap: a braking ramp, as a cobot's speed and separation monitoring slows it near an
obstacle. A compliant servo presses with about its stiffness times its lead when the pad
lands, so this bounds that push, which the force terms cannot see coming. A step asking for
more is shortened, translation and yaw by one factor (to holding the pose where even that leads
too far). With ``approach_guard_fingers`` a closing finger's servo target is shortened too, so
that its pad, carried by the arm's set-point and its finger together, keeps the same ramp. The
guard reads the instrument's geometry from the simulator: privileged, as the ``instrument``
observation is.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from liuxing_envs.envs.instrument_grasp_settings import Safety
    from liuxing_envs.sim.grasp_world import GraspWorld

#: The guard watches pads down to this gap (m); a pad touching the instrument is left to the
#: grip (its lead across the handle is what squeezes it).
GUARD_MIN_GAP = 1e-5
#: The guard's scale is refined at most this many times, until no lead is over the limit by
#: more than GUARD_TOLERANCE (m).
GUARD_TRIES = 4
GUARD_TOLERANCE = 1e-6

#: An arm controller's set-point for an action, its move times a scale (None: refused).
SetPoint = Callable[["GraspWorld", np.ndarray, float], "np.ndarray | None"]


class ApproachGuard:
    """The guard of one env's settings; :attr:`active` is False without a lead limit."""

    def __init__(self, settings: Safety) -> None:
        self.distance = settings.approach_distance
        self.lead_limit = (
            None if settings.approach_lead_limit is None else float(settings.approach_lead_limit)
        )
        self.lead_slope = float(settings.approach_lead_slope)
        self.guards_fingers = bool(settings.approach_guard_fingers)

    @property
    def active(self) -> bool:
        """Whether it guards the arm's moves at all."""
        return self.lead_limit is not None

    def near_pads(self, world: GraspWorld) -> list:
        """The pads it watches now: ``(pad, direction toward the instrument, gap)`` each."""
        return world.approach_directions(self.distance, min_gap=GUARD_MIN_GAP)

    def lead_limits(self, near) -> list[float]:
        """The lead (m) it allows each of the ``near`` pads."""
        return [self.lead_limit + self.lead_slope * gap for _, _, gap in near]

    def limit_set_point(
        self, world: GraspWorld, arm_action: np.ndarray, qpos: np.ndarray, near, set_point: SetPoint
    ) -> tuple[np.ndarray | None, list | None, bool]:
        """``qpos``, the set-point of ``arm_action``, or where it runs too far ahead of one of
        the ``near`` pads, the set-point of the same move shortened until it does not (to
        nothing: hold the pose); with the ``near`` pads' leads at it (None with the set-point)
        and whether it shortened the move."""
        limits = self.lead_limits(near)
        leads = world.pad_leads(near, qpos)
        if all(lead <= limit for lead, limit in zip(leads, limits, strict=True)):
            return qpos, leads, False
        held = set_point(world, arm_action, scale=0.0)
        if held is None:
            return None, None, True
        held_leads = world.pad_leads(near, held)
        # Holding still leads a little (the set-point points the tool straight down, the
        # compliant arm tilts). A translation moves the pads rigidly, so each lead is linear in
        # the move's scale between holding and the step; a yaw bends that, so the scale is
        # refined from where each try lands. A move that leads less than holding is not cut.
        scale = 1.0
        for _ in range(GUARD_TRIES):
            shorter = scale
            for lead, held_lead, limit in zip(leads, held_leads, limits, strict=True):
                gain = lead - held_lead
                if lead > limit and gain > 0.0:
                    shorter = min(shorter, scale * max(0.0, limit - held_lead) / gain)
            if shorter == scale:
                break
            scale = shorter
            qpos = set_point(world, arm_action, scale) if scale > 0.0 else held
            if qpos is None:
                return held, held_leads, True
            leads = world.pad_leads(near, qpos) if scale > 0.0 else held_leads
            if all(
                lead <= limit + GUARD_TOLERANCE for lead, limit in zip(leads, limits, strict=True)
            ):
                break
        return qpos, leads, True

    def brake_fingers(self, world: GraspWorld, near, arm_leads: list | None) -> bool:
        """Shorten the servo target of each finger closing toward the instrument so that its
        pad, carried also by the arm's set-point (``arm_leads``, or None to measure them),
        leads no more than allowed; whether it shortened one."""
        gripper = world.gripper
        if arm_leads is None:
            arm_leads = world.pad_leads(near, world.arm_ctrl())
        closing = gripper.closing_directions()
        shortened = False
        for (pad, toward, _), arm_lead, limit in zip(
            near, arm_leads, self.lead_limits(near), strict=True
        ):
            finger = gripper.finger_of(pad)
            rate = float(closing[finger] @ toward)  # pad travel toward it per m of closing
            if rate > 0.0:
                spare = max(0.0, limit - arm_lead)
                shortened |= gripper.limit_closing(finger, spare / rate)
        return shortened
