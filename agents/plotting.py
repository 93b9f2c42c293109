"""Figures: a run folder's learning curve (evaluation return and task metric against steps,
with the training episodes' returns behind them) and the evaluation report's figures."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from agents import run_folder

SMOOTHING_EPISODES = 100


def training_returns(run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(the run's step count at its end, return) of every training episode, in step order
    (see :func:`agents.run_folder.episode_ends`). An older run's files, which do not say where
    they start, are placed by their cumulative logged steps in time order."""
    placed, unplaced = [], []
    for path in run_folder.monitor_files(run_dir):
        monitor = run_folder.read_monitor(path)
        if monitor is None:
            continue
        ends = run_folder.episode_ends(path, monitor)
        if ends is None:
            unplaced += [(end, reward, length) for end, reward, length, _ in monitor.episodes]
        else:
            placed += [(end, e[1]) for end, e in zip(ends, monitor.episodes, strict=True)]
    unplaced.sort()
    lengths = np.cumsum([length for _, _, length in unplaced], dtype=np.int64)
    placed += [(int(end), row[1]) for end, row in zip(lengths, unplaced, strict=True)]
    if not placed:
        return np.zeros(0), np.zeros(0)
    placed.sort(key=lambda row: row[0])
    return np.array([row[0] for row in placed]), np.array([row[1] for row in placed])


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(figure, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    _pyplot().close(figure)
    return path


def plot_learning_curve(run_dir: Path, metric_label: str, episodes: int) -> Path | None:
    """The run's learning curve as ``learning_curve.png`` in ``run_dir`` (None before its
    first episode); ``episodes``: how many episodes each evaluation averaged."""
    figure = learning_curve_figure(run_dir, metric_label, episodes)
    return None if figure is None else _save(figure, Path(run_dir) / run_folder.LEARNING_CURVE)


def learning_curve_figure(run_dir: Path, metric_label: str, episodes: int):
    """The figure :func:`plot_learning_curve` saves: training returns and periodic
    evaluations against environment steps."""
    plt = _pyplot()
    from matplotlib.ticker import EngFormatter, MaxNLocator

    run_dir = Path(run_dir)
    evaluations = run_folder.read_evaluations(run_dir)
    steps, returns = training_returns(run_dir)
    if not evaluations and not len(steps):
        return None
    figure, (ax_return, ax_metric) = plt.subplots(1, 2, figsize=(10, 4))
    if len(steps):
        window = min(SMOOTHING_EPISODES, len(returns))
        smooth = np.convolve(returns, np.ones(window) / window, mode="valid")
        # Markers, so that the one point of a short run shows.
        ax_return.plot(
            steps[window - 1 :],
            smooth,
            color="0.6",
            marker=".",
            label=f"training ({window}-episode mean)",
        )
    if evaluations:
        x = [row["timesteps"] for row in evaluations]
        mean = np.array([row["mean_return"] for row in evaluations])
        # The spread across episodes mostly measures how objects differ; the band is the
        # mean's 95% interval, which is what says whether the policy changed.
        half = 1.96 * np.array([row["std_return"] for row in evaluations]) / np.sqrt(episodes)
        ax_return.plot(x, mean, color="C0", marker=".", label="evaluation (95% CI of the mean)")
        ax_return.fill_between(x, mean - half, mean + half, color="C0", alpha=0.2)
        ax_metric.plot(x, [row["mean_metric"] for row in evaluations], color="C1", marker=".")
    else:
        ax_metric.text(
            0.5, 0.5, "no periodic evaluation", ha="center", transform=ax_metric.transAxes
        )
    ax_return.set(xlabel="environment steps", ylabel="episode return")
    ax_return.legend(loc="lower right")
    ax_metric.set(xlabel="environment steps", ylabel=f"evaluation {metric_label}")
    for axis in (ax_return, ax_metric):
        axis.grid(alpha=0.3)
        axis.xaxis.set_major_formatter(EngFormatter(sep=""))  # 200k, not 200000 (they overlap)
        axis.xaxis.set_major_locator(MaxNLocator(integer=True))  # steps: no "200m" ticks
    return figure


def plot_coverage_curves(path: Path, curves: dict) -> Path:
    """Coverage against views taken, one line per contestant with its 95% CI band; ``curves``
    maps a label to a list of ``{"mean", "ci95"}`` per view (index 0: the start view)."""
    plt = _pyplot()
    figure, axis = plt.subplots(figsize=(6, 4))
    for index, (label, curve) in enumerate(curves.items()):
        views = np.arange(len(curve))
        mean = np.array([entry["mean"] for entry in curve])
        # No band where an interval is undefined (one episode).
        low, high = np.array([entry["ci95"] or [entry["mean"]] * 2 for entry in curve]).T
        axis.plot(views, mean, marker="o", color=f"C{index}", label=label)
        axis.fill_between(views, low, high, color=f"C{index}", alpha=0.2)
    axis.set(xlabel="views taken (0: start view)", ylabel="surface coverage", ylim=(0, 1))
    axis.xaxis.get_major_locator().set_params(integer=True)
    axis.grid(alpha=0.3)
    axis.legend(loc="lower right")
    return _save(figure, path)


def plot_reconstructions(
    path: Path, folder: Path, label: str, seeds: Sequence[int] | None = None
) -> Path | None:
    """Saved reconstructions (``folder/seed_<seed>/``, of ``seeds`` or else all) beside their
    ground truth: one row per episode, points seen from the same oblique view. None when
    nothing was saved."""
    if seeds is None:
        episodes = sorted(Path(folder).glob("seed_*/ground_truth.ply"))
    else:  # only this report's: an earlier report into the same folder may have left others
        episodes = [Path(folder) / f"seed_{seed}" / "ground_truth.ply" for seed in seeds]
        episodes = [episode for episode in episodes if episode.is_file()]
    if not episodes:
        return None
    import open3d as o3d  # here, not above: seconds to import, for reports with no meshes

    plt = _pyplot()
    figure = plt.figure(figsize=(7, 3.2 * len(episodes)))
    for row, truth_path in enumerate(episodes):
        truth = np.asarray(o3d.io.read_point_cloud(str(truth_path)).points)
        mesh_path = truth_path.parent / "reconstruction_mesh.ply"
        cloud_path = truth_path.parent / "reconstruction_cloud.ply"
        if mesh_path.is_file():
            built, kind = np.asarray(o3d.io.read_triangle_mesh(str(mesh_path)).vertices), "mesh"
        else:
            built, kind = np.asarray(o3d.io.read_point_cloud(str(cloud_path)).points), "cloud"
        lows, highs = truth.min(axis=0), truth.max(axis=0)
        centre, half = (lows + highs) / 2, (highs - lows).max() / 2 * 1.1
        for column, (points, title, colour) in enumerate(
            (
                (truth, "ground truth (observable surface)", "0.4"),
                (built, f"{label}: reconstruction {kind}", "C0"),
            )
        ):
            axis = figure.add_subplot(len(episodes), 2, 2 * row + column + 1, projection="3d")
            axis.scatter(*points.T, s=0.5, c=colour, depthshade=True)
            for setter, value in zip(
                (axis.set_xlim, axis.set_ylim, axis.set_zlim), centre, strict=True
            ):
                setter(value - half, value + half)
            axis.view_init(elev=30, azim=-60)
            axis.set_axis_off()
            axis.set_title(f"{truth_path.parent.name}: {title}", fontsize=8)
    return _save(figure, path)


def plot_force_traces(
    path: Path, traces: dict, force_limit: float, hard_limit: float, dt: float
) -> Path:
    """Peak fingertip force per control step for a few episodes of each contestant, one panel
    each, with the force limit and the hard limit drawn."""
    plt = _pyplot()
    figure, axes = plt.subplots(
        len(traces), 1, figsize=(7, 2.4 * len(traces)), sharex=True, squeeze=False
    )
    for axis, (label, episodes) in zip(axes[:, 0], traces.items(), strict=True):
        for index, trace in enumerate(episodes):
            axis.plot(dt * np.arange(1, len(trace) + 1), trace, lw=1, color=f"C{index}")
        axis.axhline(force_limit, color="orange", ls="--", label=f"limit {force_limit:g} N")
        axis.axhline(hard_limit, color="red", ls="--", label=f"hard limit {hard_limit:g} N")
        axis.set(ylabel="peak pad force (N)", title=label)
        axis.grid(alpha=0.3)
        axis.legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("time (s)")
    return _save(figure, path)


def plot_grasp_outcomes(path: Path, summaries: dict) -> Path:
    """Success, over-the-limit and hard-limit-stop rates per contestant, with 95% CIs."""
    plt = _pyplot()
    outcomes = (
        ("success", "success"),
        ("over_force_limit", "over the force limit"),
        ("hard_limit_exceeded", "hard-limit stop"),
    )
    figure, axis = plt.subplots(figsize=(1.8 + 1.6 * len(summaries), 3.6))
    width = 0.8 / len(outcomes)
    x = np.arange(len(summaries))
    for index, (key, name) in enumerate(outcomes):
        rates = np.array([s[key]["rate"] for s in summaries.values()])
        lows, highs = np.array([s[key]["ci95"] for s in summaries.values()]).T
        axis.bar(
            x + (index - 1) * width,
            rates,
            width,
            # Wilson bounds can sit a rounding error inside a 0% or 100% rate.
            yerr=np.clip([rates - lows, highs - rates], 0.0, None),
            capsize=3,
            label=name,
            color=("C2", "C1", "C3")[index],
        )
    axis.set_xticks(x, list(summaries), rotation=15)
    axis.set(ylabel="fraction of episodes", ylim=(0, 1.05))
    axis.legend(fontsize=8)
    axis.grid(alpha=0.3, axis="y")
    return _save(figure, path)


def plot_peak_forces(path: Path, peaks: dict, force_limit: float, hard_limit: float) -> Path:
    """Distribution of each episode's peak fingertip force per contestant, against the limits."""
    plt = _pyplot()
    figure, axis = plt.subplots(figsize=(1.8 + 1.6 * len(peaks), 3.6))
    rng = np.random.default_rng(0)
    for index, values in enumerate(peaks.values()):
        values = np.asarray(values, dtype=float)
        axis.boxplot(values, positions=[index], widths=0.5, showfliers=False)
        axis.scatter(index + rng.uniform(-0.15, 0.15, len(values)), values, s=6, alpha=0.5)
    axis.axhline(force_limit, color="orange", ls="--", label=f"limit {force_limit:g} N")
    axis.axhline(hard_limit, color="red", ls="--", label=f"hard limit {hard_limit:g} N")
    axis.set_xticks(range(len(peaks)), list(peaks), rotation=15)
    axis.set(ylabel="episode peak pad force (N)")
    axis.legend(fontsize=8)
    axis.grid(alpha=0.3, axis="y")
    return _save(figure, path)
