"""Which pad and instrument geom pairs ``GraspWorld.approach_directions`` must measure: those
whose bounding spheres come within the distance asked about (the others cannot be nearer),
as its numpy reference decides, in one call.

The reference compares the squared distance of the two centres, summed over x, y and z in
that order, with the square of the reach; the kernel sums and compares in the same order, so
it decides every pair alike. ``tests/test_grasp_kernels.py`` holds the two equal.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from liuxing_envs.kernels import jit_options


@njit(**jit_options())
def pairs_within(geom_xpos, pads_then_geoms, bound_radii, distance):
    """``(measured, count)``: ``measured[p, g]`` for the ``pads_then_geoms[p]`` (one of the
    first two entries) and ``pads_then_geoms[2 + g]`` whose centres (rows of ``geom_xpos``)
    lie closer than ``distance + bound_radii[p, g]``, and how many pairs do."""
    pads, geoms = bound_radii.shape
    measured = np.zeros((pads, geoms), dtype=np.bool_)
    count = 0
    for p in range(pads):
        pad = pads_then_geoms[p]
        for g in range(geoms):
            geom = pads_then_geoms[pads + g]
            squared = 0.0
            for axis in range(3):
                offset = geom_xpos[geom, axis] - geom_xpos[pad, axis]
                squared += offset * offset
            reach = distance + bound_radii[p, g]
            if squared < reach * reach:
                measured[p, g] = True
                count += 1
    return measured, count
