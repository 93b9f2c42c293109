"""Scan an object on the table with the wrist depth camera and save the fused point cloud.

The arm visits viewpoints on a ring around the object (inverse kinematics, collision-checked
motion), renders a depth image at each, back-projects it to world-frame points, crops them
to the space above the table, and fuses everything into one voxel-downsampled cloud written
as a .ply (plus one .npy depth image per view). Run ``python -m liuxing_envs.demo --help``.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

from liuxing_envs.opengl import mujoco_import_problem, use_headless_default

if __name__ == "__main__":  # before mujoco is imported: it reads MUJOCO_GL once, on import
    use_headless_default()
    if problem := mujoco_import_problem():
        print(f"python -m liuxing_envs.demo: error: {problem}", file=sys.stderr)
        sys.exit(2)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from liuxing_envs.open3d_import import o3d  # noqa: E402
from liuxing_envs.output_folders import OutputFolderError, prepare_output_folder  # noqa: E402
from liuxing_envs.perception.pointcloud import crop_points  # noqa: E402
from liuxing_envs.sim.arm import MOTION_MODES, Arm  # noqa: E402
from liuxing_envs.sim.camera import BACKENDS, CameraIntrinsics, DepthCamera  # noqa: E402
from liuxing_envs.sim.scene import WRIST_CAMERA, load_scene_spec, reset_to_home  # noqa: E402
from liuxing_envs.sim.viewpoints import sphere_viewpoint  # noqa: E402

DEMO_OBJECT_CENTER = (0.5, 0.0)
DEMO_VIEWS = 8
DEMO_RADIUS = 0.4
DEMO_ELEVATION_DEG = 45.0
DEMO_VOXEL_SIZE = 0.003  # m
DEMO_RESOLUTION = 128  # pixels, square
#: Points kept: above the table top (sensor noise and table-edge pixels stay out) and
#: within this box around the object.
WORKSPACE_HALF_WIDTH = 0.25  # m
TABLE_CLEARANCE = 0.003  # m
#: The files a scan writes into its folder (depth images are depth_00.npy, depth_01.npy, ...).
OUTPUT_FILES = ("scan.ply", "summary.json")
DEPTH_FILE = re.compile(r"depth_\d{2,}\.npy")


#: The mug's primitives: (name, geom type, MuJoCo size, position in the mug's frame), metres.
MUG_PARTS = (
    ("mug_body", mujoco.mjtGeom.mjGEOM_CYLINDER, (0.04, 0.05, 0.0), (0.0, 0.0, 0.05)),
    ("mug_handle_top", mujoco.mjtGeom.mjGEOM_BOX, (0.006, 0.02, 0.006), (0.0, 0.055, 0.08)),
    ("mug_handle_side", mujoco.mjtGeom.mjGEOM_BOX, (0.006, 0.006, 0.033), (0.0, 0.069, 0.053)),
    ("mug_handle_bottom", mujoco.mjtGeom.mjGEOM_BOX, (0.006, 0.02, 0.006), (0.0, 0.055, 0.026)),
)
MUG_RGBA = (0.85, 0.3, 0.25, 1.0)


def add_demo_object(spec: mujoco.MjSpec, center_xy=DEMO_OBJECT_CENTER) -> None:
    """A mug (a cylinder with a handle) built from primitives, standing at ``center_xy``."""
    mug = spec.worldbody.add_body(name="demo_mug", pos=[center_xy[0], center_xy[1], 0.0])
    for name, geom_type, size, pos in MUG_PARTS:
        mug.add_geom(name=name, type=geom_type, size=list(size), pos=list(pos), rgba=list(MUG_RGBA))


def scan(
    out_dir: Path,
    views: int = DEMO_VIEWS,
    radius: float = DEMO_RADIUS,
    elevation_deg: float = DEMO_ELEVATION_DEG,
    backend: str = "auto",
    motion: str = "kinematic",
    resolution: int = DEMO_RESOLUTION,
    voxel_size: float = DEMO_VOXEL_SIZE,
) -> dict:
    """Run the scan and write ``scan.ply``, ``depth_XX.npy`` and ``summary.json`` to out_dir.

    Those files from an earlier scan into out_dir are removed first, so that the folder holds
    one scan's outputs only (a depth image of a view this scan did not capture would pass
    for one of it); other files in out_dir are left alone."""
    spec = load_scene_spec()
    add_demo_object(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    reset_to_home(model, data)
    arm = Arm(model, data)
    intrinsics = CameraIntrinsics(width=resolution, height=resolution)
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_outputs(out_dir)
    center = np.array([*DEMO_OBJECT_CENTER, 0.05])
    lower = center - [WORKSPACE_HALF_WIDTH, WORKSPACE_HALF_WIDTH, center[2] - TABLE_CLEARANCE]
    upper = center + WORKSPACE_HALF_WIDTH

    clouds, visited = [], []
    started = time.perf_counter()
    with DepthCamera(model, WRIST_CAMERA, intrinsics=intrinsics, backend=backend) as camera:
        for k, azimuth in enumerate(np.linspace(0, 2 * np.pi, views, endpoint=False)):
            eye, rotation = sphere_viewpoint(center, azimuth, np.deg2rad(elevation_deg), radius)
            ik = arm.solve_ik(eye, rotation)
            view = {"azimuth_deg": round(float(np.rad2deg(azimuth)), 1), "ik_success": ik.success}
            if ik.success:
                motion_result = arm.move_to(ik.qpos, motion)
                view.update(
                    reached=motion_result.reached,
                    collided=motion_result.collided,
                    path_length_rad=round(motion_result.path_length, 4),
                )
                if motion_result.reached:
                    depth = camera.render(data)
                    np.save(out_dir / f"depth_{k:02d}.npy", depth)
                    points = crop_points(camera.points_world(depth, data), lower, upper)
                    clouds.append(points)
                    view["points"] = len(points)
            visited.append(view)
            print(f"view {k + 1}/{views}: {view}", flush=True)
        backend_used = camera.backend
    elapsed = time.perf_counter() - started

    cloud = o3d.geometry.PointCloud()
    if clouds:
        cloud.points = o3d.utility.Vector3dVector(np.concatenate(clouds))
    fused = cloud.voxel_down_sample(voxel_size)
    ply_path = out_dir / "scan.ply"
    # open3d writes no file for an empty cloud (no view reached, or nothing above the table).
    if fused.has_points() and not o3d.io.write_point_cloud(str(ply_path), fused):
        raise OSError(f"open3d could not write {ply_path}")
    summary = {
        "ply": str(ply_path) if fused.has_points() else None,
        "backend": backend_used,
        "motion": motion,
        "views_requested": views,
        "views_captured": len(clouds),
        "raw_points": int(sum(len(c) for c in clouds)),
        "fused_points": len(fused.points),
        "voxel_size_m": voxel_size,
        "seconds": round(elapsed, 3),
        "views": visited,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def _is_output(name: str) -> bool:
    return name in OUTPUT_FILES or DEPTH_FILE.fullmatch(name) is not None


def remove_outputs(out_dir: Path) -> list[Path]:
    """Remove the files a scan writes (:data:`OUTPUT_FILES` and depth images) from
    ``out_dir``: only files and links with exactly those names go. A link goes, not what it
    points to, which the scan would otherwise overwrite through it. Returns what was removed."""
    removed = []
    for path in sorted(out_dir.iterdir()):
        if _is_output(path.name) and (path.is_symlink() or path.is_file()):
            path.unlink()
            removed.append(path)
    return removed


def _check_out(parser: argparse.ArgumentParser, out: Path) -> None:
    """``out`` is, or can be made, a folder the scan can write its files into."""
    try:
        prepare_output_folder(out)
    except OutputFolderError as error:
        parser.error(f"--out {out}: {error}; --out names the folder the scan writes into")
    try:
        contents = list(out.iterdir())
    except OSError as error:
        parser.error(f"--out {out}: cannot list the folder: {error.strerror or error}")
    for path in contents:
        if _is_output(path.name) and path.is_dir() and not path.is_symlink():
            parser.error(f"--out {out}: {path} is a folder, where the scan writes a file")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m liuxing_envs.demo",
        description="Scan a mug with the wrist depth camera and write the fused cloud (.ply).",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("outputs/demo"),
        help="output folder (created if missing; default: %(default)s): scan.ply, summary.json "
        "and depth_NN.npy; those files from an earlier scan are removed first, others are kept",
    )
    parser.add_argument("--views", type=int, default=DEMO_VIEWS, help="viewpoints on the ring")
    parser.add_argument("--radius", type=float, default=DEMO_RADIUS, help="view distance (m)")
    parser.add_argument(
        "--elevation",
        type=float,
        default=DEMO_ELEVATION_DEG,
        help="view elevation above the table (degrees)",
    )
    parser.add_argument("--backend", choices=BACKENDS, default="auto", help="depth renderer")
    parser.add_argument(
        "--motion",
        choices=MOTION_MODES,
        default="kinematic",
        help="how the arm moves between views, one of "
        f"{', '.join(MOTION_MODES)} (default: %(default)s): kinematic sets the joints along "
        "a collision-checked path (fast); dynamic drives the servos along it under physics",
    )
    parser.add_argument(
        "--resolution", type=int, default=DEMO_RESOLUTION, help="depth image side (pixels)"
    )
    args = parser.parse_args(argv)
    if args.views < 1:
        parser.error(f"--views must be at least 1, got {args.views}")
    if not 0.15 <= args.radius <= 0.8:
        parser.error(f"--radius must be within [0.15, 0.8] m, got {args.radius}")
    if not 0.0 < args.elevation <= 90.0:
        parser.error(f"--elevation must be within (0, 90] degrees, got {args.elevation}")
    if not 8 <= args.resolution <= 1024:
        parser.error(f"--resolution must be within [8, 1024] pixels, got {args.resolution}")
    _check_out(parser, args.out)
    summary = scan(
        args.out,
        args.views,
        args.radius,
        args.elevation,
        args.backend,
        args.motion,
        args.resolution,
    )
    print(
        f"captured {summary['views_captured']}/{summary['views_requested']} views "
        f"({summary['backend']} depth, {summary['motion']} motion) in {summary['seconds']} s; "
        f"{summary['fused_points']} fused points -> {summary['ply'] or 'no scan.ply'}"
    )
    return 0 if summary["ply"] else 1


if __name__ == "__main__":
    sys.exit(main())
