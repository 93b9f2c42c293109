"""SB3's ``VecEnv`` over a Gymnasium vector env that resets ended scenes in the same step.

A task's own vector env (``gym.make_vec(env_id, N)``, e.g. ViewPlanning's) steps its scenes in
one call. SB3 expects what its ``DummyVecEnv`` over ``Monitor``-wrapped envs gives, so this
adapter gives the same: ``dones = terminated | truncated``; every info has
``TimeLimit.truncated``; an ended scene's info is its last info with ``terminal_observation``
and ``episode`` (return, length, time and the monitored info keys), written as a row of that
scene's Monitor file; the new episode's reset info goes to ``reset_infos``. So no reset-only
transition reaches the learner, and the run folder's files are those of a ``DummyVecEnv`` run.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from stable_baselines3.common.monitor import ResultsWriter
from stable_baselines3.common.vec_env import VecEnv

#: Keys of the vector env's infos that are not the scenes' own info.
_FINAL_KEYS = ("final_obs", "final_info")


class BatchedVecEnv(VecEnv):
    """``vector_env`` (its metadata's ``autoreset_mode`` must be ``SAME_STEP``, and it must
    have ``get_attr``, ``set_attr`` and ``call_at`` with scene indices) as an SB3
    ``VecEnv``; ``monitor_files`` (one per scene, or None) get the Monitor rows of each
    scene's episodes, with the ``info_keywords`` of the episode's last info."""

    def __init__(
        self,
        vector_env: VectorEnv,
        monitor_files: Sequence[str] | None = None,
        info_keywords: tuple[str, ...] = (),
    ) -> None:
        mode = vector_env.metadata.get("autoreset_mode")
        if mode != AutoresetMode.SAME_STEP:
            raise ValueError(
                f"BatchedVecEnv needs a vector env that resets in the same step "
                f"(metadata autoreset_mode SAME_STEP), got {mode!r}"
            )
        n = vector_env.num_envs
        if monitor_files is not None and len(monitor_files) != n:
            raise ValueError(
                f"monitor_files must name one file per scene ({n}), got {len(monitor_files)}"
            )
        self.vector_env = vector_env  # before VecEnv's __init__, which asks the scenes
        super().__init__(n, vector_env.single_observation_space, vector_env.single_action_space)
        self.info_keywords = tuple(info_keywords)
        self._actions: np.ndarray | None = None
        self._returns = np.zeros(n)
        self._lengths = np.zeros(n, dtype=np.int64)
        self._t_start = time.time()
        env_id = vector_env.spec.id if vector_env.spec is not None else type(vector_env).__name__
        self._writers = [
            ResultsWriter(path, {"t_start": self._t_start, "env_id": env_id}, self.info_keywords)
            for path in monitor_files or ()
        ]

    # ------------------------------------------------------------------ VecEnv API
    def reset(self):
        options = self._options if any(self._options) else None
        if options is not None and any(o != options[0] for o in options):
            raise ValueError("BatchedVecEnv resets every scene with the same options")
        observations, infos = self.vector_env.reset(
            seed=list(self._seeds), options=options[0] if options else None
        )
        self.reset_infos = [self._scene_info(infos, i) for i in range(self.num_envs)]
        self._returns[:] = 0.0
        self._lengths[:] = 0
        self._reset_seeds()
        self._reset_options()
        return observations

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        observations, rewards, terminated, truncated, infos = self.vector_env.step(self._actions)
        dones = terminated | truncated
        self._returns += rewards
        self._lengths += 1
        scene_infos = []
        for i in range(self.num_envs):
            info = self._scene_info(infos, i)
            if dones[i]:
                self.reset_infos[i] = info
                info = self._scene_info(infos["final_info"], i)
                info["terminal_observation"] = infos["final_obs"][i]
                info["episode"] = self._end_episode(i, info)
            info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            scene_infos.append(info)
        return observations, rewards.astype(np.float32), dones, scene_infos

    def close(self) -> None:
        self.vector_env.close()
        for writer in self._writers:
            writer.close()

    # The scenes may live in worker processes: asked through the vector env.
    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return list(self.vector_env.get_attr(attr_name, indices=self._get_indices(indices)))

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        indices = list(self._get_indices(indices))
        self.vector_env.set_attr(attr_name, [value] * len(indices), indices=indices)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list:
        indices = self._get_indices(indices)
        return list(self.vector_env.call_at(indices, method_name, *method_args, **method_kwargs))

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    # ------------------------------------------------------------------ internals
    def _scene_info(self, infos: dict[str, Any], i: int) -> dict[str, Any]:
        """Scene ``i``'s own info out of a vector env's dict of arrays and masks."""
        info = {}
        for key, value in infos.items():
            if key.startswith("_") or key in _FINAL_KEYS or not infos.get(f"_{key}", ())[i]:
                continue
            if isinstance(value, dict):
                info[key] = self._scene_info(value, i)
            else:  # a numpy scalar as the Python value the scene's own info held
                info[key] = value[i].item() if isinstance(value[i], np.generic) else value[i]
        return info

    def _end_episode(self, i: int, info: dict[str, Any]) -> dict[str, Any]:
        episode = {
            "r": round(float(self._returns[i]), 6),
            "l": int(self._lengths[i]),
            "t": round(time.time() - self._t_start, 6),
        }
        for key in self.info_keywords:
            episode[key] = info[key]
        if self._writers:
            self._writers[i].write_row(episode)
        self._returns[i] = 0.0
        self._lengths[i] = 0
        return episode
