"""The compiled roll-free closed-form IK (liuxing_envs.kernels.ik) against its numpy reference
(ur_ik, then ArmIK.nearest_first): the same candidates in the same order, bit for bit, and
ViewPlanning-v1 episodes that do not change when the kernel is switched off."""

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import liuxing_envs  # noqa: F401  (registers the ids)
from liuxing_envs import kernels
from liuxing_envs.sim.arm import Arm
from liuxing_envs.sim.arm_ik import IK_LIMIT_SLACK, IK_ROLL_SAMPLES, ArmIK
from liuxing_envs.sim.kinematics import flange_pose_in_base
from liuxing_envs.sim.scene import WRIST_CAMERA_SITE, load_scene_model, reset_to_home
from liuxing_envs.sim.ur_ik import ur_ik
from liuxing_envs.sim.viewpoints import sphere_viewpoint

pytest.importorskip("numba")
from liuxing_envs.kernels.ik import nearest_solutions  # noqa: E402
from tests.ik_poses import pose_of_kind
from tests.same_bits import assert_same_bits, assert_same_values

TABLE_POINT = np.array([0.5, 0.0, 0.0])
#: Site poses per kind in the random comparison, each tried at IK_ROLL_SAMPLES rolls.
POSES_PER_KIND = 250


@pytest.fixture(scope="module")
def arm():
    model = load_scene_model()
    data = mujoco.MjData(model)
    reset_to_home(model, data)
    return Arm(model, data)


def rolls(pose, count=IK_ROLL_SAMPLES):
    """``pose`` turned about its own z axis every 360 / count degrees, as the roll-free IK
    tries a camera's rolls."""
    angles = np.linspace(0, 2 * np.pi, count, endpoint=False)
    turn = np.zeros((count, 4, 4))
    turn[:, 0, 0], turn[:, 0, 1] = np.cos(angles), -np.sin(angles)
    turn[:, 1, 0], turn[:, 1, 1] = np.sin(angles), np.cos(angles)
    turn[:, 2, 2] = turn[:, 3, 3] = 1.0
    return pose @ turn


#: The kinds of pose a camera's view can ask for (no wrapped joints; tools point anywhere).
KINDS = (
    "reachable",
    "limits",
    "wrist singularity",
    "straight elbow",
    "wrist above shoulder",
    "out of reach",
    "random",
)


@pytest.mark.parametrize("narrowed", [False, True])
def test_the_kernel_orders_the_same_candidates_as_numpy_bit_for_bit(arm, narrowed):
    lower, upper = arm.lower.copy(), arm.upper.copy()
    if narrowed:  # limits that drop some solutions and leave others a shift inside
        lower[0], upper[0], lower[3], upper[3] = -2.5, 4.0, -np.pi, 1.0
    ik = arm.ik
    original = arm.lower, arm.upper
    arm.lower, arm.upper = lower, upper
    rng = np.random.default_rng(64 + narrowed)
    seen = dict.fromkeys(("candidates", "empty", "dropped", "ties"), 0)
    try:
        for kind in KINDS:
            for _ in range(POSES_PER_KIND):
                pose, reference = pose_of_kind(kind, rng, arm)
                flange_poses = rolls(pose)
                solutions, valid = ur_ik(flange_poses)
                expected = ik.nearest_first(solutions[valid], reference)
                got = nearest_solutions(
                    flange_poses,
                    reference,
                    lower - IK_LIMIT_SLACK,
                    upper + IK_LIMIT_SLACK,
                    lower,
                    upper,
                )
                assert_same_bits(got, expected)
                seen["candidates"] += len(got)
                seen["empty"] += len(got) == 0
                seen["dropped"] += int(valid.sum()) - len(got)
                distances = np.linalg.norm(got - reference, axis=1)
                seen["ties"] += int((np.diff(distances) == 0).any())
    finally:
        arm.lower, arm.upper = original
    assert seen["candidates"] > 50_000 and seen["empty"] > 100 and seen["ties"] > 0
    assert not narrowed or seen["dropped"] > 0


def test_rows_that_are_not_finite_give_no_candidates(arm):
    rng = np.random.default_rng(3)
    flange_poses = rolls(flange_pose_in_base(rng.uniform(-np.pi, np.pi, 6)))
    flange_poses[::3, 0, 3] = np.nan
    flange_poses[1, 1, 3] = np.inf
    reference = arm.qpos
    solutions, valid = ur_ik(flange_poses)
    lower, upper = arm.lower, arm.upper
    got = nearest_solutions(
        flange_poses, reference, lower - IK_LIMIT_SLACK, upper + IK_LIMIT_SLACK, lower, upper
    )
    assert_same_bits(got, arm.ik.nearest_first(solutions[valid], reference))


def test_solve_ik_answers_the_same_with_the_kernel_on_and_off(arm):
    assert arm.ik.compiled is kernels.available()
    assert ArmIK(arm, arm.collision_checks, compiled=False).compiled is False
    rng = np.random.default_rng(9)
    answered = succeeded = 0
    try:
        for _ in range(120):
            eye, rotation = sphere_viewpoint(
                TABLE_POINT + rng.uniform(-0.1, 0.1, 3),
                rng.uniform(-np.pi, np.pi),
                rng.uniform(0.1, 1.6),
                rng.uniform(0.2, 0.9),
            )
            seed_qpos = rng.uniform(arm.lower, arm.upper) if rng.random() < 0.5 else None
            check = rng.random() < 0.5
            results = []
            for compiled in (True, False):
                arm.ik.compiled = compiled
                results.append(
                    arm.solve_ik(
                        eye,
                        rotation,
                        site=WRIST_CAMERA_SITE,
                        roll_free=True,
                        seed_qpos=seed_qpos,
                        check_collisions=check,
                    )
                )
            with_kernel, without = results
            assert_same_bits(with_kernel.qpos, without.qpos)
            for field in ("success", "position_error", "rotation_error", "attempts"):
                assert getattr(with_kernel, field) == getattr(without, field), field
            assert with_kernel.in_collision == without.in_collision
            answered += 1
            succeeded += with_kernel.success
    finally:
        arm.ik.compiled = kernels.available()
    assert answered == 120 and 20 < succeeded < 120


def test_view_planning_episodes_are_the_same_with_the_kernel_on_and_off():
    kwargs = {"objects": ["box", "mug", "cylinder"], "scales": (1.0, 1.2), "coverage_samples": 2048}
    envs = [gym.make("ViewPlanning-v1", **kwargs) for _ in range(2)]
    try:
        assert envs[0].unwrapped.arm.ik.compiled is kernels.available()
        envs[1].unwrapped.arm.ik.compiled = False
        steps = refused = 0
        for seed in range(4):
            first = [env.reset(seed=seed) for env in envs]
            assert_same_values(first[0], first[1], "reset")
            for env in envs:
                env.action_space.seed(seed)
            done = False
            while not done:
                outcomes = [env.step(env.action_space.sample()) for env in envs]
                assert_same_values(outcomes[0], outcomes[1], f"seed {seed}, step {steps}")
                terminated, truncated, info = outcomes[0][2:]
                done = terminated or truncated
                steps += 1
                refused += info["refused"]
        assert steps >= 12 and 0 < refused < steps
    finally:
        for env in envs:
            env.close()
