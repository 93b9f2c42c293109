"""Inverse kinematics of the arm: the UR5e's closed form and damped least squares.

:class:`ArmIK` answers "which joint angles put this site at that pose?" for an
:class:`~liuxing_envs.sim.arm.Arm`, within its joint limits and (optionally) free of
collisions, in the arm's scratch data: asking never disturbs the simulation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import mujoco
import numpy as np

from liuxing_envs import kernels
from liuxing_envs.sim.arm_model import ArmPart, finite_qpos, homogeneous, require_id, subtree
from liuxing_envs.sim.scene import (
    ARM_BASE_BODY,
    FLANGE_SITE,
    HOME_QPOS,
    LAST_LINK_BODY,
    WRIST_CAMERA_SITE,
)
from liuxing_envs.sim.ur_ik import solutions_of_one, ur_ik
from liuxing_envs.validation import require_int, require_number

if TYPE_CHECKING:
    from liuxing_envs.sim.arm import Arm
    from liuxing_envs.sim.arm_collisions import ArmCollisions

IK_METHODS = ("auto", "analytic", "dls")
#: Rolls about the site's z axis tried by the analytic IK when the roll is free (every 15 deg).
IK_ROLL_SAMPLES = 24

IK_POSITION_TOLERANCE = 5e-4  # m
IK_ROTATION_TOLERANCE = np.deg2rad(0.25)  # rad
IK_MAX_ITERATIONS = 200
IK_RESTARTS = 12
IK_DAMPING = 0.02
IK_MAX_STEP = 0.4  # rad of joint motion per DLS iteration
IK_SEED = 0
#: An attempt is abandoned when its error shrank by less than 1 - IK_STALL_RATIO over the
#: last IK_STALL_WINDOW iterations.
IK_STALL_WINDOW = 20
IK_STALL_RATIO = 0.9
#: Metres of position error one radian of orientation error is worth in the IK error norm.
IK_ROTATION_WEIGHT = 0.2
#: How far past a joint limit a closed-form solution may land and be clipped back onto it: a
#: configuration at a limit (a wrist at +-2 pi) comes back from the closed form a rounding
#: error beyond it, and was dropped for a solution of another branch, up to 5.8 rad away.
IK_LIMIT_SLACK = 1e-9  # rad


@dataclass(frozen=True)
class IKResult:
    """Outcome of :meth:`ArmIK.solve_ik`.

    ``success`` means the pose was reached within tolerance by a collision-free configuration
    inside the joint limits (when collisions were checked). ``qpos`` is that configuration, or
    the best attempt when ``success`` is False.
    """

    success: bool
    qpos: np.ndarray
    position_error: float
    rotation_error: float
    iterations: int
    attempts: int
    in_collision: bool


class ArmIK(ArmPart):
    """The IK of an :class:`~liuxing_envs.sim.arm.Arm`, its collision checks by ``collisions``.

    The random restarts of the DLS solver are seeded with the arm's ``ik_seed``, so the same
    query gives the same answer.

    ``compiled``: whether the roll-free closed form (a camera's view, every sampled roll at
    once) runs in the compiled kernel (:mod:`liuxing_envs.kernels.ik`) or in numpy
    (:func:`~liuxing_envs.sim.ur_ik.ur_ik` and :meth:`nearest_first`), and the closed form of
    one pose (a controller's target, :meth:`closed_form_nearest`) in its kernel
    (:mod:`liuxing_envs.kernels.one_pose_ik`) or on Python floats
    (:func:`~liuxing_envs.sim.ur_ik.solutions_of_one` and :meth:`nearest_first_of_few`). Each
    pair gives the same candidates bit for bit; None (the default) picks the kernels where
    numba is installed. The attribute of that name may be set later (tests compare the two).
    """

    #: See the class docstring (a class default: copies pickled without it use numpy).
    compiled = False

    def __init__(
        self, arm: Arm, collisions: ArmCollisions, *, compiled: bool | None = None
    ) -> None:
        super().__init__(arm)
        if compiled is None:
            compiled = kernels.available()
        elif compiled and not kernels.available():
            raise ValueError("compiled=True needs numba, which is not installed")
        self.compiled = bool(compiled)
        self._collisions = collisions
        model = arm.model
        self._flange_in_site: dict[int, np.ndarray | None] = {}
        last_link = require_id(model, mujoco.mjtObj.mjOBJ_BODY, LAST_LINK_BODY)
        self._last_link_bodies = set(subtree(model, last_link).tolist())
        base_id = require_id(model, mujoco.mjtObj.mjOBJ_BODY, ARM_BASE_BODY)
        d = arm.pose_scratch(HOME_QPOS)
        self._base_inverse = np.linalg.inv(homogeneous(d.xpos[base_id], d.xmat[base_id]))
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))

    def solve_ik(
        self,
        position: np.ndarray,
        rotation: np.ndarray | None = None,
        *,
        site: str = WRIST_CAMERA_SITE,
        roll_free: bool = False,
        seed_qpos: np.ndarray | None = None,
        restarts: int = IK_RESTARTS,
        check_collisions: bool = True,
        position_tolerance: float = IK_POSITION_TOLERANCE,
        rotation_tolerance: float = IK_ROTATION_TOLERANCE,
        max_iterations: int = IK_MAX_ITERATIONS,
        method: str = "auto",
    ) -> IKResult:
        """IK of ``site`` to a world pose, within the joint limits, collision-free.

        Two solvers: ``"analytic"``, the UR5e's closed form (:mod:`liuxing_envs.sim.ur_ik`),
        for sites fixed to the last link with a target rotation: every one of the up to eight
        solutions (per sampled roll when ``roll_free``, every ``360 / IK_ROLL_SAMPLES``
        degrees) is tried in order of joint distance from the reference configuration, so
        the answer is exact and "unreachable" means no solution exists (up to the roll
        sampling); ``"dls"``, damped least squares from several seeds, for any site and for
        position-only targets. ``"auto"`` picks analytic where it applies.

        Parameters
        ----------
        position:
            Target position of the site in the world (m).
        rotation:
            Target 3x3 rotation of the site's frame, or None for position-only IK.
        roll_free:
            Constrain only the direction of the site's z axis (for a camera: its optical axis,
            which is -z), leaving the roll about it free.
        seed_qpos:
            First initial guess (default: the current configuration); then home, then
            ``restarts`` random configurations from a generator seeded with ``ik_seed``.
        check_collisions:
            Reject solutions in which the arm touches itself or the world.
        method:
            ``"auto"``, ``"analytic"`` or ``"dls"`` (see above).
        """
        arm = self._arm
        target_p = _as_vector3(position, "position")
        target_r = None if rotation is None else _as_rotation(rotation)
        if roll_free and target_r is None:
            raise ValueError("roll_free=True needs a rotation whose z axis to align")
        require_int("restarts", restarts, 0, 10**6)
        require_int("max_iterations", max_iterations, 1, 10**6)
        require_number("position_tolerance", position_tolerance, 0.0, math.inf)
        require_number("rotation_tolerance", rotation_tolerance, 0.0, math.inf)
        if method not in IK_METHODS:
            raise ValueError(f"unknown IK method {method!r}; allowed: {IK_METHODS}")
        sid = arm.site_id(site)
        reference = arm.qpos if seed_qpos is None else finite_qpos(seed_qpos, "seed_qpos")
        analytic_ok = target_r is not None and self._flange_from_site(sid) is not None
        if method == "analytic" and not analytic_ok:
            raise ValueError(
                "the analytic IK needs a target rotation and a site fixed to the last link"
            )
        if method != "dls" and analytic_ok:
            return self._solve_analytic(
                target_p, target_r, sid, roll_free, reference, check_collisions
            )
        rng = np.random.default_rng(arm.ik_seed)
        seeds = [reference, HOME_QPOS]
        sample_lo, sample_hi = np.maximum(arm.lower, -np.pi), np.minimum(arm.upper, np.pi)
        seeds += [rng.uniform(sample_lo, sample_hi) for _ in range(restarts)]

        best: IKResult | None = None
        total_iterations = 0
        for attempt, seed in enumerate(seeds, start=1):
            q, pos_err, rot_err, iterations = self._dls(
                seed,
                sid,
                target_p,
                target_r,
                roll_free,
                position_tolerance,
                rotation_tolerance,
                max_iterations,
            )
            total_iterations += iterations
            converged = pos_err <= position_tolerance and rot_err <= rotation_tolerance
            if not converged:
                if best is None or pos_err + IK_ROTATION_WEIGHT * rot_err < (
                    best.position_error + IK_ROTATION_WEIGHT * best.rotation_error
                ):
                    best = IKResult(False, q, pos_err, rot_err, total_iterations, attempt, False)
                continue
            q = self._nearest_equivalent(q, reference)
            colliding = check_collisions and self._collisions.in_collision(q)
            result = IKResult(
                not colliding, q, pos_err, rot_err, total_iterations, attempt, colliding
            )
            if not colliding:
                return result
            if best is None or not best.in_collision:
                best = result
        assert best is not None
        return IKResult(
            False,
            best.qpos,
            best.position_error,
            best.rotation_error,
            total_iterations,
            len(seeds),
            best.in_collision,
        )

    def closed_form_nearest(
        self,
        position: np.ndarray,
        rotation: np.ndarray,
        reference: np.ndarray,
        site: str = WRIST_CAMERA_SITE,
    ) -> np.ndarray | None:
        """The joint angles, within the limits, that put ``site`` at the pose by the closed
        form, nearest ``reference`` (joint space), or None where none exist: what
        ``solve_ik(position, rotation, site=site, seed_qpos=reference, method="analytic",
        check_collisions=False)`` returns as ``qpos`` when it succeeds. For a controller's
        per-step query: no collision check, no residuals, and no checks of the inputs, which
        must be a finite 3-vector, a proper 3x3 rotation and an array of finite joint
        angles."""
        # homogeneous(position, rotation), without np.eye's cost (it runs on every step).
        site_pose = np.empty((4, 4))
        site_pose[:3, :3] = rotation
        site_pose[:3, 3] = position
        site_pose[3] = _HOMOGENEOUS_ROW
        return self.closed_form_nearest_pose(site_pose, reference, site)

    def closed_form_nearest_pose(
        self, site_pose: np.ndarray, reference: np.ndarray, site: str = WRIST_CAMERA_SITE
    ) -> np.ndarray | None:
        """:meth:`closed_form_nearest` of the pose given as one 4x4 homogeneous matrix."""
        _, flange_in_site = self.flange_frames(site)
        ordered = self._one_pose_nearest_first(site_pose, flange_in_site, reference)
        return np.array(ordered[0]) if len(ordered) else None

    def flange_frames(self, site: str) -> tuple[np.ndarray, np.ndarray]:
        """``(base_inverse, flange_in_site)``, C-contiguous: the flange's pose in the arm's
        base frame is ``base_inverse @ site_pose @ flange_in_site`` for the pose of ``site``
        (fixed to the last link) in the world; for kernels that make the products."""
        flange_in_site = self._flange_from_site(self._arm.site_id(site))
        if flange_in_site is None:
            raise ValueError(
                f"the closed-form IK needs a site fixed to the last link, not {site!r}"
            )
        return np.ascontiguousarray(self._base_inverse), np.ascontiguousarray(flange_in_site)

    def nearest_first(self, candidates: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """IK solutions (rows) shifted by whole turns towards ``reference`` where that stays
        within the joint limits, those within the limits, nearest (joint space) first."""
        arm = self._arm
        if len(candidates):
            lower, upper = arm.lower - IK_LIMIT_SLACK, arm.upper + IK_LIMIT_SLACK
            turns = np.round((reference - candidates) / (2 * np.pi))
            shifted = candidates + 2 * np.pi * turns
            inside = (shifted >= lower) & (shifted <= upper)
            candidates = np.where(inside, shifted, candidates)
            within = (candidates >= lower) & (candidates <= upper)
            candidates = np.clip(candidates[within.all(axis=1)], arm.lower, arm.upper)
        # np.linalg.norm(axis=1) spelled out (the same sums): it is hot and costs ~10 us.
        offsets = candidates - reference
        return candidates[np.argsort(np.sqrt(np.add.reduce(offsets * offsets, axis=1)))]

    def nearest_first_of_few(
        self, solutions: list[tuple[int, list[float]]], reference: np.ndarray
    ) -> list[list[float]]:
        """:meth:`nearest_first` of a few solutions (``solutions_of_one``'s), on Python
        floats (numpy's per-call overhead would cost more than the arithmetic), as lists of
        joint angles. It runs on every step of a controller, so the common cases skip calls:
        a joint within half a turn of the reference needs no whole turns (``round`` of a
        quotient within +-0.5 is 0), one inside its limits needs no clipping."""
        joint_bounds = [
            (near, low - IK_LIMIT_SLACK, high + IK_LIMIT_SLACK, low, high)
            for near, low, high in zip(
                reference.tolist(), self._arm.lower.tolist(), self._arm.upper.tolist(), strict=True
            )
        ]
        kept = []
        for _, angles in solutions:
            joints, distance2 = [], 0.0
            for angle, (near, slack_low, slack_high, low, high) in zip(
                angles, joint_bounds, strict=True
            ):
                gap = near - angle
                if -math.pi <= gap <= math.pi:
                    shifted = angle + 0.0  # as angle + 2 pi * 0 (a -0.0 becomes 0.0)
                else:
                    shifted = angle + _TWO_PI * round(gap / _TWO_PI)
                if slack_low <= shifted <= slack_high:
                    angle = shifted
                elif not slack_low <= angle <= slack_high:
                    break
                if not low <= angle <= high:
                    angle = min(max(angle, low), high)
                joints.append(angle)
                distance2 += (angle - near) * (angle - near)
            else:
                kept.append((distance2, joints))
        kept.sort(key=lambda pair: pair[0])
        return [joints for _, joints in kept]

    def _flange_from_site(self, sid: int) -> np.ndarray | None:
        """Pose of the flange in the frame of site ``sid`` if the site is rigidly attached to
        the last link (else None), computed once per site."""
        if sid not in self._flange_in_site:
            arm = self._arm
            if arm.model.site_bodyid[sid] not in self._last_link_bodies:
                self._flange_in_site[sid] = None
            else:
                d = arm.pose_scratch(HOME_QPOS)
                world_site = homogeneous(d.site_xpos[sid], d.site_xmat[sid])
                fid = arm.site_id(FLANGE_SITE)
                world_flange = homogeneous(d.site_xpos[fid], d.site_xmat[fid])
                self._flange_in_site[sid] = np.linalg.inv(world_site) @ world_flange
        return self._flange_in_site[sid]

    def _solve_analytic(self, target_p, target_r, sid, roll_free, reference, check_collisions):
        flange_in_site = self._flange_from_site(sid)
        if roll_free:
            site_poses = np.empty((len(_ROLLS), 4, 4))
            site_poses[:, :3, :3] = target_r @ _ROLLS  # turning about the site's own z keeps z
            site_poses[:, :3, 3] = target_p
            site_poses[:, 3] = _HOMOGENEOUS_ROW
            flange_poses = self._base_inverse @ site_poses @ flange_in_site
            if self.compiled:
                ordered = self._nearest_compiled(flange_poses, reference)
            else:
                solutions, valid = ur_ik(flange_poses)
                ordered = self.nearest_first(solutions[valid], reference)
        else:  # a controller's target: one pose, on Python floats (see ur_ik)
            site_pose = homogeneous(target_p, target_r)
            ordered = self._one_pose_nearest_first(site_pose, flange_in_site, reference)
        tried, colliding = 0, None
        for q in map(np.asarray, ordered):
            tried += 1
            if check_collisions and self._collisions.in_collision(q):
                colliding = q if colliding is None else colliding
                continue
            return self._ik_result(True, q, sid, target_p, target_r, roll_free, tried, False)
        if colliding is not None:
            return self._ik_result(
                False, colliding, sid, target_p, target_r, roll_free, tried, True
            )
        return IKResult(False, reference.copy(), np.inf, np.inf, 0, tried, False)

    def _nearest_compiled(self, flange_poses: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """:meth:`nearest_first` of the valid ``ur_ik(flange_poses)``, by the compiled kernel:
        the same rows, bit for bit."""
        nearest_solutions = kernels.module("ik").nearest_solutions

        lower, upper = self._arm.lower, self._arm.upper
        return nearest_solutions(
            flange_poses,
            np.asarray(reference, dtype=np.float64),
            lower - IK_LIMIT_SLACK,
            upper + IK_LIMIT_SLACK,
            lower,
            upper,
        )

    def _one_pose_nearest_first(self, site_pose, flange_in_site, reference):
        """The closed-form solutions for one site pose (4x4), as :meth:`nearest_first_of_few`
        orders them: lists of joint angles, or the rows of an array by the compiled kernel
        (:mod:`liuxing_envs.kernels.one_pose_ik`, the same values bit for bit)."""
        flange_in_base = self._base_inverse @ site_pose @ flange_in_site
        if self.compiled:
            one_pose_ik = kernels.module("one_pose_ik")

            arm = self._arm
            return one_pose_ik.one_pose_nearest(
                flange_in_base,
                np.asarray(reference, dtype=np.float64),
                arm.lower,
                arm.upper,
                IK_LIMIT_SLACK,
                one_pose_ik.CONSTANTS,
            )
        return self.nearest_first_of_few(solutions_of_one(flange_in_base), reference)

    def _ik_result(self, success, q, sid, target_p, target_r, roll_free, attempts, colliding):
        # The collision scene holds the same arm, so its kinematics give the same site pose;
        # a stand-in (see use_collision_scene) computes them for a fraction of the bodies.
        collisions = self._collisions
        scene = collisions.scene
        d = collisions.posed(q)
        if scene is not collisions.live_scene:
            sid = scene.site_id(self._arm.site_name(sid))
        pos_err = float(np.linalg.norm(target_p - d.site_xpos[sid]))
        rotvec = _rotation_error(d.site_xmat[sid].reshape(3, 3), target_r, roll_free)
        return IKResult(
            success, q.copy(), pos_err, float(np.linalg.norm(rotvec)), 0, attempts, colliding
        )

    def _dls(self, seed, sid, target_p, target_r, roll_free, pos_tol, rot_tol, max_iterations):
        arm = self._arm
        m, d = arm.model, arm.scratch
        lower, upper, dof_idx = arm.lower, arm.upper, arm.dof_addresses
        q = np.clip(np.asarray(seed, dtype=float), lower, upper)
        weights = np.array(
            [1.0, 1.0, 1.0, IK_ROTATION_WEIGHT, IK_ROTATION_WEIGHT, IK_ROTATION_WEIGHT]
        )
        rows = 6 if target_r is not None else 3
        damping = IK_DAMPING**2 * np.eye(rows)
        jac = np.empty((6, len(dof_idx)))
        err = np.zeros(6)
        pos_err = rot_err = np.inf
        checkpoint_err = np.inf
        arm.pose_scratch(q)  # the world (objects) is copied once per attempt
        qpos_idx = arm.qpos_addresses
        for iteration in range(1, max_iterations + 1):
            if iteration > 1:
                d.qpos[qpos_idx] = q
                mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            err[:3] = target_p - d.site_xpos[sid]
            if target_r is not None:
                err[3:] = _rotation_error(d.site_xmat[sid].reshape(3, 3), target_r, roll_free)
            pos_err = math.sqrt(err[0] ** 2 + err[1] ** 2 + err[2] ** 2)
            rot_err = math.sqrt(err[3] ** 2 + err[4] ** 2 + err[5] ** 2)
            if pos_err <= pos_tol and rot_err <= rot_tol:
                return q, pos_err, rot_err, iteration
            if iteration % IK_STALL_WINDOW == 0:
                # A local minimum or a limit stops progress; a fresh seed does better.
                combined = pos_err + IK_ROTATION_WEIGHT * rot_err
                if combined > IK_STALL_RATIO * checkpoint_err:
                    break
                checkpoint_err = combined
            mujoco.mj_jacSite(m, d, self._jacp, self._jacr, sid)
            jac[:3] = self._jacp[:, dof_idx]
            jac[3:] = self._jacr[:, dof_idx]
            jac_w = (jac * weights[:, None])[:rows]
            err_w = (err * weights)[:rows]
            dq = jac_w.T @ np.linalg.solve(jac_w @ jac_w.T + damping, err_w)
            step = math.sqrt(dq @ dq)
            if step > IK_MAX_STEP:
                dq *= IK_MAX_STEP / step
            q = np.clip(q + dq, lower, upper)
        return q, pos_err, rot_err, iteration

    def _nearest_equivalent(self, q: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Shift joints by whole turns towards ``reference`` where the limits allow it."""
        turns = np.round((reference - q) / (2 * np.pi))
        shifted = q + turns * 2 * np.pi
        ok = (shifted >= self._arm.lower) & (shifted <= self._arm.upper)
        return np.where(ok, shifted, q)


def _rolls_about_z(angles: np.ndarray) -> np.ndarray:
    c, s = np.cos(angles), np.sin(angles)
    roll = np.zeros((len(angles), 3, 3))
    roll[:, 0, 0], roll[:, 0, 1], roll[:, 1, 0], roll[:, 1, 1], roll[:, 2, 2] = c, -s, s, c, 1
    return roll


#: The rotations about the site's z axis the analytic IK tries when the roll is free.
_ROLLS = _rolls_about_z(np.linspace(0, 2 * np.pi, IK_ROLL_SAMPLES, endpoint=False))


def _rotation_error(current: np.ndarray, target: np.ndarray, roll_free: bool) -> np.ndarray:
    """World-frame rotation vector that turns ``current`` into ``target`` (or just its z axis)."""
    if roll_free:
        a, b = current[:, 2], target[:, 2]
        axis = np.array(  # a x b, spelled out: np.cross costs ~10x more on 3-vectors
            [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
        )
        sin = math.sqrt(axis @ axis)
        angle = math.atan2(sin, float(a @ b))
        if sin < 1e-12:
            if angle < 1e-6:
                return np.zeros(3)
            axis, sin = current[:, 0], 1.0  # opposite axes: any perpendicular turn works
        return axis / sin * angle
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, (target @ current.T).ravel())
    rotvec = np.empty(3)
    mujoco.mju_quat2Vel(rotvec, quat, 1.0)
    return rotvec


def _as_vector3(value, name: str) -> np.ndarray:
    vec = np.asarray(value, dtype=float)
    if vec.shape != (3,) or not np.isfinite(vec).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return vec


def _as_rotation(value) -> np.ndarray:
    rot = np.asarray(value, dtype=float)
    if rot.shape != (3, 3) or not np.isfinite(rot).all():
        raise ValueError(f"rotation must be a finite 3x3 matrix, got shape {rot.shape}")
    # np.allclose(rot.T @ rot, I, atol=1e-6) and det(rot) > 0, spelled out: this runs on every
    # IK query, and the generic functions cost ~10x more on a 3x3 matrix.
    gram_error = np.abs(rot.T @ rot - _IDENTITY3) - _ORTHONORMAL_TOLERANCE
    if not (gram_error <= 0.0).all() or _det3(rot) < 0:
        raise ValueError("rotation must be a proper rotation matrix (orthonormal, det +1)")
    return rot


_IDENTITY3 = np.eye(3)
_HOMOGENEOUS_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_TWO_PI = 2 * np.pi
#: np.allclose's tolerance against the identity: atol + rtol * |I| (rtol = 1e-5).
_ORTHONORMAL_TOLERANCE = 1e-6 + 1e-5 * _IDENTITY3


def _det3(r: np.ndarray) -> float:
    a, b, c = r.tolist()
    return (
        a[0] * (b[1] * c[2] - b[2] * c[1])
        - a[1] * (b[0] * c[2] - b[2] * c[0])
        + a[2] * (b[0] * c[1] - b[1] * c[0])
    )
