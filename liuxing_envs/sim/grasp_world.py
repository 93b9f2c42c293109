"""InstrumentGrasp's MuJoCo world: one compiled scene (arm, gripper, tray, one instrument)
with its named physics queries (dm_control style: ids resolved once), resets and sensors."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from liuxing_envs import kernels
from liuxing_envs.forking import check_opengl_not_forked
from liuxing_envs.opengl import new_renderer
from liuxing_envs.sim.arm import Arm
from liuxing_envs.sim.arm_model import index_of
from liuxing_envs.sim.camera import CameraIntrinsics, DepthCamera
from liuxing_envs.sim.gripper import MAX_OPENING, TCP_SITE, Gripper, attach_gripper
from liuxing_envs.sim.instruments import add_instrument, add_tray, get_instrument
from liuxing_envs.sim.scene import HOME_QPOS, WRIST_CAMERA, load_scene_spec, reset_to_home

#: Closer than this (m) the direction from pad to instrument is left to the contact forces:
#: it is not defined at a touch.
APPROACH_MIN_GAP = 0.0005
#: A pad and an instrument geom whose bounding spheres are this much (m) farther apart than
#: the distance asked about are not measured: mj_geomDistance would answer that distance. The
#: slack covers its numerical error many times over.
BOUND_SLACK = 0.001
#: A pad "holds" the instrument when it presses on it with at least this force (ManiSkill).
GRASP_FORCE_THRESHOLD = 0.5  # N
#: Where the tool centre may go (a controller's workspace limit): over the inside of the tray,
#: up to TCP_MAX_HEIGHT (m), and no lower than FLOOR_CLEARANCE above the tray floor (m): the
#: fingertips are 4 mm below the tool centre, so they stop 1 mm short of it.
TCP_MAX_HEIGHT = 0.40
FLOOR_CLEARANCE = 0.005
#: Ready pose: the wrist camera (70 mm off the tool axis, on its -y side) looks straight
#: down from 0.45 m above the tray. The open fingers hide the image's top third (world +y), so
#: the camera sits 5 cm to +y of the tray centre to see every placement.
READY_TCP = np.array([0.5, 0.12, 0.305])
READY_OPENING = 0.06
#: Placements are redrawn until the whole instrument lies this far inside the tray's rim.
TRAY_MARGIN = 0.01  # m
SETTLE_STEPS = 50
#: A ``tool_start`` that puts the gripper into the instrument or the tray is raised in steps of
#: this much (m) until it touches nothing.
TOOL_START_RAISE = 0.001


def jaws_across(handle_axis: np.ndarray) -> float:
    """The tool yaw (rad, within +-pi/2) that puts the jaws across a handle along
    ``handle_axis``: they close along the tool's y axis (either half turn will do; this one
    keeps the wrist nearest its ready angle)."""
    return math.atan(handle_axis[1] / handle_axis[0]) if handle_axis[0] else math.pi / 2


def tool_down(yaw: float) -> np.ndarray:
    """Rotation of the tool frame pointing straight down, turned by ``yaw`` about world z."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])


_SLEEP_COUNTS = ("ntree_awake", "nbody_awake", "nparent_awake", "nv_awake")


class GraspWorld:
    """One compiled scene (arm, gripper, tray, one instrument) with its named queries."""

    PREFIX = "instrument/"

    def __init__(
        self,
        instrument: str,
        timestep: float,
        arm_stiffness: float,
        servo_damping_ratio: float | None,
    ) -> None:
        spec = load_scene_spec()
        attach_gripper(spec)
        self.tray = add_tray(spec)
        centre, half = np.asarray(self.tray.center), np.asarray(self.tray.inner_half_size)
        self.workspace_lower = np.array([*(centre - half), self.tray.floor_z + FLOOR_CLEARANCE])
        self.workspace_upper = np.array([*(centre + half), TCP_MAX_HEIGHT])
        self.instrument = get_instrument(instrument)
        add_instrument(spec, self.instrument, self.PREFIX)
        spec.option.timestep = timestep
        # Let an instrument at rest sleep (MuJoCo's island sleeping): while nothing touches
        # it, its ~10-30 tray contacts are neither collided nor solved: a physics step costs
        # ~9 us instead of ~21 us. The arm and gripper are actuated and never sleep; any contact
        # of theirs with the instrument (or any push on it) wakes it within that same step,
        # so grasps and impacts are simulated as before. Resets wake everything.
        spec.option.enableflags |= mujoco.mjtEnableBit.mjENBL_SLEEP
        self.name = instrument
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.arm = Arm(self.model, self.data)
        self.gripper = Gripper(self.model, self.data)
        model = self.model
        self.body = model.body(self.PREFIX + "body").id
        #: The instrument's kinematic tree (MuJoCo sleeps and wakes whole trees).
        self.instrument_tree = int(model.body_treeid[self.body])
        self._pad_geoms = set(self.gripper.pad_geoms.tolist())
        self._joint_qpos = model.jnt_qposadr[model.joint(self.PREFIX + "joint").id]
        self._joint_dof = model.jnt_dofadr[model.joint(self.PREFIX + "joint").id]
        self._grasp_site = model.site(self.PREFIX + "grasp").id
        #: The tool-centre site's id (a row of ``data.site_xpos`` and ``data.site_xmat``).
        self.tcp_site = model.site(TCP_SITE).id
        self._geoms = np.flatnonzero(model.geom_bodyid == self.body)
        self._fromto = np.zeros(6)
        # The pads, then the instrument's geoms: one gather of their centres per query.
        self._pads_then_geoms = np.concatenate([self.gripper.pad_geoms, self._geoms])
        # Sum of each pad's and geom's bounding-sphere radii (pads x geoms), plus the slack.
        self._bound_radii = (
            model.geom_rbound[self.gripper.pad_geoms][:, None]
            + model.geom_rbound[self._geoms][None, :]
            + BOUND_SLACK
        )
        self._nominal_mass = model.body_mass[self.body]
        self._nominal_inertia = model.body_inertia[self.body].copy()
        self._friction_geoms = self._friction_partners()
        self._nominal_friction = model.geom_friction[self._friction_geoms].copy()
        #: The arm servos' actuator ids, base to wrist (the arm's own).
        self.arm_actuators = self.arm.actuator_ids
        self._arm_ctrl_at = index_of(self.arm_actuators)
        # A softer servo keeps its damping ratio: kp scales, kv with its square root.
        model.actuator_gainprm[self.arm_actuators, 0] *= arm_stiffness
        model.actuator_biasprm[self.arm_actuators, 1] *= arm_stiffness
        model.actuator_biasprm[self.arm_actuators, 2] *= math.sqrt(arm_stiffness)
        if servo_damping_ratio is not None:
            self._damp_at_ready_pose(servo_damping_ratio)
        self._camera_id = model.camera(WRIST_CAMERA).id
        robot = model.body_rootid[model.site_bodyid[self.tcp_site]]
        self._on_robot = model.body_rootid[model.geom_bodyid] == robot
        self._kinematics = mujoco.MjData(model)
        self._observation_layout: np.ndarray | None = None
        self._camera: DepthCamera | None = None
        self._rgb: mujoco.Renderer | None = None

    def reset(
        self,
        grasp_xy,
        yaw: float,
        mass_scale: float,
        friction_scale: float,
        tool_start=None,
        tool_yaw_error: float = 0.0,
        jaw_clearance: float | None = None,
    ) -> None:
        """Place the instrument and the arm: in the ready pose, or (``tool_start``, an offset
        in m) with the tool centre that far from the grasp point and the jaws across the
        handle, turned from there by ``tool_yaw_error`` (rad) and open to the handle's width
        plus ``jaw_clearance`` (m; default READY_OPENING); then let the scene settle."""
        model, data = self.model, self.data
        reset_to_home(model, data)
        model.opt.noslip_iterations = 0  # the pads start clear of everything (see step())
        model.body_mass[self.body] = self._nominal_mass * mass_scale
        model.body_inertia[self.body] = self._nominal_inertia * mass_scale
        # From the compiled values each time, so a factor of 1 restores them exactly.
        model.geom_friction[self._friction_geoms] = self._nominal_friction * friction_scale
        # Put the grasp point at grasp_xy: the body origin is offset from it in the plane.
        c, s = math.cos(yaw), math.sin(yaw)
        gx, gy = self.instrument.grasp_point[:2]
        offset = np.array([c * gx - s * gy, s * gx + c * gy])
        position = [*(np.asarray(grasp_xy) - offset), self.tray.floor_z]
        data.qpos[self._joint_qpos : self._joint_qpos + 3] = position
        data.qpos[self._joint_qpos + 3 : self._joint_qpos + 7] = [
            math.cos(yaw / 2),
            0.0,
            0.0,
            math.sin(yaw / 2),
        ]
        data.qvel[self._joint_dof : self._joint_dof + 6] = 0.0
        opening = READY_OPENING
        if jaw_clearance is not None:
            opening = min(MAX_OPENING, self.instrument.grasp_width + jaw_clearance)
        if tool_start is None:
            self.place_tool(READY_TCP, 0.0, opening, tool_start)
        else:
            mujoco.mj_kinematics(model, data)
            tool_yaw = jaws_across(self.grasp_axis()) + tool_yaw_error
            tcp = np.clip(
                self.grasp_point() + tool_start, self.workspace_lower, self.workspace_upper
            )
            self.place_tool(tcp, tool_yaw, opening, tool_start)
            # An offset off the handle, or a turned tool, can put a finger into another part
            # of the instrument (a ring, a tine) or the tray's rim: the settling steps would
            # then shove it, or start the episode past the hard force limit.
            while self._robot_touches_anything():
                if tcp[2] >= self.workspace_upper[2]:
                    raise ValueError(
                        f"reset option tool_start {np.round(tool_start, 4).tolist()}: the "
                        "gripper touches the scene even raised to the workspace's top"
                    )
                tcp = tcp + [0.0, 0.0, TOOL_START_RAISE]
                tcp[2] = min(tcp[2], self.workspace_upper[2])
                self.place_tool(tcp, tool_yaw, opening, tool_start)
        mujoco.mj_forward(model, data)
        mujoco.mj_step(model, data, nstep=SETTLE_STEPS)

    def place_tool(self, tcp, tool_yaw: float, opening: float, tool_start) -> None:
        """Teleport the arm, pointing down, to the tool centre ``tcp`` turned by ``tool_yaw``,
        with the fingers ``opening`` apart."""
        ready = self._pointing_down(tcp, tool_yaw)
        if not ready.success:
            raise ValueError(
                f"reset option tool_start={np.asarray(tool_start).tolist()} puts the tool centre "
                f"at {np.round(tcp, 4).tolist()}, which the arm cannot reach"
            )
        self.arm.set_qpos(ready.qpos)
        self.gripper.set_opening(opening)

    def _pointing_down(self, tcp, tool_yaw: float):
        """The arm's IK (closed form, nearest home) for the tool pointing down at ``tcp``."""
        return self.arm.solve_ik(
            tcp,
            tool_down(tool_yaw),
            site=TCP_SITE,
            seed_qpos=HOME_QPOS,
            method="analytic",
            check_collisions=False,
        )

    def _damp_at_ready_pose(self, ratio: float) -> None:
        """Set each arm servo's kv for damping ``ratio`` at the ready pose: kv = 2 ratio
        sqrt(kp m), m the joint's diagonal entry of the mass matrix there (armature included)."""
        model = self.model
        ready = self._pointing_down(READY_TCP, 0.0)
        if not ready.success:
            raise RuntimeError("the arm cannot reach the ready pose to damp its servos there")
        scratch = mujoco.MjData(model)
        scratch.qpos[self.arm.qpos_indices] = ready.qpos
        mujoco.mj_forward(model, scratch)
        unit, column = np.zeros(model.nv), np.zeros(model.nv)
        for actuator in self.arm_actuators:
            dof = model.jnt_dofadr[model.actuator_trnid[actuator, 0]]
            unit[:] = 0.0
            unit[dof] = 1.0
            mujoco.mj_mulM(model, scratch, column, unit)
            stiffness = model.actuator_gainprm[actuator, 0]
            kv = 2.0 * ratio * math.sqrt(stiffness * column[dof])
            model.actuator_biasprm[actuator, 2] = -kv

    def _robot_touches_anything(self) -> bool:
        """Whether a geom of the arm or gripper, as posed now, overlaps one of the scene's."""
        model, data = self.model, self.data
        mujoco.mj_kinematics(model, data)
        mujoco.mj_collision(model, data)
        on_robot = self._on_robot[data.contact.geom]
        return bool(np.any(on_robot[:, 0] != on_robot[:, 1]))

    def _friction_partners(self) -> np.ndarray:
        """The geoms whose friction coefficients a contact of the instrument can take: its own
        and every geom that can touch it at its contact priority or above. MuJoCo takes a
        contact's friction from the geom of higher priority, and the element-wise maximum of
        the two at equal priority: the pads and the tray outrank the instrument, so scaling
        its own geoms alone would change none of its contacts with them."""
        model = self.model
        own = model.geom_bodyid == self.body
        contype = np.bitwise_or.reduce(model.geom_contype[own])
        conaffinity = np.bitwise_or.reduce(model.geom_conaffinity[own])
        can_touch = ((model.geom_contype & conaffinity) | (model.geom_conaffinity & contype)) != 0
        ranked = model.geom_priority >= model.geom_priority[own].min()
        return np.flatnonzero(own | (can_touch & ranked))

    def fits_on_tray(self, grasp_xy, yaw: float) -> bool:
        """Whether the instrument, its grasp point at ``grasp_xy`` and turned by ``yaw``, lies
        inside the tray's rim with TRAY_MARGIN to spare (its bounding-box corners do)."""
        low, high = self.instrument.bounding_box[:, :2] - self.instrument.grasp_point[:2]
        corners = np.array([[low[0], low[1]], [low[0], high[1]], [high[0], low[1]], high])
        c, s = math.cos(yaw), math.sin(yaw)
        placed = corners @ np.array([[c, s], [-s, c]]) + np.asarray(grasp_xy, dtype=float)
        limit = np.asarray(self.tray.inner_half_size) - TRAY_MARGIN
        return bool(np.all(np.abs(placed - self.tray.center) <= limit))

    @property
    def compiled(self) -> bool:
        """Whether the per-step arithmetic (the ``ee_delta`` set-point and the arm's
        closed-form IK, the observation, the approach query's filter, the force monitor's
        loop while the instrument sleeps) runs in the compiled kernels or in their
        references: one switch, the arm IK's ``compiled``, which tests flip to compare the
        two (and spies on ``mujoco.mj_step`` turn off: the compiled loop calls MuJoCo's C
        function itself)."""
        return self.arm.ik.compiled

    @compiled.setter
    def compiled(self, value: bool) -> None:
        self.arm.ik.compiled = bool(value)

    def observation_layout(self) -> np.ndarray:
        """The ids and addresses :func:`~liuxing_envs.kernels.grasp_observation.
        grasp_observation` reads at, in its layout (made on first use: the kernel module
        imports numba)."""
        if self._observation_layout is None:
            kernel = kernels.module("grasp_observation")
            layout = np.empty(kernel.LAYOUT_SIZE, dtype=np.int64)
            layout[kernel.TCP_SITE] = self.tcp_site
            layout[kernel.GRASP_SITE] = self._grasp_site
            layout[[kernel.LEFT_FINGER, kernel.RIGHT_FINGER]] = self.gripper.finger_qpos
            layout[[kernel.LEFT_TOUCH, kernel.RIGHT_TOUCH]] = self.gripper.touch_addresses
            layout[kernel.INSTRUMENT_DOF] = self._joint_dof
            layout[kernel.ARM_QPOS : kernel.ARM_QPOS + 6] = self.arm.qpos_addresses
            layout[kernel.ARM_DOF : kernel.ARM_DOF + 6] = self.arm.dof_addresses
            self._observation_layout = layout
        return self._observation_layout

    def arm_ctrl(self) -> np.ndarray:
        return self.data.ctrl[self._arm_ctrl_at].copy()

    def set_arm_ctrl(self, qpos: np.ndarray) -> None:
        self.data.ctrl[self._arm_ctrl_at] = qpos

    def tcp_position(self) -> np.ndarray:
        return self.data.site_xpos[self.tcp_site].copy()

    def tcp_yaw(self) -> float:
        """Angle of the tool's x axis about world z (rad); the jaws close along its y axis."""
        x_axis = self.data.site_xmat[self.tcp_site].reshape(3, 3)[:, 0]
        return math.atan2(x_axis[1], x_axis[0])

    def wrist_camera_pose(self, arm_qpos) -> tuple[np.ndarray, np.ndarray]:
        """Wrist camera position and rotation (columns = camera axes) for arm joint angles,
        by forward kinematics in a scratch copy (the hand-eye calibration a robot has)."""
        scratch = self._posed(arm_qpos)
        mujoco.mj_camlight(self.model, scratch)
        return scratch.cam_xpos[self._camera_id].copy(), scratch.cam_xmat[self._camera_id].reshape(
            3, 3
        ).copy()

    def _posed(self, arm_qpos) -> mujoco.MjData:
        """The scratch data with the arm at ``arm_qpos`` and the rest as now, its kinematics
        computed; the simulation itself is left alone."""
        scratch = self._kinematics
        scratch.qpos[:] = self.data.qpos
        scratch.qpos[self.arm.qpos_indices] = arm_qpos
        mujoco.mj_kinematics(self.model, scratch)
        return scratch

    def grasp_point(self) -> np.ndarray:
        return self.data.site_xpos[self._grasp_site].copy()

    def grasp_axis(self) -> np.ndarray:
        return self.data.site_xmat[self._grasp_site].reshape(3, 3)[:, 0].copy()

    def instrument_velocity(self) -> np.ndarray:
        return self.data.qvel[self._joint_dof : self._joint_dof + 3].copy()

    def grasped(self) -> bool:
        """Both pads press on the instrument with at least GRASP_FORCE_THRESHOLD each (what
        they press on the tray does not count)."""
        if self.data.ncon == 0:  # no contact at all: the common case, answered cheaply
            return False
        return bool(np.all(self.gripper.pad_forces_on(self.body) >= GRASP_FORCE_THRESHOLD))

    def asleep(self) -> bool:
        """Whether the instrument is asleep: at rest and touched by nothing awake."""
        return bool(self.data.tree_asleep[self.instrument_tree] >= 0)

    def pad_approaches(self, distance: float) -> list[float]:
        """How far (m) the arm's set-point would move each pad toward the instrument, for the
        pads between APPROACH_MIN_GAP and ``distance`` of it (see :meth:`pad_leads`)."""
        return self.pad_leads(self.approach_directions(distance), self.arm_ctrl())

    def approach_directions(
        self, distance: float, min_gap: float = APPROACH_MIN_GAP
    ) -> list[tuple[int, np.ndarray, float]]:
        """(pad geom, unit vector from it to the instrument's nearest point, gap in m) for
        each pad between ``min_gap`` and ``distance`` (m) of the instrument."""
        model, data = self.model, self.data
        # Only the pairs whose bounding spheres come within ``distance`` are measured: the
        # others lie farther than any gap this could return. While the gripper is away from
        # the instrument that skips every mj_geomDistance call, a step's dearest bookkeeping.
        if self.compiled:
            pairs_within = kernels.module("pad_bounds").pairs_within

            measured, count = pairs_within(
                data.geom_xpos, self._pads_then_geoms, self._bound_radii, distance
            )
        else:
            centres = data.geom_xpos[self._pads_then_geoms]
            offsets = centres[None, 2:] - centres[:2, None]
            reach = distance + self._bound_radii
            measured = np.add.reduce(offsets * offsets, axis=2) < reach * reach
            count = measured.any()
        if not count:
            return []
        near = []
        for pad, geoms in zip(self.gripper.pad_geoms, measured, strict=True):
            nearest, toward = distance, None
            for geom in self._geoms[geoms]:
                gap = mujoco.mj_geomDistance(model, data, pad, geom, nearest, self._fromto)
                if gap < nearest:
                    nearest = gap
                    toward = (self._fromto[3:] - self._fromto[:3]) / gap if gap > 0 else None
            if toward is not None and nearest >= min_gap:
                near.append((pad, toward, nearest))
        return near

    def pad_leads(self, near, arm_set_point) -> list[float]:
        """How far (m) the arm at ``arm_set_point`` would carry each of the ``near`` pads
        (from :meth:`approach_directions`) along its direction: the pad at the set-point's
        pose (fingers as open as now) less where it is. The fingers' own closing is not
        counted (its force is capped)."""
        if not near:
            return []
        data, scratch = self.data, self._posed(arm_set_point)
        return [
            float((scratch.geom_xpos[pad] - data.geom_xpos[pad]) @ toward)
            for pad, toward, _ in near
        ]

    def impact_force(self) -> float:
        """Contact force (N) on the instrument from anything but the pads, less its weight."""
        if self.asleep():
            return 0.0  # at rest on the tray: no contacts of its own are computed, no impact
        force = self.gripper.contact_force_on(self.body, exclude_geoms=self._pad_geoms)
        weight = self.model.body_mass[self.body] * -self.model.opt.gravity[2]
        return float(max(0.0, np.linalg.norm(force) - weight))

    def camera(self, intrinsics: CameraIntrinsics, backend: str) -> DepthCamera:
        """The wrist depth camera, made on first use (see DepthCamera for ``backend``)."""
        if self._camera is None:
            self._camera = DepthCamera(self.model, WRIST_CAMERA, intrinsics, backend=backend)
        return self._camera

    def rgb(self, intrinsics: CameraIntrinsics) -> np.ndarray:
        check_opengl_not_forked()  # a renderer made before a fork hangs in the child
        if self._rgb is None:
            self._rgb = new_renderer(self.model, intrinsics.height, intrinsics.width)
            self._rgb.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0  # 20 ms -> 1-2 ms
        self._rgb.update_scene(self.data, camera=WRIST_CAMERA)
        return self._rgb.render()

    def close(self) -> None:
        if self._camera is not None:
            self._camera.close()
            self._camera = None  # camera() makes a new one if the env is reset again
        if self._rgb is not None:
            self._rgb.close()
            self._rgb = None

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_rgb"] = None
        state["_sleep_counts"] = {name: getattr(self.data, name) for name in _SLEEP_COUNTS}
        return state

    def __setstate__(self, state: dict) -> None:
        counts = state.pop("_sleep_counts", {})
        self.__dict__.update(state)
        for name, value in counts.items():
            setattr(self.data, name, value)
