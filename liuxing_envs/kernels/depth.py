"""The compiled depth image: the distances :func:`mujoco.mj_multiRay` gives for one ray per
pixel, bit for bit, with the z-depth conversion of the ray-cast backend.

Every intersection routine below is MuJoCo's own arithmetic (``src/engine/engine_ray.c`` of
MuJoCo 4.0.0), operation for operation, so that each ray's distance is the same double:
``ray_map``, ``ray_quad``, ``ray_sphere``, ``ray_plane``, ``ray_capsule``,
``ray_ellipsoid``, ``ray_cylinder``, ``ray_box``, ``ray_triangle`` with its per-ray plane
basis ``b0``/``b1``, the bounding-volume slab test ``mju_raySlab``
(:func:`ray_slab_inverse`), and the rule that keeps the nearest hit, ``newdist >= 0 &&
(newdist < dist || dist < 0)``. A minimum does not depend on the order in which hits are
found, so the loops run geom by geom (nearest first) and, for meshes, triangle by triangle
over only the pixels a triangle's vertices project to, where MuJoCo runs ray by ray through
body spheres and bounding-volume trees. The culls of ``mj_multiRay`` that can change a
result through rounding are copied: a geom whose bounding sphere lies beyond the cut-off is
left out, a body's bounding sphere (about the root box of its tree, ``bvh_aabb``, in its
inertial frame ``xipos``/``ximat``; MuJoCo 3.12's source adds the box's centre unrotated,
4.0.0's results match the rotated centre) skips its geoms for rays that miss it, a mesh is
tested only by rays that meet its box (``ray_box`` on ``geom_size``), and a triangle's hit
counts only where the slab tests of its leaf and every ancestor pass. The angular bounds of
``mju_multiRayPrepare`` are left out: they are conservative by a margin far above rounding.

The rest of the speed comes from tests that cannot change a result: a ray is tested against
a geom only inside the pixel window its bounding box projects to (widened by
``WINDOW_MARGIN_PX``; of a box reaching behind the camera, the part ``WINDOW_MIN_DEPTH`` or
more in front of it, where no ray meets it nearer; none for a box wholly behind it) and only
while the geom's bounding sphere may still hold a nearer hit; a bounding sphere around the
camera is not tested (:func:`misses_sphere`); a ray entering a box clear of a face's edges
takes that face's distance (:func:`ray_box_from_outside`); a mesh's faces turned towards the
camera are tested first, so that fewer hits behind them reach the tree's slab tests.

All functions are ``numba.njit`` with :func:`liuxing_envs.kernels.jit_options` (no
``fastmath``); the model's arrays are passed in, nothing is read from globals.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from liuxing_envs.kernels import jit_options

_JIT = jit_options()
njit = numba.njit(**_JIT)

#: MuJoCo's mjMINVAL.
MINVAL = 1e-15
#: The pixel window of a box is widened by this many pixels (as PixelGrid.window does).
WINDOW_MARGIN_PX = 1e-3
#: ... and taken only when every corner lies this many metres in front of the camera.
WINDOW_MIN_DEPTH = 1e-3
#: A box wholly this far (metres) behind the camera's image plane is met by no ray (each ray
#: points in front of that plane): far above the rounding of the corners' depths.
BEHIND_MARGIN = 1e-6
#: A ray entering a box through a face, at this distance (metres, times the scale of the
#: ray's origin and the box) or more from the face's edges, is cast against that face alone;
#: so is the ray only where its slope into the face is at least ENTRY_MIN_SLOPE, and only on
#: boxes no thinner than ENTRY_MIN_HALF_SIZE (see ray_box_from_outside).
ENTRY_MARGIN = 1e-9
ENTRY_MIN_SLOPE = 1e-3
ENTRY_MIN_HALF_SIZE = 1e-6
#: A geom is skipped for a ray whose hit so far is nearer than its bounding sphere by this
#: much (metres, plus a relative 1e-9): far above rounding, far below any geom.
SPHERE_SKIP_MARGIN = 1e-6

# mjtGeom
GEOM_PLANE = 0
GEOM_HFIELD = 1
GEOM_SPHERE = 2
GEOM_CAPSULE = 3
GEOM_ELLIPSOID = 4
GEOM_CYLINDER = 5
GEOM_BOX = 6
GEOM_MESH = 7
#: The geom types this kernel casts; a scene with another visible type is cast by MuJoCo.
SUPPORTED_TYPES = (
    GEOM_PLANE,
    GEOM_SPHERE,
    GEOM_CAPSULE,
    GEOM_ELLIPSOID,
    GEOM_CYLINDER,
    GEOM_BOX,
    GEOM_MESH,
)


# --- MuJoCo's ray functions (engine_ray.c), on scalars ---------------------------------------
# Per-pixel helpers take scalars only: an array argument costs a reference count per call.
# What depends on the geom and the ray origin alone (the origin in the geom's frame, the
# bounding sphere's offset) is computed once per geom with the same operations as MuJoCo.


@njit
def ray_quad(a, b, c):
    """``ray_quad``: (smallest non-negative root or -1, x0, x1) of a x^2 + 2 b x + c."""
    det = b * b - a * c
    if det < 0 or a < MINVAL:
        return -1.0, -1.0, -1.0
    det = math.sqrt(det)
    x0 = (-b - det) / a
    x1 = (-b + det) / a
    if x0 >= 0:
        return x0, x0, x1
    if x1 >= 0:
        return x1, x0, x1
    return -1.0, x0, x1


@njit
def sphere_offset(cx, cy, cz, dist_sqr, px, py, pz):
    """The ray-independent part of ``ray_sphere`` about (cx, cy, cz) from (px, py, pz):
    ``dif = pnt - pos`` and ``c = dif . dif - dist_sqr``."""
    d0 = px - cx
    d1 = py - cy
    d2 = pz - cz
    return d0, d1, d2, d0 * d0 + d1 * d1 + d2 * d2 - dist_sqr


@njit
def ray_sphere(d0, d1, d2, c, vx, vy, vz):
    """``ray_sphere`` (no normal) with the offset of :func:`sphere_offset`."""
    a = vx * vx + vy * vy + vz * vz
    b = vx * d0 + vy * d1 + vz * d2
    x, _, _ = ray_quad(a, b, c)
    return x


@njit
def misses_sphere(d0, d1, d2, c, vx, vy, vz):
    """Whether ``ray_sphere`` (offset of :func:`sphere_offset`) gives no hit. From inside the
    sphere it always hits, so the test is left out where c < -MINVAL: for a unit ray (a = 1)
    b*b - a*c then exceeds fl(b*b), and sqrt(fl(b*b)) = |b| in binary floating point (or b*b
    is below MINVAL), so the larger root is never negative."""
    return c >= -MINVAL and ray_sphere(d0, d1, d2, c, vx, vy, vz) < 0


@njit
def map_point(pos, mat, px, py, pz):
    """The point half of ``ray_map``: mat' (pnt - pos)."""
    d0 = px - pos[0]
    d1 = py - pos[1]
    d2 = pz - pos[2]
    return (
        mat[0] * d0 + mat[3] * d1 + mat[6] * d2,
        mat[1] * d0 + mat[4] * d1 + mat[7] * d2,
        mat[2] * d0 + mat[5] * d1 + mat[8] * d2,
    )


@njit
def map_vector(m0, m1, m2, m3, m4, m5, m6, m7, m8, vx, vy, vz):
    """The direction half of ``ray_map``: mat' vec."""
    return (
        m0 * vx + m3 * vy + m6 * vz,
        m1 * vx + m4 * vy + m7 * vz,
        m2 * vx + m5 * vy + m8 * vz,
    )


@njit
def ray_plane(l0, l1, l2, w0, w1, w2, s0, s1):
    """``ray_plane`` on a ray in the plane's frame."""
    if w2 > -MINVAL:
        return -1.0
    x = -l2 / w2
    if x < 0:
        return -1.0
    p0 = l0 + x * w0
    p1 = l1 + x * w1
    if (s0 <= 0 or abs(p0) <= s0) and (s1 <= 0 or abs(p1) <= s1):
        return x
    return -1.0


@njit
def ray_capsule(l0, l1, l2, w0, w1, w2, s0, s1):
    """``ray_capsule`` after its bounding sphere test, on a ray in the capsule's frame."""
    x = -1.0
    # cylinder round side
    a = w0 * w0 + w1 * w1
    b = w0 * l0 + w1 * l1
    c = l0 * l0 + l1 * l1 - s0 * s0
    sol, _, _ = ray_quad(a, b, c)
    if sol >= 0 and abs(l2 + sol * w2) <= s1:
        if x < 0 or sol < x:
            x = sol
    # top cap
    e0 = l0
    e1 = l1
    e2 = l2 - s1
    a = w0 * w0 + w1 * w1 + w2 * w2
    b = w0 * e0 + w1 * e1 + w2 * e2
    c = e0 * e0 + e1 * e1 + e2 * e2 - s0 * s0
    _, xa, xb = ray_quad(a, b, c)
    if xa >= 0 and l2 + xa * w2 >= s1:
        if x < 0 or xa < x:
            x = xa
    if xb >= 0 and l2 + xb * w2 >= s1:
        if x < 0 or xb < x:
            x = xb
    # bottom cap
    e2 = l2 + s1
    b = w0 * e0 + w1 * e1 + w2 * e2
    c = e0 * e0 + e1 * e1 + e2 * e2 - s0 * s0
    _, xa, xb = ray_quad(a, b, c)
    if xa >= 0 and l2 + xa * w2 <= -s1:
        if x < 0 or xa < x:
            x = xa
    if xb >= 0 and l2 + xb * w2 <= -s1:
        if x < 0 or xb < x:
            x = xb
    return x


@njit
def ray_ellipsoid(l0, l1, l2, w0, w1, w2, s0, s1, s2):
    """``ray_ellipsoid`` on a ray in the ellipsoid's frame."""
    i0 = 1 / (s0 * s0)
    i1 = 1 / (s1 * s1)
    i2 = 1 / (s2 * s2)
    a = i0 * w0 * w0 + i1 * w1 * w1 + i2 * w2 * w2
    b = i0 * w0 * l0 + i1 * w1 * l1 + i2 * w2 * l2
    c = i0 * l0 * l0 + i1 * l1 * l1 + i2 * l2 * l2 - 1
    x, _, _ = ray_quad(a, b, c)
    return x


@njit
def ray_cylinder(l0, l1, l2, w0, w1, w2, s0, s1):
    """``ray_cylinder`` after its bounding sphere test, on a ray in the cylinder's frame."""
    x = -1.0
    if abs(w2) > MINVAL:
        for side in (-1, 1):
            sol = (side * s1 - l2) / w2
            if sol >= 0:
                p0 = l0 + sol * w0
                p1 = l1 + sol * w1
                if p0 * p0 + p1 * p1 <= s0 * s0:
                    if x < 0 or sol < x:
                        x = sol
    a = w0 * w0 + w1 * w1
    b = w0 * l0 + w1 * l1
    c = l0 * l0 + l1 * l1 - s0 * s0
    sol, _, _ = ray_quad(a, b, c)
    if sol >= 0 and abs(l2 + sol * w2) <= s1:
        if x < 0 or sol < x:
            x = sol
    return x


@njit
def _box_face(x, li, wi, si, la, wa, sa, lb, wb, sb):
    """One axis of ``ray_box``'s face loop: both faces normal to it."""
    if abs(wi) > MINVAL:
        for side in (-1, 1):
            sol = (side * si - li) / wi
            if sol >= 0:
                p0 = la + sol * wa
                p1 = lb + sol * wb
                if abs(p0) <= sa and abs(p1) <= sb:
                    if x < 0 or sol < x:
                        x = sol
    return x


@njit
def ray_box(l0, l1, l2, w0, w1, w2, s0, s1, s2):
    """``ray_box`` after its bounding sphere test, on a ray in the box's frame."""
    x = _box_face(-1.0, l0, w0, s0, l1, w1, s1, l2, w2, s2)
    x = _box_face(x, l1, w1, s1, l0, w0, s0, l2, w2, s2)
    return _box_face(x, l2, w2, s2, l0, w0, s0, l1, w1, s1)


@njit
def _beyond(li, si):
    """The side (1 or -1) of the slab |x| <= si that ``li`` lies beyond, 0 within it."""
    if li > si:
        return 1
    if li < -si:
        return -1
    return 0


@njit
def _entry_setup(l0, l1, l2, s0, s1, s2):
    """What :func:`ray_box_from_outside` needs of a box (half-sizes s) seen from l in its
    frame: the slab sides l lies beyond (:func:`_beyond`), the edge margin, and whether the
    box is thick enough for it."""
    margin = ENTRY_MARGIN * (1.0 + abs(l0) + abs(l1) + abs(l2) + s0 + s1 + s2)
    thick = min(s0, s1, s2) > ENTRY_MIN_HALF_SIZE
    return _beyond(l0, s0), _beyond(l1, s1), _beyond(l2, s2), margin, thick


@njit
def _entry_face(li, wi, si, ei, la, wa, sa, lb, wb, sb, margin):
    """``ray_box``'s distance to the face ``ei`` of axis i, if the ray enters the box there
    with ``margin`` to spare from the face's edges, else -1."""
    if ei == 0 or not ei * wi < -ENTRY_MIN_SLOPE:
        return -1.0
    sol = (ei * si - li) / wi
    if abs(la + sol * wa) <= sa - margin and abs(lb + sol * wb) <= sb - margin:
        return sol
    return -1.0


@njit
def ray_box_from_outside(l0, l1, l2, w0, w1, w2, s0, s1, s2, e0, e1, e2, margin):
    """:func:`ray_box`'s result, found from the one face a ray enters by when it enters
    clear of the face's edges. ``e0``, ``e1``, ``e2``: :func:`_beyond` of the ray's origin.

    Then ``ray_box`` would return that face's distance, computed by the same expression:
    the point there lies ``margin`` or more inside every other slab, so every other face's
    plane is met at least ``margin`` (times the slope ENTRY_MIN_SLOPE) earlier, outside the
    entered slab, or later, far beyond rounding either way. Other rays take ``ray_box``."""
    x = _entry_face(l0, w0, s0, e0, l1, w1, s1, l2, w2, s2, margin)
    if x >= 0:
        return x
    x = _entry_face(l1, w1, s1, e1, l0, w0, s0, l2, w2, s2, margin)
    if x >= 0:
        return x
    x = _entry_face(l2, w2, s2, e2, l0, w0, s0, l1, w1, s1, margin)
    if x >= 0:
        return x
    return ray_box(l0, l1, l2, w0, w1, w2, s0, s1, s2)


@njit
def ray_slab_inverse(c0, c1, c2, h0, h1, h2, s0, s1, s2, i0, i1, i2):
    """``mju_raySlab`` of the box (centre c, half-sizes h) on a ray in its frame from s, given
    the reciprocals ``1.0 / d`` of its direction d (MuJoCo's ``inv``): one division per axis
    for a ray's whole walk up a mesh's tree."""
    tmin = 0.0
    tmax = np.inf
    for k in range(3):
        if k == 0:
            c, h, s, inv = c0, h0, s0, i0
        elif k == 1:
            c, h, s, inv = c1, h1, s1, i1
        else:
            c, h, s, inv = c2, h2, s2, i2
        t1 = (c - h - s) * inv
        t2 = (c + h - s) * inv
        minval = t1 if t1 < t2 else t2
        maxval = t2 if t1 < t2 else t1
        tmin = tmin if tmin > minval else minval
        tmax = tmax if tmax < maxval else maxval
    return tmin < tmax


@njit
def normalize3(x, y, z):
    """``mju_normalize3``."""
    norm = math.sqrt(x * x + y * y + z * z)
    if norm < MINVAL:
        return 1.0, 0.0, 0.0
    inv = 1 / norm
    return x * inv, y * inv, z * inv


@njit
def triangle_basis(w0, w1, w2):
    """``mju_rayTree``'s basis (b0, b1) of the plane normal to the ray direction."""
    a0, a1, a2 = 1.0, 1.0, 1.0
    if abs(w0) >= abs(w1) and abs(w0) >= abs(w2):
        a0 = 0.0
    elif abs(w1) >= abs(w2):
        a1 = 0.0
    else:
        a2 = 0.0
    scl = -(w0 * a0 + w1 * a1 + w2 * a2) / (w0 * w0 + w1 * w1 + w2 * w2)
    c0, c1, c2 = normalize3(a0 + scl * w0, a1 + scl * w1, a2 + scl * w2)
    # b0 = cross(b1, lvec)
    e0 = c1 * w2 - c2 * w1
    e1 = c2 * w0 - c0 * w2
    e2 = c0 * w1 - c1 * w0
    e0, e1, e2 = normalize3(e0, e1, e2)
    return e0, e1, e2, c0, c1, c2


# --- the image ---------------------------------------------------------------------------------


@njit
def _window(corners, rotation, position, fx, fy, cx, cy, height, width, reach):
    """(first row, end row, first col, end col) of the pixels whose rays may meet the hull of
    the box ``corners`` (world, (8, 3), corner k at bits (x, y, z) of k, as
    :func:`_box_corners` orders them). Only the part of the box at least WINDOW_MIN_DEPTH in
    front of the camera is projected: ``reach`` (bool) says that no ray meets the box nearer
    than that (see :func:`_box_beyond`); without it, a box reaching behind that depth gives
    the whole image."""
    depth = np.empty(8)
    x = np.empty(8)
    y = np.empty(8)
    behind = False
    for k in range(8):
        o0 = corners[k, 0] - position[0]
        o1 = corners[k, 1] - position[1]
        o2 = corners[k, 2] - position[2]
        x[k] = rotation[0, 0] * o0 + rotation[1, 0] * o1 + rotation[2, 0] * o2
        y[k] = rotation[0, 1] * o0 + rotation[1, 1] * o1 + rotation[2, 1] * o2
        depth[k] = -(rotation[0, 2] * o0 + rotation[1, 2] * o1 + rotation[2, 2] * o2)
        if not depth[k] > WINDOW_MIN_DEPTH:
            behind = True
    x_min = np.inf
    x_max = -np.inf
    y_min = np.inf
    y_max = -np.inf
    if not behind:
        for k in range(8):
            x_min, x_max, y_min, y_max = _extend(
                x_min, x_max, y_min, y_max, x[k] / depth[k], y[k] / depth[k]
            )
        return _clip_window(x_min, x_max, y_min, y_max, fx, fy, cx, cy, height, width)
    deepest = depth.max()
    if deepest < -BEHIND_MARGIN:
        return 0, 0, 0, 0  # wholly behind the camera: every ray points away from it
    if not reach:
        return 0, height, 0, width
    # The box cut at the depth WINDOW_MIN_DEPTH: its corners in front of the cut, and where
    # its twelve edges cross it. Their projections bound the projection of the cut box.
    found = False
    for k in range(8):
        if depth[k] >= WINDOW_MIN_DEPTH:
            x_min, x_max, y_min, y_max = _extend(
                x_min, x_max, y_min, y_max, x[k] / depth[k], y[k] / depth[k]
            )
            found = True
        for bit in (1, 2, 4):
            j = k | bit
            if j == k:
                continue
            dk = depth[k] - WINDOW_MIN_DEPTH
            dj = depth[j] - WINDOW_MIN_DEPTH
            if (dk < 0.0) == (dj < 0.0):
                continue
            t = dk / (dk - dj)
            x_min, x_max, y_min, y_max = _extend(
                x_min,
                x_max,
                y_min,
                y_max,
                (x[k] + t * (x[j] - x[k])) / WINDOW_MIN_DEPTH,
                (y[k] + t * (y[j] - y[k])) / WINDOW_MIN_DEPTH,
            )
            found = True
    if not found:
        return 0, 0, 0, 0  # wholly behind the cut, where no ray meets it
    # Rounding of the cut points: widen by a relative 1e-9 of their extent
    pad = 1e-9 * (abs(x_min) + abs(x_max) + abs(y_min) + abs(y_max) + 1.0)
    return _clip_window(
        x_min - pad, x_max + pad, y_min - pad, y_max + pad, fx, fy, cx, cy, height, width
    )


@njit
def _extend(x_min, x_max, y_min, y_max, x, y):
    """The bounds grown to take in (x, y)."""
    return min(x_min, x), max(x_max, x), min(y_min, y), max(y_max, y)


@njit
def _box_beyond(pos, mat, aabb, position, distance):
    """Whether the camera ``position`` lies more than ``distance`` from the geom's bounding
    box (its ``aabb`` in the geom's frame ``pos``, ``mat``)."""
    d0 = position[0] - pos[0]
    d1 = position[1] - pos[1]
    d2 = position[2] - pos[2]
    gap2 = 0.0
    for i in range(3):
        local = mat[i] * d0 + mat[3 + i] * d1 + mat[6 + i] * d2 - aabb[i]
        outside = abs(local) - aabb[3 + i]
        if outside > 0.0:
            gap2 += outside * outside
    return gap2 > distance * distance


@njit
def _clip_window(x_min, x_max, y_min, y_max, fx, fy, cx, cy, height, width):
    if not math.isfinite(x_min + x_max + y_min + y_max):
        return 0, height, 0, width
    first_col = math.ceil(cx - 0.5 + fx * x_min - WINDOW_MARGIN_PX)
    last_col = math.floor(cx - 0.5 + fx * x_max + WINDOW_MARGIN_PX)
    first_row = math.ceil(cy - 0.5 - fy * y_max - WINDOW_MARGIN_PX)
    last_row = math.floor(cy - 0.5 - fy * y_min + WINDOW_MARGIN_PX)
    return (
        min(max(first_row, 0), height),
        min(max(last_row + 1, 0), height),
        min(max(first_col, 0), width),
        min(max(last_col + 1, 0), width),
    )


@njit
def _box_corners(pos, mat, aabb, out):
    """The eight corners of a geom's bounding box in the world, into ``out`` (8, 3)."""
    k = 0
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            for sz in (-1.0, 1.0):
                a0 = aabb[0] + sx * aabb[3]
                a1 = aabb[1] + sy * aabb[4]
                a2 = aabb[2] + sz * aabb[5]
                out[k, 0] = pos[0] + mat[0] * a0 + mat[1] * a1 + mat[2] * a2
                out[k, 1] = pos[1] + mat[3] * a0 + mat[4] * a1 + mat[5] * a2
                out[k, 2] = pos[2] + mat[6] * a0 + mat[7] * a1 + mat[8] * a2
                k += 1


@njit
def _bounding_sphere2(gtype, s0, s1, s2):
    """The squared radius of the bounding sphere MuJoCo tests first for a geom type (-1:
    none)."""
    if gtype == GEOM_BOX or gtype == GEOM_MESH:
        return s0 * s0 + s1 * s1 + s2 * s2
    if gtype == GEOM_CAPSULE:
        ssz = s0 + s1
        return ssz * ssz
    if gtype == GEOM_CYLINDER:
        return s0 * s0 + s1 * s1
    if gtype == GEOM_SPHERE:
        return s0 * s0
    return -1.0


@njit
def _primitive(gtype, l0, l1, l2, w0, w1, w2, s0, s1, s2):
    """The distance of a primitive geom after its bounding sphere test, ray in its frame."""
    if gtype == GEOM_BOX:
        return ray_box(l0, l1, l2, w0, w1, w2, s0, s1, s2)
    if gtype == GEOM_CAPSULE:
        return ray_capsule(l0, l1, l2, w0, w1, w2, s0, s1)
    if gtype == GEOM_CYLINDER:
        return ray_cylinder(l0, l1, l2, w0, w1, w2, s0, s1)
    if gtype == GEOM_PLANE:
        return ray_plane(l0, l1, l2, w0, w1, w2, s0, s1)
    if gtype == GEOM_ELLIPSOID:
        return ray_ellipsoid(l0, l1, l2, w0, w1, w2, s0, s1, s2)
    return -1.0


@njit
def _cast_primitive(
    gtype, pos, mat, size, position, rays, dist, r0, r1, c0, c1, width, skip_below, body
):
    """Cast the rays of the window [r0, r1) x [c0, c1) against a primitive geom; ``body``:
    (has a sphere, its offset and c) of the geom's body, as :func:`sphere_offset`."""
    px, py, pz = position[0], position[1], position[2]
    has_body, b0, b1, b2, bc = body
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = (
        mat[0], mat[1], mat[2], mat[3], mat[4], mat[5], mat[6], mat[7], mat[8]
    )  # fmt: skip
    s0, s1, s2 = size[0], size[1], size[2]
    l0, l1, l2 = map_point(pos, mat, px, py, pz)
    if gtype == GEOM_PLANE:
        _cast_plane(m0, m1, m3, m4, m6, m7, m2, m5, m8, l0, l1, l2, s0, s1, rays, dist, body)
        return
    r2 = _bounding_sphere2(gtype, s0, s1, s2)
    g0, g1, g2, gc = sphere_offset(pos[0], pos[1], pos[2], r2, px, py, pz)
    e0, e1, e2, margin, from_outside = _entry_setup(l0, l1, l2, s0, s1, s2)
    from_outside = from_outside and gtype == GEOM_BOX
    for r in range(r0, r1):
        for c in range(c0, c1):
            p = r * width + c
            d = dist[p]
            if d >= 0 and d < skip_below:
                continue
            vx, vy, vz = rays[p, 0], rays[p, 1], rays[p, 2]
            if has_body and misses_sphere(b0, b1, b2, bc, vx, vy, vz):
                continue
            if gtype == GEOM_SPHERE:
                newdist = ray_sphere(g0, g1, g2, gc, vx, vy, vz)
            else:
                if r2 >= 0 and misses_sphere(g0, g1, g2, gc, vx, vy, vz):
                    continue
                w0, w1, w2 = map_vector(m0, m1, m2, m3, m4, m5, m6, m7, m8, vx, vy, vz)
                if from_outside:
                    newdist = ray_box_from_outside(
                        l0, l1, l2, w0, w1, w2, s0, s1, s2, e0, e1, e2, margin
                    )
                else:
                    newdist = _primitive(gtype, l0, l1, l2, w0, w1, w2, s0, s1, s2)
            if newdist >= 0 and (newdist < d or d < 0):
                dist[p] = newdist


@njit
def _cast_plane(m0, m1, m3, m4, m6, m7, m2, m5, m8, l0, l1, l2, s0, s1, rays, dist, body):
    """:func:`ray_plane` for every ray, its direction mapped one component at a time: the
    normal's first, as most rays leave there. The same expressions as :func:`map_vector`,
    so the same doubles."""
    has_body, b0, b1, b2, bc = body
    bounded = s0 > 0 or s1 > 0
    for p in range(dist.shape[0]):
        vx, vy, vz = rays[p, 0], rays[p, 1], rays[p, 2]
        if has_body and misses_sphere(b0, b1, b2, bc, vx, vy, vz):
            continue
        w2 = m2 * vx + m5 * vy + m8 * vz
        if w2 > -MINVAL:
            continue
        x = -l2 / w2
        if x < 0:
            continue
        if bounded:
            w0 = m0 * vx + m3 * vy + m6 * vz
            w1 = m1 * vx + m4 * vy + m7 * vz
            if not (s0 <= 0 or abs(l0 + x * w0) <= s0):
                continue
            if not (s1 <= 0 or abs(l1 + x * w1) <= s1):
                continue
        d = dist[p]
        if x < d or d < 0:
            dist[p] = x


@njit
def _cast_mesh(
    pos,
    mat,
    size,
    position,
    rotation,
    rays,
    dist,
    r0,
    r1,
    c0,
    c1,
    width,
    height,
    fx,
    fy,
    cx,
    cy,
    skip_below,
    body,
    mesh,
    mesh_vertadr,
    mesh_vertnum,
    mesh_faceadr,
    mesh_facenum,
    mesh_vert,
    mesh_face,
    face_leaf,
    bvh_parent,
    bvh_aabb,
    ray_local,
    ready,
    vertex_px,
):
    """Cast the rays of the window [r0, r1) x [c0, c1) against a mesh geom."""
    px, py, pz = position[0], position[1], position[2]
    has_body, b0, b1, b2, bc = body
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = (
        mat[0], mat[1], mat[2], mat[3], mat[4], mat[5], mat[6], mat[7], mat[8]
    )  # fmt: skip
    s0, s1, s2 = size[0], size[1], size[2]
    l0, l1, l2 = map_point(pos, mat, px, py, pz)
    g0, g1, g2, gc = sphere_offset(pos[0], pos[1], pos[2], s0 * s0 + s1 * s1 + s2 * s2, px, py, pz)
    e0, e1, e2, margin, from_outside = _entry_setup(l0, l1, l2, s0, s1, s2)
    ready[:] = 0
    any_ready = False
    for r in range(r0, r1):
        for c in range(c0, c1):
            p = r * width + c
            d = dist[p]
            if d >= 0 and d < skip_below:
                continue
            vx, vy, vz = rays[p, 0], rays[p, 1], rays[p, 2]
            if has_body and misses_sphere(b0, b1, b2, bc, vx, vy, vz):
                continue
            # mj_rayMesh's ray_box on geom_size, then mju_rayTree's ray_map and basis
            if misses_sphere(g0, g1, g2, gc, vx, vy, vz):
                continue
            w0, w1, w2 = map_vector(m0, m1, m2, m3, m4, m5, m6, m7, m8, vx, vy, vz)
            if from_outside:
                box = ray_box_from_outside(l0, l1, l2, w0, w1, w2, s0, s1, s2, e0, e1, e2, margin)
            else:
                box = ray_box(l0, l1, l2, w0, w1, w2, s0, s1, s2)
            if box < 0:
                continue
            e0, e1, e2, f0, f1, f2 = triangle_basis(w0, w1, w2)
            ray_local[p, 0] = w0
            ray_local[p, 1] = w1
            ray_local[p, 2] = w2
            ray_local[p, 3] = e0
            ray_local[p, 4] = e1
            ray_local[p, 5] = e2
            ray_local[p, 6] = f0
            ray_local[p, 7] = f1
            ray_local[p, 8] = f2
            ready[p] = 1
            any_ready = True
    if not any_ready:
        return
    # Each vertex's image-plane coordinates and whether it lies in front; the camera frame
    # from the geom's: R' (pos + mat v - position).
    vadr = mesh_vertadr[mesh]
    for k in range(mesh_vertnum[mesh]):
        a0 = np.float64(mesh_vert[vadr + k, 0])
        a1 = np.float64(mesh_vert[vadr + k, 1])
        a2 = np.float64(mesh_vert[vadr + k, 2])
        o0 = pos[0] + m0 * a0 + m1 * a1 + m2 * a2 - px
        o1 = pos[1] + m3 * a0 + m4 * a1 + m5 * a2 - py
        o2 = pos[2] + m6 * a0 + m7 * a1 + m8 * a2 - pz
        q0 = rotation[0, 0] * o0 + rotation[1, 0] * o1 + rotation[2, 0] * o2
        q1 = rotation[0, 1] * o0 + rotation[1, 1] * o1 + rotation[2, 1] * o2
        q2 = rotation[0, 2] * o0 + rotation[1, 2] * o1 + rotation[2, 2] * o2
        depth = -q2
        vertex_px[k, 2] = 1.0 if depth > WINDOW_MIN_DEPTH else 0.0
        vertex_px[k, 0] = q0 / depth
        vertex_px[k, 1] = q1 / depth
    fadr = mesh_faceadr[mesh]
    # Two sweeps, the faces turned towards the camera first: the nearest hit is then mostly
    # found first, and the faces behind it fail the distance test before the tree's slab
    # tests. The nearest hit does not depend on the order.
    for f in range(2 * mesh_facenum[mesh]):
        front_sweep = f < mesh_facenum[mesh]
        if not front_sweep:
            f -= mesh_facenum[mesh]
        leaf = face_leaf[fadr + f]
        if leaf < 0:
            continue  # in no leaf of the tree: MuJoCo never tests it
        i0 = mesh_face[fadr + f, 0]
        i1 = mesh_face[fadr + f, 1]
        i2 = mesh_face[fadr + f, 2]
        # ray_triangle's per-triangle part: vertices (float to double), v - lpnt, the plane
        v00 = np.float64(mesh_vert[vadr + i0, 0])
        v01 = np.float64(mesh_vert[vadr + i0, 1])
        v02 = np.float64(mesh_vert[vadr + i0, 2])
        v10 = np.float64(mesh_vert[vadr + i1, 0])
        v11 = np.float64(mesh_vert[vadr + i1, 1])
        v12 = np.float64(mesh_vert[vadr + i1, 2])
        v20 = np.float64(mesh_vert[vadr + i2, 0])
        v21 = np.float64(mesh_vert[vadr + i2, 1])
        v22 = np.float64(mesh_vert[vadr + i2, 2])
        g00, g01, g02 = v00 - v20, v01 - v21, v02 - v22
        g10, g11, g12 = v10 - v20, v11 - v21, v12 - v22
        h0, h1, h2 = l0 - v20, l1 - v21, l2 - v22
        n0 = g01 * g12 - g02 * g11
        n1 = g02 * g10 - g00 * g12
        n2 = g00 * g11 - g01 * g10
        numerator = -(h0 * n0 + h1 * n1 + h2 * n2)
        if (numerator > 0) != front_sweep:
            continue
        if vertex_px[i0, 2] > 0 and vertex_px[i1, 2] > 0 and vertex_px[i2, 2] > 0:
            x_min = min(vertex_px[i0, 0], vertex_px[i1, 0], vertex_px[i2, 0])
            x_max = max(vertex_px[i0, 0], vertex_px[i1, 0], vertex_px[i2, 0])
            y_min = min(vertex_px[i0, 1], vertex_px[i1, 1], vertex_px[i2, 1])
            y_max = max(vertex_px[i0, 1], vertex_px[i1, 1], vertex_px[i2, 1])
            t_r0, t_r1, t_c0, t_c1 = _clip_window(
                x_min, x_max, y_min, y_max, fx, fy, cx, cy, height, width
            )
            t_r0, t_r1 = max(t_r0, r0), min(t_r1, r1)
            t_c0, t_c1 = max(t_c0, c0), min(t_c1, c1)
        else:
            t_r0, t_r1, t_c0, t_c1 = r0, r1, c0, c1
        if t_r0 >= t_r1 or t_c0 >= t_c1:
            continue
        d00, d01, d02 = v00 - l0, v01 - l1, v02 - l2
        d10, d11, d12 = v10 - l0, v11 - l1, v12 - l2
        d20, d21, d22 = v20 - l0, v21 - l1, v22 - l2
        for r in range(t_r0, t_r1):
            for c in range(t_c0, t_c1):
                p = r * width + c
                if not ready[p]:
                    continue
                e0, e1, e2 = ray_local[p, 3], ray_local[p, 4], ray_local[p, 5]
                q00 = e0 * d00 + e1 * d01 + e2 * d02
                q10 = e0 * d10 + e1 * d11 + e2 * d12
                q20 = e0 * d20 + e1 * d21 + e2 * d22
                if (q00 > 0 and q10 > 0 and q20 > 0) or (q00 < 0 and q10 < 0 and q20 < 0):
                    continue
                f0, f1, f2 = ray_local[p, 6], ray_local[p, 7], ray_local[p, 8]
                q01 = f0 * d00 + f1 * d01 + f2 * d02
                q11 = f0 * d10 + f1 * d11 + f2 * d12
                q21 = f0 * d20 + f1 * d21 + f2 * d22
                if (q01 > 0 and q11 > 0 and q21 > 0) or (q01 < 0 and q11 < 0 and q21 < 0):
                    continue
                a0 = q00 - q20
                a1 = q10 - q20
                a2 = q01 - q21
                a3 = q11 - q21
                b0 = -q20
                b1 = -q21
                det = a0 * a3 - a1 * a2
                if abs(det) < MINVAL:
                    continue
                t0 = (a3 * b0 - a1 * b1) / det
                t1 = (-a2 * b0 + a0 * b1) / det
                if t0 < 0 or t1 < 0 or t0 + t1 > 1:
                    continue
                w0, w1, w2 = ray_local[p, 0], ray_local[p, 1], ray_local[p, 2]
                denom = w0 * n0 + w1 * n1 + w2 * n2
                if abs(denom) < MINVAL:
                    continue
                sol = numerator / denom
                d = dist[p]
                if not (sol >= 0 and (sol < d or d < 0)):
                    continue
                # MuJoCo reaches this triangle only through the slab tests of its leaf and
                # of every ancestor in the mesh's tree
                node = leaf
                reached = True
                inv0, inv1, inv2 = 1.0 / w0, 1.0 / w1, 1.0 / w2
                while node >= 0:
                    if not ray_slab_inverse(
                        bvh_aabb[node, 0],
                        bvh_aabb[node, 1],
                        bvh_aabb[node, 2],
                        bvh_aabb[node, 3],
                        bvh_aabb[node, 4],
                        bvh_aabb[node, 5],
                        l0,
                        l1,
                        l2,
                        inv0,
                        inv1,
                        inv2,
                    ):
                        reached = False
                        break
                    node = bvh_parent[node]
                if reached:
                    dist[p] = sol


@njit
def cast_image(
    out,
    dist,
    position,
    rotation,
    rays,
    cos_axis,
    cutoff,
    fx,
    fy,
    cx,
    cy,
    height,
    width,
    geoms,
    geom_type,
    geom_size,
    geom_aabb,
    geom_rbound,
    geom_bodyid,
    geom_dataid,
    geom_xpos,
    geom_xmat,
    body_bvhadr,
    bvh_aabb,
    xipos,
    ximat,
    mesh_vertadr,
    mesh_vertnum,
    mesh_faceadr,
    mesh_facenum,
    mesh_vert,
    mesh_face,
    face_leaf,
    bvh_parent,
    ray_local,
    ready,
    vertex_px,
    corners,
):
    """The depth image (``out``, (H*W,) float32: ``dist * cos_axis`` where a ray hit, else 0)
    of ``rays`` ((H*W, 3) world directions, row-major pixels) cast from ``position`` against
    ``geoms`` (the visible geom ids) as ``mj_multiRay`` with this ``cutoff`` casts them;
    ``dist`` gets the ray distances (-1: no hit). ``rotation``: the camera's axes (columns).
    The rest are the model's arrays (``mesh_vert`` float32, ``mesh_face`` int32), the
    data's poses, the mesh tables of :func:`mesh_tables` and scratch space."""
    npix = height * width
    px, py, pz = position[0], position[1], position[2]
    cos_min = 1.0
    for p in range(npix):
        dist[p] = -1.0
        cos_min = min(cos_min, cos_axis[p])
    # A ray meets a box this far from the camera, or farther, no nearer to the image plane
    # than WINDOW_MIN_DEPTH (its depth is its distance times its cos_axis).
    cut_distance = WINDOW_MIN_DEPTH / cos_min * (1.0 + 1e-6) + 1e-9 if cos_min > 0 else np.inf
    # mju_multiRayPrepare's cut-off, and a lower bound on each geom's distance
    count = geoms.shape[0]
    kept = np.empty(count, dtype=np.int64)
    near = np.empty(count, dtype=np.float64)
    n = 0
    for k in range(count):
        g = geoms[k]
        o0 = geom_xpos[g, 0] - px
        o1 = geom_xpos[g, 1] - py
        o2 = geom_xpos[g, 2] - pz
        centre = math.sqrt(o0 * o0 + o1 * o1 + o2 * o2)
        if body_bvhadr[geom_bodyid[g]] != -1 and centre > cutoff + geom_rbound[g]:
            continue
        kept[n] = g
        if geom_type[g] == GEOM_PLANE or geom_rbound[g] <= 0:
            near[n] = -np.inf
        else:
            near[n] = centre - geom_rbound[g] - SPHERE_SKIP_MARGIN - 1e-9 * centre
        n += 1
    order = np.argsort(near[:n])
    for k in range(n):
        g = kept[order[k]]
        skip_below = near[order[k]]
        gtype = geom_type[g]
        pos = geom_xpos[g]
        mat = geom_xmat[g]
        size = geom_size[g]
        # mju_singleRay's body sphere about the root box of the body's tree, whose centre
        # is in the body's inertial frame (xipos, ximat)
        b = geom_bodyid[g]
        bvh = body_bvhadr[b]
        body = (False, 0.0, 0.0, 0.0, 0.0)
        if bvh != -1:
            a0, a1, a2 = bvh_aabb[bvh, 0], bvh_aabb[bvh, 1], bvh_aabb[bvh, 2]
            h0, h1, h2 = bvh_aabb[bvh, 3], bvh_aabb[bvh, 4], bvh_aabb[bvh, 5]
            d0, d1, d2, dc = sphere_offset(
                ximat[b, 0] * a0 + ximat[b, 1] * a1 + ximat[b, 2] * a2 + xipos[b, 0],
                ximat[b, 3] * a0 + ximat[b, 4] * a1 + ximat[b, 5] * a2 + xipos[b, 1],
                ximat[b, 6] * a0 + ximat[b, 7] * a1 + ximat[b, 8] * a2 + xipos[b, 2],
                h0 * h0 + h1 * h1 + h2 * h2,
                px,
                py,
                pz,
            )
            body = (True, d0, d1, d2, dc)
        if gtype == GEOM_PLANE:
            r0, r1, c0, c1 = 0, height, 0, width
        else:
            _box_corners(pos, mat, geom_aabb[g], corners)
            reach = _box_beyond(pos, mat, geom_aabb[g], position, cut_distance)
            r0, r1, c0, c1 = _window(
                corners, rotation, position, fx, fy, cx, cy, height, width, reach
            )
        if r0 >= r1 or c0 >= c1:
            continue
        if gtype == GEOM_MESH:
            _cast_mesh(
                pos,
                mat,
                size,
                position,
                rotation,
                rays,
                dist,
                r0,
                r1,
                c0,
                c1,
                width,
                height,
                fx,
                fy,
                cx,
                cy,
                skip_below,
                body,
                geom_dataid[g],
                mesh_vertadr,
                mesh_vertnum,
                mesh_faceadr,
                mesh_facenum,
                mesh_vert,
                mesh_face,
                face_leaf,
                bvh_parent,
                bvh_aabb,
                ray_local,
                ready,
                vertex_px,
            )
        else:
            _cast_primitive(
                gtype, pos, mat, size, position, rays, dist, r0, r1, c0, c1, width, skip_below, body
            )
    for p in range(npix):
        d = dist[p]
        out[p] = np.float32(d * cos_axis[p]) if d >= 0.0 else np.float32(0.0)


def mesh_tables(
    nface: int,
    nbvh: int,
    mesh_bvhadr: np.ndarray,
    mesh_bvhnum: np.ndarray,
    mesh_faceadr: np.ndarray,
    bvh_child: np.ndarray,
    bvh_nodeid: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(face_leaf, bvh_parent): per face of every mesh, the (model-wide) id of the tree leaf
    holding it (-1: none); per tree node, its parent (-1: a root). ValueError when a face
    lies in more than one leaf (then MuJoCo's reach of it is not one chain of slab tests)."""
    face_leaf = np.full(max(nface, 1), -1, dtype=np.int64)
    parent = np.full(max(nbvh, 1), -1, dtype=np.int64)
    for mesh in range(mesh_bvhadr.shape[0]):
        adr, num = int(mesh_bvhadr[mesh]), int(mesh_bvhnum[mesh])
        if adr < 0:
            continue
        children = bvh_child[adr : adr + num]
        ids = np.arange(num)
        for side in range(2):
            has = children[:, side] != -1
            parent[adr + children[has, side]] = adr + ids[has]
        leaves = ids[bvh_nodeid[adr : adr + num] != -1]
        faces = bvh_nodeid[adr + leaves] + mesh_faceadr[mesh]
        if np.unique(faces).size != faces.size:
            raise ValueError(f"mesh {mesh}: a face lies in more than one leaf of its tree")
        face_leaf[faces] = adr + leaves
    return face_leaf, parent
