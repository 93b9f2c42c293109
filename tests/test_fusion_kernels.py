"""The compiled back-projection, crop, fusion, free-space carving and observation
(liuxing_envs.kernels.fusion) against the numpy code they replace: the same hits, cropped
points, voxel keys, points, counts, occupancy and free-space grids and uint8 depth bytes at
every view, bit for bit, and ViewPlanning-v1 episodes that do not change when the kernels are
switched off.

Real MuJoCo scenes, no mocks (``MUJOCO_GL=egl`` from conftest.py).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import liuxing_envs  # noqa: F401  (registers the ids)
from liuxing_envs.envs.view_planning import ViewPlanningEnv
from liuxing_envs.perception.free_space import FreeSpaceGrid
from liuxing_envs.perception.fusion import VoxelMap
from liuxing_envs.sensors.view_sensor import ARM_FILTER_MARGIN, ViewSensor, estimate_center
from liuxing_envs.sim.scene import HOME_QPOS

pytest.importorskip("numba")
from liuxing_envs.kernels.fusion import depth_bytes  # noqa: E402

#: Small and fast env settings (one scale, few coverage samples).
FAST = {"scales": (1.0,), "coverage_samples": 1024}


def assert_same_bits(got, expected, what=""):
    got, expected = np.asarray(got), np.asarray(expected)
    assert got.shape == expected.shape and got.dtype == expected.dtype, what
    assert got.tobytes() == expected.tobytes(), what  # the signs of zeros too


def assert_same_maps(got: VoxelMap, expected: VoxelMap, what=""):
    assert got.num_voxels == expected.num_voxels, what
    assert_same_bits(got.keys, expected.keys, what)
    assert_same_bits(got.voxel_indices(), expected.voxel_indices(), what)
    assert_same_bits(got.points(), expected.points(), what)
    assert_same_bits(got.counts(), expected.counts(), what)


# --- the voxel map and the free-space grid alone --------------------------------------------


def _batches(rng, count):
    """Point batches around and inside the box: duplicates (several points per voxel),
    points outside it, exactly on its bounds, non-finite ones, and empty batches."""
    lower, upper = np.array([0.2, -0.15, 0.0]), np.array([0.5, 0.15, 0.3])
    for i in range(count):
        n = int(rng.integers(0, 800))
        points = (lower + upper) / 2 + rng.uniform(-0.6, 0.6, (n, 3)) * (upper - lower)
        if n and i % 3 == 0:  # clustered: many points per voxel
            points = np.round(points, 2) + rng.normal(0, 1e-3, points.shape)
        if n > 10:
            points[:5] = points[5:10]  # the same points twice in one batch
            points[0] = upper
            points[1] = lower
            points[2, int(rng.integers(3))] = [np.nan, np.inf, -np.inf][i % 3]
        yield lower, upper, points


@pytest.mark.parametrize("representative", ["mean", "first"])
def test_compiled_fusion_equals_numpy(representative):
    rng = np.random.default_rng(4)
    lower, upper = np.array([0.2, -0.15, 0.0]), np.array([0.5, 0.15, 0.3])
    maps = {
        compiled: VoxelMap(0.01, lower, upper, representative=representative, compiled=compiled)
        for compiled in (False, True)
    }
    assert maps[True].compiled and not maps[False].compiled
    cubes = [((0.35, 0.0, 0.15), 0.2, 8), ((0.3, 0.05, 0.1), 0.13, 16)]
    for i, (_, _, points) in enumerate(_batches(rng, 60)):
        if i == 30:
            for voxel_map in maps.values():
                voxel_map.reset()
        new = {compiled: voxel_map.fuse(points) for compiled, voxel_map in maps.items()}
        assert new[True] == new[False]
        assert_same_maps(maps[True], maps[False], f"batch {i}")
        center, size, resolution = cubes[(i // 7) % 2]  # incremental, then a new cube
        for dtype in (np.uint8, np.float32):
            assert_same_bits(
                maps[True].occupancy_grid(center, size, resolution, dtype=dtype),
                maps[False].occupancy_grid(center, size, resolution, dtype=dtype),
            )


def test_compiled_carving_equals_numpy():
    rng = np.random.default_rng(5)
    grids = {compiled: FreeSpaceGrid(12, compiled=compiled) for compiled in (False, True)}
    for i in range(80):
        center = rng.uniform(-0.1, 0.1, 3)
        size = float(rng.uniform(0.1, 0.5))
        for grid in grids.values():
            grid.reset(center, size)
        # Cameras inside and outside the cube, rays along the axes (parallel to slabs), rays
        # ending outside the cube, on its faces, at the camera, and non-finite ends.
        origin = center + rng.uniform(-1.0, 1.0, 3) * size * (0.3 if i % 2 else 1.5)
        points = center + rng.uniform(-0.7, 0.7, (int(rng.integers(1, 400)), 3)) * size
        points[:3] = origin
        points[0, 0] += 0.3 * size
        points[1, 1] -= 0.2 * size
        if len(points) > 6:
            points[3] = center + 0.5 * size
            points[4] = origin
            points[5, i % 3] = np.nan
        for _ in range(2):
            for grid in grids.values():
                grid.carve(origin, points)
            assert_same_bits(grids[True].seen(), grids[False].seen(), f"cube {i}")
            points = points[::-1] + rng.normal(0, 0.01, points.shape)


def test_compiled_depth_bytes_equal_numpy():
    rng = np.random.default_rng(6)
    for depth_range in (1.0, 0.7, 2.3):
        # Every float32 near the ties of the rounding (k + 0.5) / 255 of the range, a random
        # spread, and the ends.
        ties = (np.arange(256) + 0.5) / 255 * depth_range
        near = ties.astype(np.float32).view(np.int32)[:, None] + np.arange(-64, 65)
        values = np.concatenate(
            [
                near.ravel().view(np.float32),
                rng.uniform(-0.1, 1.2 * depth_range, 100_000).astype(np.float32),
                np.array([0.0, -0.0, depth_range, np.inf, -np.inf, 1e-30], dtype=np.float32),
            ]
        )
        out = np.empty(values.size, dtype=np.uint8)
        assert depth_bytes(values, np.float32(depth_range), out)
        expected = np.round(255 * np.clip(values / depth_range, 0.0, 1.0)).astype(np.uint8)
        assert_same_bits(out, expected)
    out = np.empty(2, dtype=np.uint8)
    assert not depth_bytes(np.array([0.5, np.nan], dtype=np.float32), np.float32(1.0), out)


# --- the sensor over seeded ViewPlanning-v1 episodes ----------------------------------------


def _sensors(env: ViewPlanningEnv) -> dict[bool, ViewSensor]:
    settings = env.settings
    return {
        compiled: ViewSensor(
            settings.sensor, settings.fusion, settings.sensor.resolution, compiled=compiled
        )
        for compiled in (False, True)
    }


def _compare_capture(sensors, scene, rng_seed: int, what: str):
    """Both sensors capture the scene's view; everything they hold or return must agree."""
    got = {}
    for compiled, sensor in sensors.items():
        got[compiled] = sensor.capture(scene, np.random.default_rng(rng_seed))
    reference, kernel = sensors[False], sensors[True]
    assert_same_bits(got[True], got[False], f"cropped points, {what}")
    assert_same_bits(kernel.hits, reference.hits, f"hits, {what}")
    assert_same_bits(kernel.depth, reference.depth, f"depth, {what}")
    assert_same_maps(kernel.map, reference.map, what)
    assert_same_bits(kernel.preview_points(scene), reference.preview_points(scene), what)
    return got[False]


def _compare_observations(sensors, scene, center, what: str):
    for sensor in sensors.values():
        sensor.carve_free_space()
    observations = {c: sensor.observation(scene, center) for c, sensor in sensors.items()}
    assert observations[True].keys() == observations[False].keys()
    for key in observations[False]:
        assert_same_bits(observations[True][key], observations[False][key], f"{key}, {what}")


@pytest.mark.parametrize(
    ("observe_free_space", "filter_arm_points"), [(False, True), (True, False), (True, True)]
)
def test_sensor_kernels_equal_numpy_over_episodes(observe_free_space, filter_arm_points):
    # Views random actions reach and, between them, views from random joint poses near home,
    # many of which show the arm's own links (filtered out of the map when asked).
    env = ViewPlanningEnv(
        observe_free_space=observe_free_space, filter_arm_points=filter_arm_points, **FAST
    )
    env.action_space.seed(7)
    rng = np.random.default_rng(7)
    sensors = _sensors(env)
    assert sensors[True].compiled and not sensors[False].compiled
    scene = env.scene
    views = with_arm = 0
    center = None

    def look():
        nonlocal views, with_arm, center
        what = f"view {views}"
        points = _compare_capture(sensors, scene, views, what)
        if center is None:
            center = estimate_center(points, env.object_region)
            for sensor in sensors.values():
                sensor.start_free_space(center)
        _compare_observations(sensors, scene, center, what)
        on_arm = scene.camera.pixels_on_geoms(
            sensors[False].depth, scene.data, scene.arm.geom_ids, ARM_FILTER_MARGIN
        )
        with_arm += bool(on_arm.any())
        views += 1

    try:
        for episode in range(3):
            env.reset(seed=100 + episode)
            for sensor in sensors.values():
                sensor.reset()
            center = None
            look()
            for step in range(8):
                if step % 2:
                    scene.look_from(HOME_QPOS + rng.uniform(-0.7, 0.7, HOME_QPOS.size), look)
                else:
                    _, _, terminated, truncated, _ = env.step(env.action_space.sample())
                    look()
                    if terminated or truncated:
                        break
    finally:
        env.close()
    assert views >= 20
    assert with_arm >= 3  # the arm's links were in sight


@pytest.mark.parametrize("observe_free_space", [False, True])
def test_episodes_are_the_same_with_the_kernels_off(observe_free_space):
    envs = [
        gym.make("ViewPlanning-v1", observe_free_space=observe_free_space, **FAST) for _ in range(2)
    ]
    assert envs[0].unwrapped.sensor.compiled
    envs[1].unwrapped.sensor.compiled = False
    assert not envs[1].unwrapped.sensor.map.compiled
    try:
        for env in envs:
            env.action_space.seed(3)
        for episode in range(3):
            results = [env.reset(seed=episode) for env in envs]
            for _ in range(6):
                (obs, info), (ref_obs, ref_info) = [(r[0], r[-1]) for r in results]
                assert obs.keys() == ref_obs.keys()
                for key in ref_obs:
                    assert_same_bits(obs[key], ref_obs[key], f"{key}, episode {episode}")
                assert info.get("coverage") == ref_info.get("coverage")
                if len(results[0]) == 5 and (results[0][2] or results[0][3]):
                    break
                action = envs[0].action_space.sample()
                envs[1].action_space.sample()
                results = [env.step(action) for env in envs]
                assert results[0][1:4] == results[1][1:4]  # reward, terminated, truncated
            assert_same_maps(envs[0].unwrapped.map, envs[1].unwrapped.map)
    finally:
        for env in envs:
            env.close()


def test_self_filter_kernel_finds_the_pixels_numpy_finds_on_views_that_show_the_arm():
    # Views from random joint poses about home, many with links of the arm in sight. With
    # no margin the returns on a link lie on its surface, where the kernel leaves the
    # answer to the numpy code.
    env = ViewPlanningEnv(**FAST)
    rng = np.random.default_rng(11)
    scene = env.scene
    found = {}

    def look():
        depth = scene.render_depth(None)
        for margin in (ARM_FILTER_MARGIN, 0.0, 0.02):
            masks = [
                scene.camera.pixels_on_geoms(
                    depth, scene.data, scene.arm.geom_ids, margin, compiled=compiled
                )
                for compiled in (True, False)
            ]
            assert_same_bits(*masks, f"margin {margin}")
            found[margin] = found.get(margin, 0) + int(masks[1].any())

    try:
        for episode in range(4):
            env.reset(seed=episode)
            for _ in range(10):
                scene.look_from(HOME_QPOS + rng.uniform(-1.0, 1.0, HOME_QPOS.size), look)
    finally:
        env.close()
    assert min(found.values()) >= 8  # views with the arm's pixels, at every margin


def test_self_filter_kernel_leaves_a_geom_at_the_near_limit_to_numpy():
    # A box whose grown far side ends a hair short of min_depth: numpy skips it, so returns
    # nearer than min_depth (a hand-made image) on it are not the box's; a kernel that
    # decided the cut without its band would mark them.
    import mujoco

    from liuxing_envs.sim.camera import DepthCamera

    xml = """<mujoco><worldbody><camera name="eye" pos="0 0 0"/>
    <geom name="box" type="box" size="0.03 0.05 0.02" pos="0 0 -0.3"/></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    camera = DepthCamera(model, "eye", backend="raycast")
    margin, near = 0.003, camera.intrinsics.min_depth
    image = np.full((camera.intrinsics.height, camera.intrinsics.width), near * 0.9, np.float32)
    box = np.array([0])
    masks = {}
    for gap in (5e-10, 0.0, -5e-10, 1e-3, -1e-3):
        model.geom_pos[0] = [0.0, 0.0, -(near - gap) + 0.02 + margin]
        mujoco.mj_forward(model, data)
        for compiled in (True, False):
            masks[compiled] = camera.pixels_on_geoms(image, data, box, margin, compiled=compiled)
        assert_same_bits(masks[True], masks[False], f"far side {gap} m short of min_depth")
    assert masks[True].any()  # the last box reaches past min_depth and covers the image
    camera.close()
