"""InstrumentGrasp's sensors: what the policy observes of the world each control step.

Proprioception and the fingertip forces always; then, by ``obs_mode``, the instrument's state
(``"state"``, PRIVILEGED: read from the simulator) or the wrist camera's depth (``"depth"``)
and colour (``"rgbd"``)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from gymnasium import spaces

from liuxing_envs import kernels
from liuxing_envs.sim.camera import CameraIntrinsics
from liuxing_envs.sim.grasp_world import jaws_across

if TYPE_CHECKING:
    from liuxing_envs.envs.instrument_grasp_settings import GraspSensors
    from liuxing_envs.sim.grasp_world import GraspWorld

#: Depth observations are uint8 (what SB3's CNNs take): level 0 = no return, levels 1-255
#: span this z-depth range linearly (about 2 mm per level); farther saturates at 255.
DEPTH_RANGE = (0.1, 0.6)  # m


def encode_depth(depth_m: np.ndarray) -> np.ndarray:
    """uint8 levels of a z-depth image in metres (see DEPTH_RANGE; 0 = no return)."""
    near, far = DEPTH_RANGE
    levels = 1.0 + np.round((np.clip(depth_m, near, far) - near) / (far - near) * 254.0)
    return np.where(depth_m > 0, levels, 0.0).astype(np.uint8)


def decode_depth(levels: np.ndarray) -> np.ndarray:
    """z-depth in metres of the ``depth`` observation's levels (0 where no return)."""
    near, far = DEPTH_RANGE
    levels = np.asarray(levels, dtype=np.float64)
    return np.where(levels > 0, near + (levels - 1.0) / 254.0 * (far - near), 0.0)


def observation_space(obs_mode: str, resolution: int) -> spaces.Dict:
    """The observation space of ``obs_mode`` with square images of ``resolution`` pixels."""
    obs = {
        "proprio": spaces.Box(-np.inf, np.inf, (19,), dtype=np.float32),
        "forces": spaces.Box(0.0, np.inf, (2,), dtype=np.float32),
    }
    if obs_mode == "state":
        obs["instrument"] = spaces.Box(-np.inf, np.inf, (14,), dtype=np.float32)
    else:
        obs["depth"] = spaces.Box(0, 255, (1, resolution, resolution), dtype=np.uint8)
    if obs_mode == "rgbd":
        obs["rgb"] = spaces.Box(0, 255, (3, resolution, resolution), dtype=np.uint8)
    return spaces.Dict(obs)


class GraspSensor:
    """The observation of a :class:`~liuxing_envs.sim.grasp_world.GraspWorld`, read through
    its named queries, and the space it lies in."""

    def __init__(self, settings: GraspSensors) -> None:
        self.obs_mode = settings.obs_mode
        self.depth_backend = settings.depth_backend
        self.intrinsics = CameraIntrinsics(width=settings.resolution, height=settings.resolution)
        self.space = observation_space(self.obs_mode, settings.resolution)

    def observe(self, world: GraspWorld, commanded_opening: float) -> dict[str, np.ndarray]:
        """The observation now; ``commanded_opening`` is the gripper controller's (the
        action's, which the approach guard may shorten)."""
        if world.compiled:
            obs = self._observe_compiled(world, commanded_opening)
        else:
            obs = self._observe_reference(world, commanded_opening)
        if self.obs_mode != "state":
            depth = world.camera(self.intrinsics, self.depth_backend).render(world.data)
            obs["depth"] = encode_depth(depth)[None]
        if self.obs_mode == "rgbd":
            obs["rgb"] = world.rgb(self.intrinsics).transpose(2, 0, 1).copy()
        return obs

    def _observe_compiled(self, world: GraspWorld, commanded_opening: float) -> dict:
        """The entries that are no image, by the kernel (one call)."""
        grasp_observation = kernels.module("grasp_observation").grasp_observation

        data = world.data
        proprio, forces, instrument = grasp_observation(
            data.qpos,
            data.qvel,
            data.site_xpos,
            data.site_xmat,
            data.sensordata,
            world.observation_layout(),
            float(commanded_opening),
            self.obs_mode == "state",
        )
        if self.obs_mode == "state":
            return {"proprio": proprio, "forces": forces, "instrument": instrument}
        return {"proprio": proprio, "forces": forces}

    def _observe_reference(self, world: GraspWorld, commanded_opening: float) -> dict:
        """The entries that are no image, in Python (the kernel's reference)."""
        gripper = world.gripper
        tcp = world.tcp_position()
        yaw = world.tcp_yaw()
        cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)
        # Lists of Python floats made into one float32 array each: concatenating 2- and
        # 3-vectors in numpy cost twice as much, every step.
        proprio = [
            *world.arm.qpos.tolist(),
            *world.arm.qvel.tolist(),
            *tcp.tolist(),
            cos_yaw,
            sin_yaw,
            gripper.opening(),
            commanded_opening,
        ]
        obs = {
            "proprio": np.array(proprio, dtype=np.float32),
            "forces": np.array(gripper.fingertip_force_values(), dtype=np.float32),
        }
        if self.obs_mode == "state":
            grasp_point, axis = world.grasp_point(), world.grasp_axis()
            # The same geometry relative to the tool, as a controller needs it: millimetre
            # offsets are small differences of the absolute positions, which a network
            # fed normalised absolute inputs resolves poorly.
            dx, dy, dz = (grasp_point - tcp).tolist()
            misalignment = 2.0 * (yaw - jaws_across(axis))  # the jaws: half-turn symmetric
            instrument = [
                *grasp_point.tolist(),
                *axis.tolist(),
                *world.instrument_velocity().tolist(),
                cos_yaw * dx + sin_yaw * dy,
                -sin_yaw * dx + cos_yaw * dy,
                dz,
                math.cos(misalignment),
                math.sin(misalignment),
            ]
            obs["instrument"] = np.array(instrument, dtype=np.float32)
        return obs
