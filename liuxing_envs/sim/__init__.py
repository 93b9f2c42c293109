"""The MuJoCo world shared by every environment: scene, arm, wrist depth camera, viewpoints."""

from liuxing_envs.sim.arm import MOTION_MODES, Arm, Contact, IKResult, MotionResult, PathCheck
from liuxing_envs.sim.camera import (
    BACKENDS,
    REALSENSE_D435_DEPTH,
    CameraIntrinsics,
    DepthCamera,
    DepthNoise,
)
from liuxing_envs.sim.scene import HOME_QPOS, load_scene_model, load_scene_spec, reset_to_home
from liuxing_envs.sim.viewpoints import look_at, sphere_point, sphere_viewpoint, view_grid

__all__ = [
    "BACKENDS",
    "HOME_QPOS",
    "MOTION_MODES",
    "REALSENSE_D435_DEPTH",
    "Arm",
    "CameraIntrinsics",
    "Contact",
    "DepthCamera",
    "DepthNoise",
    "IKResult",
    "MotionResult",
    "PathCheck",
    "load_scene_model",
    "load_scene_spec",
    "look_at",
    "reset_to_home",
    "sphere_point",
    "sphere_viewpoint",
    "view_grid",
]
