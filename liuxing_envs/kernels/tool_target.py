"""The tool pose an ``ee_delta`` action asks for: the arithmetic of
``EndEffectorDeltaController.set_point`` before its IK (the workspace clip, the yaw turned and
wrapped, the tool pointing down), as the 4x4 homogeneous pose of the tool-centre site, with
the reference's values bit for bit.

The reference's ``np.minimum`` and ``np.maximum`` keep their first argument on a tie (the
bounds are never zero, so a tie is of two equal numbers); ``math.atan2``, ``math.cos`` and
``math.sin`` are the C library's in both; ``%`` of two floats follows Python's sign rule in
numba as in numpy; and ``+ - *`` round alike, in the reference's order (no ``fastmath``).
``tests/test_grasp_kernels.py`` holds the two equal.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from liuxing_envs.kernels import jit_options


@njit(**jit_options())
def _clipped(value, low, high):
    """``np.minimum(np.maximum(value, low), high)`` of floats."""
    raised = value if value >= low else low
    return raised if raised <= high else high


@njit(**jit_options())
def tool_target_pose(
    site_xpos, site_xmat, site, arm_action, max_translation, max_yaw, scale, lower, upper
):
    """The 4x4 pose of site ``site`` (row of ``site_xpos`` and ``site_xmat``) that the
    ``ee_delta`` action ``arm_action`` (4 floats in [-1, 1]) asks for: its translation, times
    ``max_translation`` m, from where the site is, clipped to ``lower`` and ``upper``; its yaw,
    times ``max_yaw`` rad, from the site's x axis about world z, wrapped to [-pi, pi); both
    moves times ``scale`` (from a zero action's target); the tool pointing down."""
    pi = math.pi
    target = np.empty(3)
    for i in range(3):
        target[i] = _clipped(
            site_xpos[site, i] + max_translation * arm_action[i], lower[i], upper[i]
        )
    yaw_change = max_yaw * arm_action[3]
    if scale != 1.0:
        for i in range(3):
            start = _clipped(site_xpos[site, i], lower[i], upper[i])
            target[i] = start + scale * (target[i] - start)
        yaw_change *= scale
    yaw = math.atan2(site_xmat[site, 3], site_xmat[site, 0]) + yaw_change
    yaw = (yaw + pi) % (2 * pi) - pi
    c, s = math.cos(yaw), math.sin(yaw)
    pose = np.zeros((4, 4))
    pose[0, 0], pose[0, 1] = c, s
    pose[1, 0], pose[1, 1] = s, -c
    pose[2, 2] = -1.0
    for i in range(3):
        pose[i, 3] = target[i]
    pose[3, 3] = 1.0
    return pose
