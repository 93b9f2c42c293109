"""The path collision checks with and without the margin proof (``ArmCollisions.prove_free``,
:mod:`liuxing_envs.kernels.path_proof`): the same ``PathCheck`` on seeded random paths, free
and colliding, in ViewPlanning's stand-in scenes, the live scene and the gripper arm's; the
same ViewPlanning episodes; and the proof's own premises checked against MuJoCo."""

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import liuxing_envs  # noqa: F401  (registers the envs)
from liuxing_envs.sim.arm import Arm
from liuxing_envs.sim.arm_collisions import PENETRATION_TOLERANCE
from liuxing_envs.sim.gripper import attach_gripper
from liuxing_envs.sim.scene import HOME_QPOS, load_scene_spec, reset_to_home

pytest.importorskip("numba")

from liuxing_envs.kernels.path_proof import TURNING, candidate_pairs  # noqa: E402


def random_paths(arm, rng, count):
    """Straight joint paths from near home, or from anywhere, to anywhere within the
    limits: long free ones, and ones colliding at the start, midway or near the goal."""
    lower, upper = arm.lower, arm.upper
    span = np.minimum(upper - lower, 2 * np.pi)
    centre = np.clip(HOME_QPOS, lower, upper)
    paths = []
    for i in range(count):
        anywhere = centre + (rng.random(6) - 0.5) * span
        near_home = centre + rng.normal(0.0, 0.4, 6)
        q_from = near_home if i % 2 else anywhere
        q_to = centre + (rng.random(6) - 0.5) * span * (0.5 if i % 3 else 1.0)
        paths.append((np.clip(q_from, lower, upper), np.clip(q_to, lower, upper)))
    return paths


def check_both(arm, q_from, q_to):
    """``check_path`` without and with the proof, and the scene data's state after each."""
    checks = arm.collision_checks
    outcomes = []
    for prove in (False, True):
        checks.prove_free = prove
        result = checks.check_path(q_from, q_to)
        d = checks.scene.data
        state = (d.qpos.copy(), d.geom_xpos.copy(), d.contact.dist[: d.ncon].copy())
        outcomes.append((result, state))
    return outcomes


def assert_same(outcomes):
    (plain, plain_state), (proven, proven_state) = outcomes
    assert proven.free == plain.free
    assert proven.fraction == plain.fraction
    assert type(proven.fraction) is type(plain.fraction)
    assert np.array_equal(proven.last_free_qpos, plain.last_free_qpos)
    assert proven.contacts == plain.contacts
    for a, b in zip(plain_state, proven_state, strict=True):
        assert np.array_equal(a, b)


def count_waypoints(arm, paths):
    """How many waypoints MuJoCo checks along ``paths`` with the proof, of how many."""
    checks = arm.collision_checks
    checked, total = 0, 0
    for q_from, q_to in paths:
        waypoints = checks.waypoints(q_from, q_to)
        checks.posed(q_from)
        checked += len(checks._unproven(checks.scene, waypoints))
        total += len(waypoints)
    return checked, total


def test_view_planning_paths_are_the_same_with_and_without_the_proof():
    env = gym.make("ViewPlanning-v1")
    rng = np.random.default_rng(64)
    fractions, checked, total = [], 0, 0
    try:
        for episode in range(6):
            env.reset(seed=100 + episode)
            arm = env.unwrapped.scene.arm
            assert arm.collision_checks.scene is not arm.collision_checks.live_scene
            free_paths = []
            for q_from, q_to in random_paths(arm, rng, 70):
                outcomes = check_both(arm, q_from, q_to)
                assert_same(outcomes)
                fractions.append(outcomes[0][0].fraction)
                if outcomes[0][0].free:
                    free_paths.append((q_from, q_to))
            counts = count_waypoints(arm, free_paths)
            checked, total = checked + counts[0], total + counts[1]
        # Most waypoints of free paths are proven free (99% of a ViewPlanning step's).
        assert checked < 0.2 * total
        fractions = np.array(fractions)
        assert fractions.size == 420
        assert (fractions == 1.0).mean() > 0.1  # free paths
        assert (fractions == 0.0).mean() > 0.1  # colliding at the first waypoint
        assert ((fractions > 0.3) & (fractions < 1.0)).mean() > 0.1  # colliding further on
    finally:
        env.close()


def test_live_scene_and_gripper_arm_paths_are_the_same():
    rng = np.random.default_rng(7)
    for gripper in (False, True):
        spec = load_scene_spec()
        if gripper:
            attach_gripper(spec)
        model = spec.compile()
        data = mujoco.MjData(model)
        reset_to_home(model, data)
        arm = Arm(model, data)
        # The gripper's finger joints (slides) are not the arm's: the proof moves them with
        # the arm and reads their positions from the data.
        if gripper:
            assert model.njnt > 6
            data.qpos[6:] = rng.uniform(0.0, 0.01, model.nq - 6)
        for q_from, q_to in random_paths(arm, rng, 60):
            assert_same(check_both(arm, q_from, q_to))
        checked, total = count_waypoints(arm, random_paths(arm, rng, 20))
        assert checked < total  # the proof is not off there


def test_view_planning_episodes_are_the_same_with_and_without_the_proof():
    runs = []
    for prove in (False, True):
        env = gym.make("ViewPlanning-v1")
        steps = []
        try:
            env.reset(seed=21)
            env.action_space.seed(21)
            env.unwrapped.scene.arm.collision_checks.prove_free = prove
            for _ in range(60):
                obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
                steps.append((obs, reward, terminated, truncated, info))
                if terminated or truncated:
                    obs, info = env.reset()
                    steps.append((obs, info))
        finally:
            env.close()
        runs.append(steps)
    assert len(runs[0]) == len(runs[1])
    for a, b in zip(*runs, strict=True):
        assert_equal_tree(a, b)


def assert_equal_tree(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            assert_equal_tree(a[key], b[key])
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert_equal_tree(x, y)
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b, equal_nan=True)
    else:
        assert a == b or (a != a and b != b)


def stand_in(seed=0):
    env = gym.make("ViewPlanning-v1")
    env.reset(seed=seed)
    return env, env.unwrapped.scene.arm.collision_checks.scene


def pairs_of(scene):
    proof = scene.path_proof
    return proof.pairs(mujoco.get_mjcb_contactfilter() is None, True)


def test_the_candidate_pairs_hold_every_pair_mujoco_tests():
    """A contact-filter callback sees every geom pair that MuJoCo's body filters (weld,
    parent, exclude) and broad phase let through; each one with an arm geom must be a
    candidate whose geom filter (contype, conaffinity) passes."""
    env, scene = stand_in()
    m, d = scene.model, scene.data
    pairs = pairs_of(scene)
    candidates = {(int(a), int(b)) for a, b in pairs[:, :2]}
    seen = set()

    def record(model, data, g1, g2):
        seen.add((min(g1, g2), max(g1, g2)))
        return 1  # no contacts: the callback only watches

    rng = np.random.default_rng(1)
    mujoco.set_mjcb_contactfilter(record)
    try:
        for q in rng.uniform(-np.pi, np.pi, (3000, 6)):
            d.qpos[scene.qpos_at] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_collision(m, d)
    finally:
        mujoco.set_mjcb_contactfilter(None)
        env.close()
    arm_pairs = {
        (a, b)
        for a, b in seen
        if (scene.is_arm_geom[a] or scene.is_arm_geom[b])
        and (m.geom_contype[a] & m.geom_conaffinity[b] or m.geom_contype[b] & m.geom_conaffinity[a])
    }
    assert len(arm_pairs) > 30
    assert arm_pairs <= candidates


def test_the_contact_filter_callback_and_parent_filter_widen_the_pairs():
    env, scene = stand_in()
    try:
        proof = scene.path_proof
        narrow = len(proof.pairs(True, True))
        # Without the bitmask the floor (contype 0) joins: a plane, unbounded, so nothing is
        # proven (MuJoCo's callback decides then).
        assert proof.pairs(False, True) is None
        assert len(proof.pairs(True, False)) > narrow  # neighbouring links join
    finally:
        env.close()


def test_the_turning_pair_is_the_flush_shoulder_on_the_base():
    """The shoulder cylinder turns about its own axis next to the fixed geoms; it sits flush
    on the base's cylinder, the one pair that the margin cannot prove. MuJoCo reports no
    penetration between them at any pan angle."""
    env, scene = stand_in()
    m, d = scene.model, scene.data
    try:
        pairs = pairs_of(scene)
        turning = [(m.geom(a).name, m.geom(b).name) for a, b, kind in pairs if kind == TURNING]
        assert ("base_geom", "shoulder_geom") in turning
        assert all("shoulder_geom" in pair for pair in turning)
        base, shoulder = m.geom("base_geom").id, m.geom("shoulder_geom").id
        deepest = 0.0
        for pan in np.linspace(-2 * np.pi, 2 * np.pi, 4001):
            d.qpos[scene.qpos_at] = [pan, -1.2, 1.0, -1.4, -1.57, 0.0]
            mujoco.mj_kinematics(m, d)
            mujoco.mj_collision(m, d)
            for i in range(d.ncon):
                if {int(g) for g in d.contact.geom[i]} == {base, shoulder}:
                    deepest = min(deepest, float(d.contact.dist[i]))
        assert deepest > -PENETRATION_TOLERANCE / 100
    finally:
        env.close()


def test_a_mesh_lies_in_its_bounding_box():
    """The proof bounds a mesh geom (the placed object) by ``geom_aabb`` in its frame."""
    env, scene = stand_in(seed=5)
    m = scene.model
    try:
        meshes = np.flatnonzero(m.geom_type == mujoco.mjtGeom.mjGEOM_MESH)
        assert meshes.size
        for g in meshes:
            mesh = m.geom_dataid[g]
            start, count = m.mesh_vertadr[mesh], m.mesh_vertnum[mesh]
            vertices = m.mesh_vert[start : start + count]
            centre, half = m.geom_aabb[g, :3], m.geom_aabb[g, 3:]
            # float32 vertices: to their rounding, a thousandth of the proof's margin
            assert (np.abs(vertices - centre) <= half + 1e-6).all()
    finally:
        env.close()


def test_candidate_pairs_follow_a_geom_switched_off():
    """The pair table follows ``geom_contype`` at each path (objects are switched on and off
    in a shared model)."""
    env, scene = stand_in()
    m = scene.model
    try:
        obj = int(np.flatnonzero(~scene.is_arm_geom & (m.geom_bodyid > 0))[-1])
        before = pairs_of(scene)
        saved = m.geom_contype[obj], m.geom_conaffinity[obj]
        m.geom_contype[obj] = m.geom_conaffinity[obj] = 0
        try:
            after = pairs_of(scene)
        finally:
            m.geom_contype[obj], m.geom_conaffinity[obj] = saved
        assert obj in before[:, :2] and obj not in after[:, :2]
        fresh = candidate_pairs(
            scene.path_proof.moving,
            scene.is_arm_geom,
            True,
            True,
            m.body_parentid,
            m.body_weldid,
            m.body_jntnum,
            m.body_jntadr,
            m.jnt_type,
            m.jnt_pos,
            m.jnt_axis,
            m.geom_bodyid,
            m.geom_type,
            m.geom_pos,
            m.geom_quat,
            m.geom_contype,
            m.geom_conaffinity,
            m.exclude_signature,
            m.pair_geom1,
            m.pair_geom2,
        )
        assert np.array_equal(fresh, pairs_of(scene))
    finally:
        env.close()
