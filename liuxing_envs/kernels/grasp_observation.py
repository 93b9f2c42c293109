"""InstrumentGrasp's proprioception, fingertip forces and privileged instrument state read
from MuJoCo's arrays in one call: the arithmetic of ``GraspSensor.observe`` (the tool's yaw,
the grasp point in the tool's frame, the jaws' misalignment), with the reference's float32
values bit for bit.

The reference computes on Python floats, whose ``math.atan2``, ``math.atan``, ``math.cos``
and ``math.sin`` are the C library's, as numba's are; its ``+ - * /`` round alike in the same
order (no ``fastmath``), and a float64 rounds to the same float32 in both.
``tests/test_grasp_kernels.py`` holds the two equal.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from liuxing_envs.kernels import jit_options

#: Entries of the ``layout`` argument: the ids and addresses the kernel reads at.
TCP_SITE, GRASP_SITE, LEFT_FINGER, RIGHT_FINGER, LEFT_TOUCH, RIGHT_TOUCH, INSTRUMENT_DOF = range(7)
#: ``layout[ARM_QPOS:ARM_QPOS + 6]`` and ``layout[ARM_DOF:ARM_DOF + 6]``: the arm joints'.
ARM_QPOS, ARM_DOF = 7, 13
LAYOUT_SIZE = 19


@njit(**jit_options())
def grasp_observation(
    qpos, qvel, site_xpos, site_xmat, sensordata, layout, commanded_opening, with_instrument
):
    """``(proprio, forces, instrument)`` as float32 arrays of 19, 2 and 14 entries (the last
    empty unless ``with_instrument``); ``layout``: int64 ids and addresses, see the module's
    constants."""
    proprio = np.empty(19, dtype=np.float32)
    for j in range(6):
        proprio[j] = qpos[layout[ARM_QPOS + j]]
        proprio[6 + j] = qvel[layout[ARM_DOF + j]]
    tcp = layout[TCP_SITE]
    for i in range(3):
        proprio[12 + i] = site_xpos[tcp, i]
    yaw = math.atan2(site_xmat[tcp, 3], site_xmat[tcp, 0])
    cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)
    proprio[15] = cos_yaw
    proprio[16] = sin_yaw
    proprio[17] = qpos[layout[LEFT_FINGER]] + qpos[layout[RIGHT_FINGER]]
    proprio[18] = commanded_opening
    forces = np.empty(2, dtype=np.float32)
    forces[0] = sensordata[layout[LEFT_TOUCH]]
    forces[1] = sensordata[layout[RIGHT_TOUCH]]
    if not with_instrument:
        return proprio, forces, np.empty(0, dtype=np.float32)
    instrument = np.empty(14, dtype=np.float32)
    grasp, dof = layout[GRASP_SITE], layout[INSTRUMENT_DOF]
    for i in range(3):
        instrument[i] = site_xpos[grasp, i]
        instrument[3 + i] = site_xmat[grasp, 3 * i]
        instrument[6 + i] = qvel[dof + i]
    dx = site_xpos[grasp, 0] - site_xpos[tcp, 0]
    dy = site_xpos[grasp, 1] - site_xpos[tcp, 1]
    dz = site_xpos[grasp, 2] - site_xpos[tcp, 2]
    # The yaw that puts the jaws across the handle (sim.grasp_world.jaws_across).
    axis_x, axis_y = site_xmat[grasp, 0], site_xmat[grasp, 3]
    jaws = math.atan(axis_y / axis_x) if axis_x else math.pi / 2
    misalignment = 2.0 * (yaw - jaws)
    instrument[9] = cos_yaw * dx + sin_yaw * dy
    instrument[10] = -sin_yaw * dx + cos_yaw * dy
    instrument[11] = dz
    instrument[12] = math.cos(misalignment)
    instrument[13] = math.sin(misalignment)
    return proprio, forces, instrument
