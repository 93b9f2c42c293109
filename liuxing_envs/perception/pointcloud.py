"""Pinhole back-projection of depth images and simple point-cloud helpers (pure numpy).

This is the single implementation of the pinhole model in the package: the simulated depth
camera (:mod:`liuxing_envs.sim.camera`) builds its ray-cast directions from
:func:`camera_rays`, and turns depth images into points with :func:`depth_to_camera_points`.

Camera-frame convention (MuJoCo's): x right, y up, the camera looks along -z. A depth image
holds z-depth (distance along the optical axis, positive in front of the camera) in metres,
row 0 at the top, and 0 where there is no valid return. Pixel (row i, column j) has its centre
at image coordinates (u, v) = (j + 0.5, i + 0.5) (OpenCV convention), so with intrinsics
fx, fy, cx, cy its ray in the camera frame is ((u - cx) / fx, -(v - cy) / fy, -1).
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:  # the camera module imports this one; avoid a runtime cycle
    from liuxing_envs.sim.camera import CameraIntrinsics

RayNormalization = Literal["z", "unit"]

__all__ = [
    "camera_rays",
    "check_depth",
    "crop_points",
    "depth_to_camera_points",
    "transform_points",
]


@functools.lru_cache(maxsize=32)
def _cached_rays(
    width: int, height: int, fx: float, fy: float, cx: float, cy: float, normalize: str
) -> np.ndarray:
    u = np.arange(width, dtype=np.float64) + 0.5
    v = np.arange(height, dtype=np.float64) + 0.5
    x = (u - cx) / fx
    y = -(v - cy) / fy  # image rows grow downwards, camera y points up
    rays = np.empty((height, width, 3), dtype=np.float64)
    rays[..., 0] = x[None, :]
    rays[..., 1] = y[:, None]
    rays[..., 2] = -1.0
    if normalize == "unit":
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    # Shared between callers through the cache, so it must never be modified in place.
    rays.setflags(write=False)
    return rays


@functools.lru_cache(maxsize=32)
def _cached_rays_t(*key) -> np.ndarray:
    # The same rays, coordinate-major (3, height * width) and computed once per intrinsics:
    # depth_to_camera_points scales each coordinate row by the depths, which numpy does
    # several times faster than (N, 3) * (N, 1).
    rays_t = np.ascontiguousarray(_cached_rays(*key).reshape(-1, 3).T)
    rays_t.setflags(write=False)
    return rays_t


def _ray_key(intrinsics: CameraIntrinsics, normalize: str) -> tuple:
    """The arguments of the ray caches for these intrinsics."""
    return (
        int(intrinsics.width),
        int(intrinsics.height),
        float(intrinsics.fx),
        float(intrinsics.fy),
        float(intrinsics.cx),
        float(intrinsics.cy),
        normalize,
    )


def camera_rays_t(intrinsics: CameraIntrinsics) -> np.ndarray:
    """The z-normalised rays of :func:`camera_rays`, coordinate-major ``(3, height * width)``
    (read-only, cached per intrinsics): what :func:`depth_to_camera_points` scales."""
    return _cached_rays_t(*_ray_key(intrinsics, "z"))


def camera_rays(intrinsics: CameraIntrinsics, normalize: RayNormalization = "z") -> np.ndarray:
    """Per-pixel ray directions in the MuJoCo camera frame.

    Parameters
    ----------
    intrinsics
        The camera's :class:`~liuxing_envs.sim.camera.CameraIntrinsics`.
    normalize
        ``"z"``: scaled so the z component is -1, i.e. ``depth[..., None] * rays`` is the
        camera-frame point of a z-depth image. ``"unit"``: unit vectors.

    Returns
    -------
    np.ndarray
        ``(height, width, 3)`` float64, read-only (cached per intrinsics; copy to modify).
    """
    if normalize not in ("z", "unit"):
        raise ValueError(f"normalize must be 'z' or 'unit', got {normalize!r}")
    return _cached_rays(*_ray_key(intrinsics, normalize))


def check_depth(depth: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """``depth`` as an array, or a ValueError when its shape is not the intrinsics'."""
    depth = np.asarray(depth)
    expected = (intrinsics.height, intrinsics.width)
    if depth.shape != expected:
        raise ValueError(
            f"depth image has shape {depth.shape}, expected (height, width) = {expected} "
            "from the intrinsics"
        )
    return depth


def depth_to_camera_points(
    depth: np.ndarray, intrinsics: CameraIntrinsics, return_mask: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Back-project the valid pixels of a z-depth image to camera-frame points.

    Parameters
    ----------
    depth
        ``(height, width)`` z-depth in metres; pixels that are not finite and > 0 are skipped.
    intrinsics
        Intrinsics the image was taken with.
    return_mask
        Also return the ``(height, width)`` boolean mask of the pixels that produced points
        (points are in row-major pixel order).

    Returns
    -------
    points : np.ndarray
        ``(N, 3)`` float64 points in the MuJoCo camera frame (x right, y up, -z forward).
    mask : np.ndarray
        Only with ``return_mask=True``.
    """
    depth = check_depth(depth, intrinsics)
    mask = np.isfinite(depth) & (depth > 0)
    rays_t = _cached_rays_t(*_ray_key(intrinsics, "z"))
    depths = depth.reshape(-1)
    if not mask.all():  # else every pixel is valid (typical: the table fills the view)
        # Pixel indices in row-major order; np.take is several times faster than a 2-D
        # boolean index of the (height, width, 3) rays.
        valid = np.flatnonzero(mask)
        rays_t = rays_t.take(valid, axis=1)
        depths = depths.take(valid)
    # The same products as rays[mask] * depth[mask][:, None], written through the
    # transposed view so the result is the usual C-ordered (N, 3) array.
    points = np.empty((depths.size, 3), dtype=np.float64)
    np.multiply(rays_t, depths.astype(np.float64), out=points.T)
    if return_mask:
        return points, mask
    return points


def as_points(points, name: str = "points", *, finite: bool = False) -> np.ndarray:
    """``points`` as an ``(N, 3)`` float64 array; a ValueError naming ``name`` otherwise
    (also for non-finite values when ``finite``)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {points.shape}")
    if finite and not np.isfinite(points).all():  # the method skips np.all's dispatch
        raise ValueError(f"{name} must be finite (drop invalid depth pixels first)")
    return points


def _check_vector(name: str, value: np.ndarray) -> np.ndarray:
    value = np.asarray(value, dtype=np.float64)
    if value.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {value.shape}")
    return value


def transform_points(points: np.ndarray, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Map points from a frame to its parent: ``rotation @ p + position`` for every row.

    With the camera pose from :meth:`DepthCamera.pose` this takes camera-frame points to the
    world frame. ``rotation`` is 3x3 (columns = the frame's axes in the parent) or a flat
    9-vector in row-major order, as MuJoCo stores ``xmat``.
    """
    points = as_points(points)
    position = _check_vector("position", position)
    rotation = np.asarray(rotation, dtype=np.float64)
    if rotation.shape == (9,):
        rotation = rotation.reshape(3, 3)
    if rotation.shape != (3, 3):
        raise ValueError(f"rotation must have shape (3, 3) or (9,), got {rotation.shape}")
    moved = points @ rotation.T
    # In place and one column at a time: broadcasting a (3,) row over (N, 3) is about twice
    # as slow in numpy, and the sums are the same.
    for c in range(3):
        moved[:, c] += position[c]
    return moved


def crop_points(
    points: np.ndarray, lower: np.ndarray, upper: np.ndarray, return_mask: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Keep the points inside the axis-aligned box ``lower <= p <= upper`` (bounds inclusive).

    Returns the ``(M, 3)`` float64 kept points, and with ``return_mask=True`` also the ``(N,)``
    boolean mask over the input rows.
    """
    points = as_points(points)
    lower = _check_vector("lower", lower)
    upper = _check_vector("upper", upper)
    if not (lower <= upper).all():  # also NaN, which would silently keep no point
        raise ValueError(
            f"crop box bounds must be numbers with lower <= upper on every axis: lower={lower}, "
            f"upper={upper}"
        )
    # Contiguous coordinate rows: see box_mask_t.
    mask = box_mask_t(np.ascontiguousarray(points.T), lower, upper)
    kept = np.compress(mask, points, axis=0)  # = points[mask], a little cheaper
    if return_mask:
        return kept, mask
    return kept


def box_mask_t(points_t: np.ndarray, lower, upper) -> np.ndarray:
    """``(N,)`` mask of the points inside the box ``lower <= p <= upper`` (bounds inclusive),
    from coordinate-major ``(3, N)`` points; NaN coordinates compare False, so drop out.

    Equals ``np.all((points >= lower) & (points <= upper), axis=1)`` on the ``(N, 3)``
    points, which numpy runs several times slower (it loops over rows of 3 values, then
    reduces along that short axis). No validation: for callers that checked their input.
    """
    x, y, z = points_t
    mask = x >= lower[0]
    mask &= x <= upper[0]
    mask &= y >= lower[1]
    mask &= y <= upper[1]
    mask &= z >= lower[2]
    mask &= z <= upper[2]
    return mask
