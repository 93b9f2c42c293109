"""Training runs: build envs and an SB3 model from a resolved configuration, learn with
periodic evaluation and checkpoints, resume, and finish with a comparison to the baseline.

``train.py`` only parses flags into :func:`resolve_config` and calls :func:`train` or
:func:`resume`. Everything a run needs to be reproduced or resumed is in its folder
(:mod:`agents.run_folder`).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import inspect
import json
import math
import shutil
import sys
import time
from abc import abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.utils import LinearSchedule
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

import liuxing_envs
from agents import interrupts, run_folder, workers
from agents.batched_vec_env import BatchedVecEnv
from agents.config import (
    ALGOS,
    MAX_SEED,
    SCHEDULED,
    ConfigError,
    check_env_kwargs,
    check_net_arch,
    closest,
    deep_update,
    default_hyperparams,
    int_at_least,
    linear_schedule_start,
    marked,
    require_known,
    split_hyperparams,
)
from agents.curriculum import (
    STARTED_NEAR,
    StartNearGrasp,
    check_start_curriculum,
    level_callback,
    start_settings,
)
from agents.demonstrations import check_demonstrations, demonstration_sizes, seed_replay_buffer
from agents.evaluation import (
    SB3Policy,
    compare_with_baseline,
    format_comparison,
    make_env,
    run_episodes,
    task_for,
)
from agents.plotting import plot_learning_curve
from agents.spaces import describe_space, mismatched_spaces
from agents.workers import WORKER_GONE, WorkerDied
from liuxing_envs.output_folders import OutputFolderError, prepare_output_folder
from liuxing_envs.policy_parts import (
    ACTIVATIONS,
    FEATURES_EXTRACTORS,
    OPTIMIZERS,
    with_embedded_normalizer,
)
from liuxing_envs.validation import is_number

ALGO_CLASSES = {"ppo": PPO, "sac": SAC}
#: How a run's envs are stepped: SB3's vector envs over single envs, or (``batched``) the
#: task's own vector env (``gym.make_vec``'s vector entry point) through BatchedVecEnv.
VEC_ENVS = {"dummy": DummyVecEnv, "subproc": SubprocVecEnv, "batched": BatchedVecEnv}
DEFAULT_ENV_ID = "ViewPlanning-v1"
DEFAULT_ALGO = "ppo"
DEFAULT_SEED = 0
DEFAULT_VEC_ENV = "dummy"
DEFAULT_DEVICE = "auto"
DEFAULT_POLICY = "MultiInputPolicy"
#: Every observation preset of both envs is a Dict, which only SB3's MultiInputPolicy takes.
POLICIES = (DEFAULT_POLICY,)
#: ``policy_kwargs`` names that stand for an SB3 argument (see policy_kwargs()).
POLICY_KWARG_ALIASES = ("features_extractor",)
#: The torch device types training is tested on (--device; "auto" picks one of them).
SUPPORTED_DEVICE_TYPES = ("cpu", "cuda")
DEFAULT_EVAL_FREQ = 5_000  # env steps between periodic evaluations
DEFAULT_EVAL_EPISODES = 20
DEFAULT_SAVE_FREQ = 10_000  # env steps between checkpoints
DEFAULT_FINAL_EPISODES = 50
#: A run not told how many episodes to evaluate on gets one per this many training steps (at
#: least MIN_AUTO_EPISODES, at most the defaults above), so a quick run's evaluations are as
#: quick as its training.
STEPS_PER_AUTO_EPISODE = 1_000
MIN_AUTO_EPISODES = 5
DEFAULT_RUNS_DIR = Path("runs")
#: One torch thread: on a small machine the envs need the other cores, and PPO's minibatch
#: updates ran 7x slower with 2 threads competing with 4 envs on 2 cores (0.73 s vs 5.1 s).
DEFAULT_TORCH_THREADS = 1
#: Processes that step a batched vector env's scenes when neither the hyper-parameter file
#: nor ``--env-workers`` says: this one alone.
DEFAULT_ENV_WORKERS = 1
KEEP_CHECKPOINTS = 3
#: Periodic evaluation replays the same seeds each time (so its curve compares like with
#: like), offset from the training seeds.
PERIODIC_EVAL_SEED_OFFSET = 10_000
#: What a resumed run takes for a setting its config.yml lacks (written before the setting
#: existed, or edited by hand): what a new run takes when not told otherwise.
SAVED_CONFIG_DEFAULTS = {
    "n_envs": 1,
    "vec_env": DEFAULT_VEC_ENV,
    "policy": DEFAULT_POLICY,
    "demonstrations": None,
    "start_curriculum": None,
    "eval_env_kwargs": {},
    "eval_freq": DEFAULT_EVAL_FREQ,
    "eval_episodes": DEFAULT_EVAL_EPISODES,
    "save_freq": DEFAULT_SAVE_FREQ,
    "final_episodes": DEFAULT_FINAL_EPISODES,
    "device": DEFAULT_DEVICE,
    "tensorboard": False,
    "torch_threads": DEFAULT_TORCH_THREADS,
    "env_workers": DEFAULT_ENV_WORKERS,
    "init_from": None,
}


# --- configuration ---------------------------------------------------------------------------


def resolve_config(
    *,
    env_id: str = DEFAULT_ENV_ID,
    algo: str = DEFAULT_ALGO,
    config_file: str | None = None,
    hyperparams_entry: Mapping | None = None,
    hyperparams: Mapping | None = None,
    env_kwargs: Mapping | None = None,
    seed: int = DEFAULT_SEED,
    n_timesteps: int | None = None,
    n_envs: int | None = None,
    vec_env: str | None = None,
    eval_freq: int = DEFAULT_EVAL_FREQ,
    eval_episodes: int | None = None,
    save_freq: int = DEFAULT_SAVE_FREQ,
    final_episodes: int | None = None,
    device: str = DEFAULT_DEVICE,
    tensorboard: bool = False,
    torch_threads: int = DEFAULT_TORCH_THREADS,
    env_workers: int | None = None,
    init_from: str | None = None,
    init_replay_buffer: bool = False,
) -> dict:
    """Everything a run needs, checked: the hyper-parameter file's entry for ``env_id`` (or
    ``hyperparams_entry``, a recipe's whole entry, instead of any file's) with
    ``hyperparams`` and ``env_kwargs`` merged over it and the explicit arguments on top.
    ``init_from`` names a trained run whose policy the new run starts from, and with
    ``init_replay_buffer`` its newest checkpoint's replay buffer too. ``eval_episodes`` and
    ``final_episodes`` left None scale with the run (:func:`auto_episodes`). ``env_workers``
    left None is the entry's, else :data:`DEFAULT_ENV_WORKERS`."""
    require_known("environment", env_id, liuxing_envs.ENV_IDS)
    require_known("algorithm", algo, ALGOS)
    vec_env = default_vec_env(env_id) if vec_env is None else vec_env
    require_known("«vec_env»", vec_env, tuple(VEC_ENVS))
    _refuse_env_kwargs_given_twice(hyperparams or {}, env_kwargs or {})
    _refuse_counts_given_twice(hyperparams or {}, n_timesteps=n_timesteps, n_envs=n_envs)
    if hyperparams_entry is not None and config_file is not None:
        raise ConfigError("give a hyper-parameter file or a recipe's entry, not both")
    entry = (
        dict(hyperparams_entry)
        if hyperparams_entry is not None
        else default_hyperparams(algo, env_id, config_file)
    )
    merged = deep_update(entry, hyperparams or {})
    harness, algo_kwargs = split_hyperparams(merged, ALGO_CLASSES[algo])
    for key in ("env_kwargs", "eval_env_kwargs"):
        if not isinstance(harness.get(key) or {}, Mapping):
            raise ConfigError(f"{key} must be a mapping of env kwargs, got {harness[key]!r}")
    merged_env_kwargs = deep_update(harness.get("env_kwargs") or {}, env_kwargs or {})
    check_env_kwargs(env_id, merged_env_kwargs)
    eval_env_kwargs = harness.get("eval_env_kwargs") or {}
    check_env_kwargs(env_id, eval_env_kwargs)
    normalize = harness.get("normalize", False)
    if not isinstance(normalize, bool):
        raise ConfigError(f"normalize must be true or false, got {normalize!r}")
    n_timesteps = int_at_least(
        "«n_timesteps»", n_timesteps if n_timesteps is not None else harness.get("n_timesteps")
    )
    if eval_episodes is None:
        eval_episodes = auto_episodes(n_timesteps, DEFAULT_EVAL_EPISODES)
    if final_episodes is None:
        final_episodes = auto_episodes(n_timesteps, DEFAULT_FINAL_EPISODES)
    config = {
        "env_id": env_id,
        "algo": algo,
        "seed": int_at_least("«seed»", seed, minimum=0, maximum=MAX_SEED),
        "n_timesteps": n_timesteps,
        "n_envs": int_at_least(
            "«n_envs»", n_envs if n_envs is not None else harness.get("n_envs", 1)
        ),
        "vec_env": vec_env,
        "policy": require_known("policy", harness.get("policy", DEFAULT_POLICY), POLICIES),
        "normalize": normalize,
        "demonstrations": check_demonstrations(env_id, algo, harness.get("demonstrations")),
        "start_curriculum": check_start_curriculum(env_id, harness.get("start_curriculum")),
        "env_kwargs": merged_env_kwargs,
        "eval_env_kwargs": dict(eval_env_kwargs),
        "hyperparams": algo_kwargs,
        "eval_freq": int_at_least("«eval_freq»", eval_freq, minimum=0),
        "eval_episodes": int_at_least("«eval_episodes»", eval_episodes),
        "save_freq": int_at_least("«save_freq»", save_freq, minimum=0),
        "final_episodes": int_at_least("«final_episodes»", final_episodes, minimum=0),
        "device": check_device(device),
        "tensorboard": bool(tensorboard),
        "torch_threads": int_at_least("«torch_threads»", torch_threads),
    }
    if env_workers is None and harness.get("env_workers") is not None:
        # The file's choice for its own settings: a run given fewer envs or another kind of
        # vector env gets what fits those.
        from_file = int_at_least("«env_workers»", harness["env_workers"])
        env_workers = min(from_file, config["n_envs"]) if config["vec_env"] == "batched" else 1
    config["env_workers"] = check_env_workers(config, env_workers)
    if init_replay_buffer and not init_from:
        raise ConfigError("«init_replay_buffer» needs «init_from» (a run folder) to take it from")
    config["init_from"] = (
        check_init_from(init_from, env_id, algo, config["normalize"], init_replay_buffer)
        if init_from
        else None
    )
    named = config["hyperparams"].get("policy_kwargs")
    policy_kwargs(named)  # fails early on bad names
    check_policy_kwarg_names(algo, config["policy"], named or {})
    if named and "net_arch" in named:
        check_net_arch(algo, named["net_arch"])
    _check_batched(config)
    return config


def _episodes(count: int, of: str) -> str:
    return f"{count} {of} episode{'' if count == 1 else 's'}"


def auto_episodes(n_timesteps: int, most: int) -> int:
    """Episodes for an evaluation of a run of ``n_timesteps`` steps that was not given its
    size: one per STEPS_PER_AUTO_EPISODE steps, between MIN_AUTO_EPISODES and ``most``."""
    return max(MIN_AUTO_EPISODES, min(most, n_timesteps // STEPS_PER_AUTO_EPISODE))


def check_init_from(
    source: str, env_id: str, algo: str, normalize: bool, replay_buffer: bool = False
) -> dict:
    """The trained run a new run starts from (rl-baselines3-zoo's ``--trained-agent``): its
    best model (else its final one) and normaliser, for the same env, algorithm and
    normalisation, and with ``replay_buffer`` the replay buffer of its newest checkpoint.
    Recorded in the new run's config with the model's SHA-256."""
    run_dir = Path(source)
    try:
        trained = run_folder.read_config(run_dir)
    except run_folder.RunFolderError as error:
        raise ConfigError(f"«init_from»: {marked(error)}") from error
    if (trained["env_id"], trained["algo"]) != (env_id, algo):
        raise ConfigError(
            f"«init_from» {source!r} is a {trained['algo']} run on {trained['env_id']}; "
            f"this run is {algo} on {env_id}"
        )
    if bool(trained.get("normalize")) != normalize:
        raise ConfigError(
            f"«init_from» {source!r} has normalize: {bool(trained.get('normalize'))} and this "
            f"run normalize: {normalize}; its weights expect the other inputs"
        )
    model_path, normalizer_path = run_folder.policy_files(run_dir, best=True)
    if not model_path.is_file():
        raise ConfigError(f"«init_from» {source!r} has no {model_path.name}")
    if normalize and normalizer_path is None:
        raise ConfigError(
            f"«init_from» {source!r} keeps only {model_path.name}, whose observation statistics "
            "are fixed inside it; a run that normalises observations goes on from the run "
            "folder it was exported from"
        )
    if normalize and not normalizer_path.is_file():
        raise ConfigError(f"«init_from» {source!r} has no {normalizer_path.name}")
    chosen = {
        "run": str(run_dir),
        "model": str(model_path),
        "normalizer": str(normalizer_path) if normalize else None,
        "sha256": hashlib.sha256(model_path.read_bytes()).hexdigest(),
    }
    if replay_buffer:
        chosen["replay_buffer"] = str(_checkpoint_replay_buffer(run_dir, algo))
    return chosen


def _checkpoint_replay_buffer(run_dir: Path, algo: str) -> Path:
    if issubclass(ALGO_CLASSES[algo], OnPolicyAlgorithm):
        raise ConfigError(f"«init_replay_buffer»: {algo} is on-policy and keeps no replay buffer")
    steps = run_folder.latest_checkpoint(run_dir)
    path = run_folder.checkpoint_paths(run_dir, steps)["replay_buffer"] if steps else None
    if path is None or not path.is_file():
        raise ConfigError(
            f"«init_replay_buffer»: {str(run_dir)!r} has no checkpoint with a replay buffer "
            f"(looked for {run_folder.CHECKPOINTS}/replay_buffer_STEPS_steps.pkl)"
        )
    return path


def _refuse_env_kwargs_given_twice(hyperparams: Mapping, env_kwargs: Mapping) -> None:
    """ConfigError for a setting in both --hyperparams env_kwargs.X and --env-kwargs (or a
    mapping in one and a key inside it in the other): which one won would be a silent rule
    of precedence between two flags of one command line."""
    from_hyperparams = hyperparams.get("env_kwargs")
    from_hyperparams = from_hyperparams if isinstance(from_hyperparams, Mapping) else {}
    from_flag = list(_leaf_paths(env_kwargs))
    given_twice = sorted(
        ".".join(min(a, b, key=len))
        for a in _leaf_paths(from_hyperparams)
        for b in from_flag
        if a[: len(b)] == b[: len(a)]  # the same setting, or one inside the other
    )
    if given_twice:
        raise ConfigError(
            f"env kwargs {given_twice} are given both in «hyperparams» env_kwargs and in "
            "«env_kwargs»; give each setting once"
        )


def _refuse_counts_given_twice(hyperparams: Mapping, **counts) -> None:
    """ConfigError for a count given in both ``hyperparams`` and its own argument: the
    argument would win silently, and the other value would go unchecked."""
    given_twice = [
        f"{key} («hyperparams» {key}={hyperparams[key]!r} and «{key}» {value})"
        for key, value in counts.items()
        if value is not None and key in hyperparams
    ]
    if given_twice:
        raise ConfigError(f"{', '.join(given_twice)} given twice; give it once, in either")


def _leaf_paths(settings: Mapping, prefix: tuple[str, ...] = ()):
    """The key path of every setting in nested ``settings`` (a non-empty mapping's entries,
    not the mapping itself)."""
    for key, value in settings.items():
        path = (*prefix, str(key))
        if isinstance(value, Mapping) and value:
            yield from _leaf_paths(value, path)
        else:
            yield path


def check_device(device: str) -> str:
    try:
        parsed = torch.device(device) if device != "auto" else None
    except (RuntimeError, TypeError) as error:
        raise ConfigError(
            f"device {device!r} is not a torch device (auto, cpu, cuda, cuda:N)"
        ) from error
    if parsed is not None and parsed.type not in SUPPORTED_DEVICE_TYPES:
        # torch names more (meta, mps, xpu, ...): meta crashed mid-run, the rest failed as
        # "refused its hyper-parameters" or a "corrupt" checkpoint.
        raise ConfigError(
            f"device {device!r} is a {parsed.type} device; training runs on auto, cpu, cuda or "
            "cuda:N"
        )
    if parsed is not None and parsed.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(
            f"device {device!r} asked for CUDA, but this torch build ({torch.__version__}) "
            "has no usable GPU; use «device» cpu or install a CUDA build "
            "(docs/guides/rendering.md)"
        )
    return device


def check_policy_kwarg_names(algo: str, policy: str, named: Mapping) -> None:
    """A misspelt ``policy_kwargs`` entry, refused before the run folder is made (SB3 would
    refuse it only when building the model, without naming what was meant)."""
    policy_class = ALGO_CLASSES[algo].policy_aliases[policy]
    taken = inspect.signature(policy_class.__init__).parameters
    set_by_sb3 = {"self", "observation_space", "action_space", "lr_schedule"}
    # Classes are named by their aliases (features_extractor); only the optimizer is named
    # under its own key.
    unnamed_classes = {name for name in taken if name.endswith("_class")} - {"optimizer_class"}
    allowed = sorted({*taken, *POLICY_KWARG_ALIASES} - set_by_sb3 - unnamed_classes)
    for name in named:
        if name not in allowed:
            raise ConfigError(
                f"unknown policy_kwargs entry {name!r} for {algo.upper()}'s {policy}"
                f"{closest(name, allowed)}; allowed: {', '.join(allowed)}"
            )


def policy_kwargs(named: Mapping | None) -> dict:
    """The YAML's ``policy_kwargs`` with class names (features extractor, activation,
    optimizer) replaced by the classes they name."""
    if named is not None and not isinstance(named, Mapping):
        raise ConfigError(
            f"policy_kwargs must be a mapping (policy_kwargs.net_arch=[64, 64]), got {named!r}"
        )
    kwargs = dict(named or {})
    classes = sorted(key for key in kwargs if key.endswith("_class") and key != "optimizer_class")
    if classes:
        raise ConfigError(
            f"policy_kwargs {classes} take Python classes, which a hyper-parameter file cannot "
            "name; give policy_kwargs.features_extractor, activation_fn or optimizer_class by "
            "name instead"
        )
    if "features_extractor" in kwargs:
        name = kwargs.pop("features_extractor")
        kwargs["features_extractor_class"] = FEATURES_EXTRACTORS[
            require_known("features extractor", name, tuple(FEATURES_EXTRACTORS))
        ]
    if "activation_fn" in kwargs:
        name = kwargs["activation_fn"]
        kwargs["activation_fn"] = ACTIVATIONS[
            require_known("activation function", name, tuple(ACTIVATIONS))
        ]
    if "optimizer_class" in kwargs:
        name = kwargs["optimizer_class"]
        kwargs["optimizer_class"] = OPTIMIZERS[require_known("optimizer", name, tuple(OPTIMIZERS))]
    return kwargs


def algorithm_kwargs(hyperparams: Mapping) -> dict:
    kwargs = dict(hyperparams)
    if "policy_kwargs" in kwargs:
        kwargs["policy_kwargs"] = policy_kwargs(kwargs["policy_kwargs"])
    if isinstance(kwargs.get("train_freq"), list):  # YAML has no tuples; SB3 wants (n, unit)
        kwargs["train_freq"] = tuple(kwargs["train_freq"])
    for key in SCHEDULED:
        if isinstance(kwargs.get(key), str):
            # SB3's progress runs from 1 to 0 over the run's total steps, also when resumed.
            start = linear_schedule_start(key, kwargs[key])
            kwargs[key] = LinearSchedule(start, 0.0, end_fraction=1.0)
    return kwargs


# --- environments ----------------------------------------------------------------------------


def _env_factory(config: dict, monitor_file: str | None, keys):
    def make():
        interrupts.ignore_in_worker()
        env = make_env(config["env_id"], config["env_kwargs"])
        monitored = keys
        if config.get("start_curriculum"):
            env = StartNearGrasp(env, **start_settings(config["start_curriculum"]))
            monitored = (*keys, STARTED_NEAR)  # which training episodes started near the handle
        return Monitor(env, filename=monitor_file, info_keywords=monitored)

    return make


def has_own_vector_env(env_id: str) -> bool:
    """Whether ``gym.make_vec(env_id, N)`` makes the task's own vector env."""
    return gym.spec(env_id).vector_entry_point is not None


def default_vec_env(env_id: str) -> str:
    """``batched`` where the id has a vector env of its own, else ``dummy``."""
    return "batched" if has_own_vector_env(env_id) else DEFAULT_VEC_ENV


def _check_batched(config: dict) -> None:
    if config["vec_env"] != "batched":
        return
    if not has_own_vector_env(config["env_id"]):
        own = [env_id for env_id in liuxing_envs.ENV_IDS if has_own_vector_env(env_id)]
        raise ConfigError(
            f"«vec_env» batched needs an env with a vector env of its own ({', '.join(own)}); "
            f"{config['env_id']} has none: use dummy or subproc"
        )
    if config.get("start_curriculum"):
        raise ConfigError("«vec_env» batched cannot wrap each env in a start curriculum")


def check_env_workers(config: dict, workers) -> int:
    """``workers`` (None: the default) as the run's «env_workers»: at most its «n_envs», and
    more than one only for a batched vector env (the other kinds have theirs: subproc)."""
    workers = int_at_least(
        "«env_workers»", DEFAULT_ENV_WORKERS if workers is None else workers, minimum=1
    )
    if workers > config["n_envs"]:
        raise ConfigError(
            f"«env_workers» {workers} exceeds «n_envs» {config['n_envs']}: each worker process "
            "steps one scene at least"
        )
    if workers > 1 and config["vec_env"] != "batched":
        raise ConfigError(
            f"«env_workers» {workers} needs «vec_env» batched; «vec_env» subproc runs a "
            "process per env"
        )
    return workers


def build_vec_env(config: dict, run_dir: Path, start_steps: int = 0) -> gym.Env:
    """The training envs of a start (``start_steps`` 0) or resume of the run, each logging
    its episodes to a Monitor file of its own (see :func:`run_folder.monitor_path`)."""
    task = task_for(config["env_id"])
    (run_dir / run_folder.MONITOR).mkdir(parents=True, exist_ok=True)
    # Nanoseconds: a resume within the second its run stopped in, named by whole seconds,
    # overwrote that run's monitor files (its training episodes).
    stamp = time.time_ns()
    n_envs = config["n_envs"]
    monitor_files = [
        str(run_folder.monitor_path(run_dir, rank, n_envs, start_steps, stamp))
        for rank in range(n_envs)
    ]
    if config["vec_env"] == "batched":
        _check_batched(config)
        check_env_kwargs(config["env_id"], config["env_kwargs"])
        try:
            envs = gym.make_vec(
                config["env_id"],
                n_envs,
                workers=config.get("env_workers", DEFAULT_ENV_WORKERS),
                **config["env_kwargs"],
            )
        except (TypeError, ValueError, FileNotFoundError) as error:
            message = f"{config['env_id']} with env kwargs {config['env_kwargs']}: {error}"
            raise ConfigError(message) from error
        return BatchedVecEnv(envs, monitor_files, (task.metric,))
    factories = [_env_factory(config, path, (task.metric,)) for path in monitor_files]
    return VEC_ENVS[config["vec_env"]](factories)


def vector_keys(space: gym.spaces.Space) -> list[str]:
    """Keys of a Dict space that are normalised: vectors, never images."""
    return [key for key, sub in space.spaces.items() if not is_image_space(sub)]


# --- callbacks -------------------------------------------------------------------------------


#: The model attribute (saved in its zip with SB3's other attributes) holding the seconds of
#: training behind it, across resumes.
TRAINED_SECONDS = "liuxing_trained_seconds"
#: Likewise the seconds of those spent in the algorithm's gradient updates.
UPDATE_SECONDS = "liuxing_update_seconds"
#: config.yml's settings that define a run. A resume keeps them (--resume changes only
#: n_timesteps, device, final_episodes and torch_threads), so every saved model records them
#: (as the attribute RUN_DEFINITION) and a resume refuses a config.yml that changed one.
RUN_DEFINING_KEYS = (
    "env_id", "algo", "seed", "n_envs", "vec_env", "policy", "normalize", "demonstrations",
    "start_curriculum", "env_kwargs", "eval_env_kwargs", "hyperparams", "eval_freq",
    "eval_episodes", "save_freq", "tensorboard", "init_from",
)  # fmt: skip
RUN_DEFINITION = "liuxing_run_definition"


def run_definition(config: Mapping) -> dict:
    """``config``'s run-defining settings, as JSON has them (what a saved model records)."""
    return json.loads(json.dumps({key: config.get(key) for key in RUN_DEFINING_KEYS}, default=repr))


def check_run_definition(config: Mapping, model_path: Path, config_path: Path) -> None:
    """A RunFolderError naming each run-defining setting of ``config`` (read from
    ``config_path``) that differs from what the model at ``model_path`` trained under: a
    config.yml edited by hand, or damaged, would otherwise be ignored (SB3 loads its
    hyper-parameters from the model) or change the run silently (``n_envs``). A model saved
    before models recorded this passes."""
    recorded = run_folder.saved_attribute(model_path, RUN_DEFINITION)
    if not isinstance(recorded, dict):
        return
    changed = [
        f"{key} is {_shown(now)} there, but the run was trained with {_shown(then)}"
        for key, then, now in _differences(recorded, run_definition(config))
    ]
    if changed:
        raise run_folder.RunFolderError(
            f"{str(config_path)!r} no longer holds the settings its run was trained with "
            f"(was config.yml edited?): {'; '.join(changed)}. A resumed run keeps them; "
            "put them back, or start a new run («init_from» starts one from this run's policy)"
        )


_ABSENT = object()


def _shown(value) -> str:
    return "absent" if value is _ABSENT else repr(value)


def _differences(then: Mapping, now: Mapping, prefix: str = ""):
    """(dotted key, old value, new value) of each setting that differs, nested mappings
    compared key by key (a missing key's value is _ABSENT)."""
    for key in sorted({*then, *now}, key=str):
        old, new = then.get(key, _ABSENT), now.get(key, _ABSENT)
        if isinstance(old, dict) and isinstance(new, dict):
            yield from _differences(old, new, f"{prefix}{key}.")
        elif old != new or type(old) is not type(new):
            yield f"{prefix}{key}", old, new


class TrainingClock:
    """Seconds of training behind a run: this process's since ``learn()`` began, plus what the
    checkpoint it resumed from had behind it. The time a run spent stopped is not counted,
    nor the steps after its last checkpoint that a resume trains again, except a PPO
    rollout a stop cut short (at most one per stop).

    It also keeps the share of them spent in gradient updates (:class:`UpdateTimer` marks
    them), which says whether a run is bound by its env or by its learner."""

    def __init__(self, model, resuming: bool) -> None:
        self.before = _saved_seconds(model, TRAINED_SECONDS) if resuming else 0.0
        self.updates_before = _saved_seconds(model, UPDATE_SECONDS) if resuming else 0.0
        self.started = time.perf_counter()
        self.updating = 0.0
        self._update_started: float | None = None

    def seconds(self) -> float:
        return self.before + time.perf_counter() - self.started

    def update_seconds(self) -> float:
        return self.updates_before + self.updating

    def update_starts(self) -> None:
        self._update_started = time.perf_counter()

    def update_ends(self) -> None:
        if self._update_started is not None:
            self.updating += time.perf_counter() - self._update_started
            self._update_started = None

    def stamp(self, model) -> None:
        """Record the seconds behind ``model`` in it, for its zip."""
        setattr(model, TRAINED_SECONDS, round(self.seconds(), 1))
        setattr(model, UPDATE_SECONDS, round(self.update_seconds(), 1))


def _saved_seconds(model, attribute: str) -> float:
    """A saved model's count of seconds; 0 where a checkpoint of older code has none (its
    count restarts at the resume) or holds no usable number."""
    value = getattr(model, attribute, 0.0)
    try:
        value = float(value) if is_number(value) else 0.0
    except OverflowError:
        value = 0.0
    return value if math.isfinite(value) and value >= 0 else 0.0


def save_checkpoint(
    model, run_dir: Path, curriculum=None, clock: TrainingClock | None = None
) -> int:
    """Save the model, SAC's replay buffer, the normaliser and ``curriculum``'s state (an
    :class:`AdvanceStartLevel`, or None) under the model's step count, with ``clock``'s
    seconds of training in the model."""
    if clock is not None:
        clock.stamp(model)
    steps = int(model.num_timesteps)
    paths = run_folder.checkpoint_paths(run_dir, steps)
    paths["model"].parent.mkdir(parents=True, exist_ok=True)
    # Every file is written atomically, the model last: a checkpoint exists (for --resume)
    # only once its model zip does, and then its other files are complete.
    if curriculum is not None:
        run_folder.write_text_atomically(paths["curriculum"], json.dumps(curriculum.state()))
    if hasattr(model, "replay_buffer") and model.replay_buffer is not None:
        run_folder.save_atomically(model.save_replay_buffer, paths["replay_buffer"])
    normalizer = model.get_vec_normalize_env()
    if normalizer is not None:
        run_folder.save_atomically(normalizer.save, paths["normalizer"])
    run_folder.save_atomically(model.save, paths["model"])
    run_folder.prune_checkpoints(run_dir, KEEP_CHECKPOINTS)
    return steps


class _Periodic(BaseCallback):
    """Calls :meth:`act` each time the step counter passes a multiple of ``every`` (SB3
    counts ``n_envs`` steps per call, so exact multiples are rarely hit)."""

    def __init__(self, every: int) -> None:
        super().__init__()
        self.every = every
        self.next_at = every

    def _on_training_start(self) -> None:
        self._schedule()

    def _on_step(self) -> bool:
        self._act_if_due()
        return True

    def _act_if_due(self) -> None:
        # The model's counter: SB3 updates the callback's own only in on_step.
        if self.model.num_timesteps >= self.next_at:
            self.act()
            self._schedule()

    def _schedule(self) -> None:
        self.next_at = (self.model.num_timesteps // self.every + 1) * self.every

    @abstractmethod
    def act(self) -> None:
        """What to do every ``every`` steps."""


class RolloutBoundary(BaseCallback):
    """The step count at which the model's weights were last consistent with its counter.

    An on-policy algorithm (PPO) learns only from whole rollouts, and a rollout not yet
    learned from (half collected, or collected but its update failed) is lost when training
    stops; a checkpoint taken then is labelled with the steps at the start of that rollout,
    after the last update, so a resumed run collects the same rollouts and ends on the same
    step count as one never interrupted. Off-policy algorithms (SAC) keep every step in
    their replay buffer: their boundary is the current step."""

    def _on_training_start(self) -> None:
        self.steps = self.model.num_timesteps
        self._every_step = not isinstance(self.model, OnPolicyAlgorithm)

    def _on_rollout_start(self) -> None:
        self.steps = self.model.num_timesteps

    def _on_step(self) -> bool:
        if self._every_step:
            self.steps = self.model.num_timesteps
        return True


class UpdateTimer(BaseCallback):
    """Marks the gradient updates on a :class:`TrainingClock`: SB3 runs them between the end
    of one rollout and the start of the next (or the end of training), for PPO and for SAC.
    It goes first among the callbacks, so that the evaluations and checkpoints taken where a
    rollout starts are not counted as updates."""

    def __init__(self, clock: TrainingClock) -> None:
        super().__init__()
        self.clock = clock

    def _on_rollout_end(self) -> None:
        self.clock.update_starts()

    def _on_rollout_start(self) -> None:
        self.clock.update_ends()

    def _on_training_end(self) -> None:
        self.clock.update_ends()

    def _on_step(self) -> bool:
        return True


class StopWhenRequested(BaseCallback):
    """Ends ``learn()`` at the next env step once Ctrl-C or SIGTERM asked for it (see
    :mod:`agents.interrupts`). :attr:`stopped` says whether it did: a signal during the last
    update comes after the last step, and ``learn()`` then finishes its training."""

    stopped = False

    def _on_step(self) -> bool:
        self.stopped = interrupts.requested()
        return not self.stopped


class PeriodicCheckpoint(_Periodic):
    """A checkpoint every ``every`` steps, taken when the next rollout starts: only there has
    the model learned from every step it counts (PPO updates after each rollout) and does
    SAC's replay buffer hold each of them. Taken at a step, a PPO checkpoint was labelled
    with steps its weights had not learned from, and a run resumed from it ended on more
    steps and fewer updates than one never stopped."""

    def __init__(
        self, run_dir: Path, every: int, curriculum=None, clock: TrainingClock | None = None
    ) -> None:
        super().__init__(every)
        self.run_dir, self.curriculum, self.clock = run_dir, curriculum, clock

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        self._act_if_due()

    def act(self) -> None:
        save_checkpoint(self.model, self.run_dir, self.curriculum, self.clock)


class _StopRequested(Exception):
    pass


def _raise_if_requested() -> None:
    if interrupts.requested():
        raise _StopRequested


class PeriodicEvaluation(_Periodic):
    """Evaluates the current policy on its own env (the training env's kwargs with the
    config's ``eval_env_kwargs`` over them) every ``every`` steps, appends a row to
    ``evaluations.csv`` and keeps the best model (by mean return) as ``best_model.zip``.
    The caller closes :attr:`env`.

    PPO is evaluated where a rollout starts and where training ends, after its update, as
    checkpoints are taken: at the step that passes a multiple, a row and a best model were
    labelled with steps their weights had not learned from (one rollout's), and the last
    update was never scored. A resumed run first makes up an evaluation a stop cut short,
    which is not recorded (a finished run's last one: :func:`_make_up_last_evaluation`)."""

    def __init__(self, config: dict, run_dir: Path, every: int) -> None:
        super().__init__(every)
        self.run_dir = run_dir
        self.task = task_for(config["env_id"])
        self.env = make_env(config["env_id"], periodic_eval_env_kwargs(config))
        first_seed = config["seed"] + PERIODIC_EVAL_SEED_OFFSET
        self.seeds = range(first_seed, first_seed + config["eval_episodes"])
        self.best = self.best_so_far()
        self.clock: TrainingClock | None = None  # the run's, set by learn_in_run_folder

    def best_so_far(self) -> float:
        """The mean return of the best model's evaluation, which the next one must beat to
        replace it: any, where there is no best model (it came from steps a resumed run
        trains again, or was removed)."""
        steps = run_folder.best_model_steps(self.run_dir)
        history = run_folder.read_evaluations(self.run_dir)
        return max(
            (row["mean_return"] for row in history if row["timesteps"] == steps), default=-np.inf
        )

    def _on_training_start(self) -> None:
        super()._on_training_start()
        self._after_update = isinstance(self.model, OnPolicyAlgorithm)
        if evaluation_missed(self.run_dir, self.every, self.model.num_timesteps):
            self.next_at = self.model.num_timesteps  # a resumed run's, which a stop cut short

    def _on_step(self) -> bool:
        if not self._after_update:
            self._act_if_due()
        return True

    def _on_rollout_start(self) -> None:
        if self._after_update:
            self._act_if_due()

    def _on_training_end(self) -> None:
        if self._after_update:
            self._act_if_due()

    def act(self) -> None:
        if interrupts.requested():
            return  # learn() stops at the next step; an evaluation would be cut short
        try:
            self.evaluate()
        except _StopRequested:
            pass  # an evaluation cut short is not recorded; learn() stops at the next step

    def evaluate(self) -> dict:
        """Scores the model as it is now (:meth:`score`) and keeps it as the best model if
        it beats the best so far."""
        row = self.score(
            SB3Policy(self.model, self.model.get_vec_normalize_env()),
            self.model.num_timesteps,  # the callback's own counter lags outside on_step
            self.clock.seconds(),
        )
        self.logger.record("eval/mean_reward", row["mean_return"])
        self.logger.record(f"eval/{self.task.metric}", row["mean_metric"])

        def save_model(path: Path) -> None:
            setattr(self.model, TRAINED_SECONDS, row["wall_seconds"])  # behind this model
            self.model.save(path)

        normalizer = self.model.get_vec_normalize_env()
        self.keep_if_best(row, save_model, normalizer.save if normalizer is not None else None)
        return row

    def keep_if_best(self, row: dict, save_model, save_normalizer=None) -> None:
        """When ``row`` beats the best evaluation so far, save the best model with
        ``save_model(path)`` and its normaliser with ``save_normalizer(path)``, the normaliser
        first: a best model is only ever taken with its own."""
        if row["mean_return"] <= self.best:
            return
        self.best = row["mean_return"]
        if save_normalizer is not None:
            run_folder.save_atomically(save_normalizer, self.run_dir / run_folder.BEST_NORMALIZER)
        run_folder.save_atomically(save_model, self.run_dir / run_folder.BEST_MODEL)

    def score(self, policy: SB3Policy, steps: int, seconds: float) -> dict:
        """Runs the evaluation episodes with ``policy`` (trained for ``steps`` steps in
        ``seconds``) and appends their row to ``evaluations.csv``; returns the row."""
        episodes = run_episodes(
            self.env, policy, self.seeds, (self.task.metric,), on_episode=_raise_if_requested
        )
        returns = [episode["return"] for episode in episodes]
        row = {
            "timesteps": int(steps),
            "mean_return": float(np.mean(returns)),
            "std_return": float(np.std(returns)),
            "mean_metric": float(np.mean([episode[self.task.metric] for episode in episodes])),
            "wall_seconds": round(seconds, 1),
        }
        run_folder.append_evaluation(self.run_dir, row)
        return row


def evaluation_missed(run_dir: Path, every: int, steps: int) -> bool:
    """Whether a run at ``steps`` steps that evaluates every ``every`` lacks the evaluation
    of the last multiple it passed: a stop cut it short, or (PPO's at the end of training,
    which follows the last update) skipped it."""
    if not every or steps < every:
        return False
    done = {row["timesteps"] // every for row in run_folder.read_evaluations(run_dir)}
    return steps // every not in done


def _make_up_last_evaluation(run_dir: Path, config: dict, steps: int, result: dict) -> None:
    """The evaluation a stop left out at the end of a run trained for ``steps`` steps,
    scored on its final model; that model becomes the best one if it beats it, as in
    training."""
    seconds = result.get("train_seconds", math.nan)  # none where result.json was lost
    evaluation = PeriodicEvaluation(config, run_dir, config["eval_freq"])
    try:
        row = evaluation.score(load_policy(run_dir, config, best=False), steps, seconds)
    finally:
        evaluation.env.close()
    task = evaluation.task
    print(
        f"evaluation at {row['timesteps']} steps: mean return {row['mean_return']:.3f}, "
        f"{task.metric} {row['mean_metric']:.3f}"
    )
    normalizer = run_dir / run_folder.FINAL_NORMALIZER
    evaluation.keep_if_best(
        row,
        functools.partial(shutil.copyfile, run_dir / run_folder.FINAL_MODEL),
        functools.partial(shutil.copyfile, normalizer) if normalizer.is_file() else None,
    )
    plot_learning_curve(run_dir, task.metric_label, config["eval_episodes"])


# --- runs ------------------------------------------------------------------------------------


def new_run_dir(config: dict, runs_dir: Path = DEFAULT_RUNS_DIR) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path(runs_dir) / config["env_id"] / f"{config['algo']}_seed{config['seed']}_{stamp}"


def train(config: dict, run_dir: Path, progress_bar: bool = False) -> dict:
    """A new run in ``run_dir`` (created; must not already hold a run, nor be in use by
    another process)."""
    run_dir = Path(run_dir)
    _refuse_a_run_folder(run_dir)
    # Loaded before the folder is made: a refused start leaves nothing behind.
    trained = (
        load_trained_start(
            config["init_from"], config["env_id"], config["env_kwargs"], config["n_envs"]
        )
        if config.get("init_from")
        else None
    )
    before = {path.name for path in run_dir.iterdir()} if run_dir.is_dir() else None
    try:
        prepare_output_folder(run_dir)
    except OutputFolderError as error:
        raise ConfigError(f"cannot make the run folder {str(run_dir)!r}: {error}") from error
    with run_folder.exclusive(run_dir):
        _refuse_a_run_folder(run_dir)  # again: another start may have written one meanwhile
        try:
            model, evaluation = _start(config, run_dir, trained)
        except BaseException as error:
            # Refused, or stopped while setting up (SAC's demonstrations take minutes): nothing
            # to resume, and the config.yml left behind would refuse the next start here.
            _remove_written(run_dir, before)
            if isinstance(error, KeyboardInterrupt):
                print("\ninterrupted before training began: nothing was saved", file=sys.stderr)
            raise
        return learn_in_run_folder(
            model, config, run_dir, progress_bar, resuming=False, evaluation=evaluation
        )


def _refuse_a_run_folder(run_dir: Path) -> None:
    if (run_dir / run_folder.CONFIG).exists():
        raise ConfigError(
            f"{str(run_dir)!r} already holds a run; continue it with «resume» {run_dir} "
            "or choose another «run_dir»"
        )


def _start(config: dict, run_dir: Path, trained: TrainedStart | None):
    """Writes the new run's config and builds its envs, model and periodic evaluation,
    SAC's replay buffer filled as configured; closes what it opened if it fails."""
    venv = evaluation = None
    try:
        run_folder.write_config(run_dir, config)
        torch.set_num_threads(config["torch_threads"])
        venv = _checked_vec_env(config, run_dir)
        if trained is not None and trained.normalizer is not None:
            # The trained weights expect the trained run's scaling; it keeps adapting from there.
            trained.normalizer.set_venv(venv)
            trained.normalizer.training = True
            venv = trained.normalizer
        elif config["normalize"]:
            venv = VecNormalize(
                venv,
                norm_obs=True,
                norm_reward=False,
                norm_obs_keys=vector_keys(venv.observation_space),
            )
        evaluation = _periodic_evaluation(config, run_dir, venv)
        model = _checked_model(config, venv, run_dir)
        setattr(model, RUN_DEFINITION, run_definition(config))  # saved with every checkpoint
        if trained is not None:
            load_trained_weights(model, trained)
            if trained.replay_buffer is not None:
                # Its rewards are the trained run's: a changed reward kwarg applies to new ones.
                run_folder.use_replay_buffer(model, trained.replay_buffer)
        if config.get("demonstrations"):
            spec = config["demonstrations"]
            episodes, pretrain_steps = demonstration_sizes(config)
            cut = (episodes, pretrain_steps) != (spec["episodes"], spec["pretrain_steps"])
            print(
                f"seeding the replay buffer with {_episodes(episodes, spec['expert'])}"
                + (f", then {pretrain_steps} behaviour-cloning steps" if pretrain_steps else "")
                + " (hyper-parameter demonstrations; null skips them"
                + (
                    f"; cut from {spec['episodes']} episodes and {spec['pretrain_steps']} steps "
                    f"for a run of {config['n_timesteps']} steps"
                    if cut
                    else ""
                )
                + ") ...",
                flush=True,
            )
            added = seed_replay_buffer(model, config)
            run_folder.write_text_atomically(
                run_dir / run_folder.DEMONSTRATIONS, json.dumps(added, indent=2)
            )
            print(
                f"replay buffer seeded with {added['transitions']} transitions of "
                f"{_episodes(added['episodes'], added['expert'])} ({added['successes']} "
                "succeeded)"
            )
    except BaseException:
        _close_opened(venv, evaluation)
        raise
    return model, evaluation


def _remove_written(run_dir: Path, before: set[str] | None) -> None:
    """Removes what a start that never trained wrote: the run folder if it made it
    (``before`` is None), else the run's own files and folders the folder did not hold
    (``before``: its entries' names); anything else, another process's say, stays."""
    if before is None:
        shutil.rmtree(run_dir, ignore_errors=True)
        return
    for name in set(run_folder.ENTRIES) - before:
        path = run_dir / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def _close_opened(venv, evaluation: PeriodicEvaluation | None) -> None:
    """Closes what a start or resume that failed half-way had opened."""
    workers.stop(venv)
    if evaluation is not None:
        evaluation.env.close()


def resumed_seed(seed: int, steps: int) -> int:
    """The seed of a run resumed at ``steps``: drawn from both, so it lands on neither the
    training envs' first seeds nor the periodic evaluation's (``seed + steps`` did, at 10,000
    steps: ``seed + PERIODIC_EVAL_SEED_OFFSET``)."""
    return int(np.random.SeedSequence([seed, steps]).generate_state(1)[0])


def periodic_eval_env_kwargs(config: dict) -> dict:
    """The training env's kwargs with ``eval_env_kwargs`` (None or absent: none) over them.
    A split named there replaces an explicit list of objects (or instruments) the run trains
    on, which the env would otherwise take over any split."""
    changes = config.get("eval_env_kwargs") or {}
    env_kwargs = deep_update(config["env_kwargs"], changes)
    task = task_for(config["env_id"])
    if task.split_kwarg in changes and task.explicit_scene_kwarg not in changes:
        env_kwargs.pop(task.explicit_scene_kwarg, None)
    return env_kwargs


def _periodic_evaluation(config: dict, run_dir: Path, venv) -> PeriodicEvaluation | None:
    """The run's periodic evaluation (None when off), its env checked to have the training
    env's spaces: ``eval_env_kwargs`` such as another ``view_budget`` would otherwise fail
    at the first evaluation, with the training so far lost."""
    if not config["eval_freq"]:
        return None
    evaluation = PeriodicEvaluation(config, run_dir, config["eval_freq"])
    env = evaluation.env
    if (env.observation_space, env.action_space) != (venv.observation_space, venv.action_space):
        env.close()
        raise ConfigError(
            f"eval_env_kwargs {config.get('eval_env_kwargs')} give the evaluation env other "
            "observation or action spaces than the training env's; the policy could not act "
            "in it"
        )
    return evaluation


def _checked_vec_env(config: dict, run_dir: Path):
    """``build_vec_env``. An env kwarg value the env refuses is a ConfigError from
    ``make_env`` in-process; a SubprocVecEnv worker dies of it, and its pipe closes."""
    try:
        return build_vec_env(config, run_dir)
    except (EOFError, ConnectionError) as error:
        raise ConfigError(
            f"{config['env_id']} with env kwargs {config['env_kwargs']}: a worker process died "
            "building it; «vec_env» dummy shows why"
        ) from error


def _checked_model(config: dict, venv, run_dir: Path):
    """The algorithm on ``venv``, with what SB3 refuses while building it (a batch size of
    0, a ``net_arch`` that is not a list of widths) as a ConfigError."""
    try:
        return ALGO_CLASSES[config["algo"]](
            config["policy"],
            venv,
            seed=config["seed"],
            device=config["device"],
            tensorboard_log=_tensorboard_dir(config, run_dir),
            verbose=0,
            **algorithm_kwargs(config["hyperparams"]),
        )
    except (TypeError, ValueError, AssertionError, RuntimeError) as error:
        # RuntimeError: torch refusing a layer, such as net_arch [-1]'s negative width.
        raise ConfigError(
            f"{config['algo'].upper()} refused its hyper-parameters {config['hyperparams']}: "
            f"{error}"
        ) from error


@dataclass(frozen=True)
class TrainedStart:
    """What ``--init-from`` loads, once: the saved model's state dicts and bare tensors, and
    its normaliser (None without normalisation); and, with ``--init-replay-buffer``, the
    replay buffer to give the new model (else None)."""

    model_path: str
    state_dicts: dict
    variables: dict
    normalizer: VecNormalize | None
    replay_buffer: ReplayBuffer | None


def load_trained_start(
    init_from: dict, env_id: str, env_kwargs: Mapping, n_envs: int
) -> TrainedStart:
    """The ``init_from`` model, normaliser and replay buffer, or a ConfigError /
    RunFolderError when one cannot be read, the model does not observe and act in the spaces
    of ``env_id`` with ``env_kwargs`` (an env kwarg such as ``obs_mode`` changes them), or
    the buffer was filled by another number of envs than ``n_envs``."""
    from stable_baselines3.common.save_util import load_from_zip_file

    path = init_from["model"]
    try:
        saved, state_dicts, variables = load_from_zip_file(path, device="cpu")
    except run_folder.UNREADABLE as error:
        raise run_folder.RunFolderError(
            f"«init_from» model {path!r} is not readable: {type(error).__name__}: {error}"
        ) from error
    env = make_env(env_id, env_kwargs)
    try:
        for name, expected, trained_in in mismatched_spaces(env, saved):
            raise ConfigError(
                f"«init_from» model {path!r} has the {name} {describe_space(trained_in)}; "
                f"this run's env has {describe_space(expected)} (different env kwargs?)"
            )
    finally:
        env.close()
    normalizer, buffer = init_from.get("normalizer"), init_from.get("replay_buffer")
    replay_buffer = run_folder.read_replay_buffer(buffer) if buffer else None
    # SB3 stores a transition per env in each row: rows of another width would be broadcast
    # (one env's step copied into several columns) or fail mid-run.
    if replay_buffer is not None and replay_buffer.n_envs != n_envs:
        raise ConfigError(
            f"«init_replay_buffer»: {buffer!r} was filled by {replay_buffer.n_envs} env(s); "
            f"this run has «n_envs» {n_envs}: pass «n_envs» {replay_buffer.n_envs}"
        )
    return TrainedStart(
        path,
        state_dicts,
        variables or {},
        run_folder.load_normalizer(normalizer) if normalizer else None,
        replay_buffer,
    )


def load_trained_weights(model, trained: TrainedStart) -> None:
    """Every network, optimiser and (SAC) entropy coefficient of the trained model, into
    ``model`` of the same algorithm; its hyper-parameters stay the new run's."""
    from stable_baselines3.common.save_util import recursive_setattr

    try:
        model.set_parameters(trained.state_dicts, exact_match=True, device=model.device)
    except (RuntimeError, ValueError) as error:
        raise ConfigError(
            f"«init_from» model {trained.model_path!r} does not fit this run's networks "
            f"(different policy_kwargs?): {error}"
        ) from error
    # set_parameters leaves out bare tensors such as SAC's log_ent_coef: without it a tuned
    # policy would restart at entropy coefficient 1 and unlearn its precision.
    for name, tensor in trained.variables.items():
        if tensor is not None:
            recursive_setattr(model, f"{name}.data", tensor.data.to(model.device))


def resume(run_dir: Path, n_timesteps: int | None = None, progress_bar: bool = False, **overrides):
    """Continue a run from its newest checkpoint, with the step counter, the replay buffer
    (off-policy algorithms) and the observation normaliser as they were saved. ``n_timesteps``
    may raise the run's total; ``overrides`` may change ``device``, ``final_episodes``,
    ``torch_threads`` or ``env_workers``.
    A folder another process is training in is refused."""
    run_dir = Path(run_dir)
    # A folder that is no run gets read_config's message, and no lock file left in it.
    is_run = (run_dir / run_folder.CONFIG).is_file()
    with run_folder.exclusive(run_dir) if is_run else contextlib.nullcontext():
        return _resume(run_dir, n_timesteps, progress_bar, **overrides)


def _resume(run_dir: Path, n_timesteps: int | None, progress_bar: bool, **overrides):
    config = {**SAVED_CONFIG_DEFAULTS, **run_folder.read_config(run_dir)}
    _check_saved_config(config, run_dir / run_folder.CONFIG)
    steps = run_folder.latest_checkpoint(run_dir)
    if steps is None:
        raise run_folder.RunFolderError(f"{str(run_dir)!r} has no checkpoint to resume from")
    check_run_definition(
        config, run_folder.checkpoint_paths(run_dir, steps)["model"], run_dir / run_folder.CONFIG
    )
    # The run's total changes only once it trains on: a finished run keeps its own.
    total = (
        config["n_timesteps"] if n_timesteps is None else int_at_least("«n_timesteps»", n_timesteps)
    )
    checks = {
        "device": check_device,
        "final_episodes": lambda value: int_at_least("«final_episodes»", value, minimum=0),
        "torch_threads": lambda value: int_at_least("«torch_threads»", value),
        "env_workers": lambda value: check_env_workers(config, value),
    }
    for key, value in overrides.items():
        if key not in checks:
            raise ConfigError(f"resuming cannot change {key}; it can change {', '.join(checks)}")
        if value is not None:
            config[key] = checks[key](value)
    config["device"] = check_device(config["device"])
    # Checked again: a hand-edited config.yml is caught, and an older run folder's entry gets
    # the settings added since with their defaults.
    config["start_curriculum"] = check_start_curriculum(
        config["env_id"], config["start_curriculum"]
    )
    if steps >= total:
        # Stopped after its last step, or trained without the final comparison its config
        # now asks for: what is left is done alone.
        result = _read_result(run_dir, steps)
        trained = (run_dir / run_folder.FINAL_MODEL).is_file()
        left = _left_after_training(run_dir, config, steps, result) if trained else []
        if left:
            print(f"{str(run_dir)!r} finished training; running {' and '.join(left)}")
            # Recorded as any resume is: its command, and a --final-episodes it changed.
            run_folder.write_config(
                run_dir, {**config, "n_timesteps": max(config["n_timesteps"], steps)}, resuming=True
            )
            if LAST_EVALUATION in left:
                _make_up_last_evaluation(run_dir, config, steps, result)
        unexported = trained and not (run_dir / run_folder.POLICY).is_file()
        if unexported and not left:
            print(f"{str(run_dir)!r} finished training; writing its {run_folder.POLICY}")
        if unexported or LAST_EVALUATION in left:
            export_policy(run_dir, config)  # its best model may have changed, or it had none
        if left:
            if FINAL_COMPARISON not in left:
                return result
            return _final_comparison(run_dir, config, result)
        if unexported:
            return result
        raise ConfigError(
            f"{str(run_dir)!r} already reached {steps} of its {total} steps; "
            "pass a larger «n_timesteps» to continue it"
        )
    config["n_timesteps"] = total
    paths = run_folder.checkpoint_paths(run_dir, steps)
    torch.set_num_threads(config["torch_threads"])
    monitors_before = set((run_dir / run_folder.MONITOR).glob("*"))
    venv = evaluation = None
    try:
        venv = build_vec_env(config, run_dir, start_steps=steps)
        _check_checkpoint_fits(paths["model"], venv, run_dir / run_folder.CONFIG)
        saved_by = run_folder.saved_algorithm(paths["model"])
        if saved_by != config["algo"]:
            raise run_folder.RunFolderError(
                f"{str(run_dir / run_folder.CONFIG)!r}: algo {config['algo']} did not save "
                f"{str(paths['model'])!r}, {saved_by or 'another algorithm'} did (was "
                "config.yml edited?)"
            )
        if config["normalize"]:
            normalizer = run_folder.load_normalizer(paths["normalizer"])
            normalizer.set_venv(venv)
            venv = normalizer
        model = run_folder.load_model(
            ALGO_CLASSES[config["algo"]],
            paths["model"],
            env=venv,
            device=config["device"],
            tensorboard_log=_tensorboard_dir(config, run_dir),
        )
        if paths["replay_buffer"].is_file():
            run_folder.use_replay_buffer(
                model, run_folder.read_replay_buffer(paths["replay_buffer"])
            )
        elif hasattr(model, "replay_buffer"):
            print(
                f"warning: {paths['replay_buffer']} is missing; {config['algo'].upper()} "
                "resumes with an empty replay buffer",
                file=sys.stderr,
            )
        curriculum_state = run_folder.read_curriculum_state(paths["curriculum"])
        forgetting = run_folder.forget_after_checkpoint(
            run_dir,
            steps,
            (p for p in monitors_before if p.name.endswith(run_folder.MONITOR_SUFFIX)),
        )
        evaluation = _periodic_evaluation(config, run_dir, venv)
    except BaseException as error:  # refused: the run folder is left as it was
        _close_opened(venv, evaluation)
        for path in set((run_dir / run_folder.MONITOR).glob("*")) - monitors_before:
            path.unlink(missing_ok=True)
        if isinstance(error, KeyboardInterrupt):
            print(
                "\ninterrupted while resuming, before training: the run folder is as it was",
                file=sys.stderr,
            )
        older = [earlier for earlier in run_folder.checkpoint_steps(run_dir) if earlier < steps]
        damaged = isinstance(error, run_folder.UnreadableFileError) and (
            error.path in paths.values()
        )
        if damaged and older:
            # Writes are atomic, so a damaged checkpoint is a disk fault or a bad copy: say
            # how to go on from the one before it.
            previous = run_folder.checkpoint_paths(run_dir, older[-1])["replay_buffer"]
            raise run_folder.RunFolderError(
                f"{error}. The checkpoint at {older[-1]} steps is older: to resume from it, "
                f"move the files of step {steps} (checkpoints/*_{steps}_steps.*) out of "
                f"{str(run_dir)!r}"
                + (
                    " (it has no replay buffer: only the newest is kept, so "
                    f"{config['algo'].upper()} would go on with an empty one)"
                    if paths["replay_buffer"].exists() and not previous.is_file()
                    else ""
                )
            ) from error
        raise
    run_folder.forget(run_dir, forgetting)
    if forgetting.dropped_evaluations or forgetting.dropped_episodes:
        print(
            f"the run had gone on past its checkpoint at {steps} steps: "
            f"{forgetting.dropped_evaluations} periodic evaluations and "
            f"{forgetting.dropped_episodes} training episodes after it are dropped, as those "
            "steps are trained again"
        )
        if evaluation is not None:
            evaluation.best = evaluation.best_so_far()
    if forgetting.partial_files:
        names = ", ".join(str(path.relative_to(run_dir)) for path in forgetting.partial_files)
        print(f"removed what interrupted writes left: {names}")
    run_folder.write_config(run_dir, {**config, "resumed_from_steps": steps}, resuming=True)
    # A new stream: the resumed run must not replay the episodes it has already seen.
    model.set_random_seed(resumed_seed(config["seed"], steps))
    return learn_in_run_folder(
        model,
        config,
        run_dir,
        progress_bar,
        resuming=True,
        curriculum=curriculum_state,
        evaluation=evaluation,
    )


def _check_checkpoint_fits(model_path: Path, venv, config_path: Path) -> None:
    """A RunFolderError when the env that config.yml describes has other spaces than the
    checkpoint was trained in (an edited ``env_kwargs``), which SB3's load would report as a
    damaged checkpoint. An unreadable checkpoint passes, for the load to name the damage."""
    from stable_baselines3.common.save_util import load_from_zip_file

    try:
        saved, _, _ = load_from_zip_file(model_path, device="cpu", load_data=True)
    except run_folder.UNREADABLE:
        return
    for name, expected, trained_in in mismatched_spaces(venv, saved or {}):
        if trained_in is not None:
            raise run_folder.RunFolderError(
                f"{str(config_path)!r}: its env_kwargs give the {name} "
                f"{describe_space(expected)}, but {str(model_path)!r} was trained "
                f"in {describe_space(trained_in)}: was config.yml edited?"
            )


def _tensorboard_dir(config: dict, run_dir: Path) -> str | None:
    return str(run_dir / run_folder.TENSORBOARD) if config["tensorboard"] else None


def learn_in_run_folder(
    model,
    config: dict,
    run_dir: Path,
    progress_bar: bool,
    resuming: bool,
    curriculum: dict | None = None,
    evaluation: PeriodicEvaluation | None = None,
) -> dict:
    """Train ``model`` to ``config["n_timesteps"]`` in the run folder ``run_dir`` (already
    set up): periodic checkpoints and evaluations as ``config`` sets them, and a checkpoint
    to resume from when a signal stops the run or training fails (a lost worker, say). Returns
    the final comparison."""
    clock = TrainingClock(model, resuming)
    boundary, stopper = RolloutBoundary(), StopWhenRequested()
    callbacks = [UpdateTimer(clock), boundary, stopper]
    level = level_callback(config.get("start_curriculum"), curriculum)
    if level is not None:
        callbacks.append(level)
    if config["save_freq"]:
        callbacks.append(PeriodicCheckpoint(run_dir, config["save_freq"], level, clock))
    if evaluation is not None:
        evaluation.clock = clock
        callbacks.append(evaluation)
    if not config["tensorboard"]:
        # SB3's own silent logger would still make an empty tempdir/SB3-<time> folder per run.
        model.set_logger(Logger(folder=None, output_formats=[]))
    # Until the trained run is saved: acted on between learn() and the final checkpoint, a
    # signal left a folder that neither --resume nor a new start would take.
    with interrupts.deferred():
        try:
            model.learn(
                total_timesteps=config["n_timesteps"] - model.num_timesteps,
                callback=callbacks,
                reset_num_timesteps=not resuming,
                progress_bar=progress_bar,
                tb_log_name="run",
            )
            if stopper.stopped:  # learn() returned early: save and exit as Ctrl-C does
                raise KeyboardInterrupt
        except KeyboardInterrupt:
            model.num_timesteps = boundary.steps
            if stopper.stopped and not isinstance(model, OnPolicyAlgorithm):
                # SB3 asks the callbacks before it stores a step's transition: the step the
                # stop came at is counted but not in the replay buffer.
                model.num_timesteps -= model.n_envs
            with interrupts.saving():
                steps = save_checkpoint(model, run_dir, level, clock)
            print(
                f"\ninterrupted at {steps} steps; checkpoint saved. "
                f"Continue with: python train.py --resume {run_dir}"
            )
            raise
        except Exception as error:  # a dying worker, a bug, or a setting SB3 cannot train with
            # Read first: the dead worker's exit status, before anything else takes time.
            died = isinstance(error, WORKER_GONE) and workers.describe_dead(model.get_env())
            model.num_timesteps = boundary.steps
            steps = save_checkpoint(model, run_dir, level, clock)
            resume_hint = (
                f"A checkpoint was saved at {steps} steps; "
                f"after a fix, continue with: python train.py --resume {run_dir}"
            )
            if died:
                raise WorkerDied(
                    f"the vectorised {config['env_id']} env lost a worker: {died}. The other "
                    f"workers were stopped. {resume_hint}"
                ) from error
            raise RuntimeError(
                f"training stopped on {type(error).__name__}: {error} (traceback above). "
                + resume_hint
            ) from error
        finally:
            workers.stop(model.get_env())
            for callback in callbacks:
                if isinstance(callback, PeriodicEvaluation):
                    callback.env.close()
        result = _save_trained(model, config, run_dir, level, clock)
    print(describe_training_time(result), flush=True)
    if interrupts.requested():  # after the last step (its update, or the saving) ended
        left = _left_after_training(run_dir, config, result["timesteps"], result)
        rest = f" Run {' and '.join(left)} with: python train.py --resume {run_dir}" if left else ""
        print("\ninterrupted after the last step; the trained run is saved." + rest)
        raise KeyboardInterrupt
    if not config["final_episodes"]:
        return result
    return _final_comparison(run_dir, config, result)


def describe_training_time(result: Mapping) -> str:
    """The training time of a ``result.json``, with the share spent in gradient updates."""
    steps, seconds = result["timesteps"], result["train_seconds"]
    said = f"trained {steps} steps in {seconds:.0f} s"
    if seconds <= 0:
        return said
    share = result["update_seconds"] / seconds
    return f"{said}, {steps / seconds:.0f} steps/s ({share:.0%} in gradient updates)"


LAST_EVALUATION, FINAL_COMPARISON = "its last evaluation", "its final comparison"


def work_left(run_dir: Path) -> list[str]:
    """What ``resume`` would still do for the run in ``run_dir``: train on, make up its last
    evaluation, run its final comparison, write its ``policy.zip``; empty when the run is
    finished."""
    run_dir = Path(run_dir)
    config = {**SAVED_CONFIG_DEFAULTS, **run_folder.read_config(run_dir)}
    steps = run_folder.latest_checkpoint(run_dir) or 0
    if steps < config["n_timesteps"] or not (run_dir / run_folder.FINAL_MODEL).is_file():
        return ["training"]
    left = _left_after_training(run_dir, config, steps, _read_result(run_dir, steps))
    if not (run_dir / run_folder.POLICY).is_file():
        left.append(f"writing its {run_folder.POLICY}")
    return left


def _left_after_training(run_dir: Path, config: dict, steps: int, result: dict) -> list[str]:
    """What a run trained for ``steps`` steps has still to do: an evaluation a stop after
    its last step left out, and a final comparison its config asks for."""
    left = []
    if evaluation_missed(run_dir, config["eval_freq"], steps):
        left.append(LAST_EVALUATION)
    if config["final_episodes"] and "comparison" not in result:
        left.append(FINAL_COMPARISON)
    return left


def _save_trained(model, config: dict, run_dir: Path, level, clock: TrainingClock) -> dict:
    """The final model, its checkpoint, the learning curve and result.json; returns the
    result."""
    clock.stamp(model)  # the final model and its checkpoint alike
    normalizer = model.get_vec_normalize_env()
    if normalizer is not None:
        run_folder.save_atomically(normalizer.save, run_dir / run_folder.FINAL_NORMALIZER)
    run_folder.save_atomically(model.save, run_dir / run_folder.FINAL_MODEL)
    save_checkpoint(model, run_dir, level)  # so a larger --timesteps can continue a finished run
    export_policy(run_dir, config)
    plot_learning_curve(run_dir, task_for(config["env_id"]).metric_label, config["eval_episodes"])
    result = {
        "timesteps": int(model.num_timesteps),
        "train_seconds": getattr(model, TRAINED_SECONDS),
        "update_seconds": getattr(model, UPDATE_SECONDS),
    }
    if level is not None:
        result["start_curriculum"] = {"level": level.level, "advances": level.history}
    # Written before the comparison too: a run stopped during it is trained, and --resume
    # then runs the comparison alone.
    run_folder.write_text_atomically(run_dir / run_folder.RESULT, json.dumps(result, indent=2))
    return result


def _final_comparison(run_dir: Path, config: dict, result: dict) -> dict:
    """The best model against the scripted baseline, added to the run's result.json."""
    policy = load_policy(run_dir, config, best=True)
    task = task_for(config["env_id"])
    others = " and ".join(name for name in (task.baseline, task.reference) if name)
    print(
        f"final comparison: {config['final_episodes']} held-out episodes each for the trained "
        f"policy and {others} (train.py's --final-episodes sets how many) ...",
        flush=True,
    )
    try:
        comparison = compare_with_baseline(
            config["env_id"], policy, config["env_kwargs"], config["final_episodes"]
        )
    except KeyboardInterrupt:
        print(
            "\ninterrupted during the final comparison; the trained run is saved. "
            f"Run the comparison with: python train.py --resume {run_dir}"
        )
        raise
    print(format_comparison(comparison))
    result = {**result, "comparison": comparison}
    run_folder.write_text_atomically(run_dir / run_folder.RESULT, json.dumps(result, indent=2))
    return result


def _read_result(run_dir: Path, steps: int) -> dict:
    """result.json, or what a run stopped before writing it can say: its step count."""
    try:
        result = json.loads((run_dir / run_folder.RESULT).read_text())
    except (OSError, ValueError):
        result = None
    return result if isinstance(result, dict) else {"timesteps": steps}


def _check_saved_config(config: dict, path: Path) -> None:
    """A resumed run's config.yml holds values of the kinds train.py wrote (it may have been
    edited by hand or damaged); checked before the run folder is touched."""
    try:
        require_known("environment", config["env_id"], liuxing_envs.ENV_IDS)
        require_known("algorithm", config["algo"], ALGOS)
        int_at_least("seed", config["seed"], minimum=0, maximum=MAX_SEED)
        int_at_least("n_timesteps", config["n_timesteps"])
        int_at_least("n_envs", config["n_envs"])
        require_known("vec_env", config["vec_env"], tuple(VEC_ENVS))
        for key in ("eval_freq", "save_freq", "final_episodes"):
            int_at_least(key, config[key], minimum=0)
        int_at_least("eval_episodes", config["eval_episodes"])
        int_at_least("torch_threads", config["torch_threads"])
        check_env_workers(config, config["env_workers"])
        for key in ("tensorboard", "normalize"):
            if not isinstance(config[key], bool):
                raise ConfigError(f"{key} must be true or false, got {config[key]!r}")
        require_known("policy", config["policy"], POLICIES)
    except ConfigError as error:
        raise run_folder.RunFolderError(f"{str(path)!r}: {error}") from error


def load_policy(run_dir: Path, config: dict | None = None, best: bool = True) -> SB3Policy:
    """The run's best model (by periodic evaluation) or its final one, with its normaliser;
    a shipped folder's exported policy. Falls back to the final model when no evaluation
    ran."""
    run_dir = Path(run_dir)
    config = config or run_folder.read_config(run_dir)
    model_path, normalizer_path = run_folder.policy_files(run_dir, best)
    if not model_path.is_file():
        raise run_folder.RunFolderError(f"{str(run_dir)!r} has no {model_path.name}")
    if (
        config.get("normalize")
        and normalizer_path is not None
        and not normalizer_path.is_file()
        and not run_folder.takes_raw_observations(model_path)
    ):
        raise run_folder.RunFolderError(
            f"{str(run_dir)!r} trained with observation normalisation, but its "
            f"{normalizer_path.name} is missing: its policy cannot be scored on raw observations"
        )
    return SB3Policy.load(ALGO_CLASSES[config["algo"]], model_path, normalizer_path)


def export_policy(run_dir: Path, config: Mapping) -> Path:
    """Write the run's ``policy.zip``: its best model (else its final one) with the
    observation statistics it was trained on moved inside it
    (:func:`~liuxing_envs.policy_parts.with_embedded_normalizer`), so that plain
    ``PPO.load`` / ``SAC.load`` and ``predict`` on raw observations act as the run's policy
    does, wherever the package is installed."""
    run_dir = Path(run_dir)
    model_path, normalizer_path = run_folder.policy_files(run_dir, best=True)
    model = run_folder.load_model(ALGO_CLASSES[config["algo"]], model_path, device="cpu")
    if config.get("normalize"):
        if normalizer_path is None or not normalizer_path.is_file():
            raise run_folder.RunFolderError(
                f"{str(run_dir)!r} trained with observation normalisation, but the statistics "
                f"of its {model_path.name} are missing: its policy cannot be exported"
            )
        model = with_embedded_normalizer(model, run_folder.load_normalizer(normalizer_path))
    setattr(model, run_folder.RAW_OBSERVATIONS, True)
    path = run_dir / run_folder.POLICY
    run_folder.save_atomically(model.save, path)
    return path
