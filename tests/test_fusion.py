"""VoxelMap: sparse voxel fusion of world-frame points, checked against brute-force references."""

import numpy as np
import pytest

from liuxing_envs.perception.fusion import (
    DEFAULT_LOWER,
    DEFAULT_UPPER,
    DEFAULT_VOXEL_SIZE,
    Open3DVoxelMap,
    VoxelMap,
)

LOWER = np.array([0.2, -0.15, 0.0])
UPPER = np.array([0.5, 0.15, 0.3])
VOXEL = 0.01


def reference_voxels(points, lower=LOWER, upper=UPPER, voxel=VOXEL):
    """Distinct voxel indices and per-voxel means of the in-box points (np.unique, axis=0)."""
    points = np.asarray(points, dtype=np.float64)
    inside = np.all(np.isfinite(points), axis=1)
    inside[inside] = np.all((points[inside] >= lower) & (points[inside] <= upper), axis=1)
    points = points[inside]
    idx = np.floor((points - lower) / voxel).astype(np.int64)
    cells, inverse = np.unique(idx, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    sums = np.zeros((len(cells), 3))
    np.add.at(sums, inverse, points)
    counts = np.bincount(inverse, minlength=len(cells))
    return cells, sums / counts[:, None], counts


def random_points(rng, n, spread=0.05):
    """Points around the box (some outside it), clustered so voxels get several points."""
    centre = (LOWER + UPPER) / 2
    return centre + rng.uniform(-1, 1, (n, 3)) * ((UPPER - LOWER) / 2 + spread)


def sorted_rows(a):
    return a[np.lexsort(a.T[::-1])]


def test_voxel_count_and_means_match_brute_force_over_several_batches():
    rng = np.random.default_rng(0)
    voxel_map = VoxelMap(VOXEL, lower=LOWER, upper=UPPER)
    batches = [random_points(rng, n) for n in (500, 1500, 3000)]
    # Duplicated points within a batch must not be double-counted.
    batches.append(np.vstack([batches[0][:200], batches[0][:200]]))
    seen, total_new = [], 0
    for batch in batches:
        seen.append(batch)
        new = voxel_map.fuse(batch)
        cells, means, counts = reference_voxels(np.vstack(seen))
        total_new += new
        assert voxel_map.num_voxels == len(cells) == total_new
    # Same cells, same per-voxel means and counts, in the same (key) order.
    assert np.array_equal(sorted_rows(voxel_map.voxel_indices()), cells)
    order = np.lexsort(voxel_map.voxel_indices().T[::-1])
    np.testing.assert_allclose(voxel_map.points()[order], means, atol=1e-12)
    assert np.array_equal(voxel_map.counts()[order], counts)
    # Every representative lies inside its own voxel, whose centre voxel_centers reports.
    centres = voxel_map.voxel_centers()
    assert np.all(np.abs(voxel_map.points() - centres) <= VOXEL / 2 + 1e-12)


def test_per_voxel_outputs_are_in_first_observed_order():
    voxel_map = VoxelMap(VOXEL, lower=LOWER, upper=UPPER, representative="first")
    a = np.array([[0.455, 0.105, 0.255], [0.215, -0.145, 0.005]])  # high key, then low key
    b = np.array([[0.335, 0.005, 0.105], [0.456, 0.106, 0.256]])  # new, then a[0]'s voxel
    voxel_map.fuse(a)
    voxel_map.fuse(b)
    # By the fuse call that first saw them (a's before b's), then by key within a call.
    np.testing.assert_array_equal(voxel_map.points(), [a[1], a[0], b[0]])
    np.testing.assert_array_equal(voxel_map.counts(), [1, 2, 1])
    np.testing.assert_array_equal(
        voxel_map.voxel_indices(), [[1, 0, 0], [25, 25, 25], [13, 15, 10]]
    )
    assert np.all(np.diff(voxel_map.keys) > 0)  # keys are reported sorted


def test_box_can_be_given_positionally_and_has_a_workspace_default():
    rng = np.random.default_rng(7)
    points = random_points(rng, 500)
    positional = VoxelMap(VOXEL, LOWER, UPPER)
    keyword = VoxelMap(voxel_size=VOXEL, lower=LOWER, upper=UPPER)
    assert positional.fuse(points) == keyword.fuse(points) > 0
    default = VoxelMap()
    assert default.voxel_size == DEFAULT_VOXEL_SIZE
    assert np.array_equal(default.lower, DEFAULT_LOWER)
    assert np.array_equal(default.upper, DEFAULT_UPPER)
    assert default.fuse([[0.5, 0.0, 0.05], [0.5, 0.0, -0.01]]) == 1  # below the table: dropped


def test_fusing_the_same_points_twice_adds_nothing():
    rng = np.random.default_rng(1)
    points = random_points(rng, 2000)
    voxel_map = VoxelMap(VOXEL, lower=LOWER, upper=UPPER)
    first = voxel_map.fuse(points)
    before = voxel_map.points()
    assert first > 0
    assert voxel_map.fuse(points) == 0
    assert voxel_map.num_voxels == first
    # The same points again leave every mean where it was, and double the counts.
    np.testing.assert_allclose(voxel_map.points(), before, atol=1e-12)
    assert voxel_map.counts().sum() == 2 * reference_voxels(points)[2].sum()


def test_points_outside_the_box_and_non_finite_points_are_dropped():
    voxel_map = VoxelMap(VOXEL, lower=LOWER, upper=UPPER)
    outside = np.array(
        [
            LOWER - [1e-9, 0, 0],
            UPPER + [0, 0, 1e-9],
            [0.35, 0.0, -0.001],  # just below the table
            [np.nan, 0.0, 0.1],
            [0.3, np.inf, 0.1],
        ]
    )
    assert voxel_map.fuse(outside) == 0
    assert voxel_map.num_voxels == 0
    # Bounds are inclusive: both corners are kept, in the first and the last voxel.
    assert voxel_map.fuse(np.array([LOWER, UPPER])) == 2
    indices = voxel_map.voxel_indices()
    assert np.array_equal(indices[0], [0, 0, 0])
    assert np.array_equal(indices[1], voxel_map.dims - 1)
    assert voxel_map.fuse(np.empty((0, 3))) == 0


def test_box_corners_land_in_their_own_voxels_for_any_box():
    # (upper - lower) / voxel is often a hair above or below an integer in floating point;
    # the upper corner must still get a valid voxel, the one it lies in.
    rng = np.random.default_rng(5)
    for _ in range(200):
        lower = rng.uniform(-1, 1, 3).round(3)
        upper = lower + rng.integers(1, 40, 3) * 0.01
        voxel = rng.choice([0.001, 0.002, 0.003, 0.005, 0.01])
        voxel_map = VoxelMap(voxel, lower=lower, upper=upper)
        assert voxel_map.fuse(np.array([lower, upper])) == 2
        indices = voxel_map.voxel_indices()
        assert np.all((indices >= 0) & (indices < voxel_map.dims))
        assert np.all(np.abs(voxel_map.voxel_centers() - [lower, upper]) <= voxel / 2 + 1e-9)


def test_huge_grids_still_count_correctly():
    # 10^6 voxels per axis: keys need 60 bits, too many to pack the batch rows alongside them,
    # which takes the other sorting path.
    lower, upper = np.zeros(3), np.full(3, 100.0)
    voxel_map = VoxelMap(1e-4, lower=lower, upper=upper)
    rng = np.random.default_rng(6)
    points = rng.uniform(0, 100, (500, 3))
    assert voxel_map.fuse(points[:300]) == 300
    # 200 new points plus 100 in occupied voxels.
    assert voxel_map.fuse(np.vstack([points[300:], points[:100]])) == 200
    cells = reference_voxels(points, lower, upper, 1e-4)[0]
    assert np.array_equal(sorted_rows(voxel_map.voxel_indices()), cells)
    assert np.all(np.diff(voxel_map.keys) > 0)
    assert sorted(voxel_map.counts()) == [1] * 400 + [2] * 100


def test_first_representative_keeps_the_first_point_seen():
    voxel_map = VoxelMap(VOXEL, lower=LOWER, upper=UPPER, representative="first")
    a = np.array([[0.3012, 0.0011, 0.1013], [0.4005, 0.05, 0.2]])
    b = np.array([[0.3088, 0.0077, 0.1077], [0.3011, 0.0012, 0.1012]])  # same voxel as a[0]
    assert voxel_map.fuse(a) == 2
    assert voxel_map.fuse(b) == 0
    points = voxel_map.points()
    assert any(np.array_equal(p, a[0]) for p in points)
    assert any(np.array_equal(p, a[1]) for p in points)
    assert sorted(voxel_map.counts()) == [1, 3]


def test_mean_representative_is_the_mean_across_batches():
    voxel_map = VoxelMap(VOXEL, lower=LOWER, upper=UPPER)
    a = np.array([[0.301, 0.001, 0.101]])
    b = np.array([[0.309, 0.009, 0.109], [0.305, 0.002, 0.104]])
    voxel_map.fuse(a)
    voxel_map.fuse(b)
    np.testing.assert_allclose(voxel_map.points(), [np.vstack([a, b]).mean(axis=0)])


def test_reset_forgets_everything():
    rng = np.random.default_rng(2)
    voxel_map = VoxelMap(VOXEL, lower=LOWER, upper=UPPER)
    points = random_points(rng, 500)
    first = voxel_map.fuse(points)
    voxel_map.reset()
    assert voxel_map.num_voxels == 0
    assert voxel_map.points().shape == (0, 3)
    assert voxel_map.fuse(points) == first


def test_occupancy_grid_marks_exactly_the_cells_holding_voxels():
    voxel_map = VoxelMap(0.001, lower=LOWER, upper=UPPER)
    centre = np.array([0.35, 0.0, 0.1])
    # A cube of edge 0.08 m split into 4 cells of 0.02 m per axis; its low corner
    # (0.31, -0.04, 0.06) is on the 1 mm voxel grid, so every voxel is inside one cell.
    points = centre + np.array(
        [
            [-0.0395, -0.0395, -0.0395],  # cell (0, 0, 0)
            [0.0105, 0.0305, 0.0305],  # cell (2, 3, 3): x, y, z not interchangeable
            [0.0305, -0.0295, 0.0005],  # cell (3, 0, 2)
            [0.0315, -0.0285, 0.0015],  # the same cell again
            [0.0405, 0.0, 0.0],  # beyond the cube's +x face
            [0.0, -0.0415, 0.0],  # beyond the -y face
        ]
    )
    voxel_map.fuse(points)
    grid = voxel_map.occupancy_grid(centre, 0.08, 4)
    assert grid.shape == (4, 4, 4) and grid.dtype == np.uint8
    expected = np.zeros((4, 4, 4), dtype=np.uint8)
    expected[0, 0, 0] = expected[2, 3, 3] = expected[3, 0, 2] = 1
    assert np.array_equal(grid, expected)
    as_float = voxel_map.occupancy_grid(centre, 0.08, 4, dtype=np.float32)
    assert as_float.dtype == np.float32 and np.array_equal(as_float, expected)
    grid[:] = 0  # the caller owns the returned array
    assert np.array_equal(voxel_map.occupancy_grid(centre, 0.08, 4), expected)
    assert VoxelMap(0.001, lower=LOWER, upper=UPPER).occupancy_grid(centre, 0.08, 4).sum() == 0


def brute_force_grid(voxel_map, centre, size, resolution):
    cells = np.floor((voxel_map.voxel_centers() - (centre - size / 2)) / (size / resolution))
    cells = cells[np.all((cells >= 0) & (cells < resolution), axis=1)].astype(int)
    expected = np.zeros((resolution,) * 3, dtype=np.uint8)
    expected[tuple(cells.T)] = 1
    return expected


def test_occupancy_grid_matches_brute_force_while_the_map_grows():
    rng = np.random.default_rng(3)
    voxel_map = VoxelMap(VOXEL / 4, lower=LOWER, upper=UPPER)
    cubes = [(np.array([0.33, 0.02, 0.12]), 0.17, 9), (np.array([0.4, -0.05, 0.2]), 0.1, 16)]
    # Alternate cubes and fuse between calls: the incremental update must equal a recount.
    for step in range(8):
        voxel_map.fuse(random_points(rng, 400))
        centre, size, resolution = cubes[step // 3 % 2]
        grid = voxel_map.occupancy_grid(centre, size, resolution)
        assert np.array_equal(grid, brute_force_grid(voxel_map, centre, size, resolution))
        assert 0 < grid.sum() < grid.size
    voxel_map.reset()
    assert voxel_map.occupancy_grid(*cubes[0]).sum() == 0  # the last cube: no stale cache


def test_open3d_backend_agrees_with_numpy():
    rng = np.random.default_rng(4)
    reference = VoxelMap(VOXEL, lower=LOWER, upper=UPPER, representative="first")
    hashed = Open3DVoxelMap(VOXEL, lower=LOWER, upper=UPPER)
    for n in (300, 1000, 1000):
        batch = random_points(rng, n)
        assert hashed.fuse(batch) == reference.fuse(batch)
    assert np.array_equal(hashed.keys, reference.keys)
    assert np.array_equal(
        sorted_rows(hashed.voxel_indices()), sorted_rows(reference.voxel_indices())
    )
    # One point per voxel, lying inside it.
    points = hashed.points()
    assert np.all(np.abs(points - hashed.voxel_centers()) <= VOXEL / 2 + 1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"voxel_size": 0.0}, "voxel_size"),
        ({"voxel_size": float("nan")}, "voxel_size"),
        ({"lower": UPPER, "upper": LOWER}, "lower < upper"),
        ({"lower": [0, 0], "upper": UPPER}, "lower"),
        ({"representative": "median"}, "representative"),
    ],
)
def test_invalid_arguments_are_rejected(kwargs, match):
    arguments = {"voxel_size": VOXEL, "lower": LOWER, "upper": UPPER, **kwargs}
    with pytest.raises(ValueError, match=match):
        VoxelMap(**arguments)


def test_invalid_points_and_grids_are_rejected():
    voxel_map = VoxelMap(VOXEL, lower=LOWER, upper=UPPER)
    with pytest.raises(ValueError, match="shape"):
        voxel_map.fuse(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="size"):
        voxel_map.occupancy_grid([0.3, 0, 0.1], 0.0, 8)
    with pytest.raises(ValueError, match="resolution"):
        voxel_map.occupancy_grid([0.3, 0, 0.1], 0.1, 0)
    for not_a_count in (2.7, "4", True):  # 2.7 was silently a grid of 2
        with pytest.raises(ValueError, match="resolution must be an integer"):
            voxel_map.occupancy_grid([0.3, 0, 0.1], 0.1, not_a_count)
