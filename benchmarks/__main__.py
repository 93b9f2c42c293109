"""Speed benchmarks of liuxing_envs: one entry point, one report.

Run: ``MUJOCO_GL=egl python -m benchmarks`` (about 20 minutes on 2 cores). It writes
``benchmarks/RESULTS.md`` and the raw figures in ``benchmarks/RESULTS.json``.
``--quick`` runs every section briefly (a smoke test of the benchmark, not a measurement);
``--sections`` picks some.
Run it on a quiet machine: every figure is wall-clock time.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from benchmarks import kernels, peers, physics, scaling, throughput, time_split, training  # noqa: E402
from benchmarks.isolated import describe_cores, machine, spread  # noqa: E402
from benchmarks.report_files import check_writable, report_paths  # noqa: E402
from benchmarks.throughput import GRASP, GRASP_STATE, VIEW_DEFAULT, VIEW_PLANNING, Config  # noqa: E402

SECTIONS = ("throughput", "split", "kernels", "physics", "peers", "scaling", "training")
DEFAULT_OUT = Path(__file__).parent / "RESULTS.md"

#: Targets of the benchmark issue, as ratios measured in one run.
VIEW_TARGET = 1000.0  # view-steps/s, default mode, 64x64, one core
VIEW_PEER_RATIO = 7.0  # x FetchPickAndPlace-v4 with 84x84 rendering
GRASP_PEER_RATIO = 1.0  # x FetchPickAndPlace-v4 without rendering (state obs)
GRASP_PHYSICS_FRACTION = 0.8
ASYNC_TWO_WORKER_SPEEDUP = 1.6


def _parse(argv: list[str] | None) -> argparse.Namespace:
    default_md = f"{DEFAULT_OUT.parent.name}/{DEFAULT_OUT.name}"
    default_json = f"{DEFAULT_OUT.parent.name}/{DEFAULT_OUT.with_suffix('.json').name}"
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks",
        description=f"{__doc__.splitlines()[0]} Writes the Markdown report to --out (default "
        f"{default_md}) and the raw figures beside it, the same path with the suffix .json "
        f"(default {default_json}), replacing both.",
    )
    parser.add_argument("--quick", action="store_true", help="short runs: a smoke test")
    parser.add_argument(
        "--sections",
        default=None,
        help=f"comma-separated subset of {','.join(SECTIONS)} (default: all)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=DEFAULT_OUT,
        help=f"the Markdown report (default: {default_md}); the raw figures are written to the "
        f"same path with the suffix .json (default: {default_json}), so an --out ending in "
        ".json is refused. A missing folder is created.",
    )
    parser.add_argument(
        "--update",
        action="store_true",
        help="re-measure only --sections into the report at --out (its .json), keeping the "
        "others; the report then says which sections were re-measured, when",
    )
    args = parser.parse_args(argv)
    named = args.sections is not None
    args.sections = _sections(parser, args.sections)
    args.json = report_paths(parser, args.out)
    args.earlier = None
    if args.update:
        if not named:
            parser.error("--update re-measures the --sections it is given; name them")
        args.earlier = _earlier(parser, args)
    check_writable(parser, args.out, args.json)
    return args


def _sections(parser: argparse.ArgumentParser, text: str | None) -> list[str]:
    """The sections --sections names; an empty or malformed list is refused, not read as
    "all" or "none" (either would replace the whole report)."""
    if text is None:
        return list(SECTIONS)
    allowed = f"name one or more of {','.join(SECTIONS)}, comma-separated"
    names = [s.strip() for s in text.split(",")]
    if not any(names):
        parser.error(f"--sections {text!r} names no section; {allowed} (or leave it out for all)")
    if not all(names):
        parser.error(f"--sections {text!r} has an empty name between commas; {allowed}")
    unknown = sorted(set(names) - set(SECTIONS))
    if unknown:
        parser.error(f"unknown section(s) {unknown}; choose from {list(SECTIONS)}")
    return names


def _earlier(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict:
    """The earlier report's results that --update keeps, once they are known to come from
    this machine, be of the same kind of run, and make a report with the new sections (a
    malformed file fails here, not after the measurements)."""
    path = args.json
    try:
        earlier = json.loads(path.read_text())
    except OSError as error:
        parser.error(f"--update needs the earlier report's {path}: {error.strerror or error}")
    except ValueError as error:  # not JSON, or not UTF-8 text
        parser.error(f"--update: the earlier report's {path} is not valid JSON ({error})")
    if not isinstance(earlier, dict) or not isinstance(earlier.get("machine"), dict):
        parser.error(f"--update: {path} is not a benchmark report's JSON (no machine description)")
    if bool(earlier.get("quick")) != args.quick:
        parser.error(
            f"{path} is {'a quick' if args.quick is False else 'a full'} run's; "
            "--update keeps runs of one kind"
        )
    mine, theirs = machine(), earlier["machine"]
    theirs = {"usable_cores": theirs.get("cores"), **theirs}  # reports before the field
    different = [
        k for k in ("cpu", "cores", "usable_cores", "memory") if mine.get(k) != theirs.get(k)
    ]
    if different:
        parser.error(
            f"{path} was measured on another machine ({', '.join(different)} differ): "
            "its targets compare sections, which must come from one machine"
        )
    # A dry run of the report of what is kept: any section, field or machine entry that
    # report() cannot read is found now rather than after the first measurement, whatever
    # error the malformed data raises.
    stamp = {"date": "", "commit": "", "command": ""}
    try:
        report(_keep(earlier, args.sections, stamp), "")
    except Exception as error:
        parser.error(
            f"--update: {path} is not a benchmark report's JSON in the shape this version "
            f"writes ({type(error).__name__}: {error}); re-measure without --update to "
            "replace it"
        )
    return earlier


def _row(*cells) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _table(header: tuple, rows: list[tuple]) -> list[str]:
    return [_row(*header), _row(*("---" for _ in header)), *(_row(*r) for r in rows), ""]


def _number(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _rate(result: dict) -> str:
    return f"{result['median']:.0f}"


def _progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run(
    sections: list[str],
    quick: bool,
    on_progress=lambda results: None,
    earlier: dict | None = None,
    command: str = "",
) -> dict:
    """Every measurement of the chosen sections, as plain data; ``on_progress(results)`` is
    called after each measurement (so a failure late in a long run loses nothing before it).
    With ``earlier`` (a report's results), its other sections and machine are kept, and the
    sections measured again are listed under ``remeasured`` with ``command``."""
    scale, repeats = (0.1, 1) if quick else (1.0, 3)
    current = machine()
    if earlier is None:
        results: dict = {"machine": current, "quick": quick, "command": command}
    else:
        stamp = {"date": current["date"], "commit": current["commit"], "command": command}
        results = _keep(earlier, sections, stamp)
    # Sections started but not finished: a report saved mid-run, or left by a run that
    # failed, says which of its tables are missing or partial.
    unfinished = set(sections) | set(results.get("unfinished", ()))
    results["unfinished"] = [section for section in SECTIONS if section in unfinished]

    def finished(section: str) -> None:
        if section in sections:
            results["unfinished"].remove(section)
            on_progress(results)

    if "throughput" in sections:
        results["throughput"] = []
        for config in throughput.CONFIGS:
            _progress(f"throughput: {config.env_id} {config.label}")
            measured = throughput.measure(config, repeats, scale)
            results["throughput"].append(
                {"env_id": config.env_id, "mode": config.label, **measured}
            )
            on_progress(results)
    finished("throughput")
    if "split" in sections:
        results["split"] = []
        for config in time_split.SPLIT_CONFIGS:
            _progress(f"time split: {config.env_id} {config.label}")
            steps = max(40, int((400 if config.env_id == VIEW_PLANNING else 1000) * scale))
            measured = time_split.measure(config, steps)
            results["split"].append({"env_id": config.env_id, "mode": config.label, **measured})
            on_progress(results)
    finished("split")
    if "kernels" in sections:
        rounds = 2 if quick else 5
        _progress("kernels: a view step against one MuJoCo image")
        results["kernels"] = {"view_step": kernels.view_step(max(40, int(400 * scale)), rounds)}
        on_progress(results)
        _progress("kernels: each compiled kernel against its reference")
        results["kernels"]["kernels"] = kernels.kernel_ratios(rounds)
        on_progress(results)
        _progress("kernels: the vector env against SyncVectorEnv and the reference")
        runs = ((1, 1), (2, 2)) if quick else kernels.VECTOR_RUNS
        results["kernels"]["vector_env"] = kernels.vector_env(runs, max(8, int(64 * scale)), rounds)
        on_progress(results)
        _progress("kernels: the first gym.make in a fresh process")
        results["kernels"]["first_make"] = kernels.first_make(1 if quick else 3)
    finished("kernels")
    if "physics" in sections:
        results["physics"] = []
        dynamic = Config(VIEW_PLANNING, {**VIEW_DEFAULT.kwargs, "motion": "dynamic"})
        for config, steps in ((GRASP_STATE, 2000), (dynamic, 200)):
            _progress(f"physics limit: {config.env_id} {config.label}")
            measured = physics.measure(config, max(20, int(steps * scale)), repeats)
            results["physics"].append({"env_id": config.env_id, "mode": config.label, **measured})
            on_progress(results)
    finished("physics")
    if "peers" in sections:
        if peers.available():
            results["peers"] = {}
            for render, steps in ((False, 2000), (True, 300)):
                _progress(f"peer: {peers.PEER_ENV} render={render}")
                key = "rgb_84" if render else "no_render"
                results["peers"][key] = peers.measure(render, max(20, int(steps * scale)), repeats)
                on_progress(results)
        else:
            results["peers"] = None
    finished("peers")
    if "scaling" in sections:
        results["scaling"] = []
        workers = (1, 2) if quick else scaling.WORKERS
        plan = [
            (kind, count)
            for kind in scaling.KINDS
            for count in (workers if kind != "single" else (1,))
        ]
        for config, steps in ((VIEW_DEFAULT, 200), (GRASP_STATE, 1000)):
            # Rounds of every vector env in turn, so that a machine whose speed drifts over
            # minutes slows each of them alike; speed-ups are taken within each round.
            rates: dict[tuple[str, int], list[float]] = {key: [] for key in plan}
            ceilings: list[dict[str, float]] = []  # the single env's, per round
            costs: list[dict[str, dict[str, float]]] = []
            for round_ in range(repeats):
                for kind, count in plan:
                    _progress(
                        f"scaling: {config.env_id} {kind} x{count}, round {round_ + 1} of {repeats}"
                    )
                    measured = scaling.measure(config, kind, count, max(20, int(steps * scale)), 1)
                    rates[(kind, count)].append(measured["median"])
                    if kind == "single":
                        ceilings.append(measured["ceilings"])
                        costs.append(measured["vector_cost_ms"])
            for kind, count in plan:
                row = {
                    "env_id": config.env_id,
                    "kind": kind,
                    "workers": count,
                    **scaling.summarize(rates[(kind, count)], rates[("single", 1)]),
                }
                if kind == "single":
                    row["ceilings"] = _median_over_rounds(ceilings)
                    row["vector_cost_ms"] = _median_over_rounds(costs)
                results["scaling"].append(row)
            on_progress(results)
    finished("scaling")
    if "training" in sections:
        results["training"] = {"throughput": []}
        for env_id, algo, steps in training.RUNS:
            _progress(f"training throughput: {env_id} {algo}")
            measured = training.throughput(env_id, algo, max(256, int(steps * scale)))
            results["training"]["throughput"].append({"env_id": env_id, "algo": algo, **measured})
            on_progress(results)
        _progress("training: PPO before the kernels and now, side by side (default train.py)")
        steps, rounds = (
            (512, 1) if quick else (training.default_ppo_steps(), training.SIDE_BY_SIDE_ROUNDS)
        )
        results["training"]["side_by_side"] = training.side_by_side(steps, rounds)
        on_progress(results)
        _progress("training: time to beat the four-view baseline (default train.py)")
        results["training"]["time_to_beat"] = training.time_to_beat_four_view(
            512 if quick else None
        )
    finished("training")
    return results


def _median_over_rounds(rounds: list):
    """Per leaf of the rounds' (nested) dicts of figures, its median over the rounds."""
    if isinstance(rounds[0], dict):
        return {key: _median_over_rounds([r[key] for r in rounds]) for key in rounds[0]}
    return spread(rounds)["median"]


def _keep(earlier: dict, sections: list[str], stamp: dict) -> dict:
    """An earlier report's results without ``sections``, which are listed as re-measured
    with ``stamp`` (date, commit, command)."""
    results = {**earlier, "remeasured": dict(earlier.get("remeasured", {}))}
    for section in sections:
        results.pop(section, None)
        results["remeasured"][section] = stamp
    return results


def _ceiling(row: dict, single: dict, machine_: dict) -> float | None:
    """The lockstep ceiling of a vector env row (see ``benchmarks/scaling.py``): None for the
    single env, for more workers than usable cores, and in reports before it was measured."""
    usable = machine_.get("usable_cores", machine_["cores"])
    if row["kind"] == "single" or row["workers"] > usable:
        return None
    return (single.get("ceilings") or {}).get(str(row["workers"]))


def _round_range(paired: dict) -> str:
    """`` (rounds 1.92x-3.66x)``: the side-by-side rounds' speed-ups, where there are several."""
    rounds = paired.get("round_speedups") or []
    return f" (rounds {min(rounds):.2f}x-{max(rounds):.2f}x)" if len(rounds) > 1 else ""


def _speedup(row: dict, single: dict) -> float:
    """A scaling row's speed-up over one env: the median of its rounds' ratios, or (reports
    before rounds) the ratio of medians."""
    return row["speedup"] if "speedup" in row else row["median"] / single["median"]


#: Fetch's two measurements: the key in the figures, the report's row and ratio column.
_PEER_ROWS = (
    ("no_render", "FetchPickAndPlace-v4, no rendering", "vs Fetch, no rendering"),
    ("rgb_84", "FetchPickAndPlace-v4, 84x84 RGB each step", "vs Fetch, 84x84 RGB"),
)


def _find(rows: list[dict], **match) -> dict | None:
    return next((r for r in rows if all(r.get(k) == v for k, v in match.items())), None)


def targets(results: dict) -> list[tuple]:
    """(target, measured, met) for every target whose inputs this run measured."""
    out = []
    rows = results.get("throughput") or []
    view = _find(rows, env_id=VIEW_PLANNING, mode=VIEW_DEFAULT.label)
    view_gl = _find(rows, env_id=VIEW_PLANNING, mode=throughput.VIEW_DEFAULT_GL.label)
    grasp = _find(rows, env_id=GRASP, mode=GRASP_STATE.label)
    # The default mode may render with either backend (the issue: "gl or raycast"); the
    # faster one is scored and named.
    view = max((r for r in (view, view_gl) if r), key=lambda r: r["median"], default=None)
    if view:
        backend = view["mode"].split(",")[0]
        out.append(
            (
                f"ViewPlanning-v1 default mode ({backend}), 64x64: "
                f">= {VIEW_TARGET:.0f} view-steps/s",
                f"{view['median']:.0f}",
                view["median"] >= VIEW_TARGET,
            )
        )
    # The report is saved after each measurement, so Fetch may have only its first row yet.
    peer = results.get("peers") or {}
    if "rgb_84" in peer and view:
        ratio = view["median"] / peer["rgb_84"]["median"]
        out.append(
            (
                f"ViewPlanning-v1 ({backend}) / FetchPickAndPlace-v4 with 84x84 RGB: "
                f">= {VIEW_PEER_RATIO:.0f}x",
                f"{ratio:.2f}x",
                ratio >= VIEW_PEER_RATIO,
            )
        )
    if "no_render" in peer and grasp:
        ratio = grasp["median"] / peer["no_render"]["median"]
        out.append(
            (
                "InstrumentGrasp-v1 state / FetchPickAndPlace-v4 without rendering: "
                f">= {GRASP_PEER_RATIO:.1f}x",
                f"{ratio:.2f}x",
                ratio >= GRASP_PEER_RATIO,
            )
        )
    measured = results.get("kernels") or {}
    if "view_step" in measured:
        ratio = measured["view_step"]["step_to_reference"]
        out.append(
            (
                "ViewPlanning-v1 view step, resets included / one 64x64 image cast by MuJoCo "
                f"(the reference scene): <= {kernels.STEP_TO_REFERENCE_TARGET:.1f}x",
                f"{ratio:.2f}x",
                ratio <= kernels.STEP_TO_REFERENCE_TARGET,
            )
        )
    size, workers = kernels.BATCHED_TARGET_RUN
    batched = _find(measured.get("vector_env") or [], num_envs=size, workers=workers)
    if batched and "batched_to_reference" in batched:
        ratio = batched["batched_to_reference"]
        out.append(
            (
                f"ViewPlanning-v1 own vector env, {size} scenes in {workers} processes: "
                f"scene-steps/s / the reference's images/s >= {kernels.BATCHED_TARGET:.1f}x",
                f"{ratio:.2f}x",
                ratio >= kernels.BATCHED_TARGET,
            )
        )
    if "first_make" in measured:
        seconds = measured["first_make"]["median_s"]
        out.append(
            (
                f"first gym.make('ViewPlanning-v1') in a process, warm caches: "
                f"< {kernels.FIRST_MAKE_TARGET_S:.0f} s",
                f"{seconds:.2f} s",
                seconds < kernels.FIRST_MAKE_TARGET_S,
            )
        )
    limit = _find(results.get("physics") or [], env_id=GRASP)
    fraction = limit.get("env_to_limit") if limit else None
    if fraction:
        out.append(
            (
                f"InstrumentGrasp-v1 state: >= {GRASP_PHYSICS_FRACTION:.0%} of its physics limit",
                f"{fraction:.0%}",
                fraction >= GRASP_PHYSICS_FRACTION,
            )
        )
    paired = (results.get("training") or {}).get("side_by_side") or {}
    if "speedup" in paired:
        out.append(
            (
                "PPO training on ViewPlanning-v1, default train.py: env steps/s / the code "
                f"before the kernels, side by side: >= {training.PPO_SPEEDUP_TARGET:.0f}x",
                f"{paired['speedup']:.2f}x" + _round_range(paired),
                paired["speedup"] >= training.PPO_SPEEDUP_TARGET,
            )
        )
    scaled = results.get("scaling") or []
    cores = describe_cores(results["machine"])
    for env_id in (VIEW_PLANNING, GRASP):
        single = _find(scaled, env_id=env_id, kind="single")
        two = _find(scaled, env_id=env_id, kind="gymnasium-async", workers=2)
        if single and two:
            speedup = _speedup(two, single)
            ceiling = _ceiling(two, single, results["machine"])
            out.append(
                (
                    f"{env_id}: async vector env, 2 workers on {cores}: "
                    f">= {ASYNC_TWO_WORKER_SPEEDUP}x one env",
                    f"{speedup:.2f}x" + (f" (lockstep ceiling {ceiling:.2f}x)" if ceiling else ""),
                    speedup >= ASYNC_TWO_WORKER_SPEEDUP,
                )
            )
    return out


def _kernel_tables(measured: dict) -> list[str]:
    """The kernels section: a view step against MuJoCo's image, each kernel, the vector env."""
    lines = ["## Compiled kernels", "", kernels.__doc__.split("\n\n")[1].replace("\n", " "), ""]
    step = measured.get("view_step")
    if step:
        lines += _table(
            (
                "one MuJoCo image ms",
                "view step ms, resets included",
                "step / image",
                "median view step ms",
                "median reset ms",
            ),
            [
                (
                    f"{step['reference_ms']:.3f}",
                    f"{step['step_ms']:.3f}",
                    f"{step['step_to_reference']:.2f}x",
                    f"{step['median_step_ms']:.3f}" if "median_step_ms" in step else "-",
                    f"{step['reset_ms']:.3f}",
                )
            ],
        )
    if measured.get("kernels"):
        lines += _table(
            ("kernel", "reference ms / call", "compiled ms / call", "speed-up"),
            [
                (k["kernel"], f"{k['reference_ms']:.3f}", f"{k['compiled_ms']:.3f}",
                 f"{k['speedup']:.2f}x")
                for k in measured["kernels"]
            ],
        )  # fmt: skip
    if measured.get("vector_env"):
        lines += _table(
            ("scenes", "processes", "own vector env ms / scene-step", "SyncVectorEnv ms",
             "speed-up", "one MuJoCo image ms", "scene-steps/s / images/s"),
            [
                (v["num_envs"], v.get("workers", 1), f"{v['batched_ms_per_scene_step']:.3f}",
                 f"{v['sync_ms_per_scene_step']:.3f}", f"{v['sync_to_batched']:.2f}x",
                 _number(v.get("reference_ms"), ".3f"),
                 f"{v['batched_to_reference']:.2f}x" if "batched_to_reference" in v else "-")
                for v in measured["vector_env"]
            ],
        )  # fmt: skip
    return lines


def report(results: dict, command: str) -> str:
    """RESULTS.md: the machine, the command, the targets, then every table."""
    m = results["machine"]
    versions = ", ".join(f"{k} {v}" for k, v in m["versions"].items())
    unfinished = results.get("unfinished")
    incomplete = (
        [
            "",
            f"**Incomplete: saved before {', '.join(unfinished)} finished (a run still going,"
            " or one that failed or was stopped); those tables are missing or partial.**",
        ]
        if unfinished
        else []
    )
    lines = [
        "# Benchmark results",
        "",
        f"Generated by `{results.get('command') or command}` on {m['date']}"
        f" (commit {m['commit']}).",
        *(
            f"Re-measured later by `{again['command']}` on {again['date']} (commit"
            f" {again['commit']}): {section}."
            for section, again in results.get("remeasured", {}).items()
        ),
        *incomplete,
        ""
        if not results["quick"]
        else "**Quick run: a smoke test of the benchmark, not a measurement.**\n",
        f"- Machine: {m['cpu']}, {describe_cores(m)}, {m['memory']} RAM, {m['os']}",
        f"- OpenGL renderer of the gl rows: {m.get('gl_renderer', 'not recorded')}",
        f"- Python {m['python']}; {versions}; MUJOCO_GL={m['MUJOCO_GL']}",
        "- Every rate is the median of repeated runs (min and max beside it), wall clock, one"
        " process per measurement, seeded uniform random actions (drawn before the clock starts)"
        " with resets included.",
        "",
    ]
    goals = targets(results)
    if goals:
        lines += ["## Targets", ""]
        lines += _table(
            ("target", "measured", "met"), [(t, v, "yes" if ok else "**no**") for t, v, ok in goals]
        )
    if "throughput" in results:
        lines += ["## Env steps per second, one env on one core", ""]
        lines += _table(
            ("env", "mode", "steps/s median", "min", "max", "peak RSS MiB"),
            [
                (
                    r["env_id"],
                    r["mode"],
                    _rate(r),
                    f"{r['min']:.0f}",
                    f"{r['max']:.0f}",
                    f"{r['mib']:.0f}",
                )
                for r in results["throughput"]
            ],
        )
    if "split" in results:
        lines += [
            "## Where a step's time goes",
            "",
            "Exclusive milliseconds per env step (resets included), by phase; see"
            " `benchmarks/time_split.py` for what each phase wraps.",
            "",
        ]
        for r in results["split"]:
            total = r["ms_per_step"]
            phases = sorted(r["phases"].items(), key=lambda item: -item[1])
            lines += [
                f"**{r['env_id']}, {r['mode']}**: {total:.3f} ms per step "
                f"({1e3 / total:.0f} steps/s with the timers on)",
                "",
            ]
            lines += _table(
                ("phase", "ms / step", "share"),
                [(p, f"{ms:.3f}", f"{ms / total:.0%}") for p, ms in phases],
            )
    if "kernels" in results:
        lines += _kernel_tables(results["kernels"])
    if "physics" in results:
        lines += [
            "## The physics limit",
            "",
            "Every `mj_step` of seeded random episodes, resets included, replayed open loop"
            " by `mujoco.rollout` (all substeps in C). The limit is env steps/s of that"
            " replay; the env's own steps/s are timed on the same episodes in the same process, in"
            " rounds alternating with the replay's; env / limit is the median of the rounds'"
            " ratios.",
            "",
        ]
        rows = []
        for r in results["physics"]:
            rows.append(
                (
                    r["env_id"],
                    r["mode"],
                    _number(r.get("mj_steps_per_env_step"), ".1f"),
                    _number(r.get("mj_steps_per_second"), ".0f"),
                    _number(r.get("limit"), ".0f"),
                    _number(r.get("env_steps_per_second"), ".0f"),
                    _number(r.get("env_to_limit"), ".0%"),
                )
            )
        lines += _table(
            (
                "env",
                "mode",
                "mj_steps / env step",
                "mj_steps/s",
                "limit env steps/s",
                "env steps/s",
                "env / limit",
            ),
            rows,
        )
    if "peers" in results:
        lines += ["## Side by side: FetchPickAndPlace-v4 (Gymnasium-Robotics)", ""]
        peer = results["peers"]
        if peer is None:
            lines += [
                'Skipped: gymnasium-robotics is not installed (`pip install -e ".[bench]"`).',
                "",
            ]
        else:
            measured = [row for row in _PEER_ROWS if row[0] in peer]
            rows = [
                (
                    name,
                    _rate(peer[key]),
                    f"{peer[key]['min']:.0f}",
                    f"{peer[key]['max']:.0f}",
                    f"{peer[key]['mib']:.0f}",
                )
                for key, name, _ in measured
            ]
            lines += _table(("env", "steps/s median", "min", "max", "peak RSS MiB"), rows)
            ratios = [
                (
                    r["env_id"],
                    r["mode"],
                    *(f"{r['median'] / peer[key]['median']:.2f}x" for key, _, _ in measured),
                )
                for r in results.get("throughput") or []
            ]
            if ratios:
                lines += _table(("env", "mode", *(column for _, _, column in measured)), ratios)
            lines += ["Fetch runs in a `python -O` process: see `benchmarks/peers.py` for why.", ""]
    if "scaling" in results:
        lines += [
            "## Vectorised scaling",
            "",
            "Total env steps/s over all workers; speed-up against one env stepped in-process"
            " (measured in rounds, each vector env in turn; the median of the rounds' ratios)."
            " Both vector envs step their workers in lockstep, each call waiting for the slowest"
            " worker; the lockstep ceiling is the most that allows with a free core per worker"
            " and no cost of communication, from the single env's own step times (the median"
            " over rounds; see `benchmarks/scaling.py`).",
            "",
        ]
        rows = []
        for r in results["scaling"]:
            single = _find(results["scaling"], env_id=r["env_id"], kind="single")
            ceiling = _ceiling(r, single, m)
            rows.append(
                (
                    r["env_id"],
                    r["kind"],
                    r["workers"],
                    _rate(r),
                    f"{r['min']:.0f}",
                    f"{r['max']:.0f}",
                    f"{_speedup(r, single):.2f}x",
                    f"{ceiling:.2f}x" if ceiling else "-",
                )
            )
        columns = ("env", "vector env", "workers", "steps/s median", "min", "max", "speed-up")
        lines += _table((*columns, "lockstep ceiling"), rows)
        costs = [
            (r["env_id"], vector, n, f"{ms:.3f}", f"{ms * r['median'] / 1e3:.2f}")
            for r in results["scaling"]
            if r["kind"] == "single"
            for vector, by_workers in (r.get("vector_cost_ms") or {}).items()
            for n, ms in by_workers.items()
        ]
        if costs:
            lines += [
                "The vector envs' own cost: milliseconds per call of `step` on no-op twins of"
                " each env (its spaces, observation and info, and no work; random actions"
                " included), and that cost in env steps of the single env above.",
                "",
            ]
            lines += _table(
                ("env", "vector env", "workers", "ms per call", "in single env steps"), costs
            )
    if "training" in results:
        lines += [f"## Training throughput (train.py, {describe_cores(m)})", ""]
        lines += _table(
            ("env", "algorithm", "env steps", "seconds", "env steps/s", "in gradient updates"),
            [
                (
                    r["env_id"],
                    r["algo"],
                    r["timesteps"],
                    f"{r['seconds']:.1f}",
                    f"{r['steps_per_second']:.0f}",
                    # results of older code did not time the updates
                    f"{r['update_share']:.0%}" if "update_share" in r else "-",
                )
                for r in results["training"]["throughput"]
            ],
        )
        paired = results["training"].get("side_by_side") or {}
        if "speedup" in paired:
            lines += [
                f"Side by side (`benchmarks/training.py`): the default `python train.py` of "
                f"commit {paired['before_commit'][:12]}, before the compiled kernels, and of "
                f"this code, {paired['steps']} steps each, in rounds of one run each; the"
                " speed-up is the median of the rounds' ratios (min and max beside it).",
                "",
            ]
            rounds = paired.get("round_speedups") or [paired["speedup"]]
            lines += _table(
                ("code", "env steps/s per run", "speed-up", "min", "max"),
                [
                    ("before the kernels",
                     ", ".join(f"{r:.0f}" for r in paired["before_steps_per_second"]), "", "", ""),
                    ("now", ", ".join(f"{r:.0f}" for r in paired["now_steps_per_second"]),
                     f"{paired['speedup']:.2f}x", f"{min(rounds):.2f}x", f"{max(rounds):.2f}x"),
                ],
            )  # fmt: skip
        elif "skipped" in paired:
            lines += [f"Side by side: not measured ({paired['skipped']}).", ""]
        beat = results["training"].get("time_to_beat")
        if beat:
            lines += [_time_to_beat(beat), ""]
    return "\n".join(lines)


def _time_to_beat(beat: dict) -> str:
    run = f"The default `python train.py` (PPO, ViewPlanning-v1, {beat['total_steps']} steps, "
    run += f"{beat['total_seconds']:.0f} s of learning)"
    objects = beat.get("objects", "train")  # reports before the field trained on these
    against = (
        f"the four-view baseline's {beat['baseline_coverage']:.3f} mean coverage on the same "
        f"{beat['eval_episodes']} periodic-evaluation episodes ({objects} objects, evaluated "
        f"every {beat['eval_freq']} steps)"
    )
    if beat["beaten_at_seconds"] is None:
        return f"{run} never beat {against}."
    return (
        f"Time to beat the four-view baseline: {run} first beat {against} at "
        f"{beat['beaten_at_steps']} env steps, {beat['beaten_at_seconds']:.0f} s into learning "
        f"(coverage {beat['coverage_then']:.3f}; the time includes the evaluations)."
    )


def main(argv: list[str] | None = None) -> int:
    args = _parse(argv)
    command = "MUJOCO_GL=egl python -m benchmarks " + shlex.join(
        sys.argv[1:] if argv is None else argv
    )

    def save(results: dict) -> None:
        args.out.write_text(report(results, command.strip()))
        args.json.write_text(json.dumps(results, indent=1, default=str))

    if args.earlier is not None and "command" not in args.earlier:
        # Reports written before the JSON kept the command: read it off the Markdown.
        try:
            found = re.search(r"Generated by `([^`]+)`", args.out.read_text(errors="replace"))
        except OSError:
            found = None
        args.earlier["command"] = found.group(1) if found else "an earlier command"
    run(args.sections, args.quick, on_progress=save, earlier=args.earlier, command=command.strip())
    print(args.out.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
