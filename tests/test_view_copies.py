"""ViewPlanning copies: pickles and deep copies leave out what the settings rebuild, and a
copy taken mid-episode steps on exactly as the original."""

import copy
import pickle

import numpy as np
import pytest

from liuxing_envs.envs.view_planning import ViewPlanningEnv

FAST = {"objects": ["box", "mug", "cylinder"], "scales": (1.0,), "coverage_samples": 2048}


def _steps(env, actions, reset_seed):
    outputs = []
    for action in actions:
        outputs.append(env.step(action))
        if outputs[-1][2] or outputs[-1][3]:
            outputs.append(env.reset(seed=reset_seed))
    return outputs


def _assert_same(outputs, expected):
    assert len(outputs) == len(expected)
    for mine, theirs in zip(outputs, expected, strict=True):
        assert len(mine) == len(theirs)
        obs, obs_expected = mine[0], theirs[0]
        assert obs.keys() == obs_expected.keys()
        for key in obs:
            np.testing.assert_array_equal(obs[key], obs_expected[key], err_msg=key)
        assert mine[1:-1] == theirs[1:-1]
        assert mine[-1].keys() == theirs[-1].keys()
        for key, value in mine[-1].items():
            np.testing.assert_array_equal(value, theirs[-1][key], err_msg=key)


COPIES = {"pickle": lambda env: pickle.loads(pickle.dumps(env)), "deepcopy": copy.deepcopy}


@pytest.mark.parametrize("how", sorted(COPIES))
@pytest.mark.parametrize(
    "settings",
    [
        {"depth_backend": "raycast", "depth_noise": "realsense", "observe_free_space": True},
        {"depth_backend": "raycast", "motion": "dynamic", "privileged": True},
        {"depth_backend": "raycast", "action_mode": "discrete", "motion": "dynamic"},
    ],
    ids=["kinematic-noisy-free-space", "dynamic", "discrete-dynamic"],
)
def test_a_copy_taken_mid_episode_steps_on_as_the_original(how, settings):
    env = ViewPlanningEnv(**FAST, **settings)
    env.action_space.seed(2)
    env.reset(seed=3)
    env.step(env.action_space.sample())
    clone = COPIES[how](env)
    key = (env.placed.name, env.placed.scale)
    actions = [env.action_space.sample() for _ in range(6)]  # past the budget: a reset too
    copied = _steps(clone, actions, reset_seed=8)  # first: the original must not see it
    _assert_same(copied, _steps(env, actions, reset_seed=8))
    # The copy scans on alone; after its reset it shares the process's read-only set-up.
    assert clone.coverage is not env.coverage and clone.coverage.samples is env.coverage.samples
    assert clone.scene.stand_ins(*key).model is env.scene.stand_ins(*key).model
    env.close()
    clone.close()


def test_a_copy_before_the_first_reset_and_after_close_works():
    env = ViewPlanningEnv(**FAST, depth_backend="raycast")
    clone = pickle.loads(pickle.dumps(env))
    _assert_same([clone.reset(seed=1)], [env.reset(seed=1)])
    env.close()
    clone = copy.deepcopy(env)
    _assert_same([clone.reset(seed=2)], [env.reset(seed=2)])


def test_a_pickled_env_with_the_default_objects_is_small():
    env = ViewPlanningEnv(depth_backend="raycast")
    env.reset(seed=0)
    env.step(env.action_space.sample())
    size = len(pickle.dumps(env))
    assert size <= 20e6, f"{size / 1e6:.1f} MB"  # 252 MB when the caches were carried
    env.close()
