"""One folder per training run, holding everything needed to reproduce and resume it.

Layout (file names are constants here, so train.py, evaluate.py and tests agree)::

    <run>/config.yml          resolved configuration, command line, seed, versions, git commit
    <run>/model.zip           final policy            (+ vecnormalize.pkl when normalising)
    <run>/best_model.zip      best periodic evaluation (+ best_vecnormalize.pkl)
    <run>/checkpoints/        model_<steps>_steps.zip, replay_buffer_<steps>_steps.pkl (SAC),
                              vecnormalize_<steps>_steps.pkl
    <run>/evaluations.csv     periodic evaluation history
    <run>/monitor/            per-episode training returns (SB3 Monitor files)
    <run>/tensorboard/        TensorBoard logs (with --tensorboard)
    <run>/learning_curve.png  evaluation return and task metric against steps
    <run>/result.json         final comparison against the scripted baseline
"""

from __future__ import annotations

import csv
import importlib.metadata
import platform
import re
import subprocess
import sys
from pathlib import Path

import yaml

CONFIG = "config.yml"
FINAL_MODEL = "model.zip"
FINAL_NORMALIZER = "vecnormalize.pkl"
BEST_MODEL = "best_model.zip"
BEST_NORMALIZER = "best_vecnormalize.pkl"
CHECKPOINTS = "checkpoints"
EVALUATIONS = "evaluations.csv"
MONITOR = "monitor"
TENSORBOARD = "tensorboard"
LEARNING_CURVE = "learning_curve.png"
RESULT = "result.json"

_CHECKPOINT = re.compile(r"model_(\d+)_steps\.zip$")
EVALUATION_FIELDS = ("timesteps", "mean_return", "std_return", "mean_metric", "wall_seconds")
VERSIONED_PACKAGES = (
    "liuxing_envs",
    "gymnasium",
    "mujoco",
    "stable_baselines3",
    "torch",
    "numpy",
)


class RunFolderError(ValueError):
    """A run folder that cannot be used as asked (missing, incomplete, not a run)."""


def checkpoint_paths(run_dir: Path, steps: int) -> dict[str, Path]:
    folder = Path(run_dir) / CHECKPOINTS
    return {
        "model": folder / f"model_{steps}_steps.zip",
        "replay_buffer": folder / f"replay_buffer_{steps}_steps.pkl",
        "normalizer": folder / f"vecnormalize_{steps}_steps.pkl",
    }


def checkpoint_steps(run_dir: Path) -> list[int]:
    """Step counts of the run's checkpoints, ascending."""
    folder = Path(run_dir) / CHECKPOINTS
    if not folder.is_dir():
        return []
    found = (_CHECKPOINT.search(path.name) for path in folder.iterdir())
    return sorted(int(match.group(1)) for match in found if match)


def latest_checkpoint(run_dir: Path) -> int | None:
    steps = checkpoint_steps(run_dir)
    return steps[-1] if steps else None


def prune_checkpoints(run_dir: Path, keep: int) -> None:
    """Keep the newest ``keep`` model checkpoints and only the newest replay buffer (they are
    large: a ViewPlanning transition holds two depth images and two occupancy maps)."""
    steps = checkpoint_steps(run_dir)
    for index, count in enumerate(steps):
        paths = checkpoint_paths(run_dir, count)
        newest = index == len(steps) - 1
        if index < len(steps) - keep:
            for path in paths.values():
                path.unlink(missing_ok=True)
        elif not newest:
            paths["replay_buffer"].unlink(missing_ok=True)


def library_versions() -> dict[str, str]:
    versions = {"python": platform.python_version(), "platform": platform.platform()}
    for name in VERSIONED_PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def git_commit(directory: Path | None = None) -> str | None:
    """HEAD of the checkout holding this code, suffixed ``-dirty`` with local changes."""
    directory = directory or Path(__file__).resolve().parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=directory, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=directory,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return f"{commit}-dirty" if dirty else commit


def write_config(run_dir: Path, config: dict) -> None:
    document = {
        **config,
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "versions": library_versions(),
        "git_commit": git_commit(),
    }
    (Path(run_dir) / CONFIG).write_text(yaml.safe_dump(document, sort_keys=False))


def read_config(run_dir: Path) -> dict:
    run_dir = Path(run_dir)
    path = run_dir / CONFIG
    if not run_dir.is_dir():
        raise RunFolderError(f"run folder {str(run_dir)!r} does not exist")
    if not path.is_file():
        raise RunFolderError(f"{str(run_dir)!r} is not a run folder: it has no {CONFIG}")
    try:
        config = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise RunFolderError(f"{str(path)!r} is not valid YAML: {error}") from error
    missing = [key for key in ("env_id", "algo", "seed", "hyperparams") if key not in config]
    if missing:
        raise RunFolderError(f"{str(path)!r} lacks {', '.join(missing)}")
    return config


def read_evaluations(run_dir: Path) -> list[dict]:
    """The periodic-evaluation history, oldest first."""
    path = Path(run_dir) / EVALUATIONS
    if not path.is_file():
        return []
    with open(path, newline="") as handle:
        return [{key: float(value) for key, value in row.items()} for row in csv.DictReader(handle)]


def append_evaluation(run_dir: Path, row: dict) -> None:
    path = Path(run_dir) / EVALUATIONS
    new = not path.is_file()
    with open(path, "a", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=EVALUATION_FIELDS)
        if new:
            writer.writeheader()
        writer.writerow(row)


#: What a shipped policy keeps of its run: enough to load, evaluate and reproduce it.
SHIPPED_FILES = (CONFIG, BEST_MODEL, BEST_NORMALIZER, EVALUATIONS, LEARNING_CURVE, RESULT)


def ship(run_dir: Path, destination: Path) -> Path:
    """Copy a run's best policy and its record into ``destination``: a slim run folder (no
    checkpoints, replay buffers or logs) that ``load_policy`` and evaluate.py read as is."""
    import shutil

    run_dir, destination = Path(run_dir), Path(destination)
    read_config(run_dir)
    if not (run_dir / BEST_MODEL).is_file():
        raise RunFolderError(f"{str(run_dir)!r} has no {BEST_MODEL} to ship")
    destination.mkdir(parents=True, exist_ok=True)
    for name in SHIPPED_FILES:
        if (run_dir / name).is_file():
            shutil.copy2(run_dir / name, destination / name)
    return destination
