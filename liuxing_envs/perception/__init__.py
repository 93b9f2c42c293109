"""Perception: depth back-projection, voxel fusion, surface coverage and reconstruction.

``pointcloud``, ``fusion`` and ``coverage`` are numpy/scipy only (cheap enough for every
environment step). ``reconstruction`` needs open3d (about 1 s to import), so its names are
imported on first use rather than with the package.
"""

from liuxing_envs.perception.coverage import CoverageTracker
from liuxing_envs.perception.fusion import Open3DVoxelMap, VoxelMap
from liuxing_envs.perception.pointcloud import (
    camera_rays,
    crop_points,
    depth_to_camera_points,
    transform_points,
)

_RECONSTRUCTION_NAMES = (
    "Reconstruction",
    "reconstruct",
    "reconstruction_metrics",
    "sample_mesh_surface",
)

__all__ = [
    "CoverageTracker",
    "Open3DVoxelMap",
    "Reconstruction",
    "VoxelMap",
    "camera_rays",
    "crop_points",
    "depth_to_camera_points",
    "reconstruct",
    "reconstruction_metrics",
    "sample_mesh_surface",
    "transform_points",
]


def __getattr__(name: str):
    if name in _RECONSTRUCTION_NAMES:
        from liuxing_envs.perception import reconstruction

        return getattr(reconstruction, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
