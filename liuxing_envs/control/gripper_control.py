"""Gripper controllers: how the action's last entry drives the fingers.

Each keeps the commanded opening the observation reports (the action's, before the approach
guard shortens a finger's target; after a reset or a protective stop, the opening it left)."""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING

from liuxing_envs.sim.gripper import MAX_OPENING

if TYPE_CHECKING:
    from liuxing_envs.envs.instrument_grasp_settings import GripperControl
    from liuxing_envs.sim.gripper import Gripper


class GripperController(abc.ABC):
    """The commanded-opening bookkeeping every mode shares; each mode says how it drives."""

    def __init__(self, settings: GripperControl) -> None:
        self.commanded_opening = 0.0

    def prepare(self, gripper: Gripper) -> None:  # noqa: B027 (a hook most modes leave empty)
        """Set up a world's gripper for this mode (once, when the env is made)."""

    def sync(self, gripper: Gripper) -> None:
        """Take the gripper's own command as the commanded opening (after a reset, a stop)."""
        self.commanded_opening = gripper.commanded_opening()

    def apply(self, gripper: Gripper, command) -> None:
        """Drive the fingers by the action's gripper entry ``command`` (in [-1, 1])."""
        self.drive(gripper, command)
        self.sync(gripper)

    @abc.abstractmethod
    def drive(self, gripper: Gripper, command) -> None:
        """Command the fingers for ``command`` (the action's gripper entry, in [-1, 1])."""


class OpeningGripper(GripperController):
    """``gripper_control="opening"``: the pad opening to servo to, 0 m at -1 (closed) to
    MAX_OPENING at +1."""

    def drive(self, gripper: Gripper, command) -> None:
        gripper.command((command + 1.0) / 2.0 * MAX_OPENING)


class DeltaGripper(GripperController):
    """``gripper_control="delta"``: the change of the commanded opening, up to
    ``max_gripper_delta`` m per step."""

    def __init__(self, settings: GripperControl) -> None:
        super().__init__(settings)
        self.max_gripper_delta = settings.max_gripper_delta

    def drive(self, gripper: Gripper, command) -> None:
        gripper.command(self.commanded_opening + self.max_gripper_delta * command)


class ForceGripper(GripperController):
    """``gripper_control="force"``: the grip force, as an industrial gripper's force setting:
    each finger servos closed (> 0) or open (< 0) with at most |command| x ``max_grip_force``
    N, its speed capped by damping."""

    def __init__(self, settings: GripperControl) -> None:
        super().__init__(settings)
        self.max_grip_force = settings.max_grip_force

    def prepare(self, gripper: Gripper) -> None:
        gripper.use_force_commands()

    def drive(self, gripper: Gripper, command) -> None:
        gripper.grip(self.max_grip_force * float(command))


GRIPPER_CONTROLLERS = {"opening": OpeningGripper, "delta": DeltaGripper, "force": ForceGripper}


def gripper_controller(settings: GripperControl) -> GripperController:
    """The controller ``settings.gripper_control`` names."""
    return GRIPPER_CONTROLLERS[settings.gripper_control](settings)
