"""End-to-end smoke test of the main job: scan the mug, fuse, write a .ply."""

import json
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
