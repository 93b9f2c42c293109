"""Camera viewpoints: look-at rotations and points on a view sphere around a target.

Conventions: a MuJoCo camera looks along its own -z with +y up in the image. Azimuth is
measured in the table plane from +x (the direction the arm faces) towards +y; elevation is
measured up from the table plane; both in radians.
"""

from __future__ import annotations

import numpy as np

WORLD_UP = (0.0, 0.0, 1.0)
#: Image-up used when the view direction is parallel to the requested up (a top-down view):
#: +x, so the far side of the table is at the top of the image.
FALLBACK_UP = (1.0, 0.0, 0.0)


def look_at(eye, target, up=WORLD_UP) -> np.ndarray:
    """Rotation (3x3, columns = camera x, y, z in the world) of a camera at ``eye`` looking
    at ``target``, rolled so the image's up is as close to ``up`` as possible."""
    eye = np.asarray(eye, dtype=float)
    forward = np.asarray(target, dtype=float) - eye
    norm = np.linalg.norm(forward)
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"eye {eye} and target {target} must be finite and distinct")
    forward /= norm
    up = np.asarray(up, dtype=float)
    if np.linalg.norm(np.cross(forward, up)) < 1e-6:
        up = np.asarray(FALLBACK_UP)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    image_up = np.cross(right, forward)
    return np.column_stack([right, image_up, -forward])


def sphere_point(center, azimuth: float, elevation: float, radius: float) -> np.ndarray:
    """The point at (azimuth, elevation, radius) on a sphere around ``center``."""
    center = np.asarray(center, dtype=float)
    ce = np.cos(elevation)
    return center + radius * np.array(
        [ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)]
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
