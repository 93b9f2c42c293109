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
