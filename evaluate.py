"""Evaluate trained policies and scripted baselines on the same seeded episodes and write a
report (report.md, report.json, figures, optional videos).

    python evaluate.py policies/ViewPlanning-v1/ppo              # + four-view and the oracle
    python evaluate.py runs/ViewPlanning-v1/ppo_seed0_* --episodes 100 --out reports/ppo
    python evaluate.py --env ViewPlanning-v1 four-view uniform random --episodes 20
    python evaluate.py policies/InstrumentGrasp-v1/sac --baselines scripted-grasp,squeeze --video
    python evaluate.py policy.zip --env InstrumentGrasp-v1      # any run's exported policy
    python evaluate.py model.zip --env ViewPlanning-v1 --raw-observations  # not normalised

Sources are run folders (their best model; --final-model for the last one; a shipped folder's
policy.zip), model .zip files (a zip inside a run folder takes the run's config; a lone one
needs --env, and unless it is a policy.zip, which carries its observation statistics, its
vecnormalize.pkl beside it or --raw-observations) or baseline names:
ViewPlanning: four-view, uniform, random, greedy-oracle (privileged: it reads the ground
truth); InstrumentGrasp: scripted-grasp, squeeze, random, privileged-grasp (the script
reading the handle from the simulator). Several run folders of one algorithm with the same
env kwargs and training settings are aggregated as training seeds (IQM and mean, each with
a bootstrap interval over seeds and rliable's stratified one; probability of improvement
over the baseline).
Episodes are the held-out objects / instruments unless --object-set / --instrument-set say
otherwise.
"""

from __future__ import annotations

import argparse
import os
import sys

from liuxing_envs.opengl import mujoco_import_problem, use_headless_default

use_headless_default()

from agents.config import (  # noqa: E402
    MAX_SEED,
    ConfigError,
    parse_assignments,
    script_parser,
    show_package_progress,
)

#: The library's names for what a flag of another name sets (see NamesSettings).
RENAMED_FLAGS = {"env_id": "--env"}
#: The envs' splits, written out so --help needs no env import (a test keeps them in step).
OBJECT_SPLITS = ("train", "validation", "held_out", "all", "procedural")
INSTRUMENT_SPLITS = ("train", "held_out", "all")


def build_parser() -> argparse.ArgumentParser:
    parser = script_parser("evaluate.py", __doc__)
    what = parser.add_argument_group("what to evaluate")
    what.add_argument(
        "sources", nargs="*", metavar="SOURCE", help="run folders, model .zip files, baselines"
    )
    what.add_argument("--env", help="environment of lone model files and named baselines")
    what.add_argument("--algo", help="ppo or sac, for a lone model file (default: read from it)")
    what.add_argument(
        "--baselines",
        help="comma-separated baselines to add, or 'none' (default: the env's reference ones)",
    )
    what.add_argument(
        "--final-model", action="store_true", help="a run folder's final model, not its best"
    )
    what.add_argument(
        "--raw-observations",
        action="store_true",
        help="a lone model file was trained without observation normalisation (without this, "
        "its vecnormalize.pkl must lie beside it, unless it is a policy.zip)",
    )
    episodes = parser.add_argument_group("episodes")
    episodes.add_argument("--episodes", type=int, default=100, help="episodes per contestant")
    episodes.add_argument(
        "--seed", type=int, default=1_000_000, help="seed of the first episode (default: 1000000)"
    )
    episodes.add_argument(
        "--object-set", choices=OBJECT_SPLITS, help="ViewPlanning's split (default: held_out)"
    )
    episodes.add_argument(
        "--instrument-set",
        choices=INSTRUMENT_SPLITS,
        help="InstrumentGrasp's split (default: held_out)",
    )
    episodes.add_argument(
        "--env-kwargs",
        nargs="+",
        action="extend",
        metavar="KEY=VALUE",
        help="gym.make kwargs (may be repeated)",
    )
    episodes.add_argument(
        "--deterministic",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="deterministic actions for trained policies (default: on)",
    )
    report = parser.add_argument_group("report")
    report.add_argument(
        "--out",
        default="reports/latest",
        help="report folder (an earlier report's figures, meshes and videos there are replaced)",
    )
    report.add_argument(
        "--reconstruct-episodes",
        type=int,
        help="ViewPlanning episodes per contestant scored by reconstruction (~2 s each; "
        "default: 20)",
    )
    report.add_argument(
        "--save-reconstructions",
        type=int,
        help="of those, how many to save as .ply (default: 3)",
    )
    report.add_argument("--video", action="store_true", help="write mp4 videos of a few episodes")
    report.add_argument(
        "--video-episodes", type=int, help="episodes per video, with --video (default: 2)"
    )
    report.add_argument(
        "--progress-bar",
        action=argparse.BooleanOptionalAction,
        default=sys.stderr.isatty(),
        help="show a progress bar (default: on when writing to a terminal)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    show_package_progress()
    # Flags that only shape another flag's output are refused where they would do nothing.
    if args.video_episodes is not None and not args.video:
        parser.error("--video-episodes sets how many episodes each video shows; add --video")
    if args.save_reconstructions is not None and args.reconstruct_episodes == 0:
        parser.error(
            "--save-reconstructions saves some of the --reconstruct-episodes, which is 0 here"
        )
    if args.final_model and not any(os.path.isdir(source) for source in args.sources):
        parser.error("--final-model picks a run folder's final model; no source is a run folder")
    reconstruction_flags = [  # those that ask for reconstructions
        f"--{flag.replace('_', '-')}"
        for flag in ("reconstruct_episodes", "save_reconstructions")
        if getattr(args, flag) is not None and getattr(args, flag) > 0
    ]
    for flag, default in (
        ("video_episodes", 2),
        ("reconstruct_episodes", 20),
        ("save_reconstructions", 3),
    ):
        if getattr(args, flag) is None:
            setattr(args, flag, default)
    for flag in ("episodes", "video_episodes"):
        if getattr(args, flag) < 1:
            parser.error(f"--{flag.replace('_', '-')} must be at least 1")
    for flag in ("seed", "reconstruct_episodes", "save_reconstructions"):
        if getattr(args, flag) < 0:
            parser.error(f"--{flag.replace('_', '-')} must be 0 or more")
    last_seed = args.seed + args.episodes - 1  # one seed per episode
    if last_seed > MAX_SEED:  # as train.py's: torch's generator refused seeds from 2**64
        parser.error(
            f"--seed must be at most {MAX_SEED - args.episodes + 1} with --episodes "
            f"{args.episodes} (their seeds run to {last_seed}, above {MAX_SEED}), got {args.seed}"
        )
    if problem := mujoco_import_problem():
        parser.error(problem)
    # Heavy imports (torch, SB3, MuJoCo) after parsing, so --help and flag errors are instant.
    from agents import contestants as contest
    from agents import report
    from agents.evaluation import TASKS
    from agents.task_reports import REPORTS, report_for

    try:
        if args.env is not None:
            contest.check_env_id(args.env)
        if args.algo is not None:
            contest.check_algo(args.algo)
        baselines = None
        if args.baselines is not None:
            names = [name.strip() for name in args.baselines.split(",") if name.strip()]
            repeated = sorted({name for name in names if names.count(name) > 1})
            if repeated:  # it would run twice, on the same episodes, under two labels
                parser.error(f"--baselines names {', '.join(repeated)} more than once")
            baselines = [] if names == ["none"] else names
        contestants = contest.build_contestants(
            args.sources,
            env_id=args.env,
            algo=args.algo,
            baselines=baselines,
            env_kwargs=parse_assignments(args.env_kwargs, "--env-kwargs"),
            # Each task's split flag (--object-set) stores its split under its split_kwarg.
            splits={
                name: getattr(args, task.split_kwarg)
                for name, task in TASKS.items()
                if getattr(args, task.split_kwarg) is not None
            },
            best=not args.final_model,
            raw_observations=args.raw_observations,
        )
        if reconstruction_flags and not any(report_for(c.env_id).reconstructs for c in contestants):
            reconstructing = " or ".join(name for name, r in REPORTS.items() if r.reconstructs)
            parser.error(
                f"{' and '.join(reconstruction_flags)} score {reconstructing} episodes by "
                f"reconstruction; no contestant here runs a {reconstructing} task"
            )
        settings = report.Settings(
            episodes=args.episodes,
            seed=args.seed,
            deterministic=args.deterministic,
            reconstruct_episodes=min(args.reconstruct_episodes, args.episodes),
            save_episodes=args.save_reconstructions,
            video_episodes=args.video_episodes if args.video else 0,
            progress=args.progress_bar,
            command=report.command_line(),
        )
        print(
            "evaluating "
            + ", ".join(f"{c.label} ({c.env_id})" for c in contestants)
            + f" on {args.episodes} episodes",
            flush=True,
        )
        result = report.evaluate(contestants, settings, args.out)
    except (ConfigError, contest.ContestantError) as error:
        parser.error(error.for_command_line(RENAMED_FLAGS))
    except KeyboardInterrupt:
        return 130
    print(report.summary_lines(result))
    print(f"report: {os.path.join(args.out, report.REPORT_MD)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
