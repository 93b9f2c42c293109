"""Sweeps on Ray Tune (``train.py --sweep``): the file's checks before Ray starts, and real
sweeps on a local Ray, each trial an ordinary run folder."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import pytest
import yaml

from agents import run_folder
from agents.config import ConfigError
from agents.sweep_file import RUNS, load_sweep, trial_name
from tests.scripts import REPO, run_script

SMOKE = REPO / "sweeps" / "smoke.yml"


def _sweep_file(tmp_path: Path, **changes) -> Path:
    content = yaml.safe_load(SMOKE.read_text())
    for key, value in changes.items():
        if value is None:
            content.pop(key, None)
        else:
            content[key] = value
    path = tmp_path / "sweep.yml"
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"seedz": [0]}, "unknown sweep"),
        ({"grid": {"hyperparams.learning_rate": "fast"}}, "must be a non-empty list"),
        ({"grid": {"n_envs": [0]}}, "n_envs must be an integer >= 1, got 0"),
        ({"grid": {"env_kwargs.view_budget": [0]}}, "view_budget"),
        ({"grid": {"env_kwargs.no_such_setting": [1]}}, "no_such_setting"),
        ({"grid": {"hyperparams.learning_rate": [1e-4]}, "search": {"samples": 2}}, "one of"),
        (
            {"grid": None, "search": {"samples": 2, "space": {"hyperparams.gamma": {"u": [0, 1]}}}},
            "unknown sweep",
        ),
        (
            {
                "grid": None,
                "search": {
                    "samples": 2,
                    "space": {"hyperparams.learning_rate": {"log_uniform": [0, 1e-3]}},
                },
            },
            "log_uniform needs low > 0",
        ),
        (
            {
                "grid": None,
                "search": {"samples": 2, "space": {"env_kwargs.view_budget": {"int": [0, 4]}}},
            },
            "view_budget",
        ),
        ({"seeds": [0, 0]}, "seeds must differ"),
        ({"resources": {"cpu": 0}}, "cpu must be above 0"),
    ],
)
def test_a_bad_sweep_file_is_refused_naming_what_is_wrong(tmp_path, changes, message):
    with pytest.raises(ConfigError, match=message):
        load_sweep(_sweep_file(tmp_path, **changes))


def test_a_sweep_refuses_a_base_without_periodic_evaluations_or_with_its_own_seed(tmp_path):
    base = yaml.safe_load(SMOKE.read_text())["base"]
    with pytest.raises(ConfigError, match="eval_freq above 0"):
        load_sweep(_sweep_file(tmp_path, base={**base, "eval_freq": 0}))
    with pytest.raises(ConfigError, match="the sweep's seeds sets it"):
        load_sweep(_sweep_file(tmp_path, base={**base, "seed": 3}))


def test_a_grid_runs_every_combination_with_every_seed_through_train_pys_checks(tmp_path):
    sweep = load_sweep(
        _sweep_file(
            tmp_path,
            grid={"hyperparams.learning_rate": [1e-4, 3e-4], "env_kwargs.view_budget": [3, 5]},
            resources={"cpu": 2},
        )
    )
    points = sweep.grid_points()
    assert points[1] == {"hyperparams.learning_rate": 1e-4, "env_kwargs.view_budget": 5}
    assert len(points) == 4
    config = sweep.run_config(points[1], seed=7)
    assert (config["seed"], config["env_kwargs"]["view_budget"]) == (7, 5)
    assert config["hyperparams"]["learning_rate"] == 1e-4
    assert config["hyperparams"]["n_steps"] == 64  # the base's, kept
    assert config["torch_threads"] == 2  # the trial's CPUs cap its threads
    assert len({trial_name(point, 0) for point in points}) == 4


def test_a_trials_cpus_cap_its_env_worker_processes(tmp_path):
    # ppo.yml steps ViewPlanning's batched scenes in two processes; trials run side by side,
    # so a trial with one CPU keeps its scenes in its own process.
    base = {**yaml.safe_load(SMOKE.read_text())["base"], "n_envs": 2, "vec_env": "batched"}
    for cpus, workers in ((2, 2), (1, 1)):
        sweep = load_sweep(_sweep_file(tmp_path, base=base, resources={"cpu": cpus}))
        assert sweep.run_config(sweep.grid_points()[0], seed=0)["env_workers"] == workers


def test_train_py_refuses_a_bad_sweep_before_ray_starts(tmp_path):
    started = time.monotonic()
    result = run_script(
        "train.py",
        "--sweep",
        str(_sweep_file(tmp_path, grid={"env_kwargs.view_budget": [0]})),
        "--run-dir",
        str(tmp_path / "sweep"),
        check=False,
        timeout=120,
    )
    assert result.returncode == 2
    assert "env_kwargs.view_budget=0" in result.stderr and "view_budget" in result.stderr
    assert not (tmp_path / "sweep").exists()
    assert time.monotonic() - started < 60  # no Ray cluster was started for it
    result = run_script("train.py", "--sweep", str(SMOKE), "--seed", "3", check=False)
    assert result.returncode == 2 and "--seed cannot be given with --sweep" in result.stderr


def _summary(folder: Path) -> list[dict]:
    with open(folder / "summary.csv") as file:
        return list(csv.DictReader(file))


@pytest.mark.cluster
def test_the_smoke_sweep_trains_run_folders_and_the_same_command_trains_nothing_again(
    tmp_path,
):
    folder = tmp_path / "smoke"
    result = run_script("train.py", "--sweep", str(SMOKE), "--run-dir", str(folder))
    assert "2 of 2 trials finished" in result.stdout
    sweep = load_sweep(SMOKE)
    run_dirs = [folder / RUNS / trial_name(sweep.grid_points()[0], seed) for seed in (0, 1)]
    for seed, run_dir in zip((0, 1), run_dirs, strict=True):
        # What train.py alone writes: its config, evaluations, checkpoints, policy.
        config = run_folder.read_config(run_dir)
        assert (config["seed"], config["hyperparams"]["learning_rate"]) == (seed, 3e-4)
        assert [row["timesteps"] for row in run_folder.read_evaluations(run_dir)] == [64, 128]
        assert (run_dir / run_folder.POLICY).is_file()
        # The trial's CPU budget (1) caps its threads.
        assert config["torch_threads"] == 1
        log = (run_dir.parent / f"{run_dir.name}.log").read_text()
        assert "threads: torch 1, numba 1" in log
    rows = _summary(folder)
    assert sorted((row["seed"], row["status"]) for row in rows) == [
        ("0", "finished"),
        ("1", "finished"),
    ]
    assert "2 of 2" in (folder / "summary.md").read_text()
    policies = [(run_dir / run_folder.POLICY).stat().st_mtime_ns for run_dir in run_dirs]

    again = run_script("train.py", "--sweep", str(SMOKE), "--run-dir", str(folder))
    assert "2 of 2 trials finished" in again.stdout
    assert [(run_dir / run_folder.POLICY).stat().st_mtime_ns for run_dir in run_dirs] == policies

    # evaluate.py scores each trial and aggregates a configuration's seeds.
    out = tmp_path / "report"
    run_script("evaluate.py", str(folder), "--episodes", "2", "--out", str(out))
    section = json.loads((out / "report.json").read_text())["environments"]["ViewPlanning-v1"]
    (aggregate,) = section["aggregates"]
    assert aggregate["group"].endswith("(hyperparams.learning_rate=0.0003)")
    assert sorted(aggregate["runs"]) == [run_dir.name for run_dir in run_dirs]
    assert aggregate["probability_of_improvement"]["over"] == "four-view"


@pytest.mark.cluster
def test_an_optuna_search_runs_each_configuration_with_every_seed(tmp_path):
    path = _sweep_file(
        tmp_path,
        grid=None,
        seeds=[0, 1],
        search={
            "samples": 2,
            "seed": 0,
            "space": {"hyperparams.learning_rate": {"log_uniform": [1e-5, 1e-3]}},
        },
        resources={"cpu": 1},
    )
    folder = tmp_path / "search"
    result = run_script("train.py", "--sweep", str(path), "--run-dir", str(folder))
    assert "4 of 4 trials finished" in result.stdout
    rows = _summary(folder)
    by_configuration: dict[str, set[str]] = {}
    for row in rows:
        by_configuration.setdefault(row["configuration"], set()).add(row["seed"])
    assert list(by_configuration.values()) == [{"0", "1"}, {"0", "1"}]
    rates = {
        run_folder.read_config(run_dir)["hyperparams"]["learning_rate"]
        for run_dir in (folder / RUNS).iterdir()
        if run_dir.is_dir()
    }
    assert len(rates) == 2 and all(1e-5 <= rate <= 1e-3 for rate in rates)


@pytest.mark.cluster
def test_a_trial_whose_worker_is_killed_on_a_two_node_cluster_resumes_its_checkpoint(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    from ray.cluster_utils import Cluster

    from agents.sweep_file import trial_record

    base = yaml.safe_load(SMOKE.read_text())["base"]
    path = _sweep_file(
        tmp_path,
        base={**base, "n_timesteps": 2048, "eval_freq": 512, "save_freq": 128},
        max_failures=2,
    )
    sweep = load_sweep(path)
    folder = tmp_path / "sweep"
    run_dirs = [folder / RUNS / trial_name(sweep.grid_points()[0], seed) for seed in (0, 1)]
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    try:
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        command = [
            sys.executable,
            "train.py",
            "--sweep",
            str(path),
            "--run-dir",
            str(folder),
            "--ray-address",
            cluster.address,
        ]
        sweep_process = subprocess.Popen(
            command,
            cwd=REPO,
            env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")},
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        deadline = time.monotonic() + 600
        killed = run_dirs[0]
        while (run_folder.latest_checkpoint(killed) or 0) < 128 or not all(
            trial_record(run_dir).is_file() for run_dir in run_dirs
        ):
            assert sweep_process.poll() is None, sweep_process.stdout.read()
            assert time.monotonic() < deadline, "no checkpoint within 10 minutes"
            time.sleep(0.2)
        workers = [json.loads(trial_record(run_dir).read_text()) for run_dir in run_dirs]
        assert workers[0]["node"] != workers[1]["node"]  # one trial on each node
        saved_before = run_folder.latest_checkpoint(killed)
        os.kill(workers[0]["pid"], signal.SIGKILL)
        output, _ = sweep_process.communicate(timeout=900)
    finally:
        cluster.shutdown()
    assert sweep_process.returncode == 0, output[-3000:]
    assert "2 of 2 trials finished" in output
    log = (killed.parent / f"{killed.name}.log").read_text()
    assert "resumed (training left)" in log, log[-2000:]
    # Its retry started from a checkpoint at least as new as the one seen before the kill.
    starts = sorted(
        int(path.name.split("_from")[1].split("_")[0]) for path in run_folder.monitor_files(killed)
    )
    assert starts[0] == 0 and starts[-1] >= saved_before
    for run_dir in run_dirs:
        assert run_folder.latest_checkpoint(run_dir) == 2048
        assert [row["timesteps"] for row in run_folder.read_evaluations(run_dir)] == [
            512,
            1024,
            1536,
            2048,
        ]


@pytest.mark.cluster
def test_an_interrupted_sweep_resumes_with_the_same_command_and_reruns_no_finished_trial(
    tmp_path,
):
    import os
    import signal
    import subprocess
    import sys

    path = _sweep_file(tmp_path, grid={"n_timesteps": [128, 2048]}, seeds=[0])
    sweep = load_sweep(path)
    folder = tmp_path / "sweep"
    short, long = (folder / RUNS / trial_name(point, 0) for point in sweep.grid_points())
    command = [sys.executable, "train.py", "--sweep", str(path), "--run-dir", str(folder)]
    environment = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    first = subprocess.Popen(
        command, cwd=REPO, env=environment, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    deadline = time.monotonic() + 600
    while not (short / run_folder.POLICY).is_file() or not run_folder.latest_checkpoint(long):
        assert first.poll() is None, first.stdout.read().decode()[-3000:]
        assert time.monotonic() < deadline, "no checkpoint within 10 minutes"
        time.sleep(0.2)
    time.sleep(2)  # Tune records the short trial as finished
    first.send_signal(signal.SIGTERM)
    output = first.communicate(timeout=300)[0].decode()
    assert first.returncode != 0 and run_folder.latest_checkpoint(long) < 2048, output[-3000:]
    finished = (short / run_folder.POLICY).stat().st_mtime_ns

    again = run_script("train.py", "--sweep", str(path), "--run-dir", str(folder))
    assert "2 of 2 trials finished" in again.stdout
    assert (short / run_folder.POLICY).stat().st_mtime_ns == finished
    assert run_folder.latest_checkpoint(long) == 2048
    assert "resumed (training left)" in (long.parent / f"{long.name}.log").read_text()
    assert "resumed" not in (short.parent / f"{short.name}.log").read_text()
