"""The learning-curve figure of a run folder: evaluation return and task metric against steps,
with the training episodes' returns (SB3 Monitor files) behind them."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from agents import run_folder

SMOOTHING_EPISODES = 100


def training_returns(run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(cumulative env steps, episode return) of every training episode, in time order."""
    rows = []
    for path in sorted((Path(run_dir) / run_folder.MONITOR).glob("*.monitor.csv")):
        with open(path, newline="") as handle:
            handle.readline()  # the Monitor's JSON header
            rows += [(float(r["t"]), float(r["r"]), int(r["l"])) for r in csv.DictReader(handle)]
    if not rows:
        return np.zeros(0), np.zeros(0)
    rows.sort()
    lengths = np.array([row[2] for row in rows])
    return np.cumsum(lengths), np.array([row[1] for row in rows])


def plot_learning_curve(run_dir: Path, metric_label: str, episodes: int) -> Path | None:
    """``episodes``: how many episodes each evaluation averaged."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run_dir = Path(run_dir)
    evaluations = run_folder.read_evaluations(run_dir)
    steps, returns = training_returns(run_dir)
    if not evaluations and not len(steps):
        return None
    figure, (ax_return, ax_metric) = plt.subplots(1, 2, figsize=(10, 4))
    if len(steps):
        window = min(SMOOTHING_EPISODES, len(returns))
        smooth = np.convolve(returns, np.ones(window) / window, mode="valid")
        ax_return.plot(
            steps[window - 1 :], smooth, color="0.6", label=f"training ({window}-episode mean)"
        )
    if evaluations:
        x = [row["timesteps"] for row in evaluations]
        mean = np.array([row["mean_return"] for row in evaluations])
        # The spread across episodes mostly measures how objects differ; the band is the
        # mean's 95% interval, which is what says whether the policy changed.
        half = 1.96 * np.array([row["std_return"] for row in evaluations]) / np.sqrt(episodes)
        ax_return.plot(x, mean, color="C0", label="evaluation (95% CI of the mean)")
        ax_return.fill_between(x, mean - half, mean + half, color="C0", alpha=0.2)
        ax_metric.plot(x, [row["mean_metric"] for row in evaluations], color="C1", marker=".")
    ax_return.set(xlabel="environment steps", ylabel="episode return")
    ax_return.legend(loc="lower right")
    ax_metric.set(xlabel="environment steps", ylabel=f"evaluation {metric_label}")
    for axis in (ax_return, ax_metric):
        axis.grid(alpha=0.3)
    figure.tight_layout()
    path = run_dir / run_folder.LEARNING_CURVE
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path
