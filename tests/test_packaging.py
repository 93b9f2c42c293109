"""The wheel ships the MJCF assets and the resolver finds them outside a checkout."""

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_wheel_ships_assets_and_loads_the_scene_without_the_checkout(tmp_path):
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--quiet",
            "-w",
            str(tmp_path),
            str(ROOT),
        ],
        check=True,
    )
    (wheel,) = tmp_path.glob("liuxing_envs-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {"liuxing_envs/assets/tabletop.xml", "liuxing_envs/assets/ur5e.xml"} <= names

    site = tmp_path / "site"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "--quiet",
            "--target",
            str(site),
            str(wheel),
        ],
        check=True,
    )
    probe = (
        "import liuxing_envs.assets as a, liuxing_envs.sim.scene as s;"
        "print(a.assets_dir()); print(s.load_scene_model().nq)"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe],
        cwd=tmp_path,
        env={"PYTHONPATH": str(site)},
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    assert Path(out[0]) == site / "liuxing_envs" / "assets"
    assert out[1] == "6"
