r"""Train PPO or SAC on a liuxing_envs environment.

    python train.py                                   # ViewPlanning-v1, PPO, ~6 min on 2 cores
    python train.py --env InstrumentGrasp-v1 --algo sac --seed 1 -n 300000
    python train.py --algo ppo --hyperparams learning_rate=1e-4 policy_kwargs.net_arch=[64,64]
    python train.py --env-kwargs view_budget=6 --eval-freq 2000
    python train.py --resume runs/ViewPlanning-v1/ppo_seed0_20261121-101500 [-n 120000]
    python train.py --env InstrumentGrasp-v1 --algo sac \
        --init-from runs/InstrumentGrasp-v1/sac_seed0_20261121-101500 --init-replay-buffer \
        --hyperparams demonstrations=null start_curriculum=null learning_rate=3e-5
    python train.py --recipe recipes/view_planning_ppo.yml [--seed 0]  # a shipped policy
    python train.py --sweep sweeps/smoke.yml [--ray-address HOST:PORT]  # seeds x settings

Hyper-parameters come from agents/hyperparams/<algo>.yml (keyed by env id; a variant id uses
its task's -v1 entry) or --config; each
run writes a folder (see agents/run_folder.py) with its resolved config, models, checkpoints,
evaluation history and learning curve. Ctrl-C saves a checkpoint that --resume continues.
A recipe (agents/recipes.py) pins every setting of one or more chained runs; the same
command again goes on where it stopped. A sweep (agents/sweep_file.py) runs a grid or an
Optuna search of configurations, each with several seeds, on Ray Tune (the `sweep` extra):
every trial is a run folder under the sweep's folder, and the same command resumes it.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys

from liuxing_envs.opengl import mujoco_import_problem, use_headless_default

use_headless_default()

from agents import interrupts  # noqa: E402
from agents.config import (  # noqa: E402
    ConfigError,
    parse_assignments,
    script_parser,
    show_package_progress,
)
from agents.run_folder import RunFolderError  # noqa: E402
from agents.workers import WorkerDied  # noqa: E402

#: The library's names for what a flag of another name sets (see NamesSettings).
RENAMED_FLAGS = {"env_id": "--env", "n_timesteps": "-n/--timesteps", "config_file": "--config"}
#: Flags that define a run; a resumed run keeps the values in its config.yml.
RUN_DEFINING_FLAGS = (
    "env", "algo", "seed", "n_envs", "vec_env", "config", "hyperparams", "env_kwargs",
    "eval_freq", "eval_episodes", "save_freq", "run_dir", "log_folder", "tensorboard",
    "init_from", "init_replay_buffer",
)  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    parser = script_parser("train.py", __doc__)
    run = parser.add_argument_group("what to train")
    run.add_argument("--env", help="environment id (default: ViewPlanning-v1)")
    run.add_argument("--algo", help="ppo or sac (default: ppo)")
    run.add_argument("-n", "--timesteps", type=int, help="total env steps (default: from YAML)")
    run.add_argument("--seed", type=int, help="random seed (default: 0)")
    run.add_argument("--n-envs", type=int, help="parallel training envs (default: from YAML)")
    run.add_argument(
        "--vec-env",
        help="dummy (one process), subproc (a process per env) or batched (the task's own "
        "vector env, one process; the default where the task has one, else dummy)",
    )
    run.add_argument("--config", metavar="FILE", help="hyper-parameter YAML to use instead")
    run.add_argument(
        "--recipe",
        metavar="FILE",
        help="train a recipe's stages (recipes/*.yml; every setting pinned there); with "
        "--seed, --run-dir (the recipe's folder) or --log-folder only",
    )
    run.add_argument(
        "--sweep",
        metavar="FILE",
        help="run a sweep on Ray Tune (sweeps/*.yml: base settings, seeds, a grid or a "
        "search space); with --run-dir (the sweep's folder), --log-folder or --ray-address "
        "only",
    )
    run.add_argument(
        "--ray-address",
        metavar="ADDRESS",
        help="with --sweep: join this Ray cluster (default: RAY_ADDRESS, else a local Ray "
        "with this machine's cores)",
    )
    # "extend": a flag given twice adds its items to the first's (argparse's default keeps
    # only the last group, silently dropping the rest).
    run.add_argument(
        "--hyperparams",
        nargs="+",
        action="extend",
        metavar="KEY=VALUE",
        help="override hyper-parameters (may be repeated)",
    )
    run.add_argument(
        "--env-kwargs",
        nargs="+",
        action="extend",
        metavar="KEY=VALUE",
        help="gym.make kwargs (may be repeated)",
    )
    run.add_argument(
        "--init-from",
        metavar="RUN_DIR",
        help="start from a trained run's best policy and normaliser (same env and algorithm); "
        "everything else is this run's",
    )
    run.add_argument(
        "--init-replay-buffer",
        action="store_true",
        default=None,
        help="with --init-from (SAC): also start from the replay buffer (and its size) of the "
        "trained run's newest checkpoint; its rewards stay those of the trained run's env",
    )
    run.add_argument("--device", help="torch device: auto, cpu, cuda, cuda:N (default: auto)")
    run.add_argument("--torch-threads", type=int, help="torch CPU threads (default: 1)")
    run.add_argument(
        "--env-workers",
        type=int,
        help="processes stepping a batched vector env's scenes, this one included (default: "
        "from YAML, else 1)",
    )
    logs = parser.add_argument_group("evaluation, checkpoints and logs")
    logs.add_argument("--eval-freq", type=int, help="env steps between evaluations (0: none)")
    logs.add_argument(
        "--eval-episodes",
        type=int,
        help="episodes per periodic evaluation (default: one per 1,000 steps, 5 to 20)",
    )
    logs.add_argument("--save-freq", type=int, help="env steps between checkpoints (0: none)")
    logs.add_argument(
        "--final-episodes",
        type=int,
        help="held-out episodes of the final comparison (0: skip; default: one per 1,000 "
        "steps, 5 to 50)",
    )
    logs.add_argument(
        "--run-dir", help="the run's folder (default: LOG_FOLDER/ENV/ALGO_seedS_TIME)"
    )
    logs.add_argument("-f", "--log-folder", help="parent of new run folders (default: runs)")
    logs.add_argument("--tensorboard", action="store_true", default=None, help="TensorBoard logs")
    logs.add_argument(
        "--progress-bar",
        action=argparse.BooleanOptionalAction,
        default=sys.stdout.isatty(),
        help="show a progress bar (default: on when writing to a terminal)",
    )
    logs.add_argument("--resume", metavar="RUN_DIR", help="continue a run from its last checkpoint")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    show_package_progress()
    # A scheduler's SIGTERM (pre-emption, `kill`) saves a checkpoint just as Ctrl-C does.
    interrupts.install()
    if args.run_dir and args.log_folder:
        parser.error(
            "give --run-dir (the run's own folder) or --log-folder (a folder of runs), not both"
        )
    if args.ray_address and not args.sweep:
        parser.error("--ray-address goes with --sweep")
    if args.sweep and args.recipe:
        parser.error("give --sweep or --recipe, not both")
    if problem := mujoco_import_problem():
        parser.error(problem)
    # Heavy imports (torch, SB3, MuJoCo, open3d) after parsing, so --help and flag errors are
    # instant; signals wait for them: a Ctrl-C landing in open3d's import became its
    # ImportError ("initialization failed"), a traceback and exit 1.
    with interrupts.deferred():
        import liuxing_envs.sim.objects  # noqa: F401  (open3d)
        from agents import training
    if interrupts.requested():
        print("interrupted before training began: nothing was saved", file=sys.stderr)
        return interrupts.exit_status()

    try:
        if args.sweep:
            return _run_sweep(parser, args)
        if args.recipe:
            return _run_recipe(parser, args)
        if args.resume:
            given = [
                f"--{name.replace('_', '-')}"
                for name in RUN_DEFINING_FLAGS
                if getattr(args, name) is not None
            ]
            if given:
                parser.error(
                    f"{', '.join(given)} cannot be given with --resume: a resumed run keeps "
                    "the settings in its config.yml"
                )
            training.resume(
                args.resume,
                n_timesteps=args.timesteps,
                progress_bar=args.progress_bar,
                device=args.device,
                final_episodes=args.final_episodes,
                torch_threads=args.torch_threads,
                env_workers=args.env_workers,
            )
            return 0
        config = training.resolve_config(
            **_given(
                env_id=args.env,
                algo=args.algo,
                config_file=args.config,
                hyperparams=parse_assignments(args.hyperparams, "--hyperparams"),
                env_kwargs=parse_assignments(args.env_kwargs, "--env-kwargs"),
                seed=args.seed,
                n_timesteps=args.timesteps,
                n_envs=args.n_envs,
                vec_env=args.vec_env,
                eval_freq=args.eval_freq,
                eval_episodes=args.eval_episodes,
                save_freq=args.save_freq,
                final_episodes=args.final_episodes,
                device=args.device,
                tensorboard=args.tensorboard,
                torch_threads=args.torch_threads,
                env_workers=args.env_workers,
                init_from=args.init_from,
                init_replay_buffer=args.init_replay_buffer,
            )
        )
        run_dir = args.run_dir or training.new_run_dir(
            config, args.log_folder or training.DEFAULT_RUNS_DIR
        )
        print(f"run folder: {run_dir}", flush=True)
        training.train(config, run_dir, progress_bar=args.progress_bar)
    except (ConfigError, RunFolderError) as error:
        parser.error(error.for_command_line(RENAMED_FLAGS))
    except WorkerDied as error:  # the cause is the worker's, not this process's: no traceback
        print(f"train.py: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return interrupts.exit_status()
    return 0


def _refuse_flags(parser, args: argparse.Namespace, allowed: tuple[str, ...], why: str) -> None:
    """Refuse a run-defining flag beside ``allowed[0]`` (--recipe, --sweep), which sets it."""
    given = [
        f"--{name.replace('_', '-')}"
        for name in (
            *RUN_DEFINING_FLAGS,
            "resume",
            "timesteps",
            "device",
            "torch_threads",
            "env_workers",
        )
        if name not in allowed and getattr(args, name) is not None
    ]
    given += ["--final-episodes"] if args.final_episodes is not None else []
    if given:
        mode = "--" + allowed[0].replace("_", "-")
        parser.error(f"{', '.join(given)} cannot be given with {mode}: {why}")


def _run_recipe(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from agents import recipes

    _refuse_flags(parser, args, ("recipe", "seed", "run_dir", "log_folder"), "the recipe pins it")
    try:
        recipe = recipes.load_recipe(args.recipe)
        seed = recipe.seed if args.seed is None else args.seed
        parent = args.log_folder or recipes.DEFAULT_RECIPES_DIR
        folder = args.run_dir or recipe.folder(seed, parent)
        print(f"recipe {recipe.name}, seed {seed}: {folder}", flush=True)
        last = recipes.run_recipe(recipe, seed, folder, progress_bar=args.progress_bar)
    except (ConfigError, RunFolderError) as error:
        # The settings it names are the recipe's keys, not flags (--recipe takes none).
        parser.error(f"recipe {args.recipe}: {error}")
    print(f"the recipe's policy: {last / 'policy.zip'}")
    return 0


def _run_sweep(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from agents import sweep_file

    allowed = ("sweep", "run_dir", "log_folder", "ray_address")
    _refuse_flags(parser, args, allowed, "the sweep file sets it")
    try:
        sweep = sweep_file.load_sweep(args.sweep)  # checked before Ray starts
    except ConfigError as error:
        parser.error(str(error))
    try:
        from agents import sweeps
    except ImportError as error:
        parser.error(f"--sweep needs Ray Tune and Optuna ({error}): pip install -e '.[sweep]'")
    folder = args.run_dir or sweep.folder(args.log_folder or sweep_file.DEFAULT_SWEEPS_DIR)
    print(f"sweep {sweep.name}: {folder}", flush=True)
    # Tune stops a sweep cleanly on SIGINT (its state saved, each trial's training saving a
    # checkpoint): a scheduler's SIGTERM is taken for one.
    signal.signal(signal.SIGTERM, lambda signum, frame: os.kill(os.getpid(), signal.SIGINT))
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        results = sweeps.run_sweep(sweep, folder, args.ray_address)
    except ConfigError as error:
        parser.error(str(error))
    except KeyboardInterrupt:
        print(f"sweep {sweep.name} interrupted; the same command resumes it", file=sys.stderr)
        return 130
    failed = [result for result in results if result.error is not None]
    print(f"sweep {sweep.name}: {len(results) - len(failed)} of {len(results)} trials finished")
    print(f"summary: {folder}/{sweeps.SUMMARY}.md; score them: python evaluate.py {folder}")
    return 1 if failed else 0


def _given(**kwargs) -> dict:
    """Only the flags the user gave, so resolve_config's defaults apply to the rest."""
    return {key: value for key, value in kwargs.items() if value is not None}


if __name__ == "__main__":
    sys.exit(main())
