"""The force monitor: runs a control step's physics, sampling the pad forces and the impact on
the instrument, and makes the protective stop a real arm's force monitor makes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco

from liuxing_envs.sim.gripper import GRASP_NOSLIP_ITERATIONS
from liuxing_envs.sim.stability import diverged_since, divergence_count

if TYPE_CHECKING:
    from liuxing_envs.envs.instrument_grasp_settings import Safety
    from liuxing_envs.sim.grasp_world import GraspWorld

#: Forces are sampled every this many physics steps (10 ms at the default timestep).
FORCE_SAMPLE_SUBSTEPS = 5


@dataclass(frozen=True)
class ForcePeaks:
    """A control step's peaks (N) over its force samples, and how it ended."""

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
        self.substeps = substeps

    def run(self, world: GraspWorld) -> ForcePeaks:
        model, data, gripper = world.model, world.data, world.gripper
        # The pads' peaks as Python floats: this loop runs once per force sample (five times a
        # step by default), and numpy's per-call overhead on 2-vectors cost more than the
        # bookkeeping's arithmetic; for the same reason the methods and settings it calls are
        # looked up once (``mujoco.mj_step`` once per call: a benchmark wraps it).
        forces, impact_force = gripper.fingertip_force_values, world.impact_force
        step, options, substeps = mujoco.mj_step, model.opt, self.substeps
        hard_limit, hard_impact_limit = self.hard_limit, self.hard_impact_limit
        peak_left = peak_right = impact_peak = 0.0
        stopped = False
        left, right = forces()
        divergences = divergence_count(data)
        for start in range(0, substeps, FORCE_SAMPLE_SUBSTEPS):
            # Noslip iterations stop a held instrument creeping in the pads; they cost a third
            # of a physics step, so they run only while a pad touches something.
            options.noslip_iterations = GRASP_NOSLIP_ITERATIONS if max(left, right) > 0.0 else 0
            step(model, data, nstep=min(FORCE_SAMPLE_SUBSTEPS, substeps - start))
            left, right = forces()
            peak_left, peak_right = max(peak_left, left), max(peak_right, right)
            impact_peak = max(impact_peak, impact_force())
            if max(peak_left, peak_right) > hard_limit or impact_peak > hard_impact_limit:
                # Protective stop: hold the arm and the fingers where they are and end the step
                # (and the episode) here.
                world.set_arm_ctrl(world.arm.qpos)
                gripper.command(gripper.opening())
                stopped = True
                step(model, data, nstep=FORCE_SAMPLE_SUBSTEPS)
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
