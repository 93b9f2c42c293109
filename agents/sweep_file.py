"""Sweep files: what ``python train.py --sweep FILE`` runs, read and checked before Ray starts.

A sweep file names a base configuration (``train.py``'s settings, by the keywords of
:func:`agents.training.resolve_config`), the seeds every configuration runs with, and either
a grid or a search space over settings named by dotted paths::

    name: ppo_learning_rates
    base:
      env_id: ViewPlanning-v1
      algo: ppo
      n_timesteps: 80000
      eval_freq: 10000
    seeds: [0, 1, 2]
    grid:
      hyperparams.learning_rate: [3.0e-4, 1.0e-4]
    # or, with Optuna choosing up to ``samples`` configurations:
    # search:
    #   samples: 8
    #   space:
    #     hyperparams.learning_rate: {log_uniform: [1.0e-5, 1.0e-3]}
    #     env_kwargs.motion_cost: {uniform: [0.0, 0.02]}
    #     hyperparams.n_epochs: {choice: [5, 10]}
    resources: {cpu: 1, gpu: 0}   # per trial (one configuration with one seed)
    max_failures: 3               # retries of a trial whose worker died

Every grid point, and every bound and choice of a search space, is resolved with
``train.py``'s own checks when the file is read, so a bad value or an env kwarg the env
refuses stops the sweep before any trial starts, with the message ``train.py`` gives.
This module imports no Ray.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agents.config import (
    ConfigError,
    deep_update,
    int_at_least,
    load_named_file,
    require_known,
)

SWEEP_KEYS = ("name", "base", "seeds", "grid", "search", "resources", "max_failures")
#: ``resolve_config``'s keywords a sweep's base may set (the seed comes from ``seeds``; a
#: trial's threads from its CPUs).
BASE_KEYS = (
    "env_id",
    "algo",
    "config_file",
    "hyperparams",
    "env_kwargs",
    "n_timesteps",
    "n_envs",
    "vec_env",
    "eval_freq",
    "eval_episodes",
    "save_freq",
    "final_episodes",
    "device",
    "tensorboard",
)
#: The search-space forms: each maps onto Ray Tune's sampler of the same meaning.
SPACE_FORMS = ("uniform", "log_uniform", "int", "choice")
SEARCH_KEYS = ("samples", "space", "seed")
RESOURCE_KEYS = ("cpu", "gpu")
DEFAULT_RESOURCES = {"cpu": 1.0, "gpu": 0.0}
DEFAULT_MAX_FAILURES = 3
DEFAULT_SWEEPS_DIR = Path("runs") / "sweeps"
#: The folder of a sweep's trials' run folders, under the sweep's folder.
RUNS = "runs"
#: The sweep file's copy in the sweep's folder: it marks the folder as a sweep's.
RECORD = "sweep.yml"


@dataclass(frozen=True)
class Sweep:
    """A checked sweep file (see the module)."""

    name: str
    base: dict
    seeds: tuple[int, ...]
    grid: dict | None
    search: dict | None
    resources: dict
    max_failures: int
    path: Path

    @property
    def threads(self) -> int:
        """Threads a trial may use (torch, numba, BLAS): its whole CPUs, at least one."""
        return max(1, math.floor(self.resources["cpu"]))

    def grid_points(self) -> list[dict]:
        """Every combination of the grid's values, in file order (the last path fastest)."""
        if self.grid is None:
            return []
        paths = list(self.grid)
        return [
            dict(zip(paths, values, strict=True))
            for values in itertools.product(*self.grid.values())
        ]

    def run_config(self, params: Mapping[str, Any], seed: int) -> dict:
        """The run configuration of one trial: the base with ``params`` set, resolved by
        ``train.py``'s checks (ConfigError naming what is wrong)."""
        from agents import training

        settings = self.base
        for path, value in params.items():
            settings = _set_path(settings, path, value)
        config = training.resolve_config(**settings, seed=seed, torch_threads=self.threads)
        # Trials run side by side: a trial's env worker processes share its CPUs.
        config["env_workers"] = min(config["env_workers"], self.threads)
        return config

    def folder(self, parent: Path = DEFAULT_SWEEPS_DIR) -> Path:
        """Where the sweep runs by default (the same command finds it again)."""
        return Path(parent) / self.name


def configuration_id(params: Mapping[str, Any]) -> str:
    """A short name for one configuration of a sweep, the same for the same settings."""
    text = json.dumps({key: params[key] for key in sorted(params)}, sort_keys=True)
    return "c" + hashlib.sha1(text.encode()).hexdigest()[:8]


def trial_name(params: Mapping[str, Any], seed: int) -> str:
    """The run folder name of one configuration with one seed."""
    return f"{configuration_id(params)}_seed{seed}"


def trial_record(run_dir: Path) -> Path:
    """Where a trial records its settings and the Ray worker running it: ``{"params",
    "seed", "pid", "node", "host"}`` (JSON)."""
    return run_dir.parent / f"{run_dir.name}.trial.json"


def trial_settings(run_dir: Path) -> dict:
    """The settings a trial's record names (empty where it has none)."""
    path = trial_record(run_dir)
    return json.loads(path.read_text())["params"] if path.is_file() else {}


def is_sweep_folder(path: str | Path) -> bool:
    return (Path(path) / RECORD).is_file() and (Path(path) / RUNS).is_dir()


def trial_run_folders(folder: str | Path) -> dict[str, list[Path]]:
    """A sweep folder's trial run folders by configuration id (those that hold a run)."""
    from agents import run_folder

    found: dict[str, list[Path]] = {}
    for run_dir in sorted((Path(folder) / RUNS).iterdir()):
        if run_dir.is_dir() and (run_dir / run_folder.CONFIG).is_file():
            configuration, _, _ = run_dir.name.rpartition("_seed")
            found.setdefault(configuration, []).append(run_dir)
    return found


def load_sweep(path: str | Path) -> Sweep:
    """The sweep in ``path``, checked (see the module); ConfigError names what is wrong."""
    path = Path(path)
    content, where = load_named_file(path, "sweep", SWEEP_KEYS, ("name", "base", "seeds"))
    name = content["name"]
    base = _checked_base(content["base"], where)
    seeds = _checked_seeds(content["seeds"], where)
    if ("grid" in content) == ("search" in content):
        raise ConfigError(f"{where} needs a grid or a search, one of them")
    grid = _checked_grid(content["grid"], where) if "grid" in content else None
    search = _checked_search(content["search"], where) if "search" in content else None
    sweep = Sweep(
        name=name,
        base=base,
        seeds=seeds,
        grid=grid,
        search=search,
        resources=_checked_resources(content.get("resources", {}), where),
        max_failures=int_at_least(
            f"{where}: max_failures", content.get("max_failures", DEFAULT_MAX_FAILURES), 0
        ),
        path=path,
    )
    _check_every_setting(sweep, where)
    return sweep


def _checked_base(base, where: str) -> dict:
    if not isinstance(base, Mapping):
        raise ConfigError(f"{where}: base must be a mapping of train.py's settings")
    for key in base:
        if key in ("seed", "torch_threads"):
            source = "seeds" if key == "seed" else "resources.cpu"
            raise ConfigError(f"{where}: base cannot set {key}: the sweep's {source} sets it")
        require_known(f"{where}: base key", key, BASE_KEYS)
    return dict(base)


def _checked_seeds(seeds, where: str) -> tuple[int, ...]:
    if not isinstance(seeds, list) or not seeds:
        raise ConfigError(f"{where}: seeds must be a non-empty list of integers, got {seeds!r}")
    checked = tuple(int_at_least(f"{where}: a seed", seed, 0) for seed in seeds)
    if len(set(checked)) != len(checked):
        raise ConfigError(f"{where}: seeds must differ, got {list(checked)}")
    return checked


def _checked_path(path, where: str) -> str:
    if not isinstance(path, str) or not all(part.isidentifier() for part in path.split(".")):
        raise ConfigError(
            f"{where}: {path!r} is not a setting's path (dotted names, as in "
            "hyperparams.learning_rate or env_kwargs.view_budget)"
        )
    require_known(f"{where}: the setting", path.split(".")[0], BASE_KEYS)
    return path


def _checked_grid(grid, where: str) -> dict:
    if not isinstance(grid, Mapping) or not grid:
        raise ConfigError(f"{where}: grid must map settings to lists of values")
    for path, values in grid.items():
        _checked_path(path, f"{where}: grid")
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{where}: grid {path} must be a non-empty list, got {values!r}")
    return {path: list(values) for path, values in grid.items()}


def _checked_search(search, where: str) -> dict:
    if not isinstance(search, Mapping):
        raise ConfigError(f"{where}: search must be a mapping with keys {', '.join(SEARCH_KEYS)}")
    for key in search:
        require_known(f"{where}: search key", key, SEARCH_KEYS)
    samples = int_at_least(f"{where}: search samples", search.get("samples"))
    space = search.get("space")
    if not isinstance(space, Mapping) or not space:
        raise ConfigError(f"{where}: search space must map settings to distributions")
    checked = {}
    for path, spec in space.items():
        label = f"{where}: search space {_checked_path(path, where)}"
        if not isinstance(spec, Mapping) or len(spec) != 1:
            raise ConfigError(f"{label} must be one of {{{': ..., '.join(SPACE_FORMS)}: ...}}")
        ((form, value),) = spec.items()
        require_known(f"{label}: distribution", form, SPACE_FORMS)
        checked[path] = {form: _checked_distribution(form, value, label)}
    seed = int_at_least(f"{where}: search seed", search.get("seed", 0), 0)
    return {"samples": samples, "space": checked, "seed": seed}


def _checked_distribution(form: str, value, label: str):
    if form == "choice":
        if not isinstance(value, list) or not value:
            raise ConfigError(f"{label}: choice must be a non-empty list, got {value!r}")
        return list(value)
    if not (isinstance(value, list) and len(value) == 2):
        raise ConfigError(f"{label}: {form} needs [low, high], got {value!r}")
    low, high = value
    kinds = (int,) if form == "int" else (int, float)
    if any(isinstance(v, bool) or not isinstance(v, kinds) for v in value) or not low < high:
        wanted = "integers" if form == "int" else "numbers"
        raise ConfigError(f"{label}: {form} needs [low, high], {wanted} with low < high")
    if form == "log_uniform" and low <= 0:
        raise ConfigError(f"{label}: log_uniform needs low > 0, got {low!r}")
    return [low, high]


def _checked_resources(resources, where: str) -> dict:
    if not isinstance(resources, Mapping):
        raise ConfigError(f"{where}: resources must be a mapping with keys cpu and gpu")
    for key in resources:
        require_known(f"{where}: resources key", key, RESOURCE_KEYS)
    checked = {**DEFAULT_RESOURCES}
    for key, value in resources.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
            raise ConfigError(f"{where}: resources {key} must be a number >= 0, got {value!r}")
        checked[key] = float(value)
    if checked["cpu"] <= 0:
        raise ConfigError(f"{where}: resources cpu must be above 0, got {checked['cpu']!r}")
    return checked


def extreme_points(space: Mapping[str, Mapping]) -> list[dict]:
    """One setting at a time at each bound or choice of a search space: what a sweep checks
    before Optuna draws between them."""
    points = []
    for path, spec in space.items():
        # Each spec is one form (choice, uniform, ...) whose list holds its choices or bounds.
        ((_form, values),) = spec.items()
        points += [{path: value} for value in values]
    return points


def _check_every_setting(sweep: Sweep, where: str) -> None:
    points = (
        sweep.grid_points() if sweep.grid is not None else extreme_points(sweep.search["space"])
    )
    for params in points:
        try:
            config = sweep.run_config(params, sweep.seeds[0])
        except ConfigError as error:
            shown = ", ".join(f"{path}={value!r}" for path, value in params.items())
            raise ConfigError(f"{where} with {shown}: {error}") from error
        if config["eval_freq"] == 0:
            raise ConfigError(
                f"{where}: a sweep scores its trials by their periodic evaluations; set "
                "base eval_freq above 0"
            )


def _set_path(settings: Mapping, path: str, value) -> dict:
    """``settings`` with the dotted ``path`` set to ``value`` (mappings made as needed)."""
    override: Any = value
    for part in reversed(path.split(".")):
        override = {part: override}
    return deep_update(settings, override)
