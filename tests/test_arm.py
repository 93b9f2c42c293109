"""Arm: IK reach and accuracy, joint limits, collision checks, kinematic and dynamic motion."""

import mujoco
import numpy as np
import pytest

from liuxing_envs.sim.arm import JOINT_LEVER_ARMS, Arm, JointPath
from liuxing_envs.sim.arm_model import subtree
from liuxing_envs.sim.gripper import attach_gripper
from liuxing_envs.sim.kinematics import flange_pose_in_base
from liuxing_envs.sim.scene import (
    ARM_JOINT_NAMES,
    HOME_QPOS,
    WRIST_CAMERA_SITE,
    load_scene_model,
    load_scene_spec,
    reset_to_home,
)
from liuxing_envs.sim.ur_ik import solutions_of_one, ur_ik
from liuxing_envs.sim.viewpoints import look_at, sphere_viewpoint, view_grid

TABLE_POINT = np.array([0.5, 0.0, 0.0])  # on the table, in front of the arm


@pytest.fixture
def sim():
    model = load_scene_model()
    data = mujoco.MjData(model)
    reset_to_home(model, data)
    return model, data, Arm(model, data)


def independent_site_pose(model, qpos, site=WRIST_CAMERA_SITE):
    """Site pose from a fresh MjData, so nothing the Arm caches can agree with itself."""
    data = mujoco.MjData(model)
    data.qpos[:6] = qpos
    mujoco.mj_forward(model, data)
    return data.site(site).xpos.copy(), data.site(site).xmat.reshape(3, 3).copy()


def rotation_angle(a, b):
    return np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))


def hemisphere_views():
    """Radius 0.3-0.45 m, elevation 20-90 deg, azimuth every 30 deg: 183 views."""
    elevations = np.deg2rad([20, 35, 50, 65, 80, 90])
    azimuths = np.deg2rad(np.arange(0, 360, 30))
    return view_grid(TABLE_POINT, (0.30, 0.375, 0.45), elevations, azimuths)


def test_ik_reaches_most_of_the_view_hemisphere_accurately(sim):
    model, data, arm = sim
    views = hemisphere_views()
    assert len(views) == 183
    reached = 0
    for eye, rotation in views:
        result = arm.solve_ik(eye, rotation)
        if not result.success:
            continue
        reached += 1
        assert arm.within_limits(result.qpos)
        assert not arm.in_collision(result.qpos)
        position, actual = independent_site_pose(model, result.qpos)
        assert np.linalg.norm(position - eye) < 2e-3
        assert rotation_angle(actual, rotation) < np.deg2rad(1.0)
    assert reached / len(views) >= 0.8, f"reached {reached} of {len(views)} viewpoints"
    np.testing.assert_allclose(arm.qpos, HOME_QPOS, atol=1e-6)  # asking moved nothing


def test_ik_is_deterministic_and_prefers_the_nearest_equivalent_angles(sim):
    _, _, arm = sim
    eye, rotation = sphere_viewpoint(TABLE_POINT, np.deg2rad(120), np.deg2rad(50), 0.4)
    first, second = arm.solve_ik(eye, rotation), arm.solve_ik(eye, rotation)
    assert first.success
    np.testing.assert_array_equal(first.qpos, second.qpos)
    assert np.all(np.abs(first.qpos - HOME_QPOS) <= np.pi + 1e-9)


def test_ik_respects_narrowed_joint_limits():
    model = load_scene_model()
    model.jnt_range[2] = [0.5, 2.5]  # elbow may only bend one way, and not fully
    data = mujoco.MjData(model)
    data.qpos[:] = [-1.57, -1.57, 1.57, -1.57, -1.57, 0]
    mujoco.mj_forward(model, data)
    arm = Arm(model, data)
    eye, rotation = sphere_viewpoint(TABLE_POINT, np.deg2rad(90), np.deg2rad(60), 0.35)
    result = arm.solve_ik(eye, rotation)
    assert result.success
    assert 0.5 <= result.qpos[2] <= 2.5


def test_unreachable_pose_is_reported_after_every_restart(sim):
    _, _, arm = sim
    result = arm.solve_ik([2.0, 0.0, 0.5], np.eye(3), restarts=5, method="dls")
    assert not result.success
    assert result.attempts == 7  # current, home, then five random seeds
    assert result.position_error > 0.5
    analytic = arm.solve_ik([2.0, 0.0, 0.5], np.eye(3), method="analytic")
    assert not analytic.success and analytic.attempts == 0  # no closed-form solution exists


def test_analytic_and_dls_ik_agree_on_reach_and_accuracy(sim):
    model, _, arm = sim
    outcomes = {}
    for method in ("analytic", "dls"):
        reached = []
        for eye, rotation in hemisphere_views()[::3]:
            result = arm.solve_ik(eye, rotation, method=method)
            reached.append(result.success)
            if result.success:
                position, actual = independent_site_pose(model, result.qpos)
                assert np.linalg.norm(position - eye) < 2e-3
                assert rotation_angle(actual, rotation) < np.deg2rad(1.0)
        outcomes[method] = np.array(reached)
    assert outcomes["analytic"].mean() >= 0.8
    assert np.mean(outcomes["analytic"] == outcomes["dls"]) >= 0.9
    with pytest.raises(ValueError, match="unknown IK method"):
        arm.solve_ik([0.5, 0.0, 0.3], np.eye(3), method="newton")
    with pytest.raises(ValueError, match="analytic IK needs a target rotation"):
        arm.solve_ik([0.5, 0.0, 0.3], method="analytic")


def test_roll_free_ik_aligns_only_the_optical_axis(sim):
    model, _, arm = sim
    eye = np.array([0.5, 0.35, 0.3])
    rotation = look_at(eye, TABLE_POINT)
    result = arm.solve_ik(eye, rotation, roll_free=True)
    assert result.success
    position, actual = independent_site_pose(model, result.qpos)
    assert np.linalg.norm(position - eye) < 2e-3
    assert np.arccos(np.clip(actual[:, 2] @ rotation[:, 2], -1, 1)) < np.deg2rad(1.0)


def test_ik_rejects_malformed_targets(sim):
    _, _, arm = sim
    with pytest.raises(ValueError, match="position must be 3 finite numbers"):
        arm.solve_ik([0.5, np.nan, 0.3])
    with pytest.raises(ValueError, match="proper rotation"):
        arm.solve_ik([0.5, 0.0, 0.3], np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="no site named 'nope'"):
        arm.solve_ik([0.5, 0.0, 0.3], site="nope")


def wrist_into_table(arm):
    target = arm.qpos.copy()
    target[1] += 0.9  # shoulder lift swings the wrist down through the table top
    return target


def test_collision_checks_name_the_contact_and_leave_the_simulation_alone(sim):
    _, data, arm = sim
    before = data.qpos.copy()
    assert arm.collisions() == ()
    contacts = arm.collisions(wrist_into_table(arm))
    assert contacts and any("table_top" in (c.geom1, c.geom2) for c in contacts)
    assert all(c.depth > 0 for c in contacts)
    np.testing.assert_array_equal(data.qpos, before)


def geom_surface_points(model, geom):
    """Points of a primitive geom (local frame) and a radius to add: every point of the
    geom is within that radius of one of them, and the farthest point is among them."""
    kind, size = model.geom_type[geom], model.geom_size[geom]
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        return np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T * size, 0.0
    if kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        angle = np.linspace(0, 2 * np.pi, 72, endpoint=False)
        ring = size[0] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
        rims = [np.c_[ring, np.full(len(ring), z)] for z in (-size[1], size[1])]
        return np.concatenate(rims), 0.0
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return np.array([[0, 0, -size[1]], [0, 0, size[1]]]), size[0]
    assert kind == mujoco.mjtGeom.mjGEOM_SPHERE, f"geom {geom}: add its shape here"
    return np.zeros((1, 3)), size[0]


@pytest.mark.parametrize("tool", ["camera", "gripper"])
def test_joint_lever_arms_bound_the_arm_with_either_tool(tool):
    # The path check spaces its waypoints by these bounds: one too small lets the arm's
    # surface move more than path_check_step between checks, and a thin obstacle slip through.
    spec = load_scene_spec()
    if tool == "gripper":
        attach_gripper(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    arm = Arm(model, data)
    joints = [model.joint(name).id for name in ARM_JOINT_NAMES]
    solid = (model.geom_contype | model.geom_conaffinity) > 0
    beyond = [
        np.flatnonzero(np.isin(model.geom_bodyid, subtree(model, model.jnt_bodyid[j])) & solid)
        for j in joints
    ]
    shapes = {g: geom_surface_points(model, g) for g in np.unique(np.concatenate(beyond))}
    rng = np.random.default_rng(0)
    # Random configurations, and stretched ones (joints near multiples of 90 degrees).
    configurations = [rng.uniform(arm.lower, arm.upper) for _ in range(1000)]
    configurations += [rng.choice([-np.pi / 2, 0, np.pi / 2, np.pi], 6) for _ in range(1000)]
    # The fingers too, anywhere from closed to fully open: open ones reach furthest.
    fingers = [j for j in range(model.njnt) if j not in joints]
    assert len(fingers) == (2 if tool == "gripper" else 0)
    reach = np.zeros(6)
    for qpos in configurations:
        for finger in fingers:
            low, high = model.jnt_range[finger]
            data.qpos[model.jnt_qposadr[finger]] = rng.choice([low, high, rng.uniform(low, high)])
        arm.set_qpos(qpos)
        for k, joint in enumerate(joints):
            anchor, axis = data.xanchor[joint], data.xaxis[joint]
            for geom in beyond[k]:
                local, radius = shapes[geom]
                offsets = data.geom_xpos[geom] + local @ data.geom_xmat[geom].reshape(3, 3).T
                offsets -= anchor
                across = offsets - np.outer(offsets @ axis, axis)
                reach[k] = max(reach[k], np.linalg.norm(across, axis=1).max() + radius)
    assert np.all(reach <= JOINT_LEVER_ARMS), f"{tool}: reach {np.round(reach, 3)}"
    assert reach[0] > 0.9  # the test measured the whole arm, not one link


def test_path_check_finds_the_last_free_waypoint(sim):
    _, _, arm = sim
    target = wrist_into_table(arm)
    check = arm.check_path(arm.qpos, target)
    assert not check.free and 0 < check.fraction < 1
    assert not arm.in_collision(check.last_free_qpos)
    # The arm's surface moves at most path_check_step between checks, so the last free
    # waypoint is within a few steps of the contact.
    assert arm.check_path(arm.qpos, HOME_QPOS + 0.3).free


def test_kinematic_move_reaches_and_reports_its_path(sim):
    model, data, arm = sim
    eye, rotation = sphere_viewpoint(TABLE_POINT, np.deg2rad(200), np.deg2rad(45), 0.4)
    ik = arm.solve_ik(eye, rotation)
    result = arm.move_to(ik.qpos, "kinematic")
    assert result.reached and not result.collided
    np.testing.assert_allclose(arm.qpos, ik.qpos)
    assert result.path_length == pytest.approx(np.linalg.norm(ik.qpos - HOME_QPOS))
    camera_position, _ = arm.site_pose()
    assert np.linalg.norm(camera_position - eye) < 2e-3
    np.testing.assert_array_equal(data.ctrl, ik.qpos)  # the servos hold the new pose


def test_kinematic_move_into_the_table_stops_before_contact(sim):
    _, _, arm = sim
    result = arm.move_to(wrist_into_table(arm), "kinematic")
    assert result.collided and not result.reached
    assert any("table_top" in (c.geom1, c.geom2) for c in result.contacts)
    assert arm.collisions() == ()
    np.testing.assert_allclose(arm.qpos, result.qpos)


def test_dynamic_move_settles_on_target_under_physics(sim):
    model, data, arm = sim
    eye, rotation = sphere_viewpoint(TABLE_POINT, np.deg2rad(90), np.deg2rad(45), 0.4)
    ik = arm.solve_ik(eye, rotation)
    result = arm.move_to(ik.qpos, "dynamic")
    assert result.reached and not result.collided
    assert result.sim_time > 1.0  # 1 rad/s joint speed limit over a > 1 rad move
    assert np.max(np.abs(arm.qpos - ik.qpos)) <= 1e-3
    assert result.path_length >= 0.99 * np.linalg.norm(ik.qpos - HOME_QPOS)
    camera_position, _ = arm.site_pose()
    assert np.linalg.norm(camera_position - eye) < 2e-3
    assert np.sum(data.warning.number) == 0


def test_dynamic_move_into_the_table_makes_a_protective_stop(sim):
    _, data, arm = sim
    result = arm.move_to(wrist_into_table(arm), "dynamic")
    assert result.collided and not result.reached
    assert any("table_top" in (c.geom1, c.geom2) for c in result.contacts)
    np.testing.assert_allclose(data.ctrl, result.qpos)


def test_dynamic_move_times_out_honestly(sim):
    _, _, arm = sim
    target = HOME_QPOS.copy()
    target[0] += 2.0
    result = arm.move_to(target, "dynamic", timeout=0.5)
    assert not result.reached and not result.collided
    assert result.sim_time == pytest.approx(0.5, abs=0.011)


@pytest.mark.parametrize(
    ("qpos", "mode", "message"),
    [
        (np.zeros(5), "kinematic", "6 finite joint angles"),
        (np.full(6, np.nan), "kinematic", "6 finite joint angles"),
        (np.array([0, 0, 4.0, 0, 0, 0]), "kinematic", "outside the joint limits"),
        (HOME_QPOS, "teleport", "allowed: \\('kinematic', 'dynamic'\\)"),
    ],
)
def test_move_rejects_bad_input(sim, qpos, mode, message):
    _, _, arm = sim
    with pytest.raises(ValueError, match=message):
        arm.move_to(qpos, mode)


@pytest.mark.parametrize(
    ("query", "message"),
    [
        (lambda arm: arm.in_collision(np.full(6, np.nan)), "qpos must be 6 finite"),
        (lambda arm: arm.collisions(np.full(6, np.inf)), "qpos must be 6 finite"),
        (lambda arm: arm.in_collision([0.3]), "qpos must be 6 finite"),
        (lambda arm: arm.site_pose(qpos=np.full(6, np.nan)), "qpos must be 6 finite"),
        (lambda arm: arm.check_path(HOME_QPOS, np.full(6, np.nan)), "q_to must be 6 finite"),
        (lambda arm: arm.check_path(np.full(6, np.inf), HOME_QPOS), "q_from must be 6 finite"),
        (
            lambda arm: arm.solve_ik([0.5, 0.0, 0.3], np.eye(3), seed_qpos=np.full(6, np.nan)),
            "seed_qpos must be 6 finite",
        ),
        (
            lambda arm: arm.solve_ik([0.5, 0.0, 0.3], method="dls", max_iterations=0),
            "max_iterations must be an integer in \\[1,",
        ),
        (lambda arm: arm.move_to(HOME_QPOS, "dynamic", max_joint_speed=0.0), "max_joint_speed"),
        (lambda arm: arm.move_to(HOME_QPOS, "dynamic", max_joint_speed=-1.0), "max_joint_speed"),
        (lambda arm: arm.move_to(HOME_QPOS, "dynamic", timeout=np.nan), "timeout"),
    ],
)
def test_queries_and_moves_refuse_configurations_and_settings_that_mean_nothing(
    sim, query, message
):
    # A NaN configuration collides with nothing, so its collision check passed; a negative
    # or NaN speed skipped the ramp and stepped the servos straight to the goal.
    _, data, arm = sim
    before = data.qpos.copy()
    with pytest.raises(ValueError, match=message):
        query(arm)
    np.testing.assert_array_equal(data.qpos, before)


def test_ik_seeded_at_a_joint_limit_returns_that_configuration(sim):
    # The closed form gives an angle at +-2 pi back a rounding error beyond the limit: it was
    # dropped, and the arm sent to another branch up to 5.8 rad away.
    _, _, arm = sim
    rng = np.random.default_rng(4)
    for trial in range(60):
        q = rng.uniform(arm.lower, arm.upper)
        joint = trial % 6
        q[joint] = arm.upper[joint] if trial % 2 else arm.lower[joint]
        if abs(np.sin(q[4])) < 1e-3:
            continue  # the wrist singularity has no unique answer
        position, rotation = arm.site_pose(qpos=q)
        result = arm.solve_ik(position, rotation, seed_qpos=q, check_collisions=False)
        assert result.success and arm.within_limits(result.qpos)
        np.testing.assert_allclose(result.qpos, q, atol=1e-6)


def test_closed_form_ik_solves_a_straight_elbow():
    # cos(theta 3) of a straight elbow rounds to just past 1: the pose counted as unreachable.
    rng = np.random.default_rng(2)
    configurations = rng.uniform(-np.pi, np.pi, (200, 6))
    configurations[:, 2] = 0.0
    configurations[:, 4] = np.where(
        np.abs(np.sin(configurations[:, 4])) < 0.05, 1.0, configurations[:, 4]
    )
    poses = np.stack([flange_pose_in_base(q) for q in configurations])
    _, valid = ur_ik(poses)
    assert valid.any(axis=1).all()
    assert all(solutions_of_one(pose) for pose in poses)


def test_planned_paths_are_followed_in_both_modes(sim):
    _, _, arm = sim
    eye, rotation = sphere_viewpoint(TABLE_POINT, np.deg2rad(150), np.deg2rad(40), 0.4)
    goal = arm.solve_ik(eye, rotation).qpos
    path = arm.plan_path(goal)
    assert path is not None and len(path.waypoints) == 1
    result = arm.follow(path, "kinematic")
    assert result.reached and result.path_length == pytest.approx(path.length)
    np.testing.assert_allclose(arm.qpos, goal)

    back = JointPath(arm.qpos, (HOME_QPOS + 0.2, HOME_QPOS))  # two segments, under physics
    result = arm.follow(back, "dynamic")
    assert result.reached and result.path_length >= 0.99 * back.length
    assert np.max(np.abs(arm.qpos - HOME_QPOS)) <= 1e-3


def test_no_plan_into_the_table_and_paths_must_start_where_the_arm_is(sim):
    _, _, arm = sim
    assert arm.plan_path(wrist_into_table(arm)) is None
    stale = JointPath(HOME_QPOS + 0.1, (HOME_QPOS,))
    with pytest.raises(ValueError, match="does not start at the arm's current configuration"):
        arm.follow(stale)


def test_closed_form_ik_recovers_random_configurations():
    """Every valid closed-form solution reproduces the flange pose, and one of the eight is
    the configuration the pose came from (up to whole turns)."""
    rng = np.random.default_rng(7)
    configurations = rng.uniform(-np.pi, np.pi, (100, 6))
    poses = np.stack([flange_pose_in_base(q) for q in configurations])
    solutions, valid = ur_ik(poses)
    assert valid.sum(axis=1).min() >= 2
    for q, pose, candidates, ok in zip(configurations, poses, solutions, valid, strict=True):
        for candidate in candidates[ok]:
            np.testing.assert_allclose(flange_pose_in_base(candidate), pose, atol=1e-8)
        wrapped = np.angle(np.exp(1j * (candidates[ok] - q)))
        assert np.abs(wrapped).max(axis=1).min() < 1e-6


def test_the_ik_of_one_pose_orders_its_solutions_as_the_batch_does(sim):
    """A controller's query (one pose, roll fixed) shifts, filters and orders its solutions on
    Python floats; the batch (roll-free views) does it in numpy. Same rule, same answers:
    references off by whole turns and joint limits tight enough to drop some solutions."""
    arm = sim[2]
    arm.lower, arm.upper = arm.lower.copy(), arm.upper.copy()
    arm.lower[0], arm.upper[0] = -2.5, 4.0  # some shifted solutions fall outside
    rng = np.random.default_rng(5)
    compared = dropped = 0
    for q in rng.uniform(-np.pi, np.pi, (200, 6)):
        pose = flange_pose_in_base(q)
        reference = q + rng.normal(scale=0.5, size=6) + 2 * np.pi * rng.integers(-1, 2, size=6)
        solutions, valid = ur_ik(pose)
        expected = arm.ik.nearest_first(solutions[valid], reference)
        got = arm.ik.nearest_first_of_few(solutions_of_one(pose), reference)
        assert len(got) == len(expected)
        dropped += int(valid.sum()) - len(got)
        if len(got):
            np.testing.assert_allclose(np.stack(got), expected, atol=1e-9)
            compared += len(got)
    assert compared > 500 and dropped > 20


def test_closed_form_ik_of_one_pose_agrees_with_the_batch_branch_by_branch():
    """One pose (a controller's query) takes a scalar path: the same solutions in the same
    branches as the batch, for reachable, out-of-reach, singular and non-finite poses."""
    rng = np.random.default_rng(11)
    configurations = rng.uniform(-np.pi, np.pi, (300, 6))
    configurations[::10, 4] = 0.0  # the wrist singularity: those branches have no solution
    poses = np.stack([flange_pose_in_base(q) for q in configurations])
    poses[::7, :3, 3] += rng.normal(scale=0.5, size=(len(poses[::7]), 3))  # often out of reach
    poses[::13, :2, 3] = 0.01  # the wrist centre inside the shoulder offset
    poses[299, 0, 3] = np.nan
    batch, batch_valid = ur_ik(poses)
    assert 0 < batch_valid.any(axis=1).sum() < len(poses) - 30
    assert 0 < batch_valid.sum() < batch_valid.size - 300  # some branches of reachable poses fail
    for pose, expected, expected_valid in zip(poses, batch, batch_valid, strict=True):
        solutions, valid = ur_ik(pose)
        assert solutions.shape == (1, 8, 6) and valid.shape == (1, 8)
        np.testing.assert_array_equal(valid[0], expected_valid)
        assert np.isnan(solutions[0][~valid[0]]).all()
        # Rounding differs (the batch sums in BLAS), amplified near a straight elbow.
        np.testing.assert_allclose(solutions[0][valid[0]], expected[expected_valid], atol=1e-9)


def test_a_controllers_closed_form_query_gives_what_solve_ik_gives(sim):
    """closed_form_nearest, the controllers' per-step IK, returns solve_ik's analytic answer
    without its checks: the same joint angles (bit for bit: the same floats) that put the
    site at the pose, None where solve_ik finds no solution, and a clear error for a site
    the closed form cannot serve."""
    model, _, arm = sim
    rng = np.random.default_rng(17)
    solved = unreachable = 0
    for q in rng.uniform(arm.lower / 2, arm.upper / 2, (150, 6)):
        position, rotation = independent_site_pose(model, q)
        if rng.random() < 0.2:
            position = position + rng.choice([-1.0, 1.0], 3) * 1.2  # beyond the arm's reach
        reference = q + rng.normal(scale=0.3, size=6) + 2 * np.pi * rng.integers(-1, 2, size=6)
        reference = np.clip(reference, arm.lower, arm.upper)
        expected = arm.solve_ik(
            position, rotation, seed_qpos=reference, method="analytic", check_collisions=False
        )
        got = arm.closed_form_nearest(position, rotation, reference, site=WRIST_CAMERA_SITE)
        if not expected.success:
            assert got is None
            unreachable += 1
            continue
        np.testing.assert_array_equal(got, expected.qpos)
        reached, turned = independent_site_pose(model, got)
        np.testing.assert_allclose(reached, position, atol=1e-9)
        np.testing.assert_allclose(turned, rotation, atol=1e-9)
        solved += 1
    assert solved > 100 and unreachable > 10
    spec = load_scene_spec()
    spec.body("forearm_link").add_site(name="elbow_marker")
    marked = spec.compile()
    elbow_arm = Arm(marked, mujoco.MjData(marked))
    with pytest.raises(ValueError, match="fixed to the last link, not 'elbow_marker'"):
        elbow_arm.closed_form_nearest(position, rotation, reference, site="elbow_marker")


@pytest.mark.parametrize(
    ("target", "up"),
    [
        ((0.0, 0.0, -1.0), (0.0, 0.0, 1.0)),  # straight down: the fallback up (+x) rolls it
        ((1.0, 0.0, 0.0), (1.0, 0.0, 0.0)),  # along an up that is the fallback itself
        ((0.0, 0.0, 2.0), (0.0, 0.0, 5.0)),  # along a longer up
        ((0.3, -0.2, 0.1), (0.0, 0.0, 1e-9)),  # a short up is still a direction
    ],
)
def test_look_at_gives_a_rotation_looking_at_the_target_for_any_up(target, up):
    rotation = look_at(np.zeros(3), target, up)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    direction = np.asarray(target) / np.linalg.norm(target)
    np.testing.assert_allclose(-rotation[:, 2], direction, atol=1e-12)


@pytest.mark.parametrize("up", [(0.0, 0.0, 0.0), (np.nan, 0.0, 0.0), (np.inf, 0.0, 1.0)])
def test_look_at_refuses_an_up_that_is_no_direction(up):
    with pytest.raises(ValueError, match="up must be a finite non-zero vector"):
        look_at(np.zeros(3), (1.0, 0.0, 0.0), up)


@pytest.mark.parametrize("how", ["copy", "deepcopy", "pickle"])
def test_an_arm_and_its_copies_each_solve_after_the_other_is_gone(sim, how):
    """The arm's parts refer back to it weakly: a shallow copy relinked the shared parts to
    itself, and the original's IK failed once the copy was dropped."""
    import copy
    import gc
    import pickle

    _, _, arm = sim
    eye, rotation = hemisphere_views()[0]
    expected = arm.solve_ik(eye, rotation).qpos
    duplicate = {
        "copy": copy.copy,
        "deepcopy": copy.deepcopy,
        "pickle": lambda a: pickle.loads(pickle.dumps(a)),
    }[how](arm)
    np.testing.assert_array_equal(duplicate.solve_ik(eye, rotation).qpos, expected)
    del duplicate
    gc.collect()
    np.testing.assert_array_equal(arm.solve_ik(eye, rotation).qpos, expected)
