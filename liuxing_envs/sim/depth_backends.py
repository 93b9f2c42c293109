"""The depth camera's backends: how a :class:`~liuxing_envs.sim.camera.DepthCamera` turns a
MuJoCo state into a depth image, and the ray-cast backend's shortcuts.

* :class:`GLBackend`: MuJoCo's offscreen OpenGL renderer, reading the depth buffer.
* :class:`RaycastBackend`: one :func:`mujoco.mj_multiRay` ray per pixel centre; in a
  tabletop scene the rays that can only land on the table top are answered in numpy
  (:class:`TableShortcut`, with :class:`PixelGrid` and :class:`ViewFrustum` bounding which
  rays and obstacles to test), bit for bit the image casting every ray gives.
* :class:`EmbreeBackend`: the ray-cast backend with mesh geoms handed to Embree.
* :class:`CompiledBackend`: the ray-cast backend's image, bit for bit, from a compiled
  (numba) kernel with MuJoCo's arithmetic (:mod:`liuxing_envs.kernels.depth`).

A :class:`~liuxing_envs.sim.camera.DepthCamera` makes and owns its backend
(:attr:`~liuxing_envs.sim.camera.DepthCamera.active_backend`); the classes are public so that
tests and benchmarks can look into their workings.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple, Protocol

import mujoco
import numpy as np

from liuxing_envs import kernels
from liuxing_envs.forking import check_opengl_not_forked
from liuxing_envs.opengl import new_renderer
from liuxing_envs.perception.pointcloud import camera_rays

if TYPE_CHECKING:
    from liuxing_envs.sim.camera import CameraIntrinsics

__all__ = [
    "BOX_CORNERS",
    "CompiledBackend",
    "DepthBackend",
    "EmbreeBackend",
    "GLBackend",
    "PixelGrid",
    "RaycastBackend",
    "SceneCache",
    "TableShortcut",
    "ViewFrustum",
]

# Tessellation of spheres, cylinders and capsules in the GL depth renderer's context.
_GL_MIN_SLICES = 48
_GL_MIN_STACKS = 24

# Extra length allowed on a ray beyond the longest one that can still be in range, so the
# cut-off never clips a return that the range crop would keep.
_RAY_CUTOFF_MARGIN = 1.01

# The ray-cast backend's table shortcut (see TableShortcut) answers an image only when this
# many obstacles or fewer are in the field of view: each costs every ray a sphere test. In
# ViewPlanning-v0's views that show arm links, 2-7 are (the object and the links).
_SHORTCUT_MAX_OBSTACLES = 8
# Scenes with more obstacles than this get no shortcut: the per-image frustum test would not
# pay. InstrumentGrasp-v0's (29-34: tray walls, instrument parts, gripper) keep 10-22 in view.
_SHORTCUT_MAX_SCENE_OBSTACLES = 20
# Safety margins of the shortcut's tests, in metres: rays this close to an obstacle's
# bounding sphere or to the table's edge are cast rather than solved in numpy.
_SHORTCUT_SPHERE_MARGIN = 1e-6
_SHORTCUT_EDGE_MARGIN = 1e-9
# A geom this close to the field of view counts as in it: one touching the optical centre
# (a housing face through it) lands a rounding error either side of the image plane.
_VIEW_MARGIN = 1e-6
# The pixel window of an obstacle's box (see PixelGrid.window) is widened by this many
# pixels, far more than the rounding of its corners' projections, and is only taken when every
# corner lies this many metres in front of the camera (closer, it can reach any pixel).
_WINDOW_MARGIN_PX = 1e-3
_WINDOW_MIN_DEPTH = 1e-3
#: The eight corners of a box (half-size 1) in its own frame.
BOX_CORNERS = np.array(
    [[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)], dtype=np.float64
)


class ViewFrustum:
    """What a camera's pixel rays can reach: the planes through the optical centre that bound
    every pixel ray (the four image edges, and the image plane itself: rays only go
    forward), and the ray length beyond which nothing returns a depth in range."""

    def __init__(self, intrinsics: CameraIntrinsics) -> None:
        self.ray_length = _ray_cutoff(intrinsics)
        tan_y = math.tan(math.radians(intrinsics.fovy_deg) / 2)
        tan_x = tan_y * intrinsics.width / intrinsics.height
        # Unit outward normals in the camera frame (+z is back).
        planes = np.array(
            [[1, 0, tan_x], [-1, 0, tan_x], [0, 1, tan_y], [0, -1, tan_y], [0, 0, 1]], float
        )
        #: Unit outward normals in the camera frame of the planes bounding every pixel ray.
        self.planes = planes / np.linalg.norm(planes, axis=1, keepdims=True)
        #: Whether :meth:`may_reach` runs the compiled kernel (:mod:`liuxing_envs.kernels.frustum`,
        #: default where numba is installed) or the numpy code; both are conservative.
        self.compiled = kernels.available()

    def may_reach(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        geom_ids: np.ndarray,
        position: np.ndarray,
        rotation: np.ndarray,
        grow: float = 0.0,
    ) -> np.ndarray:
        """Per geom: False when it lies out of reach of every ray from a camera at
        ``position`` with axes ``rotation`` (columns); conservative, as
        :meth:`DepthCamera.may_see_geoms` documents. ``grow`` (m) widens every geom's box
        and bounding sphere: a geom then out of reach has no point within ``grow`` of it
        that a ray reaches."""
        ids = np.asarray(geom_ids, dtype=np.intp)
        if self.compiled:
            may_reach = kernels.module("frustum").may_reach

            reached = np.empty(ids.size, dtype=bool)
            may_reach(
                ids, data.geom_xpos, data.geom_xmat, model.geom_aabb, model.geom_rbound,
                np.asarray(position, dtype=np.float64), np.asarray(rotation, dtype=np.float64),
                self.planes, self.ray_length, float(grow), _VIEW_MARGIN, reached,
            )  # fmt: skip
            return reached
        offset = data.geom_xpos[ids] - position
        box = model.geom_aabb[ids] + np.repeat([0.0, grow], 3)
        normals = self.planes @ rotation.T  # (5, 3) outward normals in the world
        # Nearest point of each box to each plane (signed, > 0 outside): its centre's offset
        # minus the half-sizes weighted by how far each box axis leans along the normal.
        normals_in_geom = normals @ data.geom_xmat[ids].reshape(-1, 3, 3)  # (geom, plane, xyz)
        nearest = offset @ normals.T + (normals_in_geom @ box[:, :3, None])[..., 0]
        nearest -= (np.abs(normals_in_geom) @ box[:, 3:, None])[..., 0]
        in_range = np.sqrt(np.einsum("ni,ni->n", offset, offset)) - model.geom_rbound[ids] - grow
        return (in_range <= self.ray_length) & (nearest <= _VIEW_MARGIN).all(axis=1)


class DepthBackend(Protocol):
    name: str

    def render(self, data: mujoco.MjData) -> np.ndarray: ...

    def close(self) -> None: ...


def _ray_cutoff(intrinsics: CameraIntrinsics) -> float:
    """Longest ray length worth casting: ``max_depth`` reached on the widest (corner) pixel
    ray, with margin."""
    cos_widest_ray = float(-camera_rays(intrinsics, "unit")[..., 2].max())
    return _RAY_CUTOFF_MARGIN * intrinsics.max_depth / cos_widest_ray


def _group_mask(groups: Sequence[int]) -> np.ndarray:
    mask = np.zeros(mujoco.mjNGROUP, dtype=np.uint8)
    mask[list(groups)] = 1
    return mask


#: Words in the GL_RENDERER string of renderers that run on the CPU.
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "software rasterizer", "swiftshader")


class GLBackend:
    """Depth buffer of MuJoCo's offscreen OpenGL renderer."""

    name = "gl"

    def __init__(
        self,
        model: mujoco.MjModel,
        camera_id: int,
        intrinsics: CameraIntrinsics,
        geom_groups: Sequence[int],
    ) -> None:
        extent = float(model.stat.extent)
        near, far = model.vis.map.znear * extent, model.vis.map.zfar * extent
        if near > intrinsics.min_depth or far < intrinsics.max_depth:
            warnings.warn(
                f"the model's GL clip planes [{near:.4g}, {far:.4g}] m (visual/map znear, zfar "
                f"times the extent) do not cover the depth range [{intrinsics.min_depth}, "
                f"{intrinsics.max_depth}] m; the gl backend will miss returns outside them",
                RuntimeWarning,
                stacklevel=4,
            )
        glob = model.vis.global_
        glob.offwidth = max(int(glob.offwidth), intrinsics.width)
        glob.offheight = max(int(glob.offheight), intrinsics.height)
        # Resolving a multisampled depth buffer keeps one driver-chosen sample per pixel, not
        # necessarily the centre the ray caster uses (on a tilted surface, millimetres off), so
        # this context is made without multisampling. Curved primitives are tessellated at the
        # same moment; finer meshes keep GL within ~0.4 mm of the analytic surface (MuJoCo's
        # default 28 x 16: ~1 mm). These settings are read only while a context is created, so
        # they are borrowed and restored: other renderers on the model keep theirs.
        quality = model.vis.quality
        saved = (int(quality.offsamples), int(quality.numslices), int(quality.numstacks))
        quality.offsamples = 0
        quality.numslices = max(saved[1], _GL_MIN_SLICES)
        quality.numstacks = max(saved[2], _GL_MIN_STACKS)
        try:
            self._renderer: mujoco.Renderer | None = new_renderer(
                model, height=intrinsics.height, width=intrinsics.width
            )
        finally:
            quality.offsamples, quality.numslices, quality.numstacks = saved
        self._renderer.enable_depth_rendering()

        option = mujoco.MjvOption()
        option.geomgroup[:] = _group_mask(geom_groups)
        option.sitegroup[:] = 0
        # Only geoms are in the depth image (the ray-cast backend cannot see anything else).
        option.tendongroup[:] = 0
        option.skingroup[:] = 0
        option.flexgroup[:] = 0
        for flag in (mujoco.mjtVisFlag.mjVIS_RANGEFINDER, mujoco.mjtVisFlag.mjVIS_TENDON):
            option.flags[flag] = 0
        self._option = option

        # Effects that cost time but cannot change the depth buffer.
        flags = self._renderer.scene.flags
        for flag in (
            mujoco.mjtRndFlag.mjRND_SHADOW,
            mujoco.mjtRndFlag.mjRND_REFLECTION,
            mujoco.mjtRndFlag.mjRND_SKYBOX,
            mujoco.mjtRndFlag.mjRND_FOG,
            mujoco.mjtRndFlag.mjRND_HAZE,
        ):
            flags[flag] = 0

        camera = mujoco.MjvCamera()
        camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        camera.fixedcamid = camera_id
        self._camera = camera

    @functools.cached_property
    def renderer_name(self) -> str:
        """The OpenGL renderer's name (``GL_RENDERER``), or "" where it cannot be read."""
        try:
            self._renderer._gl_context.make_current()
            from OpenGL import GL

            return GL.glGetString(GL.GL_RENDERER).decode(errors="replace")
        except Exception:  # a platform without the attribute or PyOpenGL's binding: unknown
            return ""

    @property
    def software(self) -> bool:
        """Whether the renderer runs on the CPU (Mesa's llvmpipe, softpipe or swrast, ...),
        where ray casting is faster at the envs' image sizes."""
        name = self.renderer_name.lower()
        return any(word in name for word in SOFTWARE_RENDERERS)

    def render(self, data: mujoco.MjData) -> np.ndarray:
        assert self._renderer is not None
        check_opengl_not_forked()  # a renderer made before a fork hangs in the child
        self._renderer.update_scene(data, camera=self._camera, scene_option=self._option)
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def _ray_visible(model: mujoco.MjModel, geomgroup: np.ndarray) -> np.ndarray:
    """Per geom: whether ``mj_multiRay`` with this group mask can hit it (a geom in one of
    the groups and not fully transparent)."""
    matid = model.geom_matid
    alpha = model.geom_rgba[:, 3]
    if model.nmat:
        alpha = np.where(matid >= 0, model.mat_rgba[np.maximum(matid, 0), 3], alpha)
    group = np.clip(model.geom_group, 0, mujoco.mjNGROUP - 1)
    return (geomgroup[group] != 0) & (alpha != 0)


def _shortcut_input_views(model: mujoco.MjModel) -> tuple[np.ndarray, ...]:
    """Views of what a :class:`TableShortcut` is made from: what :func:`_ray_visible`
    reads, and where and how large the geoms are. They look into the model's own memory, so
    kept, they show its later changes without the cost of making them again per image."""
    return (
        model.geom_group,
        model.geom_rgba[:, 3],
        model.geom_matid,
        model.mat_rgba[:, 3],
        model.geom_size,
        model.geom_pos,
        model.geom_quat,
        model.body_pos,
        model.body_quat,
    )


def _shortcut_inputs(model: mujoco.MjModel) -> tuple[bytes, ...]:
    """What a :class:`TableShortcut` is made from, to tell when to make it again (a few
    µs): the bytes of :func:`_shortcut_input_views`."""
    return _snapshot(_shortcut_input_views(model))


def _snapshot(views: tuple[np.ndarray, ...]) -> tuple[bytes, ...]:
    return tuple(view.tobytes() for view in views)


class TableShortcut:
    """Pixel rays that can only land on a table top, answered without casting them.

    ``mj_multiRay`` spends about 0.1 µs on every ray before it tests a single geom (the ray's
    direction in spherical coordinates, for its culling), so in a tabletop scene most of a
    64x64 image's cost is rays that simply land on the table. The table is the static,
    axis-aligned box geom with the largest top face; the obstacles are every other geom a ray
    could meet first: the movable ones and the static ones rising above that face. A ray
    from a camera above the face that meets it inside its rectangle, and misses every
    obstacle's bounding box, lands there first. Only the rays that may meet a box are tested
    against it: those in the pixel window its corners project to (:class:`PixelGrid`) when
    the whole box is in front of the camera, else those passing within its bounding sphere.
    An answered ray's distance is computed here with the same floating-point operations as
    MuJoCo's ray-box test, so the image is bit for bit the one ``mj_multiRay`` gives
    (``tests/test_camera.py`` checks this on random views); every other ray is cast. Scenes
    without such a table, with a static plane above it, or with more than
    ``_SHORTCUT_MAX_SCENE_OBSTACLES`` obstacles get ``None`` from :meth:`for_scene`. When
    there are more than ``_SHORTCUT_MAX_OBSTACLES``, as with the arm in the scene, the
    ray-cast backend leaves out those outside each image's field of view
    (:class:`ViewFrustum`): the wrist camera lies inside the bounding spheres of its own
    housing, which is behind the image plane.
    """

    def __init__(
        self, model: mujoco.MjModel, data: mujoco.MjData, table: int, obstacles: np.ndarray
    ) -> None:
        self.position = np.array(data.geom_xpos[table])
        self.half = np.array(model.geom_size[table])
        self.bounding_radius = float(model.geom_rbound[table])
        self.obstacles = obstacles
        radii = model.geom_rbound[obstacles] + _SHORTCUT_SPHERE_MARGIN
        self.radii2 = radii * radii
        # Each obstacle's bounding box in its own frame (centre, half-sizes with margin).
        self.box_centres = model.geom_aabb[obstacles, :3].copy()
        self.box_halves = model.geom_aabb[obstacles, 3:] + _SHORTCUT_SPHERE_MARGIN

    @classmethod
    def for_scene(
        cls, model: mujoco.MjModel, data: mujoco.MjData, seen: np.ndarray
    ) -> TableShortcut | None:
        """The shortcut for this model (static geoms posed in ``data``; ``seen``: the geoms
        rays can hit, from :func:`_ray_visible`), or None."""
        ids = np.arange(model.ngeom)
        static = seen & (model.body_weldid[model.geom_bodyid] == 0)
        identity = (data.geom_xmat == np.eye(3).ravel()).all(axis=1)
        boxes = ids[static & identity & (model.geom_type == mujoco.mjtGeom.mjGEOM_BOX)]
        if boxes.size == 0:
            return None
        # Any such box gives exact images; the one with the largest top answers most rays.
        table = int(boxes[np.argmax(model.geom_size[boxes, 0] * model.geom_size[boxes, 1])])
        top = data.geom_xpos[table, 2] + model.geom_size[table, 2]
        # The highest point of each geom's oriented bounding box (planes: see below).
        z_rows = data.geom_xmat[:, 6:9]
        highest = (
            data.geom_xpos[:, 2]
            + np.einsum("gi,gi->g", z_rows, model.geom_aabb[:, :3])
            + np.einsum("gi,gi->g", np.abs(z_rows), model.geom_aabb[:, 3:])
        )
        planes = static & (model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE)
        if (planes & ~(identity & (data.geom_xpos[:, 2] <= top))).any():
            return None  # a plane tilted or above the table can be met anywhere
        rising = static & ~planes & (highest > top)
        rising[table] = False
        obstacles = ids[(seen & ~static) | rising]
        if (
            obstacles.size > _SHORTCUT_MAX_SCENE_OBSTACLES
            or (model.geom_rbound[obstacles] <= 0).any()
        ):
            return None
        return cls(model, data, table, obstacles)

    def solve(
        self,
        data: mujoco.MjData,
        position: np.ndarray,
        rays: np.ndarray,
        cutoff: float,
        in_view: np.ndarray | None = None,
        *,
        grid: PixelGrid | None = None,
        rotation: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``(dist, to_cast)``: the table distances of the rays it answers (-1 elsewhere) and
        the indices of the rays still to cast; None when the camera is not above the table,
        the table is beyond the cut-off, or more than ``_SHORTCUT_MAX_OBSTACLES`` obstacles
        are in view (then every ray is cast). ``in_view`` (a mask over :attr:`obstacles`)
        leaves out the obstacles no ray can reach. With ``grid`` and the camera's
        ``rotation`` (``rays`` are then the grid's pixel rays in row-major order), only the
        rays in each obstacle's pixel window are tested against it."""
        kept = slice(None) if in_view is None else in_view
        obstacles = self.obstacles[kept]
        if obstacles.size > _SHORTCUT_MAX_OBSTACLES:
            return None
        offset = position - self.position  # MuJoCo's ray in the (unrotated) box frame
        if offset[2] <= self.half[2]:
            return None
        if np.sqrt(offset @ offset) > cutoff + self.bounding_radius:
            return None  # mj_multiRay would leave the table out altogether
        vz = rays[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            dist = (self.half[2] - offset[2]) / vz
        edge_x = np.abs(offset[0] + dist * rays[:, 0])
        edge_y = np.abs(offset[1] + dist * rays[:, 1])
        answered = (vz < -1e-15) & (dist <= cutoff)
        answered &= (edge_x <= self.half[0] - _SHORTCUT_EDGE_MARGIN) & (
            edge_y <= self.half[1] - _SHORTCUT_EDGE_MARGIN
        )
        # Each obstacle in turn takes away the rays that may meet its box; only rays still
        # answered are tested, and with the image's pixel grid only those in the box's window.
        rows = ids = None
        if grid is not None:
            rows = answered.reshape(grid.height, grid.width)
            ids = grid.pixel_ids
        centres, halves, radii2 = self.box_centres[kept], self.box_halves[kept], self.radii2[kept]
        for j, geom in enumerate(obstacles.tolist()):
            frame = data.geom_xmat[geom].reshape(3, 3)  # columns: the geom's axes in the world
            centre = data.geom_xpos[geom]
            window = None
            if grid is not None:
                corners = (centres[j] + BOX_CORNERS * halves[j]) @ frame.T + (centre - position)
                window = grid.window(corners @ rotation)
            if window is None:
                candidates = np.flatnonzero(answered)
            else:
                inside = rows[window]
                candidates = ids[window][inside] if inside.any() else ids[:0, 0]
            if not candidates.size:
                continue
            towards = rays.take(candidates, axis=0)
            if window is None:  # the bounding sphere first: cheap, and rules out most rays
                offset_c = centre - position
                along = towards @ offset_c
                near = float(offset_c @ offset_c) - along * along <= radii2[j]
                candidates, towards = candidates[near], towards[near]
                if not candidates.size:
                    continue
            meets = self.meets_box(frame, centre, centres[j], halves[j], position, towards)
            answered[candidates[meets]] = False
        missed = ~answered
        dist[missed] = -1.0
        return dist, np.flatnonzero(missed)

    @staticmethod
    def meets_box(frame, centre, box_centre, half, position, rays) -> np.ndarray:
        """Per ray: whether it may enter the box (``box_centre``, ``half`` in the frame of a
        geom at ``centre`` with axes ``frame``) ahead of the camera (slab test in the box's
        frame; True also where the arithmetic gives NaN)."""
        origin = ((position - centre) @ frame - box_centre).tolist()
        directions = (rays @ frame).T  # rows: the rays' components along the box axes
        enter = leave = None
        with np.errstate(divide="ignore", invalid="ignore"):
            for axis in range(3):
                inverse = 1.0 / directions[axis]
                low = (-half[axis] - origin[axis]) * inverse
                high = (half[axis] - origin[axis]) * inverse
                near, far = np.minimum(low, high), np.maximum(low, high)
                enter = near if enter is None else np.maximum(enter, near, out=enter)
                leave = far if leave is None else np.minimum(leave, far, out=leave)
        misses = enter > leave
        misses |= leave < 0.0
        return ~misses


class PixelGrid:
    """The pixel rays of an image, as seen by :meth:`TableShortcut.solve`: the pinhole that
    maps a direction in the camera frame to a pixel, to bound which pixels' rays can meet a
    box without testing every ray."""

    #: How far (pixels) a window reaches beyond its corners' projections, and how far (m) in
    #: front of the camera every corner must lie for a window to be taken.
    margin_px = _WINDOW_MARGIN_PX
    min_depth = _WINDOW_MIN_DEPTH

    def __init__(self, intrinsics: CameraIntrinsics) -> None:
        self.height, self.width = intrinsics.height, intrinsics.width
        self.fx, self.fy = intrinsics.fx, intrinsics.fy
        self.cx, self.cy = intrinsics.cx, intrinsics.cy
        #: Row-major ray index of each pixel, (height, width).
        self.pixel_ids = np.arange(self.height * self.width).reshape(self.height, self.width)

    def window(self, corners: np.ndarray) -> tuple[slice, slice] | None:
        """Rows and columns of the pixels whose rays may meet the convex hull of ``corners``
        (camera frame, ``(n, 3)``): a box in front of the camera projects inside the hull of
        its projected corners. None when a corner is not in front (then any pixel may)."""
        depth = -corners[:, 2]
        if not depth.min() > _WINDOW_MIN_DEPTH:
            return None
        # Pixel (i, j) looks along ((j + 0.5 - cx) / fx, -(i + 0.5 - cy) / fy, -1).
        x = corners[:, 0] / depth
        y = corners[:, 1] / depth
        x_min, x_max, y_min, y_max = float(x.min()), float(x.max()), float(y.min()), float(y.max())
        if not math.isfinite(x_min + x_max + y_min + y_max):
            return None
        first_col = math.ceil(self.cx - 0.5 + self.fx * x_min - _WINDOW_MARGIN_PX)
        last_col = math.floor(self.cx - 0.5 + self.fx * x_max + _WINDOW_MARGIN_PX)
        first_row = math.ceil(self.cy - 0.5 - self.fy * y_max - _WINDOW_MARGIN_PX)
        last_row = math.floor(self.cy - 0.5 - self.fy * y_min + _WINDOW_MARGIN_PX)
        return (
            slice(max(first_row, 0), max(last_row + 1, 0)),
            slice(max(first_col, 0), max(last_col + 1, 0)),
        )


class SceneCache(NamedTuple):
    """A ray-cast backend's record of one scene model."""

    views: tuple  #: its _shortcut_input_views, to read the model's current inputs
    inputs: tuple  #: its _shortcut_inputs when this was made
    seen: np.ndarray  #: per geom, whether rays can hit it (_ray_visible)
    shortcut: TableShortcut | None


class RaycastBackend:
    """One :func:`mujoco.mj_multiRay` ray per pixel centre (``"multiray"``; ``"raycast"``
    where numba is missing)."""

    name = "multiray"

    def __init__(
        self,
        model: mujoco.MjModel,
        camera_id: int,
        intrinsics: CameraIntrinsics,
        geom_groups: Sequence[int],
    ) -> None:
        self._model = model
        self._camera_id = camera_id
        self._shape = (intrinsics.height, intrinsics.width)
        unit_rays = camera_rays(intrinsics, "unit").reshape(-1, 3)
        self._rays_cam = np.ascontiguousarray(unit_rays)
        # z-depth = ray length * cos(angle to the optical axis) = length * (-unit_z).
        self._cos_axis = -unit_rays[:, 2].copy()
        self._geomgroup = _group_mask(geom_groups)
        self._nray = unit_rays.shape[0]
        self._geomid = np.empty(self._nray, dtype=np.int32)
        self._dist = np.empty(self._nray, dtype=np.float64)
        self._frustum = ViewFrustum(intrinsics)
        self._cutoff = self._frustum.ray_length
        self._grid = PixelGrid(intrinsics)
        # Per scene model (MjModel hashes by identity).
        self._scenes: dict[mujoco.MjModel, SceneCache] = {}
        #: False: every ray is cast, the reference the table shortcut's images must equal
        #: bit for bit (for tests and benchmarks; the images are the same either way).
        self.use_table_shortcut = True

    @property
    def frustum(self) -> ViewFrustum:
        """What this backend's rays can reach; its ``ray_length`` is the cast's cut-off."""
        return self._frustum

    def render(
        self, data: mujoco.MjData, scene: tuple[mujoco.MjModel, mujoco.MjData] | None = None
    ) -> np.ndarray:
        position = np.array(data.cam_xpos[self._camera_id], dtype=np.float64)
        rotation = data.cam_xmat[self._camera_id].reshape(3, 3)
        rays = self._rays_cam @ rotation.T
        model, data = (self._model, data) if scene is None else scene
        cached = self.scene_for(model, data)
        shortcut = cached.shortcut
        solved = None
        if shortcut is not None and self.use_table_shortcut:
            in_view = None
            if shortcut.obstacles.size > _SHORTCUT_MAX_OBSTACLES:
                in_view = self._frustum.may_reach(
                    model, data, shortcut.obstacles, position, rotation
                )
            solved = shortcut.solve(
                data, position, rays, self._cutoff, in_view, grid=self._grid, rotation=rotation
            )
        if solved is None:
            dist = self._dist
            self._cast(model, data, position, rays, dist, cached.seen)
        else:
            dist, to_cast = solved
            if to_cast.size:
                cast = self._dist[: to_cast.size]
                self._cast(model, data, position, rays[to_cast], cast, cached.seen)
                dist[to_cast] = cast
        depth = np.where(dist >= 0.0, dist * self._cos_axis, 0.0)
        return depth.astype(np.float32).reshape(self._shape)

    def _cast(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        position: np.ndarray,
        rays: np.ndarray,
        dist: np.ndarray,
        seen: np.ndarray,
        exclude_body: int = -1,
    ) -> None:
        """Cast ``rays`` from ``position`` into ``dist`` (-1 where nothing is hit); ``seen``
        (the geoms rays can hit) is for subclasses that cast some geoms themselves. No body
        is excluded by default: the camera housing is behind the optical centre."""
        count = rays.shape[0]
        mujoco.mj_multiRay(
            model,
            data,
            position,
            np.ascontiguousarray(rays).reshape(-1),
            self._geomgroup,
            1,  # flg_static: the table and other world geoms are visible
            exclude_body,
            self._geomid[:count],
            dist,
            None,
            count,
            self._cutoff,
        )

    def scene_for(self, model: mujoco.MjModel, data: mujoco.MjData) -> SceneCache:
        """What the backend keeps of a scene model, made again whenever what it is made from
        changes: a model may show and park geoms by group (ObjectStage does), or move static
        geoms."""
        cached = self._scenes.get(model)
        if cached is None:
            views = _shortcut_input_views(model)
            inputs = _snapshot(views)
        else:
            views, inputs = cached.views, _snapshot(cached.views)
        if cached is None or cached.inputs != inputs:
            seen = _ray_visible(model, self._geomgroup)
            shortcut = TableShortcut.for_scene(model, data, seen)
            cached = self._scenes[model] = SceneCache(views, inputs, seen, shortcut)
        return cached

    def close(self) -> None:
        pass


class EmbreeBackend(RaycastBackend):
    """The ray-cast backend with triangle meshes handed to Embree.

    ``mj_multiRay`` tests a ray against a mesh geom triangle by triangle in the mesh's
    bounding box, which makes an object of a few thousand faces the dearest part of an image.
    Here the rays the table shortcut leaves are cast twice: with ``mj_multiRay`` against
    everything but the body holding the meshes in view (``bodyexclude``), and with open3d's
    :class:`RaycastingScene` (Intel Embree's BVH) against those meshes, each in its own frame;
    a ray keeps the nearer hit. Embree works in float32, so depths differ from the ray-cast
    backend's by a few micrometres (``tests/test_camera.py`` bounds this); which pixels hold a
    return is the same. Images without a mesh in view, or whose meshes are on more than one
    body or share their body with other geoms, are cast as by the ray-cast backend.
    """

    name = "embree"

    def __init__(self, *args) -> None:
        super().__init__(*args)
        import open3d  # ~1 s, so only when this backend is chosen

        self._o3d = open3d
        # Per (model, mesh id): the mesh's RaycastingScene, in the mesh geom's frame.
        self._meshes: dict[tuple[mujoco.MjModel, int], object] = {}
        self._embree_rays = np.empty((self._nray, 6), dtype=np.float32)

    @property
    def meshes_in_embree(self) -> int:
        """How many meshes have been handed to Embree so far (0: every image was cast by
        ``mj_multiRay`` alone)."""
        return len(self._meshes)

    def _cast(self, model: mujoco.MjModel, data: mujoco.MjData, position, rays, dist, seen) -> None:
        meshes = np.flatnonzero((model.geom_type == mujoco.mjtGeom.mjGEOM_MESH) & seen)
        bodies = np.unique(model.geom_bodyid[meshes])
        split = bodies.size == 1 and model.body_geomnum[bodies[0]] == meshes.size
        super()._cast(model, data, position, rays, dist, seen, int(bodies[0]) if split else -1)
        if not split:
            return
        count = rays.shape[0]
        nearest = np.where(dist >= 0.0, dist, np.inf)
        local = self._embree_rays[:count]
        for geom in meshes:
            rotation = data.geom_xmat[geom].reshape(3, 3)
            local[:, :3] = (position - data.geom_xpos[geom]) @ rotation
            local[:, 3:] = rays @ rotation
            hits = self._mesh_scene(model, int(model.geom_dataid[geom])).cast_rays(
                self._o3d.core.Tensor.from_numpy(local), nthreads=1
            )
            np.minimum(nearest, hits["t_hit"].numpy(), out=nearest)
        dist[:] = np.where(nearest <= self._cutoff, nearest, -1.0)

    def _mesh_scene(self, model: mujoco.MjModel, mesh: int):
        key = (model, mesh)
        if key not in self._meshes:
            o3d = self._o3d
            first, faces = model.mesh_faceadr[mesh], model.mesh_facenum[mesh]
            start, count = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                o3d.core.Tensor(model.mesh_vert[start : start + count].astype(np.float32)),
                o3d.core.Tensor(model.mesh_face[first : first + faces].astype(np.uint32)),
            )
            self._meshes[key] = scene
        return self._meshes[key]


class _CompiledScene(NamedTuple):
    """What the compiled backend keeps of one scene model."""

    inputs: tuple  #: the SceneCache.inputs it was made from
    geoms: np.ndarray | None  #: the geoms rays can hit; None: a type the kernel cannot cast
    arrays: tuple  #: the model's arrays the kernel reads, and its mesh tables
    vertex_px: np.ndarray  #: scratch, one row per vertex of the largest mesh


class CompiledBackend(RaycastBackend):
    """The ray-cast backend's image from a compiled kernel, bit for bit.

    :func:`liuxing_envs.kernels.depth.cast_image` casts every pixel ray with MuJoCo's own
    arithmetic for each geom type (``engine_ray.c``) and the culls of ``mj_multiRay`` that
    rounding could make matter (the cut-off, body bounding spheres, a mesh's box and the
    slab tests of its tree), testing each triangle only against the pixels it projects to.
    ``tests/test_depth_kernel.py`` checks its images against casting every ray with
    ``mj_multiRay``. Scenes holding a geom type the kernel does not cast (height fields,
    SDFs) are cast by mj_multiRay. Needs numba; ``"raycast"`` picks it where numba is
    installed, else :class:`RaycastBackend`.
    """

    name = "raycast"

    def __init__(
        self,
        model: mujoco.MjModel,
        camera_id: int,
        intrinsics: CameraIntrinsics,
        geom_groups: Sequence[int],
    ) -> None:
        if not kernels.available():
            raise ImportError(
                "CompiledBackend needs numba, which cannot be imported here; install it (pip "
                "install numba) or use depth_backend='multiray' (the same images, no numba)"
            )
        super().__init__(model, camera_id, intrinsics, geom_groups)
        self._kernel = kernels.module("depth")
        self._intrinsics = (
            float(intrinsics.fx),
            float(intrinsics.fy),
            float(intrinsics.cx),
            float(intrinsics.cy),
            int(intrinsics.height),
            int(intrinsics.width),
        )
        self._image = np.empty(self._nray, dtype=np.float32)
        self._ray_local = np.empty((self._nray, 9), dtype=np.float64)
        self._ready = np.empty(self._nray, dtype=np.uint8)
        self._corners = np.empty((8, 3), dtype=np.float64)
        self._compiled: dict[mujoco.MjModel, _CompiledScene] = {}

    def render(
        self, data: mujoco.MjData, scene: tuple[mujoco.MjModel, mujoco.MjData] | None = None
    ) -> np.ndarray:
        model, scene_data = (self._model, data) if scene is None else scene
        compiled = self._compiled_scene(model, scene_data)
        if compiled.geoms is None:
            return super().render(data, scene)
        position = np.array(data.cam_xpos[self._camera_id], dtype=np.float64)
        rotation = data.cam_xmat[self._camera_id].reshape(3, 3)
        # The same rays, by the same numpy product, as the ray-cast backend casts.
        rays = self._rays_cam @ rotation.T
        fx, fy, cx, cy, height, width = self._intrinsics
        self._kernel.cast_image(
            self._image,
            self._dist,
            position,
            rotation,
            rays,
            self._cos_axis,
            self._cutoff,
            fx,
            fy,
            cx,
            cy,
            height,
            width,
            compiled.geoms,
            *compiled.arrays[:6],
            scene_data.geom_xpos,
            scene_data.geom_xmat,
            compiled.arrays[6],
            compiled.arrays[7],
            scene_data.xipos,
            scene_data.ximat,
            *compiled.arrays[8:],
            self._ray_local,
            self._ready,
            compiled.vertex_px,
            self._corners,
        )
        return self._image.reshape(self._shape).copy()

    def _compiled_scene(self, model: mujoco.MjModel, data: mujoco.MjData) -> _CompiledScene:
        cached = self.scene_for(model, data)
        compiled = self._compiled.get(model)
        if compiled is not None and compiled.inputs is cached.inputs:
            return compiled
        geoms = np.flatnonzero(cached.seen).astype(np.int64)
        types = model.geom_type[geoms]
        supported = np.isin(types, self._kernel.SUPPORTED_TYPES).all()
        face_leaf = bvh_parent = None
        if supported:
            try:
                face_leaf, bvh_parent = self._kernel.mesh_tables(
                    model.nmeshface,
                    model.nbvh,
                    model.mesh_bvhadr,
                    model.mesh_bvhnum,
                    model.mesh_faceadr,
                    model.bvh_child,
                    model.bvh_nodeid,
                )
            except ValueError:
                supported = False
        mesh_vert = model.mesh_vert if model.nmesh else np.zeros((1, 3), np.float32)
        mesh_face = model.mesh_face if model.nmesh else np.zeros((1, 3), np.int32)
        arrays = (
            model.geom_type,
            model.geom_size,
            model.geom_aabb,
            model.geom_rbound,
            model.geom_bodyid,
            model.geom_dataid,
            model.body_bvhadr,
            model.bvh_aabb if model.nbvh else np.zeros((1, 6)),
            model.mesh_vertadr,
            model.mesh_vertnum,
            model.mesh_faceadr,
            model.mesh_facenum,
            mesh_vert,
            mesh_face,
            face_leaf,
            bvh_parent,
        )
        vertices = int(model.mesh_vertnum.max()) if model.nmesh else 1
        compiled = _CompiledScene(
            cached.inputs,
            geoms if supported else None,
            arrays,
            np.empty((max(vertices, 1), 3), dtype=np.float64),
        )
        self._compiled[model] = compiled
        return compiled
