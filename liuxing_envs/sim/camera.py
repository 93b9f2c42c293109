"""A simulated depth camera (RealSense D435-like) on a MuJoCo camera, with optional noise.

Interchangeable backends produce the same depth image:

* ``"gl"``: MuJoCo's OpenGL renderer (:class:`mujoco.Renderer`) reading the depth buffer.
  Needs an OpenGL context; on a headless machine set ``MUJOCO_GL=egl`` (or ``osmesa``)
  *before* ``mujoco`` is first imported.
* ``"raycast"``: one ray per pixel centre, intersected with MuJoCo's own arithmetic: the
  image of :func:`mujoco.mj_multiRay`, bit for bit. No GL needed; geoms are intersected
  analytically (GL draws curved primitives as tessellated meshes, so the two can differ by a
  fraction of a millimetre on spheres and cylinders). Cast by a compiled kernel where numba
  is installed (:class:`~liuxing_envs.sim.depth_backends.CompiledBackend`, several times
  as fast), else as ``"multiray"``.
* ``"multiray"``: the same image from :func:`mujoco.mj_multiRay` itself, with no numba; in a
  tabletop scene, rays that can only land on the table top are solved in numpy with MuJoCo's
  arithmetic (:class:`~liuxing_envs.sim.depth_backends.TableShortcut`; the image is
  unchanged, bit for bit).
* ``"embree"``: the ray-cast backend with mesh geoms intersected by Embree (open3d's
  ``RaycastingScene``) in float32 (:class:`~liuxing_envs.sim.depth_backends.EmbreeBackend`):
  the same pixels hold returns, depths agree to a few micrometres, and a view of a mesh
  object costs a fraction.

All see the geoms in :data:`DEPTH_GEOM_GROUPS` and nothing else (no sites, tendons, ...). The
backends themselves live in :mod:`liuxing_envs.sim.depth_backends`.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from liuxing_envs import kernels
from liuxing_envs.perception.pointcloud import (
    camera_rays,
    check_depth,
    depth_to_camera_points,
    transform_points,
)
from liuxing_envs.sim.depth_backends import (
    BOX_CORNERS,
    CompiledBackend,
    DepthBackend,
    EmbreeBackend,
    GLBackend,
    PixelGrid,
    RaycastBackend,
    ViewFrustum,
)
from liuxing_envs.sim.scene import WRIST_CAMERA
from liuxing_envs.validation import is_number

__all__ = [
    "BACKENDS",
    "DEFAULT_BACKEND",
    "DEFAULT_INTRINSICS",
    "DEPTH_GEOM_GROUPS",
    "RAY_CAST_BACKENDS",
    "REALSENSE_D435_DEPTH",
    "CameraIntrinsics",
    "DepthCamera",
    "DepthNoise",
    "crop_depth_range",
    "grazing_mask",
]

# --- defaults --------------------------------------------------------------------------------

DEFAULT_WIDTH = 64
DEFAULT_HEIGHT = 64
#: Vertical field of view of the RealSense D435 depth stream, degrees.
DEFAULT_FOVY_DEG = 58.0
#: The D435's usable depth range in metres (minimum z at its default resolution).
DEFAULT_MIN_DEPTH = 0.105
DEFAULT_MAX_DEPTH = 3.0

#: Geom groups a depth camera sees, shared by both backends so they agree: 0 (arm, table),
#: 1 and 2 (floor); MuJoCo's own default visibility. Groups 3-5 (collision-only or helper
#: geoms by convention) are invisible to the camera.
DEPTH_GEOM_GROUPS: tuple[int, ...] = (0, 1, 2)

BACKENDS: tuple[str, ...] = ("auto", "gl", "raycast", "multiray", "embree")
#: The backends that cast rays, which can cast them into a stand-in scene (``render(scene=)``).
RAY_CAST_BACKENDS: tuple[str, ...] = ("raycast", "multiray", "embree")
DEFAULT_BACKEND = "auto"

# RealSense-like noise preset. Stereo depth error grows with z^2: sigma_z = z^2 * e / (f * b)
# with subpixel error e ~ 0.08 px, f ~ 447 px (848 px wide, 87 deg) and baseline b = 50 mm,
# i.e. ~0.0036 m at 1 m; a small floor stands for the residual error at close range.
REALSENSE_SIGMA_BASE = 0.0005
REALSENSE_SIGMA_QUADRATIC = 0.0031
#: The D435's default depth unit (z16 stream in millimetres).
REALSENSE_QUANTIZATION = 0.001
#: Active stereo loses the projected pattern on surfaces seen this obliquely.
REALSENSE_GRAZING_DROPOUT_DEG = 75.0
REALSENSE_DROPOUT_PROB = 0.01


# --- intrinsics ------------------------------------------------------------------------------


def _is_int(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


@dataclass(frozen=True, kw_only=True)
class CameraIntrinsics:
    """Pinhole intrinsics and valid depth range of a depth camera (square pixels).

    Follows OpenCV: pixel (row i, column j) has its centre at (u, v) = (j + 0.5, i + 0.5),
    ``fy = (height / 2) / tan(fovy / 2)``, ``fx = fy``, ``(cx, cy) = (width / 2, height / 2)``.

    Parameters
    ----------
    width, height
        Image size in pixels.
    fovy_deg
        Full vertical field of view in degrees (MuJoCo's camera ``fovy``).
    min_depth, max_depth
        Valid z-depth range in metres; returns outside it read 0 (no data).
    """

    width: int = DEFAULT_WIDTH
    height: int = DEFAULT_HEIGHT
    fovy_deg: float = DEFAULT_FOVY_DEG
    min_depth: float = DEFAULT_MIN_DEPTH
    max_depth: float = DEFAULT_MAX_DEPTH

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if not _is_int(value) or value < 1:
                raise ValueError(
                    f"CameraIntrinsics.{name} must be an integer >= 1 (pixels), got {value!r}"
                )
        if not (math.isfinite(self.fovy_deg) and 0.0 < self.fovy_deg < 180.0):
            raise ValueError(
                "CameraIntrinsics.fovy_deg must be in the open interval (0, 180) degrees, "
                f"got {self.fovy_deg!r}"
            )
        if not (math.isfinite(self.min_depth) and self.min_depth > 0.0):
            raise ValueError(
                f"CameraIntrinsics.min_depth must be a finite number > 0 (metres), "
                f"got {self.min_depth!r}"
            )
        if not (math.isfinite(self.max_depth) and self.max_depth > self.min_depth):
            raise ValueError(
                f"CameraIntrinsics.max_depth must be finite and > min_depth "
                f"({self.min_depth} m), got {self.max_depth!r}"
            )

    @property
    def fy(self) -> float:
        """Vertical focal length in pixels."""
        return (self.height / 2.0) / math.tan(math.radians(self.fovy_deg) / 2.0)

    @property
    def fx(self) -> float:
        """Horizontal focal length in pixels (square pixels: equal to ``fy``)."""
        return self.fy

    @property
    def cx(self) -> float:
        """Principal point, column coordinate (pixel centres at integer + 0.5)."""
        return self.width / 2.0

    @property
    def cy(self) -> float:
        """Principal point, row coordinate (pixel centres at integer + 0.5)."""
        return self.height / 2.0

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K (OpenCV convention: x right, y down, z forward)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fovx_deg(self) -> float:
        """Full horizontal field of view in degrees."""
        return math.degrees(2.0 * math.atan(self.width / (2.0 * self.fx)))


#: The D435's native depth stream (848 x 480); its horizontal FOV comes out ~89 deg (spec 87).
REALSENSE_D435_DEPTH = CameraIntrinsics(
    width=848,
    height=480,
    fovy_deg=DEFAULT_FOVY_DEG,
    min_depth=DEFAULT_MIN_DEPTH,
    max_depth=DEFAULT_MAX_DEPTH,
)
DEFAULT_INTRINSICS = CameraIntrinsics()


def crop_depth_range(depth: np.ndarray, min_depth: float, max_depth: float) -> np.ndarray:
    """Set pixels outside ``[min_depth, max_depth]`` (or not finite) to 0, in place."""
    outside = ~((depth >= min_depth) & (depth <= max_depth))
    depth[outside] = 0.0
    return depth


# --- noise -----------------------------------------------------------------------------------


def _one_sided_tangent(
    points: tuple[np.ndarray, np.ndarray, np.ndarray], valid: np.ndarray, axis: int
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """Per-pixel tangent (x, y, z components, each ``(H, W)``) along an image axis, and the
    ``(H, W)`` mask of pixels that have one.

    Of the forward and backward differences, the one with the smaller depth jump is taken so
    that a pixel next to a silhouette uses its own surface, not the one behind it.
    """
    if axis == 0:
        tangent, has = _one_sided_tangent(tuple(c.T for c in points), valid.T, 1)
        return tuple(c.T for c in tangent), has.T
    height, width = valid.shape
    if width < 2:
        zeros = np.zeros((height, width))
        return (zeros, zeros, zeros), np.zeros((height, width), dtype=bool)
    pair_valid = valid[:, 1:] & valid[:, :-1]
    jump_fwd = np.full((height, width), np.inf)
    jump_bwd = np.full((height, width), np.inf)
    pair_jump = np.where(pair_valid, np.abs(points[2][:, 1:] - points[2][:, :-1]), np.inf)
    jump_fwd[:, :-1] = pair_jump
    jump_bwd[:, 1:] = pair_jump
    use_fwd = jump_fwd <= jump_bwd
    tangent = []
    for component in points:
        diff = component[:, 1:] - component[:, :-1]
        fwd = np.zeros((height, width))
        fwd[:, :-1] = diff
        bwd = np.zeros((height, width))
        bwd[:, 1:] = diff
        tangent.append(np.where(use_fwd, fwd, bwd))
    return (tangent[0], tangent[1], tangent[2]), np.isfinite(np.minimum(jump_fwd, jump_bwd))


def grazing_mask(
    depth: np.ndarray, intrinsics: CameraIntrinsics, max_angle_deg: float
) -> np.ndarray:
    """Valid pixels whose surface normal is more than ``max_angle_deg`` from the viewing ray.

    Normals come from finite differences of the depth image itself (so the result does not
    depend on the backend); within one pixel of a silhouette they can mix two surfaces.
    Pixels without a valid neighbour along both image axes are never flagged.
    """
    depth = np.asarray(depth, dtype=np.float64)
    valid = depth > 0
    rays = camera_rays(intrinsics, "z")
    rx, ry, rz = rays[..., 0], rays[..., 1], rays[..., 2]
    points = (rx * depth, ry * depth, rz * depth)
    (ux, uy, uz), has_u = _one_sided_tangent(points, valid, axis=1)
    (vx, vy, vz), has_v = _one_sided_tangent(points, valid, axis=0)
    nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    dot = nx * rx + ny * ry + nz * rz
    n_sq = nx * nx + ny * ny + nz * nz
    r_sq = rx * rx + ry * ry + rz * rz
    cos_max = math.cos(math.radians(max_angle_deg))
    # Squared cosines: no square roots needed.
    steep = dot * dot < (cos_max * cos_max) * n_sq * r_sq
    return valid & has_u & has_v & (n_sq > 0) & steep


@dataclass(frozen=True, kw_only=True)
class DepthNoise:
    """A simple per-pixel depth-sensor noise model; every effect is off by default.

    Applied in this order to the clean z-depth ``z`` (pixels already 0 stay 0):

    1. ``grazing_dropout_deg``: pixels whose surface normal is more than this many degrees
       from the viewing ray read 0 (stereo matching fails on steep surfaces). Normals are
       estimated from the depth image's own finite differences. ``None`` = off.
    2. Gaussian noise ``z + N(0, sigma(z)^2)`` with ``sigma(z) = sigma_base +
       sigma_quadratic * z^2`` (stereo error grows with z^2); ``sigma_base`` in m,
       ``sigma_quadratic`` in 1/m. Noise is i.i.d. per pixel at the simulated resolution.
    3. ``quantization``: depth rounded to multiples of this step in m (0 = none).
    4. ``dropout_prob``: each pixel independently reads 0 with this probability.
    5. Pixels pushed outside the intrinsics' ``[min_depth, max_depth]`` read 0.

    :meth:`realsense_like` gives D435-like values (sigma ~ 3.6 mm at 1 m).
    """

    sigma_base: float = 0.0
    sigma_quadratic: float = 0.0
    quantization: float = 0.0
    grazing_dropout_deg: float | None = None
    dropout_prob: float = 0.0

    def __post_init__(self) -> None:
        for name, unit in (
            ("sigma_base", "m"),
            ("sigma_quadratic", "1/m"),
            ("quantization", "m"),
        ):
            value = getattr(self, name)
            if not (is_number(value) and math.isfinite(value) and value >= 0.0):
                raise ValueError(
                    f"DepthNoise.{name} must be a finite number >= 0 ({unit}), got {value!r}"
                )
        angle = self.grazing_dropout_deg
        if angle is not None and not (is_number(angle) and math.isfinite(angle) and 0 < angle < 90):
            raise ValueError(
                "DepthNoise.grazing_dropout_deg must be None (off) or in the open interval "
                f"(0, 90) degrees, got {angle!r}"
            )
        probability = self.dropout_prob
        if not (is_number(probability) and math.isfinite(probability) and 0 <= probability <= 1):
            raise ValueError(
                f"DepthNoise.dropout_prob must be in [0, 1], got {self.dropout_prob!r}"
            )

    @classmethod
    def realsense_like(cls) -> DepthNoise:
        """D435-like noise: ~0.5 mm + 3.1 mm/m^2 z^2, 1 mm steps, 75 deg grazing, 1 % dropout."""
        return cls(
            sigma_base=REALSENSE_SIGMA_BASE,
            sigma_quadratic=REALSENSE_SIGMA_QUADRATIC,
            quantization=REALSENSE_QUANTIZATION,
            grazing_dropout_deg=REALSENSE_GRAZING_DROPOUT_DEG,
            dropout_prob=REALSENSE_DROPOUT_PROB,
        )

    @classmethod
    def from_setting(cls, value, name: str = "depth_noise") -> DepthNoise | None:
        """A DepthNoise from what an env kwarg may hold: a DepthNoise, None (no noise),
        ``"realsense"`` (:meth:`realsense_like`), or a mapping of its fields, as a YAML
        config or ``--env-kwargs 'depth_noise={sigma_base: 0.001}'`` gives it."""
        if value is None or isinstance(value, cls):
            return value
        if isinstance(value, str) and value == "realsense":
            return cls.realsense_like()
        names = [field.name for field in dataclasses.fields(cls)]
        if isinstance(value, Mapping):
            unknown = [key for key in value if key not in names]
            if unknown:
                raise ValueError(
                    f"{name} has no setting {unknown[0]!r}; its settings are {', '.join(names)}"
                )
            return cls(**value)
        raise ValueError(
            f"{name} must be a DepthNoise, None, 'realsense' or a mapping of "
            f"{', '.join(names)}; got {value!r}"
        )

    @property
    def enabled(self) -> bool:
        """Whether any effect is on (an all-off model leaves images untouched)."""
        return (
            self.sigma_base > 0.0
            or self.sigma_quadratic > 0.0
            or self.quantization > 0.0
            or self.grazing_dropout_deg is not None
            or self.dropout_prob > 0.0
        )

    def sigma(self, depth: np.ndarray) -> np.ndarray:
        """Standard deviation of the Gaussian depth noise at z-depth ``depth`` (metres)."""
        depth = np.asarray(depth, dtype=np.float64)
        return self.sigma_base + self.sigma_quadratic * depth**2

    def apply(
        self, depth: np.ndarray, intrinsics: CameraIntrinsics, rng: np.random.Generator
    ) -> np.ndarray:
        """A noisy float32 copy of the z-depth image ``depth`` (0 = invalid); see the class doc."""
        depth = np.asarray(depth)
        expected = (intrinsics.height, intrinsics.width)
        if depth.shape != expected:
            raise ValueError(f"depth has shape {depth.shape}, expected {expected}")
        if not isinstance(rng, np.random.Generator):
            raise TypeError(
                f"rng must be a numpy.random.Generator, got {type(rng).__name__}; "
                "use numpy.random.default_rng(seed)"
            )
        z = depth.astype(np.float64)
        valid = np.isfinite(z) & (z > 0)
        z[~valid] = 0.0
        if self.grazing_dropout_deg is not None:
            valid &= ~grazing_mask(z, intrinsics, self.grazing_dropout_deg)
        if self.sigma_base > 0.0 or self.sigma_quadratic > 0.0:
            z = z + rng.standard_normal(z.shape) * self.sigma(z)
        if self.quantization > 0.0:
            z = np.round(z / self.quantization) * self.quantization
        if self.dropout_prob > 0.0:
            valid &= rng.random(z.shape) >= self.dropout_prob
        z[~valid] = 0.0
        out = z.astype(np.float32)
        return crop_depth_range(out, intrinsics.min_depth, intrinsics.max_depth)


def _within_geom(
    local: np.ndarray, geom_type: int, size: np.ndarray, aabb: np.ndarray, margin: float
) -> np.ndarray:
    """Per point (in the geom's frame): whether it lies within ``margin`` of the geom."""
    if geom_type == mujoco.mjtGeom.mjGEOM_SPHERE:
        return np.einsum("ni,ni->n", local, local) <= (size[0] + margin) ** 2
    if geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE:
        along = np.clip(local[:, 2], -size[1], size[1])
        radial2 = local[:, 0] ** 2 + local[:, 1] ** 2 + (local[:, 2] - along) ** 2
        return radial2 <= (size[0] + margin) ** 2
    if geom_type == mujoco.mjtGeom.mjGEOM_CYLINDER:
        outside_radius = np.maximum(np.hypot(local[:, 0], local[:, 1]) - size[0], 0.0)
        outside_ends = np.maximum(np.abs(local[:, 2]) - size[1], 0.0)
        return outside_radius**2 + outside_ends**2 <= margin**2
    half = size if geom_type == mujoco.mjtGeom.mjGEOM_BOX else aabb[3:]
    centre = np.zeros(3) if geom_type == mujoco.mjtGeom.mjGEOM_BOX else aabb[:3]
    outside = np.maximum(np.abs(local - centre) - half, 0.0)
    return np.einsum("ni,ni->n", outside, outside) <= margin**2


def _scatter(mask: np.ndarray, values: np.ndarray) -> np.ndarray:
    """An array shaped like ``mask``, ``values`` where it is True, False elsewhere."""
    out = np.zeros(mask.shape, dtype=bool)
    out[mask] = values
    return out


# --- the camera ------------------------------------------------------------------------------


class DepthCamera:
    """A depth camera on a named MuJoCo camera, rendered with OpenGL or by ray casting.

    Depth convention of :meth:`render`: a ``(height, width)`` float32 array of z-depth in
    metres, i.e. the distance along the optical axis (not along the pixel's ray), row 0 at
    the top of the image and column 0 at the left; 0.0 means no valid return (nothing hit, or
    outside ``[intrinsics.min_depth, intrinsics.max_depth]``, or dropped by the noise model).
    The MuJoCo camera looks along its own -z with +y up in the image and +x to the right.

    The camera writes ``intrinsics.fovy_deg`` into ``model.cam_fovy`` (on construction and
    before every render, so several DepthCameras may share one MuJoCo camera) and clears
    ``cam_sensorsize`` (which would override fovy), so MuJoCo's projection is the pinhole of
    ``intrinsics``; the GL backend may also enlarge ``model.vis.global_.offwidth/offheight``.
    A GL renderer is bound to the thread that created it; release it with :meth:`close` or use
    the camera as a context manager.

    Parameters
    ----------
    model
        The compiled model holding the camera.
    camera_name
        Name of the MuJoCo camera (default: the wrist depth camera).
    intrinsics
        Image size, field of view and valid range.
    backend
        ``"gl"``, ``"raycast"``, ``"multiray"``, ``"embree"``, or ``"auto"`` (gl when an
        OpenGL context can be made on a GPU; raycast on a software renderer such as Mesa's
        llvmpipe, and with a warning where no context can be made). :attr:`backend` says which
        one is in use.
    noise
        Optional :class:`DepthNoise`; when it is enabled, :meth:`render` needs an ``rng``.
    geom_groups
        Geom groups the camera sees (every backend).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        camera_name: str = WRIST_CAMERA,
        intrinsics: CameraIntrinsics = DEFAULT_INTRINSICS,
        backend: str = DEFAULT_BACKEND,
        noise: DepthNoise | None = None,
        geom_groups: Sequence[int] = DEPTH_GEOM_GROUPS,
    ) -> None:
        if backend not in BACKENDS:
            raise ValueError(f"unknown depth backend {backend!r}; choose one of {list(BACKENDS)}")
        if not isinstance(intrinsics, CameraIntrinsics):
            raise TypeError(
                f"intrinsics must be a CameraIntrinsics, got {type(intrinsics).__name__}"
            )
        if noise is not None and not isinstance(noise, DepthNoise):
            raise TypeError(f"noise must be a DepthNoise or None, got {type(noise).__name__}")
        groups = tuple(int(g) for g in geom_groups)
        if any(not 0 <= g < mujoco.mjNGROUP for g in groups):
            raise ValueError(f"geom_groups must lie in [0, {mujoco.mjNGROUP}), got {groups}")

        camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera_name)
        if camera_id < 0:
            names = [model.camera(i).name for i in range(model.ncam)]
            raise ValueError(f"no camera named {camera_name!r} in the model; cameras: {names}")
        if model.cam_projection[camera_id] != mujoco.mjtProjection.mjPROJ_PERSPECTIVE:
            raise ValueError(f"camera {camera_name!r} is not a perspective camera")

        self.model = model
        self.camera_name = camera_name
        self.camera_id = int(camera_id)
        self.intrinsics = intrinsics
        self.noise = noise if noise is not None else DepthNoise()
        self.geom_groups = groups

        model.cam_fovy[camera_id] = intrinsics.fovy_deg
        self._frustum = ViewFrustum(intrinsics)
        self._pixel_grid = PixelGrid(intrinsics)
        # A non-zero sensor size makes MuJoCo project with cam_intrinsic instead of fovy.
        model.cam_sensorsize[camera_id] = 0.0

        self._requested_backend = backend
        self._backend: DepthBackend | None = self._make_backend(backend)
        self.backend: str = self._backend.name

    def __getstate__(self) -> dict:
        # A GL context cannot be pickled; the copy makes its own renderer when unpickled.
        state = self.__dict__.copy()
        state["_backend"] = None
        state["_was_open"] = self._backend is not None
        return state

    def __setstate__(self, state: dict) -> None:
        was_open = state.pop("_was_open")
        self.__dict__.update(state)
        if was_open:
            self._backend = self._make_backend(self._requested_backend)
            self.backend = self._backend.name

    def _make_backend(self, backend: str) -> DepthBackend:
        args = (self.model, self.camera_id, self.intrinsics, self.geom_groups)
        if backend == "gl":
            return GLBackend(*args)
        if backend == "raycast":
            return self._exact_ray_caster(args)
        if backend == "multiray":
            return RaycastBackend(*args)
        if backend == "embree":
            return EmbreeBackend(*args)
        try:
            gl = GLBackend(*args)
        except Exception as exc:  # any failure to get a GL context means: no GL here
            warnings.warn(
                f"DepthCamera: OpenGL depth rendering unavailable ({type(exc).__name__}: "
                f"{exc}); using the ray-cast backend",
                RuntimeWarning,
                stacklevel=3,
            )
            return self._exact_ray_caster(args)
        if gl.software:  # OpenGL on the CPU: ray casting is faster and machine-independent
            gl.close()
            return self._exact_ray_caster(args)
        return gl

    @staticmethod
    def _exact_ray_caster(args) -> DepthBackend:
        """``"raycast"``: the compiled kernel where numba is installed, else mj_multiRay (the
        same image)."""
        return CompiledBackend(*args) if kernels.available() else RaycastBackend(*args)

    # -- rendering --

    def render(
        self,
        data: mujoco.MjData,
        rng: np.random.Generator | None = None,
        *,
        scene: tuple[mujoco.MjModel, mujoco.MjData] | None = None,
    ) -> np.ndarray:
        """The ``(height, width)`` float32 z-depth image of ``data``'s state (see class doc).

        Needs ``data``'s kinematics to be current (after :func:`mujoco.mj_forward`,
        :func:`mujoco.mj_step`, or :func:`mujoco.mj_kinematics`); the camera pose is refreshed
        from them here with :func:`mujoco.mj_camlight`. ``rng`` drives the noise model and is
        required when :attr:`noise` is enabled.

        ``scene`` (the ray-casting backends, raycast, multiray and embree, only): a
        ``(model, data)`` pair whose geoms the rays are cast against instead of ``data``'s
        own, for instance a stand-in holding only what :meth:`may_see_geoms` allows to be in
        view (each geom and body of a model costs every ray a bounding test). The camera pose
        is still read from ``data``; the stand-in's geoms must be posed in the same world
        frame.
        """
        backend = self._require_open()
        if self.noise.enabled and rng is None:
            raise ValueError(
                "DepthCamera.render: the noise model is enabled, so an rng is required, e.g. "
                "render(data, rng=numpy.random.default_rng(seed))"
            )
        if scene is not None and backend.name not in RAY_CAST_BACKENDS:
            raise ValueError(
                f"DepthCamera.render: a stand-in scene needs one of the ray-casting backends "
                f"{list(RAY_CAST_BACKENDS)}, not {backend.name!r}"
            )
        # Another DepthCamera on the same MuJoCo camera may have set a different fovy.
        self.model.cam_fovy[self.camera_id] = self.intrinsics.fovy_deg
        mujoco.mj_camlight(self.model, data)
        depth = backend.render(data) if scene is None else backend.render(data, scene)
        crop_depth_range(depth, self.intrinsics.min_depth, self.intrinsics.max_depth)
        if self.noise.enabled:
            depth = self.noise.apply(depth, self.intrinsics, rng)
        return depth

    def may_see_geoms(self, data: mujoco.MjData, geom_ids: np.ndarray) -> np.ndarray:
        """Per geom of :attr:`model`: False when no pixel ray of the current pose can reach
        it, so it cannot show in the image (and a ray caster may leave it out). Conservative:
        True does not promise that the geom is in view.

        A geom is out of reach when its oriented bounding box lies wholly outside one of the
        planes through the optical centre that bound the field of view (the four image
        edges, and the image plane itself: rays only go forward), or when its bounding
        sphere lies beyond the ray-cast backend's ray length.
        """
        position, rotation = self.pose(data)
        return self._frustum.may_reach(self.model, data, geom_ids, position, rotation)

    def pixels_on_geoms(
        self,
        depth: np.ndarray,
        data: mujoco.MjData,
        geom_ids: np.ndarray,
        margin: float,
        *,
        compiled: bool | None = None,
    ) -> np.ndarray:
        """``(height, width)`` bool: the pixels of ``depth`` (rendered at ``data``'s state)
        whose return lies on one of ``geom_ids`` or within ``margin`` metres of it: a robot's
        self-filter, which finds its own links in its camera's image. Spheres, capsules,
        cylinders and boxes are tested exactly, other geoms by their bounding box. Only the
        geoms whose bounding sphere meets the field of view, and only the pixels their box
        projects to, are tested.

        ``compiled`` (default: where numba is installed) runs the kernel of
        :mod:`liuxing_envs.kernels.geom_pixels` on a float32 image, which gives the numpy
        code's answer bit for bit; False runs the numpy code."""
        depth = check_depth(depth, self.intrinsics)
        ids = np.asarray(geom_ids, dtype=np.intp)
        position, rotation = self.pose(data)
        if compiled is None:
            compiled = self._frustum.compiled
        elif compiled and not kernels.available():
            raise ValueError("pixels_on_geoms(compiled=True) needs numba, which is not installed")
        on_geoms = np.zeros(depth.shape, dtype=bool)
        # Most views show none of the robot: a geom whose box, grown by the margin, no ray
        # reaches has no return within the margin of it.
        ids = ids[self._frustum.may_reach(self.model, data, ids, position, rotation, margin)]
        if not ids.size:
            return on_geoms
        if compiled and depth.dtype == np.float32:
            pixels_on_geoms = kernels.module("geom_pixels").pixels_on_geoms

            grid, intrinsics = self._pixel_grid, self.intrinsics
            decided = pixels_on_geoms(
                depth, ids, data.geom_xpos, data.geom_xmat, self.model.geom_type,
                self.model.geom_size, self.model.geom_aabb, self.model.geom_rbound, position,
                rotation, self._frustum.planes, float(margin), float(intrinsics.min_depth),
                float(intrinsics.max_depth), float(grid.fx), float(grid.fy), float(grid.cx),
                float(grid.cy), grid.min_depth, grid.margin_px, on_geoms,
            )  # fmt: skip
            if decided:
                return on_geoms
            on_geoms[:] = False
        return self._pixels_on_numpy(depth, data, ids, position, rotation, margin, on_geoms)

    def _pixels_on_numpy(self, depth, data, ids, position, rotation, margin, on_geoms):
        """:meth:`pixels_on_geoms` of the geoms ``ids`` the view may reach, by numpy."""
        # Then bounding spheres, the test whose survivors the pixels are checked against.
        centres = (data.geom_xpos[ids] - position) @ rotation
        radii = self.model.geom_rbound[ids] + margin
        ahead = -centres[:, 2]
        ids = ids[
            (ahead + radii >= self.intrinsics.min_depth)
            & (ahead - radii <= self.intrinsics.max_depth)
            & (centres @ self._frustum.planes.T <= radii[:, None]).all(axis=1)
        ]
        grid = self._pixel_grid
        rays = camera_rays(self.intrinsics, "z")
        for geom in ids.tolist():
            frame = data.geom_xmat[geom].reshape(3, 3)
            centre = data.geom_xpos[geom]
            box = self.model.geom_aabb[geom]
            corners = (box[:3] + BOX_CORNERS * (box[3:] + margin)) @ frame.T + (centre - position)
            corners = corners @ rotation  # in the camera frame, which looks along -z
            nearest, farthest = -corners[:, 2].max(), -corners[:, 2].min()
            if farthest < self.intrinsics.min_depth:
                continue  # behind or at the optical centre (the wrist's own links)
            window = grid.window(corners) or (slice(None), slice(None))
            window_depth = depth[window]
            valid = (window_depth >= nearest) & (window_depth <= farthest) & (window_depth > 0.0)
            if not valid.any():
                continue
            points = (rays[window][valid] * window_depth[valid, None]) @ rotation.T + position
            local = (points - centre) @ frame  # in the geom's frame
            hits = _within_geom(
                local, int(self.model.geom_type[geom]), self.model.geom_size[geom], box, margin
            )
            on_geoms[window] |= _scatter(valid, hits)
        return on_geoms

    def pose(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """Camera position ``(3,)`` and rotation ``(3, 3)`` (columns = camera axes) in the world.

        Read from ``data.cam_xpos/cam_xmat``, which :func:`mujoco.mj_kinematics` alone does not
        update; they are refreshed here with :func:`mujoco.mj_camlight`, so ``data`` needs
        current kinematics (any of forward, step, or kinematics).
        """
        mujoco.mj_camlight(self.model, data)
        position = np.array(data.cam_xpos[self.camera_id], dtype=np.float64)
        rotation = np.array(data.cam_xmat[self.camera_id], dtype=np.float64).reshape(3, 3)
        return position, rotation

    def points_camera(self, depth: np.ndarray) -> np.ndarray:
        """``(N, 3)`` float64 camera-frame points of the valid pixels of ``depth``."""
        return depth_to_camera_points(depth, self.intrinsics)

    def points_world(self, depth: np.ndarray, data: mujoco.MjData) -> np.ndarray:
        """``(N, 3)`` float64 world-frame points of the valid pixels of ``depth`` (row-major).

        ``data`` must be in the state ``depth`` was rendered from.
        """
        position, rotation = self.pose(data)
        return transform_points(self.points_camera(depth), position, rotation)

    # -- lifetime --

    @property
    def closed(self) -> bool:
        return self._backend is None

    @property
    def active_backend(self) -> DepthBackend:
        """The backend object that renders the images (:attr:`backend` is its name): a
        :class:`~liuxing_envs.sim.depth_backends.GLBackend`, ``RaycastBackend`` or
        ``EmbreeBackend``, for tests and benchmarks that look into its workings.
        RuntimeError once the camera is closed."""
        return self._require_open()

    def _require_open(self) -> DepthBackend:
        if self._backend is None:
            raise RuntimeError("DepthCamera has been closed")
        return self._backend

    def close(self) -> None:
        """Release the renderer (if any). Safe to call more than once."""
        if self._backend is not None:
            self._backend.close()
            self._backend = None

    def __enter__(self) -> DepthCamera:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self.closed else self.backend
        return (
            f"DepthCamera(camera={self.camera_name!r}, backend={state!r}, "
            f"{self.intrinsics.width}x{self.intrinsics.height}, "
            f"fovy={self.intrinsics.fovy_deg} deg, noise={'on' if self.noise.enabled else 'off'})"
        )
