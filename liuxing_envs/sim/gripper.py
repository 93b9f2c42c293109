"""The parallel-jaw gripper: attach it to the arm, command it, read its forces.

``assets/parallel_gripper.xml`` is attached at the arm's ``flange`` site with the name prefix
``gripper/``. Grasping is by friction only: pads with elliptic friction cones (the scene's
``cone="elliptic"``, ``impratio=10``) and, for grasp scenes, ``noslip_iterations`` so that a
held object does not creep out of the pads. There is no weld or equality constraint.

Force sensing, documented:

- :meth:`Gripper.fingertip_forces`: per-finger normal force (N) from MuJoCo ``touch``
  sensors whose sites enclose the pads: the sum of the normal components of the contacts on
  each pad, whatever they touch.
- :meth:`Gripper.contact_force_on`: the net contact force (N, world frame, 3-vector) that
  everything else exerts on a body, summed over its contacts with ``mj_contactForce``.
"""

from __future__ import annotations

import mujoco
import numpy as np

from liuxing_envs.assets import asset_path
from liuxing_envs.sim.arm_model import index_of
from liuxing_envs.sim.scene import FLANGE_SITE

GRIPPER_FILE = "parallel_gripper.xml"
GRIPPER_PREFIX = "gripper/"
#: Extra iterations of MuJoCo's no-slip solver: without them a pinched instrument creeps out
#: of a firm grasp at 50-155 um/s (mujoco issue 3328); 10 cut that about 110-fold.
GRASP_NOSLIP_ITERATIONS = 10
MAX_OPENING = 0.08  # m, both fingers fully open
SERVO_FORCE_LIMIT = 40.0  # N, the finger servos' forcerange in the asset
FINGER_JOINTS = ("left_finger_joint", "right_finger_joint")
FINGER_ACTUATORS = ("left_finger", "right_finger")
PAD_GEOMS = ("left_pad", "right_pad")
PAD_TOUCH_SENSORS = ("left_pad_touch", "right_pad_touch")
TCP_SITE = GRIPPER_PREFIX + "tcp"
#: Finger joint damping (N s/m) under force commands. A force-limited servo drives its finger
#: at the full commanded force until it touches; this damping caps the closing speed at
#: force / damping (6 cm/s at 2.5 N), as an industrial gripper's speed setting does, so the
#: pads meet a handle without an impact spike.
FORCE_COMMAND_DAMPING = 40.0


def attach_gripper(spec: mujoco.MjSpec, *, noslip_iterations: int = GRASP_NOSLIP_ITERATIONS):
    """Attach the gripper to the arm's flange in ``spec`` and tune the solver for grasping:
    noslip iterations against creep, and the full implicit integrator, whose velocity
    derivatives include the gyroscopic terms: thin instruments (1e-7 kg m^2 about their long
    axis) pressed by a finger spin up without bound under ``implicitfast`` at 2 ms."""
    gripper = mujoco.MjSpec.from_file(str(asset_path(GRIPPER_FILE)))
    spec.site(FLANGE_SITE).attach_body(gripper.body("base"), GRIPPER_PREFIX, "")
    spec.option.noslip_iterations = noslip_iterations
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICIT
    return spec


class Gripper:
    """Named queries and commands of the attached gripper; ids resolved once."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        self.model, self.data = model, data

        def ids(kind: str, names) -> np.ndarray:
            lookup = getattr(model, kind)  # model.joint, model.actuator, ...
            return np.array([lookup(GRIPPER_PREFIX + name).id for name in names])

        joints = ids("joint", FINGER_JOINTS)
        self._joints = joints
        self.finger_qpos = model.jnt_qposadr[joints]
        self._left_qpos, self._right_qpos = self.finger_qpos.tolist()
        self._dof_idx = model.jnt_dofadr[joints]
        self.finger_actuators = ids("actuator", FINGER_ACTUATORS)
        # The same two actuators as a slice where they are neighbours (the asset's order):
        # the per-step commands write through it, which costs a third of a fancy index.
        self._fingers = index_of(self.finger_actuators)
        self._ctrl_high = model.actuator_ctrlrange[self.finger_actuators, 1].copy()
        self.pad_geoms = ids("geom", PAD_GEOMS)
        sensors = ids("sensor", PAD_TOUCH_SENSORS)
        #: The left and right pad's touch readings' addresses in ``data.sensordata``.
        self.touch_addresses = model.sensor_adr[sensors]
        self._left_touch, self._right_touch = self.touch_addresses.tolist()
        self.max_force = float(model.actuator_forcerange[self.finger_actuators[0], 1])
        self._wrench = np.zeros(6)

    def opening(self) -> float:
        """Distance between the pads (m)."""
        qpos = self.data.qpos  # two items: a fifth of indexing the array (np.sum: 5x more)
        return qpos.item(self._left_qpos) + qpos.item(self._right_qpos)

    def command(self, opening: float) -> None:
        """Set the servo target: the pad distance to close or open to (m), clipped to range."""
        # Floats, not np.clip: this runs every control step, and np.clip costs ~10 µs a call.
        half = 0.5 * min(max(float(opening), 0.0), MAX_OPENING)
        self.data.ctrl[self._fingers] = half

    def grip(self, force: float) -> None:
        """Force command, as an industrial gripper's force setting: each finger servos to the
        end of its travel with at most ``|force|`` N, closing for ``force > 0`` and opening
        for ``force < 0``. A held object is then squeezed with the commanded force, and
        fingers closing on nothing stop at the closed position without pressing the pads
        together. Needs :meth:`use_force_commands` first."""
        limit = min(abs(float(force)), self.max_force)
        self.model.actuator_forcerange[self._fingers] = (-limit, limit)
        self.data.ctrl[self._fingers] = 0.0 if force > 0.0 else 0.5 * MAX_OPENING

    def use_force_commands(self) -> None:
        """Damp the fingers for :meth:`grip` (see FORCE_COMMAND_DAMPING)."""
        self.model.dof_damping[self._dof_idx] = FORCE_COMMAND_DAMPING

    def set_opening(self, opening: float) -> None:
        """Teleport the fingers to ``opening`` at rest and hold them there with the servo's
        full force (for resets)."""
        half = 0.5 * float(np.clip(opening, 0.0, MAX_OPENING))
        self.data.qpos[self.finger_qpos] = half
        self.data.qvel[self._dof_idx] = 0.0
        self.data.ctrl[self.finger_actuators] = half
        self.model.actuator_forcerange[self.finger_actuators] = (-self.max_force, self.max_force)

    def closing_directions(self) -> np.ndarray:
        """World-frame unit vectors along which the left and right pad move as their finger
        closes (rows)."""
        return -self.data.xaxis[self._joints]

    def finger_of(self, pad_geom: int) -> int:
        """0 for the left finger's pad, 1 for the right's."""
        return 0 if pad_geom == self.pad_geoms[0] else 1

    def limit_closing(self, finger: int, travel: float) -> bool:
        """Keep ``finger``'s servo target from closing more than ``travel`` (m) past where the
        finger is now; True where that shortened the target."""
        actuator = self.finger_actuators[finger]
        # A finger pressed a hair past its travel's end must not get a target beyond it.
        lowest = min(
            float(self.data.qpos[self.finger_qpos[finger]]) - travel, self._ctrl_high[finger]
        )
        if self.data.ctrl[actuator] >= lowest:
            return False
        self.data.ctrl[actuator] = lowest
        return True

    def commanded_opening(self) -> float:
        left, right = self.data.ctrl[self._fingers].tolist()
        return left + right

    def fingertip_forces(self) -> np.ndarray:
        """Normal force on the left and right pad (N), from the touch sensors."""
        return self.data.sensordata[self.touch_addresses].copy()

    def fingertip_force_values(self) -> tuple[float, float]:
        """:meth:`fingertip_forces` as two Python floats (the force monitor reads them several
        times a step; this costs a third of indexing and copying an array)."""
        sensordata = self.data.sensordata
        return sensordata.item(self._left_touch), sensordata.item(self._right_touch)

    def actuator_forces(self) -> np.ndarray:
        """Force each finger servo applies (N; negative = closing)."""
        return self.data.actuator_force[self.finger_actuators].copy()

    def pads_touching(self, body_id: int) -> np.ndarray:
        """Whether the left and right pad are each in contact with ``body_id``."""
        d, m = self.data, self.model
        if d.ncon == 0:
            return np.zeros(2, dtype=bool)
        geoms = d.contact.geom
        on_body = m.geom_bodyid[geoms] == body_id
        # A contact pairs a pad with the body when one side is the pad, the other the body.
        return np.array(
            [
                np.any((geoms[:, 0] == pad) & on_body[:, 1] | (geoms[:, 1] == pad) & on_body[:, 0])
                for pad in self.pad_geoms
            ]
        )

    def pad_forces_on(self, body_id: int) -> np.ndarray:
        """Normal force (N) of the left and right pad on ``body_id`` alone: unlike
        :meth:`fingertip_forces`, a pad also pressing the tray or another body does not
        count here."""
        forces = np.zeros(2)
        d, m = self.data, self.model
        if d.ncon == 0:
            return forces
        geoms = d.contact.geom
        on_body = m.geom_bodyid[geoms] == body_id
        for side, pad in enumerate(self.pad_geoms):
            pairs = (geoms[:, 0] == pad) & on_body[:, 1] | (geoms[:, 1] == pad) & on_body[:, 0]
            for i in np.flatnonzero(pairs):
                mujoco.mj_contactForce(m, d, i, self._wrench)
                forces[side] += self._wrench[0]  # the normal, first axis of the contact frame
        return forces

    def contact_force_on(self, body_id: int, *, exclude_geoms=()) -> np.ndarray:
        """Net contact force (N, world frame) that everything else exerts on ``body_id``,
        leaving out contacts with any geom in ``exclude_geoms`` (e.g. the pads)."""
        d, m = self.data, self.model
        # The net external force on the body (contacts are its only constraints) costs one
        # pass over the bodies; the few excluded contacts are then taken back out.
        mujoco.mj_rnePostConstraint(m, d)
        total = d.cfrc_ext[body_id, 3:].copy()
        if d.ncon == 0 or not len(exclude_geoms):
            return total
        geoms = d.contact.geom
        bodies = m.geom_bodyid[geoms]
        is_excluded = np.zeros(m.ngeom, dtype=bool)
        is_excluded[list(exclude_geoms)] = True
        excluded = (bodies == body_id).any(axis=1) & (bodies[:, 0] != bodies[:, 1])
        excluded &= is_excluded[geoms].any(axis=1)
        frames = d.contact.frame
        for i in np.flatnonzero(excluded):
            mujoco.mj_contactForce(m, d, i, self._wrench)
            # The wrench is in the contact frame and acts on geom2's body (from geom1's).
            force = frames[i].reshape(3, 3).T @ self._wrench[:3]
            total -= force if bodies[i, 1] == body_id else -force
        return total
