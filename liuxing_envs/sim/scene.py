"""The shared tabletop world: load it, extend it with objects, compile it.

Every environment starts from ``assets/tabletop.xml`` (arm, wrist depth camera, table,
lights, an overview camera) and adds its own objects through :class:`mujoco.MjSpec` before
compiling, so the arm model exists in exactly one file.

World conventions: metres and radians; the table top is the plane z = 0; the arm base sits
at the origin; "in front of the arm" is +x.
"""

from __future__ import annotations

import functools

import mujoco
import numpy as np

from liuxing_envs.assets import asset_path

SCENE_FILE = "tabletop.xml"

ARM_JOINT_NAMES = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
ARM_ACTUATOR_NAMES = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
#: Bodies of the arm, base to camera; used to tell the arm's contacts from the world's.
ARM_BODY_NAMES = (
    "base",
    "shoulder_link",
    "upper_arm_link",
    "forearm_link",
    "wrist_1_link",
    "wrist_2_link",
    "wrist_3_link",
    "wrist_camera",
)
ARM_BASE_BODY = "base"
#: The link the flange belongs to; sites in its subtree move rigidly with the flange.
LAST_LINK_BODY = "wrist_3_link"
FLANGE_SITE = "flange"
WRIST_CAMERA = "wrist_depth"
WRIST_CAMERA_SITE = "wrist_depth_optical"
OVERVIEW_CAMERA = "overview"
HOME_KEYFRAME = "home"
#: The UR5e's customary home: upright, tool pointing down at the table in front.
HOME_QPOS = np.array([-np.pi / 2, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0])
TABLE_TOP_Z = 0.0


def load_scene_spec() -> mujoco.MjSpec:
    """A fresh, editable spec of the tabletop scene; add objects, then ``spec.compile()``.

    A copy of one parse per process: a ViewPlanning env makes two stand-in scenes per object
    variant, and copying a spec costs a tenth of parsing the scene's files again."""
    return _parsed_scene_spec().copy()


@functools.cache
def _parsed_scene_spec() -> mujoco.MjSpec:
    return mujoco.MjSpec.from_file(str(asset_path(SCENE_FILE)))


def load_scene_model() -> mujoco.MjModel:
    """The compiled tabletop scene with nothing on the table."""
    return load_scene_spec().compile()


def reset_to_home(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    """Put the arm at its home keyframe (positions and actuator set-points) and run forward."""
    mujoco.mj_resetDataKeyframe(model, data, model.key(HOME_KEYFRAME).id)
    mujoco.mj_forward(model, data)
