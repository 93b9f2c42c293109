"""ViewPlanning's own vector env and SB3's adapter of it: the same episodes as single envs."""

import csv

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

import liuxing_envs  # noqa: F401  (registers the ids)
from agents.batched_vec_env import BatchedVecEnv
from liuxing_envs.envs.view_planning_vector import ViewPlanningVectorEnv

ENV_ID = "ViewPlanning-v1"
#: Small settings; the arm's refusals and views that show the arm come from the actions.
FAST = {"objects": ["box", "mug", "l_bracket"], "scales": (0.9, 1.1), "coverage_samples": 2048}
N = 3


def assert_same(a, b, where="") -> None:
    """Equal, recursively through dicts, tuples and arrays (object arrays included)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{where}: {a.keys()} != {b.keys()}"
        for key in a:
            assert_same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, (list, tuple)) or (isinstance(a, np.ndarray) and a.dtype == object):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=where)
        assert a.dtype == np.asarray(b).dtype, where
    else:
        assert a == b or (a != a and b != b), f"{where}: {a!r} != {b!r}"


#: Low and far on the side away from the arm: out of its reach, so the view is refused.
UNREACHABLE = [0.0, -1.0, 1.0]


def actions(seed: int, steps: int) -> np.ndarray:
    """Seeded actions over the whole range, and a few views the arm cannot reach."""
    chosen = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, N, 3))
    chosen[1::5, 0] = UNREACHABLE
    return chosen


def test_make_vec_gives_the_vector_env_with_the_episodes_of_single_envs():
    single = gym.make_vec(
        ENV_ID,
        N,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP},
        **FAST,
    )
    batched = gym.make_vec(ENV_ID, N, **FAST)
    assert isinstance(batched, ViewPlanningVectorEnv)
    assert batched.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert batched.action_space == single.action_space
    assert batched.observation_space == single.observation_space
    assert_same(batched.reset(seed=[5, 9, 2]), single.reset(seed=[5, 9, 2]), "reset")
    refused = ended = 0
    for t, step_actions in enumerate(actions(0, 14)):  # 3 episodes of 4 views and then some
        got, expected = batched.step(step_actions), single.step(step_actions)
        assert_same(got, expected, f"step {t}")
        refused += int(got[4]["refused"].sum())
        ended += int(got[4].get("_final_obs", np.zeros(N)).sum())
    assert refused > 0 and ended == 3 * N  # both branches were taken
    # A seed as an int gives scene i the seed s + i, as Gymnasium's vector envs do.
    assert_same(batched.reset(seed=7), single.reset(seed=7), "reset(seed=7)")
    batched.close()
    single.close()


def test_a_reset_mask_resets_only_the_scenes_it_marks():
    envs = ViewPlanningVectorEnv(N, **FAST)
    envs.reset(seed=0)
    envs.step(actions(1, 1)[0])
    views_used = envs.get_attr("views_used")
    assert views_used == (1, 1, 1)
    mask = np.array([False, True, False])
    _, infos = envs.reset(seed=0, options={"reset_mask": mask})
    assert envs.get_attr("views_used") == (1, 0, 1)
    assert infos["_coverage"].tolist() == mask.tolist()
    with pytest.raises(ValueError, match="reset_mask"):
        envs.reset(options={"reset_mask": np.zeros(N, dtype=bool)})
    envs.close()


@pytest.mark.parametrize("num_envs", [0, 2.5, True, "2"])
def test_a_bad_number_of_scenes_is_refused_by_name(num_envs):
    with pytest.raises(ValueError, match="num_envs"):
        ViewPlanningVectorEnv(num_envs, **FAST)


def monitor_rows(path):
    with open(path) as file:
        next(file)  # the JSON header: its start time differs
        return [{k: v for k, v in row.items() if k != "t"} for row in csv.DictReader(file)]


def test_sb3_adapter_steps_as_dummy_vec_env_over_monitored_envs(tmp_path):
    dummy_files = [str(tmp_path / f"dummy{i}") for i in range(N)]
    batched_files = [str(tmp_path / f"batched{i}.monitor.csv") for i in range(N)]
    dummy = DummyVecEnv(
        [
            lambda path=path: Monitor(gym.make(ENV_ID, **FAST), path, info_keywords=("coverage",))
            for path in dummy_files
        ]
    )
    batched = BatchedVecEnv(gym.make_vec(ENV_ID, N, **FAST), batched_files, ("coverage",))
    for venv in (dummy, batched):
        venv.seed(11)
    assert_same(batched.reset(), dummy.reset(), "reset")
    assert_same(batched.reset_infos, dummy.reset_infos, "reset_infos")
    ended = 0
    for t, step_actions in enumerate(actions(2, 10)):
        got, expected = batched.step(step_actions), dummy.step(step_actions)
        ended += sum("terminal_observation" in info for info in got[3])
        names = ("obs", "rewards", "dones", "infos")
        for value, reference, name in zip(got, expected, names, strict=True):
            if name == "infos":  # the episode's time differs
                for info in (*value, *reference):
                    info.get("episode", {}).pop("t", None)
            assert_same(value, reference, f"step {t} {name}")
        assert got[1].dtype == expected[1].dtype
        assert_same(batched.reset_infos, dummy.reset_infos, f"step {t} reset_infos")
    assert ended == 2 * N
    assert batched.get_attr("views_used") == dummy.get_attr("views_used")
    batched.close()
    dummy.close()
    for ours, theirs in zip(batched_files, dummy_files, strict=True):
        rows = monitor_rows(ours)
        assert len(rows) == 2 and rows == monitor_rows(theirs + ".monitor.csv")


def test_the_adapter_refuses_a_vector_env_that_resets_on_the_next_step():
    envs = gym.make_vec(ENV_ID, 1, vectorization_mode="sync", **FAST)
    with pytest.raises(ValueError, match="SAME_STEP"):
        BatchedVecEnv(envs)
    envs.close()


def test_scenes_in_worker_processes_give_the_same_episodes():
    # Scene 0 in this process, scenes 1 and 2 in two workers: every reset, step, autoreset
    # and attribute the same as all three here; a worker's error is raised here by name.
    here = ViewPlanningVectorEnv(N, **FAST)
    spread = ViewPlanningVectorEnv(N, workers=3, **FAST)
    assert len(spread.worker_pids) == 2 and here.worker_pids == ()
    assert_same(spread.reset(seed=[4, 8, 1]), here.reset(seed=[4, 8, 1]), "reset")
    ended = 0
    for t, step_actions in enumerate(actions(3, 10)):
        got = spread.step(step_actions)
        assert_same(got, here.step(step_actions), f"step {t}")
        ended += int(got[4].get("_final_obs", np.zeros(N)).sum())
    assert ended == 2 * N
    mask = np.array([False, True, True])
    assert_same(
        spread.reset(seed=5, options={"reset_mask": mask}),
        here.reset(seed=5, options={"reset_mask": mask}),
        "masked reset",
    )
    assert spread.get_attr("views_used") == here.get_attr("views_used")
    assert spread.get_attr("views_used", indices=[2, 0]) == here.get_attr("views_used")[::-2]
    spread.set_attr("label", ["b", "c"], indices=[2, 1])  # an attribute of the user's
    assert spread.get_attr("label", indices=[1, 2]) == ("c", "b")
    assert_same(
        spread.call_at([1], "view_to_action", 0.0, 0.5, 0.4),
        here.call_at([1], "view_to_action", 0.0, 0.5, 0.4),
        "call_at",
    )
    bad = np.zeros((N, 3))
    bad[2, 1] = np.nan  # the last scene's: in a worker
    with pytest.raises(ValueError, match="finite"):
        spread.step(bad)
    here.close()
    spread.close()


def test_a_dead_worker_is_named_at_the_next_call_instead_of_hanging():
    import os
    import signal

    envs = ViewPlanningVectorEnv(N, workers=2, **FAST)
    envs.reset(seed=0)
    (pid,) = envs.worker_pids
    os.kill(pid, signal.SIGKILL)
    with pytest.raises(RuntimeError, match="scenes 2-2 died"):
        envs.step(actions(0, 1)[0])
    envs.close()  # closing with a dead worker does not hang either


@pytest.mark.parametrize("workers", [0, N + 1, 1.5, True])
def test_a_bad_number_of_workers_is_refused_by_name(workers):
    with pytest.raises(ValueError, match="workers must be a whole number from 1 to num_envs"):
        ViewPlanningVectorEnv(N, workers=workers, **FAST)


_EXIT_WITHOUT_CLOSING = """
from liuxing_envs.envs.view_planning_vector import ViewPlanningVectorEnv
envs = ViewPlanningVectorEnv(2, workers=2, objects=["box"], scales=(1.0,), coverage_samples=2048)
envs.reset(seed=0)
print("made")
"""


def test_a_process_that_never_closes_its_workers_still_exits():
    # At exit multiprocessing sends SIGTERM to daemon workers and waits for them; a worker
    # ignores SIGTERM (a signal to the process group is the parent's to handle), so the
    # vector env must close its workers first or the process never ends.
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-c", _EXIT_WITHOUT_CLOSING], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0 and done.stdout.strip() == "made", done.stderr[-2000:]
