"""Expert demonstrations seeding SAC's replay buffer (agents/demonstrations.py)."""

from __future__ import annotations

import numpy as np
import pytest
from stable_baselines3 import SAC
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

from agents.config import ConfigError
from agents.demonstrations import check_demonstrations, demonstration_sizes, seed_replay_buffer
from agents.evaluation import make_env

ENV_ID = "InstrumentGraspUnguarded-v1"
ENV_KWARGS: dict = {}
#: The run seed whose first demonstration (seed + 20,000, no noise) the expert lifts here.
SEED = 1


@pytest.mark.parametrize(
    "algo, spec, message",
    [
        ("ppo", {"expert": "privileged-grasp"}, "use them with sac"),
        ("sac", {"expert": "privileged-gasp"}, "did you mean 'privileged-grasp'"),
        ("sac", {"episodes": 3}, "need an expert"),
        ("sac", {"expert": "privileged-grasp", "episode": 3}, "did you mean 'episodes'"),
        ("sac", {"expert": "privileged-grasp", "episodes": 0}, "episodes must be an integer"),
        ("sac", {"expert": "privileged-grasp", "action_noise": -0.1}, "action_noise must be"),
        ("sac", {"expert": "privileged-grasp", "gripper_noise": "x"}, "gripper_noise must be"),
        ("sac", "privileged-grasp", "must be a mapping"),
    ],
)
def test_bad_demonstration_settings_name_the_problem(algo, spec, message):
    with pytest.raises(ConfigError, match=message):
        check_demonstrations(ENV_ID, algo, spec)


def test_view_planning_has_no_expert_and_defaults_are_filled_in():
    with pytest.raises(ConfigError, match="no expert for ViewPlanning-v1"):
        check_demonstrations("ViewPlanning-v1", "sac", {"expert": "privileged-grasp"})
    assert check_demonstrations(ENV_ID, "sac", None) is None
    resolved = check_demonstrations(ENV_ID, "sac", {"expert": "privileged-grasp", "episodes": 2})
    assert resolved["episodes"] == 2 and resolved["action_noise"] > resolved["gripper_noise"] > 0


def _model(n_envs: int, buffer_size: int = 5_000) -> SAC:
    venv = DummyVecEnv([lambda: make_env(ENV_ID, ENV_KWARGS)] * n_envs)
    venv = VecNormalize(venv, norm_reward=False, norm_obs_keys=["proprio", "forces", "instrument"])
    return SAC("MultiInputPolicy", venv, buffer_size=buffer_size, learning_starts=0, seed=0)


def _config(episodes: int) -> dict:
    return {
        "env_id": ENV_ID,
        "env_kwargs": ENV_KWARGS,
        "seed": SEED,
        "n_timesteps": 100_000,
        "demonstrations": check_demonstrations(
            ENV_ID, "sac", {"expert": "privileged-grasp", "episodes": episodes}
        ),
    }


@pytest.mark.parametrize(
    "steps, sizes", [(300, (1, 300)), (12_000, (12, 5_000)), (500_000, (50, 5_000))]
)
def test_a_run_shorter_than_its_demonstrations_takes_as_many_as_it_trains(steps, sizes):
    """A 300-step run spent minutes on 50 expert episodes and 5,000 cloning steps."""
    spec = {"expert": "privileged-grasp", "episodes": 50, "pretrain_steps": 5_000}
    spec = check_demonstrations(ENV_ID, "sac", spec)
    assert demonstration_sizes({"demonstrations": spec, "n_timesteps": steps}) == sizes


@pytest.mark.slow
def test_demonstrations_are_real_transitions_of_the_training_env():
    model = _model(n_envs=1)
    added = seed_replay_buffer(model, _config(episodes=2))
    buffer, normalizer = model.replay_buffer, model.get_vec_normalize_env()
    # The first episode has no noise: the expert lifts the instrument for the whole time limit.
    assert added["successes"] >= 1 and added["transitions"] == buffer.pos > 200
    first = slice(0, 200)
    rewards = buffer.rewards[first, 0]
    assert rewards.max() > 4.0  # grasped, lifted and held: 1 + 2 + 1 + reach
    assert buffer.timeouts[199, 0] and buffer.dones[199, 0]  # truncated, not terminated
    assert not buffer.dones[:199, 0].any()
    # Each stored next observation is the following transition's observation (raw, in metres).
    np.testing.assert_array_equal(
        buffer.next_observations["proprio"][:199, 0], buffer.observations["proprio"][1:200, 0]
    )
    assert np.abs(buffer.actions[: added["transitions"]]).max() <= 1.0
    # The normaliser's statistics start from the demonstrations (SB3 starts them at 1e-4).
    assert normalizer.obs_rms["instrument"].count == pytest.approx(added["transitions"], abs=1)
    tray_height = buffer.observations["instrument"][0, 0, 2]
    assert normalizer.obs_rms["instrument"].mean[2] > tray_height  # lifted for most steps
    model.get_env().close()


@pytest.mark.slow
def test_demonstrations_fill_whole_rows_of_a_multi_env_buffer():
    model = _model(n_envs=2)
    added = seed_replay_buffer(model, _config(episodes=1))
    assert added["transitions"] == 200 and model.replay_buffer.pos == 100
    observations = model.replay_buffer.observations["proprio"]
    # Row r holds transitions 2r and 2r + 1 of the episode, so consecutive steps alternate.
    np.testing.assert_array_equal(
        model.replay_buffer.next_observations["proprio"][:100, 0], observations[:100, 1]
    )
    model.get_env().close()


@pytest.mark.slow
def test_demonstrations_larger_than_the_buffer_are_refused():
    # The ring buffer wrapped and overwrote them before the first update, and the run said
    # it had added all 200.
    model = _model(n_envs=1, buffer_size=150)
    with pytest.raises(ConfigError, match="200 transitions, 200 buffer rows .* buffer_size=150"):
        seed_replay_buffer(model, _config(episodes=1))
    assert model.replay_buffer.pos == 0 and not model.replay_buffer.full
    model.get_env().close()
