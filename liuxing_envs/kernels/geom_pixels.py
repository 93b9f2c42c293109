"""The pixels of a depth image whose return lies within a margin of some geoms (a robot's
self-filter): :meth:`~liuxing_envs.sim.camera.DepthCamera.pixels_on_geoms`, compiled.

The reference is numpy code whose products are BLAS calls (the camera points' rotation to
the world, the geom frames), whose rounding depends on the CPU. This kernel computes the
same quantities in plain arithmetic, so they differ from the reference's by a few units in
the last place, and it decides only what lies far beyond that: every comparison the answer
depends on (a geom's bounding sphere against the field of view and the depth range, a
pixel's depth against the nearest and farthest corner of the geom's grown box, a point's
distance to the geom against the margin) is taken only where its two sides differ by more
than a band (:data:`DEPTH_BAND` metres, :data:`SQUARE_BAND` square metres), orders of
magnitude above rounding. Where one does not, the kernel reports the image undecided and
the caller runs the reference, so the answer is the reference's bit for bit. The pixel
window of a geom is the reference's widened by a pixel: pixels in the wider window that
the reference leaves out are far from the geom, and the kernel finds them so.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from liuxing_envs.kernels import jit_options

#: Half-width of the band around a depth comparison that is left to the reference (m).
DEPTH_BAND = 1e-9
#: Half-width of the band around a squared-distance comparison left to the reference (m²).
SQUARE_BAND = 1e-12
#: A geom box's pixel window is widened by this many pixels beyond the reference's.
WINDOW_GROWTH_PX = 1.0

# MuJoCo's mjtGeom values of the geoms tested exactly (others by their bounding box).
_SPHERE, _CAPSULE, _CYLINDER, _BOX = 2, 3, 5, 6


@njit(**jit_options())
def pixels_on_geoms(
    depth, geom_ids, geom_xpos, geom_xmat, geom_type, geom_size, geom_aabb, geom_rbound,
    position, rotation, planes, margin, min_depth, max_depth, fx, fy, cx, cy,
    window_min_depth, window_margin_px, out,
):  # fmt: skip
    """Set ``out[i, j]`` (bool, ``depth``'s shape, all False on entry) where pixel ``(i, j)``'s
    return lies within ``margin`` of one of ``geom_ids`` (those the field of view may reach),
    as the reference does. Return True when decided; False (``out`` then partial) where a
    comparison fell within its band."""
    height, width = depth.shape
    corners = np.empty((8, 3))
    for k in range(geom_ids.shape[0]):
        g = geom_ids[k]
        # The bounding-sphere test, in the camera frame (which looks along -z).
        o0 = geom_xpos[g, 0] - position[0]
        o1 = geom_xpos[g, 1] - position[1]
        o2 = geom_xpos[g, 2] - position[2]
        c0 = o0 * rotation[0, 0] + o1 * rotation[1, 0] + o2 * rotation[2, 0]
        c1 = o0 * rotation[0, 1] + o1 * rotation[1, 1] + o2 * rotation[2, 1]
        c2 = o0 * rotation[0, 2] + o1 * rotation[1, 2] + o2 * rotation[2, 2]
        radius = geom_rbound[g] + margin
        ahead = -c2
        keep = _side(ahead + radius - min_depth, DEPTH_BAND)
        keep = min(keep, _side(max_depth - (ahead - radius), DEPTH_BAND))
        for p in range(planes.shape[0]):
            lean = c0 * planes[p, 0] + c1 * planes[p, 1] + c2 * planes[p, 2]
            keep = min(keep, _side(radius - lean, DEPTH_BAND))
        if keep == 0:
            return False
        if keep < 0:
            continue
        # The box grown by the margin: its corners' depths and pixel window.
        nearest, farthest = math.inf, -math.inf
        x_min = y_min = math.inf
        x_max = y_max = -math.inf
        for n in range(8):
            local0 = geom_aabb[g, 0] + (2 * (n >> 2) - 1) * (geom_aabb[g, 3] + margin)
            local1 = geom_aabb[g, 1] + (2 * ((n >> 1) & 1) - 1) * (geom_aabb[g, 4] + margin)
            local2 = geom_aabb[g, 2] + (2 * (n & 1) - 1) * (geom_aabb[g, 5] + margin)
            w0 = geom_xmat[g, 0] * local0 + geom_xmat[g, 1] * local1 + geom_xmat[g, 2] * local2 + o0
            w1 = geom_xmat[g, 3] * local0 + geom_xmat[g, 4] * local1 + geom_xmat[g, 5] * local2 + o1
            w2 = geom_xmat[g, 6] * local0 + geom_xmat[g, 7] * local1 + geom_xmat[g, 8] * local2 + o2
            for a in range(3):
                corners[n, a] = w0 * rotation[0, a] + w1 * rotation[1, a] + w2 * rotation[2, a]
            d = -corners[n, 2]
            nearest, farthest = min(nearest, d), max(farthest, d)
        behind = _side(farthest - min_depth, DEPTH_BAND)
        if behind == 0:
            return False
        if behind < 0:
            continue  # behind or at the optical centre (the wrist's own links)
        first_row, last_row, first_col, last_col = 0, height - 1, 0, width - 1
        if nearest > 2.0 * window_min_depth:
            for n in range(8):
                d = -corners[n, 2]
                x, y = corners[n, 0] / d, corners[n, 1] / d
                x_min, x_max = min(x_min, x), max(x_max, x)
                y_min, y_max = min(y_min, y), max(y_max, y)
            if math.isfinite(x_min + x_max + y_min + y_max):
                grow = window_margin_px + WINDOW_GROWTH_PX
                first_col = max(math.ceil(cx - 0.5 + fx * x_min - grow), 0)
                last_col = min(math.floor(cx - 0.5 + fx * x_max + grow), width - 1)
                first_row = max(math.ceil(cy - 0.5 - fy * y_max - grow), 0)
                last_row = min(math.floor(cy - 0.5 - fy * y_min + grow), height - 1)
        kind = geom_type[g]
        size0, size1 = geom_size[g, 0], geom_size[g, 1]
        for i in range(first_row, last_row + 1):
            ray1 = -((i + 0.5 - cy) / fy)
            for j in range(first_col, last_col + 1):
                d = float(depth[i, j])
                if not d > 0.0 or out[i, j]:
                    continue
                near_side = _side(d - nearest, DEPTH_BAND)
                far_side = _side(farthest - d, DEPTH_BAND)
                if near_side == 0 or far_side == 0:
                    return False
                if near_side < 0 or far_side < 0:
                    continue
                # The return in the world, then in the geom's frame.
                p0 = (j + 0.5 - cx) / fx * d
                p1 = ray1 * d
                p2 = -d
                w0 = rotation[0, 0] * p0 + rotation[0, 1] * p1 + rotation[0, 2] * p2 - o0
                w1 = rotation[1, 0] * p0 + rotation[1, 1] * p1 + rotation[1, 2] * p2 - o1
                w2 = rotation[2, 0] * p0 + rotation[2, 1] * p1 + rotation[2, 2] * p2 - o2
                l0 = w0 * geom_xmat[g, 0] + w1 * geom_xmat[g, 3] + w2 * geom_xmat[g, 6]
                l1 = w0 * geom_xmat[g, 1] + w1 * geom_xmat[g, 4] + w2 * geom_xmat[g, 7]
                l2 = w0 * geom_xmat[g, 2] + w1 * geom_xmat[g, 5] + w2 * geom_xmat[g, 8]
                room = _room(kind, l0, l1, l2, size0, size1, geom_size[g, 2], geom_aabb, g, margin)
                inside = _side(room, SQUARE_BAND)
                if inside == 0:
                    return False
                if inside > 0:
                    out[i, j] = True
    return True


@njit(**jit_options())
def _side(value, band):
    """1 where ``value`` is above ``band``, -1 below ``-band``, 0 within it."""
    if value > band:
        return 1
    if value < -band:
        return -1
    return 0


@njit(**jit_options())
def _room(kind, l0, l1, l2, size0, size1, size2, geom_aabb, g, margin):
    """How much closer than the margin a point (in the geom's frame) is to the geom, as a
    difference of squares: positive where it lies within the margin."""
    if kind == _SPHERE:
        reach = size0 + margin
        return reach * reach - (l0 * l0 + l1 * l1 + l2 * l2)
    if kind == _CAPSULE:
        along = min(max(l2, -size1), size1)
        reach = size0 + margin
        return reach * reach - (l0 * l0 + l1 * l1 + (l2 - along) ** 2)
    if kind == _CYLINDER:
        out_radius = max(math.hypot(l0, l1) - size0, 0.0)
        out_ends = max(abs(l2) - size1, 0.0)
        return margin * margin - (out_radius * out_radius + out_ends * out_ends)
    if kind == _BOX:
        e0, e1, e2 = abs(l0) - size0, abs(l1) - size1, abs(l2) - size2
    else:
        e0 = abs(l0 - geom_aabb[g, 0]) - geom_aabb[g, 3]
        e1 = abs(l1 - geom_aabb[g, 1]) - geom_aabb[g, 4]
        e2 = abs(l2 - geom_aabb[g, 2]) - geom_aabb[g, 5]
    e0, e1, e2 = max(e0, 0.0), max(e1, 0.0), max(e2, 0.0)
    return margin * margin - (e0 * e0 + e1 * e1 + e2 * e2)
