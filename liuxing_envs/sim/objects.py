"""Objects to scan: a procedural library, users' mesh files, and surface ground truth.

Object frame: metres; the object rests on the table plane z = 0 (its lowest point has z = 0)
and its bounding box is centred at x = y = 0. Every library object is generated in code (no
files, no downloads) as a triangle mesh made of one or more *parts*: each part is a closed,
consistently outward-oriented surface without degenerate triangles, and parts may overlap
(a chair's legs run into its seat). A union of closed parts is what MuJoCo renders and ray
casts correctly; for ground-truth surface samples, samples that lie strictly inside another
part are rejected (see :func:`surface_samples`).

The coverage metric of ``ViewPlanning-v0`` counts the share of ground-truth samples with an
observed point nearby, restricted to the samples some camera of the env's view space could
see: :func:`observable_mask` ray-casts from a dense set of viewpoints on that space (rings
around the object's middle at the env's elevations and radii; the table occludes), and
:func:`observable_samples` caches samples, normals and that mask per (object, scale, views),
because the environment asks for them at every reset.
"""

from __future__ import annotations

import hashlib
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache, cached_property, lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull

from liuxing_envs.disk_cache import cache_key, load_array, store_array
from liuxing_envs.forking import check_open3d_not_forked
from liuxing_envs.open3d_import import o3d, open3d_version

__all__ = [
    "DEFAULT_OBSERVATION_AZIMUTH_COUNT",
    "DEFAULT_OBSERVATION_ELEVATIONS_DEG",
    "DEFAULT_OBSERVATION_RADII",
    "DEFAULT_OBSERVATION_RADIUS",
    "DEFAULT_SAMPLE_COUNT",
    "DEFAULT_SAMPLE_SEED",
    "DEFAULT_USER_MESH_SIZE",
    "MESH_FILE_EXTENSIONS",
    "OBJECT_NAMES",
    "OBJECT_SETS",
    "ObjectMesh",
    "ObservableSamples",
    "PROCEDURAL_PREFIX",
    "PROCEDURAL_SET_SIZE",
    "PROCEDURAL_SIZE_RANGE",
    "clear_memory_caches",
    "default_observation_viewpoints",
    "get_object",
    "is_object_name",
    "load_mesh_file",
    "observable_mask",
    "observable_samples",
    "observation_viewpoints",
    "surface_samples",
]

# --- defaults --------------------------------------------------------------------------------

#: Largest bounding-box side (m) a user's mesh is scaled to: a typical tabletop object.
DEFAULT_USER_MESH_SIZE = 0.15
MESH_FILE_EXTENSIONS = (".obj", ".ply", ".stl")
#: Ground-truth samples per object and the seed that makes them the same every run.
DEFAULT_SAMPLE_COUNT = 8192
DEFAULT_SAMPLE_SEED = 0
#: A sample on one part lying deeper than this (m) inside another part is hidden by the union.
#: Small but well above float32 noise, so parts that merely touch keep their samples.
DEFAULT_INTERIOR_TOLERANCE = 1e-6
#: Rays used to vote on inside/outside (odd); 3 survives a ray that slips along an edge.
DEFAULT_INSIDE_VOTES = 3
#: Rejection sampling gives up when less than this share of the surface is exposed.
MIN_EXPOSED_FRACTION = 1e-3
#: Interior rejection builds one query scene per part; a mesh in more pieces than this (a
#: fragmented scan, not an assembly of parts) is sampled without it, with a warning.
MAX_HIDING_PARTS = 64

#: Viewpoints that decide observability: spheres of these radii (m) around the object's
#: middle (its bounding box's centre), at these elevations (deg; 90 = straight down, listed
#: once) and azimuths: ViewPlanning-v0's view space by default (elevations 20-90 deg, radii
#: 0.30-0.45 m; the env passes its own), 2 x (4 rings x 24 azimuths + the top) = 194 views,
#: denser than the views an episode takes. A sample only a view outside that space could see
#: (under a chair's seat, from near the table) would cap coverage below 1 for every agent.
DEFAULT_OBSERVATION_RADII = (0.30, 0.45)
DEFAULT_OBSERVATION_ELEVATIONS_DEG = (20.0, 37.5, 55.0, 72.5, 90.0)
DEFAULT_OBSERVATION_AZIMUTH_COUNT = 24
#: Radius (m) of :func:`default_observation_viewpoints` when none is given.
DEFAULT_OBSERVATION_RADIUS = 0.4
#: A ray's first hit may fall this much (m) short of its sample and still count as reaching
#: it; far below the thinnest wall in the library (3 mm).
DEFAULT_HIT_TOLERANCE = 1e-4
#: A sample faces a viewpoint when normal . (eye - p) / |eye - p| exceeds this cosine.
DEFAULT_MIN_COSINE = 0.0
#: Views per ray cast of :func:`observable_mask`: few enough that the later groups only
#: cast towards the samples the earlier ones left unseen.
DEFAULT_VIEWS_PER_CAST = 8
#: The table as a box: top face at z = 0, this half-size in x and y and this thickness (m).
#: Thick enough that a ray from below hits its underside well before a sample at z = 0.
DEFAULT_TABLE_HALF_SIZE = 10.0
DEFAULT_TABLE_THICKNESS = 0.02

#: Cached (object, scale, ...) ground truths; the environment uses a handful of scales for
#: each of its objects (22 in the library, 64 in the procedural set), each entry ~0.2 MB at
#: 8192 samples (the scale-free samples another ~0.4 MB per object).
OBSERVABLE_CACHE_SIZE = 512


def _source_digest() -> str | None:
    """This module's source as imported, in every disk-cache key of what it computes:
    editing the code (or a default it uses) misses the results stored before. None (no disk
    cache) where the source cannot be read."""
    try:
        return hashlib.sha256(Path(__file__).read_bytes()).hexdigest()
    except OSError:
        return None


_SOURCE_DIGEST = _source_digest()

# Library tessellation.
_SEGMENTS = 48  # around a surface of revolution
_TUBE_SEGMENTS = 16  # around a swept tube (mug handle)
#: Seed of the bunny-like blob's noise: fixed, so the object is the same in every run.
BLOB_SEED = 7

#: ``procedural_<n>`` (n = 0 to 999,999) names shape n of a seeded sequence of random
#: composites, the same shape on every machine (to floating-point rounding);
#: ``OBJECT_SETS["procedural"]`` holds the first PROCEDURAL_SET_SIZE. They are a training set:
#: many shapes from the train families' parts.
PROCEDURAL_PREFIX = "procedural_"
PROCEDURAL_SET_SIZE = 64
PROCEDURAL_SEED = 1125
#: Largest bounding-box side of a procedural shape (m), drawn uniformly: the library's span.
PROCEDURAL_SIZE_RANGE = (0.10, 0.18)


# --- the mesh type ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False, repr=False)
class ObjectMesh:
    """A named triangle mesh in the object frame (metres).

    The arrays are read-only copies, so a mesh can be hashed by content: two meshes with the
    same name, vertices and faces are equal, which is what the sample caches key on.
    """

    name: str
    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int32, counter-clockwise seen from outside

    def __post_init__(self) -> None:
        vertices = np.array(self.vertices, dtype=np.float64, order="C")
        faces = np.array(self.faces, dtype=np.int32, order="C")
        if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.isfinite(vertices).all():
            raise ValueError(f"{self.name}: vertices must be a finite (V, 3) array")
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"{self.name}: faces must be a non-empty (F, 3) array")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise ValueError(f"{self.name}: faces index vertices out of range")
        vertices.setflags(write=False)
        faces.setflags(write=False)
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "faces", faces)

    def __repr__(self) -> str:
        return (
            f"ObjectMesh(name={self.name!r}, vertices={len(self.vertices)}, "
            f"faces={len(self.faces)}, extents={np.round(self.extents, 4).tolist()})"
        )

    @cached_property
    def digest(self) -> str:
        """Content hash of name, vertices and faces."""
        sha = hashlib.sha1(self.name.encode())
        sha.update(self.vertices.tobytes())
        sha.update(self.faces.tobytes())
        return sha.hexdigest()

    def __hash__(self) -> int:
        return hash(self.digest)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ObjectMesh):
            return NotImplemented
        return self.digest == other.digest

    @property
    def extents(self) -> np.ndarray:
        """Bounding-box side lengths (x, y, z)."""
        return np.ptp(self.vertices, axis=0)

    @property
    def middle(self) -> np.ndarray:
        """Bounding-box centre: where the observation views are centred."""
        return 0.5 * (self.vertices.min(axis=0) + self.vertices.max(axis=0))

    @property
    def diagonal(self) -> float:
        """Bounding-box diagonal length."""
        return float(np.linalg.norm(self.extents))

    @cached_property
    def face_areas(self) -> np.ndarray:
        return 0.5 * np.linalg.norm(self._face_cross, axis=1)

    @cached_property
    def face_normals(self) -> np.ndarray:
        """Unit normals (F, 3) from the winding (outward for an outward-oriented mesh)."""
        norm = np.linalg.norm(self._face_cross, axis=1, keepdims=True)
        return self._face_cross / np.where(norm > 0, norm, 1.0)

    @property
    def area(self) -> float:
        """Total triangle area (overlapping parts count in full)."""
        return float(self.face_areas.sum())

    @property
    def volume(self) -> float:
        """Signed enclosed volume; the sum over parts, so overlaps count twice."""
        return _signed_volume(self.vertices, self.faces)

    @cached_property
    def part_ids(self) -> np.ndarray:
        """Connected component (part) of every face, (F,) int."""
        return _face_components(self.faces, len(self.vertices))

    @cached_property
    def _face_cross(self) -> np.ndarray:
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        return np.cross(b - a, c - a)

    def scaled(self, factor: float) -> ObjectMesh:
        """The same object uniformly scaled about the object-frame origin (still resting on
        z = 0 and centred)."""
        if not (np.isfinite(factor) and factor > 0):
            raise ValueError(f"scale must be a positive number, got {factor!r}")
        if factor == 1.0:
            return self
        return ObjectMesh(self.name, self.vertices * factor, self.faces)

    def to_open3d(self) -> o3d.geometry.TriangleMesh:
        """A legacy open3d mesh (copies), e.g. for Poisson reconstruction or checks."""
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices.copy()),
            o3d.utility.Vector3iVector(self.faces.copy()),
        )
        mesh.compute_triangle_normals()
        return mesh


# --- geometry helpers ------------------------------------------------------------------------


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _face_components(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """Label of the connected component each face belongs to (faces sharing a vertex)."""
    rows = np.repeat(faces[:, 0], 2)
    cols = faces[:, 1:].ravel()
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(vertex_count,) * 2)
    _, labels = connected_components(graph, directed=False)
    return labels[faces[:, 0]]


def _is_closed(faces: np.ndarray) -> bool:
    """Every edge shared by exactly two faces that traverse it in opposite directions."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    if len(np.unique(directed, axis=0)) != len(directed):
        return False  # an edge used twice in one direction: inconsistent or non-manifold
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def _orient_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces of one closed part, flipped if they enclose a negative volume."""
    return faces[:, ::-1].copy() if _signed_volume(vertices, faces) < 0 else faces


Part = tuple[np.ndarray, np.ndarray]  # (vertices (V, 3), faces (F, 3)) of one closed part


def _loft(
    rings: np.ndarray,
    start_pole: np.ndarray | None = None,
    end_pole: np.ndarray | None = None,
    periodic: bool = False,
) -> Part:
    """Closed surface through ``rings`` (R, n, 3) of n points each, consecutive rings joined
    by quads; either periodic (the last ring joins the first: a torus) or capped by triangle
    fans to a pole point at each end. Winding is consistent; orientation is fixed later."""
    ring_count, n = rings.shape[:2]
    vertices = [rings.reshape(-1, 3)]
    k = np.arange(n)
    k1 = (k + 1) % n
    bands = ring_count if periodic else ring_count - 1
    i = np.arange(bands)[:, None]
    i1 = (i + 1) % ring_count
    a, b = i * n + k, i * n + k1
    c, d = i1 * n + k1, i1 * n + k
    faces = [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    if not periodic:
        next_index = ring_count * n
        if start_pole is not None:
            vertices.append(np.asarray(start_pole, float)[None])
            faces.append(np.stack([np.full(n, next_index), k1, k], -1))
            next_index += 1
        if end_pole is not None:
            last = (ring_count - 1) * n
            vertices.append(np.asarray(end_pole, float)[None])
            faces.append(np.stack([np.full(n, next_index), last + k, last + k1], -1))
    return np.concatenate(vertices), np.concatenate(faces).astype(np.int32)


def _revolve(
    profile: Sequence[Sequence[float]],
    segments: int = _SEGMENTS,
    *,
    phase: float = 0.0,
    closed: bool = False,
) -> Part:
    """Surface of revolution about z of a profile of (r, z) points. An open profile must start
    and end on the axis (r = 0), where it closes with a pole; a ``closed`` profile is a loop
    off the axis (a torus, a tube wall). ``segments=4, phase=pi/4`` gives square sections."""
    profile = np.asarray(profile, dtype=float)
    theta = phase + 2.0 * np.pi * np.arange(segments) / segments
    if closed:
        inner, start, end = profile, None, None
    else:
        if profile[0, 0] != 0.0 or profile[-1, 0] != 0.0:
            raise ValueError("an open profile must start and end on the axis (r = 0)")
        inner = profile[1:-1]
        start, end = (0.0, 0.0, profile[0, 1]), (0.0, 0.0, profile[-1, 1])
    r, z = inner[:, :1], inner[:, 1:]
    rings = np.stack(
        [r * np.cos(theta), r * np.sin(theta), np.broadcast_to(z, r.shape[:1] + theta.shape)],
        axis=-1,
    )
    return _loft(rings, start, end, periodic=closed)


def _box(size: Sequence[float], center: Sequence[float], yaw: float = 0.0) -> Part:
    """An axis-aligned box (then turned by ``yaw`` about z), 12 triangles."""
    corners = (np.indices((2, 2, 2)).reshape(3, -1).T - 0.5) * np.asarray(size, float)
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    vertices = corners @ rotation.T + np.asarray(center, float)
    # Corner index = 4 ix + 2 iy + iz; each face's quad is wound outward.
    quads = np.array(
        [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    )
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return vertices, faces.astype(np.int32)


def _cross2(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """z component of the cross product of 2-D vectors (numpy 2 deprecates 2-D np.cross)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _triangulate_polygon(polygon: np.ndarray) -> np.ndarray:
    """Ear-clipping triangulation (T, 3) of a simple counter-clockwise polygon (n, 2) without
    collinear consecutive vertices. O(n^3) on a handful of profile vertices at build time."""
    remaining = list(range(len(polygon)))
    triangles = []
    while len(remaining) > 3:
        for k in range(len(remaining)):
            i0, i1, i2 = remaining[k - 1], remaining[k], remaining[(k + 1) % len(remaining)]
            a, b, c = polygon[i0], polygon[i1], polygon[i2]
            if _cross2(b - a, c - b) <= 1e-12:
                continue  # reflex corner: not an ear
            others = polygon[[j for j in remaining if j not in (i0, i1, i2)]]
            # Barycentric sign test: any other vertex in (or on) the triangle blocks the ear.
            d1 = _cross2(b - a, others - a)
            d2 = _cross2(c - b, others - b)
            d3 = _cross2(a - c, others - c)
            if np.any((d1 >= 0) & (d2 >= 0) & (d3 >= 0)):
                continue
            triangles.append((i0, i1, i2))
            remaining.pop(k)
            break
        else:
            raise ValueError("polygon is not simple or not counter-clockwise")
    triangles.append(tuple(remaining))
    return np.asarray(triangles, dtype=np.int32)


def _extrude(polygon_xz: Sequence[Sequence[float]], depth: float) -> Part:
    """A prism: a simple polygon in the x-z plane extruded symmetrically along y."""
    polygon = np.asarray(polygon_xz, dtype=float)
    if _polygon_area(polygon) < 0:
        polygon = polygon[::-1]
    n = len(polygon)
    caps = _triangulate_polygon(polygon)
    front = np.column_stack([polygon[:, 0], np.full(n, -depth / 2), polygon[:, 1]])
    back = front + [0.0, depth, 0.0]
    k = np.arange(n)
    k1 = (k + 1) % n
    # The front cap runs along its boundary k -> k1, so the side quads run k1 -> k.
    sides = np.concatenate([np.stack([k1, k, k + n], -1), np.stack([k1, k + n, k1 + n], -1)])
    faces = np.concatenate([caps, caps[:, ::-1] + n, sides])
    return np.concatenate([front, back]), faces.astype(np.int32)


def _polygon_area(polygon: np.ndarray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def _tube(path: np.ndarray, radius: float, segments: int = _TUBE_SEGMENTS) -> Part:
    """A capped circular tube along a smooth path (P, 3) lying in the x-z plane."""
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    binormal = np.array([0.0, 1.0, 0.0])  # the path's plane normal: no twist
    normal = np.cross(binormal, tangent)
    theta = 2.0 * np.pi * np.arange(segments) / segments
    offsets = radius * (
        np.cos(theta)[None, :, None] * normal[:, None] + np.sin(theta)[None, :, None] * binormal
    )
    rings = path[:, None] + offsets
    return _loft(rings, path[0], path[-1])


def _swap_axes(part: Part, order: Sequence[int], offset: Sequence[float] = (0, 0, 0)) -> Part:
    """Permute coordinate axes (e.g. a z-axis revolve onto x), then translate."""
    vertices, faces = part
    return vertices[:, list(order)] + np.asarray(offset, float), faces


def _assemble(name: str, parts: Sequence[Part]) -> ObjectMesh:
    """Concatenate closed parts (each oriented outward) into one mesh resting on z = 0 with
    its bounding box centred at x = y = 0."""
    vertices, faces, offset = [], [], 0
    for part_vertices, part_faces in parts:
        vertices.append(part_vertices)
        faces.append(_orient_outward(part_vertices, part_faces) + offset)
        offset += len(part_vertices)
    vertices = np.concatenate(vertices)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    vertices = vertices - [(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2]]
    return ObjectMesh(name, vertices, np.concatenate(faces))


# --- the library -----------------------------------------------------------------------------


def _make_box() -> ObjectMesh:
    return _assemble("box", [_box((0.14, 0.09, 0.06), (0, 0, 0.03))])


def _make_cylinder() -> ObjectMesh:
    return _assemble("cylinder", [_revolve([(0, 0), (0.035, 0), (0.035, 0.12), (0, 0.12)])])


def _make_cone() -> ObjectMesh:
    return _assemble("cone", [_revolve([(0, 0), (0.05, 0), (0, 0.11)])])


def _make_torus() -> ObjectMesh:
    major, minor = 0.055, 0.017
    angle = 2.0 * np.pi * np.arange(20) / 20
    loop = np.column_stack([major + minor * np.cos(angle), minor + minor * np.sin(angle)])
    return _assemble("torus", [_revolve(loop, closed=True)])


def _make_l_bracket() -> ObjectMesh:
    outline = [(0, 0), (0.12, 0), (0.12, 0.015), (0.016, 0.015), (0.016, 0.10), (0, 0.10)]
    return _assemble("l_bracket", [_extrude(outline, 0.06)])


def _make_u_bracket() -> ObjectMesh:
    outline = [
        (0, 0), (0.12, 0), (0.12, 0.08), (0.108, 0.08),
        (0.108, 0.012), (0.012, 0.012), (0.012, 0.08), (0, 0.08),
    ]  # fmt: skip
    return _assemble("u_bracket", [_extrude(outline, 0.07)])


def _make_arch() -> ObjectMesh:
    width, height, half_gap, leg, depth = 0.16, 0.10, 0.045, 0.03, 0.05
    arc = np.linspace(np.pi, 0.0, 25)[1:-1]  # over the top, left to right
    outline = np.concatenate(
        [
            [(-width / 2, 0), (-half_gap, 0), (-half_gap, leg)],
            np.column_stack([half_gap * np.cos(arc), leg + half_gap * np.sin(arc)]),
            [(half_gap, leg), (half_gap, 0), (width / 2, 0), (width / 2, height)],
            [(-width / 2, height)],
        ]
    )
    return _assemble("arch", [_extrude(outline, depth)])


def _cup_profile(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """Profile of a shell of revolution: from the bottom centre, up the outer wall (r, z)
    points, across the rim, down the inner wall to the inner bottom centre."""
    return np.concatenate([[(0.0, 0.0)], outer, inner, [(0.0, inner[-1, 1])]])


def _make_mug() -> ObjectMesh:
    radius, height, wall, bottom = 0.04, 0.095, 0.004, 0.006
    body = _revolve(
        _cup_profile(
            np.array([(radius, 0.0), (radius, height)]),
            np.array([(radius - wall, height), (radius - wall, bottom)]),
        )
    )
    # A D-shaped handle: straight out of the wall, a half circle, straight back. Its ends
    # stop mid-wall, so the caps are buried in the wall and never seen.
    root, reach, centre_z, bend = radius - wall / 2, 0.018, 0.05, 0.025
    arc = np.linspace(np.pi / 2, -np.pi / 2, 17)
    path = np.concatenate(
        [
            [(root, 0.0, centre_z + bend)],
            np.column_stack(
                [
                    radius + reach + bend * np.cos(arc),
                    np.zeros_like(arc),
                    centre_z + bend * np.sin(arc),
                ]
            ),
            [(root, 0.0, centre_z - bend)],
        ]
    )
    return _assemble("mug", [body, _tube(path, 0.0055)])


def _make_bowl() -> ObjectMesh:
    # Outer wall: a half-ellipse (semi-axes radius x (height + sink)) centred at the rim
    # height, cut by the table so the bowl stands on a flat foot; inner wall: the same
    # ellipse shrunk by the wall thickness, ending above the foot.
    radius, height, wall, sink = 0.08, 0.06, 0.005, 0.0025
    start = np.arccos(height / (height + sink))
    s_out = np.linspace(start, np.pi / 2, 14)
    outer = np.column_stack([radius * np.sin(s_out), height - (height + sink) * np.cos(s_out)])
    s_in = np.linspace(np.pi / 2, 0.0, 16)[:-1]
    inner = np.column_stack(
        [(radius - wall) * np.sin(s_in), height - (height + sink - wall) * np.cos(s_in)]
    )
    profile = np.concatenate([[(0.0, 0.0)], outer, inner, [(0.0, wall - sink)]])
    return _assemble("bowl", [_revolve(profile, 40)])


def _make_vase() -> ObjectMesh:
    # Outer radius along the height through control points (smooth, no overshoot), a 3 mm
    # wall and a narrow neck: the inside is visible only through the mouth.
    z_ctrl = [0.0, 0.02, 0.06, 0.10, 0.14, 0.16, 0.175, 0.18]
    r_ctrl = [0.032, 0.042, 0.05, 0.04, 0.02, 0.017, 0.022, 0.026]
    radius_at = PchipInterpolator(z_ctrl, r_ctrl)
    wall, bottom, height = 0.003, 0.005, 0.18
    z_out = np.linspace(0.0, height, 18)
    z_in = np.linspace(height, bottom, 18)
    profile = _cup_profile(
        np.column_stack([radius_at(z_out), z_out]),
        np.column_stack([radius_at(z_in) - wall, z_in]),
    )
    return _assemble("vase", [_revolve(profile, 40)])


def _make_open_box() -> ObjectMesh:
    # Four-segment revolution turned by 45 degrees: a square tray with 5 mm walls, one part.
    half, height, wall, bottom = 0.065, 0.07, 0.005, 0.006
    corner, inner = half * np.sqrt(2), (half - wall) * np.sqrt(2)
    profile = [(0, 0), (corner, 0), (corner, height), (inner, height), (inner, bottom), (0, bottom)]
    return _assemble("open_box", [_revolve(profile, 4, phase=np.pi / 4)])


def _make_obelisk() -> ObjectMesh:
    base, shoulder = 0.02 * np.sqrt(2), 0.013 * np.sqrt(2)
    profile = [(0, 0), (base, 0), (shoulder, 0.16), (0, 0.19)]
    return _assemble("obelisk", [_revolve(profile, 4, phase=np.pi / 4)])


def _make_table() -> ObjectMesh:
    top = (0.16, 0.10, 0.012)
    leg, height = 0.012, 0.10
    parts = [_box(top, (0, 0, height - top[2] / 2))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            centre = (sx * (top[0] / 2 - leg), sy * (top[1] / 2 - leg), (height - 0.008) / 2)
            parts.append(_box((leg, leg, height - 0.008), centre))  # ends inside the top
    return _assemble("table", parts)


def _make_chair() -> ObjectMesh:
    seat, seat_top, leg, inset, back_top = 0.09, 0.085, 0.009, 0.039, 0.17
    parts = [_box((seat, seat, 0.01), (0, 0, seat_top - 0.005))]
    for sy in (-1, 1):
        parts.append(_box((leg, leg, 0.08), (inset, sy * inset, 0.04)))  # front legs
        parts.append(_box((leg, leg, back_top), (-inset, sy * inset, back_top / 2)))  # posts
    parts.append(_box((0.008, 2 * inset - 0.0015, 0.04), (-inset, 0, back_top - 0.03)))
    return _assemble("chair", parts)


def _make_stacked_blocks() -> ObjectMesh:
    sink = 0.002  # each block sits this deep in the one below, so no faces coincide
    blocks = [
        ((0.12, 0.08, 0.04), (0.0, 0.0), 0.0),
        ((0.09, 0.06, 0.035), (0.01, 0.0), np.radians(25)),
        ((0.05, 0.045, 0.05), (-0.01, 0.005), np.radians(-35)),
    ]
    parts, bottom = [], 0.0
    for size, (x, y), yaw in blocks:
        parts.append(_box(size, (x, y, bottom + size[2] / 2), yaw))
        bottom += size[2] - sink
    return _assemble("stacked_blocks", parts)


def _make_step_pyramid() -> ObjectMesh:
    tier, sink = 0.025, 0.002
    parts = [
        _box((side, side, tier), (0, 0, k * (tier - sink) + tier / 2))
        for k, side in enumerate((0.16, 0.12, 0.08, 0.04))
    ]
    return _assemble("step_pyramid", parts)


def _make_t_pipe() -> ObjectMesh:
    # A reducing tee lying on the table: a main tube along x and a narrower branch along +y
    # whose end is buried in the main tube's wall (the two bores do not connect; the branch
    # is a blind socket whose bottom is the main tube's outer wall).
    outer, inner, length = 0.024, 0.019, 0.16
    b_outer, b_inner, b_start, b_end = 0.012, 0.008, 0.0199, 0.075
    main = _revolve(
        [(inner, -length / 2), (outer, -length / 2), (outer, length / 2), (inner, length / 2)],
        closed=True,
    )
    branch = _revolve(
        [(b_inner, b_start), (b_outer, b_start), (b_outer, b_end), (b_inner, b_end)],
        32,
        closed=True,
    )
    return _assemble(
        "t_pipe",
        [_swap_axes(main, (2, 1, 0), (0, 0, outer)), _swap_axes(branch, (0, 2, 1), (0, 0, outer))],
    )


def _bumpy_sphere(
    rng: np.random.Generator, bumps: int, rings: int, segments: int = _SEGMENTS
) -> Part:
    """Smooth seeded noise on a unit sphere: radius 1 + a sum of von Mises bumps (smooth and
    star-shaped, so the surface cannot fold), ``rings`` polar rings of ``segments`` points."""
    centres = rng.normal(size=(bumps, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    amplitudes = rng.uniform(0.1, 0.3, bumps) * rng.choice([-1.0, 1.0], bumps, p=[0.3, 0.7])
    sharpness = rng.uniform(4.0, 12.0, bumps)
    polar = np.linspace(-np.pi / 2, np.pi / 2, rings)
    vertices, faces = _revolve(np.column_stack([np.cos(polar), np.sin(polar)]).round(12), segments)
    directions = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    radius = 1.0 + np.exp(sharpness * (directions @ centres.T - 1.0)) @ amplitudes
    return directions * radius[:, None], faces


def _make_bunny() -> ObjectMesh:
    # A bumpy sphere stretched like a crouching animal, bottom cut flat so it stands on the
    # table.
    vertices, faces = _bumpy_sphere(np.random.default_rng(BLOB_SEED), 16, 26)
    vertices = vertices * [0.075, 0.055, 0.06]
    floor = vertices[:, 2].min() + 0.012
    vertices[:, 2] = np.maximum(vertices[:, 2], floor)
    return _assemble("bunny", [(vertices, faces)])


# Validation families: chosen like the held-out ones (each hides part of its surface in a
# way no train object does), but used only to pick a model during training, so the
# held-out score stays an unbiased test.


def _make_bench() -> ObjectMesh:
    # A plank on two panel legs: a low, wide tunnel open at both ends.
    width, height, top, leg, depth = 0.16, 0.07, 0.012, 0.012, 0.06
    inner = width / 2 - leg
    outline = [
        (-width / 2, 0), (-inner, 0), (-inner, height - top), (inner, height - top),
        (inner, 0), (width / 2, 0), (width / 2, height), (-width / 2, height),
    ]  # fmt: skip
    return _assemble("bench", [_extrude(outline, depth)])


def _make_c_channel() -> ObjectMesh:
    # A C-section standing on one flange, lips turned in: the inside is seen only through
    # the slot between the lips, from one side.
    width, height, wall, lip = 0.09, 0.14, 0.012, 0.035
    outline = [
        (0, 0), (width, 0), (width, lip), (width - wall, lip), (width - wall, wall),
        (wall, wall), (wall, height - wall), (width - wall, height - wall),
        (width - wall, height - lip), (width, height - lip), (width, height), (0, height),
    ]  # fmt: skip
    return _assemble("c_channel", [_extrude(outline, 0.05)])


def _make_ring_stand() -> ObjectMesh:
    # An upright ring on a foot: its inner wall is seen only from views near its axis.
    major, minor, foot = 0.045, 0.01, (0.07, 0.04, 0.012)
    angle = 2.0 * np.pi * np.arange(20) / 20
    loop = np.column_stack([major + minor * np.cos(angle), minor * np.sin(angle)])
    ring = _swap_axes(_revolve(loop, closed=True), (0, 2, 1), (0, 0, foot[2] / 2 + major + minor))
    return _assemble("ring_stand", [_box(foot, (0, 0, foot[2] / 2)), ring])


def _make_stool() -> ObjectMesh:
    # A round seat on three thin legs that end inside it.
    seat_radius, seat, height, leg_radius, leg_offset = 0.05, 0.012, 0.09, 0.006, 0.034
    bottom = height - seat
    parts = [_revolve([(0, bottom), (seat_radius, bottom), (seat_radius, height), (0, height)])]
    for angle in 2.0 * np.pi * np.arange(3) / 3 + np.pi / 2:
        vertices, faces = _revolve(
            [(0, 0), (leg_radius, 0), (leg_radius, height - seat / 2), (0, height - seat / 2)], 12
        )
        offset = leg_offset * np.array([np.cos(angle), np.sin(angle), 0.0])
        parts.append((vertices + offset, faces))
    return _assemble("stool", parts)


_BUILDERS: dict[str, Callable[[], ObjectMesh]] = {
    "box": _make_box,
    "cylinder": _make_cylinder,
    "cone": _make_cone,
    "torus": _make_torus,
    "l_bracket": _make_l_bracket,
    "u_bracket": _make_u_bracket,
    "mug": _make_mug,
    "bowl": _make_bowl,
    "table": _make_table,
    "chair": _make_chair,
    "stacked_blocks": _make_stacked_blocks,
    "arch": _make_arch,
    "bunny": _make_bunny,
    "obelisk": _make_obelisk,
    "vase": _make_vase,
    "t_pipe": _make_t_pipe,
    "step_pyramid": _make_step_pyramid,
    "open_box": _make_open_box,
    "bench": _make_bench,
    "c_channel": _make_c_channel,
    "ring_stand": _make_ring_stand,
    "stool": _make_stool,
}

OBJECT_NAMES: tuple[str, ...] = tuple(_BUILDERS)

# The split tests generalisation to shape *families* the policy never saw, not to rescaled
# copies (the environment rescales every object anyway):
# - torus: a ring lying flat, whose hole and inner wall only steep views reveal;
# - chair: a tall, one-sided occluder (the backrest) over a thin-legged base;
# - arch: a tunnel whose ceiling is visible only from low views along its axis;
# - u_bracket: an open channel, concave along one axis only (train has L and a closed tray);
# - t_pipe: hollow tubes whose bores are visible only through their ends.
# Train keeps one member of each remaining family: convex primitives (box, cylinder, cone,
# obelisk), shells of revolution (mug, bowl, vase), a container (open_box), legged furniture
# (table), stacks (stacked_blocks, step_pyramid), a bracket (l_bracket) and a free-form blob.
# Validation (for choosing a model during training, never for the reported score): four more
# families with no member in train or held out, each hiding surface in its own way:
# - bench: a low tunnel under a plank (a train table has legs, not panels);
# - c_channel: a cavity seen only through a slot on one side;
# - ring_stand: an upright ring whose inner wall faces along one horizontal axis;
# - stool: a round seat on three thin legs, its underside seen only from low views.
_HELD_OUT = ("torus", "chair", "arch", "u_bracket", "t_pipe")
_VALIDATION = ("bench", "c_channel", "ring_stand", "stool")
OBJECT_SETS: dict[str, tuple[str, ...]] = {
    "train": tuple(name for name in OBJECT_NAMES if name not in _HELD_OUT + _VALIDATION),
    "validation": _VALIDATION,
    "held_out": _HELD_OUT,
    "all": OBJECT_NAMES,
    # Not in "all", which is the library's families.
    "procedural": tuple(f"{PROCEDURAL_PREFIX}{n}" for n in range(PROCEDURAL_SET_SIZE)),
}


def is_object_name(name: str) -> bool:
    """Whether ``name`` names a library object or a procedural shape (``procedural_<n>``)."""
    return name in _BUILDERS or _procedural_index(name) is not None


def get_object(name: str) -> ObjectMesh:
    """The library object or procedural shape ``name`` (built once, then cached)."""
    if not is_object_name(name):
        raise ValueError(
            f"unknown object {name!r}; library objects: {', '.join(OBJECT_NAMES)}, or "
            f"{PROCEDURAL_PREFIX}<n> for procedural shape n (0 <= n < 1000000, no leading zeros)"
        )
    return _build_object(name)


@cache
def _build_object(name: str) -> ObjectMesh:
    if name in _BUILDERS:
        return _BUILDERS[name]()
    return _make_procedural(_procedural_index(name))


# --- procedural shapes -----------------------------------------------------------------------
# Random composites of one to five parts of the kinds the train families are made of (boxes,
# cylinders, frusta and pyramids, convex and L-shaped prisms, cups, blobs), standing side by
# side or stacked, one part on one support. No part is a ring, a tube, an arch, a channel or a
# leg, so the held-out and validation families' defining parts stay unseen and training on
# these measures generalisation from more shapes, not from the test families. Their
# arrangement is free, though: parts may stand apart with gaps between them (15 of the 64 in
# the set), and a stacked part may overhang its support (over another part in 16 of shapes
# 64-1999, none of the set).

_PROCEDURAL_NAME_DIGITS = 6
_STACK_SINK = 0.002  # a stacked part sinks this deep into its support: no coincident faces
_CUP_WALL, _CUP_BOTTOM = 0.004, 0.005
#: A cup narrower than this inside (m, before the shape is scaled to size) would be slivers
#: or turn itself inside out: it is built solid instead, from the same random draws, so every
#: other shape stays as it was (the narrowest bore in the set, shape 4's, is 2.2 mm).
_CUP_MIN_BORE = 0.001


class _Support(NamedTuple):
    """A flat top another part can stand on: a disc of radius ``half`` at height ``top``."""

    x: float
    y: float
    half: float
    top: float


def _procedural_index(name: str) -> int | None:
    if not isinstance(name, str) or not name.startswith(PROCEDURAL_PREFIX):
        return None
    digits = name[len(PROCEDURAL_PREFIX) :]
    if not digits.isdecimal() or not digits.isascii() or len(digits) > _PROCEDURAL_NAME_DIGITS:
        return None
    if digits != str(int(digits)):  # one name per shape: no leading zeros
        return None
    return int(digits)


def _random_part(rng: np.random.Generator, half: float) -> tuple[Part, float | None]:
    """One part standing on z = 0 around the z axis, about ``half`` m in footprint radius,
    and the radius of the flat disc on its top (None where nothing can stand on it)."""
    kind = rng.choice(["box", "revolved", "prism", "l_prism", "cup", "blob"])
    height = rng.uniform(0.02, 0.11)
    yaw = rng.uniform(0.0, np.pi)
    if kind == "box":
        sx, sy = 2 * half * rng.uniform(0.35, 1.0, 2)
        return _box((sx, sy, height), (0.0, 0.0, height / 2), yaw), min(sx, sy) / 2
    if kind == "revolved":  # cylinder, frustum or cone; round or a 4- or 6-sided pyramid
        segments = int(rng.choice([32, 4, 6]))
        bottom = half * rng.uniform(0.5, 1.0)
        top = bottom * rng.choice([1.0, rng.uniform(0.3, 0.9), 0.0])
        if top == 0.0:
            return _revolve([(0, 0), (bottom, 0), (0, height)], segments, phase=yaw), None
        part = _solid_frustum(bottom, top, height, segments, yaw)
        return part, top * np.cos(np.pi / segments)  # the top polygon's inscribed radius
    if kind == "prism":  # a convex outline with a flat base, extruded
        width = 2 * half * rng.uniform(0.5, 1.0)
        tops = np.column_stack(
            [rng.uniform(-width / 2, width / 2, 4), height * rng.uniform(0.3, 1.0, 4)]
        )
        outline = np.concatenate([[(-width / 2, 0.0), (width / 2, 0.0)], tops])
        outline = outline[ConvexHull(outline).vertices]
        part = _extrude(outline, 2 * half * rng.uniform(0.3, 1.0))
        return _turned(part, yaw), None
    if kind == "l_prism":
        width = 2 * half * rng.uniform(0.6, 1.0)
        thick = min(width, height) * rng.uniform(0.12, 0.3)
        outline = [(0, 0), (width, 0), (width, thick), (thick, thick), (thick, height), (0, height)]
        vertices, faces = _extrude(outline, 2 * half * rng.uniform(0.3, 1.0))
        return _turned((vertices - [width / 2, 0.0, 0.0], faces), yaw), None
    if kind == "cup":
        radius = half * rng.uniform(0.5, 0.9)
        rim = radius * rng.uniform(0.7, 1.1)
        segments = int(rng.choice([32, 4]))
        if min(radius, rim) - _CUP_WALL < _CUP_MIN_BORE:
            return _solid_frustum(radius, rim, height, segments, yaw), None
        outer = np.array([(radius, 0.0), (rim, height)])
        inner = np.array([(rim - _CUP_WALL, height), (radius - _CUP_WALL, _CUP_BOTTOM)])
        return _revolve(_cup_profile(outer, inner), segments, phase=yaw), None
    return _random_blob(rng, half, height), None


def _solid_frustum(bottom: float, top: float, height: float, segments: int, yaw: float) -> Part:
    """A solid of revolution from a disc of radius ``bottom`` on z = 0 to one of radius
    ``top`` at ``height`` (a cylinder, frustum or, with few segments, a pyramid's frustum)."""
    return _revolve([(0, 0), (bottom, 0), (top, height), (0, height)], segments, phase=yaw)


def _random_blob(rng: np.random.Generator, half: float, height: float) -> Part:
    """A smooth star-shaped lump (a bumpy sphere stretched to an ellipsoid), its bottom cut
    flat."""
    vertices, faces = _bumpy_sphere(rng, 8, 18, 24)
    semi_axes = [half * rng.uniform(0.5, 1.0), half * rng.uniform(0.5, 1.0), height / 2]
    vertices = vertices * semi_axes
    floor = vertices[:, 2].min() + 0.2 * np.ptp(vertices[:, 2])
    vertices[:, 2] = np.maximum(vertices[:, 2], floor) - floor
    return vertices, faces


def _turned(part: Part, yaw: float) -> Part:
    c, s = np.cos(yaw), np.sin(yaw)
    vertices, faces = part
    return vertices @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]), faces


def _make_procedural(index: int) -> ObjectMesh:
    rng = np.random.default_rng([PROCEDURAL_SEED, index])
    parts: list[Part] = []
    supports: list[_Support] = []

    def add(x: float, y: float, base: float, half: float) -> None:
        (vertices, faces), flat = _random_part(rng, half)
        parts.append((vertices + [x, y, base], faces))
        if flat is not None and flat > 0.008:
            supports.append(_Support(x, y, flat, base + float(vertices[:, 2].max())))

    add(0.0, 0.0, 0.0, rng.uniform(0.03, 0.07))
    for _ in range(rng.choice([0, 1, 2], p=[0.4, 0.4, 0.2])):  # more parts on the table
        angle, reach = rng.uniform(0.0, 2 * np.pi), rng.uniform(0.03, 0.09)
        add(reach * np.cos(angle), reach * np.sin(angle), 0.0, rng.uniform(0.02, 0.05))
    for _ in range(rng.choice([0, 1, 2], p=[0.35, 0.45, 0.2])):  # parts stacked on a flat top
        if not supports:
            break
        support = supports[rng.integers(len(supports))]
        angle, reach = rng.uniform(0.0, 2 * np.pi), support.half * rng.uniform(0.0, 0.5)
        x, y = support.x + reach * np.cos(angle), support.y + reach * np.sin(angle)
        add(x, y, support.top - _STACK_SINK, support.half * rng.uniform(0.5, 1.4))
    name = f"{PROCEDURAL_PREFIX}{index}"
    mesh = _assemble(name, parts)
    size = rng.uniform(*PROCEDURAL_SIZE_RANGE)
    return ObjectMesh(name, mesh.vertices * (size / mesh.extents.max()), mesh.faces)


# --- users' mesh files -----------------------------------------------------------------------


def load_mesh_file(path: str | Path, size: float = DEFAULT_USER_MESH_SIZE) -> ObjectMesh:
    """Load a user's ``.obj``, ``.stl`` or ``.ply`` triangle mesh as an object named after the
    file's stem: duplicated vertices and degenerate or repeated triangles removed (a triangle
    repeated with its winding reversed too), scaled so its largest bounding-box side is
    ``size`` (m), centred in x and y, resting on z = 0, and wound outward: each connected
    part's triangles are made to agree with their neighbours' winding, and the part is
    flipped if they enclose a negative volume (taken about the part's centre, so that an open
    part is judged the same wherever the file puts it)."""
    path = Path(path)
    if not (np.isfinite(size) and size > 0):
        raise ValueError(f"size must be a positive length in metres, got {size!r}")
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    if path.suffix.lower() not in MESH_FILE_EXTENSIONS:
        raise ValueError(
            f"unsupported mesh file {path} (extension {path.suffix!r}); "
            f"supported: {', '.join(MESH_FILE_EXTENSIONS)}"
        )
    if not path.is_file():
        raise ValueError(f"mesh path {path} is not a file")
    if path.suffix.lower() == ".obj":
        # open3d (through assimp) silently drops an OBJ's quads and other polygons, which is
        # how Blender and most CAD tools export: read the file here instead.
        mesh = _read_obj(path)
    else:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise ValueError(
            f"could not read any triangles from mesh file {path} "
            "(unreadable, empty, or a point cloud without faces)"
        )
    mesh.remove_duplicated_vertices()
    mesh.remove_duplicated_triangles()
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.triangles, dtype=np.int64)
    if len(faces) == 0 or not np.isfinite(vertices).all():
        raise ValueError(f"mesh file {path} has no usable triangles (or non-finite vertices)")
    extent = float(np.ptp(vertices, axis=0).max())
    if not np.isfinite(extent * extent):  # the area test below squares lengths
        raise ValueError(f"mesh file {path} spans {extent:g} units: too large to scale")
    # Also drop zero-area slivers (three distinct but collinear vertices).
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    keep = np.linalg.norm(np.cross(b - a, c - a), axis=1) > 1e-12 * max(extent, 1e-30) ** 2
    faces = faces[keep]
    if len(faces) == 0 or extent <= 0:
        raise ValueError(f"mesh file {path} has no usable triangles (all degenerate)")
    # A double-sided mesh repeats each triangle reversed: keep the first of each vertex set.
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    faces = faces[np.sort(first)]
    used, faces = np.unique(faces, return_inverse=True)
    vertices = vertices[used]
    # Scaled by what is left: a dropped sliver may have reached far beyond the solid.
    vertices *= size / float(np.ptp(vertices, axis=0).max())
    faces = faces.reshape(-1, 3)
    spread = np.linalg.svd(vertices - vertices.mean(axis=0), compute_uv=False)
    if len(vertices) < 4 or spread[-1] <= 1e-9 * spread[0]:
        # MuJoCo collides a mesh through its convex hull, which a flat one does not have.
        raise ValueError(
            f"mesh file {path} is flat: all its vertices lie in one plane, so it encloses no "
            "volume; an object must be a solid (a sheet needs a thickness)"
        )
    faces = _wound_outward(vertices, faces)
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    vertices -= [(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2]]
    return ObjectMesh(path.stem, vertices, faces)


def _wound_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``faces`` with each connected part wound consistently (open3d's ``orient_triangles``,
    where the part is orientable) and outward: a file may mix parts, or triangles, wound
    either way, and ground truth on an inward part would count as unobservable."""
    # Neighbours agree when no edge is traversed twice in one direction; most files are so,
    # and open3d's pass over a scanned mesh of 200k triangles costs seconds.
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).astype(np.int64)
    if len(np.unique(edges[:, 0] * len(vertices) + edges[:, 1])) < len(edges):
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(vertices),
            o3d.utility.Vector3iVector(faces.astype(np.int32)),
        )
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            mesh.orient_triangles()  # False where a part is not orientable: left as it was
        faces = np.asarray(mesh.triangles, dtype=np.int64)
    faces = faces.copy()  # parts are flipped in place
    labels = _face_components(faces, len(vertices))
    for label in np.unique(labels):
        part = labels == label
        centre = vertices[np.unique(faces[part])].mean(axis=0)
        faces[part] = _orient_outward(vertices - centre, faces[part])
    return faces


def _read_obj(path: Path) -> o3d.geometry.TriangleMesh:
    """The vertices and faces of a Wavefront OBJ file, polygons fan-triangulated (exact for
    convex polygons); texture, normal, line and group records are ignored."""
    vertices: list[list[float]] = []
    triangles: list[tuple[int, int, int]] = []
    text = path.read_text(encoding="utf-8-sig", errors="replace")  # -sig: a leading BOM
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0] not in ("v", "f"):
            continue
        try:
            if fields[0] == "v":
                vertices.append([float(value) for value in fields[1:4]])
                if len(vertices[-1]) != 3:
                    raise ValueError("a vertex needs x, y and z")
                continue
            # "f a b c ...", each corner "v", "v/vt", "v//vn" or "v/vt/vn"; negative is relative.
            corners = [int(field.split("/")[0]) for field in fields[1:]]
            if 0 in corners:
                raise ValueError("a face refers to vertex 0 (OBJ counts vertices from 1)")
            corners = [c - 1 if c > 0 else len(vertices) + c for c in corners]
            if any(c < 0 for c in corners):
                raise ValueError("a face refers to a vertex before the first one")
        except ValueError as error:
            raise ValueError(
                f"mesh file {path}, line {number}: {error}: {line.strip()!r}"
            ) from None
        triangles.extend(
            (corners[0], corners[k], corners[k + 1]) for k in range(1, len(corners) - 1)
        )
    if triangles and max(map(max, triangles)) >= len(vertices):
        raise ValueError(f"mesh file {path} has a face referring to a vertex it does not define")
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, dtype=np.float64).reshape(-1, 3)),
        o3d.utility.Vector3iVector(np.asarray(triangles, dtype=np.int32).reshape(-1, 3)),
    )


# --- surface samples -------------------------------------------------------------------------


def _resolve(mesh: ObjectMesh | str) -> ObjectMesh:
    return get_object(mesh) if isinstance(mesh, str) else mesh


def surface_samples(
    mesh: ObjectMesh | str,
    count: int = DEFAULT_SAMPLE_COUNT,
    seed: int = DEFAULT_SAMPLE_SEED,
    *,
    interior_tolerance: float = DEFAULT_INTERIOR_TOLERANCE,
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points (N, 3) uniformly distributed over the mesh's exposed surface and their
    outward face normals (N, 3); the same for the same mesh, count and seed (cached, read-only
    arrays).

    Area-weighted: a face is drawn with probability proportional to its area, then a uniform
    point in it. Samples on one part that lie deeper than ``interior_tolerance`` inside
    another closed part are hidden by the union and rejected (each closed part is tested with
    its own inside/outside query, which stays exact although parts overlap); draws continue
    from the same random stream until ``count`` samples are kept, so the result is uniform
    over the union's surface.
    """
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"count must be a positive integer, got {count!r}")
    return _surface_samples(_resolve(mesh), int(count), int(seed), float(interior_tolerance))


@lru_cache(maxsize=OBSERVABLE_CACHE_SIZE)
def _surface_samples(
    mesh: ObjectMesh, count: int, seed: int, interior_tolerance: float
) -> tuple[np.ndarray, np.ndarray]:
    if mesh.part_ids.max() == 0 or _SOURCE_DIGEST is None:
        points, normals = _draw_surface_samples(mesh, count, seed, interior_tolerance)
    else:
        # Through the disk cache: a mesh of several parts needs open3d's inside/outside
        # queries, and importing open3d costs a process seconds that steps never need.
        key = _mesh_cache_key(mesh, count, seed, interior_tolerance)
        stored = load_array("surface", key, (count, 6), np.float64)
        if stored is None:
            points, normals = _draw_surface_samples(mesh, count, seed, interior_tolerance)
            store_array("surface", key, np.hstack([points, normals]))
        else:
            points, normals = stored[:, :3].copy(), stored[:, 3:].copy()
    points.setflags(write=False)
    normals.setflags(write=False)
    return points, normals


def _mesh_cache_key(mesh: ObjectMesh, *inputs) -> str:
    """The disk-cache key of a result computed from ``mesh`` and ``inputs`` by this module's
    code with these numpy and open3d versions."""
    return cache_key(
        _SOURCE_DIGEST, np.__version__, open3d_version(), mesh.vertices, mesh.faces, *inputs
    )


def _draw_surface_samples(
    mesh: ObjectMesh, count: int, seed: int, interior_tolerance: float
) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    cumulative = np.cumsum(mesh.face_areas)
    if cumulative[-1] <= 0:
        raise ValueError(f"{mesh.name}: the mesh has no surface area")
    containers = _closed_part_scenes(mesh)
    points, normals, kept, drawn = [], [], 0, 0
    batch = count
    while kept < count:
        face = np.searchsorted(cumulative, rng.random(batch) * cumulative[-1], side="right")
        face = np.minimum(face, len(cumulative) - 1)
        u, v = rng.random((2, batch))
        fold = u + v > 1.0  # reflect the unit square's far half into the triangle
        u, v = np.where(fold, 1.0 - u, u), np.where(fold, 1.0 - v, v)
        a, b, c = (mesh.vertices[mesh.faces[face, i]] for i in range(3))
        p = a + u[:, None] * (b - a) + v[:, None] * (c - a)
        exposed = _exposed(p, mesh.part_ids[face], containers, interior_tolerance)
        points.append(p[exposed])
        normals.append(mesh.face_normals[face[exposed]])
        kept += int(exposed.sum())
        drawn += batch
        if kept < MIN_EXPOSED_FRACTION * drawn:
            raise ValueError(f"{mesh.name}: almost all of the surface lies inside other parts")
        # Size the next batch from the observed acceptance rate, with margin.
        batch = int(np.ceil((count - kept) * drawn / max(kept, 1) * 1.1)) + 16
    return np.concatenate(points)[:count], np.concatenate(normals)[:count]


def _closed_part_scenes(mesh: ObjectMesh) -> list[tuple[int, o3d.t.geometry.RaycastingScene]]:
    """One inside/outside query scene per closed part, when there is more than one part
    (an open part has no inside, so it hides nothing)."""
    labels = mesh.part_ids
    if labels.max() == 0:
        return []
    if labels.max() + 1 > MAX_HIDING_PARTS:
        warnings.warn(
            f"{mesh.name}: {labels.max() + 1} separate parts (> {MAX_HIDING_PARTS}); surface "
            "samples inside other parts are not rejected",
            stacklevel=4,
        )
        return []
    scenes = []
    for part in np.unique(labels):
        faces = mesh.faces[labels == part]
        if not _is_closed(faces):
            continue
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)),
            o3d.core.Tensor(faces.astype(np.uint32)),
        )
        scenes.append((int(part), scene))
    return scenes


def _exposed(points: np.ndarray, parts: np.ndarray, containers, tolerance: float) -> np.ndarray:
    """Which points (on faces of ``parts``) lie outside every other closed part."""
    exposed = np.ones(len(points), dtype=bool)
    if not containers:
        return exposed
    query = o3d.core.Tensor(points.astype(np.float32))
    for part, scene in containers:
        distance = scene.compute_signed_distance(query, nsamples=DEFAULT_INSIDE_VOTES).numpy()
        exposed &= (parts == part) | (distance >= -tolerance)
    return exposed


# --- observability ---------------------------------------------------------------------------


def default_observation_viewpoints(
    radius: float = DEFAULT_OBSERVATION_RADIUS,
    *,
    center: Sequence[float] = (0.0, 0.0, 0.0),
    elevations_deg: Sequence[float] = DEFAULT_OBSERVATION_ELEVATIONS_DEG,
    azimuth_count: int = DEFAULT_OBSERVATION_AZIMUTH_COUNT,
) -> np.ndarray:
    """Camera positions (K, 3) on the upper hemisphere of ``radius`` around ``center``
    (object frame), independent of any arm: ``azimuth_count`` azimuths on every elevation
    ring (alternate rings offset by half a step, for even coverage) and a single view from
    straight above when 90 deg is listed."""
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be positive, got {radius!r}")
    if azimuth_count < 1:
        raise ValueError(f"azimuth_count must be >= 1, got {azimuth_count!r}")
    elevations = np.radians(np.asarray(elevations_deg, dtype=float))
    overhead = np.isclose(elevations, np.pi / 2)
    rings = elevations[~overhead]
    stagger = (np.arange(len(rings)) % 2)[:, None] * 0.5
    azimuth = 2.0 * np.pi * (np.arange(azimuth_count)[None, :] + stagger) / azimuth_count
    elevation = np.broadcast_to(rings[:, None], azimuth.shape)
    directions = np.stack(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ],
        axis=-1,
    ).reshape(-1, 3)
    if overhead.any():
        directions = np.concatenate([directions, [[0.0, 0.0, 1.0]]])
    return np.asarray(center, dtype=float) + radius * directions


def observation_viewpoints(
    radii: Sequence[float], *, center: Sequence[float], elevations_deg: Sequence[float]
) -> np.ndarray:
    """:func:`default_observation_viewpoints` on each sphere of ``radii``, concatenated."""
    return np.concatenate(
        [
            default_observation_viewpoints(radius, center=center, elevations_deg=elevations_deg)
            for radius in radii
        ]
    )


def _table_box(half_size: float, thickness: float) -> Part:
    return _box((2 * half_size, 2 * half_size, thickness), (0.0, 0.0, -thickness / 2))


def observable_mask(
    mesh: ObjectMesh | str,
    points: np.ndarray,
    normals: np.ndarray,
    viewpoints: np.ndarray,
    *,
    table: bool = True,
    hit_tolerance: float = DEFAULT_HIT_TOLERANCE,
    min_cosine: float = DEFAULT_MIN_COSINE,
    table_half_size: float = DEFAULT_TABLE_HALF_SIZE,
    table_thickness: float = DEFAULT_TABLE_THICKNESS,
    views_per_cast: int | None = DEFAULT_VIEWS_PER_CAST,
) -> np.ndarray:
    """Which surface samples (N,) at least one viewpoint sees (object frame throughout).

    Viewpoint ``e`` sees sample ``p`` (normal ``n``) when ``p`` faces it,
    ``n . (e - p) / |e - p| > min_cosine``, and the ray from ``e`` towards ``p`` hits nothing
    more than ``hit_tolerance`` before ``p``. With ``table`` the table (a thick box whose top
    is z = 0) occludes too, so samples under the object and views from below see nothing of
    the object's bottom. Field of view and depth range are ignored: this is what *some*
    camera at that position could see.

    The views are cast ``views_per_cast`` at a time (``None``: all at once), each group only
    towards the samples no earlier group saw: most samples are seen from the first views, so
    this casts several times fewer rays for the same mask (each ray's hit does not depend on
    the others in its batch).
    """
    mesh = _resolve(mesh)
    points = np.asarray(points, dtype=float)
    normals = np.asarray(normals, dtype=float)
    eyes = np.asarray(viewpoints, dtype=float).reshape(-1, 3)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(
            f"points and normals must both be (N, 3), got {points.shape} and {normals.shape}"
        )
    if len(eyes) == 0 or not np.isfinite(eyes).all():
        raise ValueError("viewpoints must be a non-empty finite (K, 3) array")
    if views_per_cast is not None and (
        isinstance(views_per_cast, bool)
        or not isinstance(views_per_cast, (int, np.integer))
        or views_per_cast < 1
    ):
        raise ValueError(
            f"views_per_cast must be a positive integer or None, got {views_per_cast!r}"
        )
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh.faces.astype(np.uint32)),
    )
    if table:
        # A scene of one mesh works in a forked child; adding a second waits forever there.
        check_open3d_not_forked("observable_mask()")
        table_vertices, table_faces = _table_box(table_half_size, table_thickness)
        scene.add_triangles(
            o3d.core.Tensor(table_vertices.astype(np.float32)),
            o3d.core.Tensor(table_faces.astype(np.uint32)),
        )
    visible = np.zeros(len(points), dtype=bool)
    group = len(eyes) if views_per_cast is None else views_per_cast
    for first in range(0, len(eyes), group):
        group_eyes = eyes[first : first + group]
        unseen = np.flatnonzero(~visible)
        # Facing test on every (view, unseen sample) pair, then rays only for the facing ones.
        offset = points[None, unseen, :] - group_eyes[:, None, :]  # (K, n, 3), eye -> point
        distance = np.linalg.norm(offset, axis=-1)
        cosine = -np.einsum("knj,nj->kn", offset, normals[unseen]) / np.maximum(distance, 1e-12)
        view_index, pair_index = np.nonzero(cosine > min_cosine)
        if len(pair_index) == 0:
            continue
        pair_distance = distance[view_index, pair_index]
        direction = offset[view_index, pair_index] / pair_distance[:, None]
        rays = np.concatenate([group_eyes[view_index], direction], axis=1).astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        reached = t_hit >= pair_distance - hit_tolerance  # a miss (inf): nothing in the way
        visible[unseen[pair_index[reached]]] = True
    return visible


class ObservableSamples(NamedTuple):
    """Ground-truth surface samples of an object at one scale (object frame, read-only)."""

    points: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3)
    observable: np.ndarray  # (N,) bool: seen by at least one observation viewpoint


def observable_samples(
    mesh: ObjectMesh | str,
    scale: float = 1.0,
    count: int = DEFAULT_SAMPLE_COUNT,
    seed: int = DEFAULT_SAMPLE_SEED,
    *,
    radii: Sequence[float] = DEFAULT_OBSERVATION_RADII,
    elevations_deg: Sequence[float] = DEFAULT_OBSERVATION_ELEVATIONS_DEG,
    table: bool = True,
) -> ObservableSamples:
    """Samples of ``mesh`` (a library name or an :class:`ObjectMesh`, given at scale 1)
    uniformly scaled by ``scale``, their normals, and which of them some viewpoint on spheres
    of ``radii`` around the scaled object's middle (its bounding box's centre), at
    ``elevations_deg``, sees (:func:`default_observation_viewpoints`,
    :func:`observable_mask`). Cached in memory per (mesh content, scale, count, seed, radii,
    elevations, table), and on disk: the first call for a key costs a sampling and a ray
    cast, repeats are free.

    The samples at any scale are the scale-1 samples times ``scale`` (same seed, same
    points on the surface), so samples of different scales correspond one to one.
    """
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale!r}")
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"count must be a positive integer, got {count!r}")
    radii = tuple(sorted({float(radius) for radius in radii}))  # one cache key per set
    elevations = tuple(sorted({float(elevation) for elevation in elevations_deg}))
    if not radii or not elevations:
        raise ValueError(f"radii and elevations_deg must be non-empty, got {radii}, {elevations}")
    return _observable_samples(
        _resolve(mesh), float(scale), int(count), int(seed), radii, elevations, bool(table)
    )


@lru_cache(maxsize=OBSERVABLE_CACHE_SIZE)
def _observable_samples(
    mesh: ObjectMesh,
    scale: float,
    count: int,
    seed: int,
    radii: tuple[float, ...],
    elevations_deg: tuple[float, ...],
    table: bool,
) -> ObservableSamples:
    scaled = mesh.scaled(scale)
    middle = scaled.middle
    reach = float(np.linalg.norm(scaled.vertices - middle, axis=1).max())
    if min(radii) <= reach:
        raise ValueError(
            f"observation radius {min(radii)} m must exceed the scaled object's reach "
            f"{reach:.3f} m from its middle"
        )
    points, normals = _surface_samples(mesh, count, seed, DEFAULT_INTERIOR_TOLERANCE)
    scaled_points = points * scale
    viewpoints = observation_viewpoints(radii, center=middle, elevations_deg=elevations_deg)
    mask = _stored_observable_mask(scaled, scaled_points, normals, viewpoints, table)
    for array in (scaled_points, mask):
        array.setflags(write=False)
    return ObservableSamples(scaled_points, normals, mask)


def clear_memory_caches() -> None:
    """Forget the surface and observable samples cached in this process's memory (not on
    disk): the next call computes them, or reads them from the disk cache, as a new process
    would. For tests and benchmarks that measure the cold path."""
    _surface_samples.cache_clear()
    _observable_samples.cache_clear()


def _stored_observable_mask(
    mesh: ObjectMesh, points: np.ndarray, normals: np.ndarray, viewpoints: np.ndarray, table: bool
) -> np.ndarray:
    """:func:`observable_mask` with its defaults, through the disk cache: the ray cast is
    most of the time it takes to make a ViewPlanning-v0 env, and every process repeated it."""
    if _SOURCE_DIGEST is None:
        return observable_mask(mesh, points, normals, viewpoints, table=table)
    key = _mesh_cache_key(mesh, points, normals, viewpoints, table)
    mask = load_array("observable", key, (len(points),), bool)
    if mask is None:
        mask = observable_mask(mesh, points, normals, viewpoints, table=table)
        store_array("observable", key, mask)
    return mask
