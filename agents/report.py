"""Evaluation reports: every contestant (trained policy or baseline) on the same seeded
episodes, summarised with confidence intervals, written as ``report.json`` (every
per-episode figure), ``report.md`` (readable on its own) and figures.

Episode ``k`` of every contestant of an environment uses seed ``seed + k``: the same object
or instrument in the same pose, so comparisons are paired. The report checks it and says so.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from agents import run_folder
from agents.config import marked
from agents.contestants import Contestant, ContestantError, check_fits, make_checked_env, slug
from agents.evaluation import FINAL_EVAL_SEED, run_episodes, summarize, task_for
from agents.report_folder import (
    REPORT_JSON,
    ReportFolderError,
    check_reconstruction_folders,
    check_subfolders,
    earlier_report_files,
    fresh_staging_folder,
    replace_earlier_files,
)
from agents.statistics import (
    interval_text,
    iqm,
    probability_of_improvement,
    probability_of_improvement_ci,
    run_bootstrap_ci,
    stratified_bootstrap_ci,
)
from agents.task_reports import FIGURE_FILES, ci_text, kind_text, report_for
from agents.training import SAVED_CONFIG_DEFAULTS
from agents.video import record_videos
from liuxing_envs.output_folders import OutputFolderError, prepare_output_folder

DEFAULT_EPISODES = 100
DEFAULT_RECONSTRUCT_EPISODES = 20
DEFAULT_SAVE_EPISODES = 3
DEFAULT_VIDEO_EPISODES = 2
REPORT_MD = "report.md"


@dataclass
class Settings:
    episodes: int = DEFAULT_EPISODES
    seed: int = FINAL_EVAL_SEED
    deterministic: bool = True
    #: ViewPlanning: reconstruct (Poisson, ~1-3 s) the first this many episodes of each
    reconstruct_episodes: int = DEFAULT_RECONSTRUCT_EPISODES
    #: ...and save the .ply files and a picture of the first this many of those
    save_episodes: int = DEFAULT_SAVE_EPISODES
    video_episodes: int = 0
    progress: bool = False
    command: str = ""


def evaluate(contestants: Sequence[Contestant], settings: Settings, out: Path) -> dict:
    """Run every contestant, write the report into ``out`` and return its JSON document."""
    started = time.perf_counter()
    envs = _open_envs(contestants)  # fails on a misfit model before any episode runs
    out = Path(out)
    try:
        prepare_output_folder(
            out, files=(REPORT_JSON, REPORT_MD, run_folder.GIT_DIFF, *FIGURE_FILES)
        )
        check_subfolders(out)
        # Read now: a stop leaves them all in place.
        earlier_files = earlier_report_files(out, FIGURE_FILES)
        if settings.reconstruct_episodes and settings.save_episodes:
            labels = [c.label for c in contestants if report_for(c.env_id).reconstructs]
            check_reconstruction_folders(out, labels, earlier_files)
    except (OutputFolderError, ReportFolderError) as error:
        for env in envs.values():
            env.close()
        raise ContestantError(
            f"cannot write the report into {str(out)!r}: {marked(error)}"
        ) from error
    staging = fresh_staging_folder(out)
    source = run_folder.Source.of_checkout()  # as it starts: edits while it runs do not count
    seeds = range(settings.seed, settings.seed + settings.episodes)
    progress = _progress_bar(len(contestants) * settings.episodes, settings.progress)
    results = []
    try:
        for contestant in contestants:
            progress.set_description(contestant.label[:30])
            env = envs[_env_key(contestant)]
            task = task_for(contestant.env_id)
            recorder = _recorder(contestant, settings, staging)
            episodes = run_episodes(
                env,
                contestant.make_policy(env),
                seeds,
                (task.metric, *task.extra_metrics),
                deterministic=settings.deterministic,
                recorder=recorder,
                on_episode=progress.update,
            )
            results.append(
                {
                    **_describe(contestant),
                    "limits": getattr(recorder, "limits", {}),
                    "summary": _summary(contestant.env_id, episodes),
                    "episodes": episodes,
                }
            )
    finally:
        progress.close()
        for env in envs.values():
            env.close()
    report = {
        "created": datetime.datetime.now().isoformat(timespec="seconds"),
        "command": settings.command,
        "settings": asdict(settings),
        "seeds": [seeds.start, seeds.stop - 1],
        "versions": run_folder.library_versions(),
        "git_commit": source.commit,
        "environments": {
            env_id: _environment_section(env_id, [r for r in results if r["env_id"] == env_id])
            for env_id in dict.fromkeys(c.env_id for c in contestants)
        },
    }
    # The figures and videos come after every episode: write the numbers first, so that a
    # failure drawing them loses nothing.
    report["wall_seconds"] = round(time.perf_counter() - started, 1)
    for problem in replace_earlier_files(out, earlier_files):
        print(f"warning: {problem}", file=sys.stderr)
    _write_report(report, out, source)
    figures = write_figures(report, out, settings)
    if settings.video_episodes:
        figures["videos"] = [
            str(path.relative_to(out))
            for path in record_videos(
                contestants, seeds[: settings.video_episodes], out, settings.deterministic
            )
        ]
    report["figures"] = figures
    report["wall_seconds"] = round(time.perf_counter() - started, 1)
    _write_report(report, out, source)
    return report


def _write_report(report: dict, out: Path, source: run_folder.Source) -> None:
    """report.json and report.md of ``report``, and the patch of a dirty checkout beside them
    (named in both). An earlier report's report.md goes first: a stop between the files must
    not leave it beside the new numbers or patch it contradicts."""
    (out / REPORT_MD).unlink(missing_ok=True)
    (out / run_folder.GIT_DIFF).unlink(missing_ok=True)
    report.update(source.record(out))  # the commit stays where it is; git_diff comes last
    text = json.dumps(report, indent=1, default=_json_default)
    run_folder.write_text_atomically(out / REPORT_JSON, text)
    run_folder.write_text_atomically(out / REPORT_MD, markdown(report))


# ---------------------------------------------------------------------- running
def _env_key(contestant: Contestant) -> tuple:
    return contestant.env_id, json.dumps(contestant.env_kwargs, sort_keys=True, default=str)


def _open_envs(contestants: Sequence[Contestant]) -> dict:
    """One environment per (id, kwargs), shared by the contestants that use it; every policy
    is checked against its environment here."""
    envs: dict = {}
    try:
        for contestant in contestants:
            key = _env_key(contestant)
            if key not in envs:
                envs[key] = make_checked_env(contestant)
            else:
                check_fits(contestant, envs[key])
    except BaseException:
        for env in envs.values():
            env.close()
        raise
    return envs


def _recorder(contestant: Contestant, settings: Settings, reconstructions: Path):
    return report_for(contestant.env_id).make_recorder(
        settings, reconstructions / slug(contestant.label)
    )


def _progress_bar(total: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, unit="episode", disable=not enabled, dynamic_ncols=True)


#: What a run's config.yml says about how it was trained, seed aside: runs that differ in any
#: of these are different methods, not training seeds of one.
TRAINING_SETTINGS = (
    "n_timesteps", "n_envs", "policy", "normalize", "hyperparams", "demonstrations",
    "start_curriculum", "init_from", "env_kwargs", "eval_env_kwargs", "eval_freq",
    "eval_episodes",
)  # fmt: skip


def _training_settings(config: dict | None) -> dict | None:
    """The TRAINING_SETTINGS of a run's config.yml, comparable across runs: an older
    config.yml's missing keys take the defaults a resume gives them, an empty mapping counts as
    none, and a trained start is named by its model's hash (its path differs per run)."""
    if not config:
        return None
    config = {**SAVED_CONFIG_DEFAULTS, **config}
    settings = {key: config.get(key) or None for key in TRAINING_SETTINGS}
    start = settings["init_from"]
    if start is not None:
        settings["init_from"] = {
            "sha256": start.get("sha256"),
            "replay_buffer": bool(start.get("replay_buffer")),
        }
    return settings


def _describe(contestant: Contestant) -> dict:
    config = contestant.config
    return {
        "label": contestant.label,
        "group": contestant.group,
        "kind": contestant.kind,
        "env_id": contestant.env_id,
        "env_kwargs": contestant.env_kwargs,
        "source": contestant.source,
        "model_file": contestant.model_file,
        # A path names a file that a later training run may overwrite; the hash names its bytes.
        "model_sha256": None
        if contestant.model_file is None
        else hashlib.sha256(Path(contestant.model_file).read_bytes()).hexdigest(),
        "training_seed": contestant.seed,
        "training_command": (config or {}).get("command"),
        "training_settings": _training_settings(config),
    }


# ---------------------------------------------------------------------- statistics
def _summary(env_id: str, episodes: list[dict]) -> dict:
    task = task_for(env_id)
    summary = summarize(episodes, task.metric)
    summary.update(report_for(env_id).summary(episodes))
    return summary


def _scores(result: dict, metric: str) -> np.ndarray:
    return np.array([float(e[metric]) for e in result["episodes"]])


def _without(kwargs: dict, keys) -> dict:
    return {key: value for key, value in kwargs.items() if key not in keys}


def _environment_section(env_id: str, results: list[dict]) -> dict:
    task = task_for(env_id)
    scene_keys = report_for(env_id).scene_keys
    scenes = [
        [tuple(map(str, (e.get(k) for k in scene_keys))) for e in r["episodes"]] for r in results
    ]
    section = {
        "metric": task.metric,
        "metric_label": task.metric_label,
        "baseline": task.baseline,
        "paired": all(s == scenes[0] for s in scenes),
        "contestants": results,
        "aggregates": [],
        "aggregate_notes": [],
    }
    baseline = next((r for r in results if r["label"] == task.baseline), None)
    # Training seeds of one method: the same algorithm trained the same way in the same env
    # settings.
    groups: dict[tuple[str, str, str], list[int]] = {}
    for index, result in enumerate(results):
        if result["kind"] == "policy":
            env_settings = json.dumps(result["env_kwargs"], sort_keys=True, default=str)
            training = json.dumps(result.get("training_settings"), sort_keys=True, default=str)
            groups.setdefault((result["group"], env_settings, training), []).append(index)
    for key, indices in groups.items():
        group, env_settings, _ = key
        members = [results[i] for i in indices]
        if len(members) < 2:
            others = [other for other in groups if other[0] == group and other != key]
            if others:
                differs = (
                    "other training settings (env kwargs, hyper-parameters, steps or evaluation)"
                    if any(other[1] == env_settings for other in others)
                    else "other env kwargs"
                )
                section["aggregate_notes"].append(
                    f"{members[0]['label']}: not aggregated with the other {group} runs, it ran "
                    f"with {differs}"
                )
            continue
        seeds = [m["training_seed"] for m in members]
        labels = ", ".join(m["label"] for m in members)
        if None in seeds or len(set(seeds)) < len(seeds):
            section["aggregate_notes"].append(
                f"{labels}: not aggregated as training seeds of {group}, their training seeds "
                f"{seeds} are unknown or repeated"
            )
            continue
        if any(scenes[i] != scenes[indices[0]] for i in indices):
            section["aggregate_notes"].append(
                f"{labels}: not aggregated as training seeds of {group}, they saw different scenes"
            )
            continue
        scores = np.stack([_scores(m, task.metric) for m in members])
        aggregate = {
            "group": group,
            "runs": [m["label"] for m in members],
            "iqm": None,
            "iqm_ci95": None,
            "mean": float(scores.mean()),
            "mean_ci95": list(stratified_bootstrap_ci(scores, np.mean)),
            # Whole seeds resampled: what a new set of seeds could do on these episodes.
            "iqm_seed_ci95": None,
            "mean_seed_ci95": list(run_bootstrap_ci(scores, np.mean)),
        }
        if not task.metric_is_binary:
            aggregate["iqm"] = iqm(scores)
            aggregate["iqm_ci95"] = list(stratified_bootstrap_ci(scores, iqm))
            aggregate["iqm_seed_ci95"] = list(run_bootstrap_ci(scores, iqm))
        if baseline is not None and section["paired"]:
            # The baseline ran in the first policy's env kwargs (plus what it reads itself):
            # another group's, say another view budget, would compare unlike episodes.
            own = task.baseline_env_kwargs
            if _without(members[0]["env_kwargs"], own) == _without(baseline["env_kwargs"], own):
                reference = _scores(baseline, task.metric)[None]
                aggregate["probability_of_improvement"] = {
                    "over": task.baseline,
                    "value": probability_of_improvement(scores, reference),
                    "ci95": list(probability_of_improvement_ci(scores, reference)),
                }
            else:
                aggregate["no_improvement_because"] = (
                    f"{task.baseline} ran in other env kwargs than these runs"
                )
        section["aggregates"].append(aggregate)
    return section


# ---------------------------------------------------------------------- figures
def write_figures(report: dict, out: Path, settings: Settings) -> dict:
    """The report's figures under ``out``, by name (the report links them)."""
    figures: dict = {}
    for env_id, section in report["environments"].items():
        figures.update(report_for(env_id).figures(out, section["contestants"], settings))
    return figures


def _json_default(value):
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


# ---------------------------------------------------------------------- markdown
def markdown(report: dict) -> str:
    settings = report["settings"]
    first, last = report["seeds"]
    lines = [
        "# Evaluation report",
        "",
        f"Created {report['created']} by `{report['command']}` in "
        f"{report['wall_seconds'] / 60:.1f} min",
        f"(git {report['git_commit'] or 'unknown'}"
        + (f" with the changes in `{report['git_diff']}`" if report.get("git_diff") else "")
        + "; "
        + ", ".join(f"{k} {v}" for k, v in report["versions"].items() if k != "platform")
        + ").",
        "",
        f"Each contestant ran the same {settings['episodes']} episodes, seeds {first}-{last} "
        f"({'deterministic' if settings['deterministic'] else 'stochastic'} actions for trained "
        "policies): "
        + (
            "episode k of every contestant has the same object or instrument in the same "
            "pose, so differences are paired. "
            if all(section["paired"] for section in report["environments"].values())
            else "where contestants share their env kwargs, episode k has the same object or "
            "instrument in the same pose (see each environment's note on pairing). "
        )
        + "95% intervals: percentile bootstrap of the mean "
        "(10,000 resamples) for continuous figures, Wilson for rates. Per-episode figures are "
        f"in `{REPORT_JSON}`.",
    ]
    for env_id, section in report["environments"].items():
        lines += ["", f"## {env_id}", ""]
        lines.append(
            "Paired: every contestant saw the same scenes."
            if section["paired"]
            else "**Not paired**: contestants saw different scenes (their env kwargs differ); "
            "compare them with care."
        )
        lines.append("")
        for r in section["contestants"]:
            extra = f", seed {r['training_seed']}" if r["training_seed"] is not None else ""
            model = r.get("model_file")  # absent from reports written before it was recorded
            named = model and Path(model).name != Path(r["source"]).name  # a run folder's
            scored = f" (scored: `{Path(model).name}`)" if named else ""
            lines.append(
                f"- **{r['label']}** ({kind_text(r)}{extra}): `{r['source']}`{scored}, env kwargs "
                f"`{json.dumps(r['env_kwargs'])}`"
            )
        lines.append("")
        lines += report_for(env_id).tables(section)
        for note in section.get("aggregate_notes", []):
            lines += ["", f"Not aggregated: {note}."]
        if section["aggregates"]:
            lines += [
                "",
                f"Across training seeds (IQM and mean of the per-episode {section['metric_label']} "
                "over all seeds' episodes). Two 95% intervals: *seeds*, resampling whole seeds "
                "(how much a new set of seeds could move the figure on these episodes), and "
                "*stratified*, resampling seeds within each episode as in Agarwal et al. 2021 "
                "(narrower: it mixes seeds within a resample, so most of their spread drops out; "
                "for comparison with published figures). P(improvement)'s interval resamples "
                "seeds within each episode too. All three hold these episodes fixed, and with "
                "a handful of seeds the *seeds* interval is little wider than their own range "
                "(2 seeds give 3 distinct resamples):",
                "",
                "| method | runs | IQM [seeds] [stratified] | mean [seeds] [stratified] | "
                f"P(improvement over {section['baseline']}) |",
                "|---|---|---|---|---|",
            ]
            for a in section["aggregates"]:
                poi = a.get("probability_of_improvement")
                iqm_text = "- (yes/no outcomes)"
                if a["iqm"] is not None:
                    iqm_text = (
                        f"{ci_text({'mean': a['iqm'], 'ci95': a['iqm_seed_ci95']})} "
                        f"{interval_text(a['iqm_ci95'])}"
                    )
                poi_text = "-"
                if poi:
                    poi_text = ci_text({"mean": poi["value"], "ci95": poi["ci95"]}, digits=2)
                elif "no_improvement_because" in a:
                    poi_text = f"- ({a['no_improvement_because']})"
                lines.append(
                    f"| {a['group']} | {len(a['runs'])} | {iqm_text} | "
                    f"{ci_text({'mean': a['mean'], 'ci95': a['mean_seed_ci95']})} "
                    f"{interval_text(a['mean_ci95'])} | {poi_text} |"
                )
    figures = report.get("figures", {})
    if figures:
        lines += ["", "## Figures", ""]
        for name, value in figures.items():
            for path in value if isinstance(value, list) else [value]:
                if path is None:
                    continue
                if str(path).endswith(".png"):
                    lines.append(f"![{name}]({path})")
                else:
                    lines.append(f"- [{path}]({path})")
    return "\n".join(lines) + "\n"


def summary_lines(report: dict) -> str:
    """The headline figure of every contestant, for the terminal."""
    lines = []
    for env_id, section in report["environments"].items():
        lines.append(
            f"{env_id}: {section['metric_label']} over {report['settings']['episodes']} episodes"
        )
        for result in section["contestants"]:
            summary = result["summary"]
            lines.append(
                f"  {result['label']:<32} {summary['mean']:.3f}  95% CI "
                f"{interval_text(summary['ci95'])}  ({kind_text(result)})"
            )
    return "\n".join(lines)


def command_line() -> str:
    return " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])
