"""Surgical instruments built from MuJoCo primitives, and the tray they lie on.

Instrument frame: metres; x runs along the instrument's length (tip at +x), z is up, the
instrument lies flat on z = 0 (its lowest point has z = 0) and its bounding box is centred at
x = y = 0. Every instrument is a handful of boxes, capsules, cylinders and ellipsoids (no
meshes), at most :data:`MAX_PARTS` of them, each with a colour *role*: ``"handle"`` parts are
red (the seed pipeline finds instruments by thresholding the red handle in HSV), ``"steel"``
parts are grey. Every part is at least 2 mm thick (box) or 1.5 mm in radius (capsule,
cylinder): a 2 cm drop moves an instrument 1.3 mm per 2 ms step, so no part can pass through
the 4 mm tray floor between two collision checks.

Each instrument documents its *grasp region*: a point inside its handle, the handle's axis
and the handle's width across the jaws of a top-down parallel-jaw grasp (the jaws close
horizontally, perpendicular to the axis). :func:`add_instrument` marks the region with a
site ``<prefix>grasp`` whose x axis is the handle axis, y axis the direction the jaws close
along and z axis the instrument's up.

Contact model (see :func:`add_instrument` and :func:`add_tray`): the instrument is picked by
friction alone, so its contacts carry torsional friction (``condim`` 4) and are stiffer than
MuJoCo's default, because MuJoCo's soft contacts are defined in acceleration units: the
same squeeze sinks deeper into a light body. The tray has a higher contact priority than the
instruments, so instrument-tray contacts use the tray's (steel-on-steel) friction, while
every other contact of an instrument uses the instrument's parameters, unless the other geom
(e.g. a gripper pad) has a higher priority still.

Placing: put an instrument level with its lowest point at :attr:`Tray.floor_z` (the frame's
origin, so the body's position z) or up to a few millimetres above. A level 2 cm drop sinks
0.72 mm into the tray for a few steps; landing on one end (tilted by 1-3 degrees) slaps the
other end down faster, and at the 2 ms timestep it sinks up to about 2 mm for one or two steps
(measured) before resting 2 um deep.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from liuxing_envs.sim.scene import TABLE_TOP_Z

__all__ = [
    "DEFAULT_CONDIM",
    "DEFAULT_FRICTION",
    "DEFAULT_INSTRUMENT_PRIORITY",
    "DEFAULT_SOLIMP",
    "DEFAULT_SOLREF",
    "DEFAULT_TRAY_CENTER",
    "DEFAULT_TRAY_FRICTION",
    "DEFAULT_TRAY_PRIORITY",
    "DEFAULT_TRAY_SIZE",
    "GEOM_TYPES",
    "HANDLE_RGBA",
    "INSTRUMENT_NAMES",
    "INSTRUMENT_SETS",
    "MAX_PARTS",
    "PART_ROLES",
    "STEEL_RGBA",
    "TRAY_RGBA",
    "Instrument",
    "InstrumentPart",
    "Tray",
    "add_instrument",
    "add_tray",
    "get_instrument",
    "instrument_names",
]

# --- defaults --------------------------------------------------------------------------------

#: The seed pipeline's red handle, and brushed steel; saturation 0.07 keeps steel out of any
#: HSV "red" threshold however it is lit.
HANDLE_RGBA = (0.85, 0.1, 0.1, 1.0)
STEEL_RGBA = (0.62, 0.64, 0.67, 1.0)
#: A blue instrument mat: far in hue from the red handles, darker than the steel.
TRAY_RGBA = (0.16, 0.36, 0.52, 1.0)

#: Sliding 0.8 (a rubber pad on a steel or plastic grip: 0.6-1.0), torsional 5 mm (about the
#: radius of gyration of a 2 cm x 5 mm pad-handle contact patch), rolling 1e-4 m (only used
#: with condim 6).
DEFAULT_FRICTION = (0.8, 0.005, 0.0001)
#: Sliding plus torsional friction: a two-pad grasp on a round part (capsule, cylinder) touches
#: it at two points, and only torsional friction stops the instrument swinging about the line
#: between the pads. Rolling friction (6) buys nothing for parts that lie flat.
DEFAULT_CONDIM = 4
#: Time constant 4 ms, critically damped: 2 steps of the scene's 2 ms timestep, the stiffest
#: MuJoCo deems stable (its refsafe flag clamps anything shorter to 2 steps). With MuJoCo's
#: default contact (20 ms, impedance 0.9-0.95) a 5 N squeeze sinks a pad about 3 mm into a
#: handle and a level 2 cm drop sinks 4.2 mm into the tray; with these defaults 0.13-0.16 mm
#: and 0.72 mm (measured). Impact penetration scales with speed x time constant, so a smaller
#: timestep allows a stiffer contact.
DEFAULT_SOLREF = (0.004, 1.0)
#: Impedance 0.95 at first touch rising to 0.99 at 1 mm penetration (default 0.9 -> 0.95): a
#: slightly harder contact. The time constant dominates; this halves the depth an instrument
#: rests at in the tray (measured 0.3-2.4 um instead of 0.7-5 um).
DEFAULT_SOLIMP = (0.95, 0.99, 0.001, 0.5, 2.0)
#: Contact priorities: the tray outranks the instruments, so instrument-tray contacts take the
#: tray's friction; give gripper pads a priority above DEFAULT_INSTRUMENT_PRIORITY to make
#: their own friction and condim govern the grasp.
DEFAULT_INSTRUMENT_PRIORITY = 0
DEFAULT_TRAY_PRIORITY = 1

#: Tray centre (x, y) on the table (m): in front of the arm, well inside its reach.
DEFAULT_TRAY_CENTER = (0.5, 0.0)
#: Outer size (x, y) of the tray (m): 30 cm deep, 40 cm wide.
DEFAULT_TRAY_SIZE = (0.30, 0.40)
DEFAULT_TRAY_FLOOR_THICKNESS = 0.004
#: Height of the rim's top above the table (m) and the rim's wall thickness (m).
TRAY_FLOOR_BURY = 0.02  # m
DEFAULT_TRAY_RIM_HEIGHT = 0.01
DEFAULT_TRAY_RIM_THICKNESS = 0.005
#: Stainless steel on stainless steel, dry: 0.3-0.5.
DEFAULT_TRAY_FRICTION = (0.4, 0.005, 0.0001)
#: Instruments lie flat on the tray; torsional friction there buys nothing but cost.
DEFAULT_TRAY_CONDIM = 3

#: The grasp site: an invisible marker (geom group 4 is hidden by default) 3 mm in radius.
GRASP_SITE_SIZE = 0.003
GRASP_SITE_GROUP = 4

# --- limits ----------------------------------------------------------------------------------

GEOM_TYPES = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
    "ellipsoid": mujoco.mjtGeom.mjGEOM_ELLIPSOID,
}
#: Number of MuJoCo size parameters per geom type.
_SIZE_COUNTS = {"box": 3, "capsule": 2, "cylinder": 2, "ellipsoid": 3}
PART_ROLES = ("handle", "steel")
MAX_PARTS = 12
#: Thinnest box wall and smallest round radius (m): thinner parts risk tunnelling through the
#: tray on impact and make stiff, ill-conditioned contacts.
MIN_BOX_THICKNESS = 0.002
MIN_RADIUS = 0.0015
#: Handle widths (m) the parallel-jaw gripper can hold: its pads close to 5 mm at the least
#: useful grip and open to 8 cm, but a handle wider than 25 mm leaves no margin for approach.
MIN_GRASP_WIDTH = 0.005
MAX_GRASP_WIDTH = 0.025
#: Masses (kg) the 5 N fingertip force limit can lift by friction with a wide margin.
MIN_MASS = 0.010
MAX_MASS = 0.150
#: How far (m) the lowest point of an instrument may sit from z = 0.
_ZERO_TOLERANCE = 1e-9


# --- the description -------------------------------------------------------------------------


@dataclass(frozen=True)
class InstrumentPart:
    """One primitive of an instrument, in the instrument frame.

    ``size`` holds MuJoCo's half-sizes in m: box (x, y, z), capsule and cylinder (radius,
    half-length along the part's z axis), ellipsoid (semi-axes). ``pos`` is in m, ``quat`` is
    (w, x, y, z) and is normalised on construction.
    """

    name: str
    type: str
    size: tuple[float, ...]
    pos: tuple[float, float, float]
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    role: str = "steel"

    def __post_init__(self) -> None:
        if self.type not in GEOM_TYPES:
            raise ValueError(f"part {self.name!r}: type must be one of {sorted(GEOM_TYPES)}")
        if self.role not in PART_ROLES:
            raise ValueError(f"part {self.name!r}: role must be one of {PART_ROLES}")
        size = tuple(float(s) for s in self.size)
        if len(size) != _SIZE_COUNTS[self.type]:
            raise ValueError(
                f"part {self.name!r}: a {self.type} takes {_SIZE_COUNTS[self.type]} sizes"
            )
        thinnest = {"box": MIN_BOX_THICKNESS / 2, "ellipsoid": MIN_BOX_THICKNESS / 2}
        if min(size) < thinnest.get(self.type, MIN_RADIUS) - 1e-12 or (
            self.type in ("capsule", "cylinder") and size[1] <= 0
        ):
            raise ValueError(
                f"part {self.name!r} is too thin ({size}): boxes and ellipsoids need "
                f">= {MIN_BOX_THICKNESS * 1e3:g} mm thickness, round parts >= "
                f"{MIN_RADIUS * 1e3:g} mm radius"
            )
        quat = np.asarray(self.quat, dtype=float)
        if quat.shape != (4,) or not np.linalg.norm(quat) > 0:
            raise ValueError(f"part {self.name!r}: quat must be 4 numbers, not all zero")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "pos", tuple(float(p) for p in self.pos))
        object.__setattr__(self, "quat", tuple((quat / np.linalg.norm(quat)).tolist()))

    @property
    def volume(self) -> float:
        """Volume of the primitive (m^3)."""
        return float(_volumes([self])[0])


@dataclass(frozen=True)
class Instrument:
    """A surgical instrument: its parts, mass and documented grasp region.

    Attributes
    ----------
    name:
        Library name, e.g. ``"scalpel"``.
    parts:
        The primitives, in the instrument frame (see the module docstring).
    mass:
        Total mass (kg), shared over the parts in proportion to their volumes.
    grasp_point:
        Centre of the grasp region (m, instrument frame), inside a handle part.
    grasp_axis:
        Unit direction of the handle at the grasp point (normalised on construction); the jaws
        close perpendicular to it, horizontally.
    grasp_width:
        Extent of the handle across the jaws at the grasp point (m).
    description:
        What the model stands for, with the real instrument's size and mass.
    """

    name: str
    parts: tuple[InstrumentPart, ...]
    mass: float
    grasp_point: tuple[float, float, float]
    grasp_axis: tuple[float, float, float]
    grasp_width: float
    description: str = ""

    def __post_init__(self) -> None:
        parts = tuple(self.parts)
        if not 1 <= len(parts) <= MAX_PARTS:
            raise ValueError(f"{self.name}: needs 1-{MAX_PARTS} parts, got {len(parts)}")
        names = [part.name for part in parts]
        if len(set(names)) != len(names):
            raise ValueError(f"{self.name}: part names must be unique, got {names}")
        if not any(part.role == "handle" for part in parts):
            raise ValueError(f"{self.name}: needs at least one handle part")
        if not MIN_MASS <= self.mass <= MAX_MASS:
            raise ValueError(
                f"{self.name}: mass {self.mass} kg outside [{MIN_MASS}, {MAX_MASS}] kg"
            )
        if not MIN_GRASP_WIDTH <= self.grasp_width <= MAX_GRASP_WIDTH:
            raise ValueError(
                f"{self.name}: grasp width {self.grasp_width} m outside the graspable "
                f"[{MIN_GRASP_WIDTH}, {MAX_GRASP_WIDTH}] m"
            )
        axis = np.asarray(self.grasp_axis, dtype=float)
        if axis.shape != (3,) or abs(axis[2]) > 0.5 * np.linalg.norm(axis) or not axis.any():
            raise ValueError(f"{self.name}: the grasp axis must be a mostly horizontal 3-vector")
        object.__setattr__(self, "parts", parts)
        object.__setattr__(self, "mass", float(self.mass))
        object.__setattr__(self, "grasp_width", float(self.grasp_width))
        object.__setattr__(self, "grasp_point", tuple(float(p) for p in self.grasp_point))
        object.__setattr__(self, "grasp_axis", tuple((axis / np.linalg.norm(axis)).tolist()))
        # Computed once: every reset's placement draw reads it (a frozen instance's never
        # changes), and computing it costs a few numpy calls per part.
        centres = np.array([part.pos for part in self.parts])
        half = _half_extents(self.parts)
        bounds = np.stack([(centres - half).min(axis=0), (centres + half).max(axis=0)])
        object.__setattr__(self, "_bounding_box", bounds)
        lowest = self.bounding_box[0, 2]
        if abs(lowest) > _ZERO_TOLERANCE:
            raise ValueError(f"{self.name}: the lowest point must be at z = 0, got {lowest} m")
        if not _contains(self.handle_parts, self.grasp_point).any():
            raise ValueError(f"{self.name}: the grasp point must lie inside a handle part")

    @property
    def bounding_box(self) -> np.ndarray:
        """Axis-aligned bounding box in the instrument frame, ``[[min xyz], [max xyz]]`` (m)."""
        return self._bounding_box.copy()

    @property
    def length(self) -> float:
        """Extent along the instrument's x axis (m)."""
        low, high = self.bounding_box
        return float(high[0] - low[0])

    @property
    def handle_parts(self) -> tuple[InstrumentPart, ...]:
        """The red parts a grasp should hold."""
        return tuple(part for part in self.parts if part.role == "handle")

    def geom_names(self, name_prefix: str, role: str | None = None) -> tuple[str, ...]:
        """Names :func:`add_instrument` gives the parts' geoms (only ``role``'s, if given)."""
        if role is not None and role not in PART_ROLES:
            raise ValueError(f"role must be one of {PART_ROLES} or None, got {role!r}")
        return tuple(
            f"{name_prefix}{part.name}" for part in self.parts if role in (None, part.role)
        )

    def part_masses(self, mass_scale: float = 1.0) -> np.ndarray:
        """Mass of each part (kg): ``mass * mass_scale`` shared in proportion to volume."""
        volumes = _volumes(self.parts)
        return self.mass * float(mass_scale) * volumes / volumes.sum()

    def grasp_frame(self) -> np.ndarray:
        """Rotation (3, 3) whose columns are the handle axis, the jaw-closing direction and up,
        in the instrument frame; the grasp site's orientation."""
        x = np.asarray(self.grasp_axis)
        x = x - x[2] * np.array([0.0, 0.0, 1.0])  # keep the jaws' closing direction horizontal
        x /= np.linalg.norm(x)
        z = np.array([0.0, 0.0, 1.0])
        return np.column_stack([x, np.cross(z, x), z])


# --- geometry of primitives (vectorised over parts) ------------------------------------------


def _quat_to_mat(quats: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions (w, x, y, z) to (N, 3, 3) rotation matrices."""
    w, x, y, z = np.moveaxis(np.asarray(quats, dtype=float), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def _padded_sizes(parts: Sequence[InstrumentPart]) -> np.ndarray:
    return np.array([list(part.size) + [0.0] * (3 - len(part.size)) for part in parts])


def _half_extents(parts: Sequence[InstrumentPart]) -> np.ndarray:
    """Exact axis-aligned half-extents (N, 3) of each rotated primitive (m)."""
    rot = _quat_to_mat(np.array([part.quat for part in parts]))
    size = _padded_sizes(parts)
    kinds = np.array([part.type for part in parts])
    radius, half_length = size[:, 0, None], size[:, 1, None]
    axis = np.abs(rot[:, :, 2])  # each part's local z axis in the instrument frame
    box = np.einsum("nij,nj->ni", np.abs(rot), size)
    ellipsoid = np.sqrt(np.einsum("nij,nj->ni", rot**2, size**2))
    capsule = axis * half_length + radius
    cylinder = axis * half_length + radius * np.sqrt(np.clip(1.0 - axis**2, 0.0, 1.0))
    return np.select(
        [kinds[:, None] == "box", kinds[:, None] == "ellipsoid", kinds[:, None] == "capsule"],
        [box, ellipsoid, capsule],
        cylinder,
    )


def _contains(parts: Sequence[InstrumentPart], point, tol: float = 1e-9) -> np.ndarray:
    """Whether ``point`` (m, instrument frame) lies on or inside each primitive."""
    rot = _quat_to_mat(np.array([part.quat for part in parts]))
    offset = np.asarray(point, float) - np.array([part.pos for part in parts])
    local = np.einsum("nji,nj->ni", rot, offset)  # rotate into each part's frame
    size = _padded_sizes(parts)
    kinds = np.array([part.type for part in parts])
    radius, half_length = size[:, 0], size[:, 1]
    along = np.clip(local[:, 2], -half_length, half_length)
    with np.errstate(divide="ignore", invalid="ignore"):
        ellipsoid = np.sum((local / size) ** 2, axis=1) <= 1.0 + tol
    return np.select(
        [kinds == "box", kinds == "ellipsoid", kinds == "capsule"],
        [
            np.all(np.abs(local) <= size + tol, axis=1),
            ellipsoid,
            np.hypot(np.hypot(local[:, 0], local[:, 1]), local[:, 2] - along) <= radius + tol,
        ],
        (np.abs(local[:, 2]) <= half_length + tol)
        & (np.hypot(local[:, 0], local[:, 1]) <= radius + tol),
    )


def _volumes(parts: Sequence[InstrumentPart]) -> np.ndarray:
    """Volume of each primitive (m^3)."""
    size = _padded_sizes(parts)
    kinds = np.array([part.type for part in parts])
    r, h = size[:, 0], size[:, 1]
    return np.select(
        [kinds == "box", kinds == "ellipsoid", kinds == "capsule"],
        [
            8.0 * size.prod(axis=1),
            4.0 / 3.0 * np.pi * size.prod(axis=1),
            np.pi * r**2 * 2.0 * h + 4.0 / 3.0 * np.pi * r**3,
        ],
        np.pi * r**2 * 2.0 * h,
    )


# --- building parts --------------------------------------------------------------------------


def _axis_quat(axis: Sequence[float], angle: float) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation by ``angle`` (rad) about the unit ``axis``."""
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * np.asarray(axis, float)])


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), np.asarray(b, float))
    return out


_X, _Y, _Z = np.eye(3)


def _box(name: str, center, half, role: str = "steel", yaw: float = 0.0) -> InstrumentPart:
    """A box with half-sizes ``half`` (m), turned by ``yaw`` (rad) about z."""
    return InstrumentPart(name, "box", tuple(half), tuple(center), tuple(_axis_quat(_Z, yaw)), role)


def _box_along(name: str, start, end, half_width: float, half_thickness: float, role: str):
    """A box whose x axis runs from ``start`` to ``end`` (m) and whose y axis stays horizontal."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    d = end - start
    yaw, pitch = np.arctan2(d[1], d[0]), np.arctan2(d[2], np.hypot(d[0], d[1]))
    quat = _quat_mul(_axis_quat(_Z, yaw), _axis_quat(_Y, -pitch))
    half = (0.5 * np.linalg.norm(d), half_width, half_thickness)
    return InstrumentPart(name, "box", half, tuple((start + end) / 2), tuple(quat), role)


def _rod(name: str, start, end, radius: float, role: str, kind: str = "capsule"):
    """A capsule (or cylinder) whose axis runs from ``start`` to ``end`` (m)."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    quat = np.empty(4)
    mujoco.mju_quatZ2Vec(quat, end - start)
    half = (radius, 0.5 * np.linalg.norm(end - start))
    return InstrumentPart(name, kind, half, tuple((start + end) / 2), tuple(quat), role)


def _disc(name: str, center, radius: float, half_height: float, role: str = "steel"):
    """An upright cylinder (axis z)."""
    return InstrumentPart(name, "cylinder", (radius, half_height), tuple(center), role=role)


def _ellipsoid(name: str, center, semi_axes, role: str = "steel") -> InstrumentPart:
    return InstrumentPart(name, "ellipsoid", tuple(semi_axes), tuple(center), role=role)


def _finger_ring(name: str, center_xy, half_side: float, radius: float) -> list[InstrumentPart]:
    """A finger ring lying flat: a square loop of four capsules (side ``2 half_side`` between
    centre lines, m) whose bottom touches z = 0; red, as colour-coded ring handles are."""
    cx, cy = center_xy
    z = radius
    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * half_side + (cx, cy)
    sides = zip(corners, np.roll(corners, -1, axis=0), strict=True)
    return [
        _rod(f"{name}_{i}", (*a, z), (*b, z), radius, "handle") for i, (a, b) in enumerate(sides)
    ]


def _make(
    name: str,
    parts: Sequence[InstrumentPart],
    mass: float,
    grasp_point,
    grasp_width: float,
    description: str,
    grasp_axis=(1.0, 0.0, 0.0),
) -> Instrument:
    """An instrument from parts laid out anywhere, moved so its bounding box is centred in x and
    y and its lowest point is at z = 0 (the grasp point moves with it)."""
    centres = np.array([part.pos for part in parts])
    half = _half_extents(parts)
    low, high = (centres - half).min(axis=0), (centres + half).max(axis=0)
    shift = np.array([-(low[0] + high[0]) / 2, -(low[1] + high[1]) / 2, -low[2]])
    moved = tuple(
        InstrumentPart(p.name, p.type, p.size, tuple(np.asarray(p.pos) + shift), p.quat, p.role)
        for p in parts
    )
    point = tuple(np.asarray(grasp_point, float) + shift)
    return Instrument(name, moved, mass, point, tuple(grasp_axis), grasp_width, description)


# --- the library -----------------------------------------------------------------------------
# Layouts are written tip towards +x, resting on z = 0; _make re-centres them. The ring-handled
# instruments are modelled closed (jaws shut, shanks side by side), as they lie on a tray.


def _scalpel() -> Instrument:
    t = 0.006  # handle thickness
    parts = [
        _box("handle", (-0.018, 0.0, t / 2), (0.048, 0.006, t / 2), "handle"),
        _disc("handle_end", (-0.066, 0.0, t / 2), 0.006, t / 2, "handle"),
        _box("neck", (0.03725, 0.0, t / 2), (0.00775, 0.0035, 0.0015)),
        _box("blade", (0.055, -0.0005, t / 2), (0.010, 0.005, 0.001)),
        _box("blade_tip", (0.0695, 0.0015, t / 2), (0.006, 0.0025, 0.001), yaw=np.radians(-25)),
    ]
    return _make(
        "scalpel",
        parts,
        0.020,
        (-0.02, 0.0, t / 2),
        0.012,
        "No. 3 handle with a red grip sleeve and a No. 10 blade: 15 cm, 20 g",
    )


def _tissue_forceps() -> Instrument:
    # Lies on one tine; the other rises from the rear joint to an open tip 1 cm above it.
    upper_start, upper_end = np.array([-0.058, 0.0, 0.004]), np.array([0.068, 0.0, 0.011])
    grip_x = (-0.04, 0.01)
    along = (np.array(grip_x) - upper_start[0]) / (upper_end[0] - upper_start[0])
    grip_ends = upper_start + along[:, None] * (upper_end - upper_start)
    parts = [
        _box("rear_joint", (-0.064, 0.0, 0.0025), (0.006, 0.0045, 0.0025)),
        _box("lower_tine", (0.005, 0.0, 0.001), (0.065, 0.0045, 0.001)),
        _box_along("upper_tine", upper_start, upper_end, 0.0045, 0.001, "steel"),
        _box("lower_grip", (np.mean(grip_x), 0.0, 0.0015), (0.025, 0.005, 0.0015), "handle"),
        _box_along("upper_grip", grip_ends[0], grip_ends[1], 0.005, 0.0015, "handle"),
    ]
    return _make(
        "tissue_forceps",
        parts,
        0.022,
        (np.mean(grip_x), 0.0, 0.0015),
        0.010,
        "Thumb (dressing) forceps with red grip pads, lying on one tine: 14 cm, 22 g",
    )


def _scissors() -> Instrument:
    t = 0.004  # slab thickness of blades, shanks and rings
    parts = [
        _box("blade", (0.044, 0.0, t / 2), (0.034, 0.005, t / 2)),
        _disc("blade_tip", (0.078, 0.0, t / 2), 0.005, t / 2),
        _disc("pivot", (0.008, 0.0, 0.0025), 0.0045, 0.0025),
        _box("shank", (-0.0225, 0.0, t / 2), (0.0275, 0.007, t / 2), "handle"),
        *_finger_ring("ring_a", (-0.058, 0.014), 0.008, t / 2),
        *_finger_ring("ring_b", (-0.058, -0.014), 0.008, t / 2),
    ]
    return _make(
        "scissors",
        parts,
        0.055,
        (-0.0225, 0.0, t / 2),
        0.014,
        "Mayo scissors, straight, blunt tips, red ring handles: 15 cm, 55 g",
    )


def _hemostat() -> Instrument:
    t = 0.004
    parts = [
        _box("jaw", (0.0255, 0.0, t / 2), (0.0195, 0.003, t / 2)),
        _box_along("jaw_tip", (0.044, 0.0, t / 2), (0.072, 0.008, t / 2), 0.0025, t / 2, "steel"),
        _box("box_lock", (0.0, 0.0, 0.0025), (0.006, 0.0045, 0.0025)),
        _box("shank", (-0.028, 0.0, t / 2), (0.022, 0.005, t / 2), "handle"),
        *_finger_ring("ring_a", (-0.058, 0.012), 0.007, t / 2),
        *_finger_ring("ring_b", (-0.058, -0.012), 0.007, t / 2),
    ]
    return _make(
        "hemostat",
        parts,
        0.045,
        (-0.028, 0.0, t / 2),
        0.010,
        "Kelly hemostat, curved jaws, red ring handles: 14 cm, 45 g",
    )


def _needle_holder() -> Instrument:
    t = 0.005  # shanks; the jaws and box lock are thicker
    r = 0.0022
    parts = [
        _box("jaw", (0.0265, 0.0, 0.003), (0.0185, 0.0045, 0.003)),
        _box("jaw_tip", (0.0515, 0.0, 0.0025), (0.0065, 0.0035, 0.0025)),
        _box("box_lock", (0.0, 0.0, 0.003), (0.008, 0.0055, 0.003)),
        _box("shank", (-0.043, 0.0, t / 2), (0.035, 0.006, t / 2), "handle"),
        *_finger_ring("ring_a", (-0.086, 0.014), 0.008, r),
        *_finger_ring("ring_b", (-0.086, -0.014), 0.008, r),
    ]
    return _make(
        "needle_holder",
        parts,
        0.065,
        (-0.043, 0.0, t / 2),
        0.012,
        "Mayo-Hegar needle holder, short broad jaws, red ring handles: 15 cm, 65 g",
    )


def _probe() -> Instrument:
    t = 0.007  # a flat handle, so the probe cannot roll
    z = t / 2
    parts = [
        _box("handle", (-0.0325, 0.0, z), (0.0375, 0.005, z), "handle"),
        _ellipsoid("handle_end", (-0.07, 0.0, z), (0.006, 0.005, z), "handle"),
        _rod("ferrule", (0.005, 0.0, z), (0.013, 0.0, z), 0.003, "steel", "cylinder"),
        _rod("shaft", (0.013, 0.0, z), (0.072, 0.0, z), 0.0015, "steel"),
        _ellipsoid("bulb", (0.074, 0.0, z), (0.0025, 0.0025, 0.0025)),
    ]
    return _make(
        "probe",
        parts,
        0.015,
        (-0.035, 0.0, z),
        0.010,
        "Malleable probe with a bulb tip and a flat red handle: 15 cm, 15 g",
    )


def _retractor() -> Instrument:
    t = 0.004
    prong_x = -0.0755
    parts = [
        _box("handle", (0.0, 0.0, t / 2), (0.05, 0.0075, t / 2), "handle"),
        _box("front_shaft", (0.062, 0.0, t / 2), (0.012, 0.004, 0.0015)),
        _box("front_blade", (0.0755, 0.0, 0.0075), (0.0015, 0.008, 0.007)),
        _box("rear_shaft", (-0.062, 0.0, t / 2), (0.012, 0.004, 0.0015)),
        *(
            _rod(f"prong_{i}", (prong_x, y, 0.002), (prong_x, y, 0.013), 0.0015, "steel")
            for i, y in enumerate((-0.006, 0.0, 0.006))
        ),
    ]
    return _make(
        "retractor",
        parts,
        0.035,
        (0.0, 0.0, t / 2),
        0.015,
        "Double-ended Senn retractor, blade and three-prong rake turned up: 15 cm, 35 g",
    )


_BUILDERS = {
    "scalpel": _scalpel,
    "tissue_forceps": _tissue_forceps,
    "scissors": _scissors,
    "hemostat": _hemostat,
    "needle_holder": _needle_holder,
    "probe": _probe,
    "retractor": _retractor,
}
INSTRUMENT_NAMES: tuple[str, ...] = tuple(_BUILDERS)

# Held out: the heaviest (needle holder, 65 g) and the lightest (probe, 15 g) instrument, so
# evaluation asks a policy to extrapolate grip force and slip beyond the 20-55 g it trained on,
# while each shape family stays familiar (ring handles: scissors and hemostat; a straight flat
# handle: scalpel) and no grasp mechanics are new. Five train types keep every family and the
# full range of grasp widths (10-15 mm) in training.
_HELD_OUT = ("needle_holder", "probe")
INSTRUMENT_SETS: dict[str, tuple[str, ...]] = {
    "train": tuple(name for name in INSTRUMENT_NAMES if name not in _HELD_OUT),
    "held_out": _HELD_OUT,
    "all": INSTRUMENT_NAMES,
}

_LIBRARY: dict[str, Instrument] = {}


def get_instrument(name: str) -> Instrument:
    """The library instrument ``name`` (built once, then shared: it is immutable)."""
    if name not in _BUILDERS:
        raise ValueError(
            f"unknown instrument {name!r}; valid instruments: {', '.join(INSTRUMENT_NAMES)}"
        )
    if name not in _LIBRARY:
        _LIBRARY[name] = _BUILDERS[name]()
    return _LIBRARY[name]


def instrument_names(set_name: str = "all") -> tuple[str, ...]:
    """Names of the instruments in ``set_name``: ``"train"``, ``"held_out"`` or ``"all"``."""
    if set_name not in INSTRUMENT_SETS:
        raise ValueError(
            f"unknown instrument set {set_name!r}; valid sets: {', '.join(INSTRUMENT_SETS)}"
        )
    return INSTRUMENT_SETS[set_name]


# --- adding to a scene -----------------------------------------------------------------------


def add_instrument(
    spec: mujoco.MjSpec,
    instrument: Instrument | str,
    name_prefix: str,
    *,
    pos: Sequence[float] = (0.0, 0.0, 0.0),
    quat: Sequence[float] = (1.0, 0.0, 0.0, 0.0),
    mass_scale: float = 1.0,
    friction: Sequence[float] = DEFAULT_FRICTION,
    condim: int = DEFAULT_CONDIM,
    solref: Sequence[float] = DEFAULT_SOLREF,
    solimp: Sequence[float] = DEFAULT_SOLIMP,
    priority: int = DEFAULT_INSTRUMENT_PRIORITY,
    handle_rgba: Sequence[float] = HANDLE_RGBA,
    steel_rgba: Sequence[float] = STEEL_RGBA,
    group: int = 0,
) -> mujoco.MjsBody:
    """Add ``instrument`` (or a library name) to ``spec``'s worldbody as a free body.

    Names: body ``<prefix>body``, free joint ``<prefix>joint``, one geom ``<prefix><part>`` per
    part and the grasp site ``<prefix>grasp`` (x: handle axis, y: jaw-closing direction,
    z: up). ``pos`` (m) and ``quat`` place the instrument frame in the world at qpos0; set the
    free joint's qpos to move it after compiling. Each part gets an explicit mass, its share
    by volume of ``instrument.mass * mass_scale`` (kg), so the body's total is exact; MuJoCo
    derives the inertia from the shapes. ``group`` is the geoms' visual group (0-2 are seen by
    the depth cameras).
    """
    if isinstance(instrument, str):
        instrument = get_instrument(instrument)
    if not (np.isfinite(mass_scale) and mass_scale > 0):
        raise ValueError(f"mass_scale must be a positive number, got {mass_scale}")
    if condim not in (1, 3, 4, 6):
        raise ValueError(f"condim must be 1, 3, 4 or 6, got {condim}")
    body = spec.worldbody.add_body(
        name=f"{name_prefix}body", pos=list(map(float, pos)), quat=list(map(float, quat))
    )
    body.add_freejoint(name=f"{name_prefix}joint")
    colours = {"handle": list(handle_rgba), "steel": list(steel_rgba)}
    for part, mass in zip(instrument.parts, instrument.part_masses(mass_scale), strict=True):
        body.add_geom(
            name=f"{name_prefix}{part.name}",
            type=GEOM_TYPES[part.type],
            size=list(part.size) + [0.0] * (3 - len(part.size)),
            pos=list(part.pos),
            quat=list(part.quat),
            mass=float(mass),
            rgba=colours[part.role],
            friction=list(friction),
            condim=int(condim),
            solref=list(solref),
            solimp=list(solimp),
            priority=int(priority),
            group=int(group),
        )
    frame = instrument.grasp_frame()
    site_quat = np.empty(4)
    mujoco.mju_mat2Quat(site_quat, frame.ravel())
    body.add_site(
        name=f"{name_prefix}grasp",
        pos=list(instrument.grasp_point),
        quat=site_quat.tolist(),
        size=[GRASP_SITE_SIZE] * 3,
        rgba=[0.1, 0.9, 0.1, 0.5],
        group=GRASP_SITE_GROUP,
    )
    return body


@dataclass(frozen=True)
class Tray:
    """Where :func:`add_tray` put the tray: names, its centre (x, y) on the table (m), the
    height of its floor's top (m) and the half-size (x, y) of the floor inside the rim (m)."""

    body_name: str
    geom_names: tuple[str, ...]
    center: tuple[float, float]
    floor_z: float
    inner_half_size: tuple[float, float]


def add_tray(
    spec: mujoco.MjSpec,
    center: Sequence[float] = DEFAULT_TRAY_CENTER,
    *,
    size: Sequence[float] = DEFAULT_TRAY_SIZE,
    floor_thickness: float = DEFAULT_TRAY_FLOOR_THICKNESS,
    rim_height: float = DEFAULT_TRAY_RIM_HEIGHT,
    rim_thickness: float = DEFAULT_TRAY_RIM_THICKNESS,
    rgba: Sequence[float] = TRAY_RGBA,
    friction: Sequence[float] = DEFAULT_TRAY_FRICTION,
    condim: int = DEFAULT_TRAY_CONDIM,
    solref: Sequence[float] = DEFAULT_SOLREF,
    solimp: Sequence[float] = DEFAULT_SOLIMP,
    priority: int = DEFAULT_TRAY_PRIORITY,
    name_prefix: str = "tray_",
) -> Tray:
    """Add a shallow instrument tray standing on the table (static geoms, no joint).

    ``center`` is (x, y) on the table (m); ``size`` the outer (x, y) size (m). The floor is a
    plate ``floor_thickness`` thick; the rim's top is ``rim_height`` above the table
    (``rim_height <= floor_thickness`` makes a flat plate without a rim). The tray's contact
    ``priority`` (above the instruments') makes its friction apply to instruments on it.
    """
    half_x, half_y = 0.5 * float(size[0]), 0.5 * float(size[1])
    if min(half_x, half_y) <= rim_thickness or floor_thickness < MIN_BOX_THICKNESS:
        raise ValueError(
            f"tray size {tuple(size)} m must exceed twice the rim ({rim_thickness} m) and the "
            f"floor must be at least {MIN_BOX_THICKNESS} m thick"
        )
    cx, cy = float(center[0]), float(center[1])
    body = spec.worldbody.add_body(name=f"{name_prefix}body", pos=[cx, cy, TABLE_TOP_Z])
    contact = dict(
        rgba=list(rgba),
        friction=list(friction),
        condim=int(condim),
        solref=list(solref),
        solimp=list(solimp),
        priority=int(priority),
    )
    box = mujoco.mjtGeom.mjGEOM_BOX
    floor_name = f"{name_prefix}floor"
    # The floor's collision box reaches TRAY_FLOOR_BURY down into the table (static geoms do
    # not collide with each other), so nothing pressed hard onto a thin tray pops through it.
    half_t = 0.5 * (floor_thickness + TRAY_FLOOR_BURY)
    body.add_geom(
        name=floor_name,
        type=box,
        size=[half_x, half_y, half_t],
        pos=[0, 0, floor_thickness - half_t],
    )
    names = [floor_name]
    has_rim = rim_height > floor_thickness
    if has_rim:
        half_h, half_w = 0.5 * rim_height, 0.5 * rim_thickness
        walls = {
            "rim_front": ((half_x - half_w, 0.0), (half_w, half_y)),
            "rim_back": ((-half_x + half_w, 0.0), (half_w, half_y)),
            "rim_left": ((0.0, half_y - half_w), (half_x - rim_thickness, half_w)),
            "rim_right": ((0.0, -half_y + half_w), (half_x - rim_thickness, half_w)),
        }
        for wall, ((x, y), (hx, hy)) in walls.items():
            name = f"{name_prefix}{wall}"
            body.add_geom(name=name, type=box, size=[hx, hy, half_h], pos=[x, y, half_h])
            names.append(name)
    for geom in body.geoms:
        for key, value in contact.items():
            setattr(geom, key, value)
    inset = rim_thickness if has_rim else 0.0
    return Tray(
        body_name=f"{name_prefix}body",
        geom_names=tuple(names),
        center=(cx, cy),
        floor_z=TABLE_TOP_Z + float(floor_thickness),
        inner_half_size=(half_x - inset, half_y - inset),
    )
