"""ViewPlanning's own vector env: N scenes stepped in one call, in this process or shared
with worker processes.

``gym.make_vec("ViewPlanning-v1", num_envs=N)`` makes it (its registered
``vector_entry_point``); ``vectorization_mode="sync"`` or ``"async"`` still give Gymnasium's.
"""

from __future__ import annotations

import atexit
import multiprocessing
import signal
from typing import Any, NamedTuple

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from liuxing_envs.envs.view_planning import ViewPlanningEnv


class SceneStep(NamedTuple):
    """One scene's part of a vector step; ``final`` is the ended episode's last observation
    and info when the scene was reset in the step (else None)."""

    observation: dict
    reward: float
    terminated: bool
    truncated: bool
    info: dict
    final: tuple[dict, dict] | None


def step_scenes(envs: list, actions) -> list[SceneStep]:
    """Step each scene with its action, resetting (unseeded) the scenes whose episode ends."""
    steps = []
    for env, action in zip(envs, actions, strict=True):
        observation, reward, terminated, truncated, info = env.step(action)
        final = None
        if terminated or truncated:
            final = (observation, info)
            observation, info = env.reset()
        steps.append(SceneStep(observation, float(reward), terminated, truncated, info, final))
    return steps


def reset_scenes(envs: list, seeds: list, options: dict | None, mask) -> list:
    """``(observation, info)`` of each scene reset (``mask``), None for the others."""
    return [
        env.reset(seed=seed, options=options) if reset else None
        for env, seed, reset in zip(envs, seeds, mask, strict=True)
    ]


def ask_scenes(envs: list, indices, request: tuple) -> list:
    """The answer of each scene of ``indices`` (of ``envs``) to ``request``: ``("call",
    name, args, kwargs)`` calls a method (or reads an attribute), ``("get", name)`` reads an
    attribute, ``("set", name, values)`` sets one value per scene."""
    kind, name, *rest = request
    answers = []
    for k, i in enumerate(indices):
        env = envs[i]
        if kind == "get":
            answers.append(getattr(env, name))
        elif kind == "set":
            answers.append(setattr(env, name, rest[0][k]))
        else:
            args, kwargs = rest
            attribute = getattr(env, name)
            answers.append(attribute(*args, **kwargs) if callable(attribute) else attribute)
    return answers


def serve_scenes(connection, count: int, settings: dict) -> None:
    """A worker process: ``count`` scenes of ``settings``, answering the parent's requests
    (an exception is sent back to be raised there) until told to close. It ignores SIGINT
    and SIGTERM, which a terminal or scheduler sends the whole process group: the parent
    decides when to stop and closes it; if the parent dies, its closed pipe ends this."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        envs = [ViewPlanningEnv(**settings) for _ in range(count)]
    except Exception as error:  # noqa: BLE001 (the parent raises it)
        connection.send(("error", error))
        return
    handlers = {"step": step_scenes, "reset": reset_scenes, "ask": ask_scenes}
    connection.send(("ready", None))
    while True:
        try:
            kind, arguments = connection.recv()
        except EOFError:  # the parent is gone
            return
        if kind == "close":
            for env in envs:
                env.close()
            connection.send(("closed", None))
            return
        try:
            connection.send(("ok", handlers[kind](envs, *arguments)))
        except Exception as error:  # noqa: BLE001 (the parent raises it)
            connection.send(("error", error))


class WorkerDiedError(RuntimeError):
    """A worker process of :class:`ViewPlanningVectorEnv` has died."""


#: How long a worker gets to close its scenes before it is killed.
CLOSE_GRACE_SECONDS = 5.0


class _Worker:
    """A worker process holding the scenes ``first`` to ``first + count - 1``."""

    def __init__(self, first: int, count: int, settings: dict) -> None:
        # Spawned, not forked: a forked MuJoCo/OpenGL or open3d state can hang the child.
        context = multiprocessing.get_context("spawn")
        self.first, self.count = first, count
        self.connection, child = context.Pipe()
        self.process = context.Process(
            target=serve_scenes, args=(child, count, settings), daemon=True
        )
        self.process.start()
        child.close()  # so a dead worker's pipe reads as closed instead of hanging
        # At exit multiprocessing terminates daemon workers and waits for them, and this one
        # ignores SIGTERM: it is closed first (atexit runs the later registration first).
        atexit.register(self.close)

    def send(self, kind: str, *arguments) -> None:
        try:
            self.connection.send((kind, arguments))
        except (BrokenPipeError, OSError):
            raise self._died() from None

    def receive(self):
        try:
            kind, answer = self.connection.recv()
        except (EOFError, OSError):
            raise self._died() from None
        if kind == "error":
            raise answer
        return answer

    def _died(self) -> WorkerDiedError:
        self.process.join(timeout=CLOSE_GRACE_SECONDS)
        last = self.first + self.count - 1
        return WorkerDiedError(
            f"the worker process of ViewPlanning scenes {self.first}-{last} died (exit code "
            f"{self.process.exitcode}); make the vector env again"
        )

    def close(self) -> None:
        """Ask the worker to close its scenes; kill it if it has not ended in
        :data:`CLOSE_GRACE_SECONDS` (it ignores SIGTERM)."""
        atexit.unregister(self.close)
        if self.process.is_alive():
            try:
                self.connection.send(("close", ()))
                if self.connection.poll(CLOSE_GRACE_SECONDS):
                    self.connection.recv()
            except (EOFError, OSError):
                pass
            self.process.join(timeout=CLOSE_GRACE_SECONDS)
            if self.process.is_alive():
                self.process.kill()
                self.process.join(timeout=CLOSE_GRACE_SECONDS)
        self.connection.close()


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

    ## Workers
    With ``workers`` = K > 1 the scenes are split into K nearly equal runs of consecutive
    scenes: this process steps the first, a worker process (spawned) each other, all at
    once, so a step takes both cores of a 2-core machine; the episodes are the same as with
    one. Workers are spawned, so a script that makes them does so under
    ``if __name__ == "__main__":``. A worker that dies makes the next call raise a
    :class:`WorkerDiedError` naming its scenes; an error in a worker's scene is raised here.

    ## Arguments
    ``num_envs``; ``workers`` (default 1: every scene in this process); the single env's
    keyword arguments (the same for every scene).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, workers: int = 1, **settings: Any) -> None:
        if not _whole(num_envs) or num_envs < 1:
            raise ValueError(f"num_envs must be a whole number >= 1, got {num_envs!r}")
        if not _whole(workers) or not 1 <= workers <= num_envs:
            raise ValueError(
                f"workers must be a whole number from 1 to num_envs={num_envs}, got {workers!r}"
            )
        self.num_envs = int(num_envs)
        sizes = [len(part) for part in np.array_split(np.arange(self.num_envs), int(workers))]
        # The workers first, so that they build their scenes while this process builds its own.
        starts = np.cumsum([0, *sizes[:-1]]).tolist()
        parts = zip(starts[1:], sizes[1:], strict=True)
        self._workers = [_Worker(start, size, settings) for start, size in parts]
        try:
            #: The scenes stepped in this process (every scene when ``workers`` is 1).
            self.envs = [ViewPlanningEnv(**settings) for _ in range(sizes[0])]
            for worker in self._workers:
                worker.receive()  # ready, or the error that made its scenes fail
        except WorkerDiedError as error:
            for worker in self._workers:
                worker.close()
            raise WorkerDiedError(
                f"{error}. Workers are spawned: they import the main script again, so a "
                'script that makes them must do so under `if __name__ == "__main__":`'
            ) from None
        except BaseException:
            for worker in self._workers:
                worker.close()
            raise
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
        resets = self._on_every_scene("reset", seeds, options or None, mask)
        for i, reset in enumerate(resets):
            if reset is not None:
                observation, info = reset
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
        for i, scene in enumerate(self._on_every_scene("step", actions)):
            self._rewards[i] = scene.reward
            self._terminations[i] = scene.terminated
            self._truncations[i] = scene.truncated
            if scene.final is not None:
                final = {"final_obs": scene.final[0], "final_info": scene.final[1]}
                infos = self._add_info(infos, final, i)
            self._put(i, scene.observation)
            infos = self._add_info(infos, scene.info, i)
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
        for worker in self._workers:
            worker.close()

    # ------------------------------------------------------------------ per scene
    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Each scene's ``name``: called with the arguments when it is a method."""
        return self.call_at(range(self.num_envs), name, *args, **kwargs)

    def call_at(self, indices, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """:meth:`call` on the scenes of ``indices`` only, in their order."""
        return self._ask(indices, ("call", name, args, kwargs))

    def get_attr(self, name: str, indices=None) -> tuple[Any, ...]:
        """Each scene's attribute ``name`` (of the scenes of ``indices``, default all)."""
        return self._ask(range(self.num_envs) if indices is None else indices, ("get", name))

    def set_attr(self, name: str, values: Any, indices=None) -> None:
        """Set attribute ``name`` of each scene (of ``indices``, default all) to ``values``:
        one value per scene (a list or tuple), or the same value for every one."""
        indices = list(range(self.num_envs) if indices is None else indices)
        if not isinstance(values, (list, tuple)):
            values = [values] * len(indices)
        if len(values) != len(indices):
            raise ValueError(f"set_attr needs one value per scene ({len(indices)}), got {values!r}")
        self._ask(indices, ("set", name, list(values)))

    @property
    def worker_pids(self) -> tuple[int, ...]:
        """The process ids of the worker processes (none with ``workers`` = 1)."""
        return tuple(worker.process.pid for worker in self._workers)

    @property
    def np_random_seed(self) -> tuple[int | None, ...]:
        return self.get_attr("np_random_seed")

    # ------------------------------------------------------------------ internals
    def _on_every_scene(self, kind: str, *per_scene) -> list:
        """``kind`` (step or reset) of every scene, each argument given per scene (the last
        of reset's are options, the same for all): the workers' scenes sent off first, this
        process's done while they run."""
        handlers = {"step": step_scenes, "reset": reset_scenes}

        def part(start: int, count: int) -> list:
            if kind == "reset":
                seeds, options, mask = per_scene
                return [seeds[start : start + count], options, mask[start : start + count]]
            return [per_scene[0][start : start + count]]

        for worker in self._workers:
            worker.send(kind, *part(worker.first, worker.count))
        results = handlers[kind](self.envs, *part(0, len(self.envs)))
        for worker in self._workers:
            results += worker.receive()
        return results

    def _ask(self, indices, request: tuple) -> tuple[Any, ...]:
        """Each scene's answer to ``request`` (see :func:`ask_scenes`), in ``indices``' order."""
        indices = [int(i) for i in indices]
        if any(not 0 <= i < self.num_envs for i in indices):
            raise IndexError(f"scene indices must lie in [0, {self.num_envs}), got {indices}")
        local = len(self.envs)
        answers = {}
        mine = [i for i in indices if i < local]
        requests = []
        for worker in self._workers:
            theirs = [i for i in indices if worker.first <= i < worker.first + worker.count]
            if theirs:
                worker.send(
                    "ask", [i - worker.first for i in theirs], _part(request, indices, theirs)
                )
                requests.append((worker, theirs))
        answers.update(
            zip(mine, ask_scenes(self.envs, mine, _part(request, indices, mine)), strict=True)
        )
        for worker, theirs in requests:
            answers.update(zip(theirs, worker.receive(), strict=True))
        return tuple(answers[i] for i in indices)

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


def _whole(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _part(request: tuple, indices: list[int], chosen: list[int]) -> tuple:
    """``request`` for the scenes ``chosen`` of ``indices``: a set request's values cut to
    theirs."""
    if request[0] != "set":
        return request
    position = {i: k for k, i in enumerate(indices)}
    return ("set", request[1], [request[2][position[i]] for i in chosen])
