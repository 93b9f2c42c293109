"""What a process pays before its first step: open3d, seconds to import, only when it is used."""

import subprocess
import sys

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
