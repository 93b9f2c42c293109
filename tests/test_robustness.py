"""Robustness: fuzzed actions, kwargs and reset options; simulator faults; worker errors;
determinism across processes and vector modes.

Property tests use hypothesis with a fixed seed (``derandomize``), so CI runs the same
examples every time.
"""

import json
import math
import os
import subprocess
import sys

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import liuxing_envs  # noqa: F401  (registers the ids)
from liuxing_envs.envs.instrument_grasp import REWARD_TERMS, InstrumentGraspEnv
from liuxing_envs.envs.view_planning import ViewPlanningEnv
from tests.scripts import REPO

FUZZ = settings(
    max_examples=60,
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
VIEW_FAST = {"objects": ["box", "mug"], "scales": (1.0,), "coverage_samples": 1024}
GRASP_FAST = {"instruments": ["scalpel"]}
BAD_VALUES = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, -(10**9), 10**12, "bogus", "", b"\x00"]),
    st.lists(st.text(max_size=3), min_size=1, max_size=3),
    st.dictionaries(st.text(max_size=2), st.integers(), min_size=1, max_size=2),
    st.builds(object),
)


def keyword_names(env_class) -> list[str]:
    return list(env_class.keyword_names())


def state_of(env) -> tuple:
    """Everything a rejected input must leave untouched: the physics state and the RNG."""
    inner = env.unwrapped
    data = inner.data if isinstance(inner, ViewPlanningEnv) else inner.world.data
    return (
        data.qpos.copy(),
        data.qvel.copy(),
        data.ctrl.copy(),
        data.time,
        inner.np_random.bit_generator.state["state"]["state"],
    )


def assert_same_state(a: tuple, b: tuple) -> None:
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.fixture(scope="module")
def view_env():
    env = gym.make("ViewPlanning-v1", depth_backend="raycast", **VIEW_FAST)
    env.reset(seed=0)
    yield env
    env.close()


@pytest.fixture(scope="module")
def grasp_env():
    env = gym.make("InstrumentGrasp-v1", **GRASP_FAST)
    env.reset(seed=0)
    yield env
    env.close()


@pytest.fixture(scope="module")
def discrete_env():
    env = ViewPlanningEnv(action_mode="discrete", **VIEW_FAST)
    env.reset(seed=0)
    yield env
    env.close()


def action_inputs(size: int):
    """Arrays of every shape, dtype and value (NaN, inf, huge), plus non-arrays."""
    floats = st.floats(allow_nan=True, allow_infinity=True, width=32)
    arrays = hnp.arrays(
        dtype=st.sampled_from([np.float32, np.float64, np.float16, np.int64, np.bool_]),
        shape=st.sampled_from([(), (1,), (size,), (size + 1,), (2, size), (size, 1)]),
        elements=None,
    )
    near_valid = hnp.arrays(np.float64, (size,), elements=floats)
    return st.one_of(
        near_valid,
        arrays,
        st.lists(floats, min_size=size, max_size=size),
        st.sampled_from([None, "left", {"a": 1}, [[0.0] * size]]),
    )


def check_fuzzed_step(env, action) -> None:
    """A well-formed finite action steps (clipped) to a valid observation; anything else is
    refused with a message about the action and leaves the simulation exactly as it was."""
    size = env.action_space.shape[0]
    try:
        well_formed = np.asarray(action, dtype=np.float64).shape == (size,)
        finite = well_formed and bool(np.isfinite(np.asarray(action, dtype=np.float64)).all())
    except (TypeError, ValueError):
        well_formed = finite = False
    before = state_of(env)
    if not finite:
        with pytest.raises((ValueError, TypeError), match="action"):
            env.step(action)
        assert_same_state(before, state_of(env))
        return
    obs, reward, terminated, truncated, info = env.step(action)
    assert env.observation_space.contains(obs)
    assert math.isfinite(reward)
    assert not info["sim_unstable"]
    if terminated or truncated:
        env.reset(seed=1)


@FUZZ
@given(action=action_inputs(3))
def test_view_planning_clips_or_refuses_any_action(view_env, action):
    check_fuzzed_step(view_env, action)


@FUZZ
@given(action=action_inputs(5))
def test_instrument_grasp_clips_or_refuses_any_action(grasp_env, action):
    check_fuzzed_step(grasp_env, action)


@FUZZ
@given(
    action=st.one_of(
        st.integers(-(10**6), 10**6),
        st.floats(allow_nan=True, allow_infinity=True),
        st.sampled_from([None, "3", [3], np.array([1, 2])]),
    )
)
def test_discrete_view_planning_takes_indices_only(discrete_env, action):
    env = discrete_env
    before = state_of(env)
    valid = (
        isinstance(action, int | float)
        and math.isfinite(action)
        and float(action).is_integer()
        and 0 <= action < env.action_space.n
    )
    if valid:
        env.step(int(action) if isinstance(action, float) else action)
        env.reset(seed=0)
        return
    with pytest.raises((ValueError, TypeError), match="action"):
        env.step(action)
    assert_same_state(before, state_of(env))


@pytest.mark.parametrize("env_class", [ViewPlanningEnv, InstrumentGraspEnv])
@FUZZ
@given(data=st.data())
def test_bad_kwargs_are_refused_naming_the_kwarg(env_class, data):
    name = data.draw(st.sampled_from(keyword_names(env_class)), label="kwarg")
    value = data.draw(BAD_VALUES, label="value")
    with pytest.raises((ValueError, TypeError, OSError)) as error:
        env_class(**{name: value})
    assert name in str(error.value)


@pytest.mark.parametrize(
    ("env_id", "env_class", "misspelt", "meant"),
    [("ViewPlanning-v1", ViewPlanningEnv, "view_budgett", "view_budget"),
     ("InstrumentGrasp-v1", InstrumentGraspEnv, "max_grip_forse", "max_grip_force")],
)  # fmt: skip
def test_a_misspelt_keyword_is_refused_with_the_closest_name_and_the_allowed_ones(
    env_id, env_class, misspelt, meant
):
    """gym.make with a misspelt keyword got Python's bare TypeError, naming no valid one."""
    with pytest.raises(TypeError) as error:
        gym.make(env_id, **{misspelt: 1})
    message = str(error.value)
    assert f"no keyword argument {misspelt!r} (did you mean {meant!r}?)" in message
    allowed = message.partition("; allowed: ")[2].split(" was raised")[0]
    assert allowed.split(", ") == keyword_names(env_class)


@pytest.mark.parametrize("env_id", ["ViewPlanning-v1", "InstrumentGrasp-v1"])
@FUZZ
@given(
    key=st.text(min_size=1, max_size=8),
    value=st.one_of(st.integers(), st.text(max_size=4), st.floats(allow_nan=True)),
)
def test_unknown_reset_options_are_refused(env_id, key, value, view_env, grasp_env):
    env = view_env if env_id == "ViewPlanning-v1" else grasp_env
    known = {  # each env's own documented options
        "ViewPlanning-v1": {"object", "scale", "position", "yaw"},
        "InstrumentGrasp-v1": {
            *("instrument", "position", "yaw"),
            *("tool_start", "tool_yaw_error", "jaw_clearance"),
        },
    }[env_id]
    if key in known:
        return
    before = state_of(env)
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(seed=0, options={key: value})
    assert_same_state(before, state_of(env))


@pytest.mark.parametrize(
    ("env_id", "options", "message"),
    [
        ("ViewPlanning-v1", {"object": "teapot"}, "object='teapot'"),
        ("ViewPlanning-v1", {"scale": 7.0}, "scale=7.0"),
        ("ViewPlanning-v1", {"position": (math.nan, 0.0)}, "position"),
        ("ViewPlanning-v1", {"yaw": math.inf}, "yaw"),
        ("ViewPlanning-v1", {"position": "here"}, "position"),
        ("InstrumentGrasp-v1", {"instrument": "spoon"}, "instrument='spoon'"),
        ("InstrumentGrasp-v1", {"position": (math.nan, 0.0)}, "position"),
        ("InstrumentGrasp-v1", {"yaw": "north"}, "yaw"),
    ],
)
def test_bad_reset_option_values_name_the_option(env_id, options, message, view_env, grasp_env):
    env = view_env if env_id == "ViewPlanning-v1" else grasp_env
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        env.reset(seed=0, options=options)
    env.reset(seed=0)  # still usable


# --- simulator faults ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("env_id", "kwargs"),
    [("ViewPlanning-v1", VIEW_FAST), ("InstrumentGrasp-v1", GRASP_FAST)],
)
def test_a_closed_env_refuses_to_step_until_it_is_reset(env_id, kwargs):
    """A closed env went on stepping (its renderer made anew), hiding use after close."""
    env = gym.make(env_id, **kwargs)
    env.reset(seed=0)
    action = env.action_space.sample()
    env.step(action)
    env.close()
    env.close()  # twice is harmless
    with pytest.raises(RuntimeError, match=rf"{env_id}: step\(\) after close\(\); reset\(\) it"):
        env.step(action)
    env.reset(seed=0)  # reopens it
    env.step(action)
    env.close()


def test_grasp_physics_divergence_truncates_and_the_next_reset_recovers():
    env = gym.make("InstrumentGrasp-v1", **GRASP_FAST)
    env.reset(seed=0)
    reference = [env.step(env.action_space.sample() * 0)[1] for _ in range(3)]
    env.reset(seed=0)
    world = env.unwrapped.world
    body = mujoco.mj_name2id(world.model, mujoco.mjtObj.mjOBJ_BODY, "instrument/body")
    assert body >= 0
    world.data.xfrc_applied[body, 2] = 1e30  # a force no solver survives
    obs, reward, terminated, truncated, info = env.step(np.zeros(5))
    assert info["sim_unstable"] and truncated and not terminated
    assert reward == 0.0 and all(info[term] == 0.0 for term in REWARD_TERMS)
    assert env.observation_space.contains(obs)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(5))
    env.reset(seed=0)
    assert not world.data.xfrc_applied.any()
    again = [env.step(env.action_space.sample() * 0)[1] for _ in range(3)]
    assert again == reference  # the same episode as before the fault, to the bit
    env.close()


def test_view_planning_dynamic_divergence_truncates_and_the_next_reset_recovers():
    env = ViewPlanningEnv(motion="dynamic", action_mode="discrete", **VIEW_FAST)
    env.reset(seed=0)
    env.data.qvel[:] = 1e12  # beyond MuJoCo's bound on velocities: it resets the data
    obs, reward, terminated, truncated, info = env.step(env.action_space.n - 1)  # top view
    assert info["sim_unstable"] and truncated and not terminated
    assert env.observation_space.contains(obs) and math.isfinite(reward)
    env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.n - 1)
    assert not info["sim_unstable"] and info["reachable"] and not truncated
    env.close()


def test_a_diverging_env_does_not_stop_a_vectorised_rollout():
    envs = gym.make_vec("InstrumentGrasp-v1", num_envs=2, vectorization_mode="sync", **GRASP_FAST)
    envs.reset(seed=0)
    inner = envs.envs[1].unwrapped
    inner.world.data.xfrc_applied[1:, 2] = 1e30
    _, _, _, truncated, info = envs.step(np.zeros((2, 5)))
    assert list(truncated) == [False, True]
    assert list(info["sim_unstable"]) == [False, True]
    for _ in range(3):  # autoreset brings the faulty env back
        _, _, _, truncated, info = envs.step(np.zeros((2, 5)))
        assert not info["sim_unstable"].any()
    envs.close()


# --- workers ---------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("vectorisation", ["gymnasium-async", "sb3-subproc"])
def test_a_failing_worker_names_the_env_and_the_step(vectorisation):
    # A worker whose env raises must not hang the parent: the error reaches it with the env
    # id and the step. Run in a child process so a hang shows up as a timeout, not a stuck CI.
    script = f"""
import numpy as np, gymnasium as gym, liuxing_envs
from tests.test_robustness import failing_grasp_env
if {vectorisation!r} == "gymnasium-async":
    envs = gym.vector.AsyncVectorEnv([failing_grasp_env] * 2)
else:
    from stable_baselines3.common.vec_env import SubprocVecEnv
    envs = SubprocVecEnv([failing_grasp_env] * 2)
envs.reset()
try:
    for _ in range(10):
        envs.step(np.zeros((2, 5)))
except Exception as error:
    print("RAISED", type(error).__name__, error)
"""
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120
    )
    out = result.stdout + result.stderr
    assert "RAISED" in result.stdout, out[-2000:]
    assert "InstrumentGrasp-v1" in out and "step 4" in out, out[-2000:]


@pytest.mark.slow
def test_training_on_a_dying_worker_says_so_and_keeps_a_checkpoint(tmp_path):
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import SubprocVecEnv

    from agents import run_folder, training

    config = training.resolve_config(
        env_id="InstrumentGrasp-v1", n_timesteps=1000, eval_freq=0, save_freq=0, final_episodes=0
    )
    model = PPO(
        config["policy"], SubprocVecEnv([failing_grasp_env] * 2), n_steps=2, batch_size=4, seed=0
    )
    died = r"InstrumentGrasp-v1 env lost a worker: worker \d of 2 \(pid \d+\) exited with status 1"
    with pytest.raises(RuntimeError, match=died) as error:
        training.learn_in_run_folder(model, config, tmp_path, progress_bar=False, resuming=False)
    assert "--resume" in str(error.value)
    # One whole rollout (2 envs x 2 steps) was learnt from before the fourth step failed.
    assert run_folder.latest_checkpoint(tmp_path) == 4


def failing_grasp_env():
    """InstrumentGrasp-v1 whose fourth step fails (a stand-in for any bug in a worker)."""
    env = gym.make("InstrumentGrasp-v1", **GRASP_FAST)
    calls = {"n": 0}
    controller = env.unwrapped.arm_controller
    original = controller.apply

    def apply(*args):
        calls["n"] += 1
        if calls["n"] == 4:
            raise RuntimeError("injected failure")
        return original(*args)

    controller.apply = apply
    return env


# --- determinism -----------------------------------------------------------------------------

_ROLLOUT = """
import sys, json, hashlib, numpy as np, gymnasium as gym, liuxing_envs
env_id, kwargs = sys.argv[1], json.loads(sys.argv[2])
envs = gym.make_vec(env_id, num_envs=2, vectorization_mode=sys.argv[3], **kwargs)
envs.action_space.seed(5)
digest = hashlib.sha256()
obs, _ = envs.reset(seed=[11, 12])
for _ in range(int(sys.argv[4])):
    obs, reward, terminated, truncated, _ = envs.step(envs.action_space.sample())
    for key in sorted(obs):
        digest.update(np.ascontiguousarray(obs[key]).tobytes())
    digest.update(np.asarray(reward, np.float64).tobytes())
envs.close()
print(digest.hexdigest())
"""


@pytest.mark.slow
@pytest.mark.parametrize(
    ("env_id", "kwargs", "steps"),
    [
        ("ViewPlanning-v1", {**VIEW_FAST, "depth_backend": "raycast"}, 12),
        ("InstrumentGrasp-v1", GRASP_FAST, 60),
    ],
)
def test_same_seed_same_bits_across_processes_and_vector_modes(env_id, kwargs, steps):
    digests = [
        subprocess.run(
            [sys.executable, "-c", _ROLLOUT, env_id, json.dumps(kwargs), mode, str(steps)],
            capture_output=True,
            text=True,
            check=True,
            timeout=300,
        ).stdout.strip()
        for mode in ("sync", "sync", "async")
    ]
    assert len(digests[0]) == 64
    assert digests[0] == digests[1] == digests[2]


# --- files -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A tiny finished SAC run on InstrumentGrasp-v1 (normalised observations, a replay
    buffer): every kind of file a run folder holds."""
    from tests.scripts import run_script

    run_dir = tmp_path_factory.mktemp("runs") / "run"
    run_script(
        "train.py",
        *("--env", "InstrumentGrasp-v1", "--algo", "sac", "-n", "128", "--seed", "0"),
        *("--run-dir", str(run_dir), "--eval-freq", "64", "--eval-episodes", "1"),
        *("--save-freq", "64", "--final-episodes", "0", "--no-progress-bar"),
        *("--env-kwargs", "instruments=[scalpel]", "--hyperparams", "learning_starts=32"),
        *("batch_size=16", "normalize=true", "demonstrations=null"),
    )
    return run_dir


def damaged_copy(run_dir, tmp_path, name: str, damage: str):
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    path = copy / name
    content = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(content[: len(content) // 2])
    elif damage == "foreign":
        path.write_bytes(b"this is not what you think it is\n")
    else:
        path.unlink()
    return copy, path


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncated", "foreign", "missing"])
@pytest.mark.parametrize(
    "name",
    [
        "config.yml",
        "checkpoints/model_128_steps.zip",
        "checkpoints/vecnormalize_128_steps.pkl",
        "checkpoints/replay_buffer_128_steps.pkl",
    ],
)
def test_resume_from_a_damaged_file_names_the_file(finished_run, tmp_path, name, damage):
    from tests.scripts import run_script

    run_dir, path = damaged_copy(finished_run, tmp_path, name, damage)
    if damage == "missing" and name.endswith("model_128_steps.zip"):
        expected = "64"  # the checkpoint is gone; the one before it is resumed from
        result = run_script("train.py", "--resume", str(run_dir), "-n", "160", check=False)
        assert result.returncode == 0, result.stderr[-2000:]
        assert "resumed_from_steps: " + expected in (run_dir / "config.yml").read_text()
        return
    if damage == "missing" and "replay_buffer" in name:
        result = run_script("train.py", "--resume", str(run_dir), "-n", "160", check=False)
        assert result.returncode == 0, result.stderr[-2000:]
        assert "resumes with an empty replay buffer" in result.stderr
        return
    result = run_script("train.py", "--resume", str(run_dir), "-n", "160", check=False)
    assert result.returncode == 2, result.stderr[-2000:]
    assert path.name in result.stderr, result.stderr[-2000:]
    assert "Traceback" not in result.stderr


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncated", "foreign"])
@pytest.mark.parametrize("name", ["best_model.zip", "best_vecnormalize.pkl"])
def test_evaluating_a_damaged_policy_names_the_file(finished_run, tmp_path, name, damage):
    from tests.scripts import run_script

    run_dir, path = damaged_copy(finished_run, tmp_path, name, damage)
    result = run_script("evaluate.py", str(run_dir), "--episodes", "1", check=False)
    assert result.returncode == 2, result.stderr[-2000:]
    assert path.name in result.stderr and "Traceback" not in result.stderr


def test_a_crash_mid_save_leaves_the_old_file_and_no_checkpoint(tmp_path):
    from agents import run_folder

    checkpoints = tmp_path / run_folder.CHECKPOINTS
    checkpoints.mkdir()
    complete = run_folder.checkpoint_paths(tmp_path, 64)["model"]
    complete.write_bytes(b"complete")
    half = run_folder.checkpoint_paths(tmp_path, 128)["model"]
    with pytest.raises(KeyboardInterrupt), run_folder.atomic_path(half) as temporary:
        temporary.write_bytes(b"half of a mod")
        raise KeyboardInterrupt  # killed mid-write
    with pytest.raises(KeyboardInterrupt), run_folder.atomic_path(complete) as temporary:
        temporary.write_bytes(b"half of a new version")
        raise KeyboardInterrupt
    assert complete.read_bytes() == b"complete"
    assert sorted(p.name for p in checkpoints.iterdir()) == [complete.name]
    # Even a temporary file left by a killed process (no cleanup ran) is not a checkpoint.
    (checkpoints / f"{half.name}.partial.zip").write_bytes(b"half")
    assert run_folder.latest_checkpoint(tmp_path) == 64


def test_a_foreign_pickle_is_not_taken_for_a_normaliser(tmp_path):
    import pickle

    from agents import run_folder

    path = tmp_path / "vecnormalize.pkl"
    path.write_bytes(pickle.dumps({"not": "a VecNormalize"}))
    with pytest.raises(run_folder.RunFolderError, match="holds a dict, not a VecNormalize"):
        run_folder.load_normalizer(path)


@pytest.mark.parametrize(
    ("command", "out_flag"),
    [
        (["train.py", "-n", "10"], "--run-dir"),
        (["evaluate.py", "four-view", "--env", "ViewPlanning-v1", "--episodes", "1"], "--out"),
        (["-m", "liuxing_envs.demo", "--views", "1"], "--out"),
    ],
    ids=["train", "evaluate", "demo"],
)
def test_an_unknown_mujoco_gl_platform_is_named_with_the_allowed_ones(command, out_flag, tmp_path):
    # import mujoco itself raises on it, before any fallback to ray casting can run.
    result = subprocess.run(
        [sys.executable, *command, out_flag, str(tmp_path / "out")],
        cwd=REPO,
        capture_output=True,
        text=True,
        env={**os.environ, "MUJOCO_GL": "bogus"},
        timeout=120,
    )
    assert result.returncode == 2, result.stderr
    error = " ".join(result.stderr.split())
    assert "MuJoCo cannot start with MUJOCO_GL='bogus'" in error
    assert "egl (headless" in error and "disable (no OpenGL" in error
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "out").exists()
