"""Interval estimates for evaluation reports.

- :func:`bootstrap_ci` and :func:`wilson_interval`: 95% intervals of one policy's mean figure
  and success rate over evaluation episodes.
- :func:`iqm`, :func:`stratified_bootstrap_ci` and :func:`probability_of_improvement`: the
  aggregate figures of Agarwal et al., "Deep RL at the edge of the statistical precipice"
  (NeurIPS 2021), for several training seeds. Scores are ``(runs, tasks)`` matrices; here a
  run is a training seed and a task is one seeded evaluation episode (one object or
  instrument in one pose). The stratified bootstrap resamples seeds independently within
  each episode, as rliable does where each (run, game) pair is its own training run. Here a
  seed's policy plays every episode, so that mixes seeds within a resample and leaves most of
  the seed-to-seed spread out: it is kept for comparison with published figures.
- :func:`run_bootstrap_ci`: the interval for "how much could a new set of seeds move the
  figure on these episodes": whole seeds resampled with replacement, each with all its
  episodes.

The aggregate functions follow the rliable library's definitions. They are written out here
because rliable 1.2.0 (its latest release) cannot be imported next to pandas 3 (its bootstrap
dependency ``arch`` 7 fails at import; ``arch`` 8 dropped the argument rliable passes).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

BOOTSTRAP_RESAMPLES = 10_000
CONFIDENCE = 0.95


def _percentiles(samples: np.ndarray) -> tuple[float, float]:
    tail = 100.0 * (1.0 - CONFIDENCE) / 2.0
    low, high = np.percentile(samples, [tail, 100.0 - tail])
    return float(low), float(high)


def bootstrap_ci(values, seed: int = 0) -> tuple[float, float] | None:
    """95% percentile-bootstrap confidence interval of the mean; None for a single value,
    whose every resample is that value (a zero-width interval would claim certainty)."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        raise ValueError("bootstrap_ci needs at least one value")
    if values.size == 1:
        return None
    rng = np.random.default_rng(seed)
    means = rng.choice(values, size=(BOOTSTRAP_RESAMPLES, len(values))).mean(axis=1)
    return _percentiles(means)


def interval_text(ci: Sequence[float] | None, scale: float = 1.0, digits: int = 3) -> str:
    """``[low, high]`` for reports; a note where :func:`bootstrap_ci` gave none."""
    if ci is None:
        return "[no interval from one value]"
    low, high = ci
    return f"[{low * scale:.{digits}f}, {high * scale:.{digits}f}]"


def wilson_interval(successes: int, trials: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate."""
    if not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials, got {successes} of {trials}")
    if trials == 0:
        return 0.0, 1.0
    p = successes / trials
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = (
        z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / (1 + z * z / trials)
    )
    # Exact at the ends: floating point would put the bound a rounding error inside 0 or 1.
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == trials else min(1.0, centre + half)
    return low, high


def iqm(scores) -> float:
    """Interquartile mean: the mean of the middle 50% of all scores (rliable's
    ``aggregate_iqm``: 25% trimmed from each end, by count)."""
    flat = np.sort(np.asarray(scores, dtype=float).ravel())
    if flat.size == 0:
        raise ValueError("iqm needs at least one score")
    if np.isnan(flat[-1]):  # sorted last, a NaN would be trimmed away unseen
        return math.nan
    cut = int(0.25 * flat.size)
    return float(flat[cut : flat.size - cut].mean())


def _score_matrix(scores) -> np.ndarray:
    scores = np.asarray(scores, dtype=float)
    if scores.ndim != 2 or 0 in scores.shape:
        raise ValueError(f"scores must be a non-empty (runs, tasks) matrix, got {scores.shape}")
    return scores


def stratified_bootstrap_ci(scores, statistic=iqm, seed: int = 0) -> tuple[float, float]:
    """95% percentile interval of ``statistic`` over a ``(runs, tasks)`` score matrix, resampling
    runs with replacement independently within each task (rliable's ``StratifiedBootstrap``)."""
    scores = _score_matrix(scores)
    runs, tasks = scores.shape
    rng = np.random.default_rng(seed)
    columns = np.arange(tasks)
    samples = np.empty(BOOTSTRAP_RESAMPLES)
    for index in range(BOOTSTRAP_RESAMPLES):
        rows = rng.integers(runs, size=(runs, tasks))
        samples[index] = statistic(scores[rows, columns])
    return _percentiles(samples)


def run_bootstrap_ci(scores, statistic=np.mean, seed: int = 0) -> tuple[float, float] | None:
    """95% percentile interval of ``statistic`` over a ``(runs, tasks)`` score matrix, resampling
    whole runs (rows) with replacement; None for a single run (see :func:`bootstrap_ci`)."""
    scores = _score_matrix(scores)
    runs = len(scores)
    if runs == 1:
        return None
    rng = np.random.default_rng(seed)
    samples = np.array(
        [statistic(scores[rng.integers(runs, size=runs)]) for _ in range(BOOTSTRAP_RESAMPLES)]
    )
    return _percentiles(samples)


def probability_of_improvement(scores_x, scores_y) -> float:
    """P(X > Y): for each task, the Mann-Whitney probability that a run of X scores above a
    run of Y (ties count half), averaged over tasks. Matrices are ``(runs, tasks)`` with the
    same tasks; the run counts may differ (a scripted baseline has one run)."""
    x = np.asarray(scores_x, dtype=float)
    y = np.asarray(scores_y, dtype=float)
    if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1]:
        raise ValueError(
            f"need (runs, tasks) matrices over the same tasks, got {x.shape}, {y.shape}"
        )
    if np.isnan(x).any() or np.isnan(y).any():
        return math.nan  # a NaN compares as neither above nor equal: it would count as a loss
    above = (x[:, None, :] > y[None, :, :]).mean(axis=(0, 1))
    ties = (x[:, None, :] == y[None, :, :]).mean(axis=(0, 1))
    return float(np.mean(above + 0.5 * ties))


def probability_of_improvement_ci(scores_x, scores_y, seed: int = 0) -> tuple[float, float]:
    """95% stratified-bootstrap interval of :func:`probability_of_improvement`, resampling the
    runs of both within each task; 1,000 resamples (a tenth of the other intervals': each
    costs a comparison of every pair of runs on every task)."""
    x = np.asarray(scores_x, dtype=float)
    y = np.asarray(scores_y, dtype=float)
    rng = np.random.default_rng(seed)
    columns = np.arange(x.shape[1])
    samples = np.empty(BOOTSTRAP_RESAMPLES // 10)
    for index in range(samples.size):
        x_rows = rng.integers(x.shape[0], size=x.shape)
        y_rows = rng.integers(y.shape[0], size=y.shape)
        samples[index] = probability_of_improvement(x[x_rows, columns], y[y_rows, columns])
    return _percentiles(samples)
