"""The wheel: it ships the MJCF assets, and what a model trained in the checkout needs to
load, so that the package installed on its own (no checkout on the path) makes the envs and
runs saved policies."""

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


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The package's wheel, built from this checkout."""
    folder = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--quiet",
            "-w",
            str(folder),
            str(ROOT),
        ],
        check=True,
    )
    (built,) = folder.glob("liuxing_envs-*.whl")
    return built


def _install(wheel: Path, target) -> None:
    """``wheel`` alone into the folder ``target`` (its dependencies are already installed)."""
    pip = [sys.executable, "-m", "pip", "install", "--no-deps", "--quiet"]
    subprocess.run([*pip, "--target", str(target), str(wheel)], check=True)


@pytest.mark.slow
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


def _throwaway_venv(folder: Path, wheel: Path) -> Path:
    """A virtual environment holding only ``wheel``, installed without its dependencies; it
    reads those from this interpreter's site-packages (a path, so their ``.pth`` files, among
    them the editable install's that puts the checkout on the path, are not run). Downloads
    nothing. Returns its python."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(folder)], check=True)
    python = folder / "bin" / "python"
    purelib = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    _install(wheel, purelib)
    dependencies = [sysconfig.get_paths()["purelib"], *site.getsitepackages()]
    (Path(purelib) / "dependencies.pth").write_text("\n".join(dict.fromkeys(dependencies)) + "\n")
    return python


_ACT_FROM_THE_WHEEL = """
import json, sys
import gymnasium as gym
import liuxing_envs
from stable_baselines3 import PPO

try:
    import agents
except ModuleNotFoundError:
    pass
else:
    sys.exit(f"the checkout's agents/ is importable: {agents.__file__}")
model = PPO.load(sys.argv[1], device="cpu")
env = gym.make("ViewPlanning-v1", object_set="train")
observation, _ = env.reset(seed=1_000_000)
action, _ = model.predict(observation, deterministic=True)
print(json.dumps({"package": liuxing_envs.__file__, "action": action.tolist()}))
"""


@pytest.mark.slow
def test_a_model_trained_here_loads_and_acts_from_the_installed_wheel_alone(wheel, tmp_path):
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
    python = _throwaway_venv(tmp_path / "venv", wheel)
    acted = subprocess.run(
        [str(python), "-c", _ACT_FROM_THE_WHEEL, str(model_file)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        # The session's disk cache and GL settings, but nothing that puts the checkout on the path.
        env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
    )
    assert acted.returncode == 0, acted.stderr[-3000:]
    result = json.loads(acted.stdout.splitlines()[-1])
    assert not Path(result["package"]).is_relative_to(ROOT)  # the wheel's copy
    import gymnasium as gym

    env = gym.make("ViewPlanning-v1", object_set="train")
    observation, _ = env.reset(seed=1_000_000)
    expected, _ = PPO.load(model_file, device="cpu").predict(observation, deterministic=True)
    np.testing.assert_array_equal(np.asarray(result["action"], dtype=expected.dtype), expected)
