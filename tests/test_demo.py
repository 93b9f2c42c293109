"""End-to-end smoke test of the main job: scan the mug, fuse, write a .ply."""

import json
import os
import subprocess
import sys

import numpy as np
import open3d as o3d
import pytest

from liuxing_envs.demo import main


@pytest.mark.parametrize(("backend", "motion"), [("raycast", "kinematic"), ("gl", "dynamic")])
def test_scan_writes_a_cloud_of_the_mug(tmp_path, backend, motion):
    code = main(
        [
            "--out",
            str(tmp_path),
            "--views",
            "4",
            "--resolution",
            "64",
            "--backend",
            backend,
            "--motion",
            motion,
        ]
    )
    assert code == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["backend"] == backend and summary["views_captured"] == 4
    points = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "scan.ply")).points)
    assert len(points) == summary["fused_points"] > 200
    # Every fused point is on the mug (radius 4 cm, 10 cm tall, handle to y = 7.5 cm),
    # none on the table or the arm.
    assert points[:, 2].min() > 0.0 and points[:, 2].max() <= 0.1 + 1e-3
    radial = np.hypot(points[:, 0] - 0.5, points[:, 1])
    assert radial.max() <= 0.0755
    assert len(list(tmp_path.glob("depth_*.npy"))) == 4


def test_bad_flags_exit_with_a_clear_message():
    result = subprocess.run(
        [sys.executable, "-m", "liuxing_envs.demo", "--views", "0"],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 2
    assert "--views must be at least 1, got 0" in result.stderr


def _refused(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as exit_:
        main(list(argv))
    assert exit_.value.code == 2
    return " ".join(capsys.readouterr().err.split())


def test_an_out_that_is_a_file_or_not_writable_is_refused(tmp_path, capsys):
    file = tmp_path / "scan.ply"
    file.write_text("not a folder")
    error = _refused(capsys, "--out", str(file))
    assert f"--out {file}: {file} is a file, not a folder" in error
    error = _refused(capsys, "--out", str(file / "inside"))
    assert f"{file} is a file, not a folder" in error
    assert file.read_text() == "not a folder"
    if os.geteuid() != 0:  # root writes whatever the permissions say
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        assert "cannot write into the folder" in _refused(capsys, "--out", str(locked))
        assert "cannot create the folder" in _refused(capsys, "--out", str(locked / "sub"))


def test_a_rerun_with_fewer_views_leaves_only_its_own_depth_images(tmp_path, capsys):
    quick = ("--resolution", "16", "--backend", "raycast", "--out", str(tmp_path))
    assert main(["--views", "4", *quick]) == 0
    # Files the scan did not write stay, whatever their names; a link named like a depth
    # image goes, not the file it points to.
    kept = {"notes.txt": "mine", "depth_5.npy": "not the scan's name", "depth_old.npy": "mine"}
    for name, text in kept.items():
        (tmp_path / name).write_text(text)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "depth.npy").write_text("linked")
    (tmp_path / "depth_03.npy").unlink()
    (tmp_path / "depth_03.npy").symlink_to(elsewhere / "depth.npy")
    assert main(["--views", "2", *quick]) == 0
    assert sorted(p.name for p in tmp_path.glob("depth_??.npy")) == ["depth_00.npy", "depth_01.npy"]
    assert {name: (tmp_path / name).read_text() for name in kept} == kept
    assert (elsewhere / "depth.npy").read_text() == "linked"
    assert json.loads((tmp_path / "summary.json").read_text())["views_requested"] == 2
    # A folder with an output's name is neither removed nor written into.
    (tmp_path / "scan.ply").unlink()
    (tmp_path / "scan.ply").mkdir()
    error = _refused(capsys, "--views", "2", *quick)
    assert f"{tmp_path / 'scan.ply'} is a folder, where the scan writes a file" in error


def test_motion_help_lists_the_choices(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    motion = text.split("--motion {kinematic,dynamic}")[-1].split("--resolution")[0]
    assert "kinematic" in motion and "dynamic" in motion and "default: kinematic" in motion


def test_a_scan_that_captures_nothing_says_so_and_keeps_its_summary(tmp_path, capsys):
    # Straight down from 0.8 m is out of reach: no view, no points. It ended in open3d's
    # "could not write scan.ply" traceback, with no summary.json.
    quick = ("--resolution", "16", "--backend", "raycast", "--out", str(tmp_path))
    assert main(["--views", "4", *quick]) == 0  # an earlier scan's scan.ply goes
    assert main(["--views", "1", "--radius", "0.8", "--elevation", "90", *quick]) == 1
    assert "captured 0/1 views" in capsys.readouterr().out
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["views_captured"] == 0 and summary["ply"] is None
    assert not (tmp_path / "scan.ply").exists()
