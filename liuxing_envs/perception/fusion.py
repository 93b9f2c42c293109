"""Sparse voxel map of observed world-frame points (pure numpy, sorted int64 keys).

Each step of a scan back-projects a depth image to a few hundred to a few thousand world-frame
points; :class:`VoxelMap` fuses them into a sparse set of occupied voxels inside an
axis-aligned box and keeps one representative point per voxel (the mean of the points that
fell in it, or the first one), so :meth:`VoxelMap.points` is a down-sampled cloud of
everything observed so far.

Voxel ``(i, j, k)`` covers ``lower + voxel_size * [i, i+1) x [j, j+1) x [k, k+1)`` (metres):
the grid is anchored at the box's ``lower`` corner. A voxel is identified by the packed int64
key ``(i * ny + j) * nz + k``. Per-voxel data (representative point, point count) lives in
append-only arrays in the order voxels were first fused; a sorted array of keys with their
slots finds them. Fusing is one sort of the batch's keys, one ``searchsorted`` and a merge of
the new keys into the sorted index: no Python loop over points, no hash table.

:class:`Open3DVoxelMap` is the same interface on ``open3d.core.HashMap``; it exists so the
benchmark can compare the two, and keeps the first point per voxel only.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from liuxing_envs import kernels
from liuxing_envs.perception.pointcloud import as_points, box_mask_t
from liuxing_envs.validation import require_int

__all__ = [
    "DEFAULT_GRID_RESOLUTION",
    "DEFAULT_LOWER",
    "DEFAULT_UPPER",
    "DEFAULT_VOXEL_SIZE",
    "Open3DVoxelMap",
    "Representative",
    "VoxelMap",
]

#: Voxel edge in metres: finer than a 64x64 pixel's footprint at working distance (about
#: 5 mm), so fusing loses no return; ViewPlanning-v0 fuses at its own ``map_voxel_size``.
DEFAULT_VOXEL_SIZE = 0.002
#: Default box of the map, metres: the table top (z = 0) in front of the arm, up to 0.5 m high.
DEFAULT_LOWER = (0.15, -0.4, 0.0)
DEFAULT_UPPER = (0.85, 0.4, 0.5)
#: Cells per axis of :meth:`VoxelMap.occupancy_grid` (32³ = 32768 values).
DEFAULT_GRID_RESOLUTION = 32
#: The finest occupancy or free-space grid accepted: 1024 cells per axis is a gigabyte.
MAX_GRID_RESOLUTION = 1024
#: Initial storage, in voxels (grown by doubling).
_MIN_CAPACITY = 4096
#: Packed keys must stay below 2**62 so sums of indices never overflow int64.
_MAX_CELLS = 2**62

Representative = Literal["mean", "first"]


def checked_cube(center, size) -> tuple[np.ndarray, float]:
    """``center`` (3 finite numbers) and ``size`` (a positive number of metres) of a cube,
    as float64 and float; raises ``ValueError`` naming the bad one."""
    center = _as_vector("center", center)
    size = float(size)
    if not math.isfinite(size) or size <= 0:
        raise ValueError(f"size must be a positive number of metres, got {size}")
    return center, size


def _as_vector(name: str, value) -> np.ndarray:
    value = np.asarray(value, dtype=np.float64)
    # math.isfinite on 3 Python floats: ~10x cheaper than numpy's isfinite + all.
    if value.shape != (3,) or not all(map(math.isfinite, value.tolist())):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return value


class VoxelMap:
    """Sparse map of the voxels that observed points fell into, within a box.

    Per-voxel outputs (:meth:`points`, :meth:`counts`, :meth:`voxel_indices`,
    :meth:`voxel_centers`) share one order: by the :meth:`fuse` call that first observed the
    voxel, then by key within a call. :attr:`keys` is sorted.

    Parameters
    ----------
    voxel_size
        Voxel edge in metres (> 0).
    lower, upper
        Corners of the axis-aligned box in the world frame (metres, ``lower < upper``). Points
        outside it (bounds inclusive), and non-finite points, are dropped by :meth:`fuse`.
        Default: the table-top workspace in front of the arm, ``DEFAULT_LOWER`` to
        ``DEFAULT_UPPER``.
    representative
        The point kept per voxel: ``"mean"`` (centroid of every point fused into it, which
        averages sensor noise) or ``"first"`` (the first point observed in it, unaltered).
    compiled
        Fuse and mark occupancy grids with the compiled kernels of
        :mod:`liuxing_envs.kernels.fusion` (the same keys, points, counts and grids as the
        numpy code, bit for bit). Default: where numba is installed. The attribute of the
        same name may be changed between calls.
    """

    def __init__(
        self,
        voxel_size: float = DEFAULT_VOXEL_SIZE,
        lower=DEFAULT_LOWER,
        upper=DEFAULT_UPPER,
        *,
        representative: Representative = "mean",
        compiled: bool | None = None,
    ) -> None:
        voxel_size = float(voxel_size)
        if not np.isfinite(voxel_size) or voxel_size <= 0:
            raise ValueError(f"voxel_size must be a positive number of metres, got {voxel_size}")
        lower = _as_vector("lower", lower)
        upper = _as_vector("upper", upper)
        if np.any(upper <= lower):
            raise ValueError(f"box must have lower < upper on every axis: {lower} vs {upper}")
        if representative not in ("mean", "first"):
            raise ValueError(f"representative must be 'mean' or 'first', got {representative!r}")
        # +1 so that a point exactly on `upper` still has a voxel (the bounds are inclusive).
        dims = np.floor((upper - lower) / voxel_size).astype(np.int64) + 1
        if float(np.prod(dims.astype(np.float64))) >= _MAX_CELLS:
            raise ValueError(f"box {lower}..{upper} at {voxel_size} m has too many voxels to pack")
        self.voxel_size = voxel_size
        self.lower = lower
        self.upper = upper
        self.dims = dims
        self.representative: Representative = representative
        if compiled is None:
            compiled = kernels.available()
        elif compiled and not kernels.available():
            raise ValueError("compiled=True needs numba, which is not installed")
        #: Whether :meth:`fuse` and :meth:`occupancy_grid` run the compiled kernels.
        self.compiled = bool(compiled)
        self._inv_size = 1.0 / voxel_size
        self._strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
        self._last = dims - 1
        # Slots only ever get appended, so occupancy grids can be updated incrementally.
        self._append_only = True
        self._key_bits = int(np.prod(dims) - 1).bit_length()
        self.reset()

    # -- state -------------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget every observation."""
        self._size = 0
        # Sorted index: keys ascending, and the storage slot of each.
        self._sorted_keys = np.empty(0, dtype=np.int64)
        self._sorted_slots = np.empty(0, dtype=np.int64)
        # Storage by slot (first-observed order), grown by doubling. Values are the sum of the
        # voxel's points ("mean") or its first point, coordinate-major (3, capacity): numpy
        # broadcasts (3, M) - (3, 1) several times faster than (M, 3) - (3,).
        self._slot_keys = np.empty(0, dtype=np.int64)
        self._values = np.empty((3, 0), dtype=np.float64)
        self._counts = np.empty(0, dtype=np.int64)
        self._points_cache: np.ndarray | None = None  # (3, M)
        # occupancy_grid's last cube, its grid and how many voxels (slots) it includes.
        self._grid_cache: tuple | None = None

    @property
    def num_voxels(self) -> int:
        """Number of occupied voxels."""
        return self._size

    def __len__(self) -> int:
        return self.num_voxels

    @property
    def keys(self) -> np.ndarray:
        """Packed keys of the occupied voxels, sorted ascending, ``(M,)`` int64 (a copy)."""
        return self._sorted_keys.copy()

    def _keys_in_order(self) -> np.ndarray:
        return self._slot_keys[: self._size]

    def voxel_indices(self) -> np.ndarray:
        """Integer ``(i, j, k)`` of the occupied voxels, ``(M, 3)`` int64."""
        keys = self._keys_in_order()
        return np.stack(
            (
                keys // self._strides[0],
                (keys // self._strides[1]) % self.dims[1],
                keys % self.dims[2],
            ),
            axis=1,
        )

    def voxel_centers(self) -> np.ndarray:
        """World-frame centres of the occupied voxels, ``(M, 3)`` metres."""
        return self.lower + (self.voxel_indices() + 0.5) * self.voxel_size

    def points(self) -> np.ndarray:
        """One representative point per occupied voxel, ``(M, 3)`` float64 metres (a copy)."""
        return self._points_t().T.copy()

    def _points_t(self) -> np.ndarray:
        if self._points_cache is None:
            values = self._values[:, : self._size]
            if self.representative == "mean":
                values = values / self._counts[: self._size]
            self._points_cache = values
        return self._points_cache

    def counts(self) -> np.ndarray:
        """How many fused points fell into each occupied voxel, ``(M,)`` int64 (a copy)."""
        return self._counts[: self._size].copy()

    # -- fusing ------------------------------------------------------------------------------

    def _crop_t(self, points: np.ndarray) -> np.ndarray:
        """The points inside the box, coordinate-major ``(3, K)``."""
        pt = np.ascontiguousarray(as_points(points).T)
        # Comparisons with NaN are False, so non-finite points drop out here as well.
        mask = box_mask_t(pt, self.lower, self.upper)
        # np.compress/np.take: numpy's fancy indexing along axis 1 is ~5x slower.
        return pt if mask.all() else np.compress(mask, pt, axis=1)

    def _keys_t(self, pt: np.ndarray) -> np.ndarray:
        # In place where possible: each temporary costs about as much as the arithmetic.
        scaled = pt - self.lower[:, None]
        scaled *= self._inv_size
        idx = scaled.astype(np.int64)  # >= 0: a floor
        # Rounding of (p - lower) / size can land one past the last cell for p == upper.
        np.minimum(idx, self._last[:, None], out=idx)
        keys = idx[0] * self._strides[0]
        keys += idx[1] * self._strides[1]
        keys += idx[2]
        return keys

    def voxel_keys(self, points: np.ndarray) -> np.ndarray:
        """Packed keys ``(K,)`` int64 of the given ``(N, 3)`` points that lie inside the box."""
        return self._keys_t(self._crop_t(points))

    def fuse(self, points: np.ndarray) -> int:
        """Add world-frame points ``(N, 3)`` (metres); returns how many voxels became occupied.

        Points outside the box or not finite are ignored. Fusing points that all fall in
        already-occupied voxels returns 0 (with ``representative="mean"`` they still move the
        voxels' centroids).
        """
        if self.compiled:
            points = np.ascontiguousarray(as_points(points))
            if self._key_bits + int(len(points)).bit_length() < 63:
                return self._fuse_compiled(points)
        pt = self._crop_t(points)
        n = pt.shape[1]
        if n == 0:
            return 0
        keys = self._keys_t(pt)
        # Sort (key, row) pairs packed in one int64: several times cheaper than a stable
        # argsort, and ties keep row order, so each run starts with its first point.
        shift = int(n).bit_length()
        if self._key_bits + shift < 63:
            packed = keys  # not needed unpacked any more: pack in place
            packed <<= shift
            packed |= np.arange(n, dtype=np.int64)
            packed.sort()
            order = packed & ((1 << shift) - 1)
            sorted_keys = packed >> shift
        else:
            order = np.argsort(keys, kind="stable")
            sorted_keys = keys[order]
        run_start = np.empty(n, dtype=bool)
        run_start[0] = True
        np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=run_start[1:])
        if run_start.all():  # the common case for a sparse view: one point per voxel
            batch_keys = sorted_keys
            batch_counts = np.ones(n, dtype=np.int64)
            batch_values = np.take(pt, order, axis=1)
        else:
            starts = np.flatnonzero(run_start)
            batch_keys = sorted_keys[starts]
            batch_counts = np.diff(np.append(starts, n))
            if self.representative == "mean":
                run = np.cumsum(run_start) - 1
                batch_values = np.stack(
                    [
                        np.bincount(run, weights=pt[c, order], minlength=starts.size)
                        for c in range(3)
                    ]
                )
            else:
                batch_values = np.take(pt, order[starts], axis=1)

        m = self._size
        pos = np.searchsorted(self._sorted_keys, batch_keys)
        if m:
            exists = self._sorted_keys[np.minimum(pos, m - 1)] == batch_keys
        else:
            exists = np.zeros(batch_keys.size, dtype=bool)
        if exists.any():
            # Index lists once, then np.take: cheaper than a boolean index per array.
            old = np.flatnonzero(exists)
            new = np.flatnonzero(~exists)
            # batch_keys are unique, so each fancy-indexed += touches a voxel once.
            hit = self._sorted_slots.take(pos.take(old))
            self._counts[hit] += batch_counts.take(old)
            if self.representative == "mean":
                added = batch_values.take(old, axis=1)
                for c in range(3):  # three 1-D scatters beat one 2-D fancy index
                    self._values[c, hit] += added[c]
            new_keys, new_pos = batch_keys.take(new), pos.take(new)
            new_values = batch_values.take(new, axis=1)
            new_counts = batch_counts.take(new)
        else:
            new_keys, new_pos, new_values, new_counts = batch_keys, pos, batch_values, batch_counts
        k = new_keys.size
        if k:
            self._append(new_keys, new_values, new_counts)
            self._insert_sorted(new_pos, new_keys, np.arange(m, m + k, dtype=np.int64))
        self._points_cache = None
        return int(k)

    def _fuse_compiled(self, points: np.ndarray) -> int:
        """:meth:`fuse` of C-ordered ``(N, 3)`` float64 points by the compiled kernel."""
        fuse = kernels.module("fusion").fuse

        m = self._size
        if m + len(points) > self._slot_keys.size:
            self._grow(m + len(points))
        k, self._sorted_keys, self._sorted_slots = fuse(
            points,
            self.lower,
            self.upper,
            self._inv_size,
            self._last,
            self._strides,
            self.representative == "mean",
            self._sorted_keys,
            self._sorted_slots,
            self._slot_keys,
            self._values,
            self._counts,
            m,
        )
        self._size = m + k
        self._points_cache = None
        return int(k)

    def _grow(self, needed: int) -> None:
        # Doubling keeps appends amortised O(k) however large the map grows.
        m = self._size
        capacity = max(2 * self._slot_keys.size, needed, _MIN_CAPACITY)
        slot_keys = np.empty(capacity, dtype=np.int64)
        stored = np.empty((3, capacity), dtype=np.float64)
        counts = np.empty(capacity, dtype=np.int64)
        slot_keys[:m] = self._slot_keys[:m]
        stored[:, :m] = self._values[:, :m]
        counts[:m] = self._counts[:m]
        self._slot_keys, self._values, self._counts = slot_keys, stored, counts

    def _append(self, keys: np.ndarray, values: np.ndarray, counts: np.ndarray) -> None:
        m, k = self._size, keys.size
        if m + k > self._slot_keys.size:
            self._grow(m + k)
        self._slot_keys[m : m + k] = keys
        self._values[:, m : m + k] = values
        self._counts[m : m + k] = counts
        self._size = m + k

    def _insert_sorted(self, pos: np.ndarray, keys: np.ndarray, slots: np.ndarray) -> None:
        # pos is ascending (keys are sorted), so new entry j lands at pos[j] + j of the merged
        # index. One mask serves both arrays (np.insert would redo it per array).
        m = self._sorted_keys.size
        at = pos + np.arange(keys.size)
        old = np.ones(m + keys.size, dtype=bool)
        old[at] = False
        merged_keys = np.empty(m + keys.size, dtype=np.int64)
        merged_keys[at] = keys
        merged_keys[old] = self._sorted_keys
        merged_slots = np.empty(m + keys.size, dtype=np.int64)
        merged_slots[at] = slots
        merged_slots[old] = self._sorted_slots
        self._sorted_keys, self._sorted_slots = merged_keys, merged_slots

    # -- summaries ---------------------------------------------------------------------------

    def occupancy_grid(
        self,
        center,
        size: float,
        resolution: int = DEFAULT_GRID_RESOLUTION,
        *,
        dtype=np.uint8,
    ) -> np.ndarray:
        """Dense occupancy of a cube around ``center``: a compact summary for a policy.

        The cube has edge ``size`` metres centred on ``center`` (world frame) and is split into
        ``resolution`` cells per axis; a cell is 1 when the centre of some occupied voxel lies
        in it (cells half-open ``[lo, hi)``), else 0. Voxel centres, unlike the mean points,
        never move, so a call with the same cube as the previous call only adds the voxels
        fused since (O(new voxels)); another cube costs one pass over all voxels.

        Returns
        -------
        np.ndarray
            A new ``(R, R, R)`` array of ``dtype`` (uint8 by default, float32 for a network
            input), indexed ``[x, y, z]`` from the cube's low corner.
        """
        center, size = checked_cube(center, size)
        require_int("resolution", resolution, 1, MAX_GRID_RESOLUTION)  # 2.7 was cut to 2
        resolution = int(resolution)
        cube = (tuple(center.tolist()), size, resolution)  # Python floats: cheap to compare
        if self._grid_cache is not None and self._grid_cache[0] == cube:
            _, grid, done = self._grid_cache
        else:
            # One spare last cell takes the voxels outside the cube (see _mark_cells).
            grid, done = np.zeros(resolution**3 + 1, dtype=np.uint8), 0
        keys = self._keys_in_order()
        if keys.size > done:
            self._mark_cells(grid, keys[done:], center, size, resolution)
        if self._append_only:
            self._grid_cache = (cube, grid, int(keys.size))
        return grid[:-1].reshape((resolution,) * 3).astype(dtype)

    def _mark_cells(
        self, grid: np.ndarray, keys: np.ndarray, center: np.ndarray, size: float, resolution: int
    ) -> None:
        # Voxel index -> position in cube cells. A call typically marks the few hundred
        # voxels of one view, so numpy's per-call overhead dominates: one (3, K) array rather
        # than per-axis 1-D ones, and divmod for quotient and remainder in one pass.
        scale = self.voxel_size * resolution / size
        offset = (self.lower - (center - 0.5 * size)) * (resolution / size) + 0.5 * scale
        if self.compiled:
            kernels.module("fusion").mark_cells(
                grid, keys, self.dims[1], self.dims[2], scale, offset, resolution
            )
            return
        index = np.empty((3, keys.size), dtype=np.int64)
        np.divmod(keys, self.dims[2], out=(index[1], index[2]))  # key // dims[2], k
        np.divmod(index[1], self.dims[1], out=(index[0], index[1]))  # i, j
        q = index * scale
        q += offset[:, None]
        ok = (q >= 0) & (q < resolution)
        inside = ok[0] & ok[1] & ok[2]
        cell = q.astype(np.int64)  # truncation is a floor where inside (q >= 0)
        flat = cell[0] * resolution
        flat += cell[1]
        flat *= resolution
        flat += cell[2]
        # Outside voxels write to the spare cell rather than being gathered out first (a
        # masked gather costs more than the whole scatter).
        flat[~inside] = resolution**3
        grid[flat] = 1


class Open3DVoxelMap(VoxelMap):
    """:class:`VoxelMap` on an ``open3d.core.HashMap`` (for benchmarking against numpy).

    Same voxels and keys; keeps one point per voxel (the first one inserted, which open3d
    does not promise to be the first in the batch), per-voxel outputs are in key order, and
    ``counts()`` is not tracked.
    """

    def __init__(
        self,
        voxel_size: float = DEFAULT_VOXEL_SIZE,
        lower=DEFAULT_LOWER,
        upper=DEFAULT_UPPER,
        *,
        initial_capacity: int = 1 << 15,
    ) -> None:
        self._initial_capacity = int(initial_capacity)
        super().__init__(voxel_size, lower=lower, upper=upper, representative="first")
        self._append_only = False  # its per-voxel order is key order: recompute grids

    def reset(self) -> None:
        import open3d.core as o3c

        self._o3c = o3c
        self._map = o3c.HashMap(
            self._initial_capacity, o3c.int64, [1], o3c.float64, [3], device=o3c.Device("CPU:0")
        )
        self._points_cache = None
        self._grid_cache = None

    @property
    def num_voxels(self) -> int:
        return int(self._map.size())

    @property
    def keys(self) -> np.ndarray:
        return self._keys_in_order().copy()

    def _keys_in_order(self) -> np.ndarray:
        # This map's per-voxel outputs are in key order (the hash map's own order is arbitrary).
        return np.sort(self._active(self._map.key_tensor()).ravel())

    def counts(self) -> np.ndarray:
        # A deliberate limit of this benchmark-only variant, not a missing piece.
        raise TypeError("Open3DVoxelMap keeps no per-voxel point counts; use VoxelMap for them")

    def _active(self, tensor) -> np.ndarray:
        index = self._map.active_buf_indices().to(self._o3c.int64)
        return tensor[index].numpy()

    def _points_t(self) -> np.ndarray:
        if self._points_cache is None:
            keys = self._active(self._map.key_tensor()).ravel()
            values = self._active(self._map.value_tensor())
            self._points_cache = np.ascontiguousarray(values[np.argsort(keys)].T)
        return self._points_cache

    def fuse(self, points: np.ndarray) -> int:
        pt = self._crop_t(points)
        if pt.shape[1] == 0:
            return 0
        keys = self._keys_t(pt)
        before = self._map.size()
        self._map.insert(
            self._o3c.Tensor.from_numpy(np.ascontiguousarray(keys[:, None])),
            self._o3c.Tensor.from_numpy(np.ascontiguousarray(pt.T)),
        )
        self._points_cache = None
        return int(self._map.size() - before)
