"""Closed-form inverse kinematics of the UR5e (all eight solutions of a flange pose).

The UR arms have three parallel middle joints and intersecting-free wrist offsets that make
the inverse kinematics solvable in closed form (Hawkins 2013, "Analytic inverse kinematics
for the Universal Robots UR-5/UR-10 arms"). For a flange pose in the arm's base frame there
are up to eight solutions: shoulder left/right x wrist up/down x elbow up/down. Solutions
are returned in (-pi, pi]; joints with a wider range may be shifted by whole turns.

Everything is vectorised over a batch of poses, so many candidate poses (for example every
roll of a camera about its optical axis) cost one numpy pass. A single pose (a controller's
target, once per control step) takes a scalar path instead: the same formulas on Python
floats, several times faster than numpy's per-call overhead on arrays of one to eight
elements. The two agree to rounding: within 2e-15 rad for 99% of random poses' solutions and
5e-11 rad at worst in 30,000, near a straight elbow, where the closed form amplifies it. (The
batch sums its 3-vector products in BLAS and einsum, whose order and fused multiply-adds
depend on the CPU.)
"""

from __future__ import annotations

import math

import numpy as np

from liuxing_envs.sim.kinematics import DH_A, DH_D

_D1, _D4, _D5, _D6 = DH_D[0], DH_D[3], DH_D[4], DH_D[5]
_A2, _A3 = DH_A[1], DH_A[2]
#: Solutions closer than this to a singularity (wrist or shoulder) are dropped, in radians
#: of sin(theta5) / in metres of the reach test margins.
_SINGULAR = 1e-6
#: How far past +-1 a cosine (theta 3, theta 5) may round and still count as +-1: a straight
#: elbow or wrist is reachable, not a miss.
COS_SLACK = 1e-9
_SIGNS = np.array([1.0, -1.0])
_TWO_PI = 2 * np.pi
_SHOULDER_HEIGHT = np.array([0.0, 0.0, _D1])  # origin of DH frame 1 in the base frame
#: The scalar path's constants as Python floats (numpy scalars would make its arithmetic slow).
_D1F, _D4F, _D5F, _D6F = (float(d) for d in (_D1, _D4, _D5, _D6))
_A2F, _A3F = float(_A2), float(_A3)


def ur_ik(flange_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All closed-form solutions for a batch of flange poses in the base frame.

    Parameters
    ----------
    flange_poses:
        (N, 4, 4) or (4, 4) homogeneous poses of the flange (DH frame 6) in the base frame.

    Returns
    -------
    solutions:
        (N, 8, 6) joint angles; NaN rows where a branch has no solution.
    valid:
        (N, 8) bool mask of the finite solutions.
    """
    poses = np.asarray(flange_poses, dtype=float)
    if poses.ndim == 2:
        poses = poses[None]
    if poses.shape[1:] != (4, 4):
        raise ValueError(f"flange_poses must be (N, 4, 4), got {poses.shape}")
    n = len(poses)
    if n == 1:
        solutions = np.full((1, 8, 6), np.nan)
        for row, angles in solutions_of_one(poses[0]):
            solutions[0, row] = angles
        return solutions, np.isfinite(solutions).all(axis=2)
    signs = _SIGNS

    # This runs once per environment step on a few dozen poses, so the cost is numpy's
    # per-call overhead, not arithmetic: the branches are broadcast axes (n, shoulder, wrist,
    # elbow) of one pass, and the DH chains are expanded by hand to the few entries needed.
    rotation, p = poses[:, :3, :3], poses[:, :3, 3]
    x_axis, y_axis, z_axis = rotation[:, :, 0], rotation[:, :, 1], rotation[:, :, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        # Theta 1: the wrist-2 centre lies d4 off the plane through the base axis.
        p05 = p - _D6 * z_axis
        radius = np.hypot(p05[:, 0], p05[:, 1])
        phi1 = np.arctan2(p05[:, 1], p05[:, 0])
        phi2 = np.arccos(_D4 / radius)  # NaN where the wrist is inside the shoulder offset
        theta1 = phi1[:, None] + signs * phi2[:, None] + np.pi / 2  # (n, shoulder)
        s1, c1 = np.sin(theta1), np.cos(theta1)
        # Theta 5 from the flange position seen along the rotated shoulder axis.
        cos5 = (p[:, 0, None] * s1 - p[:, 1, None] * c1 - _D4) / _D6
        base5 = np.arccos(np.clip(cos5, -1.0, 1.0))
        base5[np.abs(cos5) > 1.0 + COS_SLACK] = np.nan
        theta5 = base5[:, :, None] * signs  # (n, shoulder, wrist)
        s5, c5 = np.sin(theta5), np.cos(base5)[:, :, None]
        singular = np.abs(s5) < _SINGULAR
        # Row 3 of R16 = Rz(theta234) Ry(-theta5) Rz(theta6) is (s5 c6, -s5 s6, c5), and it
        # equals z1 . R06 with z1 = (s1, -c1, 0): theta6 follows from the x and y columns.
        x_on_z1 = (x_axis[:, 0, None] * s1 - x_axis[:, 1, None] * c1)[:, :, None]
        y_on_z1 = (y_axis[:, 0, None] * s1 - y_axis[:, 1, None] * c1)[:, :, None]
        theta6 = np.arctan2(-y_on_z1 / s5, x_on_z1 / s5)  # singular rows are blanked below
        s6, c6 = np.sin(theta6), np.cos(theta6)
        # The three parallel joints: a planar 3R problem in frame 1. T14 = T10 T06 T65 T54 is
        # needed only for the origin of frame 3 in frame 1, p13 = T14 (0, -d4, 0, 1), and the
        # first column of R14. With alpha = +-pi/2 or 0 the inverse DH transforms are signed
        # permutations, so both are R10 R06 applied to a short vector (and a translation):
        #   T06 T65 T54 (0, -d4, 0, 1) = p + R06 (s6 d5 - c6 s5 d4, c6 d5 + s6 s5 d4, -d6 - c5 d4)
        #   R06 R65 R54 e1 = R06 (c6 c5, -s6 c5, -s5)
        # and R10 = [[c1, s1, 0], [0, 0, 1], [s1, -c1, 0]] with T10 translating by (0, -d1, 0).
        local = np.empty(theta6.shape + (2, 3))  # (n, shoulder, wrist, {p13, column}, xyz)
        local[..., 0, 0] = s6 * _D5 - c6 * s5 * _D4
        local[..., 0, 1] = c6 * _D5 + s6 * s5 * _D4
        local[..., 0, 2] = -_D6 - c5 * _D4
        local[..., 1, 0] = c6 * c5
        local[..., 1, 1] = -s6 * c5
        local[..., 1, 2] = -s5
        in_base = (local.reshape(n, 8, 3) @ rotation.transpose(0, 2, 1)).reshape(local.shape)
        in_base[..., 0, :] += (p - _SHOULDER_HEIGHT)[:, None, None, :]
        # The x rows of R10 (p13 and the column at once); R10 preserves lengths for the reach.
        along_x = c1[:, :, None, None] * in_base[..., 0] + s1[:, :, None, None] * in_base[..., 1]
        p13_x, p13_y, column_x, column_y = (
            along_x[..., 0],
            in_base[..., 0, 2],
            along_x[..., 1],
            in_base[..., 1, 2],
        )
        reach = np.einsum("...i,...i->...", in_base[..., 0, :], in_base[..., 0, :])
        cos3 = (reach - _A2**2 - _A3**2) / (2 * _A2 * _A3)
        # A straight elbow rounds to just past +-1 (its branch would be dropped as NaN).
        cos3 = np.where(np.abs(cos3) <= 1.0 + COS_SLACK, np.clip(cos3, -1.0, 1.0), cos3)
        theta3 = np.arccos(cos3)[..., None] * signs  # (n, shoulder, wrist, elbow)
        theta2 = (
            np.arcsin(_A3 * np.sin(theta3) / np.sqrt(reach)[..., None])
            - np.arctan2(p13_y, -p13_x)[..., None]
        )
        # R34 = Rz(theta3)^T Rz(theta2)^T R14, so theta4 is the angle of R14's first column
        # less theta2 + theta3 (wrapped below).
        theta4 = np.arctan2(column_y, column_x)[..., None] - theta2 - theta3

        q = np.empty((n, 2, 2, 2, 6))
        q[..., 0] = theta1[:, :, None, None]
        q[..., 1] = theta2
        q[..., 2] = theta3
        q[..., 3] = theta4
        q[..., 4] = theta5[..., None]
        q[..., 5] = theta6[..., None]
        q[singular] = np.nan
        # Wrap to (-pi, pi] by whole turns; values already within [-pi, pi] (the float pi)
        # are left untouched, which is what np.angle(np.exp(1j * q)) gives them. NaN stays.
        q -= _TWO_PI * np.rint(q / _TWO_PI)
    solutions = q.reshape(n, 8, 6)
    valid = np.isfinite(solutions).all(axis=2)
    return solutions, valid


def solutions_of_one(pose: np.ndarray) -> list[tuple[int, list[float]]]:
    """``ur_ik`` of one (4, 4) pose on Python floats, the same formulas: its valid solutions
    as ``(row, joint angles)`` in row (branch) order, where ``row`` is the solution's index
    among the batch's eight."""
    solutions: list[tuple[int, list[float]]] = []
    if not np.isfinite(pose).all():
        return solutions
    (x0, y0, z0, px), (x1, y1, z1, py), (x2, y2, z2, pz), _ = pose.tolist()
    # See ur_ik for the geometry of each joint; branches: shoulder, wrist, elbow.
    x05, y05 = px - _D6F * z0, py - _D6F * z1
    radius = float(np.hypot(x05, y05))  # numpy's hypot, as the batch (math.hypot differs)
    if not radius > 0.0 or not _D4F / radius <= 1.0:  # inside the shoulder offset
        return solutions
    phi1, phi2 = math.atan2(y05, x05), math.acos(_D4F / radius)
    for shoulder_row, shoulder in ((0, 1.0), (4, -1.0)):
        theta1 = phi1 + shoulder * phi2 + math.pi / 2
        s1, c1 = math.sin(theta1), math.cos(theta1)
        cos5 = (px * s1 - py * c1 - _D4F) / _D6F
        if abs(cos5) > 1.0 + COS_SLACK:
            continue
        base5 = math.acos(min(max(cos5, -1.0), 1.0))
        c5 = math.cos(base5)
        x_on_z1, y_on_z1 = x0 * s1 - x1 * c1, y0 * s1 - y1 * c1
        for wrist_row, wrist in ((shoulder_row, 1.0), (shoulder_row + 2, -1.0)):
            theta5 = base5 * wrist
            s5 = math.sin(theta5)
            if abs(s5) < _SINGULAR:
                continue
            theta6 = math.atan2(-y_on_z1 / s5, x_on_z1 / s5)
            s6, c6 = math.sin(theta6), math.cos(theta6)
            # p13 and R14's first column in the base frame (R06 times the local vectors).
            u0, u1, u2 = s6 * _D5F - c6 * s5 * _D4F, c6 * _D5F + s6 * s5 * _D4F, -_D6F - c5 * _D4F
            v0, v1, v2 = c6 * c5, -s6 * c5, -s5
            b0 = u0 * x0 + u1 * y0 + u2 * z0 + px
            b1 = u0 * x1 + u1 * y1 + u2 * z1 + py
            b2 = u0 * x2 + u1 * y2 + u2 * z2 + (pz - _D1F)
            column_x = c1 * (v0 * x0 + v1 * y0 + v2 * z0) + s1 * (v0 * x1 + v1 * y1 + v2 * z1)
            column_y = v0 * x2 + v1 * y2 + v2 * z2
            reach = b0 * b0 + b1 * b1 + b2 * b2
            cos3 = (reach - _A2F**2 - _A3F**2) / (2 * _A2F * _A3F)
            if not -1.0 - COS_SLACK <= cos3 <= 1.0 + COS_SLACK:
                continue
            cos3 = min(max(cos3, -1.0), 1.0)
            base3, shoulder_to_wrist = math.acos(cos3), math.sqrt(reach)
            offset = math.atan2(b2, -(c1 * b0 + s1 * b1))
            column = math.atan2(column_y, column_x)
            for row, elbow in ((wrist_row, 1.0), (wrist_row + 1, -1.0)):
                theta3 = base3 * elbow
                sin2 = _A3F * math.sin(theta3) / shoulder_to_wrist
                if not -1.0 <= sin2 <= 1.0:
                    continue
                theta2 = math.asin(sin2) - offset
                theta4 = column - theta2 - theta3
                angles = [
                    angle if -math.pi <= angle <= math.pi else _wrapped(angle)
                    for angle in (theta1, theta2, theta3, theta4, theta5, theta6)
                ]
                solutions.append((row, angles))
    return solutions


def _wrapped(angle: float) -> float:
    """The batch's wrap to (-pi, pi] by whole turns (np.rint and round both round half to even)."""
    return angle - _TWO_PI * round(angle / _TWO_PI)
