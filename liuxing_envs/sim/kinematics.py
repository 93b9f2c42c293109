"""Reference kinematics of the UR5e: the Denavit-Hartenberg table the MJCF is built from.

The MJCF model (``assets/ur5e.xml``) is the source of truth for simulation; this module is
an independent, closed-form forward kinematics used to check that model and to reason about
the arm without a simulator.
"""

from __future__ import annotations

import numpy as np

#: Standard DH parameters of the UR5e (Universal Robots' published table).
DH_A = np.array([0.0, -0.425, -0.3922, 0.0, 0.0, 0.0])
DH_D = np.array([0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996])
DH_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])

#: Link masses of the UR5e in kg, base to wrist 3.
LINK_MASSES = np.array([3.761, 8.058, 2.846, 1.37, 1.3, 0.365])


def dh_transform(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    """Homogeneous transform Rz(theta) Tz(d) Tx(a) Rx(alpha) of one DH row."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def flange_pose_in_base(joint_angles: np.ndarray) -> np.ndarray:
    """4x4 pose of the tool flange (DH frame 6) in the arm's base frame."""
    joint_angles = np.asarray(joint_angles, dtype=float)
    if joint_angles.shape != (6,):
        raise ValueError(f"expected 6 joint angles, got shape {joint_angles.shape}")
    pose = np.eye(4)
    for theta, d, a, alpha in zip(joint_angles, DH_D, DH_A, DH_ALPHA, strict=True):
        pose = pose @ dh_transform(theta, d, a, alpha)
    return pose
