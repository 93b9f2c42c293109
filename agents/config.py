"""Training configuration: hyper-parameter files, ``key=value`` overrides and their checks.

One YAML file per algorithm under ``agents/hyperparams/``, keyed by environment id (the
rl-baselines3-zoo layout). Each entry holds the algorithm's constructor arguments plus the
harness keys in :data:`HARNESS_KEYS`. Values given on the command line as ``key=value`` are
parsed as YAML scalars/flow collections (``yaml.safe_load``), never evaluated as Python.
"""

from __future__ import annotations

import argparse
import copy
import inspect
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import yaml

from liuxing_envs.validation import closest

HYPERPARAMS_DIR = Path(__file__).resolve().parent / "hyperparams"
ALGOS = ("ppo", "sac")

#: Keys of a hyper-parameter entry that configure the harness, not the SB3 algorithm.
HARNESS_KEYS = {
    "n_timesteps": "total environment steps of a run",
    "n_envs": "parallel training environments",
    "env_workers": "processes stepping a batched vector env's scenes, this one included "
    "(train.py's --env-workers; a sweep trial's CPUs at most)",
    "policy": "SB3 policy class name (MultiInputPolicy for the Dict observations)",
    "env_kwargs": "keyword arguments of gym.make for training and evaluation",
    "eval_env_kwargs": "env_kwargs the periodic evaluation changes, e.g. {object_set: validation}"
    " to choose the best model on shapes it never trained on",
    "normalize": "wrap in VecNormalize (observations only; vector keys only)",
    "demonstrations": "expert episodes put in SAC's replay buffer first (agents/demonstrations.py)",
    "start_curriculum": "training episodes that start near the handle (agents/curriculum.py)",
}


class _Loader(yaml.SafeLoader):
    """YAML 1.1 reads ``1e-4`` (no dot) as a string; hyper-parameters are written that way."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+][0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def script_parser(prog: str, doc: str) -> argparse.ArgumentParser:
    """The parser of a command-line script: the docstring's first paragraph describes it, the
    rest (examples, notes) follows the flags in ``--help`` as written."""
    paragraphs = doc.split("\n\n")
    return argparse.ArgumentParser(
        prog=prog,
        description=paragraphs[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(paragraphs[1:]),
    )


def show_package_progress() -> None:
    """Let the package's INFO messages through to stderr (a slow first preparation of an
    object set, say) in a command-line script; library users choose their own logging."""
    import logging

    logging.basicConfig(format="%(message)s", level=logging.WARNING)
    logging.getLogger("liuxing_envs").setLevel(logging.INFO)


def safe_load(text: str):
    """``yaml.safe_load`` that also reads ``1e-4`` as a float; never constructs objects."""
    return yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)


_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


#: How a message marks a setting it is about: «name», the keyword of the library call.
_SETTING = re.compile(r"«([a-z][a-z0-9_]*)»")


class NamesSettings:
    """An error whose message marks the settings it is about as «name» (the keyword of the
    library call or the key of a config file): ``str()`` shows those names, and
    :meth:`for_command_line` the flags a script takes them as, so that only the scripts
    speak of flags."""

    def __str__(self) -> str:
        return _SETTING.sub(r"\1", super().__str__())

    @property
    def marked(self) -> str:
        """The message with its settings still marked, for a message that wraps it."""
        return super().__str__()

    def for_command_line(self, renamed: Mapping[str, str] | None = None) -> str:
        """The message with each setting named by its flag: ``renamed``'s, else
        ``--name-with-dashes``."""
        renamed = renamed or {}
        return _SETTING.sub(
            lambda match: renamed.get(match[1], "--" + match[1].replace("_", "-")), self.marked
        )


def marked(error: Exception) -> str:
    """An error's message for another message to wrap: its settings still marked where it
    marks them (:class:`NamesSettings`)."""
    return error.marked if isinstance(error, NamesSettings) else str(error)


class ConfigError(NamesSettings, ValueError):
    """A configuration value the harness cannot use; the message says what is allowed."""


MAX_SEED = 2**32 - 1  # numpy's generators take seeds up to here


def int_at_least(name: str, value, minimum: int = 1, maximum: int | None = None) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, np.integer))
        or value < minimum
        or (maximum is not None and value > maximum)
    ):
        wanted = f">= {minimum}" if maximum is None else f"in [{minimum}, {maximum}]"
        raise ConfigError(f"{name} must be an integer {wanted}, got {value!r}")
    return int(value)


def number_in(name: str, value, low: float, high: float) -> float:
    """``value`` as a float, or ConfigError unless it is a number in [low, high]."""
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float, np.integer, np.floating))
        or not low <= value <= high
    ):
        raise ConfigError(f"{name} must be a number in [{low}, {high}], got {value!r}")
    return float(value)


def require_known(kind: str, name: str, allowed: Sequence[str]) -> str:
    if name not in allowed:
        raise ConfigError(
            f"unknown {kind} {name!r}{closest(name, allowed)}; allowed: {', '.join(allowed)}"
        )
    return name


def check_env_kwargs(env_id: str, env_kwargs: Mapping) -> None:
    """Unknown keyword names fail here, with a suggestion, and values the env's settings
    refuse, with the env's message, before any env is made."""
    import gymnasium as gym
    from gymnasium.envs.registration import load_env_creator

    import liuxing_envs  # noqa: F401  (registers the ids)
    from liuxing_envs.registration import settings_of

    accepted = load_env_creator(gym.spec(env_id).entry_point).keyword_names()
    for name in env_kwargs:
        if name not in accepted:
            raise ConfigError(
                f"unknown env kwarg {name!r} for {env_id}{closest(name, accepted)}; "
                f"allowed: {', '.join(accepted)}"
            )
    settable = {name: value for name, value in env_kwargs.items() if name != "render_mode"}
    try:
        settings_of(env_id, **settable)
    except (TypeError, ValueError) as error:
        raise ConfigError(f"{env_id} with env kwargs {dict(env_kwargs)}: {error}") from error


def parse_assignments(items: Sequence[str] | None, flag: str) -> dict:
    """``["a=1", "b.c=[64, 64]"]`` -> ``{"a": 1, "b": {"c": [64, 64]}}``.

    Values are YAML (``1e-3``, ``true``, ``[64, 64]``, ``{a: 1}``, ``null``); dotted keys
    build nested mappings so ``policy_kwargs.net_arch=[64,64]`` overrides one entry.
    """
    result: dict = {}
    given: list[tuple[str, ...]] = []
    for item in items or ():
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"{flag} expects key=value items, got {item!r}")
        try:
            value = safe_load(text) if text.strip() else None
        except yaml.YAMLError as error:
            raise ConfigError(f"{flag} {key}: cannot parse {text!r} as a YAML value") from error
        parts = key.split(".")
        if not all(_NAME.fullmatch(part) for part in parts):
            raise ConfigError(f"{flag} expects key=value items with names as keys, got {item!r}")
        path = tuple(parts)
        for earlier in given:
            # The same key twice, or a mapping and one of its entries: which one wins would
            # depend on the order, so neither does.
            if earlier[: len(path)] == path or path[: len(earlier)] == earlier:
                twice = "given twice" if earlier == path else f"given with {'.'.join(earlier)}"
                raise ConfigError(f"{flag} {key}: {twice}; give each setting once")
        given.append(path)
        target = result
        for part in parts[:-1]:
            target = target.setdefault(part, {})
        target[parts[-1]] = value
    return result


#: Algorithm kwargs that default to None (off) and otherwise take a number.
OPTIONAL_NUMBERS = ("target_kl", "clip_range_vf")
#: Bounds of the algorithm numbers whose meaning has them: SB3 takes ``gamma=2`` and trains.
HYPERPARAM_RANGES = {
    "gamma": (0.0, 1.0),
    "gae_lambda": (0.0, 1.0),
    "tau": (0.0, 1.0),
    "learning_rate": (0.0, np.inf),
    "clip_range": (0.0, np.inf),
    "clip_range_vf": (0.0, np.inf),
    "ent_coef": (0.0, np.inf),
    "vf_coef": (0.0, np.inf),
    "max_grad_norm": (0.0, np.inf),
    "target_kl": (0.0, np.inf),
    # Counts: SB3 takes 0 and fails later (target_update_interval=0 divides by zero).
    "n_steps": (1, np.inf),
    "batch_size": (1, np.inf),
    "n_epochs": (1, np.inf),
    "buffer_size": (1, np.inf),
    "learning_starts": (0, np.inf),
    "train_freq": (1, np.inf),
    "gradient_steps": (-1, np.inf),  # -1: as many as env steps
    "target_update_interval": (1, np.inf),
    "stats_window_size": (1, np.inf),
    "sde_sample_freq": (-1, np.inf),  # -1: once per rollout
}
#: SAC's hyper-parameters that take "auto" (``ent_coef`` also ``auto_<initial value>``) or a
#: number.
AUTO_OR_NUMBER = ("ent_coef", "target_entropy")
#: Algorithm kwargs that train.py sets from its own flags.
SET_BY_FLAGS = {"seed": "«seed»", "device": "«device»", "tensorboard_log": "«tensorboard»"}


#: Hyper-parameters SB3 also takes as a schedule of the training progress; here written as
#: rl-baselines3-zoo does, ``lin_<start>``: ``start`` decaying linearly to 0 over the run.
SCHEDULED = ("learning_rate", "clip_range")
LINEAR_PREFIX = "lin_"


def linear_schedule_start(key: str, value: str, algo_name: str = "the algorithm's") -> float:
    """The start of ``lin_<start>``, or a ConfigError naming the accepted forms."""
    start = np.nan
    if value.startswith(LINEAR_PREFIX):
        try:
            start = float(value[len(LINEAR_PREFIX) :])
        except ValueError:
            pass
    if not (np.isfinite(start) and start > 0):
        raise ConfigError(
            f"{algo_name} hyper-parameter {key} must be a number >= 0 or "
            f"{LINEAR_PREFIX}<number > 0> (a linear decay to 0 over the run, e.g. "
            f"{LINEAR_PREFIX}3.0e-4; a number in quotes is text), got {value!r}"
        )
    return start


def check_hyperparam_value(algo_name: str, key: str, value, default) -> None:
    """A value of the kind the algorithm's own default has, so ``gamma=abc`` fails here with
    its name instead of as a tensor error minutes into training. Only scalars are checked:
    a list is one of SB3's tuple forms, of which ``train_freq: [n, step|episode]`` is checked
    too. A None default leaves the kind open, except for the numbers that default to off
    (``target_kl``). The keys in :data:`SCHEDULED` also take ``lin_<start>``."""
    if key == "train_freq" and isinstance(value, (list, tuple)):
        check_train_freq_pair(algo_name, value)
        return
    if key.endswith("_class") and value is not None:
        raise ConfigError(
            f"{algo_name} hyper-parameter {key} takes a Python class, which a hyper-parameter "
            f"file cannot name; leave it out (SB3's default), got {value!r}"
        )
    if isinstance(value, (list, tuple, dict)) or (value is None and default is None):
        return
    if key in SCHEDULED and isinstance(value, str):
        linear_schedule_start(key, value, algo_name)
        return
    if key in AUTO_OR_NUMBER and isinstance(default, str):
        if isinstance(value, str):
            _check_auto(algo_name, key, value)
            return
        default = 0.0  # a number, checked as one below
    if default is None:
        if key not in OPTIONAL_NUMBERS:
            return
        default = 0.0
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(
                f"{algo_name} hyper-parameter {key} must be true or false, got {value!r}"
            )
        return
    if isinstance(default, (int, float)):
        kind = "an integer" if isinstance(default, int) else "a number"
        wanted = (
            (int, np.integer) if isinstance(default, int) else (int, float, np.integer, np.floating)
        )
        if isinstance(value, bool) or not isinstance(value, wanted) or not np.isfinite(value):
            raise ConfigError(f"{algo_name} hyper-parameter {key} must be {kind}, got {value!r}")
        low, high = HYPERPARAM_RANGES.get(key, (-np.inf, np.inf))
        if not low <= value <= high:
            raise ConfigError(
                f"{algo_name} hyper-parameter {key} must be in [{low}, {high}], got {value!r}"
            )


def _check_auto(algo_name: str, key: str, value: str) -> None:
    """``auto``, or for ``ent_coef`` also ``auto_<initial value > 0>``, or a ConfigError."""
    initial = np.nan
    if key == "ent_coef" and value.startswith("auto_"):
        try:
            initial = float(value[len("auto_") :])
        except ValueError:
            pass
    if value == "auto" or (np.isfinite(initial) and initial > 0):
        return
    forms = "'auto', 'auto_<initial value > 0>' or a number >= 0"
    if key != "ent_coef":
        forms = "'auto' or a number"
    raise ConfigError(f"{algo_name} hyper-parameter {key} must be {forms}, got {value!r}")


#: The units of SB3's ``train_freq: [n, unit]``.
TRAIN_FREQ_UNITS = ("step", "episode")


def check_train_freq_pair(algo_name: str, value) -> None:
    """``train_freq`` in SB3's pair form: an integer >= 1 and a unit. SB3 drops a third item
    silently and fails only when training starts on a count of 0."""
    form = (
        f"an integer >= 1 or a pair [n, unit], n an integer >= 1 and unit one of {TRAIN_FREQ_UNITS}"
    )
    message = f"{algo_name} hyper-parameter train_freq must be {form}, got {value!r}"
    if len(value) != 2:
        raise ConfigError(message)
    count, unit = value
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ConfigError(message)
    if unit not in TRAIN_FREQ_UNITS:
        raise ConfigError(f"{message}{closest(str(unit), TRAIN_FREQ_UNITS)}")


#: The critic's key in a ``net_arch`` mapping, per algorithm (the actor's is ``pi``).
NET_ARCH_CRITIC = {"ppo": "vf", "sac": "qf"}


def check_net_arch(algo: str, net_arch) -> None:
    """``policy_kwargs.net_arch``: a list of hidden-layer widths (positive integers) for actor
    and critic alike, or a mapping of exactly ``pi`` and the critic's key to such lists. SB3
    gives a network missing from the mapping no hidden layer, silently, and a zero-width
    layer makes a constant network."""
    critic = NET_ARCH_CRITIC[algo]
    forms = (
        f"a list of layer widths ([256, 256]) or a mapping of exactly pi and {critic} to such "
        f"lists ({{pi: [64], {critic}: [256]}})"
    )

    def widths(value) -> bool:
        return isinstance(value, list | tuple) and all(
            isinstance(width, int) and not isinstance(width, bool) and width >= 1 for width in value
        )

    if isinstance(net_arch, Mapping):
        ok = set(net_arch) == {"pi", critic} and all(map(widths, net_arch.values()))
    else:
        ok = widths(net_arch)
    if not ok:
        raise ConfigError(
            f"{algo.upper()} policy_kwargs.net_arch must be {forms}, got {net_arch!r}"
        )


def deep_update(base: Mapping, overrides: Mapping) -> dict:
    """A copy of ``base`` with ``overrides`` merged in, mapping by mapping."""
    merged = copy.deepcopy(dict(base))
    for key, value in overrides.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = deep_update(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def load_named_file(
    path: Path, kind: str, keys: Sequence[str], required: Sequence[str]
) -> tuple[dict, str]:
    """The top-level mapping of the YAML file ``path`` (a ``kind`` of file: recipe, sweep)
    with only ``keys`` and all of ``required``, and how messages name the file; its
    ``name`` must be a word."""
    content = load_yaml(path)
    where = f"{kind} {str(path)!r}"
    if not isinstance(content, Mapping):
        raise ConfigError(f"{where} must be a mapping with keys {', '.join(keys)}")
    for key in content:
        require_known(f"{where}: key", key, keys)
    missing = [key for key in required if key not in content]
    if missing:
        raise ConfigError(f"{where} has no {', '.join(missing)}")
    name = content.get("name")
    if name is not None and (not isinstance(name, str) or not name.isidentifier()):
        raise ConfigError(f"{where}: name must be a word (letters, digits, _), got {name!r}")
    return dict(content), where


def keep_beside(source: Path, record: Path, holder: str) -> None:
    """Copy the YAML file ``source`` to ``record`` (in the folder of what it made), or, where
    ``record`` is there already, refuse a folder that holds ``holder`` (another recipe's or
    sweep's: its file differs)."""
    from agents.run_folder import write_text_atomically

    folder = record.parent
    folder.mkdir(parents=True, exist_ok=True)
    if record.is_file():
        if load_yaml(record) != load_yaml(source):
            raise ConfigError(
                f"{str(folder)!r} holds {holder} ({record.name} there differs from "
                f"{str(source)!r}): give another folder"
            )
        return
    write_text_atomically(record, source.read_text())


def load_yaml(path: str | Path) -> dict:
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"config file {str(path)!r} is a folder; give a YAML file")
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    try:
        content = safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise ConfigError(f"config file {str(path)!r} is not valid YAML: {error}") from error
    if content is None:
        raise ConfigError(
            f"config file {str(path)!r} is empty; it must map env ids to hyper-parameters, "
            "as agents/hyperparams/<algo>.yml does"
        )
    if not isinstance(content, dict):
        raise ConfigError(f"config file {str(path)!r} must hold a mapping, got {type(content)}")
    odd = [key for key in content if not isinstance(key, str)]
    if odd:
        raise ConfigError(f"config file {str(path)!r} has keys that are not names: {odd}")
    return content


def default_hyperparams(algo: str, env_id: str, config_file: str | Path | None = None) -> dict:
    """The entry for ``env_id`` in ``config_file`` (default: ``agents/hyperparams/<algo>.yml``),
    or else for its task's benchmark id (``InstrumentGraspRGBD-v1`` -> ``InstrumentGrasp-v1``).
    A deprecated id (``InstrumentGrasp-v0``) needs an entry of its own.

    A custom file may hold a single entry without an env-id key; it is then used as is.
    """
    require_known("algorithm", algo, ALGOS)
    path = Path(config_file) if config_file else HYPERPARAMS_DIR / f"{algo}.yml"
    content = load_yaml(path)
    from liuxing_envs.registration import BY_ID, benchmark_id, family

    # A variant trains with its benchmark id's entry unless the file has one of its own. A
    # deprecated version does not: the benchmark id's entry is tuned for that id's defaults,
    # which are not the old version's.
    registration = BY_ID.get(env_id)
    fallback = (
        benchmark_id(family(env_id)) if registration and not registration.deprecated else None
    )
    if env_id in content:
        entry = content[env_id]
    elif fallback in content:
        entry = content[fallback]
    elif registration and registration.deprecated and benchmark_id(family(env_id)) in content:
        raise ConfigError(
            f"{env_id!r} is deprecated and {str(path)!r} has no entry for it: train "
            f"{benchmark_id(family(env_id))!r}, or give a config file with an entry for {env_id!r}"
        )
    elif config_file and not any(key in BY_ID for key in content):
        entry = content
    else:
        raise ConfigError(
            f"{str(path)!r} has no entry for {env_id!r}{closest(env_id, map(str, content))}; "
            f"it has: {', '.join(map(str, content)) or 'none'}"
        )
    if not isinstance(entry, dict):
        raise ConfigError(f"the entry for {env_id!r} in {str(path)!r} must be a mapping")
    return copy.deepcopy(entry)


def split_hyperparams(hyperparams: Mapping, algo_class: type) -> tuple[dict, dict]:
    """(harness settings, algorithm kwargs); unknown names raise with a suggestion, and so
    do values of the wrong kind (see :func:`check_hyperparam_value`)."""
    parameters = inspect.signature(algo_class.__init__).parameters
    accepted = [
        name
        for name in parameters
        if name not in ("self", "policy", "env", "_init_setup_model", "verbose", *SET_BY_FLAGS)
    ]
    allowed = sorted(set(accepted) | set(HARNESS_KEYS))
    harness, algo_kwargs = {}, {}
    for key, value in hyperparams.items():
        if key in HARNESS_KEYS:
            harness[key] = value
        elif key in SET_BY_FLAGS:
            raise ConfigError(
                f"{key} is not a hyper-parameter here: set it with {SET_BY_FLAGS[key]}"
            )
        elif key in accepted:
            check_hyperparam_value(algo_class.__name__, key, value, parameters[key].default)
            algo_kwargs[key] = value
        else:
            raise ConfigError(
                f"unknown hyper-parameter {key!r} for {algo_class.__name__}{closest(key, allowed)}"
                f"; allowed: {', '.join(allowed)}"
            )
    return harness, algo_kwargs
