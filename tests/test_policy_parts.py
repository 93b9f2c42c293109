"""Policy parts shipped in the package: observation statistics carried inside a policy."""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import SAC

import liuxing_envs  # noqa: F401 (registers the ids)
from agents import run_folder
from liuxing_envs.policy_parts import NormalizedObservations, with_embedded_normalizer

SHIPPED_GRASP = Path(__file__).resolve().parents[1] / "policies" / "InstrumentGrasp-v1" / "sac"


@pytest.fixture(scope="module")
def shipped_grasp():
    """The shipped grasp policy and the VecNormalize it was trained behind."""
    normalizer = run_folder.load_normalizer(SHIPPED_GRASP / "best_vecnormalize.pkl")
    normalizer.training = False
    return SAC.load(SHIPPED_GRASP / "best_model.zip", device="cpu"), normalizer


def test_a_policy_with_its_normalizer_inside_acts_on_raw_observations_as_before(
    shipped_grasp, tmp_path
):
    model, normalizer = shipped_grasp
    embedded = with_embedded_normalizer(
        SAC.load(SHIPPED_GRASP / "best_model.zip", device="cpu"), normalizer
    )
    assert isinstance(embedded.actor.features_extractor, NormalizedObservations)
    embedded.save(tmp_path / "embedded.zip")
    reloaded = SAC.load(tmp_path / "embedded.zip", device="cpu")  # no VecNormalize file
    env = gym.make("InstrumentGrasp-v1")
    observation, _ = env.reset(seed=1_000_000)
    for _ in range(60):
        expected, _ = model.predict(normalizer.normalize_obs(observation), deterministic=True)
        for policy in (embedded, reloaded):
            acted, _ = policy.predict(observation, deterministic=True)
            np.testing.assert_array_equal(acted, expected)  # the same float64 arithmetic
        observation, *_ = env.step(expected)
    # Without the statistics the raw observations give other actions: the test can tell.
    unnormalized, _ = model.predict(observation, deterministic=True)
    normalized, _ = reloaded.predict(observation, deterministic=True)
    assert not np.array_equal(unnormalized, normalized)


def test_the_evaluators_loader_applies_no_normalizer_file_to_a_policy_that_carries_one(
    shipped_grasp, tmp_path
):
    from agents.evaluation import SB3Policy

    model, normalizer = shipped_grasp
    with_embedded_normalizer(
        SAC.load(SHIPPED_GRASP / "best_model.zip", device="cpu"), normalizer
    ).save(tmp_path / "best_model.zip")
    (tmp_path / "best_vecnormalize.pkl").write_bytes(
        (SHIPPED_GRASP / "best_vecnormalize.pkl").read_bytes()
    )
    loaded = SB3Policy.load(SAC, tmp_path / "best_model.zip", tmp_path / "best_vecnormalize.pkl")
    env = gym.make("InstrumentGrasp-v1")
    observation, _ = env.reset(seed=1_000_001)
    expected, _ = model.predict(normalizer.normalize_obs(observation), deterministic=True)
    acted, _ = loaded.predict(observation, deterministic=True)
    np.testing.assert_array_equal(acted, expected)  # normalised once, not twice
