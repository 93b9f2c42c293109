"""The MJCF arm and scene: structure, kinematics against the UR5e DH table, physics health."""

import mujoco
import numpy as np
import pytest

from liuxing_envs.assets import asset_path, assets_dir
from liuxing_envs.sim.kinematics import LINK_MASSES, flange_pose_in_base
from liuxing_envs.sim.scene import (
    ARM_ACTUATOR_NAMES,
    ARM_BODY_NAMES,
    ARM_JOINT_NAMES,
    FLANGE_SITE,
    HOME_QPOS,
    load_scene_model,
    reset_to_home,
)


@pytest.fixture(scope="module")
def model():
    return load_scene_model()


def test_assets_resolve_from_checkout_or_wheel():
    assert (assets_dir() / "ur5e.xml").is_file()
    with pytest.raises(FileNotFoundError, match="no asset named 'nope.xml'"):
        asset_path("nope.xml")


def test_object_counts_are_pinned(model):
    # Changing any of these changes every environment built on the scene: bump env versions.
    assert (model.nq, model.nv, model.nu, model.ncam) == (6, 6, 6, 2)
    assert [model.joint(i).name for i in range(model.njnt)] == list(ARM_JOINT_NAMES)
    assert [model.actuator(i).name for i in range(model.nu)] == list(ARM_ACTUATOR_NAMES)
    assert {model.camera(i).name for i in range(model.ncam)} == {"wrist_depth", "overview"}


def test_link_masses_joint_ranges_and_torque_limits_match_the_ur5e(model):
    masses = [model.body(name).mass[0] for name in ARM_BODY_NAMES[1:7]]
    np.testing.assert_allclose(masses, LINK_MASSES)
    two_pi = 2 * np.pi
    expected_ranges = [[-two_pi, two_pi]] * 6
    expected_ranges[2] = [-np.pi, np.pi]
    np.testing.assert_allclose(model.jnt_range, expected_ranges, atol=1e-6)
    np.testing.assert_allclose(model.jnt_actfrcrange[:, 1], [150, 150, 150, 28, 28, 28])
    np.testing.assert_allclose(model.key("home").qpos, HOME_QPOS, atol=1e-6)


def test_forward_kinematics_matches_the_dh_table(model):
    data = mujoco.MjData(model)
    base = model.body("base").id
    flange = model.site(FLANGE_SITE).id
    rng = np.random.default_rng(7)
    for _ in range(50):
        q = rng.uniform(model.jnt_range[:, 0], model.jnt_range[:, 1])
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        base_pose = np.eye(4)
        base_pose[:3, :3] = data.xmat[base].reshape(3, 3)
        base_pose[:3, 3] = data.xpos[base]
        expected = base_pose @ flange_pose_in_base(q)
        np.testing.assert_allclose(data.site_xpos[flange], expected[:3, 3], atol=1e-3)
        rotation = data.site_xmat[flange].reshape(3, 3)
        angle = np.arccos(np.clip((np.trace(expected[:3, :3].T @ rotation) - 1) / 2, -1, 1))
        assert angle < np.deg2rad(0.05)


def test_home_is_collision_free_and_held_by_gravity_compensation(model):
    data = mujoco.MjData(model)
    reset_to_home(model, data)
    assert data.ncon == 0
    mujoco.mj_step(model, data, nstep=1000)  # 2 s under physics
    assert np.max(np.abs(data.qpos - HOME_QPOS)) < 1e-3
    assert np.max(np.abs(data.qvel)) < 1e-3


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_controls_for_seconds_raise_no_warnings(model, seed):
    data = mujoco.MjData(model)
    reset_to_home(model, data)
    rng = np.random.default_rng(seed)
    low, high = model.actuator_ctrlrange.T
    for _ in range(20):  # 20 set-points held for 0.25 s each: 5 s of simulated time
        data.ctrl[:] = np.clip(HOME_QPOS + rng.normal(0, 0.6, 6), low, high)
        mujoco.mj_step(model, data, nstep=125)
    assert data.time == pytest.approx(5.0)
    assert np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))
    assert np.sum(data.warning.number) == 0, [w.number for w in data.warning]
    # The torque limit clamps servo plus gravity compensation, as on the real joint.
    assert np.all(np.abs(data.qfrc_actuator) <= model.jnt_actfrcrange[:, 1] + 1e-9)
