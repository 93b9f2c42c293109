"""The compiled depth kernel (``"raycast"`` with numba) against ``"multiray"`` (MuJoCo's
``mj_multiRay``) over many seeded views: how many
pixels differ (the kernel must give ``mj_multiRay``'s image bit for bit) and what an image
costs with each, with and without the arm in view.

Run: ``MUJOCO_GL=egl python -m benchmarks.depth_kernel_check [--views 2000]`` (prints a
Markdown summary; ``--json`` also writes the figures). The views are ViewPlanning-v1's
scenes (train, held-out and procedural objects), half at the views random actions reach and
half at random joint angles around home, which often show arm links. Each image is
rendered by both backends into the same stand-in scene the env casts into; the ray-cast
backend is timed as the env uses it (with its table shortcut) and compared against casting
every ray. Timing alternates the backends per view and keeps the fastest of five renders
of each.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from liuxing_envs.envs.view_planning import ViewPlanningEnv  # noqa: E402
from liuxing_envs.sim.camera import CameraIntrinsics, DepthCamera  # noqa: E402
from liuxing_envs.sim.objects import OBJECT_SETS  # noqa: E402
from liuxing_envs.sim.scene import HOME_QPOS, WRIST_CAMERA  # noqa: E402

#: The object sets the views are spread over, and the objects of each.
OBJECTS = {
    "train": list(OBJECT_SETS["train"]),
    "held_out": list(OBJECT_SETS["held_out"]),
    "procedural": list(OBJECT_SETS["procedural"])[::8],
}
REPEATS = 5


def _best_of(render, repeats: int = REPEATS) -> tuple[np.ndarray, float]:
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        image = render()
        best = min(best, time.perf_counter() - start)
    return image, best


def _look(scene, cameras: dict, figures: dict, index: int) -> None:
    """Render the current view with each camera into the env's stand-in scene."""
    placed = scene.placed
    stand_ins = scene.stand_ins(placed.name, placed.scale)
    ray_scene = stand_ins.ray_scene(scene.data, placed, cameras["multiray"])
    arm = ray_scene[0] is stand_ins.model
    data = scene.data
    reference = cameras["every_ray"].render(data, scene=ray_scene)
    order = ("multiray", "compiled") if index % 2 else ("compiled", "multiray")
    images = {}
    for name in order:
        camera = cameras[name]
        images[name], seconds = _best_of(lambda c=camera: c.render(data, scene=ray_scene))
        figures["times_ms"][name][arm].append(seconds * 1e3)
    differing = int((images["compiled"] != reference).sum())
    figures["views"] += 1
    figures["views_with_arm"] += arm
    figures["views_differing"] += differing > 0
    figures["pixels_differing"] += differing
    figures["pixels_differing_from_shortcut_image"] += int(
        (images["compiled"] != images["multiray"]).sum()
    )


def check(views: int = 2000, resolution: int = 64, seed: int = 0) -> dict:
    """Compare the backends over ``views`` seeded views; returns the figures."""
    intrinsics = CameraIntrinsics(width=resolution, height=resolution)
    per_set = [views // len(OBJECTS)] * len(OBJECTS)
    per_set[0] += views - sum(per_set)
    figures = {
        "views": 0,
        "views_differing": 0,
        "pixels_differing": 0,
        "pixels_differing_from_shortcut_image": 0,
        "views_with_arm": 0,
        "times_ms": {"multiray": {True: [], False: []}, "compiled": {True: [], False: []}},
    }
    rng = np.random.default_rng(seed)
    for objects, count in zip(OBJECTS.values(), per_set, strict=True):
        env = ViewPlanningEnv(
            depth_backend="multiray", objects=objects, scales=(1.0,), coverage_samples=1024
        )
        env.action_space.seed(int(rng.integers(1 << 30)))
        scene = env.scene
        multiray = DepthCamera(scene.model, WRIST_CAMERA, intrinsics, backend="multiray")
        every_ray = DepthCamera(scene.model, WRIST_CAMERA, intrinsics, backend="multiray")
        every_ray.active_backend.use_table_shortcut = False
        compiled = DepthCamera(scene.model, WRIST_CAMERA, intrinsics, backend="raycast")

        cameras = {"multiray": multiray, "every_ray": every_ray, "compiled": compiled}
        env.reset(seed=int(rng.integers(1 << 30)))
        for index in range(count):
            if index % 2 == 0:
                qpos = HOME_QPOS + rng.uniform(-0.7, 0.7, HOME_QPOS.size)
                scene.look_from(qpos, functools.partial(_look, scene, cameras, figures, index))
                continue
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            _look(scene, cameras, figures, index)
            if terminated or truncated:
                env.reset(seed=int(rng.integers(1 << 30)))
        for camera in (multiray, every_ray, compiled):
            camera.close()
        env.close()
    times = figures.pop("times_ms")
    summary = {}
    for name, by_arm in times.items():
        for arm, values in by_arm.items():
            key = f"{name}_{'with' if arm else 'without'}_arm"
            summary[key] = {
                "views": len(values),
                "median_ms": float(np.median(values)) if values else None,
                "mean_ms": float(np.mean(values)) if values else None,
            }
        every = by_arm[True] + by_arm[False]
        summary[f"{name}_all"] = {
            "views": len(every),
            "median_ms": float(np.median(every)),
            "mean_ms": float(np.mean(every)),
        }
    figures["ms_per_image"] = summary
    figures["resolution"] = resolution
    return figures


def report(figures: dict) -> str:
    lines = [
        f"# Compiled depth kernel against mj_multiRay ({figures['views']} views, "
        f"{figures['resolution']}x{figures['resolution']})",
        "",
        f"- Pixels differing from casting every ray with mj_multiRay: "
        f"{figures['pixels_differing']} (in {figures['views_differing']} views)",
        f"- Pixels differing from the multiray backend's image (table shortcut on): "
        f"{figures['pixels_differing_from_shortcut_image']}",
        f"- Views with the arm in the cast scene: {figures['views_with_arm']}",
        "",
        "| images | views | multiray ms (median / mean) | compiled ms (median / mean) | ratio |",
        "|---|---|---|---|---|",
    ]
    times = figures["ms_per_image"]
    for label, suffix in (("arm in view", "with_arm"), ("no arm", "without_arm"), ("all", "all")):
        old, new = times[f"multiray_{suffix}"], times[f"compiled_{suffix}"]
        if not old["views"]:
            continue
        lines.append(
            f"| {label} | {old['views']} | {old['median_ms']:.3f} / {old['mean_ms']:.3f} | "
            f"{new['median_ms']:.3f} / {new['mean_ms']:.3f} | "
            f"{old['median_ms'] / new['median_ms']:.2f}x |"
        )
    lines += ["", "Times: the fastest of five renders per view (DepthCamera.render into the "]
    lines[-1] += "env's stand-in scene), the backends alternating."
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.depth_kernel_check", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--views", type=int, default=2000, help="seeded views (default 2000)")
    parser.add_argument("--resolution", type=int, default=64, help="image side in pixels")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    figures = check(args.views, args.resolution, args.seed)
    print(report(figures))
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
