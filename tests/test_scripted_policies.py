"""The scripted baselines as SB3-style policies: batches of one, new episodes, seeding."""

import copy

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

import liuxing_envs  # noqa: F401  (registers the ids)
from agents.evaluation import run_episodes
from agents.grasp_baselines import PrivilegedGrasp, RandomGrasp, ScriptedGrasp
from agents.view_baselines import FourViewpointBaseline, GreedyOracle, RandomViews


def play(env, policy, seed):
    """One episode in a plain Gymnasium loop: no policy.reset(), no episode_start."""
    observation, _ = env.reset(seed=seed)
    actions, done = [], False
    while not done:
        action, _ = policy.predict(observation)
        actions.append(np.array(action))
        observation, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    return np.array(actions), info


def test_a_scripted_grasp_starts_each_episode_afresh_in_a_plain_loop():
    # It used to carry its phase into the next episode: after a lift it began the next one
    # lifting, and failed it.
    env = gym.make("InstrumentGrasp-v1", terminate_on_success=True)
    policy = PrivilegedGrasp(env)
    first, info = play(env, policy, seed=1)
    assert info["is_success"]
    again, info_again = play(env, policy, seed=2)
    fresh, info_fresh = play(env, PrivilegedGrasp(env), seed=2)
    assert info_fresh["is_success"] and info_again["is_success"]
    np.testing.assert_array_equal(again, fresh)


@pytest.mark.parametrize("action_mode", ["continuous", "discrete"])
def test_view_baselines_take_a_batch_of_one_as_sb3_does(action_mode):
    env = gym.make("ViewPlanning-v1", action_mode=action_mode, object_set="held_out")
    for make in (FourViewpointBaseline, GreedyOracle):
        policy = make(env)
        observation, _ = env.reset(seed=3)
        single, _ = policy.predict(observation)
        batch, _ = policy.predict({key: value[None] for key, value in observation.items()})
        assert np.shape(batch) == (1, *np.shape(single))
        np.testing.assert_array_equal(batch[0], single)
    # SB3's own evaluation loop (batched, with episode_start) plays the same episode.
    vec_env = DummyVecEnv([lambda: Monitor(env)])
    vec_env.seed(3)
    returns, _ = evaluate_policy(
        FourViewpointBaseline(env), vec_env, n_eval_episodes=1, return_episode_rewards=True
    )
    episode = run_episodes(env, FourViewpointBaseline(env), [3], keys=())[0]
    assert returns[0] == pytest.approx(episode["return"], abs=1e-5)


def test_a_batch_of_several_envs_is_refused_by_name():
    env = gym.make("ViewPlanning-v1")
    observation, _ = env.reset(seed=0)
    batch = {key: np.stack([value, value]) for key, value in observation.items()}
    with pytest.raises(ValueError, match="one observation or a batch of one, not a batch of 2"):
        FourViewpointBaseline(env).predict(batch)


@pytest.mark.parametrize(
    ("env_id", "make"), [("ViewPlanning-v1", RandomViews), ("InstrumentGrasp-v1", RandomGrasp)]
)
def test_random_baselines_play_an_episode_by_its_seed_alone(env_id, make):
    env = gym.make(env_id)
    env.action_space.seed(123)
    untouched = copy.deepcopy(env.action_space)
    policy = make(env)
    alone = run_episodes(env, policy, [5], keys=())[0]
    after_others = run_episodes(env, make(env), [0, 1, 5], keys=())[2]
    assert alone["return"] == after_others["return"]
    # The env's own action space is neither reseeded nor drawn from by the policy.
    np.testing.assert_array_equal(env.action_space.sample(), untouched.sample())


@pytest.mark.parametrize(
    ("env_id", "make"), [("ViewPlanning-v1", RandomViews), ("InstrumentGrasp-v1", RandomGrasp)]
)
def test_random_baselines_do_not_replay_the_env_s_own_draws(env_id, make):
    # Gymnasium seeds an env and a space alike: a policy seeded with the episode's seed drew
    # the env's reset stream, so its first random view followed the object drawn.
    env = gym.make(env_id)
    policy = make(env)
    for seed in (0, 7):
        observation, _ = env.reset(seed=seed)
        policy.reset(seed=seed)
        action, _ = policy.predict(observation)
        replayed = copy.deepcopy(env.action_space)
        replayed.seed(seed)
        assert not np.array_equal(np.asarray(action), replayed.sample())


def test_a_scripted_grasp_built_on_one_env_acts_in_another_when_reset():
    # It used to detect a new episode from its own env's step counter, which an env it is not
    # stepped in never moves: it restarted before every action and never grasped.
    kwargs = {"obs_mode": "rgbd", "terminate_on_success": True}
    built_on, played_in = (
        gym.make("InstrumentGrasp-v1", **kwargs),
        gym.make("InstrumentGrasp-v1", **kwargs),
    )
    policy = ScriptedGrasp(built_on)
    policy.reset()
    _, info = play(played_in, policy, seed=1)
    assert info["is_success"]
