"""Perception utilities: depth back-projection and point-cloud helpers (pure numpy)."""

from liuxing_envs.perception.pointcloud import (
    camera_rays,
    crop_points,
    depth_to_camera_points,
    transform_points,
)

__all__ = [
    "camera_rays",
    "crop_points",
    "depth_to_camera_points",
    "transform_points",
]
