"""Collision checking of the arm: its contacts at a configuration, along a straight joint
path, and the planning of a free path from the current configuration.

Every check poses a private scratch data (the arm's, or a smaller stand-in scene's: see
:meth:`ArmCollisions.use_collision_scene`), never the live one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from liuxing_envs import kernels
from liuxing_envs.sim.arm_model import (
    ArmPart,
    arm_geom_mask,
    arm_joint_ids,
    finite_qpos,
    index_of,
    require_id,
)
from liuxing_envs.sim.scene import HOME_QPOS

if TYPE_CHECKING:
    from liuxing_envs.sim.arm import Arm

#: Largest displacement of any point of the arm between two checked waypoints of a path.
#: The thinnest part of the camera arm (the 25 mm camera housing) stays inside an obstacle
#: for at least 25 mm plus the obstacle's width of travel, so a 20 mm step cannot skip a
#: contact. With the gripper attached the fingers are 12 mm thick and the pads 6 mm: give
#: such an arm a path_check_step under 6 mm for the same guarantee (no env here checks the
#: gripper arm's paths; InstrumentGrasp-v0 moves it by servo and lets physics collide).
PATH_CHECK_STEP = 0.02  # m
#: Upper bounds on the distance from each joint axis to any point of the arm beyond it (m),
#: which turn a joint-space step into a bound on how far the arm's surface moves. They hold
#: with the wrist camera alone and with the parallel gripper attached, its fingers open or
#: closed (sampled maxima over the joint ranges, the open fingers reaching furthest: 1.13,
#: 1.12, 0.69, 0.30, 0.26 and 0.09 m), with 6% or more to spare.
JOINT_LEVER_ARMS = np.array([1.20, 1.20, 0.75, 0.33, 0.29, 0.15])
#: Contacts shallower than this are touching, not colliding (MuJoCo reports dist <= 0).
PENETRATION_TOLERANCE = 1e-4  # m
#: How far apart every pair of geoms that MuJoCo would test must be for a waypoint to be
#: proven free without MuJoCo (:mod:`liuxing_envs.kernels.path_proof`): ten times
#: PENETRATION_TOLERANCE and a thousand times MuJoCo's default ``ccd_tolerance``.
FREE_MARGIN = 1e-3  # m
#: How deep a part turning about its own axis of symmetry (the shoulder on the arm's base)
#: may sink into a fixed one along that axis, the same at every waypoint, for the proof still
#: to hold: flush parts touch; a hundredth of PENETRATION_TOLERANCE.
FLUSH_TOLERANCE = 1e-6  # m
_FILTERPARENT = int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)


@dataclass(frozen=True)
class Contact:
    """A contact involving the arm: the two geoms and how deep they interpenetrate (m)."""

    geom1: str
    geom2: str
    depth: float


@dataclass(frozen=True)
class CollisionScene:
    """Where :class:`ArmCollisions` checks collisions: a model holding the arm, a data to pose
    it in, the arm's joint addresses there and which geoms are the arm's."""

    model: mujoco.MjModel
    data: mujoco.MjData
    qpos_at: slice | np.ndarray
    is_arm_geom: np.ndarray
    #: Site ids in this model, by name, looked up on first use.
    site_ids: dict[str, int] = field(default_factory=dict)

    def site_id(self, site: str) -> int:
        if site not in self.site_ids:
            self.site_ids[site] = require_id(self.model, mujoco.mjtObj.mjOBJ_SITE, site)
        return self.site_ids[site]

    @cached_property
    def path_proof(self):
        """This scene's :class:`~liuxing_envs.kernels.path_proof.PathProof` (imports numba)."""
        qpos_at = self.qpos_at
        if isinstance(qpos_at, slice):
            qpos_at = np.arange(qpos_at.start, qpos_at.stop)
        return kernels.module("path_proof").PathProof(
            self.model, self.data, qpos_at, self.is_arm_geom
        )


@dataclass(frozen=True)
class PathCheck:
    """Outcome of :meth:`ArmCollisions.check_path`: whether the straight joint path is free
    and, if not, the last free waypoint before the first collision."""

    free: bool
    last_free_qpos: np.ndarray
    fraction: float
    contacts: tuple[Contact, ...]


@dataclass(frozen=True)
class JointPath:
    """A collision-checked joint-space path from ``start`` through ``waypoints`` (the last one
    is the goal), made of straight segments; returned by :meth:`ArmCollisions.plan_path`."""

    start: np.ndarray
    waypoints: tuple[np.ndarray, ...]

    @property
    def length(self) -> float:
        """Joint-space length (rad): sum of the segments' Euclidean norms."""
        points = (self.start, *self.waypoints)
        return float(sum(np.linalg.norm(b - a) for a, b in zip(points, points[1:], strict=False)))


class ArmCollisions(ArmPart):
    """The collision checks of an :class:`~liuxing_envs.sim.arm.Arm`, in its scratch data or
    in a collision scene chosen with :meth:`use_collision_scene`.

    ``is_arm_geom`` marks the arm's geoms in the arm's (live) model. ``prove_free`` (default:
    where numba is installed; an attribute too) lets :meth:`check_path` skip the waypoints
    that a compiled distance bound proves free (:mod:`liuxing_envs.kernels.path_proof`):
    the others go to MuJoCo as before, so every result is the same either way.
    """

    def __init__(
        self, arm: Arm, is_arm_geom: np.ndarray, *, prove_free: bool | None = None
    ) -> None:
        super().__init__(arm)
        #: Whether :meth:`check_path` skips the waypoints proven free without MuJoCo.
        self.prove_free = kernels.available() if prove_free is None else bool(prove_free)
        #: The scene of the live model, posed in the arm's scratch data.
        self.live_scene = CollisionScene(arm.model, arm.scratch, arm.qpos_at, is_arm_geom)
        #: The scene the checks run in now.
        self.scene = self.live_scene
        # Other collision scenes by (model, data) identity: an env switches between a few
        # stand-ins every reset, and making one (its arm-geom mask) costs ~0.1 ms.
        self._scene_cache: dict[tuple[int, int], CollisionScene] = {}

    def use_collision_scene(
        self, model: mujoco.MjModel | None, data: mujoco.MjData | None = None
    ) -> None:
        """Check collisions (:meth:`collisions`, :meth:`check_path`, the IK's checks) in
        another model, or in the live one again when ``model`` is None.

        The other model must hold this arm (same joint and geom names) and the obstacles that
        matter, posed in ``data`` by the caller, who keeps them where the live ones are; the
        arm's joints there are set by each check. A model with fewer bodies than the live
        one (say, without the live scene's hidden objects) makes every check cheaper:
        forward kinematics visits every body.
        """
        if model is None:
            self.scene = self.live_scene
            return
        if data is None or data.qpos.shape != (model.nq,):
            raise ValueError("use_collision_scene needs the model's own MjData")
        key = (id(model), id(data))
        scene = self._scene_cache.get(key)
        # The cached scene holds its model and data, so their ids cannot be reused meanwhile;
        # what it derives from them (joint addresses, the arm's geoms) is fixed at compile time.
        if scene is None or scene.model is not model or scene.data is not data:
            joints = arm_joint_ids(model)
            scene = self._scene_cache[key] = CollisionScene(
                model,
                data,
                index_of(model.jnt_qposadr[joints]),
                arm_geom_mask(model),
            )
        self.scene = scene

    def collisions(self, qpos: np.ndarray | None = None) -> tuple[Contact, ...]:
        """Contacts of the arm (with itself or the world) at ``qpos`` (default: now).

        The rest of the world (objects, their poses) is the live data's, or the collision
        scene's (:meth:`use_collision_scene`).
        """
        d = self.posed(self._arm.qpos if qpos is None else finite_qpos(qpos))
        mujoco.mj_collision(self.scene.model, d)
        return arm_contacts(d, self.scene)

    def in_collision(self, qpos: np.ndarray) -> bool:
        return bool(self.collisions(qpos))

    def check_path(self, q_from: np.ndarray, q_to: np.ndarray) -> PathCheck:
        """Collision-check the straight joint-space path from ``q_from`` to ``q_to``.

        With :attr:`prove_free`, MuJoCo checks only the waypoints that the distance bound
        does not prove free, in order: the first colliding waypoint and its contacts are
        MuJoCo's, as are the data's state afterwards (posed and collided at the last waypoint
        checked, or at the goal), so the result is the same as without it.
        """
        q_from, q_to = finite_qpos(q_from, "q_from"), finite_qpos(q_to, "q_to")
        scene = self.scene
        m, d = scene.model, scene.data
        waypoints = self.waypoints(q_from, q_to)
        count = len(waypoints)
        start = q_from.copy()
        self.posed(start)  # the world (objects) is copied once per path
        checked = self._unproven(scene, waypoints) if self.prove_free else range(count)
        # The hot loop of planning (dozens of waypoints per path): locals, and the contact
        # filter only runs when MuJoCo found any contact at all.
        qpos, qpos_at = d.qpos, scene.qpos_at
        kinematics, collision = mujoco.mj_kinematics, mujoco.mj_collision
        k = -1
        for k in checked:
            qpos[qpos_at] = waypoints[k]
            kinematics(m, d)
            collision(m, d)
            if d.ncon:
                contacts = arm_contacts(d, scene)
                if contacts:
                    last_free = waypoints[k - 1] if k else start
                    return PathCheck(False, last_free, k / count, contacts)
        if k != count - 1:  # the goal was proven free: leave the data as MuJoCo's loop does
            qpos[qpos_at] = waypoints[-1]
            kinematics(m, d)
            collision(m, d)
        return PathCheck(True, waypoints[-1], 1.0, ())

    def _unproven(self, scene: CollisionScene, waypoints: np.ndarray) -> list[int]:
        """The indices of the waypoints not proven free by :data:`FREE_MARGIN`, the scene's
        data posed at the path's start."""
        return scene.path_proof.unproven(
            waypoints,
            FREE_MARGIN,
            FLUSH_TOLERANCE,
            mujoco.get_mjcb_contactfilter() is None,  # a callback replaces the bitmask
            not scene.model.opt.disableflags & _FILTERPARENT,
        )

    def plan_path(
        self, goal: np.ndarray, *, via: np.ndarray | None = HOME_QPOS
    ) -> JointPath | None:
        """A collision-free path from the current configuration to ``goal``: the straight
        joint-space segment if it is free, else two straight segments through ``via``
        (default: home, a retract pose clear of the table), else None."""
        arm = self._arm
        start, goal = arm.qpos, arm.checked_qpos(goal)
        if self.check_path(start, goal).free:
            return JointPath(start, (goal,))
        if via is not None:
            via = arm.checked_qpos(via)
            if self.check_path(start, via).free and self.check_path(via, goal).free:
                return JointPath(start, (via, goal))
        return None

    def posed(self, qpos: np.ndarray) -> mujoco.MjData:
        """The collision scene's data with the arm at ``qpos``, kinematics done."""
        scene = self.scene
        if scene is self.live_scene:  # its obstacles are copied from the live data
            return self._arm.pose_scratch(qpos)
        scene.data.qpos[scene.qpos_at] = qpos
        mujoco.mj_kinematics(scene.model, scene.data)
        return scene.data

    def waypoints(self, q_from: np.ndarray, q_to: np.ndarray) -> np.ndarray:
        """The checked waypoints of the straight path, ``q_to`` last, ``q_from`` left out:
        close enough that no point of the arm moves more than ``path_check_step`` between
        two of them."""
        q_from, q_to = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
        sweep = float(np.abs(q_to - q_from) @ JOINT_LEVER_ARMS)
        count = max(1, int(np.ceil(sweep / self._arm.path_check_step)))
        fractions = np.arange(1, count + 1)[:, None] / count
        return q_from + fractions * (q_to - q_from)


def arm_contacts(d: mujoco.MjData, scene: CollisionScene) -> tuple[Contact, ...]:
    """The arm's penetrating contacts in ``d``, a data of ``scene``'s model."""
    if d.ncon == 0:
        return ()
    model, is_arm_geom = scene.model, scene.is_arm_geom
    geoms = d.contact.geom[: d.ncon]
    dist = d.contact.dist[: d.ncon]
    hits = np.flatnonzero(
        (is_arm_geom[geoms[:, 0]] | is_arm_geom[geoms[:, 1]]) & (dist < -PENETRATION_TOLERANCE)
    )
    return tuple(
        Contact(model.geom(geoms[i, 0]).name, model.geom(geoms[i, 1]).name, -float(dist[i]))
        for i in hits
    )
