"""FreeSpaceGrid: the cells depth rays cross, against exact cases and a fine-sampled reference."""

import numpy as np
import pytest

from liuxing_envs.perception.free_space import FreeSpaceGrid

#: A cube of 8 one-metre cells per axis with its low corner at the origin: cell (i, j, k)
#: spans [i, i+1) x [j, j+1) x [k, k+1).
RESOLUTION, SIZE, CENTER = 8, 8.0, (4.0, 4.0, 4.0)


def grid(ray_stride=1):
    free_space = FreeSpaceGrid(RESOLUTION, ray_stride=ray_stride)
    free_space.reset(CENTER, SIZE)
    return free_space


def marked(free_space):
    return {tuple(cell) for cell in np.argwhere(free_space.seen())}


def reference_cells(origin, points, samples=20000):
    """Cells met by each segment from ``origin`` to half a cell short of its point, sampled
    finely (in this cube, metres are cells)."""
    cells = set()
    origin = np.asarray(origin, float)
    for point in np.asarray(points, float):
        direction = point - origin
        stop = 1.0 - 0.5 / np.linalg.norm(direction)
        along = origin + np.linspace(0.0, stop, samples)[:, None] * direction
        inside = np.all((along >= 0) & (along < RESOLUTION), axis=1)
        cells |= {tuple(cell) for cell in np.floor(along[inside]).astype(int)}
    return cells


def test_a_ray_marks_the_cells_it_crosses_and_stops_half_a_cell_short_of_its_surface():
    free_space = grid()
    # From outside the cube along x, to a surface at x = 6.2: the cells x = 0..5 (the last
    # reached at 5.7), not the surface's cell 6 nor cell 7 behind it.
    free_space.carve((-3.0, 2.5, 3.5), [(6.2, 2.5, 3.5)])
    assert marked(free_space) == {(x, 2, 3) for x in range(6)}


def test_a_diagonal_ray_marks_only_the_cells_on_the_diagonal():
    free_space = grid()
    free_space.carve((-1.0, -1.0, -1.0), [(6.5, 6.5, 6.5)])
    assert marked(free_space) == {(k, k, k) for k in range(7)}


def test_rays_that_miss_the_cube_or_stop_before_it_mark_nothing():
    free_space = grid()
    free_space.carve((-1.0, -1.0, 9.0), [(-1.0, 9.0, 9.0), (-5.0, 2.0, 2.0)])
    free_space.carve((-3.0, 2.5, 2.5), [(-0.2, 2.5, 2.5)])  # the surface is outside the cube
    free_space.carve((1.5, 1.5, 1.5), np.zeros((0, 3)))  # no returns
    assert marked(free_space) == set()


@pytest.mark.parametrize("camera_z", [7.5, 4.5])
def test_a_camera_inside_the_cube_marks_from_its_own_cell_on(camera_z):
    free_space = grid()
    free_space.carve((2.5, 2.5, camera_z), [(2.5, 2.5, 0.5)])
    assert marked(free_space) == {(2, 2, z) for z in range(1, int(camera_z) + 1)}


def test_rays_in_a_face_plane_or_grazing_it_stay_in_the_cube():
    free_space = grid()
    # In the plane of a high face: outside the half-open cube, so nothing.
    free_space.carve((2.5, 8.0, 3.5), [(6.2, 8.0, 3.5)])
    free_space.carve((8.0, 2.5, 3.5), [(8.0, 6.5, 3.5)])
    assert marked(free_space) == set()
    # In the plane of a low face: inside.
    free_space.carve((-3.0, 0.0, 3.5), [(6.2, 0.0, 3.5)])
    assert marked(free_space) == {(x, 0, 3) for x in range(6)}
    # Grazing the high x face from just inside: rounding may reach x = 8, which is cell 7,
    # never a wrap into the next row or an index past the end.
    free_space = grid()
    free_space.carve((8.0 - 1e-12, 2.5, 3.5), [(8.0 - 1e-12 + 1e-8, 6.7, 3.5)])
    assert {(x, z) for x, _, z in marked(free_space)} == {(7, 3)}


def test_random_rays_mark_the_cells_a_fine_sampling_meets():
    rng = np.random.default_rng(0)
    origin = (4.0, -6.0, 11.0)
    points = rng.uniform(0.5, 7.5, (60, 3))
    free_space = grid()
    free_space.carve(origin, points)
    reference = reference_cells(origin, points)
    carved = marked(free_space)
    # Steps of at most half a cell can only skip the corner of a cell a ray grazes.
    assert carved <= reference
    assert len(carved) >= 0.9 * len(reference)


def test_reset_clears_and_moves_the_cube():
    free_space = grid()
    free_space.carve((-3.0, 2.5, 3.5), [(6.2, 2.5, 3.5)])
    free_space.reset((5.0, 4.0, 4.0), SIZE)  # one cell further along x
    assert marked(free_space) == set()
    free_space.carve((-3.0, 2.5, 3.5), [(6.2, 2.5, 3.5)])
    assert marked(free_space) == {(x, 2, 3) for x in range(5)}


def test_ray_stride_carves_with_every_nth_ray():
    points = [(6.2, y + 0.5, 3.5) for y in range(4)]
    free_space = grid(ray_stride=2)
    free_space.carve((-3.0, 2.0, 3.5), points)
    # Near the surfaces (x = 5) each ray is in its own row: only the 1st and 3rd carved.
    assert {cell[1] for cell in marked(free_space) if cell[0] == 5} == {0, 2}


def test_occupied_cells_are_never_free():
    free_space = grid()
    free_space.carve((-3.0, 2.5, 3.5), [(6.2, 2.5, 3.5)])
    occupied = np.zeros((RESOLUTION,) * 3, dtype=np.uint8)
    occupied[3, 2, 3] = 1
    free = free_space.free(occupied)
    assert free.dtype == bool
    assert {tuple(cell) for cell in np.argwhere(free)} == {(x, 2, 3) for x in (0, 1, 2, 4, 5)}


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: FreeSpaceGrid(0), "resolution must be an integer in"),
        (lambda: FreeSpaceGrid(2.5), "resolution must be an integer in"),  # was a grid of 2
        (lambda: FreeSpaceGrid(8, ray_stride=0), "ray_stride must be an integer in"),
        (lambda: FreeSpaceGrid(8).carve((0.0, 0.0), [(1.0, 1.0, 1.0)]), r"origin must have"),
        (lambda: FreeSpaceGrid(8).carve((0.0, 0.0, 0.0), [(1.0, 1.0)]), r"shape \(N, 3\)"),
        (lambda: FreeSpaceGrid(8).free(np.zeros((4, 4, 4))), r"shape \(8, 8, 8\)"),
        (lambda: FreeSpaceGrid(8).reset((0.0, np.nan, 0.0), 1.0), "center must be 3 finite"),
        (lambda: FreeSpaceGrid(8).reset((0.0, 0.0, 0.0), -1.0), "size must be a positive"),
    ],
)
def test_bad_arguments_get_clear_errors(call, message):
    with pytest.raises(ValueError, match=message):
        call()
