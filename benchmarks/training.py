"""Training throughput of ``train.py`` and the wall-clock time PPO needs to beat the
four-view baseline on ViewPlanning-v1.

Throughput: ``train.py`` with each algorithm's YAML for each env, run as a subprocess for a
fixed number of steps with periodic evaluation and checkpoints off; env steps per second is
the run's ``timesteps / train_seconds`` from its ``result.json`` (learning only, not start-up),
and the share of those seconds spent in gradient updates (``update_seconds``): above half, a
run is bound by its learner rather than by its env.
SAC runs with ``learning_starts=0``, so every step pays for its gradient update as in the
rest of a long run (the YAMLs' warm-ups of random steps would be a third of a short one).

Side by side: the default ``python train.py`` (PPO on ViewPlanning-v1) of the code before the
compiled kernels (BEFORE_KERNELS, extracted from the repository's history) and of this code,
each for this code's default budget (its ``ppo.yml``), in alternating rounds; the ratio of
their env steps per second is the PPO training target's. Each side runs with its own
defaults: before, ``ppo.yml``'s larger extractor and ``depth_backend="auto"`` (OpenGL); now,
the leaner extractor, the raycast kernel and the batched vector env. Their held-out
coverage is compared in ``reports/sweeps/view_planning_ppo_budgets/``, not here.

Time to beat: the default ``python train.py`` (PPO, ViewPlanning-v1) cut to
TIME_TO_BEAT_STEPS steps, whose periodic evaluation replays the same seeded episodes every
``eval_freq`` steps on its training objects. ``ppo.yml``'s learning rate decays to 0 over the
run's length, so over the shorter run it falls faster than in the first steps of the 40k
one (0.70 of its start at 6,000 steps instead of 0.85). The four-view baseline plays those same
episodes, and the time to beat is the first evaluation whose mean coverage exceeds the
baseline's (``wall_seconds`` counts from the start of learning and includes the evaluations
themselves).
"""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

from benchmarks.isolated import REPO  # noqa: E402

#: Periodic evaluation every this many steps in the time-to-beat run (the YAML's is 5000).
EVAL_FREQ = 1000
#: The time-to-beat run's length: the default run's first steps (it beat the baseline within
#: 6,000 in every measurement), not its whole 80,000.
TIME_TO_BEAT_STEPS = 20_000
#: The last commit before the compiled kernels, whose default PPO run the target is against.
BEFORE_KERNELS = "f6594a5e9a192744f6c63a2503d3dc22dec98e49"
#: PPO training on ViewPlanning-v1: at least this many times the env steps/s of before.
PPO_SPEEDUP_TARGET = 3.0
#: Rounds of the side-by-side runs (about 20 minutes each on the 2-core machine).
SIDE_BY_SIDE_ROUNDS = 3
VIEW_PLANNING = "ViewPlanning-v1"
#: (env id, algorithm, env steps): enough for a few policy updates past learning_starts.
RUNS = (
    ("ViewPlanning-v1", "ppo", 2048),
    ("ViewPlanning-v1", "sac", 1200),
    ("InstrumentGrasp-v1", "ppo", 8192),
    ("InstrumentGrasp-v1", "sac", 7000),
)


def _train(args: list[str], run_dir: Path, tree: Path = REPO) -> dict:
    """``train.py`` of the checkout ``tree`` with this interpreter; its result.json."""
    command = [sys.executable, "train.py", *args, "--run-dir", str(run_dir), "--no-progress-bar"]
    environment = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run(command, capture_output=True, text=True, cwd=tree, env=environment)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr[-3000:]}")
    return json.loads((run_dir / "result.json").read_text())


def throughput(env_id: str, algo: str, steps: int) -> dict:
    """Env steps/s of ``train.py --env env_id --algo algo`` over ``steps`` steps."""
    steady = ["--hyperparams", "learning_starts=0"] if algo == "sac" else []
    with tempfile.TemporaryDirectory() as folder:
        result = _train(
            [
                *("--env", env_id, "--algo", algo, "-n", str(steps)),
                *("--eval-freq", "0", "--save-freq", "0", "--final-episodes", "0"),
                *steady,
            ],
            Path(folder) / "run",
        )
    return {
        "timesteps": result["timesteps"],
        "seconds": result["train_seconds"],
        "steps_per_second": result["timesteps"] / result["train_seconds"],
        "update_share": result["update_seconds"] / result["train_seconds"],
    }


def default_ppo_steps() -> int:
    """The default run's budget: ViewPlanning-v1's ``n_timesteps`` in this code's ppo.yml."""
    hyperparameters = _read_yaml(REPO / "agents" / "hyperparams" / "ppo.yml")
    return int(hyperparameters[VIEW_PLANNING]["n_timesteps"])


def side_by_side(steps: int, rounds: int) -> dict:
    """Env steps/s of the default ``train.py`` before the kernels and now (see the module
    docstring) in ``rounds`` rounds of a run of ``steps`` on each side; the speed-up is the
    median of the rounds' ratios.
    Where the repository's history lacks BEFORE_KERNELS (a shallow clone), says so instead."""
    quiet = ("--eval-freq", "0", "--save-freq", "0", "--final-episodes", "0")
    with tempfile.TemporaryDirectory() as folder:
        before = Path(folder) / "before"
        archive = subprocess.run(
            ["git", "-C", str(REPO), "archive", BEFORE_KERNELS], capture_output=True, check=False
        )
        if archive.returncode != 0:
            return {"skipped": f"git archive {BEFORE_KERNELS[:12]} failed: a shallow clone?"}
        with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as files:
            files.extractall(before, filter="data")
        rates: dict[str, list[float]] = {"before": [], "now": []}
        for round_ in range(rounds):
            for side, tree in (("before", before), ("now", REPO)):
                run_dir = Path(folder) / f"{side}_{round_}"
                result = _train(["-n", str(steps), *quiet], run_dir, tree)
                rates[side].append(result["timesteps"] / result["train_seconds"])
    # Each round's ratio, its two runs minutes apart: the machine's speed drifts more than
    # that between rounds (a fifth or more within a quarter of an hour on the 2-core VM).
    ratios = sorted(now / before for before, now in zip(rates["before"], rates["now"], strict=True))
    return {
        "steps": steps,
        "before_commit": BEFORE_KERNELS,
        "before_steps_per_second": rates["before"],
        "now_steps_per_second": rates["now"],
        "round_speedups": ratios,
        "speedup": float(np.median(ratios)),
    }


def time_to_beat_four_view(timesteps: int | None = None) -> dict:
    """Train the default run for TIME_TO_BEAT_STEPS (or ``timesteps``, evaluated twice) and
    find its first periodic evaluation above the baseline."""
    sys.path.insert(0, str(REPO))
    from agents.evaluation import make_env, run_episodes
    from agents.training import PERIODIC_EVAL_SEED_OFFSET
    from agents.view_baselines import FourViewpointBaseline

    with tempfile.TemporaryDirectory() as folder:
        run_dir = Path(folder) / "run"
        length = TIME_TO_BEAT_STEPS if timesteps is None else timesteps
        eval_freq = EVAL_FREQ if timesteps is None else max(1, timesteps // 2)
        arguments = ["-n", str(length), "--eval-freq", str(eval_freq), "--final-episodes", "0"]
        result = _train(arguments, run_dir)
        config = json.loads(json.dumps(_read_yaml(run_dir / "config.yml")))
        with open(run_dir / "evaluations.csv", newline="") as stream:
            history = [{k: float(v) for k, v in row.items()} for row in csv.DictReader(stream)]
    first = config["seed"] + PERIODIC_EVAL_SEED_OFFSET
    env = make_env(config["env_id"], config["env_kwargs"])
    episodes = run_episodes(
        env, FourViewpointBaseline(env), range(first, first + config["eval_episodes"]), ["coverage"]
    )
    env.close()
    baseline = sum(e["coverage"] for e in episodes) / len(episodes)
    beaten = next((row for row in history if row["mean_metric"] > baseline), None)
    return {
        "objects": config["env_kwargs"].get("object_set", "train"),
        "baseline_coverage": baseline,
        "eval_episodes": config["eval_episodes"],
        "eval_freq": config["eval_freq"],
        "total_steps": result["timesteps"],
        "total_seconds": result["train_seconds"],
        "beaten_at_steps": None if beaten is None else int(beaten["timesteps"]),
        "beaten_at_seconds": None if beaten is None else beaten["wall_seconds"],
        "coverage_then": None if beaten is None else beaten["mean_metric"],
    }


def _read_yaml(path: Path) -> dict:
    import yaml

    return yaml.safe_load(path.read_text())
