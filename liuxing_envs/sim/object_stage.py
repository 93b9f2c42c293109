"""Put one object at a time on the table without recompiling the model.

Recompiling a model (and rebuilding its OpenGL context) for every episode would cost tens of
milliseconds per reset, so every object the environment may show is compiled into the scene
once, at each of a few discrete scales, as a mocap body. :meth:`ObjectStage.place` shows one
variant at a pose on the table and parks all others: they are moved far below the floor,
their geoms are moved to a geom group no camera renders, and their collisions are switched
off, so they cost neither rendering, ray casting nor collision checks. Collisions are switched
per geom and per body: MuJoCo's broad phase skips a body whose compiled ``body_contype`` and
``body_conaffinity`` are both 0 before it looks at any of its geoms.

MuJoCo collides mesh geoms through their convex hulls; the rendered and ray-cast surface is
the true (possibly concave) mesh. Arm-object collision checks are therefore conservative.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

#: Geom group the parked variants are moved to: outside the depth cameras' groups (0-2).
PARKED_GEOM_GROUP = 5
PARKING_POSITION = (0.0, 0.0, -10.0)
OBJECT_RGBA = (0.78, 0.62, 0.42, 1.0)


@dataclass(frozen=True)
class PlacedObject:
    """The variant on the table: its name, scale, pose (position of the base centre on the
    table, yaw about z) and the world-from-object transform."""

    name: str
    scale: float
    position: np.ndarray
    yaw: float
    rotation: np.ndarray

    def to_world(self, points_object: np.ndarray) -> np.ndarray:
        """Points in the placed variant's own frame (already at its scale) to the world."""
        return np.asarray(points_object) @ self.rotation.T + self.position

    def to_object(self, points_world: np.ndarray) -> np.ndarray:
        """World-frame points to the placed variant's own frame (inverse of :meth:`to_world`)."""
        return (np.asarray(points_world) - self.position) @ self.rotation


class ObjectStage:
    """Every (object, scale) variant as a hidden mocap body; one of them shown at a time.

    Use in two phases: construct with the meshes and add them to a spec with
    :meth:`add_to_spec`, compile, then :meth:`bind` the compiled model before :meth:`place`.

    Parameters
    ----------
    meshes:
        Objects with ``name``, ``vertices`` (V, 3) and ``faces`` (F, 3) in the object frame
        (resting on z = 0, centred in x and y).
    scales:
        The discrete uniform scales each object is compiled at.
    """

    def __init__(self, meshes: Sequence, scales: Sequence[float]) -> None:
        if not meshes:
            raise ValueError("an ObjectStage needs at least one object")
        names = [mesh.name for mesh in meshes]
        if len(set(names)) != len(names):
            raise ValueError(f"object names must be unique, got {names}")
        if not scales or any(not (np.isfinite(s) and s > 0) for s in scales):
            raise ValueError(f"scales must be positive numbers, got {list(scales)}")
        if len({float(s) for s in scales}) != len(scales):
            raise ValueError(f"scales must be distinct, got {list(scales)}")
        self.meshes = {mesh.name: mesh for mesh in meshes}
        self.scales = tuple(float(s) for s in scales)
        self._model: mujoco.MjModel | None = None
        self._data: mujoco.MjData | None = None
        self._variants: dict[tuple[str, float], tuple[int, int, np.ndarray]] = {}
        self._geom_groups: dict[tuple[str, float], np.ndarray] = {}
        self.placed: PlacedObject | None = None

    @staticmethod
    def _body_name(name: str, scale: float) -> str:
        # Named by the scale itself, not its index, so a stage holding only some of the
        # scales (a stand-in scene) names the same variant the same way.
        return f"object_{name}_x{scale!r}"

    def add_to_spec(self, spec: mujoco.MjSpec) -> None:
        for name, mesh in self.meshes.items():
            for scale in self.scales:
                body_name = self._body_name(name, scale)
                mesh_name = f"{body_name}_mesh"
                spec.add_mesh(
                    name=mesh_name,
                    uservert=np.asarray(mesh.vertices, dtype=np.float64).ravel().tolist(),
                    userface=np.asarray(mesh.faces, dtype=np.int32).ravel().tolist(),
                    scale=[scale] * 3,
                )
                body = spec.worldbody.add_body(
                    name=body_name, mocap=True, pos=list(PARKING_POSITION)
                )
                body.add_geom(
                    name=f"{body_name}_geom",
                    type=mujoco.mjtGeom.mjGEOM_MESH,
                    meshname=mesh_name,
                    rgba=list(OBJECT_RGBA),
                    group=PARKED_GEOM_GROUP,
                    # Compiled colliding, so MuJoCo builds the convex hull that makes
                    # collision queries fast; bind() switches collisions off until place().
                    contype=1,
                    conaffinity=1,
                )

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Resolve the compiled variants' ids once."""
        self._model, self._data = model, data
        for name in self.meshes:
            for scale in self.scales:
                body_id = model.body(self._body_name(name, scale)).id
                geoms = np.flatnonzero(model.geom_bodyid == body_id)
                self._variants[(name, scale)] = (body_id, int(model.body_mocapid[body_id]), geoms)
                _set_collisions(model, body_id, geoms, 0)
        self.placed = None

    @property
    def active_geom_ids(self) -> np.ndarray:
        if self.placed is None:
            return np.zeros(0, dtype=int)
        return self._variants[(self.placed.name, self.placed.scale)][2]

    def place(self, name: str, scale: float, position, yaw: float) -> PlacedObject:
        """Show variant (name, scale) with its base centre at ``position`` (on the table),
        turned by ``yaw`` about z; park whatever was shown before. Kinematics are not run."""
        if self._model is None:
            raise RuntimeError("ObjectStage.bind(model, data) must be called before place()")
        key = (name, float(scale))
        if key not in self._variants:
            raise ValueError(
                f"no object variant {key}; objects: {sorted(self.meshes)}, scales: {self.scales}"
            )
        model, data = self._model, self._data
        if self.placed is not None:
            old_body, old_mocap, old_geoms = self._variants[(self.placed.name, self.placed.scale)]
            data.mocap_pos[old_mocap] = PARKING_POSITION
            model.geom_group[old_geoms] = PARKED_GEOM_GROUP
            _set_collisions(model, old_body, old_geoms, 0)
        body, mocap, geoms = self._variants[key]
        position = np.asarray(position, dtype=float)
        data.mocap_pos[mocap] = position
        half = 0.5 * float(yaw)
        data.mocap_quat[mocap] = [np.cos(half), 0.0, 0.0, np.sin(half)]
        model.geom_group[geoms] = 0
        _set_collisions(model, body, geoms, 1)
        c, s = np.cos(yaw), np.sin(yaw)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self.placed = PlacedObject(name, float(scale), position.copy(), float(yaw), rotation)
        return self.placed


def _set_collisions(model: mujoco.MjModel, body: int, geoms: np.ndarray, bits: int) -> None:
    model.geom_contype[geoms] = bits
    model.geom_conaffinity[geoms] = bits
    model.body_contype[body] = bits
    model.body_conaffinity[body] = bits
