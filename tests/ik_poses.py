"""Hard flange poses for the closed-form IK's bit-for-bit tests: joints at their limits,
singular wrists, straight elbows, wrapped angles, unreachable targets, with reference
configurations that tie or wrap."""

import numpy as np

from liuxing_envs.sim.kinematics import DH_A, DH_D, flange_pose_in_base


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def pose_of_kind(kind, rng, arm):
    """A flange pose in the base frame and a reference configuration, of a hard kind."""
    q = rng.uniform(-np.pi, np.pi, 6)
    if kind == "limits":  # a joint at its limit: solutions a rounding error past it
        joint = rng.integers(6)
        q[joint] = arm.upper[joint] if rng.random() < 0.5 else arm.lower[joint]
        q[joint] += rng.choice([0.0, 1e-12, -1e-12, 5e-10, -5e-10])
    elif kind == "wrist singularity":  # sin(theta 5) about the 1e-6 threshold
        q[4] = rng.choice([0.0, np.pi]) + rng.choice([1.0, -1.0]) * 10 ** rng.uniform(-8, -4)
    elif kind == "straight elbow":  # cos(theta 3) rounds past +-1
        q[2] = rng.choice([0.0, 1e-9, -1e-9, np.pi, -np.pi])
    elif kind == "wrap":  # joints about +-pi, where the solutions wrap by a whole turn
        q = rng.choice([np.pi, -np.pi], size=6) + rng.choice([0.0, 1e-15, -1e-15, 1e-9], size=6)
    pose = flange_pose_in_base(q)
    if kind == "wrist above shoulder":  # the wrist centre within or at d4 of the base axis
        pose[:3, :3] = random_rotation(rng)
        radius = DH_D[3] * rng.choice([0.0, 0.5, 1.0 - 1e-12, 1.0, 1.0 + 1e-12, 1.0 + 1e-6])
        heading = rng.uniform(-np.pi, np.pi)
        centre = np.array(
            [radius * np.cos(heading), radius * np.sin(heading), rng.uniform(-0.3, 0.8)]
        )
        pose[:3, 3] = centre + DH_D[5] * pose[:3, 2]
    elif kind == "out of reach":  # beyond, or at the edge of, the arm's reach
        reach = abs(DH_A[1]) + abs(DH_A[2]) + DH_D[3] + DH_D[5]
        pose[:3, 3] *= reach * rng.uniform(0.9, 1.5) / np.linalg.norm(pose[:3, 3])
    elif kind == "random":  # anywhere within a metre
        pose[:3, :3] = random_rotation(rng)
        pose[:3, 3] = rng.uniform(-1.0, 1.0, 3)
    elif kind == "tool down":  # a grasp controller's targets: the tool pointing down
        yaw = rng.uniform(-np.pi, np.pi)
        c, s = np.cos(yaw), np.sin(yaw)
        pose[:3, :3] = [[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]]
        pose[:3, 3] = [rng.uniform(0.2, 0.8), rng.uniform(-0.4, 0.4), rng.uniform(-0.1, 0.5)]
    reference = [
        q,
        q + rng.normal(scale=0.3, size=6) + 2 * np.pi * rng.integers(-1, 2, size=6),
        rng.uniform(arm.lower, arm.upper),
        np.where(rng.random(6) < 0.5, arm.lower, arm.upper),
        q + rng.choice([np.pi, -np.pi, 3 * np.pi], size=6),  # a half-turn gap: round's ties
    ][rng.integers(5)]
    return pose, reference


#: Every kind pose_of_kind knows.
KINDS = (
    "reachable",
    "limits",
    "wrist singularity",
    "straight elbow",
    "wrap",
    "wrist above shoulder",
    "out of reach",
    "random",
    "tool down",
)
