"""The learning curve's training episodes, as SB3's Monitor writes them."""

from __future__ import annotations

import json

import numpy as np

from agents import run_folder
from agents.plotting import learning_curve_figure, plot_learning_curve, training_returns


def _write_monitor(path, t_start: float, episodes: list[tuple[float, int, float]]) -> None:
    """A Monitor file as SB3's Monitor writes it: a JSON header with the file's start time, a
    CSV header, then one row per episode of (return, length, seconds since the start)."""
    header = json.dumps({"t_start": t_start, "env_id": "InstrumentGrasp-v1"})
    rows = "".join(f"{r},{length},{t}\n" for r, length, t in episodes)
    path.write_text(f"#{header}\nr,l,t\n{rows}")


def test_a_resumed_runs_episodes_follow_the_first_segments(tmp_path):
    """Each Monitor file counts ``t`` from its own start and a resumed run writes a new one:
    the resumed episode comes last although its file sorts first and its ``t`` is smallest."""
    monitor = tmp_path / run_folder.MONITOR
    monitor.mkdir()
    _write_monitor(monitor / "b.monitor.csv", 1000.0, [(-1.5, 4, 0.5), (2.25, 4, 0.9)])
    _write_monitor(monitor / "a.monitor.csv", 1010.0, [(7.0, 2, 0.1)])  # the resumed run
    # A crash can leave a file empty, or a last line cut short: both are skipped.
    (monitor / "c.monitor.csv").write_text("")
    with open(monitor / "b.monitor.csv", "a") as handle:
        handle.write("1.5,4")
    steps, returns = training_returns(tmp_path)
    np.testing.assert_array_equal(steps, [4, 8, 10])
    np.testing.assert_array_equal(returns, [-1.5, 2.25, 7.0])
    assert plot_learning_curve(tmp_path, "success rate", 10).is_file()


def test_a_short_runs_learning_curve_shows_its_point_on_whole_steps(tmp_path):
    """A run of one episode and no evaluation drew an invisible line, and the empty
    evaluation axis read "0, 200m, 400m, ...": steps in milli-steps."""
    monitor = tmp_path / run_folder.MONITOR
    monitor.mkdir()
    _write_monitor(monitor / "a.monitor.csv", 1000.0, [(1.0, 200, 0.1)])
    figure = learning_curve_figure(tmp_path, "success rate", 2)
    figure.canvas.draw()
    returns, metric = figure.axes
    (training,) = returns.get_lines()
    assert training.get_marker() not in (None, "None", "")  # one point, drawn
    for axis in (returns, metric):
        labels = [label.get_text() for label in axis.get_xticklabels()]
        assert labels and all(text.lstrip("-").isdigit() for text in labels), labels
    assert [text.get_text() for text in metric.texts] == ["no periodic evaluation"]


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
