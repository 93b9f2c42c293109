"""Recipes: one file that trains a policy from scratch with every setting pinned.

A recipe (``recipes/*.yml``) names its documented seed and one or more stages, trained in
order by one command, each an ordinary run folder under the recipe's folder::

    name: instrument_grasp_sac
    seed: 2                          # the documented seed (--seed trains another)
    stages:
      - name: scratch
        env_id: InstrumentGrasp-v1
        algo: sac
        n_timesteps: 500000
        hyperparams: {...}           # the whole entry: agents/hyperparams/ is not read
        env_kwargs: {...}            # every setting of the env's task
        ...                          # and every other setting of a run's config.yml
      - name: fine_tune
        init_from: scratch           # an earlier stage's run
        init_replay_buffer: true
        ...

Every env setting that applies to the task and every constructor argument of the algorithm
is written out, so a later change of a default changes no recipe (:func:`unpinned` says
what a stage leaves to defaults; ``python -m agents.recipes pin RUN_DIR`` writes a pinned
one-stage recipe from any run folder). ``python train.py --recipe FILE`` runs it; the same
command again goes on where it stopped: finished stages are kept, a stopped one resumes.
"""

from __future__ import annotations

import argparse
import inspect
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import yaml

from agents import run_folder
from agents.config import (
    SET_BY_FLAGS,
    ConfigError,
    keep_beside,
    load_named_file,
    require_known,
    split_hyperparams,
)

#: What a stage gives, besides its name: the settings of a run's config.yml.
STAGE_KEYS = (
    "env_id",
    "algo",
    "n_timesteps",
    "n_envs",
    "vec_env",
    "hyperparams",
    "env_kwargs",
    "eval_freq",
    "eval_episodes",
    "save_freq",
    "final_episodes",
    "init_from",
    "init_replay_buffer",
)
#: What a stage may leave out: whether (and how) it starts from an earlier stage.
OPTIONAL_STAGE_KEYS = ("init_from", "init_replay_buffer")
#: Constructor arguments the harness sets itself (from the run's own settings).
SET_BY_THE_HARNESS = ("policy", "env", "verbose", *SET_BY_FLAGS)
RECIPE_KEYS = ("name", "seed", "stages")
DEFAULT_RECIPES_DIR = Path("runs") / "recipes"


@dataclass(frozen=True)
class Recipe:
    name: str
    seed: int
    stages: tuple[dict, ...]
    path: Path

    def folder(self, seed: int, parent: Path = DEFAULT_RECIPES_DIR) -> Path:
        """Where a seed of the recipe trains (the same command finds it again)."""
        return Path(parent) / f"{self.name}_seed{seed}"

    def stage_dir(self, folder: Path, index: int) -> Path:
        return Path(folder) / f"{index + 1}_{self.stages[index]['name']}"


def load_recipe(path: str | Path) -> Recipe:
    """The recipe in ``path``, checked: known keys, every stage complete and pinned, each
    ``init_from`` an earlier stage. Raises ConfigError naming what is wrong."""
    path = Path(path)
    content, where = load_named_file(path, "recipe", RECIPE_KEYS, RECIPE_KEYS)
    stages = content["stages"]
    if not isinstance(stages, list) or not stages:
        raise ConfigError(f"{where}: stages must be a non-empty list of mappings")
    names: list[str] = []
    for index, stage in enumerate(stages):
        label = f"{where}, stage {index + 1}"
        if not isinstance(stage, Mapping):
            raise ConfigError(f"{label} must be a mapping")
        for key in stage:
            require_known(f"{label}: key", key, ("name", *STAGE_KEYS))
        absent = [
            k for k in ("name", *STAGE_KEYS) if k not in stage and k not in OPTIONAL_STAGE_KEYS
        ]
        if absent:
            raise ConfigError(f"{label} has no {', '.join(absent)}")
        if stage["name"] in names or not str(stage["name"]).isidentifier():
            raise ConfigError(f"{label}: name {stage['name']!r} must be a new word")
        source = stage.get("init_from")
        if source is not None and source not in names:
            raise ConfigError(
                f"{label}: init_from {source!r} is not an earlier stage; earlier: "
                f"{', '.join(names) or 'none'}"
            )
        names.append(stage["name"])
        label = f"{label} ({stage['name']})"
        try:
            resolve_stage(stage, content["seed"], init_from=None)  # values checked up front
        except ConfigError as error:
            raise ConfigError(f"{label}: {error}") from error
        left = unpinned(stage)
        if left:
            raise ConfigError(
                f"{label} leaves {', '.join(left)} to their defaults, which may change: pin "
                "them (python -m agents.recipes pin RUN_DIR writes every setting of a run)"
            )
    return Recipe(content["name"], int(content["seed"]), tuple(map(dict, stages)), path)


def resolve_stage(stage: Mapping, seed: int, init_from: Path | None) -> dict:
    """The run config of ``stage`` (train.py's checks), starting from ``init_from``."""
    from agents import training

    return training.resolve_config(
        env_id=stage["env_id"],
        algo=stage["algo"],
        hyperparams_entry=stage["hyperparams"],
        env_kwargs=stage["env_kwargs"],
        seed=seed,
        n_timesteps=stage["n_timesteps"],
        n_envs=stage["n_envs"],
        vec_env=stage["vec_env"],
        eval_freq=stage["eval_freq"],
        eval_episodes=stage["eval_episodes"],
        save_freq=stage["save_freq"],
        final_episodes=stage["final_episodes"],
        init_from=str(init_from) if init_from is not None else None,
        init_replay_buffer=bool(stage.get("init_replay_buffer")) and init_from is not None,
    )


def unpinned(stage: Mapping) -> list[str]:
    """What ``stage`` leaves to a default: env settings of its task and constructor
    arguments of its algorithm it does not write out."""
    from agents.training import ALGO_CLASSES

    task = pinned_env_kwargs(stage["env_id"], stage["env_kwargs"])
    left = [f"env_kwargs.{name}" for name in task if name not in stage["env_kwargs"]]
    _, algo_kwargs = split_hyperparams(stage["hyperparams"], ALGO_CLASSES[stage["algo"]])
    arguments = inspect.signature(ALGO_CLASSES[stage["algo"]]).parameters
    left += [
        f"hyperparams.{name}"
        for name in arguments
        if name not in algo_kwargs and name not in SET_BY_THE_HARNESS and not name.startswith("_")
    ]
    return left


def pinned_env_kwargs(env_id: str, env_kwargs: Mapping) -> dict:
    """Every setting that applies to the task ``env_kwargs`` makes of ``env_id``, by name."""
    from liuxing_envs.registration import settings_of

    try:
        settings = settings_of(env_id, **env_kwargs).applicable()
    except (TypeError, ValueError) as error:
        raise ConfigError(f"{env_id} with env kwargs {dict(env_kwargs)}: {error}") from error
    return {name: _plain(value) for name, value in settings.items()}


def pin(run_dir: Path, name: str) -> dict:
    """A one-stage recipe that trains ``run_dir``'s configuration again (see
    :func:`pinned_stage`)."""
    config = run_folder.read_config(run_dir)
    return {"name": name, "seed": config["seed"], "stages": [pinned_stage(config)]}


def pinned_stage(config: Mapping, name: str | None = None) -> dict:
    """A run config (``resolve_config``'s, or a run folder's) as a recipe stage with every
    setting written out: its env's settings and its algorithm's constructor arguments,
    defaults included. It starts from no earlier stage."""
    from agents.training import ALGO_CLASSES

    algo_class = ALGO_CLASSES[config["algo"]]
    hyperparams = {
        key: config[key]
        for key in ("policy", "normalize", "demonstrations", "start_curriculum", "eval_env_kwargs")
    }
    defaults = {
        key: _plain(parameter.default)
        for key, parameter in inspect.signature(algo_class).parameters.items()
        if key not in SET_BY_THE_HARNESS
        and not key.startswith("_")
        and parameter.default is not inspect.Parameter.empty
    }
    hyperparams.update({**defaults, **config["hyperparams"]})
    stage = {"name": name or config["algo"]}
    stage.update({key: config[key] for key in STAGE_KEYS if key not in OPTIONAL_STAGE_KEYS})
    stage.update(
        hyperparams=hyperparams,
        env_kwargs=pinned_env_kwargs(config["env_id"], config["env_kwargs"]),
    )
    return stage


def _plain(value):
    """A setting as YAML writes and reads it back: tuples as lists."""
    if isinstance(value, tuple | list):
        return [_plain(item) for item in value]
    return value


def run_recipe(
    recipe: Recipe, seed: int | None = None, folder: Path | None = None, progress_bar=False
) -> Path:
    """Trains the recipe's stages in order under ``folder`` (default: its seed's folder under
    runs/recipes/); a stage already finished there is kept, one stopped is resumed (each
    checked to be the recipe's stage with this seed). Returns the last stage's run folder,
    whose ``policy.zip`` is the recipe's policy."""
    from agents import training

    seed = recipe.seed if seed is None else seed
    folder = Path(folder) if folder is not None else recipe.folder(seed)
    _record_recipe(recipe, folder)
    run_dirs: dict[str, Path] = {}
    for index, stage in enumerate(recipe.stages):
        run_dir = recipe.stage_dir(folder, index)
        source = stage.get("init_from")
        init_from = run_dirs[source] if source else None
        run_dirs[stage["name"]] = run_dir
        heading = f"stage {index + 1} of {len(recipe.stages)} ({stage['name']}): {run_dir}"
        if (run_dir / run_folder.CONFIG).is_file():
            _check_same_stage(run_dir, stage, seed, init_from)
            left = training.work_left(run_dir)
            if not left:
                print(f"{heading} finished before; kept", flush=True)
                continue
            print(f"{heading} resumed ({', '.join(left)} left)", flush=True)
            training.resume(run_dir, progress_bar=progress_bar)
            continue
        print(heading, flush=True)
        config = resolve_stage(stage, seed, init_from)
        training.train(config, run_dir, progress_bar=progress_bar)
    return run_dirs[recipe.stages[-1]["name"]]


RECORD = "recipe.yml"


def _record_recipe(recipe: Recipe, folder: Path) -> None:
    """Keep the recipe beside its runs; a folder started from another recipe is refused."""
    keep_beside(recipe.path, folder / RECORD, "the runs of another recipe")


def _check_same_stage(run_dir: Path, stage: Mapping, seed: int, init_from: Path | None) -> None:
    """Refuse a stage's existing run folder trained with other settings or another seed."""
    from agents import training

    config = run_folder.read_config(run_dir)
    saved = training.run_definition(config)
    expected = training.run_definition(resolve_stage(stage, seed, init_from))
    differ = [key for key in expected if key != "init_from" and saved[key] != expected[key]]
    differ += ["n_timesteps"] if config["n_timesteps"] != stage["n_timesteps"] else []
    if differ:
        raise ConfigError(
            f"{str(run_dir)!r} was trained with another {', '.join(differ)} than stage "
            f"{stage['name']!r} of the recipe with seed {seed}: give another folder"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m agents.recipes",
        description="Write a recipe that pins every setting of a run folder's configuration.",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    pin_parser = commands.add_parser("pin", help="a one-stage recipe from a run folder")
    pin_parser.add_argument("run_dir", type=Path)
    pin_parser.add_argument("--name", default="recipe", help="the recipe's name (a word)")
    args = parser.parse_args(argv)
    try:
        recipe = pin(args.run_dir, args.name)
    except (ConfigError, run_folder.RunFolderError) as error:
        parser.error(str(error))
    yaml.safe_dump(recipe, sys.stdout, sort_keys=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
