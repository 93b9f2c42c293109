"""The roll-free closed-form IK of :class:`~liuxing_envs.sim.arm_ik.ArmIK`: ``ur_ik`` of a
batch of flange poses followed by ``ArmIK.nearest_first``, with the same results bit for bit.

The elementwise arithmetic (``+ - * /``, ``sqrt``, ``sin``, ``cos``, ``hypot``, ``rint``) runs
in the kernels below, each operation in the order and grouping of the numpy reference
(:func:`liuxing_envs.sim.ur_ik.ur_ik`), so it rounds the same: IEEE arithmetic is exact to
the bit, and numpy's float64 ``sin``, ``cos`` and ``hypot`` are the C library's, which numba
calls too (``tests/test_ik_kernel.py`` holds the two equal over 3,500 seeded poses and
their rolls). Everything whose last bits depend on numpy's build and the CPU stays a numpy
call on the same values, between the kernels:

- ``arccos``, ``arcsin`` and ``arctan2``: numpy computes them with SIMD code (Intel's SVML on
  AVX-512 machines) that differs from the C library's in the last bit for about one value in
  ten (the value alone decides the result: not the array's length, stride or alignment);
- ``ur_ik``'s 3x3 products (``matmul`` calls BLAS, whose kernels fuse multiply-adds
  depending on the CPU) and its squared reach (``einsum``, which pairs its terms by SIMD
  lane), called on arrays of the same layouts;
- the order of equal distances: numpy's ``argsort`` is not stable, so the kernel sorts
  stably and, where two distances tie, leaves the order to numpy.

So the pipeline is eight short kernels and ten numpy calls on a few dozen values each,
about a quarter of the reference's cost. The layout: ``n`` poses, each with shoulder (2),
wrist (2) and elbow (2) branches in ``ur_ik``'s order; a solution's row among a pose's eight
is ``4 * shoulder + 2 * wrist + elbow``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from liuxing_envs.kernels import jit_options
from liuxing_envs.sim import ur_ik

#: The constants of ``ur_ik``'s arithmetic, as its numpy expressions compute them (the
#: kernels take them as an argument: numba would freeze module globals into its cache).
CONSTANTS = np.array(
    [
        ur_ik._D4,
        ur_ik._D5,
        ur_ik._D6,
        ur_ik._A3,
        ur_ik._A2**2,
        ur_ik._A3**2,
        2 * ur_ik._A2 * ur_ik._A3,
        1.0 + ur_ik.COS_SLACK,
        ur_ik._SINGULAR,
        ur_ik._TWO_PI,
        np.pi / 2,
    ],
    dtype=np.float64,
)
_D4, _D5, _D6, _A3, _A2SQ, _A3SQ, _DEN, _COS_LIMIT, _SINGULAR, _TWO_PI, _HALF_PI = range(11)
_SIGNS = (1.0, -1.0)
_SHOULDER_HEIGHT = ur_ik._SHOULDER_HEIGHT


@njit(**jit_options())
def _wrist_centres(poses, consts):
    """Per pose: the wrist-2 centre's y and x (``arctan2``'s arguments) and d4 / radius."""
    n = poses.shape[0]
    out = np.empty((3, n))
    d6 = consts[_D6]
    for i in range(n):
        x05 = poses[i, 0, 3] - d6 * poses[i, 0, 2]
        y05 = poses[i, 1, 3] - d6 * poses[i, 1, 2]
        out[0, i] = y05
        out[1, i] = x05
        out[2, i] = consts[_D4] / math.hypot(x05, y05)
    return out


@njit(**jit_options())
def _shoulders(poses, phi1, phi2, consts):
    """Per pose and shoulder: theta 1, its sine and cosine, cos theta 5 and its clipped value."""
    n = poses.shape[0]
    out = np.empty((5, n, 2))
    for i in range(n):
        px, py = poses[i, 0, 3], poses[i, 1, 3]
        for s in range(2):
            theta1 = (phi1[i] + _SIGNS[s] * phi2[i]) + consts[_HALF_PI]
            s1, c1 = math.sin(theta1), math.cos(theta1)
            cos5 = ((px * s1 - py * c1) - consts[_D4]) / consts[_D6]
            out[0, i, s] = theta1
            out[1, i, s] = s1
            out[2, i, s] = c1
            out[3, i, s] = cos5
            out[4, i, s] = _clip(cos5, -1.0, 1.0)
    return out


@njit(**jit_options())
def _wrists(poses, shoulders, base5, consts):
    """Per pose, shoulder and wrist: theta 5, its sine, cos of |theta 5|, and ``arctan2``'s
    arguments for theta 6."""
    n = poses.shape[0]
    out = np.empty((5, n, 2, 2))
    for i in range(n):
        for s in range(2):
            base = base5[i, s]
            if abs(shoulders[3, i, s]) > consts[_COS_LIMIT]:
                base = np.nan
            s1, c1 = shoulders[1, i, s], shoulders[2, i, s]
            x_on_z1 = poses[i, 0, 0] * s1 - poses[i, 1, 0] * c1
            y_on_z1 = poses[i, 0, 1] * s1 - poses[i, 1, 1] * c1
            c5 = math.cos(base)
            for w in range(2):
                theta5 = base * _SIGNS[w]
                s5 = math.sin(theta5)
                out[0, i, s, w] = theta5
                out[1, i, s, w] = s5
                out[2, i, s, w] = c5
                out[3, i, s, w] = -y_on_z1 / s5
                out[4, i, s, w] = x_on_z1 / s5
    return out


@njit(**jit_options())
def _local_vectors(wrists, theta6, consts):
    """``ur_ik``'s ``local``: per branch, p13 and R14's first column before R06 turns them."""
    n = theta6.shape[0]
    d4, d5, d6 = consts[_D4], consts[_D5], consts[_D6]
    local = np.empty((n, 2, 2, 2, 3))
    for i in range(n):
        for s in range(2):
            for w in range(2):
                s5, c5 = wrists[1, i, s, w], wrists[2, i, s, w]
                s6, c6 = math.sin(theta6[i, s, w]), math.cos(theta6[i, s, w])
                local[i, s, w, 0, 0] = s6 * d5 - (c6 * s5) * d4
                local[i, s, w, 0, 1] = c6 * d5 + (s6 * s5) * d4
                local[i, s, w, 0, 2] = -d6 - c5 * d4
                local[i, s, w, 1, 0] = c6 * c5
                local[i, s, w, 1, 1] = -s6 * c5
                local[i, s, w, 1, 2] = -s5
    return local


@njit(**jit_options())
def _from_shoulder(in_base, poses, shoulder_height):
    """``in_base[..., 0, :] += p - shoulder_height``: p13 from the shoulder (in place)."""
    for i in range(in_base.shape[0]):
        for c in range(3):
            shift = poses[i, c, 3] - shoulder_height[c]
            for s in range(2):
                for w in range(2):
                    in_base[i, s, w, 0, c] += shift


@njit(**jit_options())
def _elbows(in_base, reach, shoulders, consts):
    """Per pose, shoulder and wrist: cos theta 3 (clipped within the slack) and the arguments
    of the two ``arctan2`` of theta 2 and theta 4."""
    n = reach.shape[0]
    out = np.empty((5, n, 2, 2))
    for i in range(n):
        for s in range(2):
            s1, c1 = shoulders[1, i, s], shoulders[2, i, s]
            for w in range(2):
                cos3 = ((reach[i, s, w] - consts[_A2SQ]) - consts[_A3SQ]) / consts[_DEN]
                if abs(cos3) <= consts[_COS_LIMIT]:
                    cos3 = _clip(cos3, -1.0, 1.0)
                out[0, i, s, w] = cos3
                out[1, i, s, w] = in_base[i, s, w, 0, 2]
                out[2, i, s, w] = -(c1 * in_base[i, s, w, 0, 0] + s1 * in_base[i, s, w, 0, 1])
                out[3, i, s, w] = in_base[i, s, w, 1, 2]
                out[4, i, s, w] = c1 * in_base[i, s, w, 1, 0] + s1 * in_base[i, s, w, 1, 1]
    return out


@njit(**jit_options())
def _sines_of_theta2(base3, reach, consts):
    """``arcsin``'s argument for theta 2 of each branch."""
    n = reach.shape[0]
    out = np.empty((n, 2, 2, 2))
    for i in range(n):
        for s in range(2):
            for w in range(2):
                root = math.sqrt(reach[i, s, w])
                for e in range(2):
                    out[i, s, w, e] = consts[_A3] * math.sin(base3[i, s, w] * _SIGNS[e]) / root
    return out


@njit(**jit_options())
def _nearest(
    shoulders,
    wrists,
    theta6,
    base3,
    asin2,
    offset,
    column,
    reference,
    slack_lower,
    slack_upper,
    lower,
    upper,
    consts,
):
    """The valid solutions, wrapped, shifted towards ``reference``, within the limits and
    clipped onto them (``ArmIK.nearest_first``), their distances from ``reference`` in row
    order, and whether two distances tie: if not, the solutions come nearest first, else in
    row order for ``np.argsort`` to order them."""
    n = theta6.shape[0]
    two_pi = consts[_TWO_PI]
    candidates = np.empty((8 * n, 6))
    distances = np.empty(8 * n)
    q = np.empty(6)
    count = 0
    for i in range(n):
        for s in range(2):
            for w in range(2):
                if abs(wrists[1, i, s, w]) < consts[_SINGULAR]:
                    continue
                for e in range(2):
                    theta3 = base3[i, s, w] * _SIGNS[e]
                    theta2 = asin2[i, s, w, e] - offset[i, s, w]
                    q[0] = shoulders[0, i, s]
                    q[1] = theta2
                    q[2] = theta3
                    q[3] = (column[i, s, w] - theta2) - theta3
                    q[4] = wrists[0, i, s, w]
                    q[5] = theta6[i, s, w]
                    valid = True
                    for j in range(6):
                        angle = q[j] - _whole_turns(q[j], two_pi)
                        if not np.isfinite(angle):
                            valid = False
                            break
                        q[j] = angle
                    if not valid:
                        continue
                    for j in range(6):
                        angle = q[j]
                        shifted = angle + _whole_turns(reference[j] - angle, two_pi)
                        if slack_lower[j] <= shifted and shifted <= slack_upper[j]:
                            angle = shifted
                        elif not (slack_lower[j] <= angle and angle <= slack_upper[j]):
                            valid = False
                            break
                        q[j] = _clip(angle, lower[j], upper[j])
                    if not valid:
                        continue
                    distance2 = 0.0
                    for j in range(6):
                        offset_j = q[j] - reference[j]
                        square = offset_j * offset_j
                        distance2 = square if j == 0 else distance2 + square
                        candidates[count, j] = q[j]
                    distances[count] = math.sqrt(distance2)
                    count += 1
    candidates, distances = candidates[:count], distances[:count]
    # Sorted by distance (a stable sort). Where two distances are equal, numpy's argsort (not
    # stable) decides their order: the caller asks it.
    order = np.argsort(distances, kind="mergesort")
    for k in range(1, count):
        if distances[order[k]] == distances[order[k - 1]]:
            return candidates, distances, True
    return candidates[order], distances, False


@njit(**jit_options())
def _whole_turns(x, two_pi):
    """``two_pi * np.rint(x / two_pi)``: within 3 rad of 0 that is a zero of the sign of x
    (``rint`` keeps the sign), with no division."""
    if abs(x) < 3.0:
        return math.copysign(0.0, x)
    return two_pi * np.rint(x / two_pi)


@njit(**jit_options())
def _clip(x, low, high):
    """np.clip of a float: max, then min, NaN kept (numpy's ``_NPY_CLIP``)."""
    if x != x:
        return x
    x = x if x > low else low
    return x if x < high else high


def nearest_solutions(
    flange_poses: np.ndarray,
    reference: np.ndarray,
    slack_lower: np.ndarray,
    slack_upper: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
) -> np.ndarray:
    """``ArmIK.nearest_first(solutions[valid], reference)`` of ``solutions, valid =
    ur_ik(flange_poses)``, bit for bit: the closed-form solutions of a batch of (n, 4, 4)
    flange poses in the base frame, n >= 2 (``ur_ik`` takes another path for one pose), within
    ``[slack_lower, slack_upper]`` after the shift by whole turns towards ``reference``,
    clipped onto ``[lower, upper]``, nearest (joint space) first, as a (k, 6) array. The
    limits are the arm's (``lower``, ``upper``) and those widened by ``IK_LIMIT_SLACK``."""
    poses = np.ascontiguousarray(flange_poses, dtype=np.float64)
    consts = CONSTANTS
    with np.errstate(invalid="ignore", divide="ignore"):
        centres = _wrist_centres(poses, consts)
        phi1 = np.arctan2(centres[0], centres[1])
        phi2 = np.arccos(centres[2])
        shoulders = _shoulders(poses, phi1, phi2, consts)
        wrists = _wrists(poses, shoulders, np.arccos(shoulders[4]), consts)
        theta6 = np.arctan2(wrists[3], wrists[4])
        local = _local_vectors(wrists, theta6, consts)
        # ur_ik's product, the same call on the same layouts.
        n = len(poses)
        rotation = poses[:, :3, :3]
        in_base = (local.reshape(n, 8, 3) @ rotation.transpose(0, 2, 1)).reshape(local.shape)
        _from_shoulder(in_base, poses, _SHOULDER_HEIGHT)
        reach = np.einsum("...i,...i->...", in_base[..., 0, :], in_base[..., 0, :])
        elbows = _elbows(in_base, reach, shoulders, consts)
        base3 = np.arccos(elbows[0])
        offset = np.arctan2(elbows[1], elbows[2])
        column = np.arctan2(elbows[3], elbows[4])
        asin2 = np.arcsin(_sines_of_theta2(base3, reach, consts))
    candidates, distances, tied = _nearest(
        shoulders,
        wrists,
        theta6,
        base3,
        asin2,
        offset,
        column,
        reference,
        slack_lower,
        slack_upper,
        lower,
        upper,
        consts,
    )
    return candidates[np.argsort(distances)] if tied else candidates
