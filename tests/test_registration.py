"""The registered ids: v1 benchmark tasks, their variants, and the deprecated v0 ids."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.envs.registration import load_env_creator

import liuxing_envs
from liuxing_envs.envs.instrument_grasp import InstrumentGraspEnv
from liuxing_envs.registration import BY_ID, REGISTRATIONS, family

#: Small scenes, so that every id is quick to make.
FAST = {
    "ViewPlanning": {"objects": ["box"], "scales": [1.0], "coverage_samples": 512},
    "InstrumentGrasp": {"instruments": ["scalpel"]},
}


def make_quietly(env_id: str, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env = gym.make(env_id, **FAST[family(env_id)], **kwargs)
    # Gymnasium adds its own "out of date" warning for a v0 id once a v1 exists.
    ours = [w for w in caught if "is deprecated and will be removed" in str(w.message)]
    return env, ours


@pytest.mark.parametrize("registration", REGISTRATIONS, ids=lambda r: r.env_id)
def test_every_id_makes_steps_and_says_whether_it_is_deprecated(registration):
    env, deprecations = make_quietly(registration.env_id)
    try:
        env.action_space.seed(0)
        obs, _ = env.reset(seed=0)
        assert env.observation_space.contains(obs)
        obs, reward, *_ = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs) and np.isfinite(reward)
    finally:
        env.close()
    if registration.deprecated:
        (warning,) = deprecations
        assert f"use {family(registration.env_id)}-v1" in str(warning.message)
    else:
        assert deprecations == []
        # v1 ids end their own episodes: no registered time limit cuts them short.
        assert env.spec.max_episode_steps is None


@pytest.mark.parametrize(
    "registration", [r for r in REGISTRATIONS if r.kwargs], ids=lambda r: r.env_id
)
def test_a_variant_differs_from_its_task_by_its_registered_settings_alone(registration):
    base, _ = make_quietly(f"{family(registration.env_id)}-v1")
    variant, _ = make_quietly(registration.env_id)
    try:
        differences = variant.unwrapped.settings.differences(base.unwrapped.settings)
        assert differences == {
            name: (value, base.unwrapped.settings.flat()[name])
            for name, value in registration.kwargs.items()
            if base.unwrapped.settings.flat()[name] != value
        }
        assert differences  # a variant that changes nothing would be a second name
    finally:
        base.close()
        variant.close()


def test_the_v1_ids_default_to_the_ray_caster_and_v0_kept_its_backend():
    for family_name in FAST:
        v1, _ = make_quietly(f"{family_name}-v1")
        v0, _ = make_quietly(f"{family_name}-v0")
        try:
            assert v1.unwrapped.settings.flat()["depth_backend"] == "raycast"
            assert v0.unwrapped.settings.flat()["depth_backend"] == "auto"
        finally:
            v1.close()
            v0.close()


def test_an_unknown_id_is_named_with_the_closest_registered_one():
    with pytest.raises(
        ValueError, match=r"'InstrumentGrasp-v2' \(did you mean 'InstrumentGrasp-v1'"
    ):
        family("InstrumentGrasp-v2")
    assert set(liuxing_envs.ENV_IDS) == set(BY_ID)


@pytest.mark.parametrize(
    ("env_id", "kwargs", "message"),
    [
        ("ViewPlanningDiscrete-v1", {"action_mode": "continuous"},
         r"ViewPlanningDiscrete-v1 is defined by action_mode='discrete'; for "
         r"action_mode='continuous' make ViewPlanning-v1$"),
        ("InstrumentGraspDepth-v1", {"obs_mode": "state"},
         r"InstrumentGraspDepth-v1 is defined by obs_mode='depth'; for obs_mode='state' make "
         r"InstrumentGrasp-v1$"),
        ("InstrumentGraspDepth-v1", {"obs_mode": "rgbd"},
         r"for obs_mode='rgbd' make InstrumentGraspRGBD-v1$"),
        ("InstrumentGraspUnguarded-v1", {"approach_lead_limit": 0.001},
         r"defined by approach_lead_limit=None, approach_lead_slope=0.0, "
         r"approach_guard_fingers=False; for approach_lead_limit=0.001 make InstrumentGrasp-v1 "
         r"with approach_lead_limit=0.001$"),
    ],
)  # fmt: skip
def test_a_variant_refuses_a_keyword_that_changes_what_defines_it(env_id, kwargs, message):
    with pytest.raises(ValueError, match=message):
        gym.make(env_id, **FAST[family(env_id)], **kwargs)


def test_a_variant_takes_its_own_settings_again_and_any_other_keyword():
    env, _ = make_quietly("ViewPlanningDiscrete-v1", action_mode="discrete", view_budget=2)
    try:
        assert env.spec.id == "ViewPlanningDiscrete-v1"
        assert env.action_space == gym.spaces.Discrete(33) and env.unwrapped.view_budget == 2
        env.reset(seed=0)
        assert [env.step(0)[2] for _ in range(2)] == [False, True]
    finally:
        env.close()
    # The tools that read the entry point's keywords and episode length see the env class's.
    creator = load_env_creator(gym.spec("InstrumentGraspRGBD-v1").entry_point)
    assert creator.keyword_names() == InstrumentGraspEnv.keyword_names()
    assert creator.episode_length_setting == "episode_steps"


def test_a_variant_makes_async_vector_envs_in_spawned_workers():
    envs = gym.make_vec("InstrumentGraspDepth-v1", num_envs=2, vectorization_mode="async",
                        vector_kwargs={"context": "spawn"}, **FAST["InstrumentGrasp"])  # fmt: skip
    try:
        observations, _ = envs.reset(seed=0)
        assert observations["depth"].shape == (2, 1, 64, 64) and "instrument" not in observations
        envs.step(np.zeros((2, 5), np.float32))
        assert envs.spec.id == "InstrumentGraspDepth-v1"
    finally:
        envs.close()
