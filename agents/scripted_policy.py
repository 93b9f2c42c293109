"""What every scripted baseline shares: SB3's ``predict`` on one env's observations.

SB3's ``predict`` takes an observation with or without a leading batch dimension and answers
in kind; its ``evaluate_policy`` always batches, even with one env. A scripted baseline acts
in the one env it was built on (it reads that env's action scales, camera model or, when
privileged, its simulator), so it takes one observation, bare or as a batch of one, and a
batch of several is refused by name. ``episode_start`` (SB3's flag of a new episode) and
:meth:`ScriptedPolicy.reset` clear what it remembers of the episode. :class:`RandomActions`
is the random baseline of both envs.
"""

from __future__ import annotations

import abc
import copy

import numpy as np
from stable_baselines3.common.utils import is_vectorized_observation


def sampling_seed(seed: int | None) -> int | None:
    """The seed of a policy's own sampling for an episode seed: derived from it, since an
    action space seeded with the env's seed would draw the env's own reset stream (so a
    random first view would follow the object drawn)."""
    if seed is None:
        return None
    return int(np.random.SeedSequence([seed, _SAMPLING_STREAM]).generate_state(1)[0])


#: Tells the policies' sampling streams from the env's, which Gymnasium seeds alike.
_SAMPLING_STREAM = 0x52414E44


class ScriptedPolicy(abc.ABC):
    """Base of the scripted baselines: subclasses implement :meth:`act` on one observation
    and, when they remember anything within an episode, :meth:`reset`."""

    def __init__(self, env) -> None:
        self.env = env.unwrapped

    @abc.abstractmethod
    def act(self, observation):
        """The action for one (unbatched) observation."""

    def reset(self, seed: int | None = None) -> None:
        """Forget the episode; ``seed`` reseeds a policy that samples (so that an episode
        played by seed does not depend on the episodes before it)."""
        return None  # a policy that remembers nothing and samples nothing has nothing to do

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        batched = is_vectorized_observation(observation, self.env.observation_space)
        if batched:
            size = len(next(iter(observation.values())))
            if size != 1:
                raise ValueError(
                    f"{type(self).__name__} acts in the one env it was built on, so it takes "
                    f"one observation or a batch of one, not a batch of {size}: build one "
                    "policy per env, or evaluate with n_envs=1"
                )
            observation = {key: value[0] for key, value in observation.items()}
        if episode_start is not None and np.any(episode_start):
            self.reset()
        action = self.act(observation)
        if batched:
            action = np.asarray(action)[None]
        return action, state


class RandomActions(ScriptedPolicy):
    """Uniform samples of the env's action space from a stream of its own: seeded with
    ``seed``, and again with each episode's by :meth:`reset`."""

    def __init__(self, env, seed: int | None = 0) -> None:
        super().__init__(env)
        self.action_space = copy.deepcopy(self.env.action_space)  # the env's own stays unseeded
        self.action_space.seed(sampling_seed(seed))

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.action_space.seed(sampling_seed(seed))

    def act(self, observation):
        return self.action_space.sample()
