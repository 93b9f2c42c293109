"""The arm: the 6-DoF arm of a compiled tabletop scene, composed of its IK, collision checks
and motion.

:class:`Arm` wraps the arm joints of a compiled tabletop scene (``assets/ur5e.xml``): their
state (joint addresses, limits, angles, site poses) and a private scratch
:class:`mujoco.MjData` for everything hypothetical (IK iterations, collision checks of
configurations and paths), so asking questions never disturbs the simulation; only
:meth:`Arm.move_to`, :meth:`Arm.follow` and :meth:`Arm.set_qpos` change the live ``data``.
Its jobs are parts of their own, each in its module:

- :class:`~liuxing_envs.sim.arm_ik.ArmIK` (``arm.ik``): the closed-form and damped least
  squares IK;
- :class:`~liuxing_envs.sim.arm_collisions.ArmCollisions` (``arm.collision_checks``): contacts
  at a configuration and along a path, path planning, the collision scene (possibly a smaller
  one that holds the same arm and obstacles: :meth:`Arm.use_collision_scene`);
- :class:`~liuxing_envs.sim.arm_motion.ArmMotion` (``arm.motion``): kinematic and dynamic
  motion (see :mod:`liuxing_envs.sim.arm_motion`).

The arm's methods for them delegate to the parts; callers (and instrumentation wrapping
``arm.solve_ik`` and the like on the instance) go through the arm.
"""

from __future__ import annotations

import mujoco
import numpy as np

from liuxing_envs.sim.arm_collisions import (
    JOINT_LEVER_ARMS,
    PATH_CHECK_STEP,
    ArmCollisions,
    Contact,
    JointPath,
    PathCheck,
)
from liuxing_envs.sim.arm_ik import IK_SEED, ArmIK, IKResult
from liuxing_envs.sim.arm_model import (
    arm_geom_mask,
    arm_joint_ids,
    finite_qpos,
    index_of,
    require_id,
)
from liuxing_envs.sim.arm_motion import MOTION_MODES, ArmMotion, MotionResult
from liuxing_envs.sim.scene import ARM_ACTUATOR_NAMES, WRIST_CAMERA_SITE

__all__ = [
    "JOINT_LEVER_ARMS",
    "MOTION_MODES",
    "PATH_CHECK_STEP",
    "Arm",
    "Contact",
    "IKResult",
    "JointPath",
    "MotionResult",
    "PathCheck",
]


class Arm:
    """The 6-DoF arm of a compiled tabletop scene.

    Parameters
    ----------
    model, data:
        A model compiled from :func:`liuxing_envs.sim.scene.load_scene_spec` (possibly with
        objects added) and its live data.
    path_check_step:
        Largest displacement (m) of any point of the arm between collision-checked waypoints:
        below the thickness of the thinnest part that could meet an obstacle (the default
        suits the camera arm, not the gripper's 6 mm pads; see ``PATH_CHECK_STEP``).
    ik_seed:
        Seed of the random restarts of the IK; fixed so the same query gives the same answer.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        *,
        path_check_step: float = PATH_CHECK_STEP,
        ik_seed: int = IK_SEED,
    ) -> None:
        if not path_check_step > 0:
            raise ValueError(f"path_check_step must be > 0 m, got {path_check_step}")
        self.model = model
        self.data = data
        self.path_check_step = float(path_check_step)
        self.ik_seed = int(ik_seed)
        #: Data for hypothetical configurations (the parts' checks and IK iterations).
        self.scratch = mujoco.MjData(model)

        joint_ids = arm_joint_ids(model)
        #: Addresses of the arm's joints in ``qpos`` and ``qvel``, its actuators' ids, and
        #: what to index ``qpos`` with to read or write the joints (for the parts' hot loops:
        #: do not modify).
        self.qpos_addresses = model.jnt_qposadr[joint_ids].copy()
        self.qpos_at = index_of(self.qpos_addresses)
        self.dof_addresses = model.jnt_dofadr[joint_ids].copy()
        self._dof_at = index_of(self.dof_addresses)
        self.actuator_ids = np.array(
            [require_id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in ARM_ACTUATOR_NAMES]
        )
        self.lower = model.jnt_range[joint_ids, 0].copy()
        self.upper = model.jnt_range[joint_ids, 1].copy()
        is_arm_geom = arm_geom_mask(model)
        self._geom_ids = np.flatnonzero(is_arm_geom)
        self._site_ids: dict[str, int] = {}
        self._site_names: dict[int, str] = {}

        self.collision_checks = ArmCollisions(self, is_arm_geom)
        self.ik = ArmIK(self, self.collision_checks)
        self.motion = ArmMotion(self, self.collision_checks)

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        for part in (self.collision_checks, self.ik, self.motion):
            # Copied parts (pickle, deepcopy) come without their link; a shallow copy shares
            # the original's parts, which stay linked to it.
            if not part.linked:
                part.link(self)

    # ------------------------------------------------------------------ state
    @property
    def qpos_indices(self) -> np.ndarray:
        """Addresses of the six arm joints in ``qpos``."""
        return self.qpos_addresses.copy()

    @property
    def geom_ids(self) -> np.ndarray:
        """Ids of the arm's geoms (its links, down to the camera mount) in the live model."""
        return self._geom_ids.copy()

    @property
    def qpos(self) -> np.ndarray:
        """Current joint angles of the arm (rad), a copy."""
        return self.data.qpos[self.qpos_at].copy()

    @property
    def qvel(self) -> np.ndarray:
        """Current joint velocities of the arm (rad/s), a copy."""
        return self.data.qvel[self._dof_at].copy()

    def within_limits(self, qpos: np.ndarray) -> bool:
        qpos = np.asarray(qpos)
        return bool(((qpos >= self.lower) & (qpos <= self.upper)).all())

    def checked_qpos(self, qpos) -> np.ndarray:
        """``qpos`` as 6 finite joint angles within the limits, or a ValueError."""
        target = finite_qpos(qpos)
        if not self.within_limits(target):
            raise ValueError(
                f"qpos {np.round(target, 4).tolist()} is outside the joint limits "
                f"[{self.lower.round(4).tolist()}, {self.upper.round(4).tolist()}]"
            )
        return target

    def site_id(self, site: str) -> int:
        if site not in self._site_ids:
            self._site_ids[site] = require_id(self.model, mujoco.mjtObj.mjOBJ_SITE, site)
            self._site_names[self._site_ids[site]] = site
        return self._site_ids[site]

    def site_name(self, sid: int) -> str:
        """The name of a site id that :meth:`site_id` returned."""
        return self._site_names[sid]

    def site_pose(self, site: str = WRIST_CAMERA_SITE, qpos: np.ndarray | None = None):
        """World position (3,) and rotation (3, 3) of a site, now or at configuration ``qpos``."""
        sid = self.site_id(site)
        d = self.data if qpos is None else self.pose_scratch(finite_qpos(qpos))
        return d.site_xpos[sid].copy(), d.site_xmat[sid].reshape(3, 3).copy()

    def set_qpos(self, qpos: np.ndarray) -> None:
        """Teleport the live arm to ``qpos`` at rest, hold it there, and update kinematics."""
        self.data.qpos[self.qpos_addresses] = qpos
        self.data.qvel[self.dof_addresses] = 0.0
        self.data.ctrl[self.actuator_ids] = qpos
        mujoco.mj_forward(self.model, self.data)

    def pose_scratch(self, qpos: np.ndarray) -> mujoco.MjData:
        """The scratch data with the live world (objects, mocap) and the arm at ``qpos``."""
        d = self.scratch
        d.qpos[:] = self.data.qpos
        d.mocap_pos[:] = self.data.mocap_pos
        d.mocap_quat[:] = self.data.mocap_quat
        d.qpos[self.qpos_at] = qpos
        mujoco.mj_kinematics(self.model, d)
        return d

    # ------------------------------------------------- collisions (ArmCollisions)
    def use_collision_scene(
        self, model: mujoco.MjModel | None, data: mujoco.MjData | None = None
    ) -> None:
        """See :meth:`ArmCollisions.use_collision_scene`."""
        self.collision_checks.use_collision_scene(model, data)

    def collisions(self, qpos: np.ndarray | None = None) -> tuple[Contact, ...]:
        """See :meth:`ArmCollisions.collisions`."""
        return self.collision_checks.collisions(qpos)

    def in_collision(self, qpos: np.ndarray) -> bool:
        return self.collision_checks.in_collision(qpos)

    def check_path(self, q_from: np.ndarray, q_to: np.ndarray) -> PathCheck:
        """See :meth:`ArmCollisions.check_path`."""
        return self.collision_checks.check_path(q_from, q_to)

    def plan_path(self, goal: np.ndarray, **options) -> JointPath | None:
        """See :meth:`ArmCollisions.plan_path` (``via``)."""
        return self.collision_checks.plan_path(goal, **options)

    # ------------------------------------------------------------------ IK (ArmIK)
    def solve_ik(self, position: np.ndarray, rotation=None, **options) -> IKResult:
        """See :meth:`ArmIK.solve_ik` (its keyword options)."""
        return self.ik.solve_ik(position, rotation, **options)

    def closed_form_nearest(
        self, position, rotation, reference, site: str = WRIST_CAMERA_SITE
    ) -> np.ndarray | None:
        """See :meth:`ArmIK.closed_form_nearest`."""
        return self.ik.closed_form_nearest(position, rotation, reference, site)

    def closed_form_nearest_pose(
        self, site_pose, reference, site: str = WRIST_CAMERA_SITE
    ) -> np.ndarray | None:
        """See :meth:`ArmIK.closed_form_nearest_pose`."""
        return self.ik.closed_form_nearest_pose(site_pose, reference, site)

    # ------------------------------------------------------------ motion (ArmMotion)
    def move_to(self, qpos: np.ndarray, mode: str = "kinematic", **settings) -> MotionResult:
        """See :meth:`ArmMotion.move_to` (``max_joint_speed``, ``timeout``,
        ``settle_tolerance``)."""
        return self.motion.move_to(qpos, mode, **settings)

    def follow(self, path: JointPath, mode: str = "kinematic", **settings) -> MotionResult:
        """See :meth:`ArmMotion.follow` (``max_joint_speed``, ``timeout``,
        ``settle_tolerance``)."""
        return self.motion.follow(path, mode, **settings)
