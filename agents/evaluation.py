"""Seeded evaluation of policies (trained or scripted) and the statistics reported for them.

Every policy exposes SB3's ``predict(observation, state=None, episode_start=None,
deterministic=True)`` for one unbatched observation; scripted ones may also have ``reset()``,
called at each episode start. :data:`TASKS` says, per task family, which figure is the
headline, which split is held out, which scripted baselines it has and which one a learner must
beat; how a report presents a task is declared in :mod:`agents.task_reports`.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agents import run_folder
from agents.config import ConfigError, check_env_kwargs
from agents.grasp_baselines import GRASP_BASELINES, ScriptedGrasp
from agents.spaces import describe_space, same_space
from agents.statistics import bootstrap_ci, interval_text, wilson_interval
from agents.view_baselines import BASELINES as VIEW_BASELINES
from liuxing_envs.registration import BY_ID, family

#: Evaluation seeds start here, away from the training (``seed``) and periodic-evaluation
#: (``seed + PERIODIC_EVAL_SEED_OFFSET``) streams.
FINAL_EVAL_SEED = 1_000_000
#: The split every final comparison and, by default, evaluate.py reports.
HELD_OUT_SPLIT = "held_out"


@dataclass(frozen=True)
class Task:
    """What evaluating one environment means."""

    metric: str  #: ``info`` key of the per-episode headline figure, read at the episode's end
    metric_label: str
    split_kwarg: str  #: the env kwarg naming a split of the scene library
    #: the env kwarg listing a scene's items explicitly, which overrides any split
    explicit_scene_kwarg: str
    #: every scripted baseline, by the name evaluate.py takes: ``env -> policy``
    baselines: Mapping[str, Callable]
    baseline: str  #: the baseline a learner must beat
    #: whether the metric is a yes/no outcome (0 or 1 per episode), which has no IQM: the
    #: trimmed mean of 0/1 values is a distorted rate (80% success reads as 1.0)
    metric_is_binary: bool = False
    #: kwargs the baseline's env needs on top of the run's (e.g. the camera it reads)
    baseline_env_kwargs: Mapping = field(default_factory=dict)
    #: further ``info`` keys worth reporting, read at each episode's end
    extra_metrics: tuple[str, ...] = ()
    #: a privileged reference (ground truth), reported for scale, never a competitor
    reference: str | None = None
    #: baselines good enough to seed SAC's replay buffer with their episodes
    #: (agents/demonstrations.py)
    experts: tuple[str, ...] = ()

    @property
    def make_baseline(self) -> Callable:
        return self.baselines[self.baseline]

    @property
    def make_reference(self) -> Callable | None:
        return None if self.reference is None else self.baselines[self.reference]

    @property
    def held_out_kwargs(self) -> dict:
        """Env kwargs selecting the held-out split."""
        return {self.split_kwarg: HELD_OUT_SPLIT}


#: What a report measures, by task family (every version and variant of a task).
TASKS = {
    "ViewPlanning": Task(
        metric="coverage",
        metric_label="final coverage",
        split_kwarg="object_set",
        explicit_scene_kwarg="objects",
        baselines=VIEW_BASELINES,
        baseline="four-view",
        extra_metrics=("is_success",),
        reference="greedy-oracle",
    ),
    "InstrumentGrasp": Task(
        metric="is_success",
        metric_label="success rate",
        metric_is_binary=True,
        split_kwarg="instrument_set",
        explicit_scene_kwarg="instruments",
        baselines=GRASP_BASELINES,
        baseline="scripted-grasp",
        baseline_env_kwargs=ScriptedGrasp.ENV_KWARGS,
        experts=("privileged-grasp",),
        extra_metrics=(
            "peak_force",
            "hard_limit_exceeded",
            "force_violations",
            "impact_violations",
            "guarded_steps",
            "guarded_finger_steps",
        ),
    ),
}


def task_for(env_id: str) -> Task:
    return TASKS[family(env_id)]


def make_env(env_id: str, env_kwargs: Mapping | None = None, **make_kwargs):
    """``gym.make`` with the run's env kwargs. Where an id registers a time limit (the v0
    ids: their default episode lengths), a changed ``view_budget`` or ``episode_steps`` moves
    the limit with it."""
    import gymnasium as gym
    from gymnasium.envs.registration import load_env_creator

    import liuxing_envs  # noqa: F401  (registers the ids)

    env_kwargs = dict(env_kwargs or {})
    check_env_kwargs(env_id, env_kwargs)  # a name misspelt in a run's config.yml, say
    if BY_ID[env_id].max_episode_steps is not None:
        # The setting that sets the episode's length moves the id's time limit with it.
        length = load_env_creator(gym.spec(env_id).entry_point).episode_length_setting
        if length in env_kwargs:
            make_kwargs.setdefault("max_episode_steps", env_kwargs[length])
    try:
        return gym.make(env_id, **make_kwargs, **env_kwargs)
    except (TypeError, ValueError, FileNotFoundError) as error:
        # What the envs raise for a kwarg value they refuse (a missing mesh file among them).
        raise ConfigError(f"{env_id} with env kwargs {env_kwargs}: {error}") from error


def held_out_env_kwargs(env_id: str, env_kwargs: Mapping) -> dict:
    """A run's env kwargs moved onto the held-out split; a run trained on an explicit list of
    objects (or instruments) is still compared on the held-out split, not on its own list."""
    task = task_for(env_id)
    kept = {key: value for key, value in env_kwargs.items() if key != task.explicit_scene_kwarg}
    return {**kept, **task.held_out_kwargs}


def compare_with_baseline(
    env_id: str,
    policy,
    env_kwargs: Mapping,
    episodes: int,
    seed: int = FINAL_EVAL_SEED,
    reference: bool = True,
) -> dict:
    """``policy``, the task's scripted baseline and (if ``reference`` and the task has one)
    its privileged reference, on the same held-out seeded episodes."""
    task = task_for(env_id)
    held_out = held_out_env_kwargs(env_id, env_kwargs)
    seeds = range(seed, seed + episodes)
    keys = (task.metric, *task.extra_metrics)

    def evaluate(make_policy, extra_kwargs=None) -> dict:
        env = make_env(env_id, {**held_out, **(extra_kwargs or {})})
        try:
            return summarize(run_episodes(env, make_policy(env), seeds, keys), task.metric)
        finally:
            env.close()

    result = {
        "env_id": env_id,
        "split": task.held_out_kwargs,
        "metric": task.metric_label,
        "seeds": [seeds.start, seeds.stop - 1],
        "policy": evaluate(lambda env: policy),
        "baseline": {
            "name": task.baseline,
            **evaluate(task.make_baseline, task.baseline_env_kwargs),
        },
    }
    if reference and task.make_reference is not None:
        result["reference"] = {"name": task.reference, **evaluate(task.make_reference)}
    return result


def format_comparison(result: dict) -> str:
    policy, baseline = result["policy"], result["baseline"]
    split = ", ".join(f"{k}={v}" for k, v in result["split"].items())
    rows = [("trained policy", policy), (baseline["name"], baseline)]
    if "reference" in result:
        rows.append((f"{result['reference']['name']} (privileged)", result["reference"]))
    lines = [f"{result['env_id']} ({split}), {policy['episodes']} episodes: {result['metric']}"]
    for name, row in rows:
        lines.append(f"  {name:<28} {row['mean']:.3f}  95% CI {interval_text(row['ci95'])}")
    lines.append(f"  {'policy - ' + baseline['name']:<28} {policy['mean'] - baseline['mean']:+.3f}")
    return "\n".join(lines)


def run_episodes(
    env,
    policy,
    seeds: Iterable[int],
    keys: Iterable[str],
    deterministic: bool = True,
    recorder=None,
    on_episode: Callable[[], None] | None = None,
) -> list[dict]:
    """One episode per seed; returns per episode its seed, return, length, the final
    ``info`` values of ``keys`` and what ``recorder`` (see :mod:`agents.recorders`) adds.
    ``on_episode`` is called after each episode (a progress bar's update). Sampled actions
    (``deterministic=False``) draw from torch's generator seeded with the episode's seed, and a
    scripted policy is reset with it, so an episode does not depend on what ran before it in
    the process."""
    keys = tuple(keys)
    episodes = []
    for index, seed in enumerate(seeds):
        observation, info = env.reset(seed=int(seed))
        seed_sampling(int(seed), deterministic)
        if hasattr(policy, "reset"):
            policy.reset(seed=int(seed))
        if recorder is not None:
            recorder.begin(env, info)
        total, length, done = 0.0, 0, False
        while not done:
            action, _ = policy.predict(observation, deterministic=deterministic)
            observation, reward, terminated, truncated, info = env.step(action)
            total += float(reward)
            length += 1
            done = terminated or truncated
            if recorder is not None:
                recorder.step(env, float(reward), info)
        episode = {"seed": int(seed), "return": total, "length": length}
        episode.update({key: _scalar(info[key]) for key in keys if key in info})
        if recorder is not None:
            episode.update(recorder.end(env, index, int(seed)))
        episodes.append(episode)
        if on_episode is not None:
            on_episode()
    return episodes


def seed_sampling(seed: int, deterministic: bool) -> None:
    """Seeds torch's generator, which sampled actions draw from, with an episode's seed."""
    if not deterministic:
        import torch  # loaded with the policy already; not needed by baselines

        torch.manual_seed(seed)


def _scalar(value):
    value = np.asarray(value).item()
    return bool(value) if isinstance(value, (bool, np.bool_)) else value


def summarize(episodes: list[dict], metric: str) -> dict:
    """Mean and 95% CI of ``metric`` (Wilson for yes/no figures, bootstrap otherwise), plus
    the mean return and the mean of every other recorded number but the seed and the
    angles."""
    values = [episode[metric] for episode in episodes]
    binary = all(isinstance(value, bool) for value in values)
    mean = float(np.mean(values))
    if binary:
        ci = wilson_interval(int(sum(values)), len(values))
    else:
        ci = bootstrap_ci(values)
    summary = {
        "episodes": len(episodes),
        "metric": metric,
        "mean": mean,
        "ci95": None if ci is None else list(ci),
        "mean_return": float(np.mean([episode["return"] for episode in episodes])),
    }
    for key in episodes[0]:
        values = [episode.get(key) for episode in episodes]
        # An angle's arithmetic mean means nothing (pi and -pi average to 0).
        if key in ("seed", "return", "length", "yaw", "start_yaw", metric) or not all(
            isinstance(value, numbers.Real) for value in values
        ):
            continue
        summary[f"mean_{key}"] = float(np.mean(values))
    return summary


class SB3Policy:
    """A saved SB3 model (and its observation normaliser, if it was trained with one) as a
    single-observation policy."""

    def __init__(self, model, normalizer=None) -> None:
        self.model = model
        self.normalizer = normalizer

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        if self.normalizer is not None:
            observation = self.normalizer.normalize_obs(observation)
        return self.model.predict(observation, state, episode_start, deterministic)

    @classmethod
    def load(cls, algo_class, model_path: Path, normalizer_path: Path | None, device="cpu"):
        """Raises :class:`agents.run_folder.RunFolderError` naming a file that is missing,
        truncated, corrupt or foreign. A model that carries its observation statistics
        (:class:`~liuxing_envs.policy_parts.NormalizedObservations`) takes raw observations:
        a normaliser file beside it is not applied a second time."""
        from liuxing_envs.policy_parts import NormalizedObservations

        model = run_folder.load_model(algo_class, model_path, device=device)
        normalizer = None
        carries_statistics = any(
            isinstance(part, NormalizedObservations) for part in model.policy.modules()
        )
        if (
            not carries_statistics
            and normalizer_path is not None
            and Path(normalizer_path).is_file()
        ):
            normalizer = run_folder.load_normalizer(normalizer_path)
            normalizer.training = False
            if not same_space(model.observation_space, normalizer.observation_space):
                # Caught here, not as a KeyError deep in SB3 in the middle of an evaluation.
                raise run_folder.RunFolderError(
                    f"{str(normalizer_path)!r} normalises observations of "
                    f"{describe_space(normalizer.observation_space)}, but the model "
                    f"{str(model_path)!r} takes {describe_space(model.observation_space)}: "
                    "they come from different runs"
                )
        return cls(model, normalizer)
