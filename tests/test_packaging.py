"""The wheel: it ships the MJCF assets, and what a model trained in the checkout needs to
load, so that the package installed on its own (no checkout on the path) makes the envs and
runs saved policies."""

import contextlib
import fcntl
import json
import os
import site
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import numpy as np
import pytest

from tests.scripts import run_script

ROOT = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def _made_once(tmp_path_factory, name: str):
    """A folder shared by every xdist worker of the session and the lock that guards it:
    the first worker to take the lock makes what is missing in it, the others then find it
    made (so the wheel is built, and the kernels in its venv compiled, once a session)."""
    session = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):  # each worker's folder lies in the session's
        session = session.parent
    folder = session / name
    folder.mkdir(exist_ok=True)
    with open(folder.parent / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield folder
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def wheel(tmp_path_factory) -> Path:
    """The package's wheel, built from this checkout."""
    with _made_once(tmp_path_factory, "wheel") as folder:
        if not list(folder.glob("liuxing_envs-*.whl")):
            subprocess.run(
                [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet"]
                + ["-w", str(folder), str(ROOT)],
                check=True,
            )
        (built,) = folder.glob("liuxing_envs-*.whl")
    return built


def _install(wheel: Path, target) -> None:
    """``wheel`` alone into the folder ``target`` (its dependencies are already installed)."""
    pip = [sys.executable, "-m", "pip", "install", "--no-deps", "--quiet"]
    subprocess.run([*pip, "--target", str(target), str(wheel)], check=True)


@pytest.mark.long
def test_wheel_ships_assets_and_loads_the_scene_without_the_checkout(wheel, tmp_path):
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {"liuxing_envs/assets/tabletop.xml", "liuxing_envs/assets/ur5e.xml"} <= names

    target = tmp_path / "site"
    _install(wheel, target)
    probe = (
        "import liuxing_envs.assets as a, liuxing_envs.sim.scene as s;"
        "print(a.assets_dir()); print(s.load_scene_model().nq)"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe],
        cwd=tmp_path,
        env={"PYTHONPATH": str(target)},
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    assert Path(out[0]) == target / "liuxing_envs" / "assets"
    assert out[1] == "6"


@pytest.fixture(scope="session")
def wheel_python(wheel, tmp_path_factory) -> Path:
    """The python of a virtual environment holding only ``wheel``, installed without its
    dependencies; it reads those from this interpreter's site-packages (a path, so their
    ``.pth`` files, among them the editable install's that puts the checkout on the path, are
    not run). Downloads nothing."""
    with _made_once(tmp_path_factory, "wheel_venv") as folder:
        python = folder / "bin" / "python"
        made = folder / "made"
        if not made.exists():
            subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(folder)], check=True)
            purelib = subprocess.run(
                [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                capture_output=True,
                text=True,
                check=True,
            ).stdout.strip()
            _install(wheel, purelib)
            dependencies = [sysconfig.get_paths()["purelib"], *site.getsitepackages()]
            (Path(purelib) / "dependencies.pth").write_text(
                "\n".join(dict.fromkeys(dependencies)) + "\n"
            )
            made.touch()
    return python


def run_in_wheel_venv(python: Path, script: str, *args: str, cwd: Path) -> dict:
    """``script`` run by the wheel's venv (the session's disk cache and GL settings, but
    nothing that puts the checkout on the path); the JSON its last line prints."""
    ran = subprocess.run(
        [str(python), "-c", script, *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=900,
        # One torch thread, as training uses: the test's neighbours need the other cores.
        env={**{k: v for k, v in os.environ.items() if k != "PYTHONPATH"}, "OMP_NUM_THREADS": "1"},
    )
    assert ran.returncode == 0, ran.stderr[-3000:]
    return json.loads(ran.stdout.splitlines()[-1])


#: Opens each script run from the wheel: the checkout's agents/ must not be importable.
_NO_CHECKOUT = """
import json, sys
try:
    import agents
except ModuleNotFoundError:
    pass
else:
    sys.exit(f"the checkout's agents/ is importable: {agents.__file__}")
import gymnasium as gym
import liuxing_envs
"""

_ACT_FROM_THE_WHEEL = (
    _NO_CHECKOUT
    + """
from stable_baselines3 import PPO

model = PPO.load(sys.argv[1], device="cpu")
env = gym.make("ViewPlanning-v1", object_set="train")
observation, _ = env.reset(seed=1_000_000)
action, _ = model.predict(observation, deterministic=True)
print(json.dumps({"package": liuxing_envs.__file__, "action": action.tolist()}))
"""
)


@pytest.mark.long
def test_a_model_trained_here_loads_and_acts_from_the_installed_wheel_alone(wheel_python, tmp_path):
    """A saved model names its features extractor by import path: one that named the
    checkout's agents/ folder failed in a pip install with "No module named 'agents'"."""
    from stable_baselines3 import PPO

    import liuxing_envs  # noqa: F401 (registers the ids)

    run = tmp_path / "run"
    run_script(
        "train.py",
        *("--env", "ViewPlanning-v1", "--algo", "ppo", "-n", "32", "--n-envs", "1"),
        *("--run-dir", str(run), "--eval-freq", "0", "--save-freq", "0"),
        *("--final-episodes", "0", "--no-progress-bar"),
        *("--hyperparams", "n_steps=32", "batch_size=32", "n_epochs=1"),
        *("env_kwargs.object_set=train", "policy_kwargs.features_extractor=perception"),
    )
    model_file = run / "model.zip"
    result = run_in_wheel_venv(wheel_python, _ACT_FROM_THE_WHEEL, str(model_file), cwd=tmp_path)
    assert not Path(result["package"]).is_relative_to(ROOT)  # the wheel's copy
    import gymnasium as gym

    env = gym.make("ViewPlanning-v1", object_set="train")
    observation, _ = env.reset(seed=1_000_000)
    expected, _ = PPO.load(model_file, device="cpu").predict(observation, deterministic=True)
    np.testing.assert_array_equal(np.asarray(result["action"], dtype=expected.dtype), expected)


#: A user's plain SB3 loop over a shipped policy: its policy.zip on the registered id, reset
#: with given seeds; and SB3's own evaluate_policy on the id as registered.
_SCORE_FROM_THE_WHEEL = (
    _NO_CHECKOUT
    + """
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.evaluation import evaluate_policy

policy_zip, algo, env_id, env_kwargs, seeds, metric = sys.argv[1:]
model = {"ppo": PPO, "sac": SAC}[algo].load(policy_zip, device="cpu")
env = gym.make(env_id, **json.loads(env_kwargs))
scores = []
for seed in json.loads(seeds):
    observation, info = env.reset(seed=seed)
    done = False
    while not done:
        action, _ = model.predict(observation, deterministic=True)
        observation, reward, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    scores.append(float(info[metric]))
mean_return, _ = evaluate_policy(model, gym.make(env_id), n_eval_episodes=2)
print(json.dumps({"scores": scores, "evaluate_policy": mean_return}))
"""
)

SHIPPED_REPORT = ROOT / "reports" / "shipped" / "report.json"


def shipped_policies() -> list[tuple[str, dict, dict]]:
    """Each shipped policy folder with the report's entry for it and its task's metric."""
    report = json.loads(SHIPPED_REPORT.read_text())
    found = []
    for env_id, entry in report["environments"].items():
        for contestant in entry["contestants"]:
            if contestant["kind"] == "policy":
                found.append((env_id, contestant, entry["metric"]))
    return found


def test_the_shipped_report_scores_every_shipped_policy_by_its_policy_zip():
    scored = {Path(c["model_file"]) for _, c, _ in shipped_policies()}
    assert scored == {p.relative_to(ROOT) for p in (ROOT / "policies").glob("*/*/policy.zip")}


@pytest.mark.long
@pytest.mark.parametrize("index", range(3))
def test_a_shipped_policy_scores_its_report_from_the_installed_wheel_alone(
    wheel_python, tmp_path, index
):
    """Plain ``SAC.load`` / ``PPO.load`` and ``predict`` on the env's raw observations, on
    the registered v1 id's held-out split with the report's episode seeds: the report's
    score, within its interval, and episode by episode."""
    from agents.run_folder import read_config
    from liuxing_envs.registration import settings_of

    env_id, contestant, metric = shipped_policies()[index]
    folder = ROOT / Path(contestant["model_file"]).parent
    (split, held_out), *defaults = sorted(
        contestant["env_kwargs"].items(), key=lambda item: not item[0].endswith("_set")
    )
    assert held_out == "held_out"
    # The rest of the report's kwargs (a recipe's run names every setting) are the id's
    # defaults, so the plain gym.make below makes the env the report scored.
    assert settings_of(env_id, **dict(defaults)) == settings_of(env_id)
    episodes = contestant["episodes"]
    result = run_in_wheel_venv(
        wheel_python,
        _SCORE_FROM_THE_WHEEL,
        *(str(folder / "policy.zip"), read_config(folder)["algo"], env_id),
        *(json.dumps({split: "held_out"}), json.dumps([e["seed"] for e in episodes]), metric),
        cwd=tmp_path,
    )
    reported = [float(e[metric]) for e in episodes]
    low, high = contestant["summary"]["ci95"]
    assert low <= np.mean(result["scores"]) <= high
    # Episode by episode too. torch's and numpy's float kernels differ in their last bits
    # between CPU families (the report was made on an Intel Xeon; an AMD EPYC differs in 2
    # of 100 ViewPlanning episodes, by at most 0.003), and a continuous action's last bit can
    # move a view, so a few episodes may differ; wrong seeds or settings change nearly all.
    same = np.isclose(result["scores"], reported, rtol=0.0, atol=1e-9)
    assert same.mean() >= 0.9, f"episodes {np.flatnonzero(~same).tolist()} differ"
    assert np.isfinite(result["evaluate_policy"])
