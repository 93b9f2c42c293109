"""The grasp step's kernels against their Python references, bit for bit: the one-pose
closed-form IK (liuxing_envs.kernels.one_pose_ik against ur_ik.solutions_of_one, then
ArmIK.nearest_first_of_few), the ee_delta set-point (kernels.one_pose_ik against the
controller's numpy) and the observation (kernels.grasp_observation against the sensor's
Python); InstrumentGrasp-v1 episodes that do not change when the kernels are switched off;
and the grasp step's leaner bookkeeping against what it replaced."""

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import liuxing_envs  # noqa: F401  (registers the ids)
from agents.grasp_baselines import PrivilegedGrasp
from liuxing_envs import kernels
from liuxing_envs.sim.arm import Arm
from liuxing_envs.sim.arm_ik import IK_LIMIT_SLACK
from liuxing_envs.sim.kinematics import flange_pose_in_base
from liuxing_envs.sim.scene import WRIST_CAMERA_SITE, load_scene_model, reset_to_home
from liuxing_envs.sim.ur_ik import solutions_of_one

pytest.importorskip("numba")
from liuxing_envs.kernels import force_loop, one_pose_ik  # noqa: E402
from liuxing_envs.sim.mujoco_errors import error_trap, function_address  # noqa: E402
from tests.ik_poses import KINDS, pose_of_kind
from tests.same_bits import assert_same_bits, assert_same_values

#: Poses per kind in the random comparison.
POSES_PER_KIND = 700


@pytest.fixture(scope="module")
def arm():
    model = load_scene_model()
    data = mujoco.MjData(model)
    reset_to_home(model, data)
    return Arm(model, data)


def reference_order(arm, pose, reference):
    """The Python path: ``nearest_first_of_few(solutions_of_one(pose))`` as an (n, 6) array."""
    ordered = arm.ik.nearest_first_of_few(solutions_of_one(pose), reference)
    return np.array(ordered, dtype=np.float64).reshape(len(ordered), 6)


def kernel_order(arm, pose, reference):
    return one_pose_ik.one_pose_nearest(
        pose, reference, arm.lower, arm.upper, IK_LIMIT_SLACK, one_pose_ik.CONSTANTS
    )


def test_the_kernel_finds_the_same_solutions_bit_for_bit(arm):
    rng = np.random.default_rng(640)
    seen = dict.fromkeys(("solutions", "none", "partial"), 0)
    for kind in KINDS:
        for _ in range(POSES_PER_KIND):
            pose, _ = pose_of_kind(kind, rng, arm)
            expected = solutions_of_one(pose)
            rows, angles = one_pose_ik.solutions_of_one(pose, one_pose_ik.CONSTANTS)
            assert rows.tolist() == [row for row, _ in expected]
            assert_same_bits(angles, np.array([a for _, a in expected]).reshape(len(expected), 6))
            seen["solutions"] += len(expected)
            seen["none"] += not expected
            seen["partial"] += 0 < len(expected) < 8
    assert seen["solutions"] > 25_000 and seen["none"] > 1000 and seen["partial"] > 1000


@pytest.mark.parametrize("narrowed", [False, True])
def test_the_kernel_orders_the_same_solutions_bit_for_bit(arm, narrowed):
    lower, upper = arm.lower.copy(), arm.upper.copy()
    if narrowed:  # limits that drop some solutions and leave others a shift inside
        lower[0], upper[0], lower[3], upper[3] = -2.5, 4.0, -np.pi, 1.0
    original = arm.lower, arm.upper
    arm.lower, arm.upper = lower, upper
    rng = np.random.default_rng(65 + narrowed)
    seen = dict.fromkeys(("solutions", "empty", "dropped", "ties", "clipped"), 0)
    try:
        for kind in KINDS:
            for _ in range(POSES_PER_KIND):
                pose, reference = pose_of_kind(kind, rng, arm)
                expected = reference_order(arm, pose, reference)
                got = kernel_order(arm, pose, reference)
                assert_same_bits(got, expected)
                seen["solutions"] += len(got)
                seen["empty"] += len(got) == 0
                seen["dropped"] += len(solutions_of_one(pose)) - len(got)
                distances = np.linalg.norm(got - reference, axis=1)
                seen["ties"] += int((np.diff(distances) == 0).any())
                seen["clipped"] += int(((got == lower) | (got == upper)).any())
    finally:
        arm.lower, arm.upper = original
    assert seen["solutions"] > 15_000 and seen["empty"] > 1000 and seen["clipped"] > 100
    assert seen["ties"] > 100 and (not narrowed or seen["dropped"] > 5000)


def test_poses_that_are_not_finite_or_huge_give_what_the_reference_gives(arm):
    rng = np.random.default_rng(3)
    checked = 0
    for value in (np.nan, np.inf, -np.inf, 1e300, -1e300, 1e155, 0.0):
        for _ in range(20):
            pose = flange_pose_in_base(rng.uniform(-np.pi, np.pi, 6))
            entry = tuple(rng.integers(0, 3, size=2)), (rng.integers(0, 3), 3)
            pose[entry[rng.integers(2)]] = value
            reference = rng.uniform(arm.lower, arm.upper)
            assert_same_bits(
                kernel_order(arm, pose, reference), reference_order(arm, pose, reference)
            )
            rows, angles = one_pose_ik.solutions_of_one(pose, one_pose_ik.CONSTANTS)
            assert rows.tolist() == [row for row, _ in solutions_of_one(pose)]
            checked += 1
    assert checked == 140


def test_ik_queries_answer_the_same_with_the_kernel_on_and_off(arm):
    """closed_form_nearest (a controller's query) and solve_ik with a fixed roll take the
    one-pose path."""
    assert arm.ik.compiled is kernels.available()
    rng = np.random.default_rng(12)
    answered = found = 0
    try:
        for _ in range(300):
            q = rng.uniform(arm.lower, arm.upper)
            posed = arm.pose_scratch(q)
            site = WRIST_CAMERA_SITE
            sid = arm.site_id(site)
            position = posed.site_xpos[sid] + rng.normal(scale=0.05, size=3)
            rotation = posed.site_xmat[sid].reshape(3, 3).copy()
            reference = q + rng.normal(scale=0.4, size=6)
            results = []
            for compiled in (True, False):
                arm.ik.compiled = compiled
                nearest = arm.ik.closed_form_nearest(position, rotation, reference, site=site)
                solved = arm.solve_ik(
                    position, rotation, site=site, seed_qpos=reference, method="analytic"
                )
                results.append((nearest, solved))
            (nearest, solved), (nearest_py, solved_py) = results
            assert (nearest is None) == (nearest_py is None)
            if nearest is not None:
                assert_same_bits(nearest, nearest_py)
                found += 1
            assert_same_bits(solved.qpos, solved_py.qpos)
            for field in ("success", "position_error", "rotation_error", "attempts"):
                assert getattr(solved, field) == getattr(solved_py, field), field
            answered += 1
    finally:
        arm.ik.compiled = kernels.available()
    assert answered == 300 and 50 < found < 300


def set_compiled(env, compiled):
    for world in env.unwrapped.worlds:
        world.compiled = compiled


@pytest.mark.parametrize(
    ("obs_mode", "force_limit", "seeds", "press", "statuses"),
    [
        ("state", None, (0, 1, 2), False, {force_loop.DONE, force_loop.AWAKE}),
        ("state", 0.5, (4,), False, {force_loop.DONE, force_loop.AWAKE}),
        ("state", 0.1, (1, 3, 5), True, {force_loop.STOPPED}),
        ("depth", None, (6, 3), False, {force_loop.DONE}),
    ],
)
def test_grasp_episodes_are_the_same_with_the_kernel_on_and_off(
    obs_mode, force_limit, seeds, press, statuses, monkeypatch
):
    """The privileged expert (grasps, lifts) with noise, and random actions, in two envs
    stepped alike, one with the kernels and one without; a low force limit (and so hard limit)
    makes the expert's grasps protective stops, and random actions pressing down (``press``)
    make stops on the tray while the instrument sleeps, which the compiled force loop meets
    itself. ``statuses``: how the compiled force loop must have ended at least once."""
    seen = set()
    sleeping_samples = force_loop.sleeping_samples

    def spy(*arguments):
        status, sample = sleeping_samples(*arguments)
        seen.add(status)
        return status, sample

    monkeypatch.setattr(force_loop, "sleeping_samples", spy)
    kwargs = {"obs_mode": obs_mode, "instruments": ["scalpel", "tissue_forceps"]}
    if obs_mode == "depth":
        kwargs["resolution"] = 32
    if force_limit is not None:
        kwargs["force_limit"] = force_limit
    envs = [gym.make("InstrumentGrasp-v1", **kwargs) for _ in range(2)]
    try:
        assert envs[0].unwrapped.world.compiled is kernels.available()
        set_compiled(envs[1], False)
        rng = np.random.default_rng(8)
        steps = grasped = stopped = 0
        for seed in seeds:
            first = [env.reset(seed=seed) for env in envs]
            assert_same_values(first[0], first[1], "reset")
            observation = first[0][0]
            expert = PrivilegedGrasp(envs[0]) if seed % 2 == 0 else None
            done, step = False, 0
            while not done and step < 200:
                if expert is None:
                    action = rng.uniform(-1.0, 1.0, envs[0].action_space.shape)
                    if press:
                        action[2] = -1.0
                else:
                    action, _ = expert.predict(observation)
                    if rng.random() < 0.1:
                        action = np.clip(action + rng.normal(scale=0.2, size=action.shape), -1, 1)
                action = np.asarray(action, dtype=np.float32)
                outcomes = [env.step(action) for env in envs]
                assert_same_values(outcomes[0], outcomes[1], f"seed {seed}, step {step}")
                observation, _, terminated, truncated, info = outcomes[0]
                done = terminated or truncated
                grasped += info["grasped"]
                stopped += info["hard_limit_exceeded"]
                step += 1
                steps += 1
        assert steps >= (40 if press else 130) * len(seeds)
        assert grasped > 0 if force_limit is None else stopped > 0
        assert statuses <= seen
    finally:
        for env in envs:
            env.close()


def test_the_gripper_s_float_reads_and_slice_writes_match_the_arrays():
    env = gym.make("InstrumentGrasp-v1")
    try:
        env.reset(seed=0)
        for world in env.unwrapped.worlds:
            gripper = world.gripper
            assert gripper.finger_actuators.tolist() == list(
                range(gripper._fingers.start, gripper._fingers.stop)
            )
        world = env.unwrapped.world
        gripper, data, model = world.gripper, world.data, world.model
        rng = np.random.default_rng(0)
        for _ in range(40):
            env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
            values = gripper.fingertip_force_values()
            assert all(type(value) is float for value in values)
            assert list(values) == gripper.fingertip_forces().tolist()
        for force in (2.0, -1.5, 0.0, 100.0):
            gripper.grip(force)
            limit = min(abs(force), gripper.max_force)
            assert (
                model.actuator_forcerange[gripper.finger_actuators].tolist()
                == [[-limit, limit]] * 2
            )
            ctrl = data.ctrl[gripper.finger_actuators].tolist()
            assert ctrl == [0.0 if force > 0.0 else 0.04] * 2
            assert gripper.commanded_opening() == ctrl[0] + ctrl[1]
        gripper.command(0.03)
        assert data.ctrl[gripper.finger_actuators].tolist() == [0.015, 0.015]
    finally:
        env.close()


def random_arm_poses(world, rng, count):
    """Put the live arm, ``count`` times, with its tool at a random point of (and around) the
    workspace, pointing down at a random yaw, then each joint turned by up to 0.05 rad (as
    the compliant arm tilts), its kinematics computed."""
    low, high = world.workspace_lower - 0.03, world.workspace_upper + 0.03
    placed = 0
    while placed < count:
        try:
            world.place_tool(rng.uniform(low, high), rng.uniform(-np.pi, np.pi), 0.04, None)
        except ValueError:  # out of the arm's reach
            continue
        qpos = world.arm.qpos + rng.uniform(-0.05, 0.05, 6)
        world.data.qpos[world.arm.qpos_indices] = qpos
        mujoco.mj_kinematics(world.model, world.data)
        placed += 1
        yield


@pytest.mark.parametrize("numpy_blas", [True, False])
def test_the_ee_delta_set_point_is_the_same_with_the_kernels_on_and_off(numpy_blas, monkeypatch):
    """Random arm poses (their tool centres in and out of the workspace) and actions (the
    corners of the action box among them), whole and scaled moves; the set-point in one
    kernel that calls numpy's BLAS, and in two around numpy's matrix products where that
    BLAS is not found."""
    if numpy_blas:
        if np.show_config(mode="dicts")["Build Dependencies"]["blas"]["name"] != "scipy-openblas":
            pytest.skip("this numpy is not built with the OpenBLAS of numpy's wheels")
        assert kernels.numpy_dgemm() is not None, "numpy's BLAS was not found"
    else:
        monkeypatch.setattr(kernels, "numpy_dgemm", lambda: None)
    env = gym.make("InstrumentGrasp-v1")
    try:
        env.reset(seed=0)
        world, controller = env.unwrapped.world, env.unwrapped.arm_controller
        rng = np.random.default_rng(3)
        answered = 0
        for _ in random_arm_poses(world, rng, 150):
            world.set_arm_ctrl(world.arm.qpos)
            for scale in (1.0, 0.0, 0.37):
                action = rng.choice([-1.0, 0.0, 1.0, rng.uniform(-1, 1)], size=4)
                points = []
                for compiled in (True, False):
                    world.compiled = compiled
                    points.append(controller.set_point(world, action, scale))
                world.compiled = kernels.available()
                assert (points[0] is None) == (points[1] is None)
                if points[0] is not None:
                    assert_same_bits(points[0], points[1])
                    answered += 1
        assert answered > 100
    finally:
        env.close()


def test_the_observation_is_the_same_with_the_kernels_on_and_off():
    """Random arm poses, and a handle along world y (its axis' x exactly 0, where the jaws'
    yaw is pi/2 by definition)."""
    env = gym.make("InstrumentGrasp-v1")
    try:
        env.reset(seed=1)
        world, sensor = env.unwrapped.world, env.unwrapped.sensor
        grasp_site = world.model.site("instrument/grasp").id
        rng = np.random.default_rng(4)
        for _ in random_arm_poses(world, rng, 60):
            if rng.random() < 0.3:
                world.data.site_xmat[grasp_site] = [0, -1, 0, 1, 0, 0, 0, 0, 1]
            opening = float(rng.uniform(0.0, 0.08))
            observations = []
            for compiled in (True, False):
                world.compiled = compiled
                observations.append(sensor.observe(world, opening))
            world.compiled = kernels.available()
            assert_same_values(observations[0], observations[1], "observation")
    finally:
        env.close()


def brute_force_approach(world, distance, min_gap):
    """``approach_directions`` as it was: every pad against every instrument geom."""
    model, data = world.model, world.data
    geoms = np.flatnonzero(model.geom_bodyid == model.body("instrument/body").id)
    fromto, near = np.zeros(6), []
    for pad in world.gripper.pad_geoms:
        nearest, toward = distance, None
        for geom in geoms:
            gap = mujoco.mj_geomDistance(model, data, pad, geom, nearest, fromto)
            if gap < nearest:
                nearest = gap
                toward = (fromto[3:] - fromto[:3]) / gap if gap > 0 else None
        if toward is not None and nearest >= min_gap:
            near.append((pad, toward, nearest))
    return near


@pytest.mark.parametrize("compiled", [True, False])
def test_the_approach_query_skips_only_pads_far_from_the_instrument(compiled):
    """Along the expert's approaches and grasps of three instruments, with a wide and the
    default distance: the bounding-sphere filter, by its kernel and by numpy, changes no
    answer."""
    env = gym.make("InstrumentGrasp-v1", instruments=["scalpel", "scissors", "retractor"])
    set_compiled(env, compiled)
    try:
        near_steps = 0
        for seed in range(3):
            observation, _ = env.reset(seed=seed)
            expert, world = PrivilegedGrasp(env), env.unwrapped.world
            for _ in range(200):
                observation, _, terminated, truncated, _ = env.step(expert.predict(observation)[0])
                for distance, min_gap in ((0.015, 1e-5), (0.08, 0.0005)):
                    found = world.approach_directions(distance, min_gap)
                    expected = brute_force_approach(world, distance, min_gap)
                    assert_same_values(found, expected, f"seed {seed}")
                    near_steps += bool(found)
                if terminated or truncated:
                    break
        assert near_steps > 200
    finally:
        env.close()


#: A chain of 30 hinged balls with too little memory for a step: MuJoCo's stack overflows.
_STARVED_MODEL = (
    "<mujoco><size memory='4K'/><worldbody>"
    + "<body pos='0 0 .1'><joint type='hinge'/><geom size='.05'/>" * 30
    + "</body>" * 30
    + "</worldbody></mujoco>"
)
_FREE_BALL = (
    "<mujoco><worldbody><body pos='0 0 .2'><freejoint/><geom size='.1'/></body>"
    "<geom type='plane' size='1 1 .1'/></worldbody></mujoco>"
)


def force_loop_layout(model, data, sensordata, tree_asleep):
    """The force loop's layout for a model without pads: its touches read ``sensordata[0]``
    and its instrument's tree is ``tree_asleep[0]`` (arrays that stand in for mjData's)."""
    from liuxing_envs.sim.stability import DIVERGENCE_WARNINGS

    trap = error_trap()
    layout = np.zeros(force_loop.LAYOUT_SIZE, dtype=np.int64)
    layout[force_loop.MJ_STEP] = function_address("mj_step")
    layout[force_loop.SET_HANDLER], layout[force_loop.HANDLER] = trap.set_handler, trap.handler
    layout[force_loop.JUMP_BUFFER] = trap.jump_buffer.ctypes.data
    layout[force_loop.MODEL], layout[force_loop.DATA] = model._address, data._address
    layout[force_loop.SENSORDATA] = sensordata.ctypes.data
    layout[force_loop.TREE_ASLEEP] = tree_asleep.ctypes.data
    layout[force_loop.QPOS], layout[force_loop.QVEL] = data.qpos.ctypes.data, data.qvel.ctypes.data
    layout[force_loop.NQ], layout[force_loop.NV] = model.nq, model.nv
    layout[force_loop.WARNING_NUMBERS] = data.warning.number.ctypes.data
    layout[force_loop.WARNING_STRIDE] = data.warning.number.strides[0]
    layout[force_loop.DIVERGENCE_WARNINGS :] = [int(w) for w in DIVERGENCE_WARNINGS]
    layout[force_loop.HOOKS], layout[force_loop.HOOK_COUNT] = (
        trap.hooks.ctypes.data,
        len(trap.hooks),
    )
    return layout


def installed_log_handler():
    """This thread's log handler, as MuJoCo's setter reports it (0: none)."""
    import ctypes

    setter = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p)(error_trap().set_handler)
    current = setter(None)
    setter(current)
    return current or 0


def test_the_force_loop_steps_as_mj_step_does_and_leaves_no_handler_installed():
    model = mujoco.MjModel.from_xml_string(_FREE_BALL)
    data, reference = mujoco.MjData(model), mujoco.MjData(model)
    for state in (data, reference):
        state.qvel[:] = [0.3, -0.2, 1.0, 2.0, 1.0, 0.5]
    samples = np.array([5, 5, 3], dtype=np.int64)
    awake = np.full(1, -1, dtype=np.int32)  # a tree that never sleeps: one sample per call
    layout = force_loop_layout(model, data, np.zeros(1), awake)
    peaks, limits, divergence = np.zeros(3), np.array([1.0, 1.0]), np.zeros(2, dtype=np.int64)
    sample = 0
    while sample < len(samples):
        status, sample = force_loop.sleeping_samples(
            layout, samples, sample, model.opt.noslip_iterations, peaks, limits, divergence
        )
        assert status == force_loop.AWAKE
        mujoco.mj_step(model, reference, int(samples[sample]))
        assert_same_bits(data.qpos, reference.qpos)
        assert_same_bits(data.qvel, reference.qvel)
        sample += 1
    assert installed_log_handler() == 0
    # Asleep, the same samples in one call, with the step's divergence verdict.
    awake[0] = 0
    for state in (data, reference):
        mujoco.mj_resetData(model, state)
        state.qvel[:] = [0.3, -0.2, 1.0, 2.0, 1.0, 0.5]
    assert force_loop.sleeping_samples(
        layout, samples, 0, model.opt.noslip_iterations, peaks, limits, divergence
    ) == (force_loop.DONE, len(samples))
    mujoco.mj_step(model, reference, int(samples.sum()))
    assert_same_bits(data.qpos, reference.qpos)
    assert divergence.tolist() == [0, force_loop.STABLE]


@pytest.mark.parametrize(
    ("value", "verdict"),
    [(np.nan, "DIVERGED"), (-np.inf, "DIVERGED"), (1e301, "UNDECIDED"), (1e200, "STABLE")],
)
def test_the_force_loop_s_divergence_verdict_is_what_numpy_s_sums_decide(value, verdict):
    """A state the kernel leaves is judged as ``diverged_since``'s sum of qpos and qvel
    judges it, or left to that sum where only numpy's order of summing decides (a sample of
    no physics steps, so that MuJoCo's own checks do not reset the value first); a step
    that MuJoCo resets, counting a warning, is a divergence."""
    from liuxing_envs.sim.stability import diverged_since, divergence_count

    model = mujoco.MjModel.from_xml_string(_FREE_BALL)
    data = mujoco.MjData(model)
    layout = force_loop_layout(model, data, np.zeros(1), np.zeros(1, dtype=np.int32))
    divergence, peaks, limits = np.zeros(2, dtype=np.int64), np.zeros(3), np.array([1.0, 1.0])

    def run(steps):
        samples = np.array([steps], dtype=np.int64)
        count = divergence_count(data)
        status, _ = force_loop.sleeping_samples(layout, samples, 0, 0, peaks, limits, divergence)
        assert status == force_loop.DONE and divergence[force_loop.COUNT_AT_START] == count
        return count

    data.qvel[3] = value
    count = run(0)
    assert divergence[force_loop.VERDICT] == getattr(force_loop, verdict)
    if verdict != "UNDECIDED":
        assert (verdict == "DIVERGED") == diverged_since(data, count)
    if not np.isfinite(value):
        run(1)  # MuJoCo's check finds it, resets the data and counts a warning
        assert divergence_count(data) == count + 1
        assert divergence[force_loop.VERDICT] == force_loop.DIVERGED


@pytest.mark.parametrize("broken", ["memory", "integrator"])
def test_a_mujoco_error_in_the_force_loop_raises_as_the_bindings_raise_it(broken):
    """A stack too small for a step, and an integrator MuJoCo refuses inside mj_step (an
    error that names the function that raised it)."""
    model = mujoco.MjModel.from_xml_string(_STARVED_MODEL if broken == "memory" else _FREE_BALL)
    if broken != "memory":
        setattr(model.opt, broken, 99)
    with pytest.raises(mujoco.FatalError) as from_bindings:
        mujoco.mj_step(model, mujoco.MjData(model))
    data = mujoco.MjData(model)
    trap = error_trap()
    layout = force_loop_layout(model, data, np.zeros(1), np.zeros(1, dtype=np.int32))
    status, _ = force_loop.sleeping_samples(
        layout, np.array([5], dtype=np.int64), 0, 0, np.zeros(3), np.array([1.0, 1.0]),
        np.zeros(2, dtype=np.int64),
    )  # fmt: skip
    assert status == force_loop.FAILED
    assert installed_log_handler() == 0
    error = trap.error()
    assert isinstance(error, mujoco.FatalError)
    assert str(error) == str(from_bindings.value)
    # The process goes on, and so do the bindings' own error and a healthy model's steps.
    with pytest.raises(mujoco.FatalError):
        mujoco.mj_step(model, mujoco.MjData(model))
    healthy = mujoco.MjModel.from_xml_string(_FREE_BALL)
    mujoco.mj_step(healthy, mujoco.MjData(healthy), 10)


def test_the_force_loop_leaves_steps_with_mujoco_hooks_or_a_busy_kernel_to_the_bindings(
    monkeypatch,
):
    """User code set as a MuJoCo hook runs (and its exception is raised) as in the bindings'
    mj_step; a step while another thread's kernel holds the error handler's buffers goes
    through the bindings too; the episodes are the same as without either."""
    calls, statuses = [], []
    sleeping_samples = force_loop.sleeping_samples

    def spy(*arguments):
        result = sleeping_samples(*arguments)
        statuses.append(result[0])
        return result

    monkeypatch.setattr(force_loop, "sleeping_samples", spy)
    envs = [gym.make("InstrumentGrasp-v1", instruments=["scalpel"]) for _ in range(2)]
    set_compiled(envs[1], False)
    rng = np.random.default_rng(5)
    actions = rng.uniform(-1, 1, (60, envs[0].action_space.shape[0])).astype(np.float32)
    for env in envs:
        env.reset(seed=2)
    try:
        for step, action in enumerate(actions):
            if step == 20:
                mujoco.set_mjcb_control(lambda model, data: calls.append(data.time))
            if step == 40:
                mujoco.set_mjcb_control(None)
                error_trap().lock.acquire()
            hooked, kernel_calls = len(calls), len(statuses)
            outcomes = [env.step(action) for env in envs]
            assert_same_values(outcomes[0], outcomes[1], f"step {step}")
            if 20 <= step < 40:  # both envs' physics ran through the hook
                assert len(calls) - hooked >= 2 * envs[0].unwrapped.substeps
                assert statuses[kernel_calls:] == [force_loop.HOOKED]
            elif 40 <= step < 50:  # the buffers held: no kernel call
                assert len(statuses) == kernel_calls
            else:
                assert force_loop.HOOKED not in statuses[kernel_calls:]
                assert len(statuses) > kernel_calls
            if step == 49:
                error_trap().lock.release()

        def failing(model, data):
            raise ValueError("from the control hook")

        mujoco.set_mjcb_control(failing)
        with pytest.raises(ValueError, match="from the control hook"):
            envs[0].step(actions[0])
    finally:
        mujoco.set_mjcb_control(None)
        if error_trap().lock.locked():
            error_trap().lock.release()
        for env in envs:
            env.close()
