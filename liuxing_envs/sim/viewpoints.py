"""Camera viewpoints: look-at rotations and points on a view sphere around a target.

Conventions: a MuJoCo camera looks along its own -z with +y up in the image. Azimuth is
measured in the table plane from +x (the direction the arm faces) towards +y; elevation is
measured up from the table plane; both in radians.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

WORLD_UP = (0.0, 0.0, 1.0)
#: Image-up used when the view direction is parallel to the requested up (a top-down view):
#: +x, so the far side of the table is at the top of the image.
FALLBACK_UP = (1.0, 0.0, 0.0)


def look_at(eye, target, up=WORLD_UP) -> np.ndarray:
    """Rotation (3x3, columns = camera x, y, z in the world) of a camera at ``eye`` looking
    at ``target``, rolled so the image's up is as close to ``up`` as possible."""
    # Plain float arithmetic: this runs once per env step, and np.cross / np.linalg.norm on
    # 3-vectors cost several microseconds each in call overhead alone.
    ex, ey, ez = (float(v) for v in np.asarray(eye, dtype=float))
    tx, ty, tz = (float(v) for v in np.asarray(target, dtype=float))
    fx, fy, fz = tx - ex, ty - ey, tz - ez
    norm = math.sqrt(fx * fx + fy * fy + fz * fz)
    if not math.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"eye {np.asarray(eye)} and target {target} must be finite and distinct")
    fx, fy, fz = fx / norm, fy / norm, fz / norm
    ux, uy, uz = (float(v) for v in np.asarray(up, dtype=float))
    if not (math.isfinite(ux + uy + uz) and ux * ux + uy * uy + uz * uz > 0.0):
        raise ValueError(f"up must be a finite non-zero vector, got {up}")
    up_norm = math.sqrt(ux * ux + uy * uy + uz * uz)
    rx, ry, rz = _cross(fx, fy, fz, ux, uy, uz)
    # Looking along up (to within 1e-6 rad): up gives no roll, so the fallback does; and when
    # up is the fallback's own direction, world y.
    for fallback in (FALLBACK_UP, (0.0, 1.0, 0.0)):
        if math.sqrt(rx * rx + ry * ry + rz * rz) >= 1e-6 * up_norm:
            break
        rx, ry, rz = _cross(fx, fy, fz, *fallback)
        up_norm = 1.0
    norm = math.sqrt(rx * rx + ry * ry + rz * rz)
    rx, ry, rz = rx / norm, ry / norm, rz / norm
    ix, iy, iz = _cross(rx, ry, rz, fx, fy, fz)
    return np.array([[rx, ix, -fx], [ry, iy, -fy], [rz, iz, -fz]])


def look_at_quat(eye, target, up=WORLD_UP) -> np.ndarray:
    """:func:`look_at` as a MuJoCo quaternion (w, x, y, z), for a camera or a mocap body."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(look_at(eye, target, up)).ravel())
    return quat


def _cross(ax, ay, az, bx, by, bz) -> tuple[float, float, float]:
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


def sphere_point(center, azimuth: float, elevation: float, radius: float) -> np.ndarray:
    """The point at (azimuth, elevation, radius) on a sphere around ``center``."""
    center = np.asarray(center, dtype=float)
    ce = math.cos(elevation)
    return center + radius * np.array(
        [ce * math.cos(azimuth), ce * math.sin(azimuth), math.sin(elevation)]
    )


def sphere_viewpoint(center, azimuth: float, elevation: float, radius: float):
    """Camera position and look-at rotation for the view from (azimuth, elevation, radius)."""
    eye = sphere_point(center, azimuth, elevation, radius)
    return eye, look_at(eye, center)


def view_grid(center, radii, elevations, azimuths) -> list[tuple[np.ndarray, np.ndarray]]:
    """Viewpoints (position, rotation) at every (radius, elevation, azimuth) combination.

    A view at elevation pi/2 (straight down) is the same for every azimuth, so it is listed
    once per radius.
    """
    views = []
    for radius in radii:
        for elevation in elevations:
            overhead = np.isclose(elevation, np.pi / 2)
            for azimuth in azimuths[:1] if overhead else azimuths:
                views.append(sphere_viewpoint(center, azimuth, elevation, radius))
    return views
