"""Closed-form inverse kinematics of the UR5e (all eight solutions of a flange pose).

The UR arms have three parallel middle joints and intersecting-free wrist offsets that make
the inverse kinematics solvable in closed form (Hawkins 2013, "Analytic inverse kinematics
for the Universal Robots UR-5/UR-10 arms"). For a flange pose in the arm's base frame there
are up to eight solutions: shoulder left/right x wrist up/down x elbow up/down. Solutions
are returned in (-pi, pi]; joints with a wider range may be shifted by whole turns.

Everything is vectorised over a batch of poses, so many candidate poses (for example every
roll of a camera about its optical axis) cost one numpy pass.
"""

from __future__ import annotations

import numpy as np

from liuxing_envs.sim.kinematics import DH_A, DH_ALPHA, DH_D

_D1, _D4, _D5, _D6 = DH_D[0], DH_D[3], DH_D[4], DH_D[5]
_A2, _A3 = DH_A[1], DH_A[2]
#: Solutions closer than this to a singularity (wrist or shoulder) are dropped, in radians
#: of sin(theta5) / in metres of the reach test margins.
_SINGULAR = 1e-6


def _dh_batch(theta: np.ndarray, joint: int) -> np.ndarray:
    """(N, 4, 4) DH transforms of one joint for a batch of angles."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(DH_ALPHA[joint]), np.sin(DH_ALPHA[joint])
    out = np.zeros((len(theta), 4, 4))
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2], out[:, 0, 3] = ct, -st * ca, st * sa, DH_A[joint] * ct
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2], out[:, 1, 3] = st, ct * ca, -ct * sa, DH_A[joint] * st
    out[:, 2, 1], out[:, 2, 2], out[:, 2, 3] = sa, ca, DH_D[joint]
    out[:, 3, 3] = 1.0
    return out


def _inverse(transforms: np.ndarray) -> np.ndarray:
    rot = transforms[:, :3, :3].transpose(0, 2, 1)
    out = np.zeros_like(transforms)
    out[:, :3, :3] = rot
    out[:, :3, 3] = -np.einsum("nij,nj->ni", rot, transforms[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


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
    signs = np.array([1.0, -1.0])

    x_axis, y_axis, z_axis = poses[:, :3, 0], poses[:, :3, 1], poses[:, :3, 2]
    p = poses[:, :3, 3]
    # The eight branches are extra batch rows (shoulder x wrist x elbow, in that order), so
    # a single pose costs one numpy pass rather than eight.
    # Theta 1: the wrist-2 centre lies d4 off the plane through the base axis.
    p05 = p - _D6 * z_axis
    radius = np.hypot(p05[:, 0], p05[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        phi1 = np.arctan2(p05[:, 1], p05[:, 0])
        phi2 = np.arccos(_D4 / radius)  # NaN where the wrist is inside the shoulder offset
    theta1 = phi1[:, None] + signs * phi2[:, None] + np.pi / 2  # (n, shoulder)
    s1, c1 = np.sin(theta1), np.cos(theta1)
    # Theta 5 from the flange position seen along the rotated shoulder axis.
    with np.errstate(invalid="ignore"):
        cos5 = (p[:, 0, None] * s1 - p[:, 1, None] * c1 - _D4) / _D6
        base5 = np.arccos(np.clip(cos5, -1.0, 1.0))
    base5[np.abs(cos5) > 1.0 + 1e-9] = np.nan
    theta5 = base5[:, :, None] * signs  # (n, shoulder, wrist)
    s5 = np.sin(theta5)
    singular = np.abs(s5) < _SINGULAR
    # Row 3 of R16 = Rz(theta234) Ry(-theta5) Rz(theta6) is (s5 c6, -s5 s6, c5), and it
    # equals z1 . R06 with z1 = (s1, -c1, 0): theta6 follows from the x and y columns.
    x_on_z1 = x_axis[:, 0, None] * s1 - x_axis[:, 1, None] * c1
    y_on_z1 = y_axis[:, 0, None] * s1 - y_axis[:, 1, None] * c1
    with np.errstate(invalid="ignore", divide="ignore"):
        theta6 = np.arctan2(-y_on_z1[:, :, None] / s5, x_on_z1[:, :, None] / s5)
    theta6 = np.where(singular, 0.0, theta6)
    # The three parallel joints: a planar 3R problem in frame 1.
    theta1 = np.broadcast_to(theta1[:, :, None], theta5.shape).reshape(-1)
    theta5, theta6, singular = theta5.reshape(-1), theta6.reshape(-1), singular.reshape(-1)
    t14 = (
        _inverse(_dh_batch(theta1, 0))
        @ np.repeat(poses, 4, axis=0)
        @ _inverse(_dh_batch(theta6, 5))
        @ _inverse(_dh_batch(theta5, 4))
    )
    p13 = (t14 @ np.array([0.0, -_D4, 0.0, 1.0]))[:, :3]
    reach = np.einsum("ni,ni->n", p13, p13)
    with np.errstate(invalid="ignore"):
        cos3 = (reach - _A2**2 - _A3**2) / (2 * _A2 * _A3)
        theta3 = (np.arccos(cos3)[:, None] * signs).reshape(-1)  # (n * 8,)
        theta2 = -np.repeat(np.arctan2(p13[:, 1], -p13[:, 0]), 2) + np.arcsin(
            _A3 * np.sin(theta3) / np.repeat(np.sqrt(reach), 2)
        )
    t34 = (
        _inverse(_dh_batch(theta3, 2)) @ _inverse(_dh_batch(theta2, 1)) @ np.repeat(t14, 2, axis=0)
    )
    theta4 = np.arctan2(t34[:, 1, 0], t34[:, 0, 0])
    q = np.stack(
        [
            np.repeat(theta1, 2),
            theta2,
            theta3,
            theta4,
            np.repeat(theta5, 2),
            np.repeat(theta6, 2),
        ],
        axis=1,
    )
    q[np.repeat(singular, 2)] = np.nan
    solutions = np.angle(np.exp(1j * q)).reshape(n, 8, 6)  # wrap to (-pi, pi]; NaN stays
    valid = np.all(np.isfinite(solutions), axis=2)
    return solutions, valid
