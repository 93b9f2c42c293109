"""Env steps per second of one env on one core, per env and mode, with peak memory.

Each configuration runs in a fresh process: a single env made with ``gym.make`` (so the
TimeLimit and its resets are included), seeded uniform random actions, a warm-up, then
several timed runs. Random actions keep the gripper near the instrument and the tray about
as often as a learning policy early in training, and spread views over the whole sphere.
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import asdict, dataclass, field, replace

os.environ.setdefault("MUJOCO_GL", "egl")

from benchmarks.isolated import random_action_throughput, run_in_fresh_process  # noqa: E402

VIEW_PLANNING = "ViewPlanning-v1"
GRASP = "InstrumentGrasp-v1"


@dataclass(frozen=True)
class Config:
    env_id: str
    kwargs: dict = field(default_factory=dict)
    steps: int = 400  #: per timed run

    def to_json(self) -> str:
        """The ``--one`` argument of a measurement's fresh process."""
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> Config:
        return cls(**json.loads(text))

    @property
    def label(self) -> str:
        kw = self.kwargs
        if self.env_id == VIEW_PLANNING:
            size = kw["resolution"]
            return f"{kw['depth_backend']}, {kw['motion']}, {size}x{size}"
        if kw["obs_mode"] == "state":
            return "state"
        return f"{kw['obs_mode']}, {kw['depth_backend']}, 64x64"


def _view(backend: str, motion: str, resolution: int, steps: int = 400) -> Config:
    kwargs = {"depth_backend": backend, "motion": motion, "resolution": resolution}
    return Config(VIEW_PLANNING, kwargs, steps)


def _grasp(obs_mode: str, backend: str | None, steps: int) -> Config:
    """A grasp configuration; state observations render nothing, so they take no backend."""
    backend_kwargs = {} if backend is None else {"depth_backend": backend}
    return Config(GRASP, {"obs_mode": obs_mode, **backend_kwargs}, steps)


#: The default mode of ViewPlanning-v1: kinematic motion at 64x64, ray-cast depth. The gl and
#: embree backends (the latter the ray-cast one with meshes cast by Embree) are measured
#: beside it.
VIEW_DEFAULT = _view("raycast", "kinematic", 64)
VIEW_DEFAULT_GL = _view("gl", "kinematic", 64)
GRASP_STATE = _grasp("state", None, 2000)
CONFIGS = (
    VIEW_DEFAULT,
    VIEW_DEFAULT_GL,
    _view("embree", "kinematic", 64),
    _view("raycast", "dynamic", 64, 200),
    _view("gl", "dynamic", 64, 200),
    _view("raycast", "kinematic", 128),
    _view("gl", "kinematic", 128),
    GRASP_STATE,
    _grasp("depth", "gl", 1000),
    _grasp("depth", "raycast", 1000),
    _grasp("rgbd", "gl", 300),
)


def make_env(config: Config):
    """The env, with every object's set-ups built (no timed step pays for one)."""
    import gymnasium as gym

    import liuxing_envs  # noqa: F401  (registers the envs)

    env = gym.make(config.env_id, **config.kwargs)
    env.unwrapped.prepare_objects()
    return env


def measure(config: Config, repeats: int, scale: float = 1.0) -> dict:
    """Throughput of ``config`` in a fresh process (see module doc); ``scale`` shortens runs."""
    shorter = replace(config, steps=max(20, int(config.steps * scale)))
    return run_in_fresh_process(
        "benchmarks.throughput", "--one", shorter.to_json(), "--repeats", str(repeats)
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", required=True, help="a Config as JSON")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    config = Config.from_json(args.one)
    env = make_env(config)
    length = env.unwrapped.episode_length
    warmup = 2 * length if length < 50 else 100
    print(json.dumps(random_action_throughput(env, config.steps, args.repeats, warmup)))


if __name__ == "__main__":
    main()
