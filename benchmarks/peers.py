"""A peer suite in the same run: Gymnasium-Robotics ``FetchPickAndPlace-v4``, one env on one
core, seeded random actions with resets, with and without an 84x84 RGB image per step.

Optional: ``pip install -e ".[bench]"`` brings gymnasium-robotics; without it this section
is skipped. gymnasium-robotics 1.4.2 asserts ``joint_type in (mjJNT_HINGE, mjJNT_SLIDE)``
when it sets joints, a membership test that MuJoCo 4's enum types fail for a numpy int even
when the values match, so its env cannot be made under MuJoCo 4.0 with assertions on. The
peer therefore runs in a ``python -O`` process (assertions stripped, nothing else changed).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import warnings

os.environ.setdefault("MUJOCO_GL", "egl")

from benchmarks.isolated import random_action_throughput, run_in_fresh_process  # noqa: E402

PEER_ENV = "FetchPickAndPlace-v4"
IMAGE_SIZE = 84


def available() -> bool:
    return importlib.util.find_spec("gymnasium_robotics") is not None


class _RenderEachStep:
    """Adds the env's ``render()`` to every step, as a pixel-observation wrapper would."""

    def __init__(self, env) -> None:
        self.env = env
        self.action_space = env.action_space

    def reset(self, **kwargs):
        return self.env.reset(**kwargs)

    def step(self, action):
        result = self.env.step(action)
        self.env.render()
        return result

    def close(self) -> None:
        self.env.close()


def peer_throughput(render: bool, steps: int, repeats: int) -> dict:
    import gymnasium as gym

    with warnings.catch_warnings():  # its import warns about Adroit reward versions
        warnings.simplefilter("ignore")
        import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    kwargs = {"render_mode": "rgb_array", "width": IMAGE_SIZE, "height": IMAGE_SIZE}
    env = gym.make(PEER_ENV, **(kwargs if render else {}))
    if render:
        env = _RenderEachStep(env)
    return random_action_throughput(env, steps, repeats, warmup=100)


def measure(render: bool, steps: int, repeats: int = 3) -> dict:
    return run_in_fresh_process(
        "benchmarks.peers",
        *(["--render"] if render else []),
        *("--steps", str(steps), "--repeats", str(repeats)),
        optimize=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--render", action="store_true")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(json.dumps(peer_throughput(args.render, args.steps, args.repeats)))


if __name__ == "__main__":
    main()
