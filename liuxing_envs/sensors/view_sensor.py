"""ViewPlanning's sensor pipeline: a depth image from the wrist camera, back-projected to
world points (less the arm's own), cropped to the workspace, fused into a voxel map, rays
carved through a free-space grid, the view sphere's centre estimated from the first cloud,
and the arrays the observation shows of them."""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from liuxing_envs import kernels
from liuxing_envs.perception.free_space import FreeSpaceGrid
from liuxing_envs.perception.fusion import VoxelMap
from liuxing_envs.perception.pointcloud import camera_rays_t, crop_points
from liuxing_envs.perception.reconstruction import Reconstruction, reconstruct
from liuxing_envs.sim.object_stage import PlacedObject
from liuxing_envs.sim.objects import surface_samples
from liuxing_envs.sim.view_scene import WORKSPACE_LOWER, WORKSPACE_UPPER, ViewScene

#: Returns this close to one of the arm's own geoms are the arm (with ``filter_arm_points``):
#: exact returns lie on its surface, GL's tessellation puts them up to 0.34 mm off it.
ARM_FILTER_MARGIN = 0.003  # m
_NO_SKIP = np.zeros(0, dtype=bool)
#: Ground-truth surface samples for reconstruction metrics (about 4 * area / τ² are needed).
METRIC_SAMPLES = 100_000


def estimate_center(points: np.ndarray, region: np.ndarray) -> np.ndarray:
    """The view sphere's centre from the first image's cloud: its bounding box's centre at
    half its height; the middle of the placement ``region`` where nothing was seen."""
    if len(points) == 0:
        return np.array([*region.mean(axis=0), 0.05])
    low, high = points.min(axis=0), points.max(axis=0)
    return np.array([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, high[2] / 2])


class ViewSensor:
    """The episode's fused view of the scene: the latest image, the fused map, the carved
    free space and where each image was taken from. The scene is passed to each call, so
    this holds only what a copy of the env must carry.

    With ``compiled`` (default: where numba is installed) back-projection, crop, fusion, the
    occupancy grid and the uint8 depth run as the kernels of :mod:`liuxing_envs.kernels.fusion`,
    with the same results as the numpy code bit for bit; :attr:`compiled` switches between the
    two (for the map too) at any time."""

    def __init__(self, sensor, fusion, resolution: int, *, compiled: bool | None = None) -> None:
        self.filter_arm_points = bool(sensor.filter_arm_points)
        self.depth_obs_range = float(sensor.depth_obs_range)
        self.noise_enabled = sensor.depth_noise is not None and sensor.depth_noise.enabled
        self.map_grid = fusion.map_grid
        self.map_extent = float(fusion.map_extent)
        lower = np.array(WORKSPACE_LOWER, dtype=float)
        lower[2] = float(fusion.table_crop_height)
        #: The world box fused points must lie in: above the table top, over the table.
        self.crop = (lower, np.array(WORKSPACE_UPPER, dtype=float))
        self.map = VoxelMap(fusion.map_voxel_size, *self.crop, compiled=compiled)
        self._compiled = self.map.compiled
        self.free_space = (
            FreeSpaceGrid(self.map_grid, compiled=self.map.compiled)
            if fusion.observe_free_space
            else None
        )
        self.depth = np.zeros((resolution, resolution), dtype=np.float32)
        self.hits = np.zeros((0, 3))  # world points of the latest image, uncropped
        self.camera_locations: list[np.ndarray] = []

    @property
    def compiled(self) -> bool:
        """Whether the compiled kernels run (the numpy code where False); setting it sets the
        map's too."""
        return self._compiled

    @compiled.setter
    def compiled(self, value: bool) -> None:
        if value and not kernels.available():
            raise ValueError("compiled=True needs numba, which is not installed")
        self._compiled = self.map.compiled = bool(value)
        if self.free_space is not None:
            self.free_space.compiled = self._compiled

    def reset(self) -> None:
        self.map.reset()
        self.camera_locations = []

    def capture(self, scene: ViewScene, rng: np.random.Generator) -> np.ndarray:
        """Render depth at the current pose, fuse it, and return the new cropped points."""
        self.depth = scene.render_depth(rng if self.noise_enabled else None)
        self.hits = self.world_points(scene, self.depth)
        points = self._crop(self.hits)
        self.map.fuse(points)
        self.camera_locations.append(scene.camera.pose(scene.data)[0])
        return points

    def preview_points(self, scene: ViewScene) -> np.ndarray:
        """The cropped world points of a depth image at the live state, not fused; noise, if
        any, from a generator of its own, so the episode's noise stream is left untouched."""
        rng = np.random.default_rng(0) if self.noise_enabled else None
        return self._crop(self.world_points(scene, scene.render_depth(rng)))

    def _crop(self, points: np.ndarray) -> np.ndarray:
        if self._compiled:
            return kernels.module("fusion").crop(points, *self.crop)
        return crop_points(points, *self.crop)

    def world_points(self, scene: ViewScene, depth: np.ndarray) -> np.ndarray:
        """World points of the image's returns at the live state, less those on the arm's
        own links with ``filter_arm_points`` (the depth observation keeps them: the camera
        does see the arm)."""
        camera = scene.camera
        on_arm = None
        if self.filter_arm_points:
            on_arm = camera.pixels_on_geoms(
                depth, scene.data, scene.arm.geom_ids, ARM_FILTER_MARGIN
            )
            if not on_arm.any():
                on_arm = None
        if self._compiled:
            return self._world_points_compiled(camera, scene.data, depth, on_arm)
        if on_arm is not None:
            depth = np.where(on_arm, 0.0, depth).astype(depth.dtype)
        return camera.points_world(depth, scene.data)

    def _world_points_compiled(self, camera, data, depth, on_arm) -> np.ndarray:
        """:meth:`world_points` by the kernels: the pixels on the arm are skipped rather than
        zeroed; the rotation stays numpy's BLAS product, as in ``transform_points``."""
        fusion = kernels.module("fusion")
        back_project, translate = fusion.back_project, fusion.translate

        depth = np.asarray(depth)
        if depth.shape != (camera.intrinsics.height, camera.intrinsics.width):
            return camera.points_world(depth, data)  # for its error message
        skip = _NO_SKIP if on_arm is None else on_arm.ravel()
        points = back_project(depth.ravel(), camera_rays_t(camera.intrinsics), skip)
        position, rotation = camera.pose(data)
        moved = points @ rotation.T
        translate(moved, position)
        return moved

    def reconstruct(self, mesh, placed: PlacedObject, tau_fraction: float, save_dir=None,
                    **kwargs) -> tuple[Reconstruction, dict]:  # fmt: skip
        """The fused cloud meshed (:func:`liuxing_envs.perception.reconstruction.reconstruct`
        takes ``kwargs``) and scored against dense samples of the placed ``mesh``'s whole
        surface with τ = ``tau_fraction`` × its bounding-box diagonal. The camera locations are
        the episode's views'."""
        if "camera_locations" in kwargs:
            raise TypeError(
                "reconstruct() takes the camera locations from the episode's views; call "
                "liuxing_envs.perception.reconstruct(env.unwrapped.map.points(), "
                "camera_locations=...) to give others"
            )
        record = reconstruct(
            self.map.points(), camera_locations=np.array(self.camera_locations), **kwargs
        )
        diagonal = placed.scale * mesh.diagonal
        # Dense ground truth: precision is only meaningful with samples much closer than τ.
        surface, _ = surface_samples(mesh, METRIC_SAMPLES, 0)
        metrics = record.metrics(placed.to_world(placed.scale * surface), tau_fraction * diagonal)
        if save_dir is not None:
            record.save(save_dir)
        return record, metrics

    def start_free_space(self, center: np.ndarray) -> None:
        if self.free_space is not None:
            self.free_space.reset(center, self.map_extent)

    def carve_free_space(self) -> None:
        """Mark the cells the latest image's rays crossed (needs the episode's centre)."""
        if self.free_space is not None:
            self.free_space.carve(self.camera_locations[-1], self.hits)

    def observation_spaces(self) -> dict[str, spaces.Box]:
        side, cells = self.depth.shape[0], self.map_grid**3
        found = {
            "depth": spaces.Box(0, 255, (1, side, side), dtype=np.uint8),
            "map": spaces.Box(0.0, 1.0, (cells,), dtype=np.float32),
            "camera_pose": spaces.Box(-2.0, 2.0, (9,), dtype=np.float32),
        }
        if self.free_space is not None:
            found["free_space"] = spaces.Box(0.0, 1.0, (cells,), dtype=np.float32)
        return found

    def _depth_bytes(self) -> np.ndarray:
        """The uint8 depth observation ``(H, W)``: 255 at ``depth_obs_range`` and beyond."""
        if self._compiled and self.depth.dtype == np.float32:
            depth_bytes = kernels.module("fusion").depth_bytes

            out = np.empty(self.depth.shape, dtype=np.uint8)
            if depth_bytes(self.depth.ravel(), np.float32(self.depth_obs_range), out.ravel()):
                return out
        scaled = np.clip(self.depth / self.depth_obs_range, 0.0, 1.0)
        return np.round(255 * scaled).astype(np.uint8)

    def observation(self, scene: ViewScene, center: np.ndarray) -> dict[str, np.ndarray]:
        """The depth image as uint8, the fused map's occupancy about ``center``, the camera's
        pose (position from ``center``, optical axis, image-up axis) and, when observed, the
        free space."""
        depth = self._depth_bytes()
        occupied = self.map.occupancy_grid(center, self.map_extent, self.map_grid, dtype=np.float32)
        position, rotation = scene.camera.pose(scene.data)
        pose = np.concatenate([position - center, -rotation[:, 2], rotation[:, 1]])
        obs = {
            "depth": depth[None],
            "map": occupied.flatten(),
            "camera_pose": pose.astype(np.float32),
        }
        if self.free_space is not None:
            obs["free_space"] = self.free_space.free(occupied).astype(np.float32).ravel()
        return obs
