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


def test_the_reconstruction_figure_shows_only_the_episodes_it_is_given(tmp_path):
    import matplotlib.image
    import open3d as o3d

    from agents.plotting import plot_reconstructions

    rng = np.random.default_rng(0)
    for seed in (7, 8):  # seed 7: left by an earlier report into the same folder
        folder = tmp_path / f"seed_{seed}"
        folder.mkdir()
        for name in ("ground_truth.ply", "reconstruction_cloud.ply"):
            cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.random((50, 3))))
            o3d.io.write_point_cloud(str(folder / name), cloud)
    both = plot_reconstructions(tmp_path / "both.png", tmp_path, "x")
    mine = plot_reconstructions(tmp_path / "mine.png", tmp_path, "x", seeds=[8, 9])
    rows = [matplotlib.image.imread(path).shape[0] for path in (both, mine)]
    assert rows[0] == 2 * rows[1]
    assert plot_reconstructions(tmp_path / "none.png", tmp_path, "x", seeds=[9]) is None
