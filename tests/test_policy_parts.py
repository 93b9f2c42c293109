"""Policy parts shipped in the package: observation statistics carried inside a policy."""

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import SAC
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

import liuxing_envs  # noqa: F401 (registers the ids)
from liuxing_envs.policy_parts import NormalizedObservations, with_embedded_normalizer


@pytest.fixture(scope="module")
def normalized_grasp(tmp_path_factory):
    """A SAC model on InstrumentGrasp-v1 behind a VecNormalize whose statistics come from
    random steps (far from zero mean and unit variance), saved as a run saves them."""
    folder = tmp_path_factory.mktemp("normalized")
    venv = VecNormalize(DummyVecEnv([lambda: gym.make("InstrumentGrasp-v1")]), norm_reward=False)
    venv.seed(0)
    venv.action_space.seed(0)
    venv.reset()
    for _ in range(150):
        venv.step(np.array([venv.action_space.sample()]))
    model = SAC("MultiInputPolicy", venv, seed=0, device="cpu")
    model.save(folder / "model.zip")
    venv.save(folder / "vecnormalize.pkl")
    venv.training = False
    return folder, venv


def test_a_policy_with_its_normalizer_inside_acts_on_raw_observations_as_before(
    normalized_grasp, tmp_path
):
    folder, normalizer = normalized_grasp
    model = SAC.load(folder / "model.zip", device="cpu")
    embedded = with_embedded_normalizer(SAC.load(folder / "model.zip", device="cpu"), normalizer)
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
    normalized_grasp, tmp_path
):
    from agents.evaluation import SB3Policy

    folder, normalizer = normalized_grasp
    model = SAC.load(folder / "model.zip", device="cpu")
    with_embedded_normalizer(SAC.load(folder / "model.zip", device="cpu"), normalizer).save(
        tmp_path / "best_model.zip"
    )
    (tmp_path / "best_vecnormalize.pkl").write_bytes((folder / "vecnormalize.pkl").read_bytes())
    loaded = SB3Policy.load(SAC, tmp_path / "best_model.zip", tmp_path / "best_vecnormalize.pkl")
    env = gym.make("InstrumentGrasp-v1")
    observation, _ = env.reset(seed=1_000_001)
    expected, _ = model.predict(normalizer.normalize_obs(observation), deterministic=True)
    acted, _ = loaded.predict(observation, deterministic=True)
    np.testing.assert_array_equal(acted, expected)  # normalised once, not twice


def test_the_pooled_extractor_sees_occupancy_at_half_the_grid_and_depth_at_16_pixels():
    import torch

    from liuxing_envs.policy_parts import FEATURES_EXTRACTORS, PooledPerceptionExtractor

    space = gym.make("ViewPlanning-v1", observe_free_space=True).observation_space
    extractor = FEATURES_EXTRACTORS["perception_pooled"](space)
    assert isinstance(extractor, PooledPerceptionExtractor)
    torch.manual_seed(0)
    observation = {key: torch.zeros((1, *sub.shape)) for key, sub in space.spaces.items()}

    def features(**changes):
        with torch.no_grad():
            return extractor({**observation, **changes})

    def cube(*cells):
        grid = torch.zeros((1, 16, 16, 16))
        for cell in cells:
            grid[(0, *cell)] = 1.0
        return grid.reshape(1, -1)

    # A cell occupied anywhere in its 2x2x2 block reads alike; in the next block it does not.
    assert torch.equal(features(map=cube((4, 6, 8))), features(map=cube((5, 7, 9))))
    assert not torch.equal(features(map=cube((4, 6, 8))), features(map=cube((6, 6, 8))))
    # Free space is the map's second channel, pooled alike.
    assert not torch.equal(features(free_space=cube((4, 6, 8))), features())
    # Depth is averaged over 4x4 pixel blocks: moving a return within its block changes
    # nothing, and the image counts.
    image = torch.zeros((1, 1, 64, 64))
    moved = image.clone()
    image[0, 0, 8, 12], moved[0, 0, 11, 15] = 0.5, 0.5
    assert torch.equal(features(depth=image), features(depth=moved))
    assert not torch.equal(features(depth=image), features())


@pytest.mark.parametrize("batch", [1, 64])
def test_the_pooled_extractors_cheap_pools_give_torchs_own_pools_numbers(batch):
    import torch
    from torch import nn

    from liuxing_envs.policy_parts import HalvingMaxPool3d, average_pool

    generator = torch.Generator().manual_seed(batch)
    cubes = (torch.rand((batch, 2, 16, 16, 16), generator=generator) < 0.1).float()
    noise = torch.randn((batch, 1, 8, 12, 6), generator=generator)
    noise[0, 0, 3, 5, 1] = float("nan")  # max pooling keeps a NaN
    for value in (cubes, noise):
        torch.testing.assert_close(
            HalvingMaxPool3d()(value), nn.MaxPool3d(2)(value), rtol=0, atol=0, equal_nan=True
        )
    for side in (16, 32, 48, 64, 80, 128):
        for images in (
            torch.randint(0, 256, (batch, 1, side, side), generator=generator).float() / 255,
            torch.randn((batch, 4, side, side), generator=generator),
        ):
            pooled = average_pool(images.shape[1:], 16)(images)
            assert torch.equal(pooled, nn.AdaptiveAvgPool2d(16)(images)), side
    # Where its windows would divide inexactly (3x3 pixels) it is the adaptive pool itself.
    assert isinstance(average_pool((1, 48, 48), 16), nn.AdaptiveAvgPool2d)
    assert isinstance(average_pool((1, 64, 64), 16), nn.AvgPool2d)
