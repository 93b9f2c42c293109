"""Where one env step's time goes: exclusive wall time per phase, per env and mode.

Each configuration runs in a fresh process. The phases are the env's own methods and the
library calls it makes, wrapped with timers for this process only (the wrappers cost about
a microsecond per call, which the "other" share absorbs along with gym's wrappers, action
parsing and info dicts). A phase called inside another is counted once, in the inner one.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections import defaultdict

os.environ.setdefault("MUJOCO_GL", "egl")

from benchmarks.isolated import random_steps, run_in_fresh_process  # noqa: E402
from benchmarks.throughput import GRASP, VIEW_PLANNING, Config, make_env  # noqa: E402


class PhaseTimer:
    """Exclusive time per phase of wrapped callables (nested phases are not double counted)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self._stack: list[list] = []  # [phase, time spent in nested phases]

    def wrap(self, owner, name: str, phase: str) -> None:
        original = getattr(owner, name)
        stack, seconds = self._stack, self.seconds

        def timed(*args, **kwargs):
            frame = [phase, 0.0]
            stack.append(frame)
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - start
                stack.pop()
                seconds[phase] += elapsed - frame[1]
                if stack:
                    stack[-1][1] += elapsed

        setattr(owner, name, timed)


def _instrument_view_planning(env, timer: PhaseTimer) -> None:
    from liuxing_envs.perception.coverage import CoverageTracker
    from liuxing_envs.sensors import view_sensor

    timer.wrap(env.arm, "solve_ik", "IK (closed form + collision checks)")
    timer.wrap(env.arm, "plan_path", "path collision checks")
    timer.wrap(env.arm, "follow", "motion (physics when dynamic)")
    timer.wrap(env.scene, "render_depth", "depth rendering")
    timer.wrap(env.camera, "points_world", "back-projection")
    timer.wrap(view_sensor, "crop_points", "workspace crop")
    timer.wrap(env.map, "fuse", "fusion (voxel map)")
    timer.wrap(CoverageTracker, "update", "coverage")
    timer.wrap(env, "_observation", "observation")


def _instrument_grasp(env, timer: PhaseTimer) -> None:
    import mujoco

    from liuxing_envs import kernels
    from liuxing_envs.sim import grasp_world
    from liuxing_envs.sim.camera import DepthCamera
    from liuxing_envs.sim.gripper import Gripper

    timer.wrap(mujoco, "mj_step", "physics (mj_step)")
    if kernels.available():
        from liuxing_envs.kernels import force_loop

        # Its mj_step calls, and the force samples between them, in one call.
        timer.wrap(force_loop, "sleeping_samples", "physics (mj_step)")
    timer.wrap(env.arm_controller, "apply", "controller (IK)")
    timer.wrap(Gripper, "fingertip_forces", "force sensing")
    timer.wrap(grasp_world.GraspWorld, "impact_force", "force sensing")
    timer.wrap(DepthCamera, "render", "depth rendering")
    timer.wrap(grasp_world.GraspWorld, "rgb", "RGB rendering")
    timer.wrap(env, "_observation", "observation")


def split(config: Config, steps: int) -> dict:
    """Milliseconds per env step, per phase (resets included), over ``steps`` random steps."""
    env = make_env(config)
    env.action_space.seed(0)
    env.reset(seed=0)
    timer = PhaseTimer()
    instrument = _instrument_view_planning if config.env_id == VIEW_PLANNING else _instrument_grasp
    instrument(env.unwrapped, timer)
    random_steps(env, steps // 4)  # warm-up
    timer.seconds.clear()
    total = random_steps(env, steps)
    env.close()
    phases = {phase: 1e3 * s / steps for phase, s in timer.seconds.items()}
    phases["other (gym wrappers, actions, rewards, info)"] = 1e3 * total / steps - sum(
        phases.values()
    )
    return {"ms_per_step": 1e3 * total / steps, "phases": phases}


SPLIT_CONFIGS = (
    Config(VIEW_PLANNING, {"depth_backend": "raycast", "motion": "kinematic", "resolution": 64}),
    Config(VIEW_PLANNING, {"depth_backend": "gl", "motion": "kinematic", "resolution": 64}),
    Config(VIEW_PLANNING, {"depth_backend": "raycast", "motion": "dynamic", "resolution": 64}),
    Config(GRASP, {"obs_mode": "state"}),
    Config(GRASP, {"obs_mode": "depth", "depth_backend": "raycast"}),
    Config(GRASP, {"obs_mode": "rgbd", "depth_backend": "gl"}),
)


def measure(config: Config, steps: int) -> dict:
    return run_in_fresh_process(
        "benchmarks.time_split", "--one", config.to_json(), "--steps", str(steps)
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", required=True, help="a Config as JSON")
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args()
    print(json.dumps(split(Config.from_json(args.one), args.steps)))


if __name__ == "__main__":
    main()
