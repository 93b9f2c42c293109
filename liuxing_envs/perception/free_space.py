"""Space seen to be empty: the cells of a cube that depth rays crossed before hitting a surface.

An occupancy map of fused points says where surfaces are, not where nothing was seen: an
unseen cell and one a camera looked straight through both read 0. Next-best-view planners
therefore keep a third state (OctoMap's free / occupied / unknown); the unknown cells next to
surfaces are where the next view should look. :class:`FreeSpaceGrid` keeps the "seen" half
of that on the same cube as :meth:`liuxing_envs.perception.fusion.VoxelMap.occupancy_grid`.

Each ray from the camera to a surface point is clipped to the cube and sampled at steps of at
most half a cell, stopping half a cell short of the surface, and every sampled cell is marked
seen. Rays without a return (no surface within range) carve nothing: in this suite they are
rare (the table is behind the object) and their length is unknown. All rays of a view are
handled in one numpy pass, or, with ``compiled`` (the default where numba is installed), the
ray's entry and exit and the sampling in a compiled loop
(:func:`liuxing_envs.kernels.fusion.carve`) that marks the same cells: numpy still computes
the rays and their lengths (an ``einsum``), the kernel repeats the rest operation for
operation.
"""

from __future__ import annotations

import numpy as np

from liuxing_envs import kernels
from liuxing_envs.perception.fusion import MAX_GRID_RESOLUTION, checked_cube
from liuxing_envs.perception.pointcloud import as_points
from liuxing_envs.validation import require_int

__all__ = ["DEFAULT_RAY_STRIDE", "FreeSpaceGrid"]

#: Carve with every n-th ray of an image (of its pixels with a return, row-major). At the
#: suite's defaults a pixel spans about 5 mm of the object at working distance and a cell of
#: its cube 2 cm, so half the rays still cross nearly every cell the image sees.
DEFAULT_RAY_STRIDE = 2
#: Samples per cell length along a ray. One would skip the corners of cells a ray clips
#: (10% of the cells a fine sampling meets, over 20 seeds of the random rays of
#: tests/test_free_space.py); two skip 4.4%.
_SAMPLES_PER_CELL = 2


class FreeSpaceGrid:
    """Which cells of a cube (edge ``size`` m around ``center``, ``resolution`` cells per axis,
    indexed [x, y, z] from the low corner) some ray has crossed. Call :meth:`reset` with the
    cube before the first :meth:`carve` of an episode. ``compiled`` (default: where numba is
    installed; the attribute may be changed at any time) carves with the compiled kernel,
    which marks the same cells as the numpy code."""

    def __init__(
        self, resolution: int, ray_stride: int = DEFAULT_RAY_STRIDE, *, compiled: bool | None = None
    ) -> None:
        require_int("resolution", resolution, 1, MAX_GRID_RESOLUTION)
        require_int("ray_stride", ray_stride, 1, 2**31 - 1)
        if compiled is None:
            compiled = kernels.available()
        elif compiled and not kernels.available():
            raise ValueError("compiled=True needs numba, which is not installed")
        #: Whether :meth:`carve` runs the compiled kernel.
        self.compiled = bool(compiled)
        self.resolution = int(resolution)
        self.ray_stride = int(ray_stride)
        self._seen = np.zeros(self.resolution**3, dtype=bool)
        self._lower = np.zeros(3)
        self._cell = 1.0

    def reset(self, center, size: float) -> None:
        center, size = checked_cube(center, size)
        self._lower = center - 0.5 * size
        self._cell = size / self.resolution
        self._seen[:] = False

    def carve(self, origin, points: np.ndarray) -> None:
        """Mark the cells crossed by the rays from ``origin`` (the camera, world frame) to each
        of ``points`` ((N, 3), world frame, the surfaces the rays hit)."""
        points = as_points(points)[:: self.ray_stride]
        origin = np.asarray(origin, dtype=np.float64)
        if origin.shape != (3,):
            raise ValueError(f"origin must have shape (3,), got {origin.shape}")
        if len(points) == 0:
            return
        resolution = self.resolution
        # In cell units from the cube's low corner, where the cube is [0, R)^3.
        start = (origin - self._lower) / self._cell
        delta = (points - self._lower) / self._cell - start
        length = np.sqrt(np.einsum("ij,ij->i", delta, delta))
        if self.compiled:
            kernels.module("fusion").carve(
                start, delta, length, resolution, float(_SAMPLES_PER_CELL), self._seen
            )
            return
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = 1.0 / delta
            bound_low = -start * inverse
            bound_high = (resolution - start) * inverse
        # Per axis, the interval of t inside the slab [0, R). A ray parallel to a slab is
        # inside it for all t or for none, whatever 0 * inf gives.
        parallel = delta == 0.0
        in_slab = (start >= 0.0) & (start < resolution)
        enter = np.where(
            parallel, np.where(in_slab, -np.inf, np.inf), np.minimum(bound_low, bound_high)
        )
        leave = np.where(
            parallel, np.where(in_slab, np.inf, -np.inf), np.maximum(bound_low, bound_high)
        )
        enter = np.maximum(enter.max(axis=1), 0.0)
        leave = np.minimum(leave.min(axis=1), 1.0 - 0.5 / np.maximum(length, 1e-12))
        crossing = leave > enter  # False for NaN points too
        if not crossing.any():
            return
        enter, leave, delta = enter[crossing], leave[crossing], delta[crossing]
        # Evenly spaced samples along each ray's in-cube part, at most half a cell apart.
        steps = int(np.ceil(_SAMPLES_PER_CELL * ((leave - enter) * length[crossing]).max())) + 1
        t = enter[:, None] + (leave - enter)[:, None] * np.linspace(0.0, 1.0, steps)
        flat = np.zeros(t.shape)
        for axis, weight in enumerate((resolution * resolution, resolution, 1)):
            # Rounding can put a sample on the cube's far face (R), whose true cell is R - 1.
            cell = np.clip(np.floor(start[axis] + t * delta[:, axis, None]), 0, resolution - 1)
            flat += cell * weight
        self._seen[flat.astype(np.int64).ravel()] = True

    def seen(self) -> np.ndarray:
        """A new ``(R, R, R)`` bool array: cells some ray crossed."""
        return self._seen.reshape((self.resolution,) * 3).copy()

    def free(self, occupied: np.ndarray) -> np.ndarray:
        """Cells seen and not ``occupied`` (an ``(R, R, R)`` array of the same cube): where a
        ray crossed a cell that also holds a surface point, the point wins."""
        occupied = np.asarray(occupied, dtype=bool)
        if occupied.shape != (self.resolution,) * 3:
            raise ValueError(
                f"occupied must have this grid's shape {(self.resolution,) * 3}, got "
                f"{occupied.shape}"
            )
        return self.seen() & ~occupied
