"""Back-projection, workspace crop and voxel fusion of a view, and the occupancy observation.

The references are numpy code in :mod:`liuxing_envs.perception.pointcloud`
(``depth_to_camera_points``, ``crop_points``), :class:`~liuxing_envs.perception.fusion.VoxelMap`
(``fuse``, ``_mark_cells``) and :meth:`~liuxing_envs.sensors.view_sensor.ViewSensor.observation`
(the uint8 depth). Every operation here is elementwise in the reference, so each result is
the same double (or float32) when the same operations run in the same order:

- a camera point is ``ray * float64(depth)`` per coordinate;
- the rotation to the world frame stays in numpy (``points @ rotation.T`` is a BLAS product
  whose summation order, FMA or not, depends on the CPU), and only the translation
  ``+ position[c]`` is done here;
- a voxel index is ``int64((p - lower) * inv_size)``, clipped to the last cell;
- a voxel's sum of points, where a batch puts several points in one voxel, is
  ``0.0 + p1 + p2 + ...`` in row order (numpy's ``bincount`` with weights), and a batch of
  one point per voxel stores the points as they are; an occupied voxel adds the batch's sum
  to its own;
- new voxels are appended in ascending key order, the order of numpy's sorted batch;
- an occupancy cell is ``int64(index * scale + offset)``;
- the uint8 depth is float32 arithmetic: ``round_half_even(255 * clip(depth / range, 0, 1))``.

All functions are ``numba.njit`` with :func:`liuxing_envs.kernels.jit_options`; tunables are
arguments.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from liuxing_envs.kernels import jit_options

njit = numba.njit(**jit_options())


@njit
def back_project(depth, rays_t, skip):
    """Camera-frame points ``(N, 3)`` of the pixels of the flat float32 ``depth`` that are
    finite, > 0 and not ``skip`` (a flat bool mask; empty: none skipped), in row-major pixel
    order: ``rays_t[:, p] * float64(depth[p])``."""
    n = depth.size
    use_skip = skip.size == n
    count = 0
    for p in range(n):
        d = depth[p]
        if math.isfinite(d) and d > 0 and not (use_skip and skip[p]):
            count += 1
    points = np.empty((count, 3), dtype=np.float64)
    row = 0
    for p in range(n):
        d = depth[p]
        if math.isfinite(d) and d > 0 and not (use_skip and skip[p]):
            d64 = np.float64(d)
            points[row, 0] = rays_t[0, p] * d64
            points[row, 1] = rays_t[1, p] * d64
            points[row, 2] = rays_t[2, p] * d64
            row += 1
    return points


@njit
def translate(points, position):
    """``points[:, c] += position[c]`` in place."""
    for i in range(points.shape[0]):
        for c in range(3):
            points[i, c] = points[i, c] + position[c]


@njit
def _inside(points, i, lower, upper):
    # NaN compares False, so non-finite points are outside.
    for c in range(3):
        v = points[i, c]
        if not (v >= lower[c] and v <= upper[c]):
            return False
    return True


@njit
def crop(points, lower, upper):
    """The rows of ``points`` inside ``lower <= p <= upper`` (inclusive), in row order."""
    n = points.shape[0]
    count = 0
    for i in range(n):
        if _inside(points, i, lower, upper):
            count += 1
    kept = np.empty((count, 3), dtype=np.float64)
    row = 0
    for i in range(n):
        if _inside(points, i, lower, upper):
            for c in range(3):
                kept[row, c] = points[i, c]
            row += 1
    return kept


@njit
def fuse(
    points,
    lower,
    upper,
    inv_size,
    last,
    strides,
    mean,
    sorted_keys,
    sorted_slots,
    slot_keys,
    values,
    counts,
    size,
):
    """Fuse ``points`` (N, 3) into a :class:`VoxelMap`'s state; return ``(new voxels, merged
    sorted keys, merged sorted slots)``. The storage ``slot_keys``, ``values`` (3, capacity)
    and ``counts`` is written in place and must have room for ``size + N`` voxels; ``mean``:
    the representative is the mean (else the first point)."""
    n_all = points.shape[0]
    rows = np.empty(n_all, dtype=np.int64)
    n = 0
    for i in range(n_all):
        if _inside(points, i, lower, upper):
            rows[n] = i
            n += 1
    if n == 0:
        return 0, sorted_keys, sorted_slots
    # Keys packed with the batch row below them: ties keep row order.
    shift = 0
    while (n >> shift) > 0:
        shift += 1
    packed = np.empty(n, dtype=np.int64)
    for r in range(n):
        i = rows[r]
        key = np.int64(0)
        for c in range(3):
            scaled = points[i, c] - lower[c]
            scaled *= inv_size
            index = np.int64(scaled)
            if index > last[c]:
                index = last[c]
            key += index * strides[c]
        packed[r] = (key << shift) | r
    packed.sort()
    mask = (np.int64(1) << shift) - 1
    # Runs of equal keys: the batch's voxels.
    all_single = True
    for r in range(1, n):
        if (packed[r] >> shift) == (packed[r - 1] >> shift):
            all_single = False
            break
    batch_keys = np.empty(n, dtype=np.int64)
    batch_counts = np.zeros(n, dtype=np.int64)
    batch_values = np.zeros((3, n), dtype=np.float64)
    runs = -1
    previous = np.int64(-1)
    for r in range(n):
        key = packed[r] >> shift
        i = rows[packed[r] & mask]
        if r == 0 or key != previous:
            runs += 1
            batch_keys[runs] = key
            previous = key
            if all_single or not mean:
                for c in range(3):
                    batch_values[c, runs] = points[i, c]
            else:
                for c in range(3):
                    batch_values[c, runs] = 0.0 + points[i, c]
        elif mean:
            for c in range(3):
                batch_values[c, runs] = batch_values[c, runs] + points[i, c]
        batch_counts[runs] += 1
    runs += 1
    # Merge into the map: existing voxels grow, new ones are appended in key order.
    m = sorted_keys.size
    is_new = np.zeros(runs, dtype=np.bool_)
    k = 0
    at = 0
    for b in range(runs):
        key = batch_keys[b]
        while at < m and sorted_keys[at] < key:
            at += 1
        if at < m and sorted_keys[at] == key:
            slot = sorted_slots[at]
            counts[slot] += batch_counts[b]
            if mean:
                for c in range(3):
                    values[c, slot] = values[c, slot] + batch_values[c, b]
        else:
            is_new[b] = True
            slot = size + k
            slot_keys[slot] = key
            for c in range(3):
                values[c, slot] = batch_values[c, b]
            counts[slot] = batch_counts[b]
            k += 1
    if k == 0:
        return 0, sorted_keys, sorted_slots
    merged_keys = np.empty(m + k, dtype=np.int64)
    merged_slots = np.empty(m + k, dtype=np.int64)
    a = 0
    out = 0
    new_slot = size
    for b in range(runs):
        if not is_new[b]:
            continue
        key = batch_keys[b]
        while a < m and sorted_keys[a] < key:
            merged_keys[out] = sorted_keys[a]
            merged_slots[out] = sorted_slots[a]
            a += 1
            out += 1
        merged_keys[out] = key
        merged_slots[out] = new_slot
        new_slot += 1
        out += 1
    while a < m:
        merged_keys[out] = sorted_keys[a]
        merged_slots[out] = sorted_slots[a]
        a += 1
        out += 1
    return k, merged_keys, merged_slots


@njit
def mark_cells(grid, keys, dim1, dim2, scale, offset, resolution):
    """Set ``grid[cell] = 1`` for the cell of each voxel key (the spare last cell, index
    ``resolution**3``, for voxels outside the cube)."""
    spare = resolution * resolution * resolution
    for v in range(keys.size):
        key = keys[v]
        rest = key // dim2
        index2 = key % dim2
        index0 = rest // dim1
        index1 = rest % dim1
        q0 = np.float64(index0) * scale
        q0 += offset[0]
        q1 = np.float64(index1) * scale
        q1 += offset[1]
        q2 = np.float64(index2) * scale
        q2 += offset[2]
        inside = (
            q0 >= 0 and q0 < resolution and q1 >= 0 and q1 < resolution
            and q2 >= 0 and q2 < resolution
        )  # fmt: skip
        if inside:
            flat = np.int64(q0) * resolution
            flat += np.int64(q1)
            flat *= resolution
            flat += np.int64(q2)
            grid[flat] = 1
        else:
            grid[spare] = 1


@njit
def depth_bytes(depth, depth_range, out):
    """``out[p] = round_half_even(255 * clip(depth[p] / depth_range, 0, 1))`` in float32, as
    uint8, over the flat float32 ``depth`` and float32 ``depth_range``; False if a value is
    NaN (numpy leaves the uint8 of NaN to the platform; ``out`` then holds 0 there).

    The rounding adds and subtracts 2**23 in float32, whose default rounding (to nearest,
    ties to even) is numpy's ``round`` for 0 <= y <= 255."""
    scale = np.float32(255.0)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    magic = np.float32(8388608.0)
    nan = False
    for p in range(depth.size):
        x = np.float32(depth[p] / depth_range)
        nan |= x != x
        x = x if x > zero else zero
        x = x if x < one else one
        y = np.float32(scale * x)
        r = np.float32(np.float32(y + magic) - magic)
        out[p] = np.uint8(np.int32(r))
    return not nan


@njit
def _minimum(a, b):
    # np.minimum: NaN propagates.
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@njit
def _maximum(a, b):
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


@njit
def carve(start, delta, length, resolution, samples_per_cell, seen):
    """:meth:`FreeSpaceGrid.carve` after its numpy part: mark in ``seen`` (flat bool) the
    cells of the samples along each ray ``start + t * delta[i]`` (cell units, ``length`` its
    numpy length) between where it enters the cube [0, R)^3 and half a cell short of its end.
    The samples are ``linspace(0, 1, steps)`` as numpy makes it."""
    n = delta.shape[0]
    enter = np.empty(n, dtype=np.float64)
    leave = np.empty(n, dtype=np.float64)
    crossing = np.zeros(n, dtype=np.bool_)
    longest = -np.inf
    any_crossing = False
    for i in range(n):
        low_t = -np.inf
        high_t = np.inf
        for c in range(3):
            d = delta[i, c]
            if d == 0.0:
                in_slab = start[c] >= 0.0 and start[c] < resolution
                e = -np.inf if in_slab else np.inf
                f = np.inf if in_slab else -np.inf
            else:
                inverse = 1.0 / d
                bound_low = -start[c] * inverse
                bound_high = (resolution - start[c]) * inverse
                e = _minimum(bound_low, bound_high)
                f = _maximum(bound_low, bound_high)
            low_t = e if c == 0 else _maximum(low_t, e)
            high_t = f if c == 0 else _minimum(high_t, f)
        low_t = _maximum(low_t, 0.0)
        high_t = _minimum(high_t, 1.0 - 0.5 / _maximum(length[i], 1e-12))
        enter[i] = low_t
        leave[i] = high_t
        if high_t > low_t:
            crossing[i] = True
            span = (high_t - low_t) * length[i]
            if not any_crossing:
                longest = span
                any_crossing = True
            else:
                longest = _maximum(longest, span)
    if not any_crossing:
        return
    steps = np.int64(np.ceil(samples_per_cell * longest)) + 1
    # np.linspace(0.0, 1.0, steps): i * (1.0 / (steps - 1)) + 0.0, the last one 1.0.
    fractions = np.zeros(steps, dtype=np.float64)
    if steps > 1:
        step = 1.0 / (steps - 1)
        for j in range(steps):
            fractions[j] = j * step + 0.0
        fractions[steps - 1] = 1.0
    top = np.float64(resolution - 1)
    weights = (np.float64(resolution * resolution), np.float64(resolution), 1.0)
    cells = seen.size
    for i in range(n):
        if not crossing[i]:
            continue
        low_t = enter[i]
        span = leave[i] - low_t
        for j in range(steps):
            t = low_t + span * fractions[j]
            flat = 0.0
            for c in range(3):
                # np.clip(np.floor(...), 0, R - 1): NaN would stay NaN (comparisons fail).
                cell = np.floor(start[c] + t * delta[i, c])
                if cell < 0.0:
                    cell = 0.0
                if cell > top:
                    cell = top
                flat += cell * weights[c]
            if not (flat >= 0.0 and flat < cells):
                raise IndexError("a ray sample outside the grid (non-finite input)")
            seen[np.int64(flat)] = True
