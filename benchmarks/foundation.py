"""Cost of the simulation core: IK, motion, depth rendering and back-projection.

Run: ``MUJOCO_GL=egl python -m benchmarks.foundation`` (prints a Markdown table).
Figures are medians over repeats on whatever machine runs it.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from liuxing_envs.sim import (  # noqa: E402
    HOME_QPOS,
    Arm,
    CameraIntrinsics,
    DepthCamera,
    load_scene_model,
    reset_to_home,
    view_grid,
)

TABLE_POINT = np.array([0.5, 0.0, 0.0])


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def hemisphere():
    """The IK acceptance grid of tests/test_arm.py."""
    elevations = np.deg2rad([20, 35, 50, 65, 80, 90])
    return view_grid(
        TABLE_POINT, (0.30, 0.375, 0.45), elevations, np.deg2rad(np.arange(0, 360, 30))
    )


def main() -> None:
    argparse.ArgumentParser(
        prog="python -m benchmarks.foundation", description=__doc__.splitlines()[0]
    ).parse_args()  # no options: --help, and a clear error on anything else
    model = load_scene_model()
    data = mujoco.MjData(model)
    reset_to_home(model, data)
    arm = Arm(model, data)
    rows = []

    solved, ik_times, qs = 0, [], []
    for eye, rotation in hemisphere():
        start = time.perf_counter()
        result = arm.solve_ik(eye, rotation)
        ik_times.append(time.perf_counter() - start)
        solved += result.success
        if result.success:
            qs.append(result.qpos)
    rows.append(("IK reach, hemisphere r 0.30-0.45 m, elev 20-90 deg", f"{solved}/{len(ik_times)}"))
    rows.append(("IK solve, median (ms)", f"{1e3 * np.median(ik_times):.2f}"))

    def kinematic_round_trip():
        arm.move_to(qs[7], "kinematic")
        arm.move_to(HOME_QPOS, "kinematic")

    rows.append(
        ("kinematic move there and back (ms)", f"{median_ms(kinematic_round_trip, 50):.2f}")
    )
    start = time.perf_counter()
    result = arm.move_to(qs[7], "dynamic")
    wall = time.perf_counter() - start
    rows.append(
        (
            "dynamic move home -> view (sim s / wall ms)",
            f"{result.sim_time:.2f} / {1e3 * wall:.1f}",
        )
    )
    reset_to_home(model, data)

    for size in (64, 128):
        for backend in ("gl", "raycast"):
            intrinsics = CameraIntrinsics(width=size, height=size)
            with DepthCamera(model, intrinsics=intrinsics, backend=backend) as camera:
                camera.render(data)
                ms = median_ms(lambda cam=camera: cam.render(data), 200)
                depth = camera.render(data)
                back = median_ms(lambda cam=camera, d=depth: cam.points_world(d, data), 200)
            rows.append((f"depth {size}x{size} {backend} render (ms)", f"{ms:.2f}"))
        rows.append((f"back-projection {size}x{size} to world (ms)", f"{back:.3f}"))

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
        f"mujoco {mujoco.__version__}, MUJOCO_GL={os.environ['MUJOCO_GL']}\n"
    )
    print("| measurement | value |\n| --- | --- |")
    for name, value in rows:
        print(f"| {name} | {value} |")


if __name__ == "__main__":
    main()
