"""One folder per training run, holding everything needed to reproduce and resume it.

Layout (file names are constants here, so train.py, evaluate.py and tests agree)::

    <run>/config.yml          resolved configuration, command line, seed, versions, git commit
    <run>/git_diff.patch      the checkout's uncommitted changes when it trained (commit
                              ``-dirty``; a resume's: git_diff_resume<k>.patch)
    <run>/model.zip           final policy            (+ vecnormalize.pkl when normalising)
    <run>/best_model.zip      best periodic evaluation (+ best_vecnormalize.pkl)
    <run>/policy.zip          the best (else final) policy with its observation statistics
                              inside: plain ``PPO.load`` / ``SAC.load`` anywhere the package
                              is installed, acting on the env's raw observations (written when
                              training ends; what a shipped policy keeps)
    <run>/checkpoints/        model_<steps>_steps.zip, replay_buffer_<steps>_steps.pkl (SAC),
                              vecnormalize_<steps>_steps.pkl, curriculum_<steps>_steps.json
                              (the start curriculum's level, when it advances)
    <run>/evaluations.csv     periodic evaluation history (wall_seconds: of training behind the
                              row, across resumes; see training.TrainingClock)
    <run>/monitor/            per-episode training returns (SB3 Monitor files), one per env
                              and start of training: env<rank>-of-<n_envs>_from<steps>_<ns>
    <run>/tensorboard/        TensorBoard logs (with --tensorboard)
    <run>/learning_curve.png  evaluation return and task metric against steps
    <run>/result.json         final comparison against the scripted baseline
    <run>/demonstrations.json expert episodes that seeded the replay buffer (when configured)
    <run>/.lock               held by the process training in the folder (see exclusive())
"""

from __future__ import annotations

import csv
import importlib.metadata
import io
import itertools
import json
import os
import pickle
import platform
import re
import subprocess
import sys
import zipfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import yaml

from agents.config import NamesSettings

CONFIG = "config.yml"
FINAL_MODEL = "model.zip"
FINAL_NORMALIZER = "vecnormalize.pkl"
BEST_MODEL = "best_model.zip"
BEST_NORMALIZER = "best_vecnormalize.pkl"
POLICY = "policy.zip"
CHECKPOINTS = "checkpoints"
EVALUATIONS = "evaluations.csv"
MONITOR = "monitor"
TENSORBOARD = "tensorboard"
LEARNING_CURVE = "learning_curve.png"
RESULT = "result.json"
DEMONSTRATIONS = "demonstrations.json"
LOCK = ".lock"
GIT_DIFF = "git_diff.patch"

#: Everything a run writes into its folder.
ENTRIES = (
    CONFIG,
    FINAL_MODEL,
    FINAL_NORMALIZER,
    BEST_MODEL,
    BEST_NORMALIZER,
    POLICY,
    CHECKPOINTS,
    EVALUATIONS,
    MONITOR,
    TENSORBOARD,
    LEARNING_CURVE,
    RESULT,
    DEMONSTRATIONS,
    GIT_DIFF,
    LOCK,
)

_CHECKPOINT = re.compile(r"model_(\d+)_steps\.zip")
MONITOR_SUFFIX = ".monitor.csv"
_MONITOR_NAME = re.compile(r"env(\d+)-of-(\d+)_from(\d+)_\d+" + re.escape(MONITOR_SUFFIX))
#: What a truncated, corrupt or foreign model, normaliser or replay-buffer file raises on load.
UNREADABLE = (
    AssertionError,  # SB3's checks of a model saved by another algorithm
    zipfile.BadZipFile,
    pickle.UnpicklingError,
    EOFError,
    ValueError,
    KeyError,
    AttributeError,
    ImportError,
    RuntimeError,
    OSError,
)
EVALUATION_FIELDS = ("timesteps", "mean_return", "std_return", "mean_metric", "wall_seconds")
VERSIONED_PACKAGES = (
    "liuxing_envs",
    "gymnasium",
    "mujoco",
    "stable_baselines3",
    "torch",
    "numpy",
)


#: What a run's config.yml must hold; write_config writes git_commit last, so a file cut
#: short anywhere lacks it.
REQUIRED_CONFIG_KEYS = (
    "env_id", "algo", "seed", "n_timesteps", "normalize", "env_kwargs", "hyperparams",
    "git_commit",
)  # fmt: skip


class RunFolderError(NamesSettings, ValueError):
    """A run folder that cannot be used as asked (missing, incomplete, not a run)."""


class UnreadableFileError(RunFolderError):
    """A file of a run folder that is there but cannot be read (truncated, corrupt, foreign)."""

    def __init__(self, message: str, path: Path) -> None:
        super().__init__(message)
        self.path = Path(path)


def checkpoint_paths(run_dir: Path, steps: int) -> dict[str, Path]:
    folder = Path(run_dir) / CHECKPOINTS
    return {
        "model": folder / f"model_{steps}_steps.zip",
        "replay_buffer": folder / f"replay_buffer_{steps}_steps.pkl",
        "normalizer": folder / f"vecnormalize_{steps}_steps.pkl",
        "curriculum": folder / f"curriculum_{steps}_steps.json",
    }


def checkpoint_steps(run_dir: Path) -> list[int]:
    """Step counts of the run's checkpoints, ascending."""
    folder = Path(run_dir) / CHECKPOINTS
    if not folder.is_dir():
        return []
    found = (_CHECKPOINT.fullmatch(path.name) for path in folder.iterdir())
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


def git_diff(directory: Path | None = None) -> bytes:
    """The uncommitted changes to tracked files of the checkout holding this code, binary files
    included, as ``git apply`` takes them (``git diff HEAD --binary``: what a ``-dirty`` commit
    lacks), or b"" where there are none or no checkout."""
    directory = directory or Path(__file__).resolve().parent
    try:
        return subprocess.run(
            ["git", "diff", "HEAD", "--binary", "--no-ext-diff", "--no-textconv"],
            cwd=directory,
            capture_output=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return b""


class Source(NamedTuple):
    """The code at work: its commit (``-dirty`` with local changes) and those changes."""

    commit: str | None
    diff: bytes

    @classmethod
    def of_checkout(cls, checkout: Path | None = None) -> Source:
        commit = git_commit(checkout)
        dirty = commit is not None and commit.endswith("-dirty")
        return cls(commit, git_diff(checkout) if dirty else b"")

    def record(self, folder: Path, patch_name: str = GIT_DIFF) -> dict[str, str | None]:
        """The commit, for a config or report, and where a dirty checkout's changes went:
        written to ``folder/patch_name`` so the run can be rebuilt (``git checkout COMMIT &&
        git apply PATCH``), not just dated."""
        if not self.diff:
            return {"git_commit": self.commit}
        with atomic_path(Path(folder) / patch_name) as temporary:
            temporary.write_bytes(self.diff)
        return {"git_diff": patch_name, "git_commit": self.commit}


@contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to, renamed onto ``path`` (atomically) only
    when the block finishes: a crash mid-write leaves the old file or none, never half of
    one. The temporary name keeps the suffix (SB3 appends ``.zip`` to a model path without
    it) and is not a checkpoint name, so nothing loads it."""
    path = Path(path)
    temporary = path.with_name(f"{path.name}.partial{path.suffix}")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def partial_writes(run_dir: Path) -> list[Path]:
    """What writes through :func:`atomic_path` that a kill cut short left in the run folder."""
    run_dir = Path(run_dir)
    folders = (run_dir, run_dir / CHECKPOINTS, run_dir / MONITOR)
    return sorted(path for folder in folders for path in folder.glob("*.partial*"))


@contextmanager
def exclusive(run_dir: Path) -> Iterator[None]:
    """Holds ``run_dir`` (an existing folder) for this process while the block runs, or fails
    with a RunFolderError naming the process that holds it: two processes training in one
    folder (a job submitted twice, a requeued one) would write the same steps twice into its
    monitor files and overwrite each other's checkpoints. The lock is the kernel's (flock), so
    a killed process leaves none behind."""
    try:
        import fcntl
    except ImportError:  # not a POSIX system: no locking
        yield
        return
    path = Path(run_dir) / LOCK
    try:
        descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as error:
        raise RunFolderError(
            f"cannot write into the run folder {str(run_dir)!r}: {error}"
        ) from error
    try:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(descriptor, 32).decode(errors="replace").strip() or "unknown"
            raise RunFolderError(
                f"{str(run_dir)!r} is in use by another training process (pid {holder}); "
                "wait for it to finish, or stop it first"
            ) from None
        except OSError as error:  # a file system without flock (some network ones)
            print(
                f"warning: {str(run_dir)!r} cannot be locked ({error}); nothing stops a second "
                "process from training in it",
                file=sys.stderr,
            )
        else:
            os.ftruncate(descriptor, 0)
            os.write(descriptor, str(os.getpid()).encode())
        yield
    finally:
        os.close(descriptor)  # releases the lock


def save_atomically(save, path: Path) -> None:
    """``save(path)`` (e.g. ``model.save``, ``VecNormalize.save``) through :func:`atomic_path`."""
    with atomic_path(path) as temporary:
        save(temporary)


def write_text_atomically(path: Path, text: str) -> None:
    save_atomically(lambda temporary: temporary.write_text(text), path)


#: A hyper-parameter only this algorithm saves in an SB3 zip's ``data``. The policy class
#: does not tell: PPO's lives in ``stable_baselines3.common.policies``, as A2C's does.
ALGO_SIGNATURES = {"ppo": "clip_range", "sac": "target_entropy"}


def saved_algorithm(path: Path) -> str | None:
    """The algorithm (``ppo`` or ``sac``) that saved an SB3 model zip, read from its ``data``
    record; None for another algorithm. UnreadableFileError if it is no SB3 model zip."""
    try:
        with zipfile.ZipFile(path) as archive:
            data = json.loads(archive.read("data"))
        data["policy_class"]["__module__"]  # what every SB3 model's record names
    except (zipfile.BadZipFile, KeyError, ValueError, TypeError, OSError) as error:
        raise UnreadableFileError(
            f"{str(path)!r} is not a stable-baselines3 model zip ({error})", path
        ) from error
    return next((algo for algo, key in ALGO_SIGNATURES.items() if key in data), None)


def load_model(algo_class, path: Path, **kwargs):
    """``algo_class.load(path, **kwargs)``, failing with a RunFolderError that names the file
    and the problem when it is missing, truncated, corrupt or not a model of that kind."""
    path = Path(path)
    if not path.is_file():
        raise RunFolderError(f"model file {str(path)!r} does not exist")
    try:
        return algo_class.load(path, **kwargs)
    except UNREADABLE as error:
        raise UnreadableFileError(
            f"{str(path)!r} is not a readable {algo_class.__name__} model zip (truncated, "
            f"corrupt or foreign): {type(error).__name__}: {error}",
            path,
        ) from error


def load_normalizer(path: Path):
    """A saved VecNormalize, or a RunFolderError naming the file and the problem."""
    from stable_baselines3.common.vec_env import VecNormalize

    path = Path(path)
    try:
        normalizer = pickle.load(io.BytesIO(path.read_bytes()))
    except UNREADABLE as error:
        raise UnreadableFileError(
            f"{str(path)!r} is not a readable VecNormalize file (missing, truncated, corrupt "
            f"or foreign): {type(error).__name__}: {error}",
            path,
        ) from error
    if not isinstance(normalizer, VecNormalize):
        raise RunFolderError(
            f"{str(path)!r} holds a {type(normalizer).__name__}, not a VecNormalize"
        )
    return normalizer


def read_replay_buffer(path: Path):
    """The SB3 replay buffer pickled at ``path``, or a RunFolderError naming the file."""
    from stable_baselines3.common.buffers import ReplayBuffer
    from stable_baselines3.common.save_util import load_from_pkl

    try:
        buffer = load_from_pkl(Path(path))
    except UNREADABLE as error:
        raise UnreadableFileError(
            f"{str(path)!r} is not a readable replay buffer (truncated, corrupt or foreign): "
            f"{type(error).__name__}: {error}",
            path,
        ) from error
    if not isinstance(buffer, ReplayBuffer):
        raise RunFolderError(
            f"{str(path)!r} holds a {type(buffer).__name__}, not an SB3 replay buffer"
        )
    return buffer


def use_replay_buffer(model, buffer) -> None:
    """Give an off-policy ``model`` a buffer from :func:`read_replay_buffer`: what SB3's
    ``load_replay_buffer`` does for the buffers it writes (no HER here), split so that a
    buffer can be read, and refused, before a run folder is made."""
    model.replay_buffer = buffer
    buffer.device = model.device


def read_curriculum_state(path: Path) -> dict | None:
    """A checkpoint's start-curriculum state, None where the run saved none, or a
    RunFolderError naming the file when it is unreadable."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        state = json.loads(path.read_text())
        level, recent = float(state["level"]), [bool(s) for s in state["recent"]]
        history = [[int(steps), float(at)] for steps, at in state["history"]]
    except (ValueError, TypeError, KeyError, UnicodeDecodeError) as error:
        raise UnreadableFileError(
            f"{str(path)!r} is not a readable start-curriculum state (truncated or corrupt): "
            f"{type(error).__name__}: {error}",
            path,
        ) from error
    return {"level": level, "recent": recent, "history": history}


def write_config(run_dir: Path, config: dict, resuming: bool = False) -> None:
    """Writes ``config`` with this process's command line, library versions and commit (and
    its uncommitted changes, see Source.record). Resuming, it keeps the run's first command,
    versions and commit, and appends the resuming command to ``resume_commands`` and its
    versions and commit to ``resume_sources``."""
    command = " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])
    earlier = {key: value for key, value in config.items() if key != "git_commit"}
    if not resuming:
        source = Source.of_checkout().record(run_dir)
        document = {**earlier, "command": command, "versions": library_versions(), **source}
    else:
        resumes = [*config.get("resume_commands", []), command]
        patch_name = f"git_diff_resume{len(resumes)}.patch"
        resumed = {
            "command": command,
            "versions": library_versions(),
            **Source.of_checkout().record(run_dir, patch_name),
        }
        document = {
            **earlier,
            "resume_commands": resumes,
            "resume_sources": [*config.get("resume_sources", []), resumed],
            "git_commit": config.get("git_commit"),
        }
    write_text_atomically(Path(run_dir) / CONFIG, yaml.safe_dump(document, sort_keys=False))


def read_config(run_dir: Path) -> dict:
    run_dir = Path(run_dir)
    path = run_dir / CONFIG
    if run_dir.is_file():
        raise RunFolderError(f"run folder {str(run_dir)!r} is a file, not a run's folder")
    if not run_dir.is_dir():
        raise RunFolderError(f"run folder {str(run_dir)!r} does not exist")
    if not path.is_file():
        raise RunFolderError(f"{str(run_dir)!r} is not a run folder: it has no {CONFIG}")
    try:
        config = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise RunFolderError(f"{str(path)!r} is not valid YAML: {error}") from error
    if not isinstance(config, dict):
        raise RunFolderError(f"{str(path)!r} is not a run configuration (a YAML mapping)")
    missing = [key for key in REQUIRED_CONFIG_KEYS if key not in config]
    if missing:
        raise RunFolderError(
            f"{str(path)!r} lacks {', '.join(missing)}: truncated, or not written by train.py"
        )
    for key in ("env_kwargs", "eval_env_kwargs", "hyperparams"):
        if not isinstance(config.get(key) or {}, dict):
            raise RunFolderError(f"{str(path)!r}: {key} must be a mapping, got {config[key]!r}")
    return config


def read_evaluations(run_dir: Path) -> list[dict]:
    """The periodic-evaluation history, oldest first."""
    return [
        {key: float(row[key]) for key in EVALUATION_FIELDS} for row in _evaluation_rows(run_dir)
    ]


def _evaluation_rows(run_dir: Path) -> list[dict]:
    """The history's rows as written (strings), checked to be numbers in every column."""
    path = Path(run_dir) / EVALUATIONS
    if not path.is_file():
        return []
    try:
        with open(path, newline="") as handle:
            rows = list(csv.DictReader(handle))
        for row in rows:
            for key in EVALUATION_FIELDS:
                float(row[key])
    except (KeyError, TypeError, ValueError, UnicodeDecodeError) as error:
        raise RunFolderError(
            f"{str(path)!r} is not an evaluation history with columns "
            f"{', '.join(EVALUATION_FIELDS)}: {type(error).__name__}: {error}"
        ) from error
    return rows


def append_evaluation(run_dir: Path, row: dict) -> None:
    """Add a row to the history, rewriting the (small) file atomically; a damaged history
    is refused rather than extended."""
    _write_evaluations(run_dir, [*_evaluation_rows(run_dir), row])


def _write_evaluations(run_dir: Path, rows: list[dict]) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=EVALUATION_FIELDS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomically(Path(run_dir) / EVALUATIONS, buffer.getvalue())


class MonitorFile(NamedTuple):
    """An SB3 Monitor file: its two header lines, and per complete episode its end (seconds
    since the epoch), return, length and line as written."""

    header: list[str]
    episodes: list[tuple[float, float, int, str]]


def read_monitor(path: Path) -> MonitorFile | None:
    """The Monitor file at ``path``; None when it holds no episode to place in time (empty,
    not a Monitor file, or cut short by a crash before its header). A row a crash cut short
    is left out. ``t`` counts from the file's own start (its JSON header's ``t_start``)."""
    try:
        lines = Path(path).read_text().splitlines(keepends=True)
        start = float(json.loads(lines[0].lstrip("#"))["t_start"])
        columns = next(csv.reader([lines[1]]))
    except (OSError, UnicodeDecodeError, IndexError, ValueError, KeyError, TypeError):
        return None
    episodes = []
    for line in lines[2:]:
        try:
            row = dict(zip(columns, next(csv.reader([line])), strict=True))
            episodes.append((start + float(row["t"]), float(row["r"]), int(row["l"]), line))
        except (ValueError, KeyError, StopIteration):
            continue
    return MonitorFile(lines[:2], episodes)


def monitor_path(run_dir: Path, rank: int, n_envs: int, start_steps: int, stamp: int) -> Path:
    """The Monitor file of env ``rank`` of ``n_envs`` in a start (or resume) of training at
    ``start_steps``. The name carries what places its episodes in the run's steps (see
    :func:`episode_ends`); ``stamp`` (nanoseconds) keeps two starts apart."""
    name = f"env{rank}-of-{n_envs}_from{start_steps}_{stamp}{MONITOR_SUFFIX}"
    return Path(run_dir) / MONITOR / name


def monitor_files(run_dir: Path) -> list[Path]:
    return sorted((Path(run_dir) / MONITOR).glob(f"*{MONITOR_SUFFIX}"))


def episode_ends(path: Path, monitor: MonitorFile) -> list[int] | None:
    """The run's step count when each episode of the Monitor file at ``path`` ended; None for
    a file whose name does not say where its start of training began (an older run's).

    Every start of training resets its envs and steps them in lockstep, each step counting
    ``n_envs``: an env's k-th step since the start ends at ``start + n_envs * k``. Exact,
    whatever episodes an earlier stop cut off unlogged."""
    match = _MONITOR_NAME.fullmatch(Path(path).name)
    if match is None:
        return None
    n_envs, start = int(match[2]), int(match[3])
    lengths = (episode[2] for episode in monitor.episodes)
    return [start + n_envs * steps for steps in itertools.accumulate(lengths)]


class Forgetting(NamedTuple):
    """What :func:`forget_after_checkpoint` found to drop; :func:`forget` drops it."""

    evaluations: list[dict]  #: the history's rows to keep
    dropped_evaluations: int
    best_model_discarded: bool
    monitors: dict[Path, MonitorFile]  #: the files to rewrite, with the episodes they keep
    dropped_episodes: int
    partial_files: list[Path]  #: what writes a kill cut short left (see partial_writes)


def forget_after_checkpoint(run_dir: Path, steps: int, monitors: Iterable[Path]) -> Forgetting:
    """What a run recorded after its checkpoint at ``steps``, which a resume from it trains
    again (a run killed without saving, or a PPO run stopped half-way through a rollout):
    periodic evaluations past ``steps``, the best model if it came from those steps, and the
    training episodes of the ``monitors`` files that ended after ``steps``. Kept, they would
    be counted twice. Also the files of writes a kill cut short. Reads and checks all;
    nothing changes until :func:`forget`, so a resume refused in between leaves the folder
    as it was."""
    rows = _evaluation_rows(run_dir)
    kept = [row for row in rows if float(row["timesteps"]) <= steps]
    best = best_model_steps(run_dir)
    files = {path: found for path in monitors if (found := read_monitor(path)) is not None}
    dropped = set()
    unplaced = {}
    for path, file in files.items():
        ends = episode_ends(path, file)
        if ends is None:
            unplaced[path] = file
        else:
            dropped |= {(path, index) for index, end in enumerate(ends) if end > steps}
    dropped |= _after_steps_in_time_order(unplaced, steps)
    rewritten = {}
    for path, file in files.items():
        episodes = [e for index, e in enumerate(file.episodes) if (path, index) not in dropped]
        if len(episodes) < len(file.episodes):
            rewritten[path] = MonitorFile(file.header, episodes)
    return Forgetting(
        kept,
        len(rows) - len(kept),
        best is not None and best > steps,
        rewritten,
        len(dropped),
        partial_writes(run_dir),
    )


def _after_steps_in_time_order(files: dict[Path, MonitorFile], steps: int) -> set:
    """For Monitor files of older runs, which do not say where they start: the episodes
    beyond the first ``steps`` logged steps in time order (an episode a stop cut off was
    never logged, so this can keep one that ended after ``steps``)."""
    in_time_order = sorted(
        (episode[0], episode[2], path, index)
        for path, file in files.items()
        for index, episode in enumerate(file.episodes)
    )
    ends_at = itertools.accumulate(length for _, length, _, _ in in_time_order)
    return {
        (path, index)
        for (_, _, path, index), total in zip(in_time_order, ends_at, strict=True)
        if total > steps
    }


def forget(run_dir: Path, forgetting: Forgetting) -> None:
    """Drops what :func:`forget_after_checkpoint` found, and the exported policy, which the
    resumed run writes again when it ends."""
    (Path(run_dir) / POLICY).unlink(missing_ok=True)
    for path in forgetting.partial_files:
        path.unlink(missing_ok=True)
    if forgetting.dropped_evaluations:
        _write_evaluations(run_dir, forgetting.evaluations)
    if forgetting.best_model_discarded:
        for name in (BEST_MODEL, BEST_NORMALIZER):
            (Path(run_dir) / name).unlink(missing_ok=True)
    for path, file in forgetting.monitors.items():
        write_text_atomically(path, "".join([*file.header, *(e[3] for e in file.episodes)]))


def saved_attribute(model_path: Path, name: str):
    """The attribute ``name`` an SB3 model zip saved as JSON (None without it, or if the zip
    cannot be read)."""
    try:
        with zipfile.ZipFile(model_path) as archive:
            return json.loads(archive.read("data")).get(name)
    except (OSError, zipfile.BadZipFile, KeyError, ValueError, AttributeError):
        return None


def best_model_steps(run_dir: Path) -> int | None:
    """The step count the best model was saved at (None without one, or if unreadable)."""
    steps = saved_attribute(Path(run_dir) / BEST_MODEL, "num_timesteps")
    try:
        return int(steps) if steps is not None else None
    except (TypeError, ValueError):
        return None


def policy_files(run_dir: Path, best: bool = True) -> tuple[Path, Path | None]:
    """The model zip to score a run by, and where its normaliser would be (None for an
    exported policy, which takes raw observations): the best model when ``best`` and the run
    has one, else its final model, else (a shipped folder, when ``best``) its exported
    policy. The model may not exist."""
    run_dir = Path(run_dir)
    if best and (run_dir / BEST_MODEL).is_file():
        return run_dir / BEST_MODEL, run_dir / BEST_NORMALIZER
    if best and not (run_dir / FINAL_MODEL).is_file() and (run_dir / POLICY).is_file():
        return run_dir / POLICY, None
    return run_dir / FINAL_MODEL, run_dir / FINAL_NORMALIZER


#: The attribute an exported policy saves (True): it acts on the env's raw observations.
RAW_OBSERVATIONS = "liuxing_takes_raw_observations"


def takes_raw_observations(model_path: Path) -> bool:
    """Whether an SB3 model zip is an exported policy (``policy.zip``), which acts on the
    env's raw observations (any statistics it was trained behind are inside it) and so needs
    no normaliser file; False for a zip that cannot be read."""
    return saved_attribute(Path(model_path), RAW_OBSERVATIONS) is True


#: What a shipped policy keeps of its run: enough to load, evaluate and reproduce it.
SHIPPED_FILES = (CONFIG, POLICY, EVALUATIONS, LEARNING_CURVE, RESULT, GIT_DIFF)


def ship(run_dir: Path, destination: Path) -> Path:
    """Copy a finished run's exported policy and its record into ``destination``: a slim run
    folder (no checkpoints, replay buffers or logs) that ``load_policy``, evaluate.py and plain
    SB3 read as is."""
    import shutil

    run_dir, destination = Path(run_dir), Path(destination)
    read_config(run_dir)
    if not (run_dir / POLICY).is_file():
        raise RunFolderError(
            f"{str(run_dir)!r} has no {POLICY} to ship: it is written when training ends "
            f"(finish the run with: python train.py --resume {run_dir})"
        )
    destination.mkdir(parents=True, exist_ok=True)
    resume_patches = sorted(path.name for path in run_dir.glob("git_diff_resume*.patch"))
    for name in (*SHIPPED_FILES, *resume_patches):
        if (run_dir / name).is_file():
            shutil.copy2(run_dir / name, destination / name)
    return destination
