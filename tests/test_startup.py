"""What a process pays before its first step: open3d, seconds to import, only when it is used;
numba's compilation, once per checkout."""

import os
import subprocess
import sys

import pytest

_STEP_BOTH_ENVS = """
import sys
import gymnasium as gym
import liuxing_envs

for env_id in ("ViewPlanning-v1", "InstrumentGrasp-v1"):
    env = gym.make(env_id)
    env.reset(seed=0)
    for _ in range(3):
        env.step(env.action_space.sample())
    env.close()
print("open3d imported" if "open3d" in sys.modules else "open3d not imported")
"""


def _step_both_envs() -> str:
    done = subprocess.run(
        [sys.executable, "-c", _STEP_BOTH_ENVS], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.strip().splitlines()[-1]


def test_envs_step_without_importing_open3d_once_their_ground_truth_is_cached():
    _step_both_envs()  # fills the session's disk cache where an earlier test has not
    assert _step_both_envs() == "open3d not imported"


def test_a_slow_first_preparation_of_the_objects_says_what_it_does(tmp_path, monkeypatch, caplog):
    """With a cold disk cache the first env of a process ray-cast for minutes, silently."""
    import logging

    import gymnasium as gym

    from liuxing_envs.sim import objects, view_scene

    monkeypatch.setenv("LIUXING_ENVS_CACHE", str(tmp_path / "cold"))
    monkeypatch.setattr(view_scene, "SLOW_PREPARATION_SECONDS", 0.0)  # every variant counts
    objects.clear_memory_caches()
    with caplog.at_level(logging.INFO, logger="liuxing_envs"):
        gym.make("ViewPlanning-v1", objects=["box", "bench"]).close()
    objects.clear_memory_caches()  # the other tests' envs read the session's cache again
    messages = [r.getMessage() for r in caplog.records if r.name.startswith("liuxing_envs")]
    assert len(messages) == 10  # two objects at the default five scales
    assert "'box' at scale " in messages[0] and "(1 of 10 object variants;" in messages[0]
    assert "'bench' at scale " in messages[-1] and "(10 of 10 object variants;" in messages[-1]


_COUNT_COMPILED = """
import sys
from pathlib import Path
print(sum(1 for _ in Path(sys.argv[1]).rglob("*.nbc")))
"""


@pytest.mark.long
def test_the_kernel_warm_up_leaves_nothing_for_a_run_to_compile(tmp_path):
    # make install runs `python -m liuxing_envs.kernels`; afterwards stepping the envs in
    # the settings a training and its evaluation use (the oracle's previews, free space,
    # both grasp observation kinds) must find every kernel it calls in numba's cache.
    environ = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "MUJOCO_GL": "egl"}

    def run(*args: str) -> str:
        done = subprocess.run(
            [sys.executable, *args], capture_output=True, text=True, timeout=900, env=environ
        )
        assert done.returncode == 0, done.stderr[-2000:]
        return done.stdout

    assert "kernels compiled and cached" in run("-m", "liuxing_envs.kernels")
    compiled = int(run("-c", _COUNT_COMPILED, str(tmp_path)))
    modules = {path.name.split(".")[0] for path in tmp_path.rglob("*.nbc")}
    assert {"coverage", "depth", "fusion", "ik", "one_pose_ik", "path_proof", "frustum"} <= modules
    run("-c", _STEP_BOTH_ENVS)
    run("-c", _STEP_VIEW_PLANNING_AS_TRAINING_DOES)
    assert int(run("-c", _COUNT_COMPILED, str(tmp_path))) == compiled


_STEP_VIEW_PLANNING_AS_TRAINING_DOES = """
import gymnasium as gym
import liuxing_envs

vec = gym.make_vec("ViewPlanning-v1", num_envs=2, object_set="procedural")
vec.reset(seed=0)
for _ in range(6):
    vec.step(vec.action_space.sample())
vec.close()
env = gym.make("ViewPlanning-v1", object_set="held_out").unwrapped
env.reset(seed=1)
env.preview_view(0.5, 0.4, 0.45)
"""
