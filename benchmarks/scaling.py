"""Vectorised scaling: total env steps per second with 1, 2 and 4 worker processes.

Two vector envs are measured: Gymnasium's ``gym.make_vec(..., vectorization_mode="async")``
and stable-baselines3's ``SubprocVecEnv`` (what ``train.py --vec-env subproc`` uses), each
against one env stepped in this process. Every measurement runs in a fresh parent process,
with seeded random actions and the vector env's own autoreset. Every call of ``step`` is
counted as one env step per worker, so Gymnasium's vector env resets in the same call as
the step that ends an episode (``AutoresetMode.SAME_STEP``): with its default,
``NEXT_STEP``, the call after the last step of an episode only resets, and counting it would
overstate ViewPlanning-v1 (4-step episodes) by a quarter. SB3's ``SubprocVecEnv`` resets
in the same call already. On a machine with fewer cores
than workers, the workers share the cores: the speed-up then measures overhead as much as
parallelism. ``python -m benchmarks`` measures every vector env once per round, for several
rounds, and takes each speed-up within a round: on a machine whose speed drifts over
minutes, a ratio of two measurements made minutes apart would measure the drift.

A vector env of this kind steps its workers in lockstep: each call waits for the slowest
worker. :func:`lockstep_ceilings` bounds what that alone allows, from one env's own step
times: with ``n`` workers on ``n`` free cores and no cost of communication at all, the
speed-up is at most ``n * mean step time / mean time of the slowest of n steps``. Workers in
lockstep start their episodes together, so where every episode has the same length (a
ViewPlanning-v1 view budget) they stay in phase and the slowest is taken among steps of the
same phase (the dearer first step after a reset falls on every worker at once); otherwise
among all steps, as if independent, which makes the figure an estimate rather than a
bound. The other cost is the vector env's own: :func:`vector_cost_ms` times its calls on
:class:`NoOpTwin` copies of the env, which have its spaces, observation and info but do no
work.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.isolated import (  # noqa: E402
    random_action_throughput,
    random_actions,
    random_steps,
    run_in_fresh_process,
    spread,
)
from benchmarks.throughput import Config, make_env  # noqa: E402

WORKERS = (1, 2, 4)
KINDS = ("single", "gymnasium-async", "sb3-subproc")


def vector_env(config: Config, kind: str, workers: int):
    """``workers`` envs of ``config`` in a vector env of ``kind`` (see ``KINDS``)."""
    if kind == "gymnasium-async":
        import liuxing_envs  # noqa: F401

        envs = gym.make_vec(
            config.env_id,
            num_envs=workers,
            vectorization_mode="async",
            vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP},
            **config.kwargs,
        )
        envs.call("prepare_objects")  # as make_env does for the other kinds
        return envs
    return _subproc_vec_env([lambda: make_env(config)] * workers)


def _subproc_vec_env(env_fns):
    # Imported here: stable-baselines3 brings torch, which the other measurements go without.
    from stable_baselines3.common.vec_env import SubprocVecEnv

    return SubprocVecEnv(env_fns)


def mean_slowest(times: np.ndarray, n: int) -> float:
    """Expected maximum of ``n`` independent draws from the empirical distribution
    ``times``: exact, from its order statistics, so the same times give the same figure."""
    ordered = np.sort(times)
    share = np.arange(ordered.size + 1) / ordered.size
    return float(ordered @ np.diff(share**n))


#: Episodes that must have ended, all as long, before steps are grouped by phase: with
#: fewer, a phase holds too few steps for its slowest-of-n to be estimated.
MIN_EPISODES_IN_PHASE = 3
#: Steps timed for the ceilings per step timed for the rate: order statistics need many.
CEILING_STEPS_PER_RATE_STEP = 4


def lockstep_ceilings(config: Config, steps: int, workers=WORKERS) -> dict[str, float]:
    """Per worker count (a string key, as JSON keeps it): the speed-up ceiling of a lockstep
    vector env (see the module doc), from ``steps`` seeded random steps of one env (after
    ``steps // 4`` untimed, which fill the per-process caches)."""
    env = make_env(config)
    env.action_space.seed(0)
    env.reset(seed=0)  # seeds the episode stream; random_steps starts its own episode
    random_steps(env, steps // 4)
    env.reset()
    times, phases, lengths, phase = [], [], [], 0
    for action in random_actions(env.action_space, steps):
        start = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(action)
        ended = terminated or truncated
        if ended:  # the reset belongs to the call, as in the vector env's same-step autoreset
            env.reset()
        times.append(time.perf_counter() - start)
        phases.append(phase)
        phase = 0 if ended else phase + 1
        if ended:
            lengths.append(phases[-1] + 1)
    env.close()
    return ceilings_from_times(np.array(times), np.array(phases), lengths, workers)


def ceilings_from_times(
    times: np.ndarray, phases: np.ndarray, lengths: list[int], workers=WORKERS
) -> dict[str, float]:
    """:func:`lockstep_ceilings` from the step times, each step's phase (its index in its
    episode) and the lengths of the episodes that ended. Steps are grouped by phase when at
    least :data:`MIN_EPISODES_IN_PHASE` episodes ended, all as long, and the one cut short
    is no longer; otherwise the slowest of n is taken among all steps, as if the workers'
    steps were independent (an estimate, not a bound: workers that start together stay
    partly in phase)."""
    in_phase = (
        len(lengths) >= MIN_EPISODES_IN_PHASE
        and len(set(lengths)) == 1
        and int(phases.max()) < lengths[0]
    )
    ceilings = {}
    for n in workers:
        if in_phase:  # each phase weighted by its steps (the last episode may be cut short)
            weighted = (
                np.count_nonzero(phases == p) * mean_slowest(times[phases == p], n)
                for p in range(lengths[0])
            )
            slowest = sum(weighted) / times.size
        else:
            slowest = mean_slowest(times, n)
        ceilings[str(n)] = n * float(times.mean()) / slowest
    return ceilings


def vector_throughput(config: Config, kind: str, workers: int, steps: int, repeats: int) -> dict:
    """Total env steps/s (``steps`` per worker per timed run); for the single env, also its
    lockstep ceilings and the vector envs' own cost (:func:`vector_cost_ms`)."""
    if kind == "single":
        measured = random_action_throughput(make_env(config), steps, repeats, warmup=steps // 4)
        return {
            **measured,
            "ceilings": lockstep_ceilings(config, CEILING_STEPS_PER_RATE_STEP * steps * repeats),
            "vector_cost_ms": vector_cost_ms(config, steps * repeats),
        }
    rates = _vector_rates(vector_env(config, kind, workers), kind, workers, steps, repeats)
    return spread(rates)


def _vector_rates(env, kind: str, workers: int, steps: int, repeats: int) -> list[float]:
    """Env steps/s of ``repeats`` timed runs of ``steps`` calls of seeded random actions
    (after ``steps // 4`` untimed), drawn before each run's clock starts; closes ``env``."""
    sb3 = kind == "sb3-subproc"
    space = env.action_space
    space.seed(0)
    if sb3:
        env.seed(0)
        env.reset()
    else:
        env.reset(seed=0)

    def run(count: int) -> float:
        if sb3:
            actions = [np.stack(random_actions(space, workers)) for _ in range(count)]
        else:
            actions = random_actions(space, count)
        start = time.perf_counter()
        for action in actions:
            env.step(action)
        return count * workers / (time.perf_counter() - start)

    run(max(1, steps // 4))
    rates = [run(steps) for _ in range(repeats)]
    env.close()
    return rates


class NoOpTwin(gym.Env):
    """An env with a real one's spaces that does no work: every step returns the same
    observation and a copy of the same info, and terminates an episode every
    ``episode_steps``. A vector env of these costs what the vector env itself does per
    call: processes, pipes, shared memory and merging the infos (a little less than with
    the real env, whose last step of an episode may carry more info)."""

    def __init__(self, spaces, observation, info: dict, episode_steps: int) -> None:
        self.observation_space, self.action_space = spaces
        self._observation, self._info, self._episode_steps = observation, info, episode_steps
        self._steps = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._steps = 0
        return self._observation, dict(self._info)

    def step(self, action):
        self._steps += 1
        ended = self._steps % self._episode_steps == 0
        return self._observation, 0.0, ended, False, dict(self._info)


def vector_cost_ms(config: Config, calls: int, workers=(1, 2)) -> dict[str, dict[str, float]]:
    """Per vector env kind and worker count: milliseconds per call of ``step`` on
    :class:`NoOpTwin` copies of ``config``'s env (random actions drawn before the clock starts,
    as in every rate here)."""
    real = make_env(config)
    real.action_space.seed(0)
    real.reset(seed=0)
    observation, _, _, _, info = real.step(real.action_space.sample())
    spaces = (real.observation_space, real.action_space)
    episode_steps = real.unwrapped.episode_length
    twin = functools.partial(NoOpTwin, spaces, observation, info, episode_steps)
    real.close()
    cost: dict[str, dict[str, float]] = {}
    for kind in KINDS[1:]:
        cost[kind] = {}
        for count in workers:
            if kind == "gymnasium-async":
                env = gym.vector.AsyncVectorEnv(
                    [twin] * count, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP
                )
            else:
                env = _subproc_vec_env([twin] * count)
            rates = _vector_rates(env, kind, count, calls, 1)
            cost[kind][str(count)] = 1e3 * count / rates[0]
    return cost


def summarize(rates: list[float], single_rates: list[float]) -> dict:
    """Median, min and max of one vector env's rates over rounds, and its speed-up: the median
    over rounds of its rate against the single env's in the same round."""
    ratios = [r / s for r, s in zip(rates, single_rates, strict=True)]
    return {**spread(rates), "speedup": spread(ratios)["median"]}


def measure(config: Config, kind: str, workers: int, steps: int, repeats: int = 3) -> dict:
    return run_in_fresh_process(
        "benchmarks.scaling",
        *("--one", config.to_json(), "--kind", kind, "--workers", str(workers)),
        *("--steps", str(steps), "--repeats", str(repeats)),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", required=True, help="a Config as JSON")
    parser.add_argument("--kind", choices=KINDS, required=True)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    config = Config.from_json(args.one)
    print(json.dumps(vector_throughput(config, args.kind, args.workers, args.steps, args.repeats)))


if __name__ == "__main__":
    main()
