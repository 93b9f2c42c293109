"""The arm: inverse kinematics, collision checking and motion of the 6-DoF arm.

:class:`Arm` wraps the arm joints of a compiled tabletop scene (``assets/ur5e.xml``). It keeps
a private scratch :class:`mujoco.MjData` for everything hypothetical (IK iterations, collision
checks of configurations and paths), so asking questions never disturbs the simulation; only
:meth:`Arm.move_to` changes the live ``data``. Collision checks may run in a smaller scene
that holds the same arm and obstacles (:meth:`Arm.use_collision_scene`).

Two ways to move, both collision-checked and reporting the same :class:`MotionResult`:

``kinematic``
    The configuration is set directly along the straight joint-space path. The path is checked
    waypoint by waypoint first; if it would collide, the arm stops at the last collision-free
    waypoint (like a protective stop) and reports the contact. Fast; no dynamics.
``dynamic``
    The position actuators track a set-point that moves along the same path at a bounded joint
    speed, under full physics (gravity compensation, torque limits), until the arm settles
    within tolerance of the target or a timeout. A contact between the arm and anything halts
    the set-point where the arm is (a protective stop).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

from liuxing_envs.sim.scene import (
    ARM_ACTUATOR_NAMES,
    ARM_BASE_BODY,
    ARM_JOINT_NAMES,
    FLANGE_SITE,
    HOME_QPOS,
    LAST_LINK_BODY,
    WRIST_CAMERA_SITE,
)
from liuxing_envs.sim.stability import diverged_since, divergence_count
from liuxing_envs.sim.ur_ik import solutions_of_one, ur_ik
from liuxing_envs.validation import require_int, require_number

MOTION_MODES = ("kinematic", "dynamic")
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

#: Dynamic moves last ``max|Δq| / max_joint_speed``: the set-point's mean speed on the
#: joint that moves most. Its cubic ease peaks at 1.5 times that (1.5 rad/s), still well
#: under the UR5e's 3.14 rad/s.
DYNAMIC_MAX_JOINT_SPEED = 1.0  # rad/s
DYNAMIC_CONTROL_PERIOD = 0.01  # s between set-point updates and contact checks
DYNAMIC_SETTLE_TOLERANCE = 1e-3  # rad, every joint
DYNAMIC_SETTLE_SPEED = 0.02  # rad/s, every joint
DYNAMIC_TIMEOUT = 8.0  # s of simulated time
#: How far past a joint limit a closed-form solution may land and be clipped back onto it: a
#: configuration at a limit (a wrist at +-2 pi) comes back from the closed form a rounding
#: error beyond it, and was dropped for a solution of another branch, up to 5.8 rad away.
IK_LIMIT_SLACK = 1e-9  # rad
#: Contacts shallower than this are touching, not colliding (MuJoCo reports dist <= 0).
PENETRATION_TOLERANCE = 1e-4  # m


@dataclass(frozen=True)
class Contact:
    """A contact involving the arm: the two geoms and how deep they interpenetrate (m)."""

    geom1: str
    geom2: str
    depth: float


@dataclass(frozen=True)
class IKResult:
    """Outcome of :meth:`Arm.solve_ik`.

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


@dataclass(frozen=True)
class _CollisionScene:
    """Where :class:`Arm` checks collisions: a model holding the arm, a data to pose it in,
    the arm's joint addresses there and which geoms are the arm's."""

    model: mujoco.MjModel
    data: mujoco.MjData
    qpos_at: slice | np.ndarray
    is_arm_geom: np.ndarray
    #: Site ids in this model, by name, looked up on first use.
    site_ids: dict[str, int] = field(default_factory=dict)

    def site_id(self, site: str) -> int:
        if site not in self.site_ids:
            self.site_ids[site] = _require_id(self.model, mujoco.mjtObj.mjOBJ_SITE, site)
        return self.site_ids[site]


@dataclass(frozen=True)
class PathCheck:
    """Outcome of :meth:`Arm.check_path`: whether the straight joint path is free and, if not,
    the last free waypoint before the first collision."""

    free: bool
    last_free_qpos: np.ndarray
    fraction: float
    contacts: tuple[Contact, ...]


@dataclass(frozen=True)
class JointPath:
    """A collision-checked joint-space path from ``start`` through ``waypoints`` (the last one
    is the goal), made of straight segments; returned by :meth:`Arm.plan_path`."""

    start: np.ndarray
    waypoints: tuple[np.ndarray, ...]

    @property
    def length(self) -> float:
        """Joint-space length (rad): sum of the segments' Euclidean norms."""
        points = (self.start, *self.waypoints)
        return float(sum(np.linalg.norm(b - a) for a, b in zip(points, points[1:], strict=False)))


@dataclass(frozen=True)
class MotionResult:
    """Outcome of :meth:`Arm.move_to`.

    ``path_length`` is the joint-space distance actually travelled (sum of the Euclidean norms
    of the joint increments, radians). ``sim_time`` is the simulated time the motion took
    (0 for kinematic motion). ``unstable`` means the physics diverged during a dynamic
    motion (see :mod:`liuxing_envs.sim.stability`): MuJoCo reset the data, so the motion
    stopped there and the live state is no longer the episode's.
    """

    reached: bool
    qpos: np.ndarray
    path_length: float
    collided: bool
    contacts: tuple[Contact, ...]
    sim_time: float
    mode: str
    unstable: bool = False


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
        self._scratch = mujoco.MjData(model)

        joint_ids = _arm_joint_ids(model)
        self._qpos_idx = model.jnt_qposadr[joint_ids].copy()
        self._qpos_at = _qpos_writer(self._qpos_idx)
        self._dof_idx = model.jnt_dofadr[joint_ids].copy()
        self._actuator_ids = np.array(
            [_require_id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in ARM_ACTUATOR_NAMES]
        )
        self.lower = model.jnt_range[joint_ids, 0].copy()
        self.upper = model.jnt_range[joint_ids, 1].copy()

        base_id = _require_id(model, mujoco.mjtObj.mjOBJ_BODY, ARM_BASE_BODY)
        self._is_arm_geom = _arm_geom_mask(model)
        self._geom_ids = np.flatnonzero(self._is_arm_geom)
        self._live_collisions = _CollisionScene(
            model, self._scratch, self._qpos_at, self._is_arm_geom
        )
        self._collisions = self._live_collisions
        # Other collision scenes by (model, data) identity: an env switches between a few
        # stand-ins every reset, and making one (its arm-geom mask) costs ~0.1 ms.
        self._scene_cache: dict[tuple[int, int], _CollisionScene] = {}
        self._site_ids: dict[str, int] = {}
        self._site_names: dict[int, str] = {}
        self._flange_in_site: dict[int, np.ndarray | None] = {}
        last_link = _require_id(model, mujoco.mjtObj.mjOBJ_BODY, LAST_LINK_BODY)
        self._last_link_bodies = set(_subtree(model, last_link).tolist())
        d = self._pose_scratch(HOME_QPOS)
        self._base_inverse = np.linalg.inv(_homogeneous(d.xpos[base_id], d.xmat[base_id]))
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))

    # ------------------------------------------------------------------ state
    @property
    def qpos_indices(self) -> np.ndarray:
        """Addresses of the six arm joints in ``qpos``."""
        return self._qpos_idx.copy()

    @property
    def geom_ids(self) -> np.ndarray:
        """Ids of the arm's geoms (its links, down to the camera mount) in the live model."""
        return self._geom_ids.copy()

    @property
    def qpos(self) -> np.ndarray:
        """Current joint angles of the arm (rad), a copy."""
        return self.data.qpos[self._qpos_idx].copy()

    @property
    def qvel(self) -> np.ndarray:
        """Current joint velocities of the arm (rad/s), a copy."""
        return self.data.qvel[self._dof_idx].copy()

    def within_limits(self, qpos: np.ndarray) -> bool:
        qpos = np.asarray(qpos)
        return bool(((qpos >= self.lower) & (qpos <= self.upper)).all())

    def site_id(self, site: str) -> int:
        if site not in self._site_ids:
            self._site_ids[site] = _require_id(self.model, mujoco.mjtObj.mjOBJ_SITE, site)
            self._site_names[self._site_ids[site]] = site
        return self._site_ids[site]

    def site_pose(self, site: str = WRIST_CAMERA_SITE, qpos: np.ndarray | None = None):
        """World position (3,) and rotation (3, 3) of a site, now or at configuration ``qpos``."""
        sid = self.site_id(site)
        d = self.data if qpos is None else self._pose_scratch(_finite_qpos(qpos))
        return d.site_xpos[sid].copy(), d.site_xmat[sid].reshape(3, 3).copy()

    # ------------------------------------------------------------- collisions
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
            self._collisions = self._live_collisions
            return
        if data is None or data.qpos.shape != (model.nq,):
            raise ValueError("use_collision_scene needs the model's own MjData")
        key = (id(model), id(data))
        scene = self._scene_cache.get(key)
        # The cached scene holds its model and data, so their ids cannot be reused meanwhile;
        # what it derives from them (joint addresses, the arm's geoms) is fixed at compile time.
        if scene is None or scene.model is not model or scene.data is not data:
            joints = _arm_joint_ids(model)
            scene = self._scene_cache[key] = _CollisionScene(
                model,
                data,
                _qpos_writer(model.jnt_qposadr[joints]),
                _arm_geom_mask(model),
            )
        self._collisions = scene

    def collisions(self, qpos: np.ndarray | None = None) -> tuple[Contact, ...]:
        """Contacts of the arm (with itself or the world) at ``qpos`` (default: now).

        The rest of the world (objects, their poses) is the live data's, or the collision
        scene's (:meth:`use_collision_scene`).
        """
        d = self._posed_for_collisions(self.qpos if qpos is None else _finite_qpos(qpos))
        mujoco.mj_collision(self._collisions.model, d)
        return self._arm_contacts(d, self._collisions)

    def in_collision(self, qpos: np.ndarray) -> bool:
        return bool(self.collisions(qpos))

    def check_path(self, q_from: np.ndarray, q_to: np.ndarray) -> PathCheck:
        """Collision-check the straight joint-space path from ``q_from`` to ``q_to``."""
        q_from, q_to = _finite_qpos(q_from, "q_from"), _finite_qpos(q_to, "q_to")
        scene = self._collisions
        m, d = scene.model, scene.data
        waypoints = self._waypoints(q_from, q_to)
        last_free = q_from.copy()
        self._posed_for_collisions(last_free)  # the world (objects) is copied once per path
        # The hot loop of planning (dozens of waypoints per path): locals, and the contact
        # filter only runs when MuJoCo found any contact at all.
        qpos, qpos_at = d.qpos, scene.qpos_at
        kinematics, collision = mujoco.mj_kinematics, mujoco.mj_collision
        for k, q in enumerate(waypoints):
            qpos[qpos_at] = q
            kinematics(m, d)
            collision(m, d)
            if d.ncon:
                contacts = self._arm_contacts(d, scene)
                if contacts:
                    fraction = k / len(waypoints)
                    return PathCheck(False, last_free, fraction, contacts)
            last_free = q
        return PathCheck(True, last_free, 1.0, ())

    def plan_path(
        self, goal: np.ndarray, *, via: np.ndarray | None = HOME_QPOS
    ) -> JointPath | None:
        """A collision-free path from the current configuration to ``goal``: the straight
        joint-space segment if it is free, else two straight segments through ``via``
        (default: home, a retract pose clear of the table), else None."""
        start, goal = self.qpos, self._checked_qpos(goal)
        if self.check_path(start, goal).free:
            return JointPath(start, (goal,))
        if via is not None:
            via = self._checked_qpos(via)
            if self.check_path(start, via).free and self.check_path(via, goal).free:
                return JointPath(start, (via, goal))
        return None

    # ------------------------------------------------------------------- IK
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
        sid = self.site_id(site)
        reference = self.qpos if seed_qpos is None else _finite_qpos(seed_qpos, "seed_qpos")
        analytic_ok = target_r is not None and self._flange_from_site(sid) is not None
        if method == "analytic" and not analytic_ok:
            raise ValueError(
                "the analytic IK needs a target rotation and a site fixed to the last link"
            )
        if method != "dls" and analytic_ok:
            return self._solve_analytic(
                target_p, target_r, sid, roll_free, reference, check_collisions
            )
        rng = np.random.default_rng(self.ik_seed)
        seeds = [reference, HOME_QPOS]
        sample_lo, sample_hi = np.maximum(self.lower, -np.pi), np.minimum(self.upper, np.pi)
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
            colliding = check_collisions and self.in_collision(q)
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

    def _flange_from_site(self, sid: int) -> np.ndarray | None:
        """Pose of the flange in the frame of site ``sid`` if the site is rigidly attached to
        the last link (else None), computed once per site."""
        if sid not in self._flange_in_site:
            if self.model.site_bodyid[sid] not in self._last_link_bodies:
                self._flange_in_site[sid] = None
            else:
                d = self._pose_scratch(HOME_QPOS)
                world_site = _homogeneous(d.site_xpos[sid], d.site_xmat[sid])
                fid = self.site_id(FLANGE_SITE)
                world_flange = _homogeneous(d.site_xpos[fid], d.site_xmat[fid])
                self._flange_in_site[sid] = np.linalg.inv(world_site) @ world_flange
        return self._flange_in_site[sid]

    def _solve_analytic(self, target_p, target_r, sid, roll_free, reference, check_collisions):
        flange_in_site = self._flange_from_site(sid)
        if roll_free:
            site_poses = np.empty((len(_ROLLS), 4, 4))
            site_poses[:, :3, :3] = target_r @ _ROLLS  # turning about the site's own z keeps z
            site_poses[:, :3, 3] = target_p
            site_poses[:, 3] = _HOMOGENEOUS_ROW
            solutions, valid = ur_ik(self._base_inverse @ site_poses @ flange_in_site)
            ordered = self._nearest_first(solutions[valid], reference)
        else:  # a controller's target: one pose, on Python floats (see ur_ik)
            ordered = self._one_pose_nearest_first(target_p, target_r, flange_in_site, reference)
        tried, colliding = 0, None
        for q in map(np.asarray, ordered):
            tried += 1
            if check_collisions and self.in_collision(q):
                colliding = q if colliding is None else colliding
                continue
            return self._ik_result(True, q, sid, target_p, target_r, roll_free, tried, False)
        if colliding is not None:
            return self._ik_result(
                False, colliding, sid, target_p, target_r, roll_free, tried, True
            )
        return IKResult(False, reference.copy(), np.inf, np.inf, 0, tried, False)

    def _nearest_first(self, candidates: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """IK solutions (rows) shifted by whole turns towards ``reference`` where that stays
        within the joint limits, those within the limits, nearest (joint space) first."""
        if len(candidates):
            lower, upper = self.lower - IK_LIMIT_SLACK, self.upper + IK_LIMIT_SLACK
            turns = np.round((reference - candidates) / (2 * np.pi))
            shifted = candidates + 2 * np.pi * turns
            inside = (shifted >= lower) & (shifted <= upper)
            candidates = np.where(inside, shifted, candidates)
            within = (candidates >= lower) & (candidates <= upper)
            candidates = np.clip(candidates[within.all(axis=1)], self.lower, self.upper)
        # np.linalg.norm(axis=1) spelled out (the same sums): it is hot and costs ~10 us.
        offsets = candidates - reference
        return candidates[np.argsort(np.sqrt(np.add.reduce(offsets * offsets, axis=1)))]

    def _nearest_first_of_few(
        self, solutions: list[tuple[int, list[float]]], reference: np.ndarray
    ) -> list[list[float]]:
        """:meth:`_nearest_first` of a few solutions (``solutions_of_one``'s), on Python
        floats (numpy's per-call overhead would cost more than the arithmetic), as lists of
        joint angles. It runs on every step of a controller, so the common cases skip calls:
        a joint within half a turn of the reference needs no whole turns (``round`` of a
        quotient within +-0.5 is 0), one inside its limits needs no clipping."""
        joint_bounds = [
            (near, low - IK_LIMIT_SLACK, high + IK_LIMIT_SLACK, low, high)
            for near, low, high in zip(
                reference.tolist(), self.lower.tolist(), self.upper.tolist(), strict=True
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
        flange_in_site = self._flange_from_site(self.site_id(site))
        if flange_in_site is None:
            raise ValueError(
                f"the closed-form IK needs a site fixed to the last link, not {site!r}"
            )
        ordered = self._one_pose_nearest_first(position, rotation, flange_in_site, reference)
        return np.array(ordered[0]) if ordered else None

    def _one_pose_nearest_first(self, position, rotation, flange_in_site, reference):
        """The closed-form solutions for one site pose, as :meth:`_nearest_first_of_few`
        orders them."""
        flange_in_base = self._base_inverse @ _homogeneous(position, rotation) @ flange_in_site
        return self._nearest_first_of_few(solutions_of_one(flange_in_base), reference)

    def _ik_result(self, success, q, sid, target_p, target_r, roll_free, attempts, colliding):
        # The collision scene holds the same arm, so its kinematics give the same site pose;
        # a stand-in (see use_collision_scene) computes them for a fraction of the bodies.
        scene = self._collisions
        d = self._posed_for_collisions(q)
        if scene is not self._live_collisions:
            sid = scene.site_id(self._site_names[sid])
        pos_err = float(np.linalg.norm(target_p - d.site_xpos[sid]))
        rotvec = _rotation_error(d.site_xmat[sid].reshape(3, 3), target_r, roll_free)
        return IKResult(
            success, q.copy(), pos_err, float(np.linalg.norm(rotvec)), 0, attempts, colliding
        )

    def _dls(self, seed, sid, target_p, target_r, roll_free, pos_tol, rot_tol, max_iterations):
        m, d = self.model, self._scratch
        q = np.clip(np.asarray(seed, dtype=float), self.lower, self.upper)
        weights = np.array(
            [1.0, 1.0, 1.0, IK_ROTATION_WEIGHT, IK_ROTATION_WEIGHT, IK_ROTATION_WEIGHT]
        )
        rows = 6 if target_r is not None else 3
        damping = IK_DAMPING**2 * np.eye(rows)
        jac = np.empty((6, len(self._dof_idx)))
        err = np.zeros(6)
        pos_err = rot_err = np.inf
        checkpoint_err = np.inf
        self._pose_scratch(q)  # the world (objects) is copied once per attempt
        qpos_idx = self._qpos_idx
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
            jac[:3] = self._jacp[:, self._dof_idx]
            jac[3:] = self._jacr[:, self._dof_idx]
            jac_w = (jac * weights[:, None])[:rows]
            err_w = (err * weights)[:rows]
            dq = jac_w.T @ np.linalg.solve(jac_w @ jac_w.T + damping, err_w)
            step = math.sqrt(dq @ dq)
            if step > IK_MAX_STEP:
                dq *= IK_MAX_STEP / step
            q = np.clip(q + dq, self.lower, self.upper)
        return q, pos_err, rot_err, iteration

    def _nearest_equivalent(self, q: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Shift joints by whole turns towards ``reference`` where the limits allow it."""
        turns = np.round((reference - q) / (2 * np.pi))
        shifted = q + turns * 2 * np.pi
        ok = (shifted >= self.lower) & (shifted <= self.upper)
        return np.where(ok, shifted, q)

    # ---------------------------------------------------------------- motion
    def move_to(
        self,
        qpos: np.ndarray,
        mode: str = "kinematic",
        *,
        max_joint_speed: float = DYNAMIC_MAX_JOINT_SPEED,
        timeout: float = DYNAMIC_TIMEOUT,
        settle_tolerance: float = DYNAMIC_SETTLE_TOLERANCE,
    ) -> MotionResult:
        """Move the live arm to joint configuration ``qpos`` along the straight joint path
        (see the module docstring)."""
        target = self._checked_qpos(qpos)
        self._check_mode(mode)
        _check_dynamic_settings(max_joint_speed, timeout, settle_tolerance)
        if mode == "kinematic":
            return self._move_kinematic(target)
        return self._move_dynamic(target, max_joint_speed, timeout, settle_tolerance)

    def follow(
        self,
        path: JointPath,
        mode: str = "kinematic",
        *,
        max_joint_speed: float = DYNAMIC_MAX_JOINT_SPEED,
        timeout: float = DYNAMIC_TIMEOUT,
        settle_tolerance: float = DYNAMIC_SETTLE_TOLERANCE,
    ) -> MotionResult:
        """Execute a path from :meth:`plan_path`, which must start at the current configuration.

        Kinematic motion trusts the plan's collision checks and jumps to the goal; dynamic
        motion drives the servos through every waypoint under physics (``timeout`` applies
        to each segment) and stops at the first contact or missed waypoint.
        """
        self._check_mode(mode)
        _check_dynamic_settings(max_joint_speed, timeout, settle_tolerance)
        now = self.qpos
        # np.allclose(path.start, now, atol=1e-9) spelled out: it is hot and costs 10 us.
        if not (np.abs(path.start - now) <= 1e-9 + 1e-5 * np.abs(now)).all():
            raise ValueError("the path does not start at the arm's current configuration")
        if mode == "kinematic":
            self.set_qpos(path.waypoints[-1])
            return MotionResult(True, path.waypoints[-1].copy(), path.length, False, (), 0.0, mode)
        travelled, sim_time = 0.0, 0.0
        for waypoint in path.waypoints:
            result = self._move_dynamic(waypoint, max_joint_speed, timeout, settle_tolerance)
            travelled += result.path_length
            sim_time += result.sim_time
            if not result.reached:
                break
        return MotionResult(
            result.reached,
            result.qpos,
            travelled,
            result.collided,
            result.contacts,
            sim_time,
            mode,
            result.unstable,
        )

    def _move_kinematic(self, target: np.ndarray) -> MotionResult:
        start = self.qpos
        check = self.check_path(start, target)
        final = target if check.free else check.last_free_qpos
        self.set_qpos(final)
        return MotionResult(
            reached=check.free,
            qpos=final.copy(),
            path_length=float(np.linalg.norm(final - start)),
            collided=not check.free,
            contacts=check.contacts,
            sim_time=0.0,
            mode="kinematic",
        )

    def _move_dynamic(self, target, max_joint_speed, timeout, settle_tolerance) -> MotionResult:
        m, d = self.model, self.data
        start = self.qpos
        delta = target - start
        duration = float(np.max(np.abs(delta))) / max_joint_speed
        substeps = max(1, round(DYNAMIC_CONTROL_PERIOD / m.opt.timestep))
        period = substeps * m.opt.timestep
        t = 0.0
        previous = start
        path_length = 0.0
        divergences = divergence_count(d)
        while t < timeout:
            progress = min(1.0, t / duration) if duration > 0 else 1.0
            d.ctrl[self._actuator_ids] = start + _smoothstep(progress) * delta
            mujoco.mj_step(m, d, nstep=substeps)
            t += period
            if diverged_since(d, divergences):
                return MotionResult(
                    False, self.qpos, path_length, False, (), t, "dynamic", unstable=True
                )
            q = self.qpos
            path_length += float(np.linalg.norm(q - previous))
            previous = q
            contacts = self._arm_contacts(d, self._live_collisions)
            if contacts:
                d.ctrl[self._actuator_ids] = q
                return MotionResult(False, q, path_length, True, contacts, t, "dynamic")
            settled = (
                progress >= 1.0
                and np.max(np.abs(q - target)) <= settle_tolerance
                and np.max(np.abs(self.qvel)) <= DYNAMIC_SETTLE_SPEED
            )
            if settled:
                return MotionResult(True, q, path_length, False, (), t, "dynamic")
        return MotionResult(False, self.qpos, path_length, False, (), t, "dynamic")

    def _checked_qpos(self, qpos) -> np.ndarray:
        target = _finite_qpos(qpos)
        if not self.within_limits(target):
            raise ValueError(
                f"qpos {np.round(target, 4).tolist()} is outside the joint limits "
                f"[{self.lower.round(4).tolist()}, {self.upper.round(4).tolist()}]"
            )
        return target

    @staticmethod
    def _check_mode(mode: str) -> None:
        if mode not in MOTION_MODES:
            raise ValueError(f"unknown motion mode {mode!r}; allowed: {MOTION_MODES}")

    def set_qpos(self, qpos: np.ndarray) -> None:
        """Teleport the live arm to ``qpos`` at rest, hold it there, and update kinematics."""
        self.data.qpos[self._qpos_idx] = qpos
        self.data.qvel[self._dof_idx] = 0.0
        self.data.ctrl[self._actuator_ids] = qpos
        mujoco.mj_forward(self.model, self.data)

    # --------------------------------------------------------------- helpers
    def _pose_scratch(self, qpos: np.ndarray) -> mujoco.MjData:
        """The scratch data with the live world (objects, mocap) and the arm at ``qpos``."""
        d = self._scratch
        d.qpos[:] = self.data.qpos
        d.mocap_pos[:] = self.data.mocap_pos
        d.mocap_quat[:] = self.data.mocap_quat
        d.qpos[self._qpos_at] = qpos
        mujoco.mj_kinematics(self.model, d)
        return d

    def _posed_for_collisions(self, qpos: np.ndarray) -> mujoco.MjData:
        """The collision scene's data with the arm at ``qpos``, kinematics done."""
        scene = self._collisions
        if scene is self._live_collisions:  # its obstacles are copied from the live data
            return self._pose_scratch(qpos)
        scene.data.qpos[scene.qpos_at] = qpos
        mujoco.mj_kinematics(scene.model, scene.data)
        return scene.data

    @staticmethod
    def _arm_contacts(d: mujoco.MjData, scene: _CollisionScene) -> tuple[Contact, ...]:
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

    def _waypoints(self, q_from: np.ndarray, q_to: np.ndarray) -> np.ndarray:
        q_from, q_to = np.asarray(q_from, dtype=float), np.asarray(q_to, dtype=float)
        sweep = float(np.abs(q_to - q_from) @ JOINT_LEVER_ARMS)
        count = max(1, int(np.ceil(sweep / self.path_check_step)))
        fractions = np.arange(1, count + 1)[:, None] / count
        return q_from + fractions * (q_to - q_from)


def _check_dynamic_settings(max_joint_speed, timeout, settle_tolerance) -> None:
    # A speed of 0 divided by zero; a negative or NaN one skipped the ramp and stepped the
    # servos to the goal at once.
    require_number("max_joint_speed", max_joint_speed, 1e-6, math.inf)
    require_number("timeout", timeout, 1e-6, math.inf)
    require_number("settle_tolerance", settle_tolerance, 1e-9, math.inf)


def _finite_qpos(qpos, name: str = "qpos") -> np.ndarray:
    """``qpos`` as 6 finite joint angles, or a ValueError naming it (a NaN configuration
    is in collision with nothing, so a check of it would pass)."""
    try:
        angles = np.asarray(qpos, dtype=float)
    except (TypeError, ValueError):
        angles = None
    if angles is None or angles.shape != (6,) or not np.isfinite(angles).all():
        raise ValueError(f"{name} must be 6 finite joint angles, got {qpos!r}")
    return angles


def _rolls_about_z(angles: np.ndarray) -> np.ndarray:
    c, s = np.cos(angles), np.sin(angles)
    roll = np.zeros((len(angles), 3, 3))
    roll[:, 0, 0], roll[:, 0, 1], roll[:, 1, 0], roll[:, 1, 1], roll[:, 2, 2] = c, -s, s, c, 1
    return roll


#: The rotations about the site's z axis the analytic IK tries when the roll is free.
_ROLLS = _rolls_about_z(np.linspace(0, 2 * np.pi, IK_ROLL_SAMPLES, endpoint=False))


def _homogeneous(position, rotation) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(rotation).reshape(3, 3)
    pose[:3, 3] = position
    return pose


def _smoothstep(s: float) -> float:
    """Zero-velocity start and end for the dynamic set-point (cubic ease)."""
    return s * s * (3.0 - 2.0 * s)


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


def _require_id(model: mujoco.MjModel, obj: mujoco.mjtObj, name: str) -> int:
    idx = mujoco.mj_name2id(model, obj, name)
    if idx < 0:
        kind = obj.name.removeprefix("mjOBJ_").lower()
        raise ValueError(f"the model has no {kind} named {name!r}; is it a liuxing_envs scene?")
    return idx


def _arm_joint_ids(model: mujoco.MjModel) -> np.ndarray:
    return np.array([_require_id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in ARM_JOINT_NAMES])


def _qpos_writer(addresses: np.ndarray) -> slice | np.ndarray:
    """What to index ``qpos`` with to write the arm's joints: a slice when they are
    contiguous. Writing a slice costs a fifth of a fancy-index write, and the planning loop
    sets the joints dozens of times per path."""
    first = int(addresses[0])
    contiguous = np.array_equal(addresses, np.arange(first, first + len(addresses)))
    return slice(first, first + len(addresses)) if contiguous else addresses.copy()


def _arm_geom_mask(model: mujoco.MjModel) -> np.ndarray:
    base = _require_id(model, mujoco.mjtObj.mjOBJ_BODY, ARM_BASE_BODY)
    return np.isin(model.geom_bodyid, _subtree(model, base))


def _subtree(model: mujoco.MjModel, root: int) -> np.ndarray:
    """Ids of ``root`` and every body below it."""
    inside = np.zeros(model.nbody, dtype=bool)
    inside[root] = True
    for body in range(root + 1, model.nbody):  # parents always precede children
        inside[body] = inside[model.body_parentid[body]]
    return np.flatnonzero(inside)
