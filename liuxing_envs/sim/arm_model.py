"""Lookups of the arm in a compiled scene, shared by :class:`~liuxing_envs.sim.arm.Arm` and its
parts: ids by name, the arm's joint addresses and geoms, and the checks of joint arguments."""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from liuxing_envs.sim.scene import ARM_BASE_BODY, ARM_JOINT_NAMES

if TYPE_CHECKING:
    from liuxing_envs.sim.arm import Arm


class ArmPart:
    """A part of an :class:`~liuxing_envs.sim.arm.Arm` (its IK, collision checks, motion),
    which refers back to the arm weakly: the arm owns its parts, and a strong reference back
    would keep every arm, with its MuJoCo model and data, alive until Python's cycle collector
    happened to run (ten envs made and closed in a row held 50 MB more)."""

    def __init__(self, arm: Arm) -> None:
        self.link(arm)

    def link(self, arm: Arm) -> None:
        """Refer to ``arm`` (again, after a copy)."""
        self._arm_ref = weakref.ref(arm)

    @property
    def linked(self) -> bool:
        """Whether the part refers to a live arm (a copy's parts do once the arm's copy
        has linked them)."""
        return "_arm_ref" in self.__dict__ and self._arm_ref() is not None

    @property
    def _arm(self) -> Arm:
        return self._arm_ref()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        del state["_arm_ref"]  # the arm's copy links its parts' copies (Arm.__setstate__)
        return state


def require_id(model: mujoco.MjModel, obj: mujoco.mjtObj, name: str) -> int:
    idx = mujoco.mj_name2id(model, obj, name)
    if idx < 0:
        kind = obj.name.removeprefix("mjOBJ_").lower()
        raise ValueError(f"the model has no {kind} named {name!r}; is it a liuxing_envs scene?")
    return idx


def arm_joint_ids(model: mujoco.MjModel) -> np.ndarray:
    return np.array([require_id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in ARM_JOINT_NAMES])


def index_of(addresses: np.ndarray) -> slice | np.ndarray:
    """What to index an array of MuJoCo's data (``qpos``, ``qvel``, ``ctrl``) with to read or
    write these addresses: a slice when they are contiguous. Writing a slice costs a fifth of
    a fancy-index write, and the planning loop sets the joints dozens of times per path."""
    first = int(addresses[0])
    contiguous = np.array_equal(addresses, np.arange(first, first + len(addresses)))
    return slice(first, first + len(addresses)) if contiguous else addresses.copy()


def arm_geom_mask(model: mujoco.MjModel) -> np.ndarray:
    base = require_id(model, mujoco.mjtObj.mjOBJ_BODY, ARM_BASE_BODY)
    return np.isin(model.geom_bodyid, subtree(model, base))


def subtree(model: mujoco.MjModel, root: int) -> np.ndarray:
    """Ids of ``root`` and every body below it."""
    inside = np.zeros(model.nbody, dtype=bool)
    inside[root] = True
    for body in range(root + 1, model.nbody):  # parents always precede children
        inside[body] = inside[model.body_parentid[body]]
    return np.flatnonzero(inside)


def finite_qpos(qpos, name: str = "qpos") -> np.ndarray:
    """``qpos`` as 6 finite joint angles, or a ValueError naming it (a NaN configuration
    is in collision with nothing, so a check of it would pass)."""
    try:
        angles = np.asarray(qpos, dtype=float)
    except (TypeError, ValueError):
        angles = None
    if angles is None or angles.shape != (6,) or not np.isfinite(angles).all():
        raise ValueError(f"{name} must be 6 finite joint angles, got {qpos!r}")
    return angles


def homogeneous(position, rotation) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(rotation).reshape(3, 3)
    pose[:3, 3] = position
    return pose
