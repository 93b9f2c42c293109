"""Sweeps on Ray Tune: every configuration of a sweep file, each with every seed, as
ordinary run folders (``python train.py --sweep FILE``).

One Tune trial is one configuration with one seed. It trains in a child process
(``python -m agents.sweep_trial``) in its run folder under ``SWEEP/runs/``, exactly what
``train.py`` alone writes there, and reports each periodic evaluation to Tune as it lands in
``evaluations.csv``. A trial whose worker dies (killed, out of memory, its node lost) is
retried by Tune up to ``max_failures`` times; the retry resumes the run folder from its
newest checkpoint. The same command resumes an interrupted sweep: Tune's own state under
``SWEEP/tune/`` keeps finished trials finished, and a finished run folder trains nothing.

A configuration's score is the interquartile mean of every periodic evaluation score (the
task's metric: coverage, success) of all its seeds; with a search space, Optuna (through
Tune's searcher) learns from those scores, one per configuration. ``SWEEP/summary.md`` and
``summary.csv`` are rewritten as results come in.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import pickle
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from agents import run_folder
from agents.config import keep_beside
from agents.statistics import iqm
from agents.sweep_file import (
    RECORD,
    RUNS,
    Sweep,
    configuration_id,
    trial_name,
    trial_record,
)

#: The metric every trial reports: one periodic evaluation's mean of the task's metric.
SCORE = "score"
#: Where Tune keeps the sweep's state (its experiment folder), under the sweep's folder.
TUNE_FOLDER = "tune"
SUMMARY = "summary"
FINISHED, FAILED = "finished", "failed"
#: How often (s) a trial looks for new evaluations of its run.
POLL_SECONDS = 1.0
#: How long (s) a retried trial waits for its killed predecessor's training process to
#: save its checkpoint and free the run folder.
LOCK_WAIT_SECONDS = 120.0
REPO_ROOT = Path(__file__).resolve().parents[1]


class TrialFailed(RuntimeError):
    """A trial's training process ended with an error (its log's tail is the message)."""


# ---------------------------------------------------------------------------- the trial
def run_trial(trial: Mapping[str, Any], sweep: Sweep, folder: str) -> None:
    """Tune's function trainable: trains one configuration with one seed in its run folder
    (resuming it where it stopped), reporting each periodic evaluation."""
    from ray import tune

    params, seed = dict(trial["params"]), int(trial["seed"])
    run_dir = Path(folder) / RUNS / trial_name(params, seed)
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    config = sweep.run_config(params, seed)
    _record_trial(run_dir, params, seed)
    _wait_for_the_folder(run_dir)
    environment = {**os.environ, **thread_caps(sweep.threads), "PYTHONPATH": str(REPO_ROOT)}
    log = run_dir.parent / f"{run_dir.name}.log"
    with open(log, "ab") as output:
        child = subprocess.Popen(
            [sys.executable, "-m", "agents.sweep_trial", str(run_dir)],
            stdin=subprocess.PIPE,
            stdout=output,
            stderr=subprocess.STDOUT,
            cwd=REPO_ROOT,
            env=environment,
            preexec_fn=_stop_with_parent,
        )
        child.stdin.write(pickle.dumps(config))
        child.stdin.close()
        reported: set[int] = set()
        while True:
            finished = child.poll() is not None
            for row in _new_evaluations(run_dir, reported):
                tune.report(
                    {
                        SCORE: row["mean_metric"],
                        "timesteps": row["timesteps"],
                        "mean_return": row["mean_return"],
                        "configuration": configuration_id(params),
                        "seed": seed,
                    }
                )
            if finished:
                break
            time.sleep(POLL_SECONDS)
    if child.returncode != 0:
        tail = log.read_text(errors="replace").splitlines()[-15:]
        raise TrialFailed(
            f"{run_dir.name}: training exited with {child.returncode}:\n" + "\n".join(tail)
        )


def _record_trial(run_dir: Path, params: Mapping[str, Any], seed: int) -> None:
    """The trial's settings and the Ray worker running it (its latest attempt's)."""
    import ray

    record = {
        "params": dict(params),
        "seed": seed,
        "pid": os.getpid(),
        "node": ray.get_runtime_context().get_node_id(),
        "host": socket.gethostname(),
    }
    run_folder.write_text_atomically(trial_record(run_dir), json.dumps(record))


def thread_caps(threads: int) -> dict[str, str]:
    """The environment that holds a trial's numerical libraries to ``threads`` threads."""
    value = str(threads)
    names = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")
    return dict.fromkeys(names, value)


def _stop_with_parent() -> None:
    """In the training process: a SIGTERM when the Ray worker that started it dies (it
    then saves a checkpoint and exits), so a killed trial leaves no training behind."""
    import ctypes

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def _wait_for_the_folder(run_dir: Path) -> None:
    """Waits while another process holds ``run_dir`` (a killed trial's training saving its
    checkpoint), up to LOCK_WAIT_SECONDS."""
    if not (run_dir / run_folder.LOCK).exists():
        return
    deadline = time.monotonic() + LOCK_WAIT_SECONDS
    while True:
        try:
            with run_folder.exclusive(run_dir):
                return
        except run_folder.RunFolderError:
            if time.monotonic() > deadline:
                raise
            time.sleep(POLL_SECONDS)


def _new_evaluations(run_dir: Path, reported: set[int]) -> list[dict]:
    if not (run_dir / run_folder.EVALUATIONS).is_file():
        return []
    rows = [row for row in run_folder.read_evaluations(run_dir) if row["timesteps"] not in reported]
    reported.update(row["timesteps"] for row in rows)
    return rows


# ---------------------------------------------------------------------------- seeds
def _seed_groups(searcher, seeds):
    """``searcher`` (Optuna's) suggesting configurations that each run with every seed, and
    learning each configuration's score once all its seeds have ended (made lazily: Ray is
    imported only when a sweep runs)."""
    from ray.tune.search import Searcher

    class SeedGroups(Searcher):
        def __init__(self) -> None:
            super().__init__(metric=SCORE, mode="max")
            self.searcher = searcher
            self.seeds = list(seeds)
            self.pending: list[tuple[str, dict, int]] = []
            self.groups: dict[str, dict] = {}
            self.group_of: dict[str, str] = {}

        def set_search_properties(self, metric, mode, config, **spec) -> bool:
            return True  # the space is the wrapped searcher's own

        def suggest(self, trial_id: str):
            if not self.pending:
                group = f"configuration_{len(self.groups)}"
                params = self.searcher.suggest(group)
                if not isinstance(params, dict):
                    return params  # None (wait) or FINISHED
                self.groups[group] = {"scores": {}, "ended": 0, "errors": 0}
                self.pending = [(group, params, seed) for seed in self.seeds]
            group, params, seed = self.pending.pop(0)
            self.group_of[trial_id] = group
            return {"params": params, "seed": seed}

        def on_trial_result(self, trial_id: str, result: dict) -> None:
            group = self.groups[self.group_of[trial_id]]
            group["scores"][(result["seed"], result["timesteps"])] = result[SCORE]

        def on_trial_complete(self, trial_id: str, result=None, error: bool = False) -> None:
            name = self.group_of.get(trial_id)
            if name is None:
                return
            group = self.groups[name]
            group["ended"] += 1
            group["errors"] += bool(error)
            if group["ended"] < len(self.seeds):
                return
            scores = list(group["scores"].values())
            if scores:
                self.searcher.on_trial_complete(name, {SCORE: iqm(scores)})
            else:
                self.searcher.on_trial_complete(name, None, error=True)

        # Tune pickles these with the sweep's state, so a resumed sweep goes on where its
        # search stood (Optuna's study included).
        def get_state(self) -> dict:
            return dict(self.__dict__)

        def set_state(self, state: dict) -> None:
            self.__dict__.update(state)

        def save(self, checkpoint_path: str) -> None:
            with open(checkpoint_path, "wb") as file:
                pickle.dump(self.get_state(), file)

        def restore(self, checkpoint_path: str) -> None:
            with open(checkpoint_path, "rb") as file:
                self.set_state(pickle.load(file))

    return SeedGroups()


def _tune_space(space: Mapping[str, Mapping]):
    from ray import tune

    samplers = {
        "uniform": lambda value: tune.uniform(*value),
        "log_uniform": lambda value: tune.loguniform(*value),
        "int": lambda value: tune.randint(value[0], value[1] + 1),
        "choice": tune.choice,
    }
    domains = {}
    for path, spec in space.items():
        ((form, value),) = spec.items()
        domains[path] = samplers[form](value)
    return domains


# ---------------------------------------------------------------------------- the summary
def _summary_callback(folder: Path):
    from ray import tune

    class SummaryTable(tune.Callback):
        """Rewrites the sweep's summary (each trial's best score and status, each
        configuration's IQM so far) as results come in."""

        def __init__(self) -> None:
            self.scores: dict[str, dict[int, float]] = {}
            #: Tune calls back before it sets a trial's status: the ended ones, by id.
            self.ended: dict[str, str] = {}

        def on_trial_result(self, iteration, trials, trial, result, **info) -> None:
            self.scores.setdefault(trial.trial_id, {})[result["timesteps"]] = result[SCORE]
            write_summary(folder, trials, self.scores, self.ended)

        def on_trial_complete(self, iteration, trials, trial, **info) -> None:
            self.ended[trial.trial_id] = FINISHED
            write_summary(folder, trials, self.scores, self.ended)

        def on_trial_error(self, iteration, trials, trial, **info) -> None:
            self.ended[trial.trial_id] = FAILED
            write_summary(folder, trials, self.scores, self.ended)

    return SummaryTable()


def write_summary(folder: Path, trials, scores, ended: Mapping[str, str]) -> None:
    """``summary.csv`` (one row per trial: its best evaluation score so far and its status)
    and ``summary.md`` (one row per configuration: its seeds' IQM so far) of the sweep in
    ``folder``; ``scores`` maps trial ids to their evaluations' scores by step."""
    rows = []
    for trial in trials:
        params, seed = trial.config["params"], trial.config["seed"]
        own = scores.get(trial.trial_id, {})
        rows.append(
            {
                "configuration": configuration_id(params),
                "seed": seed,
                "status": _status(trial, ended),
                "evaluations": len(own),
                "timesteps": max(own, default=0),
                "best_score": max(own.values(), default=math.nan),
                "settings": " ".join(f"{key}={value}" for key, value in params.items()),
            }
        )
    rows.sort(key=lambda row: (row["configuration"], row["seed"]))
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]) if rows else ["configuration"])
    writer.writeheader()
    writer.writerows(rows)
    run_folder.write_text_atomically(folder / f"{SUMMARY}.csv", text.getvalue())
    markdown = _summary_markdown(trials, scores, ended)
    run_folder.write_text_atomically(folder / f"{SUMMARY}.md", markdown)


def _status(trial, ended: Mapping[str, str]) -> str:
    if trial.trial_id in ended:
        return ended[trial.trial_id]
    return {"RUNNING": "running", "TERMINATED": FINISHED, "ERROR": FAILED}.get(
        trial.status, "waiting"
    )


def _summary_markdown(trials, scores, ended) -> str:
    configurations: dict[str, dict] = {}
    for trial in trials:
        params = trial.config["params"]
        entry = configurations.setdefault(
            configuration_id(params), {"params": params, "scores": [], "trials": []}
        )
        entry["scores"] += list(scores.get(trial.trial_id, {}).values())
        entry["trials"].append(trial)
    lines = [
        "| configuration | settings | seeds finished | evaluations | IQM score so far |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, entry in sorted(configurations.items()):
        done = sum(_status(trial, ended) == FINISHED for trial in entry["trials"])
        shown = f"{iqm(entry['scores']):.3f}" if entry["scores"] else "-"
        settings = ", ".join(f"{key}={value}" for key, value in entry["params"].items())
        lines.append(
            f"| {name} | {settings} | {done} of {len(entry['trials'])} | "
            f"{len(entry['scores'])} | {shown} |"
        )
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------- the sweep
def record_sweep(sweep: Sweep, folder: Path) -> None:
    """Keep the sweep file beside its trials; a folder of another sweep is refused."""
    keep_beside(sweep.path, folder / RECORD, "another sweep")


def run_sweep(sweep: Sweep, folder: Path, ray_address: str | None = None, verbose: int = 1):
    """Runs (or resumes) ``sweep`` in ``folder`` on a local Ray (the machine's cores) or the
    cluster at ``ray_address``; returns Tune's result grid."""
    import ray
    from ray import tune

    folder = Path(folder).resolve()
    record_sweep(sweep, folder)
    runtime = {"env_vars": {"PYTHONPATH": str(REPO_ROOT)}}
    if not ray.is_initialized():
        # "local": a Ray of its own, never one another process started on this machine
        # (ray.init alone joins the newest local cluster it finds).
        address = ray_address or os.environ.get("RAY_ADDRESS") or "local"
        ray.init(address=address, runtime_env=runtime, include_dashboard=False)
    trainable = tune.with_resources(
        tune.with_parameters(run_trial, sweep=sweep, folder=str(folder)),
        {"cpu": sweep.resources["cpu"], "gpu": sweep.resources["gpu"]},
    )
    experiment = folder / TUNE_FOLDER
    if tune.Tuner.can_restore(str(experiment)):
        tuner = tune.Tuner.restore(
            str(experiment), trainable, resume_unfinished=True, resume_errored=True
        )
        return tuner.fit()
    run_config = tune.RunConfig(
        name=TUNE_FOLDER,
        storage_path=str(folder),
        failure_config=tune.FailureConfig(max_failures=sweep.max_failures),
        callbacks=[_summary_callback(folder)],
        verbose=verbose,
    )
    if sweep.grid is not None:
        param_space = {
            "params": tune.grid_search(sweep.grid_points()),
            "seed": tune.grid_search(list(sweep.seeds)),
        }
        tune_config = tune.TuneConfig(metric=SCORE, mode="max")
    else:
        from ray.tune.search.optuna import OptunaSearch

        optuna = OptunaSearch(metric=SCORE, mode="max", seed=sweep.search["seed"], space=None)
        optuna.set_search_properties(SCORE, "max", _tune_space(sweep.search["space"]))
        param_space = {}
        tune_config = tune.TuneConfig(
            metric=SCORE,
            mode="max",
            search_alg=_seed_groups(optuna, sweep.seeds),
            num_samples=sweep.search["samples"] * len(sweep.seeds),
        )
    tuner = tune.Tuner(
        trainable, param_space=param_space, tune_config=tune_config, run_config=run_config
    )
    return tuner.fit()
