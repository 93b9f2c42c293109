"""What evaluate.py compares: trained policies (run folders or model files) and scripted
baselines, each resolved to an environment, its kwargs and a way to build the policy.

Every loading problem is found here, before any episode runs: a folder that is not a run, a
model file that is not an SB3 zip, a model whose spaces do not fit its environment, a run
trained with observation normalisation whose statistics are missing.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from agents import run_folder
from agents.config import NamesSettings, check_env_kwargs, closest, marked, require_known
from agents.evaluation import HELD_OUT_SPLIT, TASKS, SB3Policy, make_env, task_for
from agents.spaces import describe_space, same_space
from agents.sweep_file import is_sweep_folder, trial_run_folders, trial_settings
from agents.training import ALGO_CLASSES
from liuxing_envs.registration import family

#: Baselines by task family (every version and variant of a task runs them), as each
#: :class:`agents.evaluation.Task` declares them. A task's privileged reference (the greedy
#: oracle reads the ground truth) is reported as such, never as a competitor.
BASELINES: dict[str, Mapping[str, Callable]] = {
    name: task.baselines for name, task in TASKS.items()
}
PRIVILEGED_BASELINES = frozenset(task.reference for task in TASKS.values() if task.reference)


class ContestantError(NamesSettings, ValueError):
    """An input evaluate.py cannot use; the message names it and what is wrong."""


@dataclass
class Contestant:
    """One policy or baseline to evaluate on one environment."""

    label: str  #: unique name in the report
    group: str  #: contestants sharing a group are training seeds of one method
    kind: str  #: "policy", "baseline" or "privileged"
    env_id: str
    env_kwargs: dict
    source: str  #: the path or baseline name given
    make_policy: Callable = field(repr=False)  #: env -> policy with SB3's ``predict``
    seed: int | None = None  #: training seed of a policy
    config: dict | None = field(default=None, repr=False)
    model_file: str | None = None  #: the policy's .zip that is scored (best, final, a checkpoint)


def check_env_id(env_id: str) -> str:
    import liuxing_envs

    return require_known("environment", env_id, liuxing_envs.ENV_IDS)


def check_algo(algo: str) -> str:
    return require_known("algorithm", algo, list(ALGO_CLASSES))


# ---------------------------------------------------------------------- baselines
def baseline_names(env_id: str) -> list[str]:
    return list(task_for(env_id).baselines)


def reference_baselines(env_id: str) -> list[str]:
    """The baselines a report on ``env_id`` shows by default: the one a learner must beat and
    the task's privileged reference, if any."""
    task = task_for(env_id)
    return [task.baseline] + ([task.reference] if task.reference else [])


def baseline_contestant(name: str, env_id: str, env_kwargs: Mapping) -> Contestant:
    """``env_kwargs``: the scene the policies run in; the baseline adds what it reads (the
    scripted grasp needs the RGB-D camera and the end-effector controller)."""
    allowed = baseline_names(env_id)
    if name not in allowed:
        raise ContestantError(
            f"unknown baseline {name!r} for {env_id}{closest(name, allowed)}; "
            f"allowed: {', '.join(allowed)}"
        )
    make_policy = task_for(env_id).baselines[name]
    return Contestant(
        label=name,
        group=name,
        kind="privileged" if name in PRIVILEGED_BASELINES else "baseline",
        env_id=env_id,
        env_kwargs={**env_kwargs, **getattr(make_policy, "ENV_KWARGS", {})},
        source=name,
        make_policy=make_policy,
    )


# ---------------------------------------------------------------------- trained policies
def policy_contestant(
    path: str | Path,
    *,
    env_id: str | None = None,
    algo: str | None = None,
    best: bool = True,
    raw_observations: bool = False,
) -> Contestant:
    """A run folder (its best model, else its final one) or a model zip. A zip inside a run
    folder (or its ``checkpoints/``) takes the run's config and normaliser; a lone zip needs
    ``env_id``, its algorithm is read from the zip unless ``algo`` is given, and it needs its
    normaliser beside it (named as in a run folder) unless it is a run's exported ``policy.zip``
    (which takes raw observations) or ``raw_observations``."""
    path = Path(path)
    if not path.exists():
        raise ContestantError(f"{str(path)!r} does not exist (give a run folder or a model .zip)")
    if path.is_dir():
        config = _read_run_config(path)
        model_path, normalizer_path = run_folder.policy_files(path, best)
        if not model_path.is_file() and (path / run_folder.POLICY).is_file():
            raise ContestantError(
                f"{str(path)!r} keeps only its exported {run_folder.POLICY} (its best policy), "
                "no final model"
            )
        if not model_path.is_file():
            raise ContestantError(
                f"run folder {str(path)!r} has no {model_path.name}: has it finished?"
            )
        if normalizer_path is None:
            _algo_in_zip(model_path)  # a damaged one is named as such, not as unnormalised
    else:
        run_dir = _run_folder_of(path)
        config = _read_run_config(run_dir) if run_dir is not None else None
        model_path, normalizer_path = path, _normalizer_beside(path)
    if config is not None:
        if algo is not None and algo != config["algo"]:
            raise ContestantError(
                f"{str(path)!r} is a {config['algo']} run's, not {algo}: drop «algo» (it is "
                "for lone model files)"
            )
        env_id, algo = config["env_id"], config["algo"]
        env_kwargs = dict(config.get("env_kwargs") or {})
        normalize = bool(config.get("normalize")) and not run_folder.takes_raw_observations(
            model_path
        )
        seed = config.get("seed")
    else:
        if env_id is None:
            raise ContestantError(
                f"{str(path)!r} is not in a run folder, so its environment is unknown: "
                "pass «env_id»"
            )
        saved_by = _algo_in_zip(model_path)
        if algo is not None and algo != saved_by:
            raise ContestantError(
                f"{str(model_path)!r} was saved by {saved_by}, not {algo}: drop «algo» or "
                f"pass «algo» {saved_by}"
            )
        algo = saved_by
        # Without a run's config, the statistics saved beside the file (as a run folder
        # names them) say it was trained with normalisation; a zip copied without them would
        # act on raw observations, which the spaces check cannot catch.
        exported = run_folder.takes_raw_observations(model_path)
        normalize = normalizer_path.is_file() and not exported
        if not normalize and not exported and not raw_observations:
            raise ContestantError(
                f"{str(model_path)!r} is not in a run folder, is no exported policy.zip and "
                f"has no {normalizer_path.name} "
                "beside it, so whether it was trained on normalised observations is unknown: "
                "evaluate its run folder, put its normaliser beside it under that name, or "
                "pass «raw_observations» if it was trained without one"
            )
        env_kwargs, seed = {}, None
    if normalize and (normalizer_path is None or not normalizer_path.is_file()):
        raise ContestantError(
            f"{str(model_path)!r} was trained with observation normalisation, but its "
            f"statistics ({normalizer_path.name if normalizer_path else 'vecnormalize.pkl'}) "
            "are missing: evaluating it on raw observations would be meaningless"
        )
    policy = _load(algo, model_path, normalizer_path if normalize else None)
    # Resolved: "." (run from inside the run folder) has no name, and "model.zip" no parent's.
    named = path.resolve()
    label = named.name if named.is_dir() else f"{named.parent.name}/{named.stem}"
    return Contestant(
        label=label,
        group=algo,
        kind="policy",
        env_id=env_id,
        env_kwargs=env_kwargs,
        source=str(path),
        make_policy=lambda env: policy,
        seed=seed,
        config=config,
        model_file=str(model_path),  # as the source was given: a relative path stays so
    )


def check_fits(contestant: Contestant, env) -> None:
    """The policy's observation and action spaces are the environment's."""
    if contestant.kind != "policy":
        return
    model = contestant.make_policy(env).model
    for what, expected, actual in (
        ("observation", env.observation_space, model.observation_space),
        ("action", env.action_space, model.action_space),
    ):
        if not same_space(expected, actual):
            raise ContestantError(
                f"{contestant.source!r} does not fit {contestant.env_id} with env kwargs "
                f"{contestant.env_kwargs or '{}'}: its {what} space is {describe_space(actual)}, "
                f"the environment's is {describe_space(expected)}"
            )


def slug(label: str) -> str:
    """``label`` as a file or folder name."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in label)


def unique_labels(contestants: Sequence[Contestant]) -> None:
    """Suffix repeated labels (two runs with the same folder name) with their position."""
    seen: dict[str, int] = {}
    for contestant in contestants:
        seen[contestant.label] = seen.get(contestant.label, 0) + 1
    counts: dict[str, int] = {}
    for contestant in contestants:
        if seen[contestant.label] > 1:
            counts[contestant.label] = counts.get(contestant.label, 0) + 1
            contestant.label = f"{contestant.label} ({counts[contestant.label]})"


# ---------------------------------------------------------------------- helpers
def _read_run_config(run_dir: Path) -> dict:
    try:
        config = run_folder.read_config(run_dir)
    except run_folder.RunFolderError as error:
        raise ContestantError(marked(error)) from error
    if config["algo"] not in ALGO_CLASSES:
        raise ContestantError(
            f"{str(run_dir)!r}: unknown algo {config['algo']!r}; allowed: {', '.join(ALGO_CLASSES)}"
        )
    try:
        task_for(config["env_id"])
    except ValueError as error:
        raise ContestantError(f"{str(run_dir)!r}: {error}") from error
    return config


def _run_folder_of(model_path: Path) -> Path | None:
    for folder in (model_path.parent, model_path.parent.parent):
        if (folder / run_folder.CONFIG).is_file():
            return folder
    return None


def _normalizer_beside(model_path: Path) -> Path:
    """Where a run folder keeps the statistics saved with a model file: ``best_model.zip``
    -> ``best_vecnormalize.pkl``, a checkpoint ``model_<N>_steps.zip`` ->
    ``vecnormalize_<N>_steps.pkl``, any other (``model.zip``) -> ``vecnormalize.pkl``."""
    name = model_path.name
    if name == run_folder.BEST_MODEL:
        return model_path.parent / run_folder.BEST_NORMALIZER
    if name.startswith("model_") and name.endswith("_steps.zip"):
        return model_path.parent / name.replace("model_", "vecnormalize_").replace(".zip", ".pkl")
    return model_path.parent / run_folder.FINAL_NORMALIZER


def _algo_in_zip(model_path: Path) -> str:
    """The algorithm that saved an SB3 model zip."""
    try:
        algo = run_folder.saved_algorithm(model_path)
    except run_folder.RunFolderError as error:
        raise ContestantError(marked(error)) from error
    if algo is None:
        raise ContestantError(
            f"{str(model_path)!r} holds a policy of an algorithm evaluate.py does not know; "
            f"it knows {', '.join(ALGO_CLASSES)}"
        )
    return algo


def _load(algo: str, model_path: Path, normalizer_path: Path | None) -> SB3Policy:
    try:
        return SB3Policy.load(ALGO_CLASSES[algo], model_path, normalizer_path)
    except run_folder.RunFolderError as error:
        raise ContestantError(marked(error)) from error


def make_checked_env(contestant: Contestant, **make_kwargs):
    """The contestant's environment (a ConfigError for kwargs it refuses), after checking its
    policy fits it."""
    env = make_env(contestant.env_id, contestant.env_kwargs, **make_kwargs)
    try:
        check_fits(contestant, env)
    except ContestantError:
        env.close()
        raise
    return env


# ---------------------------------------------------------------------- assembling


def sweep_contestants(folder: str, *, best: bool, raw_observations: bool) -> list[Contestant]:
    """Each trial of the sweep in ``folder`` that has a model to score, grouped by its
    configuration (its seeds are aggregated; the others are told apart)."""
    contestants = []
    for configuration, run_dirs in trial_run_folders(folder).items():
        for run_dir in run_dirs:
            models = (run_folder.BEST_MODEL, run_folder.FINAL_MODEL)
            if not any((run_dir / name).is_file() for name in models):
                print(f"{run_dir.name}: no model yet; left out", flush=True)
                continue
            contestant = policy_contestant(
                str(run_dir), best=best, raw_observations=raw_observations
            )
            settings = ", ".join(f"{k}={v}" for k, v in trial_settings(run_dir).items())
            group = f"{contestant.group} {configuration}" + (f" ({settings})" if settings else "")
            contestants.append(dataclasses.replace(contestant, group=group))
    if not contestants:
        raise ContestantError(f"the sweep in {folder!r} has no trained model to evaluate yet")
    return contestants


def build_contestants(
    sources: Sequence[str],
    *,
    env_id: str | None = None,
    algo: str | None = None,
    baselines: Sequence[str] | None = None,
    env_kwargs: Mapping | None = None,
    splits: Mapping[str, str] | None = None,
    best: bool = True,
    raw_observations: bool = False,
) -> list[Contestant]:
    """Contestants for the given sources (run folders, model zips, baseline names), plus
    ``baselines`` (default: each environment's reference baselines; ``[]``: none).

    Each policy runs in its run's env kwargs, less the scene it was trained on (its split or
    explicit list of objects or instruments), updated with ``env_kwargs``; the baselines of
    an environment run in its first policy's (so the same view budget, say), plus what they
    read. Every contestant is put on ``splits[task family]`` (default ``held_out``) unless
    ``env_kwargs`` names objects or instruments explicitly; a split for an environment that
    no contestant runs in is refused, as is a list of contestants left empty."""
    env_kwargs = dict(env_kwargs or {})
    splits = dict(splits or {})
    contestants: list[Contestant] = []
    named_baselines: list[str] = []
    seen: set[str] = set()
    for source in sources:
        looks_like_path = Path(source).suffix == ".zip" or "/" in source or Path(source).exists()
        key = str(Path(source).resolve()) if looks_like_path else source
        if key in seen:  # it would run twice, on the same episodes, under two labels
            raise ContestantError(f"{source!r} is given more than once")
        seen.add(key)
        if not looks_like_path:
            named_baselines.append(source)
            continue
        if is_sweep_folder(source):
            contestants += sweep_contestants(source, best=best, raw_observations=raw_observations)
            continue
        contestants.append(
            policy_contestant(
                source, env_id=env_id, algo=algo, best=best, raw_observations=raw_observations
            )
        )
    twice = sorted(set(named_baselines) & set(baselines or ()))
    if twice:  # it would run once, silently, where the command line asks for it twice
        raise ContestantError(
            f"{', '.join(twice)} is given both as a contestant and in «baselines»; give it once"
        )
    env_ids = list(dict.fromkeys(c.env_id for c in contestants))
    uses_env = named_baselines or any(c.config is None for c in contestants)  # lone zips
    if env_id is not None and env_ids and env_id not in env_ids and not uses_env:
        # It would only add env_id's baselines to the report: surely a mistaken --env.
        raise ContestantError(
            f"«env_id» {env_id} is not the environment of the runs given "
            f"({', '.join(env_ids)}): «env_id» is for lone model files and baseline names, a "
            "run folder knows its own; drop «env_id»"
        )
    if env_id is not None and env_id not in env_ids:
        env_ids.append(env_id)
    if not env_ids:
        if named_baselines:  # a run folder's name mistyped, or a baseline's without --env
            raise ContestantError(
                f"{', '.join(map(repr, named_baselines))}: no such run folder or model file, "
                "and baseline names need «env_id» ("
                + "; ".join(f"{task}: {', '.join(names)}" for task, names in BASELINES.items())
                + ")"
            )
        raise ContestantError(
            "nothing to evaluate on: give a run folder or model file, or «env_id» with baselines"
        )
    if named_baselines and len(env_ids) > 1:
        raise ContestantError(
            f"baseline names ({', '.join(named_baselines)}) are ambiguous with policies of "
            f"{', '.join(env_ids)}: evaluate one environment at a time, or use «baselines»"
        )
    if "render_mode" in env_kwargs:
        raise ContestantError(
            "render_mode is the report's to set (rgb_array for «video»): leave it out of "
            "«env_kwargs»"
        )
    for current in env_ids:
        task = task_for(current)
        split = task.split_kwarg
        if split in env_kwargs:
            raise ContestantError(
                f"the {split.replace('_', ' ')} is chosen with «{split}», "
                f"not «env_kwargs» {split}=..."
            )
        if task.explicit_scene_kwarg in env_kwargs and family(current) in splits:
            raise ContestantError(
                f"«{split}» and «env_kwargs» {task.explicit_scene_kwarg}=... both "
                f"choose {current}'s episodes; give one of them"
            )
    for contestant in contestants:
        task = task_for(contestant.env_id)
        # What it was trained on is not what it is scored on (the split decides, below).
        for key in (task.split_kwarg, task.explicit_scene_kwarg):
            contestant.env_kwargs.pop(key, None)
        contestant.env_kwargs.update(env_kwargs)
    first_policies: dict[str, Contestant] = {}
    for contestant in contestants:
        first_policies.setdefault(contestant.env_id, contestant)
    for current in env_ids:
        check_env_kwargs(current, env_kwargs)
        allowed = baseline_names(current)
        for name in named_baselines:
            if name not in allowed:
                raise ContestantError(
                    f"{name!r} is neither a run folder or model file (none of that name "
                    f"exists) nor a baseline of {current}{closest(name, allowed)}; its "
                    f"baselines: {', '.join(allowed)}"
                )
        first_policy = first_policies.get(current)
        scene = dict(first_policy.env_kwargs) if first_policy else dict(env_kwargs)
        wanted = list(named_baselines)
        if baselines is None and not named_baselines:
            wanted = reference_baselines(current)
        elif baselines:
            wanted += [b for b in baselines if b not in wanted]
        for name in wanted:
            contestants.append(baseline_contestant(name, current, scene))
    if not contestants:
        raise ContestantError(
            f"nothing to evaluate on {', '.join(env_ids)}: «baselines» none leaves no "
            "contestant; give a run folder, a model file or baseline names"
        )
    for split_family in splits:
        if split_family not in {family(current) for current in env_ids}:
            flag = f"«{TASKS[split_family].split_kwarg}»"
            raise ContestantError(
                f"{flag} chooses {split_family} episodes, but nothing here runs a "
                f"{split_family} task (evaluating {', '.join(env_ids)}); drop {flag}"
            )
    for contestant in contestants:
        task = task_for(contestant.env_id)
        if task.explicit_scene_kwarg not in contestant.env_kwargs:
            contestant.env_kwargs[task.split_kwarg] = splits.get(
                family(contestant.env_id), HELD_OUT_SPLIT
            )
    if raw_observations and not any(_scored_raw(c) for c in contestants):
        # It would be ignored: it names no source, so it cannot be what the user meant.
        raise ContestantError(
            "«raw_observations» is for a lone model file trained without normalisation, and "
            "no source given is one (a run folder's config.yml, or a normaliser beside a zip, "
            "says how its policy was trained): drop «raw_observations»"
        )
    unique_labels(contestants)
    return contestants


def _scored_raw(contestant: Contestant) -> bool:
    """A lone model zip with no normaliser beside it: the one --raw-observations is for."""
    if contestant.kind != "policy" or contestant.config is not None:
        return False
    return not _normalizer_beside(Path(contestant.model_file)).is_file()
