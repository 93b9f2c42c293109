"""The coverage update of :class:`~liuxing_envs.perception.coverage.CoverageTracker`'s grid.

One pass over a view's points: each point's cell, its row in a dense table of the grid's
cells, then a distance test against every sample registered in that cell that is not
covered yet. The arithmetic is the numpy reference's (``_hits_grid``): the cell is
``floor((p - origin) * inv_cell)`` and the squared distance sums x, y, z in that order, so the
same samples are covered; the gain is a count, so it is exact. A cell whose registered
samples are all covered is marked clear, and later points in it are not tested again: most
points of a view fall where earlier views covered everything.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from liuxing_envs.kernels import jit_options


@njit(**jit_options())
def cover(
    points,
    origin,
    inv_cell,
    dims,
    strides,
    cell_slot,
    cell_ptr,
    cell_samples,
    samples,
    eps2,
    done,
    clear,
):
    """Mark in ``done`` every sample of ``samples`` (N, 3) within ``sqrt(eps2)`` of a point of
    ``points`` (P, 3); return how many samples this newly marked. ``cell_slot`` maps a cell's
    linear index to its row of ``cell_ptr`` (-1: no sample registered there); ``clear`` (one
    per row, uint8) marks the cells found with every registered sample done."""
    gained = 0
    for p in range(points.shape[0]):
        key = 0
        inside = True
        for c in range(3):
            cell = np.floor((points[p, c] - origin[c]) * inv_cell)
            if not (cell >= 0 and cell < dims[c]):
                inside = False
                break
            key += np.int64(cell) * strides[c]
        if not inside:
            continue
        slot = cell_slot[key]
        if slot < 0 or clear[slot]:
            continue
        pending = 0
        for entry in range(cell_ptr[slot], cell_ptr[slot + 1]):
            sample = np.intp(cell_samples[entry])
            if done[sample]:
                continue
            d = samples[sample, 0] - points[p, 0]
            d2 = d * d
            d = samples[sample, 1] - points[p, 1]
            d2 += d * d
            d = samples[sample, 2] - points[p, 2]
            d2 += d * d
            if d2 <= eps2:
                done[sample] = True
                gained += 1
            else:
                pending += 1
        if pending == 0:
            clear[slot] = 1
    return gained


@njit(**jit_options())
def register(row_keys, neighbour_offsets, reach2, num_cells):
    """The grid's registrations (the reference is ``CoverageTracker._build_grid``'s packed
    sort): sample row ``i``, in cell ``row_keys[i]``, is registered in its neighbour cell
    ``row_keys[i] + neighbour_offsets[j]`` where ``reach2[i, j] <= 1``. Returns the occupied
    cells' keys (ascending), the CSR pointers into the rows registered in each (ascending by
    row, as the packed sort orders them), those rows, and the dense table of each cell's
    slot among the occupied ones (-1: none)."""
    n, m = reach2.shape
    count = np.zeros(num_cells, np.int64)
    for i in range(n):
        for j in range(m):
            if reach2[i, j] <= 1.0:
                count[row_keys[i] + neighbour_offsets[j]] += 1
    occupied = 0
    for key in range(num_cells):
        occupied += count[key] > 0
    keys = np.empty(occupied, np.int64)
    ptr = np.empty(occupied + 1, np.int64)
    slot = np.full(num_cells, -1, np.int32)
    filled = 0
    s = 0
    for key in range(num_cells):
        c = count[key]
        if c > 0:
            keys[s], ptr[s], slot[key] = key, filled, s
            count[key] = filled  # from here on: where the cell's next row goes
            filled += c
            s += 1
    ptr[occupied] = filled
    rows = np.empty(filled, np.int64)
    for i in range(n):
        for j in range(m):
            if reach2[i, j] <= 1.0:
                key = row_keys[i] + neighbour_offsets[j]
                rows[count[key]] = i
                count[key] += 1
    return keys, ptr, rows, slot
