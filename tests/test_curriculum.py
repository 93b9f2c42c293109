"""The start-state curriculum: seeded starts near the handle for training episodes only."""

import json

import numpy as np
import pytest

import liuxing_envs  # noqa: F401  (registers the ids)
from agents import run_folder
from agents.config import ConfigError
from agents.curriculum import (
    STARTED_NEAR,
    AdvanceStartLevel,
    StartNearGrasp,
    check_start_curriculum,
)
from agents.evaluation import make_env
from agents.training import PeriodicEvaluation, build_vec_env, resolve_config
from liuxing_envs.sim.grasp_world import READY_TCP
from tests.test_train import run_train


def tool_offsets(env, seeds):
    """The tool centre's offset from the grasp point, and the clearance of the jaws around the
    handle, at each seeded reset."""
    starts = []
    for seed in seeds:
        observation, _ = env.reset(seed=seed)
        offset = observation["proprio"][12:15] - observation["instrument"][:3]
        clearance = observation["proprio"][17] - env.unwrapped.world.instrument.grasp_width
        starts.append([*offset, clearance])
    return np.array(starts)


def test_starts_near_the_handle_as_often_and_as_close_as_configured():
    env = StartNearGrasp(
        make_env("InstrumentGrasp-v1"),
        probability=0.5,
        height=(0.02, 0.06),
        jitter=0.01,
        clearance=(0.01, 0.03),
    )
    offsets = tool_offsets(env, range(40))
    near = offsets[:, 2] < 0.1
    assert 10 <= near.sum() <= 30  # 40 draws at p = 0.5
    assert np.all(np.abs(offsets[near, :2]) <= 0.01 + 2e-3)
    assert np.all((offsets[near, 2] >= 0.02 - 2e-3) & (offsets[near, 2] <= 0.06 + 2e-3))
    assert np.all((offsets[near, 3] >= 0.01 - 2e-3) & (offsets[near, 3] <= 0.03 + 2e-3))
    far = env.reset(seed=int(np.flatnonzero(~near)[0]))[0]["proprio"][12:15]
    np.testing.assert_allclose(far, READY_TCP, atol=2e-3)
    # Seeded: the same seeds give the same starts; an explicit start is left alone.
    np.testing.assert_array_equal(tool_offsets(env, range(40)), offsets)
    always = StartNearGrasp(make_env("InstrumentGrasp-v1"), probability=1.0)
    observation, _ = always.reset(seed=0, options={"tool_start": [0.0, 0.0, 0.2]})
    offset = observation["proprio"][12:15] - observation["instrument"][:3]
    np.testing.assert_allclose(offset, [0.0, 0.0, 0.2], atol=2e-3)
    # The caller's own start options are passed on as given, never mixed with drawn ones.
    with pytest.raises(ValueError, match="jaw_clearance needs tool_start"):
        always.reset(seed=0, options={"jaw_clearance": 0.01})


def test_the_level_widens_the_starts_towards_the_env_limits():
    env = StartNearGrasp(make_env("InstrumentGrasp-v1"), probability=1.0, height=(0.0, 0.0))
    at_the_handle = tool_offsets(env, range(20))
    assert np.all(np.abs(at_the_handle[:, :2]) <= 0.005 + 2e-3)
    assert np.all(at_the_handle[:, 2] <= 5e-3)  # within millimetres once settled
    env.set_level(1.0)
    widest = tool_offsets(env, range(20))
    # Level 1: up to 30 cm above the grasp point and 5 cm to the side (the workspace clips).
    assert widest[:, 2].max() > 0.15 and np.all(widest[:, 2] <= 0.3 + 2e-3)
    assert np.abs(widest[:, :2]).max() > 0.02 and np.all(np.abs(widest[:, :2]) <= 0.05 + 2e-3)
    with pytest.raises(ConfigError, match="start level must be a number in"):
        env.set_level(1.5)


def test_the_last_step_of_an_episode_says_where_it_started():
    env = StartNearGrasp(make_env("InstrumentGrasp-v1", max_episode_steps=3), probability=0.5)
    started = []
    for seed in range(6):
        observation, _ = env.reset(seed=seed)
        near = observation["proprio"][14] - observation["instrument"][2] < 0.1
        for _ in range(3):
            *_, truncated, info = env.step(np.zeros(env.action_space.shape, np.float32))
            assert (STARTED_NEAR in info) == truncated
        started.append((near, info[STARTED_NEAR]))
    assert {near for near, _ in started} == {True, False}
    assert all(near == flag for near, flag in started)


def feed(callback, *episodes):
    """Ends one training episode per (started near the handle, succeeded) pair."""
    for near, success in episodes:
        callback.update_locals(
            {"dones": [True], "infos": [{STARTED_NEAR: near, "is_success": success}]}
        )
        callback.on_step()


def test_the_level_advances_when_enough_recent_starts_near_the_handle_succeed(tmp_path):
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import Logger

    config = resolve_config(
        env_id="InstrumentGrasp-v1",
        algo="sac",
        hyperparams={"start_curriculum": {"probability": 1.0}, "n_envs": 1},
    )
    venv = build_vec_env(config, tmp_path)
    model = SAC("MultiInputPolicy", venv, buffer_size=10)
    model.set_logger(Logger(folder=None, output_formats=[]))  # learn() would set one up
    callback = AdvanceStartLevel(advance_at=0.5, window=4, level_step=0.4)
    callback.init_callback(model)
    callback.on_training_start({}, {})
    feed(callback, (True, False), (True, False), (True, True))
    feed(callback, (False, True), (False, True))  # from the ready pose: not counted
    assert callback.level == 0.0
    feed(callback, (True, False))  # a full window at 1/4
    assert callback.level == 0.0
    feed(callback, (True, True))  # the window slides to 2/4
    assert callback.level == pytest.approx(0.4)
    assert venv.get_attr("level") == [pytest.approx(0.4)]
    feed(callback, (True, True), (True, True), (True, True))  # a new window, not yet full
    assert callback.level == pytest.approx(0.4)
    feed(callback, (True, True), (True, True), (True, True), (True, True), (True, True))
    assert callback.level == 1.0  # capped
    restored = AdvanceStartLevel(0.5, 4, 0.4, state=json.loads(json.dumps(callback.state())))
    assert restored.state() == callback.state()
    venv.close()


def monitor_rows(monitor_file) -> list[list[str]]:
    """One Monitor file's episodes: reward, length, time and the info keywords, as written."""
    return [line.split(",") for line in monitor_file.read_text().splitlines()[2:]]


def episode_ends(monitor_file, offset: int) -> list[int]:
    """The step counts at which the training episodes of one Monitor file ended."""
    lengths = [int(row[1]) for row in monitor_rows(monitor_file)]
    return (offset + np.cumsum(lengths)).tolist()


@pytest.mark.slow
def test_the_start_level_is_saved_with_checkpoints_and_resumed(tmp_path):
    run_dir = tmp_path / "run"
    # Every episode starts near the handle and raises the level by 0.1.
    curriculum = "start_curriculum={probability: 1.0, advance_at: 0.0, window: 1, level_step: 0.1}"
    run_train(
        *("--env", "InstrumentGrasp-v1", "--algo", "sac", "-n", "400", "--n-envs", "1"),
        *("--run-dir", str(run_dir), "--eval-freq", "0", "--save-freq", "200"),
        *("--final-episodes", "0", "--no-progress-bar"),
        *("--hyperparams", "learning_starts=64", "batch_size=32", "demonstrations=null"),
        curriculum,
    )
    (first,) = (run_dir / run_folder.MONITOR).glob("*.csv")
    ends = episode_ends(first, 0)
    saved = json.loads(run_folder.checkpoint_paths(run_dir, 400)["curriculum"].read_text())
    expected = [[end, round(0.1 * count, 6)] for count, end in enumerate(ends, 1)][:10]
    assert ends and saved["history"] == expected and saved["level"] == expected[-1][1]

    run_train("--resume", str(run_dir), "-n", "800", "--final-episodes", "0", "--no-progress-bar")
    (second,) = set((run_dir / run_folder.MONITOR).glob("*.csv")) - {first}
    ends += episode_ends(second, 400)  # the episode cut at 400 steps was not counted
    result = json.loads((run_dir / run_folder.RESULT).read_text())
    expected = [[end, round(0.1 * count, 6)] for count, end in enumerate(ends, 1)][:10]
    assert len(expected) > len(saved["history"])  # it went on from the saved level
    assert result["start_curriculum"] == {"level": expected[-1][1], "advances": expected}
    flags = {row[-1] for path in (first, second) for row in monitor_rows(path)}
    assert flags == {"True"}


def test_a_corrupt_start_level_is_named(tmp_path):
    path = tmp_path / "curriculum_200_steps.json"
    path.write_text('{"level": 0.5')
    with pytest.raises(run_folder.RunFolderError, match="curriculum_200_steps.json"):
        run_folder.read_curriculum_state(path)
    assert run_folder.read_curriculum_state(tmp_path / "absent.json") is None


def test_only_the_training_envs_start_near_the_handle(tmp_path):
    config = resolve_config(
        env_id="InstrumentGrasp-v1",
        algo="ppo",
        hyperparams={"start_curriculum": {"probability": 1.0}, "n_envs": 1},
    )
    assert config["start_curriculum"]["clearance"] == [0.02, 0.05]  # the defaults filled in
    training = build_vec_env(config, tmp_path)
    observation = training.reset()
    training.close()
    offset = observation["proprio"][0, 12:15] - observation["instrument"][0, :3]
    assert offset[2] < 0.1
    evaluation = PeriodicEvaluation(config, tmp_path, every=1)
    for seed in evaluation.seeds:
        observation, _ = evaluation.env.reset(seed=seed)
        np.testing.assert_allclose(observation["proprio"][12:15], READY_TCP, atol=2e-3)
    evaluation.env.close()


@pytest.mark.parametrize(
    ("env_id", "settings", "message"),
    [
        ("ViewPlanning-v1", {"probability": 0.5}, "InstrumentGrasp tasks only"),
        ("InstrumentGrasp-v1", {"probablity": 0.5}, "unknown start_curriculum key"),
        ("InstrumentGrasp-v1", {"probability": 1.5}, "probability must be a number in"),
        ("InstrumentGrasp-v1", {"height": [0.05, 0.02]}, "low <= high"),
        ("InstrumentGrasp-v1", {"height": 0.05}, "pair"),
        ("InstrumentGrasp-v1", {"clearance": [0.02, 0.5]}, "clearance must be a number in"),
        ("InstrumentGrasp-v1", {"yaw_jitter": 3}, "yaw_jitter"),
        ("InstrumentGrasp-v1", [0.5], "mapping"),
        ("InstrumentGrasp-v1", {"advance_at": 1.2}, "advance_at must be a number in"),
        ("InstrumentGrasp-v1", {"window": 0}, "window must be a whole number"),
        ("InstrumentGrasp-v1", {"window": 2.5}, "window must be a whole number"),
        ("InstrumentGrasp-v1", {"level_step": 0}, "level_step must be a number in"),
    ],
)
def test_bad_settings_name_the_problem(env_id, settings, message):
    with pytest.raises(ConfigError, match=message):
        check_start_curriculum(env_id, settings)
