"""Markers drawn into a MuJoCo scene for ``render()``: fused points and a camera frustum."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from liuxing_envs.sim.camera import CameraIntrinsics


def add_points(scene: mujoco.MjvScene, points: np.ndarray, limit: int) -> None:
    if len(points) > limit:
        points = points[np.linspace(0, len(points) - 1, limit).astype(int)]
    size = np.array([0.004, 0.0, 0.0])
    rgba = np.array([0.1, 0.9, 0.3, 1.0], dtype=np.float32)
    eye = np.eye(3).ravel()
    for point in points:
        if scene.ngeom >= scene.maxgeom:
            return
        mujoco.mjv_initGeom(
            scene.geoms[scene.ngeom], mujoco.mjtGeom.mjGEOM_SPHERE, size, point, eye, rgba
        )
        scene.ngeom += 1


def add_frustum(scene, position, rotation, intrinsics: CameraIntrinsics, length: float) -> None:
    half_h = math.tan(math.radians(intrinsics.fovy_deg) / 2)
    half_w = half_h * intrinsics.width / intrinsics.height
    rgba = np.array([1.0, 0.85, 0.1, 1.0], dtype=np.float32)
    corners = [
        position + length * (rotation @ np.array([sx * half_w, sy * half_h, -1.0]))
        for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))
    ]
    segments = [(position, c) for c in corners]
    segments += [(corners[i], corners[(i + 1) % 4]) for i in range(4)]
    for start, end in segments:
        if scene.ngeom >= scene.maxgeom:
            return
        geom = scene.geoms[scene.ngeom]
        mujoco.mjv_initGeom(
            geom, mujoco.mjtGeom.mjGEOM_LINE, np.zeros(3), np.zeros(3), np.eye(3).ravel(), rgba
        )
        mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_LINE, 3.0, start, end)
        scene.ngeom += 1
