"""CoverageTracker: surface coverage within epsilon, checked against brute-force distances."""

import tracemalloc

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from liuxing_envs.perception.coverage import COVERAGE_METHODS, CoverageTracker

RADIUS = 0.06
CENTRE = np.array([0.5, 0.0, 0.07])


def sphere(rng, n, radius=RADIUS):
    v = rng.normal(size=(n, 3))
    return CENTRE + radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def view(rng, n, noise=0.002):
    """Noisy points on the half of the sphere facing a random direction."""
    direction = rng.normal(size=3)
    points = sphere(rng, 3 * n)
    points = points[(points - CENTRE) @ direction > 0][:n]
    return points + rng.normal(scale=noise, size=points.shape)


def brute_force_covered(samples, points, epsilon):
    if len(points) == 0:
        return np.zeros(len(samples), dtype=bool)
    return cdist(samples, points).min(axis=1) <= epsilon


def bytes_kept_by(make) -> int:
    """Memory (numpy arrays included) that ``make()`` allocates and its result keeps."""
    tracemalloc.start()
    try:
        made = make()
        kept = tracemalloc.get_traced_memory()[0]
        del made
        return kept
    finally:
        tracemalloc.stop()


METHODS = [{"method": m} for m in COVERAGE_METHODS]


@pytest.mark.parametrize("options", METHODS, ids=list(COVERAGE_METHODS))
def test_matches_brute_force_and_gains_add_up(options):
    rng = np.random.default_rng(0)
    samples = sphere(rng, 2048)
    epsilon = 0.004
    observable = rng.random(len(samples)) < 0.8
    tracker = CoverageTracker(samples, epsilon, observable, **options)
    seen = np.zeros(len(samples), dtype=bool)
    gains, coverages = [], [tracker.coverage]
    for n in (50, 300, 0, 800, 800, 2000):
        points = view(rng, n) if n else np.empty((0, 3))
        gain = tracker.update(points)
        newly = brute_force_covered(samples, points, epsilon) & observable & ~seen
        seen |= newly
        assert gain == pytest.approx(newly.sum() / observable.sum(), abs=1e-15)
        assert np.array_equal(tracker.covered, seen)
        gains.append(gain)
        coverages.append(tracker.coverage)
    assert 0.0 < coverages[-1] < 1.0
    assert all(0.0 <= c <= 1.0 for c in coverages)
    assert np.all(np.diff(coverages) >= 0)  # monotone
    assert sum(gains) == pytest.approx(tracker.coverage, abs=1e-12)
    assert tracker.num_covered == seen.sum()
    assert gains[2] == 0.0  # the empty view


@pytest.mark.parametrize("options", METHODS, ids=list(COVERAGE_METHODS))
def test_epsilon_boundary_in_every_direction(options):
    rng = np.random.default_rng(1)
    epsilon = 0.002
    # Samples far apart (10 epsilon) on a lattice, so each probe can only cover its own.
    samples = np.stack(np.meshgrid(*[np.arange(6) * 10 * epsilon] * 3, indexing="ij"), -1)
    samples = samples.reshape(-1, 3) + rng.uniform(-epsilon, epsilon, (216, 3)) + [0.4, -0.1, 0]
    directions = rng.normal(size=(216, 3))
    # Include axis and diagonal directions: they cross into face, edge and corner cells.
    directions[:8] = [[1, 0, 0], [0, -1, 0], [0, 0, 1], [1, 1, 0], [1, 1, 1], [-1, -1, -1],
                      [1, -1, 1], [0, 1, -1]]  # fmt: skip
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)

    far = CoverageTracker(samples, epsilon, **options)
    assert far.update(samples + 1.1 * epsilon * directions) == 0.0
    assert far.coverage == 0.0
    near = CoverageTracker(samples, epsilon, **options)
    assert near.update(samples + 0.9 * epsilon * directions) == 1.0
    assert near.coverage == 1.0
    # Half in, half out: exactly the near half is covered.
    half = CoverageTracker(samples, epsilon, **options)
    scale = np.where(np.arange(216) % 2 == 0, 0.999, 1.001)[:, None]
    half.update(samples + scale * epsilon * directions)
    assert np.array_equal(half.covered, np.arange(216) % 2 == 0)


def test_both_methods_agree_on_points_exactly_at_epsilon():
    # A squared distance a rounding error above epsilon**2 whose square root is epsilon: the
    # kdtree method once counted it (distance <= epsilon) where the grid method did not.
    rng = np.random.default_rng(5)
    epsilon = 0.01
    samples = rng.uniform(-0.1, 0.1, (300, 3)) + [0.5, 0.0, 0.1]
    directions = rng.normal(size=samples.shape)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = samples + epsilon * directions
    covered = [
        CoverageTracker(samples, epsilon, method=method).update(points)
        for method in COVERAGE_METHODS
    ]
    assert covered[0] == covered[1]
    single = np.array([[0.1, 0.2, 0.3]])
    point = np.array([[0.10456535710689069, 0.1922333483436855, 0.29565988058504955]])
    gains = [CoverageTracker(single, epsilon, method=m).update(point) for m in COVERAGE_METHODS]
    assert gains == [0.0] * len(COVERAGE_METHODS)


@pytest.mark.parametrize("options", METHODS, ids=list(COVERAGE_METHODS))
def test_any_sample_layout_and_epsilon(options):
    # Arbitrary extents, offsets and epsilons put samples on or near cell boundaries of the
    # grid method (its first version failed on ~40 % of these layouts).
    rng = np.random.default_rng(4)
    for _ in range(150):
        samples = rng.uniform(-1, 1, (40, 3)) * rng.uniform(0.01, 0.5) + rng.uniform(-1, 1, 3)
        samples[:4] = np.round(samples[:4], 2)  # some on round coordinates
        epsilon = rng.choice([rng.uniform(0.001, 0.05), 0.01, 0.005])
        tracker = CoverageTracker(samples, epsilon, **options)
        points = samples + rng.normal(size=samples.shape) * epsilon * 0.7
        tracker.update(points)
        assert np.array_equal(tracker.covered, brute_force_covered(samples, points, epsilon))


@pytest.mark.parametrize("method", COVERAGE_METHODS)
def test_preview_predicts_the_gain_without_recording_it(method):
    rng = np.random.default_rng(5)
    samples = sphere(rng, 2000)
    tracker = CoverageTracker(samples, 0.004, method=method)
    for n in (300, 300, 1000):
        points = view(rng, n)
        before = tracker.covered
        predicted = tracker.preview(points)
        assert np.array_equal(tracker.covered, before)  # nothing recorded
        assert tracker.preview(points) == predicted
        assert tracker.update(points) == pytest.approx(predicted, abs=1e-15)
        assert predicted > 0
    assert tracker.preview(points) == 0.0  # the same view again adds nothing
    assert tracker.preview(np.empty((0, 3))) == 0.0


@pytest.mark.parametrize("method", COVERAGE_METHODS)
def test_fresh_trackers_share_the_set_up_but_not_what_they_covered(method):
    rng = np.random.default_rng(8)
    samples = sphere(rng, 2000)
    observable = rng.random(2000) < 0.9
    original = CoverageTracker(samples, 0.004, observable, method=method)
    original.update(view(rng, 800))
    first, second = original.fresh(), original.fresh()
    alone = CoverageTracker(samples, 0.004, observable, method=method)
    assert first.coverage == 0.0 and original.coverage > 0.0
    for _ in range(3):  # interleaved scans, each as if it had its tracker to itself
        a, b = view(rng, 500), view(rng, 500)
        assert first.update(a) == alone.update(a)
        second.update(b)
        assert np.array_equal(first.covered, alone.covered)
    assert not np.array_equal(first.covered, second.covered)
    # One set-up in memory: a fresh tracker allocates its own scan state, not a second grid
    # (nor a second copy of the samples).
    set_up = bytes_kept_by(lambda: CoverageTracker(samples, 0.004, observable, method=method))
    assert bytes_kept_by(original.fresh) < 0.25 * set_up


@pytest.mark.parametrize("method", COVERAGE_METHODS)
def test_non_observable_samples_never_count(method):
    rng = np.random.default_rng(2)
    samples = sphere(rng, 1000)
    observable = samples[:, 2] > CENTRE[2] - 0.5 * RADIUS  # e.g. not the bottom cap
    tracker = CoverageTracker(samples, 0.003, observable, method=method)
    gain = tracker.update(samples)  # every sample observed exactly
    assert gain == 1.0 and tracker.coverage == 1.0
    assert np.array_equal(tracker.covered, observable)
    assert tracker.num_covered == observable.sum() < len(samples)
    assert tracker.update(samples) == 0.0


@pytest.mark.parametrize("method", COVERAGE_METHODS)
def test_points_far_away_or_empty_gain_nothing_and_reset_restarts(method):
    rng = np.random.default_rng(3)
    samples = sphere(rng, 500)
    tracker = CoverageTracker(samples, 0.003, method=method)
    assert tracker.update(np.empty((0, 3))) == 0.0
    assert tracker.update(samples + [1.0, 0.0, 0.0]) == 0.0
    expected = brute_force_covered(samples, samples[:100], 0.003)
    assert tracker.update(samples[:100]) == pytest.approx(expected.mean())
    tracker.reset()
    assert tracker.coverage == 0.0 and not tracker.covered.any()
    assert tracker.update(samples[:100]) == pytest.approx(expected.mean())
    assert np.array_equal(tracker.covered, expected)


@pytest.mark.parametrize(
    ("args", "kwargs", "error", "match"),
    [
        ((np.zeros((5, 2)), 0.01), {}, ValueError, "samples"),
        ((np.zeros((0, 3)), 0.01), {}, ValueError, "at least one"),
        ((np.full((5, 3), np.nan), 0.01), {}, ValueError, "finite"),
        ((np.zeros((5, 3)), 0.0), {}, ValueError, "epsilon"),
        ((np.zeros((5, 3)), float("nan")), {}, ValueError, "epsilon"),
        ((np.zeros((5, 3)), 0.01, np.ones(4, dtype=bool)), {}, ValueError, "observable"),
        ((np.zeros((5, 3)), 0.01, np.arange(5)), {}, TypeError, "boolean"),
        ((np.zeros((5, 3)), 0.01, np.zeros(5, dtype=bool)), {}, ValueError, "observable"),
        ((np.zeros((5, 3)), 0.01), {"method": "octree"}, ValueError, "method"),
    ],
)
def test_invalid_construction_is_rejected(args, kwargs, error, match):
    with pytest.raises(error, match=match):
        CoverageTracker(*args, **kwargs)


def test_invalid_points_are_rejected():
    tracker = CoverageTracker(np.zeros((5, 3)), 0.01)
    with pytest.raises(ValueError, match="shape"):
        tracker.update(np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        tracker.update(np.array([[0.0, np.nan, 0.0]]))
    assert tracker.coverage == 0.0


def test_the_compiled_update_equals_the_numpy_grid_over_a_long_scan():
    # The compiled kernel replaces the numpy grid update: the same samples covered after every
    # one of 500 updates of every size, previews included, with epsilons on and off round values.
    rng = np.random.default_rng(5)
    for epsilon in (0.004, 0.003, 0.0025):
        samples = sphere(rng, 4096)
        observable = rng.random(len(samples)) < 0.9
        reference = CoverageTracker(samples, epsilon, observable, method="grid")
        compiled = CoverageTracker(samples, epsilon, observable, method="compiled")
        for step in range(170):
            points = view(rng, int(rng.integers(0, 600)), noise=float(rng.uniform(0, 0.004)))
            if step % 7 == 0:
                assert compiled.preview(points) == reference.preview(points)
            assert compiled.update(points) == reference.update(points)
            assert np.array_equal(compiled.covered, reference.covered)
            if step % 40 == 39:
                reference.reset()
                compiled.reset()
        assert compiled.num_covered == reference.num_covered > 0


def test_the_default_method_is_the_compiled_one_where_numba_is_installed():
    pytest.importorskip("numba")
    assert CoverageTracker(np.zeros((5, 3)), 0.01).method == "compiled"
