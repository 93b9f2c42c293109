"""The learning curve's training episodes, as SB3's Monitor writes them."""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
from stable_baselines3.common.monitor import Monitor

import liuxing_envs  # noqa: F401  (registers the envs)
from agents import run_folder
from agents.plotting import plot_learning_curve, training_returns


def _write_monitor(path, episodes: int, length: int, pause: float = 0.0) -> None:
    """``episodes`` episodes of ``length`` steps, written by a real Monitor to ``path``."""
    env = Monitor(gym.make("InstrumentGrasp-v0", max_episode_steps=length), str(path))
    env.reset(seed=0)
    for _ in range(episodes):
        time.sleep(pause)
        done = False
        while not done:
            *_, terminated, truncated, _ = env.step(np.zeros(5, dtype=np.float32))
            done = terminated or truncated
        env.reset()
    env.close()


def test_a_resumed_runs_episodes_follow_the_first_segments(tmp_path):
    """Each Monitor file counts ``t`` from its own start and a resumed run writes a new one:
    the resumed episode comes last although its file sorts first and its ``t`` is smallest."""
    monitor = tmp_path / run_folder.MONITOR
    monitor.mkdir()
    _write_monitor(monitor / "b", episodes=2, length=4, pause=0.3)
    _write_monitor(monitor / "a", episodes=1, length=2)
    # A crash can leave a file empty, or a last line cut short: both are skipped.
    (monitor / "c.monitor.csv").write_text("")
    with open(monitor / "b.monitor.csv", "a") as handle:
        handle.write("1.5,4")
    steps, returns = training_returns(tmp_path)
    np.testing.assert_array_equal(steps, [4, 8, 10])
    assert returns.shape == (3,)
    assert plot_learning_curve(tmp_path, "success rate", 10).is_file()
