"""InstrumentGrasp's task: the reward terms, success, and the episode's statistics."""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, NamedTuple

if TYPE_CHECKING:
    from liuxing_envs.envs.instrument_grasp_settings import InstrumentGraspSettings
    from liuxing_envs.safety.force_monitor import ForcePeaks
    from liuxing_envs.sim.grasp_world import GraspWorld

#: The most the reach, grasp, lift and hold terms pay in one step.
MAX_STEP_REWARD = 5.0
REWARD_TERMS = (
    "reward_reach", "reward_grasp", "reward_lift", "reward_hold",
    "reward_force", "reward_impact", "reward_approach", "reward_failure", "reward_success",
)  # fmt: skip


@dataclasses.dataclass
class EpisodeStats:
    """What an episode has counted so far."""

    #: Control steps taken.
    steps: int = 0
    #: Consecutive steps grasped at the target height.
    hold_count: int = 0
    #: Whether the instrument has been held long enough.
    held: bool = False
    #: The episode's peak pad force (N).
    peak_force: float = 0.0
    #: Control steps whose peak pad force was over the limit.
    force_violations: int = 0
    #: Control steps whose peak impact was over the limit.
    impact_violations: int = 0
    #: Control steps whose arm move the approach guard shortened.
    guarded_steps: int = 0
    #: Control steps in which the approach guard shortened a finger's target.
    guarded_finger_steps: int = 0


class StepResult(NamedTuple):
    """A control step's reward terms and what they make of it (a named tuple, as
    :class:`~liuxing_envs.safety.force_monitor.ForcePeaks`)."""

    terms: dict
    reward: float
    success: bool
    terminated: bool
    grasped: bool
    lift: float


class InstrumentGraspTask:
    """Lift the instrument by ``target_height`` and hold it, grasped, for ``hold_time``, the
    pad forces never over ``force_limit``. Reads the world through its named queries."""

    def __init__(self, settings: InstrumentGraspSettings) -> None:
        task, safety = settings.task, settings.safety
        self.force_limit, self.impact_limit = safety.force_limit, safety.impact_limit
        self.target_height = task.target_height
        # At height for a step at least.
        self.hold_steps = max(1, round(task.hold_time * settings.timing.control_hz))
        self.reach_sharpness = float(task.reach_sharpness)
        self.force_penalty, self.impact_penalty = task.force_penalty, task.impact_penalty
        self.failure_penalty = task.failure_penalty
        self.approach_penalty, self.approach_allowance = (
            task.approach_penalty,
            task.approach_allowance,
        )
        self.approach_distance = safety.approach_distance
        self.terminate_on_success = bool(task.terminate_on_success)
        self.episode_steps = task.episode_steps
        self.stats = EpisodeStats()
        self.start_height = 0.0

    def reset(self, world: GraspWorld) -> None:
        """Start an episode's statistics, the instrument placed."""
        self.stats = EpisodeStats()
        self.start_height = world.grasp_point()[2]

    def approach(self, world: GraspWorld) -> float:
        """The approach penalty's measure (m) for the arm's new set-point: how far it carries
        the near pads toward the instrument beyond ``approach_allowance``, summed (0 when the
        penalty is off)."""
        if not self.approach_penalty:
            return 0.0
        return sum(
            max(0.0, move - self.approach_allowance)
            for move in world.pad_approaches(self.approach_distance)
        )

    def count_guard(self, slowed: bool, fingers_braked: bool) -> None:
        """Count the approach guard's interventions in this step."""
        self.stats.guarded_steps += slowed
        self.stats.guarded_finger_steps += fingers_braked

    def step(
        self, world: GraspWorld, peaks: ForcePeaks, broke_limit: bool, approach: float
    ) -> StepResult:
        """Count a control step whose physics ran to ``peaks`` and score it."""
        stats = self.stats
        stats.steps += 1
        grasped = world.grasped()
        grasp_point = world.grasp_point()
        lift = grasp_point[2] - self.start_height
        at_height = grasped and lift >= self.target_height
        stats.hold_count = stats.hold_count + 1 if at_height else 0
        step_peak = peaks.pad
        stats.peak_force = max(stats.peak_force, step_peak)
        stats.force_violations += step_peak > self.force_limit
        stats.impact_violations += peaks.impact > self.impact_limit
        stats.held = stats.held or stats.hold_count >= self.hold_steps
        success = stats.held and stats.peak_force <= self.force_limit
        ends_in_success = success and self.terminate_on_success

        offset = world.tcp_position() - grasp_point
        distance = math.sqrt(offset.dot(offset))  # np.linalg.norm's own sum, without its checks
        terms = {
            "reward_reach": 1.0 - math.tanh(self.reach_sharpness * distance),
            "reward_grasp": float(grasped),
            "reward_lift": 2.0 * min(1.0, max(lift, 0.0) / self.target_height) if grasped else 0.0,
            "reward_hold": float(at_height),
            "reward_force": -self.force_penalty
            * (max(peaks.left - self.force_limit, 0.0) + max(peaks.right - self.force_limit, 0.0)),
            "reward_impact": -self.impact_penalty * max(0.0, peaks.impact - self.impact_limit),
            "reward_approach": -self.approach_penalty * approach,
            "reward_failure": -self.failure_penalty if broke_limit else 0.0,
            # Ending early must not pay less than holding on until the episode's end would.
            "reward_success": MAX_STEP_REWARD * max(0, self.episode_steps - stats.steps)
            if ends_in_success and not broke_limit
            else 0.0,
        }
        return StepResult(
            terms=terms,
            reward=float(sum(terms.values())),
            success=success,
            terminated=bool(broke_limit or ends_in_success),
            grasped=grasped,
            lift=lift,
        )

    def unstable_step(self) -> dict:
        """Count a step whose physics diverged: its reward terms, every one 0."""
        self.stats.steps += 1
        return dict.fromkeys(REWARD_TERMS, 0.0)

    def info(
        self,
        world: GraspWorld,
        terms: dict,
        *,
        grasped: bool,
        step_peak: float,
        success: bool,
        lift: float,
        unstable: bool = False,
        broke_limit: bool = False,
    ) -> dict:
        """The step's ``info``: its reward terms and the episode's statistics."""
        stats = self.stats
        return {
            **terms,
            "is_success": bool(success),
            "grasped": bool(grasped),
            "peak_force": stats.peak_force,
            "step_peak_force": step_peak,
            "grip_force": max(world.gripper.fingertip_force_values()),
            "lift_height": float(lift),
            "force_violations": stats.force_violations,
            "impact_violations": stats.impact_violations,
            "guarded_steps": stats.guarded_steps,
            "guarded_finger_steps": stats.guarded_finger_steps,
            "instrument": world.name,
            "sim_unstable": unstable,
            "hard_limit_exceeded": bool(broke_limit),
        }
