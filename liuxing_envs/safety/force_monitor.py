"""The force monitor: runs a control step's physics, sampling the pad forces and the impact on
the instrument, and makes the protective stop a real arm's force monitor makes."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import mujoco
import numpy as np

from liuxing_envs import kernels
from liuxing_envs.sim.gripper import GRASP_NOSLIP_ITERATIONS
from liuxing_envs.sim.stability import DIVERGENCE_WARNINGS, diverged_since, divergence_count

if TYPE_CHECKING:
    from liuxing_envs.envs.instrument_grasp_settings import Safety
    from liuxing_envs.sim.grasp_world import GraspWorld

#: Forces are sampled every this many physics steps (10 ms at the default timestep).
FORCE_SAMPLE_SUBSTEPS = 5


def noslip_wanted(left: float, right: float) -> int:
    """The noslip iterations for the next physics steps, given the pad forces now: noslip
    stops a held instrument creeping in the pads, and costs a third of a physics step, so it
    runs only while a pad touches something."""
    return GRASP_NOSLIP_ITERATIONS if max(left, right) > 0.0 else 0


class _CompiledLoop(NamedTuple):
    """The compiled loop's arguments for one world's data (addresses of this process)."""

    layout: np.ndarray
    samples: np.ndarray
    limits: np.ndarray
    divergence: np.ndarray
    trap: object  # liuxing_envs.sim.mujoco_errors.ErrorTrap


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

    #: The compiled loop's arguments per world, by ``id`` of its data: (data, arguments),
    #: the data kept so that its id stays its own (addresses of this process: never pickled).
    _compiled: dict | None = None

    def __init__(self, settings: Safety, substeps: int) -> None:
        self.hard_limit, self.hard_impact_limit = settings.hard_limit, settings.hard_impact_limit
        #: The physics steps of each force sample: FORCE_SAMPLE_SUBSTEPS, the last the rest.
        self._samples = tuple(
            min(FORCE_SAMPLE_SUBSTEPS, substeps - start)
            for start in range(0, substeps, FORCE_SAMPLE_SUBSTEPS)
        )

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_compiled"] = None
        return state

    @property
    def substeps(self) -> int:
        """Physics steps per control step (fixed when the monitor is made)."""
        return sum(self._samples)

    def run(self, world: GraspWorld) -> ForcePeaks:
        arguments = self._compiled_loop(world) if world.compiled else None
        compiled = None
        if arguments is not None and arguments.trap.lock.acquire(blocking=False):
            try:
                compiled = self._run_compiled(world, arguments)
            finally:
                arguments.trap.lock.release()
        if compiled is not None:
            peaks, first, stepped, stopped, divergences, diverged = compiled
            if not stopped and first < len(self._samples):
                peaks, stopped = self._run_python(world, peaks, first, stepped)
        else:  # no kernel, its buffers in another thread's use, or a MuJoCo hook set
            divergences = divergence_count(world.data)
            peaks, stopped = self._run_python(world, (0.0, 0.0, 0.0), 0, False)
            diverged = None
        if stopped:
            peaks = self._stop(world, peaks)
        if diverged is None:
            # Checked once per control step: after a divergence MuJoCo's reset state is
            # finite, so the loop above runs on harmlessly, and its figures are discarded by
            # the caller.
            diverged = diverged_since(world.data, divergences)
        return ForcePeaks(*peaks, stopped, diverged)

    def _run_python(self, world: GraspWorld, peaks: tuple, first: int, stepped: bool):
        """The samples from ``first`` (whose physics has run already when ``stepped``):
        ``(peaks, stopped)``."""
        model, data = world.model, world.data
        # This loop runs once per force sample (five times a step by default), so it keeps to
        # Python floats and plain comparisons (numpy's and max()'s per-call overhead cost more
        # than the bookkeeping's arithmetic), looks the methods and settings it calls up once
        # (``mujoco.mj_step`` once per call: a benchmark wraps it) and passes ``nstep`` by
        # position, which pybind11 takes faster than a keyword.
        forces, impact_force = world.gripper.fingertip_force_values, world.impact_force
        step, options = mujoco.mj_step, model.opt
        hard_limit, hard_impact_limit = self.hard_limit, self.hard_impact_limit
        peak_left, peak_right, impact_peak = peaks
        left, right = forces()
        noslip = options.noslip_iterations
        for sample in range(first, len(self._samples)):
            if sample > first or not stepped:
                wanted = noslip_wanted(left, right)
                if wanted != noslip:
                    options.noslip_iterations = noslip = wanted
                step(model, data, self._samples[sample])
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
                return (peak_left, peak_right, impact_peak), True
        return (peak_left, peak_right, impact_peak), False

    def _run_compiled(self, world: GraspWorld, arguments: _CompiledLoop):
        """The samples the compiled loop takes, while the instrument sleeps: ``(peaks, the
        sample the Python loop goes on from, whether that sample's physics has run, stopped,
        the divergence count before the step, whether the step diverged)``, the last None
        where the Python loop goes on or the kernel cannot decide (then the caller checks);
        None where a MuJoCo hook holds user code and the kernel did nothing."""
        kernel = kernels.module("force_loop")

        layout, samples, limits, divergence, trap = arguments
        limits[kernel.HARD_LIMIT] = self.hard_limit
        limits[kernel.HARD_IMPACT_LIMIT] = self.hard_impact_limit
        options = world.model.opt
        peaks = np.zeros(3)
        first = 0
        while True:
            status, first = kernel.sleeping_samples(
                layout, samples, first, options.noslip_iterations, peaks, limits, divergence
            )
            if status != kernel.NOSLIP:
                break
            options.noslip_iterations = noslip_wanted(*world.gripper.fingertip_force_values())
        if status == kernel.FAILED:
            raise trap.error()
        if status == kernel.HOOKED and first == 0:
            return None
        # (A hook set by another thread between two calls of this step leaves the rest of
        # the step, from that sample, to the Python loop.)
        count, verdict = divergence.tolist()
        diverged = None
        if status == kernel.DONE and verdict != kernel.UNDECIDED:
            diverged = verdict == kernel.DIVERGED
        stepped, stopped = status == kernel.AWAKE, status == kernel.STOPPED
        return tuple(peaks.tolist()), first, stepped, stopped, count, diverged

    def _compiled_loop(self, world: GraspWorld) -> _CompiledLoop | None:
        """The compiled loop's arguments for ``world`` (made once per world), or None where
        a kernel cannot call MuJoCo safely here (:mod:`liuxing_envs.sim.mujoco_errors`)."""
        if self._compiled is None:
            self._compiled = {}
        made = self._compiled.get(id(world.data))
        if made is not None:
            return made[1]
        from liuxing_envs.sim.mujoco_errors import error_trap, function_address

        kernel, data = kernels.module("force_loop"), world.data
        trap, mj_step = error_trap(), function_address("mj_step")
        if trap is None or mj_step is None:
            self._compiled[id(data)] = (data, None)  # not asked again
            return None
        layout = np.empty(kernel.LAYOUT_SIZE, dtype=np.int64)
        layout[kernel.MJ_STEP], layout[kernel.SET_HANDLER] = mj_step, trap.set_handler
        layout[kernel.HANDLER] = trap.handler
        layout[kernel.JUMP_BUFFER] = trap.jump_buffer.ctypes.data
        layout[kernel.MODEL], layout[kernel.DATA] = world.model._address, data._address
        # The arrays are views of mjData's own memory, which stays where it is while data lives
        # (this monitor keeps a reference to it with the addresses).
        warnings = data.warning.number
        for entry, array in (
            (kernel.SENSORDATA, data.sensordata),
            (kernel.TREE_ASLEEP, data.tree_asleep),
            (kernel.QPOS, data.qpos),
            (kernel.QVEL, data.qvel),
            (kernel.WARNING_NUMBERS, warnings),
        ):
            layout[entry] = array.ctypes.data
        layout[kernel.WARNING_STRIDE] = warnings.strides[0]
        layout[[kernel.LEFT_TOUCH, kernel.RIGHT_TOUCH]] = world.gripper.touch_addresses
        layout[kernel.TREE] = world.instrument_tree
        layout[kernel.NOSLIP_WHEN_TOUCHING] = GRASP_NOSLIP_ITERATIONS
        layout[kernel.NQ], layout[kernel.NV] = world.model.nq, world.model.nv
        layout[kernel.HOOKS], layout[kernel.HOOK_COUNT] = trap.hooks.ctypes.data, len(trap.hooks)
        layout[kernel.DIVERGENCE_WARNINGS :] = [int(warning) for warning in DIVERGENCE_WARNINGS]
        limits = np.array([self.hard_limit, self.hard_impact_limit], dtype=np.float64)
        samples = np.array(self._samples, dtype=np.int64)
        divergence = np.zeros(2, dtype=np.int64)
        arguments = _CompiledLoop(layout, samples, limits, divergence, trap)
        self._compiled[id(data)] = (data, arguments)
        return arguments

    def _stop(self, world: GraspWorld, peaks: tuple) -> tuple:
        """Protective stop: hold the arm and the fingers where they are and step one force
        sample more; the peaks with that sample's."""
        gripper = world.gripper
        world.set_arm_ctrl(world.arm.qpos)
        gripper.command(gripper.opening())
        mujoco.mj_step(world.model, world.data, FORCE_SAMPLE_SUBSTEPS)
        left, right = gripper.fingertip_force_values()
        peak_left, peak_right, impact_peak = peaks
        return (
            max(peak_left, left),
            max(peak_right, right),
            max(impact_peak, world.impact_force()),
        )

    def broke_limit(self, peaks: ForcePeaks) -> bool:
        """Whether the step's peaks passed a hard limit."""
        return peaks.pad > self.hard_limit or peaks.impact > self.hard_impact_limit
