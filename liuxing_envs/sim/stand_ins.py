"""Stand-ins of the tabletop scene with one object variant each, where ViewPlanning's hot
loops (path collision checks, ray casting) run instead of the env's model of every variant."""

from __future__ import annotations

import weakref

import mujoco
import numpy as np

from liuxing_envs.sim.camera import DepthCamera
from liuxing_envs.sim.object_stage import PARKING_POSITION, ObjectStage, PlacedObject
from liuxing_envs.sim.scene import ARM_BASE_BODY, load_scene_spec


class VariantScenes:
    """Stand-ins of the tabletop scene with one object variant only.

    The env's model holds one body per (object, scale) variant, parked when not shown: 74
    bodies for the train set. Forward kinematics and ``mj_multiRay`` visit every body and
    geom, parked or not, so the hot loops run in stand-ins that hold the table and this
    variant only, with the same names, geoms and world frame, giving identical answers:

    * the stand-in with the arm is the arm's collision scene (:meth:`Arm.use_collision_scene`),
      where a path waypoint's kinematics cost a third of the env model's;
    * ray casting uses the same stand-in, synced from the live data before each image, or, for
      the views in which :meth:`DepthCamera.may_see_geoms` rules out every arm geom (most of
      them: the arm is behind the camera), one without the arm. Casting into them costs about
      30% and 45% less than into the env's model.
    """

    #: Arena of a stand-in's data: kinematics, a few contacts and ray casting need a few KiB.
    MEMORY = 1 << 18

    def __init__(self, live: mujoco.MjModel, mesh, scale: float) -> None:
        self._with_arm = StandIn(mesh, scale, with_arm=True)
        self._without_arm = StandIn(mesh, scale, with_arm=False)
        model = self._with_arm.model
        for obj, count in (
            (mujoco.mjtObj.mjOBJ_BODY, self._with_arm.nbody),
            (mujoco.mjtObj.mjOBJ_GEOM, self._with_arm.ngeom),
        ):
            for i in range(count):
                if mujoco.mj_id2name(live, obj, i) != mujoco.mj_id2name(model, obj, i):
                    raise RuntimeError("the stand-in scene does not match the env's model")
        # The arm's geoms: the shared ones not on the world body.
        self._arm_geoms = np.flatnonzero(model.geom_bodyid[: self._with_arm.ngeom] > 0)
        if self._without_arm.model.ngeom != model.ngeom - self._arm_geoms.size:
            raise RuntimeError("the arm-free stand-in holds more than the world and object")

    @property
    def model(self) -> mujoco.MjModel:
        """The stand-in model with the arm, shared by the envs of a process."""
        return self._with_arm.model

    def collision_scene(self, placed: PlacedObject) -> tuple[mujoco.MjModel, mujoco.MjData]:
        """The stand-in with the arm, ``placed`` on the table, for the arm's collision checks."""
        return self._with_arm.model, self._with_arm.place(placed)

    def ray_scene(
        self, live: mujoco.MjData, placed: PlacedObject, camera: DepthCamera
    ) -> tuple[mujoco.MjModel, mujoco.MjData]:
        """The stand-in to cast the live view into, with ``placed`` on the table."""
        stand_in = self._with_arm
        if not camera.may_see_geoms(live, self._arm_geoms).any():
            stand_in = self._without_arm
        return stand_in.model, stand_in.sync(live, placed)


class StandIn:
    """One stand-in model of :class:`VariantScenes` and its kinematic state.

    Its first :attr:`nbody` bodies and :attr:`ngeom` geoms (world, table, arm, camera; none
    of the arm's without it) have the ids of the live model's and are posed from it:
    ObjectStage appends the object after the scene's own bodies.
    """

    def __init__(self, mesh, scale: float, *, with_arm: bool) -> None:
        self._stage = ObjectStage([mesh], (scale,))
        self.model = stand_in_model(mesh, scale, with_arm)
        self.data = mujoco.MjData(self.model)
        # The model is shared by the envs of a process, and binding switches its one
        # variant's collisions off until it is placed: placing it here keeps them on for the
        # envs whose stand-in was placed before. Each env poses the variant in its own data.
        self._stage.bind(self.model, self.data)
        self._stage.place(mesh.name, scale, PARKING_POSITION, 0.0)
        self._placed: PlacedObject | None = None
        self.nbody = self.model.nbody - 1 if with_arm else 0
        self.ngeom = self.model.ngeom - 1 if with_arm else 0

    def place(self, placed: PlacedObject) -> mujoco.MjData:
        """The data with ``placed`` on the table, as the live object is."""
        if placed is not self._placed:  # a new episode
            self._stage.place(placed.name, placed.scale, placed.position, placed.yaw)
            self._placed = placed
            mujoco.mj_kinematics(self.model, self.data)
        return self.data

    def sync(self, live: mujoco.MjData, placed: PlacedObject) -> mujoco.MjData:
        """The data with ``placed`` on the table and the arm (if any) posed as in ``live``."""
        d, nbody, ngeom = self.place(placed), self.nbody, self.ngeom
        if not nbody:
            return d  # the object is all that moves
        # Objects are mocap bodies: the arm's joints are the whole qpos of both models.
        d.qpos[:] = live.qpos
        mujoco.mj_kinematics(self.model, d)  # places the object from its mocap pose
        # The shared bodies' poses are copied, not just recomputed: after mj_step (dynamic
        # motion) the live poses lag qpos by one integration step, and the image must show
        # what the live data shows.
        for name in ("xpos", "xquat", "xmat", "xipos", "ximat"):
            getattr(d, name)[:nbody] = getattr(live, name)[:nbody]
        d.geom_xpos[:ngeom] = live.geom_xpos[:ngeom]
        d.geom_xmat[:ngeom] = live.geom_xmat[:ngeom]
        return d


#: The stand-in models alive in this process, by (mesh, scale, with_arm): an entry goes with
#: the last env that uses it, so a process making envs for one large mesh after another does
#: not keep them all, and any number of variants is shared.
STAND_IN_MODELS: weakref.WeakValueDictionary = weakref.WeakValueDictionary()


def stand_in_model(mesh, scale: float, with_arm: bool) -> mujoco.MjModel:
    """The compiled stand-in of one variant (see :class:`VariantScenes`), shared by every env
    of a process: about 0.34 MB and 3 ms apiece, so each env after the first is about 0.3 GB
    smaller and 3 s faster to make with the 320 procedural variants. Each env's
    :class:`StandIn` leaves its one variant shown and collidable whenever it places it."""
    key = (mesh, float(scale), with_arm)
    model = STAND_IN_MODELS.get(key)
    if model is None:
        spec = load_scene_spec()
        spec.memory = VariantScenes.MEMORY
        if not with_arm:
            spec.delete(spec.body(ARM_BASE_BODY))
            for name in list(spec.keys):  # the keyframes hold the arm's joints
                spec.delete(name)
        ObjectStage([mesh], (scale,)).add_to_spec(spec)
        model = STAND_IN_MODELS[key] = spec.compile()
    return model
