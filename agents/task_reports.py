"""What an evaluation report shows of each task, declared once per task family.

A :class:`TaskReport` holds the hooks the harness (:mod:`agents.report`, :mod:`agents.video`,
evaluate.py) calls for a task: what it records of each episode, the figures it adds to an
episode summary, its markdown tables, its figures and its video read-out. :data:`REPORTS`
declares them by task family and :func:`report_for` looks one up; what evaluating a task
means (its headline figure, splits, baselines) is its :class:`agents.evaluation.Task`. A new
task adds its functions and one entry here, and changes no harness file.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agents import plotting
from agents.contestants import slug
from agents.recorders import COVERAGE_LEVELS, GraspRecorder, ViewPlanningRecorder
from agents.report_folder import (
    RECONSTRUCTIONS_FOLDER,
)
from agents.statistics import bootstrap_ci, interval_text, wilson_interval
from liuxing_envs.registration import family

#: ViewPlanning episodes are a handful of views: each is held on screen this long in a video.
VIEW_SECONDS = 1.0
#: Episodes per contestant drawn in the grasp report's force-trace figure.
DEFAULT_TRACE_EPISODES = 5


@dataclass(frozen=True)
class TaskReport:
    """The hooks a report calls for one task family.

    ``settings`` is the report's :class:`agents.report.Settings`; ``results`` the contestants
    of one environment as report.json holds them (``label``, ``summary``, ``episodes``,
    ``limits``); ``section`` an environment's section of report.json."""

    #: the recorded per-episode keys that place an episode's scene (its object or instrument
    #: and its pose): contestants whose episodes agree on them are paired
    scene_keys: tuple[str, ...]
    #: ``(settings, save_dir) -> recorder`` (see :mod:`agents.recorders`); ``save_dir`` is the
    #: contestant's folder for saved reconstructions
    make_recorder: Callable
    #: ``episodes -> dict``: the task's figures added to an episode summary
    summary: Callable
    #: ``section -> markdown lines``: the task's tables
    tables: Callable
    #: ``(out, results, settings) -> {name: path or paths under out}``: writes the figures
    figures: Callable
    #: the files ``figures`` writes at the report folder's top (an earlier report's are
    #: replaced)
    figure_files: tuple[str, ...]
    #: ``(info, seconds) -> lines``: a video frame's text read-out
    readout: Callable
    #: ``(env, fps) -> (repeat, dt)``: how many video frames show each step's picture, and the
    #: seconds one step takes (0 where time is not the point)
    frame_timing: Callable
    #: whether episodes are scored by reconstruction (evaluate.py's --reconstruct-episodes)
    reconstructs: bool = False


COVERAGE_FIGURE = "coverage_vs_views.png"
FORCE_TRACES_FIGURE = "force_traces.png"
GRASP_OUTCOMES_FIGURE = "grasp_outcomes.png"
PEAK_FORCES_FIGURE = "peak_forces.png"


# ---------------------------------------------------------------------- shared helpers
def mean_ci(values) -> dict | None:
    """Mean, bootstrap 95% interval and count of the values that are not ``None``."""
    values = [v for v in values if v is not None]
    if not values:
        return None
    ci = bootstrap_ci(values)
    return {
        "mean": float(np.mean(values)),
        "ci95": None if ci is None else list(ci),
        "n": len(values),
    }


def rate(flags) -> dict:
    """Rate, Wilson 95% interval and count of the true ``flags``."""
    flags = [bool(flag) for flag in flags]
    low, high = wilson_interval(sum(flags), len(flags))
    return {"rate": sum(flags) / len(flags), "ci95": [low, high], "count": sum(flags)}


def ci_text(entry: dict | None, scale: float = 1.0, digits: int = 3) -> str:
    if entry is None:
        return "-"
    return f"{entry['mean'] * scale:.{digits}f} {interval_text(entry['ci95'], scale, digits)}"


def percent_text(entry: dict) -> str:
    low, high = entry["ci95"]
    return f"{100 * entry['rate']:.0f}% [{100 * low:.0f}, {100 * high:.0f}]"


def kind_text(result: dict) -> str:
    return {"policy": "trained", "baseline": "baseline", "privileged": "privileged"}[result["kind"]]


def relative(path: Path | None, out: Path) -> str | None:
    return None if path is None else str(Path(path).relative_to(out))


# ---------------------------------------------------------------------- ViewPlanning
def view_planning_recorder(settings, save_dir: Path) -> ViewPlanningRecorder:
    return ViewPlanningRecorder(
        reconstruct_episodes=settings.reconstruct_episodes,
        save_dir=save_dir,
        save_episodes=min(settings.save_episodes, settings.reconstruct_episodes),
    )


def view_planning_summary(episodes: list[dict]) -> dict:
    longest = max(len(e["coverage_after_view"]) for e in episodes)
    # An episode that ended early (terminate_on_success) keeps its last coverage.
    curves = np.array(
        [
            np.pad(c, (0, longest - len(c)), mode="edge")
            for c in (e["coverage_after_view"] for e in episodes)
        ]
    )
    summary = {
        "coverage_after_view": [mean_ci(curves[:, k]) for k in range(longest)],
        "refused_views": mean_ci([e["refused_views"] for e in episodes]),
        "joint_path_length": mean_ci([e["joint_path_length"] for e in episodes]),
        "motion_cost": mean_ci([e["motion_cost"] for e in episodes]),
    }
    for level in COVERAGE_LEVELS:
        key = f"views_to_{round(100 * level)}"
        views = [e[key] for e in episodes]
        summary[key] = {
            "reached": rate([v is not None for v in views]),
            "views_if_reached": mean_ci(views),
        }
    for key in ("chamfer", "fscore", "precision", "completeness"):
        summary[key] = mean_ci([e[key] for e in episodes if key in e])
    return summary


def view_planning_tables(section: dict) -> list[str]:
    results = section["contestants"]
    levels = [f"views_to_{round(100 * level)}" for level in COVERAGE_LEVELS]
    lines = [
        "| contestant | kind | final coverage [95% CI] | "
        + " | ".join(f"reached {k[-2:]}% (views if reached)" for k in levels)
        + " | Chamfer mm [95% CI] | F-score [95% CI] | joint path rad | refused views |",
        "|---|---|---|" + "---|" * len(levels) + "---|---|---|---|",
    ]
    for r in results:
        s = r["summary"]
        reached = []
        for key in levels:
            entry = s[key]
            views = entry["views_if_reached"]
            reached.append(
                f"{100 * entry['reached']['rate']:.0f}%"
                + (f" ({views['mean']:.2f})" if views else "")
            )
        final = ci_text({"mean": s["mean"], "ci95": s["ci95"]})
        lines.append(
            f"| {r['label']} | {kind_text(r)} | {final} | "
            + " | ".join(reached)
            + f" | {ci_text(s['chamfer'], 1000, 2)} | {ci_text(s['fscore'])}"
            + f" | {s['joint_path_length']['mean']:.2f} | {s['refused_views']['mean']:.2f} |"
        )
    budget = max(len(r["summary"]["coverage_after_view"]) for r in results)
    lines += [
        "",
        "Coverage after each view (mean; view 0 is the start view taken at reset):",
        "",
        "| contestant | " + " | ".join(f"view {k}" for k in range(budget)) + " |",
        "|---|" + "---|" * budget,
    ]
    for r in results:
        curve = r["summary"]["coverage_after_view"]
        lines.append(
            f"| {r['label']} | " + " | ".join(f"{entry['mean']:.3f}" for entry in curve) + " |"
        )
    lines += reconstruction_note(results)
    return lines


def reconstruction_note(results: list[dict]) -> list[str]:
    """What the Chamfer and F-score columns average: the episodes reconstructed, less, for
    Chamfer, those whose scan fused nothing (no finite distance), named per contestant."""
    reconstructed = max(sum("chamfer" in e for e in r["episodes"]) for r in results)
    if not reconstructed:
        return []
    note = (
        f"Chamfer distance and F-score: open3d Poisson reconstructions of the first "
        f"{reconstructed} episodes of each contestant, against dense ground-truth surface "
        "samples (τ = 1% of the object's bounding-box diagonal)."
    )
    with_distance = {r["label"]: (r["summary"]["chamfer"] or {"n": 0})["n"] for r in results}
    fewer = [f"{label} {n}" for label, n in with_distance.items() if n < reconstructed]
    if fewer:
        note += (
            " A scan that fused nothing has no Chamfer distance (its F-score is 0), so the "
            f"Chamfer column averages fewer: {', '.join(fewer)} of {reconstructed}."
        )
    return ["", note]


def view_planning_figures(out: Path, results: list[dict], settings) -> dict:
    figures = {
        "coverage_vs_views": relative(
            plotting.plot_coverage_curves(
                out / COVERAGE_FIGURE,
                {r["label"]: r["summary"]["coverage_after_view"] for r in results},
            ),
            out,
        )
    }
    pictures = []
    saved = min(settings.save_episodes, settings.reconstruct_episodes)
    saved_seeds = range(settings.seed, settings.seed + saved)
    for result in results:
        folder = out / RECONSTRUCTIONS_FOLDER / slug(result["label"])
        picture = plotting.plot_reconstructions(
            folder / "reconstructions.png", folder, result["label"], saved_seeds
        )
        if picture is not None:
            pictures.append(relative(picture, out))
    figures["reconstructions"] = pictures
    return figures


def view_planning_readout(info: dict, seconds: float) -> list[str]:
    lines = [f"view {info['views_used']}  coverage {info['coverage']:.3f}"]
    if info.get("refused"):
        lines.append("view refused")
    return lines


def view_planning_frame_timing(env, fps: float) -> tuple[int, float]:
    return max(1, round(VIEW_SECONDS * fps)), 0.0


# ---------------------------------------------------------------------- InstrumentGrasp
def grasp_recorder(settings, save_dir: Path) -> GraspRecorder:
    return GraspRecorder()


def grasp_summary(episodes: list[dict]) -> dict:
    peaks = np.array([e["peak_force"] for e in episodes])
    return {
        "success": rate([e["is_success"] for e in episodes]),
        "hard_limit_exceeded": rate([e["hard_limit_exceeded"] for e in episodes]),
        "over_force_limit": rate([e["force_violations"] > 0 for e in episodes]),
        "peak_force_quantiles": {
            q: float(np.quantile(peaks, float(q))) for q in ("0.5", "0.9", "1.0")
        },
        "max_lift": mean_ci([e["max_lift"] for e in episodes]),
        "time_to_lift": mean_ci([e["time_to_lift"] for e in episodes]),
    }


def grasp_tables(section: dict) -> list[str]:
    lines = [
        "| contestant | kind | success [95% CI] | hard-limit stops | episodes over the force "
        "limit | peak force N (median / p90 / max) | max lift cm | time to lift s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in section["contestants"]:
        s = r["summary"]
        q = s["peak_force_quantiles"]
        lift = s["time_to_lift"]
        lines.append(
            f"| {r['label']} | {kind_text(r)} | {percent_text(s['success'])} | "
            f"{s['hard_limit_exceeded']['count']} | {s['over_force_limit']['count']} | "
            f"{q['0.5']:.1f} / {q['0.9']:.1f} / {q['1.0']:.1f} | "
            f"{100 * s['max_lift']['mean']:.1f} | "
            + (f"{lift['mean']:.2f} (n={lift['n']})" if lift else "-")
            + " |"
        )
    return lines


def grasp_figures(out: Path, results: list[dict], settings) -> dict:
    limits = results[0]["limits"]
    traces = {
        r["label"]: [e["force_trace"] for e in r["episodes"][:DEFAULT_TRACE_EPISODES]]
        for r in results
    }
    return {
        "force_traces": relative(
            plotting.plot_force_traces(out / FORCE_TRACES_FIGURE, traces, **limits), out
        ),
        "grasp_outcomes": relative(
            plotting.plot_grasp_outcomes(
                out / GRASP_OUTCOMES_FIGURE, {r["label"]: r["summary"] for r in results}
            ),
            out,
        ),
        "peak_forces": relative(
            plotting.plot_peak_forces(
                out / PEAK_FORCES_FIGURE,
                {r["label"]: [e["peak_force"] for e in r["episodes"]] for r in results},
                limits["force_limit"],
                limits["hard_limit"],
            ),
            out,
        ),
    }


def grasp_readout(info: dict, seconds: float) -> list[str]:
    return [
        f"t {seconds:.2f} s  grip {info.get('grip_force', 0.0):.1f} N  "
        f"peak {info.get('peak_force', 0.0):.1f} N",
        f"lift {100 * info.get('lift_height', 0.0):.1f} cm"
        + ("  grasped" if info.get("grasped") else ""),
    ]


def grasp_frame_timing(env, fps: float) -> tuple[int, float]:
    return 1, env.unwrapped.dt


# ---------------------------------------------------------------------- declarations
#: What a report shows, by task family (every version and variant of a task).
REPORTS = {
    "ViewPlanning": TaskReport(
        scene_keys=("object", "scale", "position", "yaw"),
        make_recorder=view_planning_recorder,
        summary=view_planning_summary,
        tables=view_planning_tables,
        figures=view_planning_figures,
        figure_files=(COVERAGE_FIGURE,),
        readout=view_planning_readout,
        frame_timing=view_planning_frame_timing,
        reconstructs=True,
    ),
    "InstrumentGrasp": TaskReport(
        scene_keys=("instrument", "start_position", "start_yaw"),
        make_recorder=grasp_recorder,
        summary=grasp_summary,
        tables=grasp_tables,
        figures=grasp_figures,
        figure_files=(FORCE_TRACES_FIGURE, GRASP_OUTCOMES_FIGURE, PEAK_FORCES_FIGURE),
        readout=grasp_readout,
        frame_timing=grasp_frame_timing,
    ),
}


#: Every task's figure files.
FIGURE_FILES = tuple(name for report in REPORTS.values() for name in report.figure_files)


def report_for(env_id: str) -> TaskReport:
    return REPORTS[family(env_id)]
