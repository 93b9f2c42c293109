"""The start-state curriculum: seeded starts near the handle for training episodes only."""

import numpy as np
import pytest

import liuxing_envs  # noqa: F401  (registers the ids)
from agents.config import ConfigError
from agents.curriculum import StartNearGrasp, check_start_curriculum
from agents.evaluation import make_env
from agents.training import PeriodicEvaluation, build_vec_env, resolve_config
from liuxing_envs.envs.instrument_grasp import READY_TCP


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
        make_env("InstrumentGrasp-v0"),
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
    always = StartNearGrasp(make_env("InstrumentGrasp-v0"), probability=1.0)
    observation, _ = always.reset(seed=0, options={"tool_start": [0.0, 0.0, 0.2]})
    offset = observation["proprio"][12:15] - observation["instrument"][:3]
    np.testing.assert_allclose(offset, [0.0, 0.0, 0.2], atol=2e-3)
    # The caller's own start options are passed on as given, never mixed with drawn ones.
    with pytest.raises(ValueError, match="jaw_clearance needs tool_start"):
        always.reset(seed=0, options={"jaw_clearance": 0.01})


def test_only_the_training_envs_start_near_the_handle(tmp_path):
    config = resolve_config(
        env_id="InstrumentGrasp-v0",
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
        ("ViewPlanning-v0", {"probability": 0.5}, "InstrumentGrasp-v0 only"),
        ("InstrumentGrasp-v0", {"probablity": 0.5}, "unknown start_curriculum key"),
        ("InstrumentGrasp-v0", {"probability": 1.5}, "probability must be a number in"),
        ("InstrumentGrasp-v0", {"height": [0.05, 0.02]}, "low <= high"),
        ("InstrumentGrasp-v0", {"height": 0.05}, "pair"),
        ("InstrumentGrasp-v0", {"clearance": [0.02, 0.5]}, "clearance must be a number in"),
        ("InstrumentGrasp-v0", {"yaw_jitter": 3}, "yaw_jitter"),
        ("InstrumentGrasp-v0", [0.5], "mapping"),
    ],
)
def test_bad_settings_name_the_problem(env_id, settings, message):
    with pytest.raises(ConfigError, match=message):
        check_start_curriculum(env_id, settings)
