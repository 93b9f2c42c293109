"""The physics limit: how fast MuJoCo alone steps our models through the same trajectories.

Each configuration runs in a fresh process. The env runs seeded random episodes while every
``mj_step`` it makes is recorded (its model, the controls, the step count) from the state
each episode starts in; :func:`mujoco.rollout.rollout` then replays those controls open
loop, all substeps in C with no Python in between. The limit is env steps per second of that
replay: what the env could reach if everything but physics were free. The env's rate counts
its resets, so the replay counts theirs too: a reset's own physics (InstrumentGrasp's settling
steps) is replayed as a segment of its own, as it starts from bodies the reset has just
placed. The env's own rate is
timed in the same process, replaying the same seeds and actions with nothing recorded, its
rounds alternating with the replay's, and each round's ratio taken, so a machine whose speed
drifts slows both alike.

InstrumentGrasp switches noslip iterations on while a pad touches something; the replay
switches them off throughout, so the limit is, if anything, optimistic, and the fraction
conservative. (With random actions a pad almost never touches anything, so this changes
little.) Each instrument has its own model, and each episode is replayed in its instrument's.
The benchmark's envs draw no random masses or frictions (``mass_range`` and ``friction_range``
are off by default); with them on, every episode of an instrument would be replayed with its
last episode's values, which does not change what a substep costs.

ViewPlanning-v1 steps physics only in ``motion="dynamic"``; in the default kinematic mode its
MuJoCo work is ray casting, kinematics and collision checks, shown by the time split.
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import rollout  # noqa: E402

from benchmarks.isolated import run_in_fresh_process  # noqa: E402
from benchmarks.throughput import Config, make_env  # noqa: E402

STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS


class _Recorder:
    """Wraps ``mujoco.mj_step`` to record each episode's physics as a replayable segment."""

    def __init__(self) -> None:
        self.segments: list[dict] = []
        self._segment_open = False
        self._step = mujoco.mj_step
        mujoco.mj_step = self._recorded_step

    def _recorded_step(self, model, data, nstep: int = 1) -> None:
        if not self._segment_open or self.segments[-1]["model"] is not model:
            self._segment_open = True
            state = np.empty(mujoco.mj_stateSize(model, STATE_SPEC))
            mujoco.mj_getState(model, data, state, STATE_SPEC)
            self.segments.append({"model": model, "state": state, "controls": []})
        self.segments[-1]["controls"].append(np.repeat(data.ctrl[None], nstep, axis=0))
        self._step(model, data, nstep=nstep)

    def new_episode(self) -> None:
        """The next step starts a new segment, from the state it finds."""
        self._segment_open = False

    def close(self) -> None:
        mujoco.mj_step = self._step


def limit(config: Config, steps: int, repeats: int) -> dict:
    """Env steps/s of the recorded physics replayed by rollout, mj_steps per env step, and the
    env's own steps/s on the same episodes (each the median of ``repeats`` rounds)."""
    env = make_env(config)
    env.action_space.seed(0)
    actions = [env.action_space.sample() for _ in range(steps)]

    def run_env(recorder: _Recorder | None = None) -> float:
        """Env steps/s of seeded episodes: reset(seed=0), then unseeded resets as they end;
        ``recorder`` records the physics of each reset and of each episode's steps, each
        its own segment (a reset moves bodies between its physics and the steps')."""
        start = time.perf_counter()
        done = True
        for step, action in enumerate(actions):
            if done:
                if recorder is not None:
                    recorder.new_episode()
                env.reset(seed=0 if step == 0 else None)
                if recorder is not None:
                    recorder.new_episode()
            _, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
        return steps / (time.perf_counter() - start)

    # The recorder sees the bindings' mj_step calls, so the recorded run leaves a compiled
    # force loop (which calls MuJoCo's C function itself) off; the episodes are the same.
    worlds = getattr(env.unwrapped, "worlds", ())
    compiled = [world.compiled for world in worlds]
    for world in worlds:
        world.compiled = False
    recorder = _Recorder()
    run_env(recorder)
    recorder.close()
    for world, was_compiled in zip(worlds, compiled, strict=True):
        world.compiled = was_compiled
    segments = recorder.segments
    data = {id(s["model"]): mujoco.MjData(s["model"]) for s in segments}
    controls = [np.concatenate(s["controls"]) for s in segments]
    substeps = sum(len(c) for c in controls)
    if substeps == 0:
        env.close()
        return {"mj_steps_per_env_step": 0.0, "mj_steps_per_second": None, "limit": None}
    # The env's noslip setting is saved and put back around each replay (see the module
    # docstring), so its own rounds run as they did while recorded.
    noslip = {id(s["model"]): s["model"].opt.noslip_iterations for s in segments}

    def replay() -> float:
        for segment in segments:
            segment["model"].opt.noslip_iterations = 0
        start = time.perf_counter()
        for segment, control in zip(segments, controls, strict=True):
            model = segment["model"]
            rollout.rollout(model, data[id(model)], segment["state"][None], control[None])
        rate = steps / (time.perf_counter() - start)
        for segment in segments:
            segment["model"].opt.noslip_iterations = noslip[id(segment["model"])]
        return rate

    replay()  # warm-up
    run_env()  # and the env's (a kernel compiled on first use, where its cache is cold)
    rates, env_rates = [], []
    for _ in range(repeats):
        rates.append(replay())
        env_rates.append(run_env())
    env.close()
    # Each round's env rate against the replay beside it, so that a drift between rounds
    # cancels; the rates themselves are the medians of their rounds.
    fractions = sorted(e / r for e, r in zip(env_rates, rates, strict=True))
    rates.sort()
    env_rates.sort()
    return {
        "mj_steps_per_env_step": substeps / steps,
        "mj_steps_per_second": rates[len(rates) // 2] * substeps / steps,
        "limit": rates[len(rates) // 2],
        "env_steps_per_second": env_rates[len(env_rates) // 2],
        "env_to_limit": fractions[len(fractions) // 2],
    }


def measure(config: Config, steps: int, repeats: int = 3) -> dict:
    return run_in_fresh_process(
        "benchmarks.physics",
        "--one",
        config.to_json(),
        "--steps",
        str(steps),
        "--repeats",
        str(repeats),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", required=True, help="a Config as JSON")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(json.dumps(limit(Config.from_json(args.one), args.steps, args.repeats)))


if __name__ == "__main__":
    main()
