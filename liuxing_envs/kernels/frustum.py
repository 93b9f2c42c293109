"""Which geoms a camera's pixel rays may reach: the test of
:meth:`~liuxing_envs.sim.depth_backends.ViewFrustum.may_reach`, compiled.

A geom is out of reach when its oriented bounding box lies wholly outside one of the planes
through the optical centre that bound the field of view, or when its bounding sphere lies
beyond the ray length. The test is conservative by a margin far above rounding, and its
answer only decides what is tested further (which stand-in scene is cast, which geoms the
self-filter tests pixel by pixel), never a result; so its sums run in loop order rather
than in numpy's BLAS order.
"""

from __future__ import annotations

import math

from numba import njit

from liuxing_envs.kernels import jit_options


@njit(**jit_options())
def may_reach(
    geom_ids, geom_xpos, geom_xmat, geom_aabb, geom_rbound, position, rotation, planes,
    ray_length, grow, view_margin, out,
):  # fmt: skip
    """Set ``out[k]`` for geom ``geom_ids[k]``: False when no ray from a camera at
    ``position`` with axes ``rotation`` (columns) can reach its box grown by ``grow`` metres
    (``planes``: unit outward normals in the camera frame). Return how many may be reached."""
    normals = planes @ rotation.T  # outward normals in the world
    reached = 0
    for k in range(geom_ids.shape[0]):
        g = geom_ids[k]
        o0 = geom_xpos[g, 0] - position[0]
        o1 = geom_xpos[g, 1] - position[1]
        o2 = geom_xpos[g, 2] - position[2]
        inside = math.sqrt(o0 * o0 + o1 * o1 + o2 * o2) - geom_rbound[g] - grow <= ray_length
        p = 0
        while inside and p < normals.shape[0]:
            n0, n1, n2 = normals[p, 0], normals[p, 1], normals[p, 2]
            nearest = o0 * n0 + o1 * n1 + o2 * n2
            for j in range(3):
                # The plane's normal along the geom's axis j, and the box's extent along it.
                along = n0 * geom_xmat[g, j] + n1 * geom_xmat[g, 3 + j] + n2 * geom_xmat[g, 6 + j]
                nearest += along * geom_aabb[g, j] - abs(along) * (geom_aabb[g, 3 + j] + grow)
            inside = nearest <= view_margin
            p += 1
        out[k] = inside
        reached += inside
    return reached
