"""ViewPlanning's own vector env: N scenes in one process, stepped in one call.

``gym.make_vec("ViewPlanning-v1", num_envs=N)`` makes it (its registered
``vector_entry_point``); ``vectorization_mode="sync"`` or ``"async"`` still give Gymnasium's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from liuxing_envs.envs.view_planning import ViewPlanningEnv


class ViewPlanningVectorEnv(VectorEnv):
    """``num_envs`` ViewPlanning scenes stepped together, with the same episodes as as many
    single envs given the same seeds.

    ## Spaces
    The single env's spaces batched (``batch_space``): actions ``(N, 3)`` (``(N,)`` for the
    discrete variant), each observation key with a leading axis of N.

    ## Resets
    ``reset(seed=s)`` resets scene i with seed ``s + i`` (a list gives each scene its own;
    None keeps each scene's stream). ``options`` go to every scene; ``options["reset_mask"]``
    (a boolean array of N) resets only the scenes it marks, as Gymnasium's vector envs do.

    ## Autoreset
    ``metadata["autoreset_mode"]`` is ``SAME_STEP``: a scene whose episode ends in a step is
    reset in that step (unseeded: its random stream goes on). The step returns the new
    episode's first observation; ``infos["final_obs"]`` and ``infos["final_info"]`` hold the
    ended episode's last observation and info, masked by ``infos["_final_obs"]``. No step
    returns a transition that only resets.

    ## Infos
    A dict of arrays, one entry per scene, each key with a boolean mask ``_key`` of the scenes
    that returned it (Gymnasium's convention).

    ## Arguments
    ``num_envs`` and the single env's keyword arguments (the same for every scene).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, **settings: Any) -> None:
        whole = isinstance(num_envs, (int, np.integer)) and not isinstance(num_envs, bool)
        if not whole or num_envs < 1:
            raise ValueError(f"num_envs must be a whole number >= 1, got {num_envs!r}")
        self.num_envs = int(num_envs)
        self.envs = [ViewPlanningEnv(**settings) for _ in range(self.num_envs)]
        first = self.envs[0]
        self.settings = first.settings
        self.single_action_space = first.action_space
        self.single_observation_space = first.observation_space
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self._observations = {
            key: np.zeros((self.num_envs, *space.shape), dtype=space.dtype)
            for key, space in self.single_observation_space.spaces.items()
        }
        self._rewards = np.zeros(self.num_envs, dtype=np.float64)
        self._terminations = np.zeros(self.num_envs, dtype=np.bool_)
        self._truncations = np.zeros(self.num_envs, dtype=np.bool_)

    # ------------------------------------------------------------------ Gymnasium API
    def reset(
        self,
        *,
        seed: int | list[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        seeds = self._seeds(seed)
        options = dict(options or {})
        mask = self._reset_mask(options.pop("reset_mask", None))
        infos: dict[str, Any] = {}
        for i in np.flatnonzero(mask):
            observation, info = self.envs[i].reset(seed=seeds[i], options=options or None)
            self._put(i, observation)
            infos = self._add_info(infos, info, i)
        self._terminations[mask] = False
        self._truncations[mask] = False
        return self._copy_observations(), infos

    def step(self, actions):
        actions = np.asarray(actions)
        if actions.shape[:1] != (self.num_envs,):
            raise ValueError(
                f"actions must have a leading axis of num_envs={self.num_envs}, "
                f"got shape {actions.shape}"
            )
        infos: dict[str, Any] = {}
        for i, env in enumerate(self.envs):
            observation, reward, terminated, truncated, info = env.step(actions[i])
            self._rewards[i] = reward
            self._terminations[i] = terminated
            self._truncations[i] = truncated
            if terminated or truncated:
                infos = self._add_info(infos, {"final_obs": observation, "final_info": info}, i)
                observation, info = env.reset()
            self._put(i, observation)
            infos = self._add_info(infos, info, i)
        return (
            self._copy_observations(),
            self._rewards.copy(),
            self._terminations.copy(),
            self._truncations.copy(),
            infos,
        )

    def close_extras(self, **kwargs: Any) -> None:
        for env in self.envs:
            env.close()

    # ------------------------------------------------------------------ per scene
    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Each scene's ``name``: called with the arguments when it is a method."""
        results = []
        for env in self.envs:
            attribute = getattr(env, name)
            results.append(attribute(*args, **kwargs) if callable(attribute) else attribute)
        return tuple(results)

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Each scene's attribute ``name``."""
        return tuple(getattr(env, name) for env in self.envs)

    @property
    def np_random_seed(self) -> tuple[int | None, ...]:
        return self.get_attr("np_random_seed")

    # ------------------------------------------------------------------ internals
    def _seeds(self, seed) -> list[int | None]:
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            return [int(seed) + i for i in range(self.num_envs)]
        seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ValueError(
                f"seed must be None, an int or a list of num_envs={self.num_envs} seeds, "
                f"got a list of {len(seeds)}"
            )
        return seeds

    def _reset_mask(self, mask) -> np.ndarray:
        if mask is None:
            return np.ones(self.num_envs, dtype=np.bool_)
        mask = np.asarray(mask)
        if mask.dtype != np.bool_ or mask.shape != (self.num_envs,) or not mask.any():
            raise ValueError(
                f"options['reset_mask'] must be a boolean array of shape ({self.num_envs},) "
                f"with at least one True, got {mask!r}"
            )
        return mask

    def _put(self, i: int, observation: dict[str, np.ndarray]) -> None:
        for key, batch in self._observations.items():
            batch[i] = observation[key]

    def _copy_observations(self) -> dict[str, np.ndarray]:
        return {key: batch.copy() for key, batch in self._observations.items()}
