"""The force monitor: runs a control step's physics, sampling the pad forces and the impact on
the instrument, and makes the protective stop a real arm's force monitor makes."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import mujoco

from liuxing_envs.sim.gripper import GRASP_NOSLIP_ITERATIONS
from liuxing_envs.sim.stability import diverged_since, divergence_count

if TYPE_CHECKING:
    from liuxing_envs.envs.instrument_grasp_settings import Safety
    from liuxing_envs.sim.grasp_world import GraspWorld

#: Forces are sampled every this many physics steps (10 ms at the default timestep).
FORCE_SAMPLE_SUBSTEPS = 5


class ForcePeaks(NamedTuple):
    """A control step's peaks (N) over its force samples, and how it ended (a named tuple:
    made every step, it costs a third of a frozen dataclass)."""

    left: float = 0.0
    right: float = 0.0
    impact: float = 0.0
    #: The protective stop held the arm and fingers (a hard limit was passed).
    stopped: bool = False
    #: The physics diverged (MuJoCo reset its data): the figures mean nothing.
    diverged: bool = False

    @property
    def pad(self) -> float:
        """The higher pad's peak."""
        return max(self.left, self.right)


class ForceMonitor:
    """Steps the physics ``substeps`` at a time, sampling forces every FORCE_SAMPLE_SUBSTEPS;
    a pad force over ``hard_limit`` or an impact over ``hard_impact_limit`` stops the arm and
    the fingers where they are and ends the step there."""

    def __init__(self, settings: Safety, substeps: int) -> None:
        self.hard_limit, self.hard_impact_limit = settings.hard_limit, settings.hard_impact_limit
        #: The physics steps of each force sample: FORCE_SAMPLE_SUBSTEPS, the last the rest.
        self._samples = tuple(
            min(FORCE_SAMPLE_SUBSTEPS, substeps - start)
            for start in range(0, substeps, FORCE_SAMPLE_SUBSTEPS)
        )

    @property
    def substeps(self) -> int:
        """Physics steps per control step (fixed when the monitor is made)."""
        return sum(self._samples)

    def run(self, world: GraspWorld) -> ForcePeaks:
        model, data, gripper = world.model, world.data, world.gripper
        # This loop runs once per force sample (five times a step by default), so it keeps to
        # Python floats and plain comparisons (numpy's and max()'s per-call overhead cost more
        # than the bookkeeping's arithmetic), looks the methods and settings it calls up once
        # (``mujoco.mj_step`` once per call: a benchmark wraps it) and passes ``nstep`` by
        # position, which pybind11 takes faster than a keyword.
        forces, impact_force = gripper.fingertip_force_values, world.impact_force
        step, options = mujoco.mj_step, model.opt
        hard_limit, hard_impact_limit = self.hard_limit, self.hard_impact_limit
        peak_left = peak_right = impact_peak = 0.0
        stopped = False
        left, right = forces()
        divergences = divergence_count(data)
        noslip = options.noslip_iterations
        for substeps in self._samples:
            # Noslip iterations stop a held instrument creeping in the pads; they cost a third
            # of a physics step, so they run only while a pad touches something.
            wanted = GRASP_NOSLIP_ITERATIONS if max(left, right) > 0.0 else 0
            if wanted != noslip:
                options.noslip_iterations = noslip = wanted
            step(model, data, substeps)
            left, right = forces()
            impact = impact_force()
            # As max(): a new peak only where it is higher (NaN never is).
            if left > peak_left:
                peak_left = left
            if right > peak_right:
                peak_right = right
            if impact > impact_peak:
                impact_peak = impact
            if peak_left > hard_limit or peak_right > hard_limit or impact_peak > hard_impact_limit:
                # Protective stop: hold the arm and the fingers where they are and end the step
                # (and the episode) here.
                world.set_arm_ctrl(world.arm.qpos)
                gripper.command(gripper.opening())
                stopped = True
                step(model, data, FORCE_SAMPLE_SUBSTEPS)
                left, right = forces()
                peak_left, peak_right = max(peak_left, left), max(peak_right, right)
                impact_peak = max(impact_peak, impact_force())
                break
        # Checked once per control step: after a divergence MuJoCo's reset state is finite,
        # so the loop above runs on harmlessly, and its figures are discarded by the caller.
        diverged = diverged_since(data, divergences)
        return ForcePeaks(peak_left, peak_right, impact_peak, stopped, diverged)

    def broke_limit(self, peaks: ForcePeaks) -> bool:
        """Whether the step's peaks passed a hard limit."""
        return peaks.pad > self.hard_limit or peaks.impact > self.hard_impact_limit
