"""The simulated depth camera: both backends, back-projection, intrinsics, noise, lifetime.

Real MuJoCo scenes and real rendering (``MUJOCO_GL=egl`` from conftest.py), no mocks.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import warnings

import mujoco
import numpy as np
import pytest

from liuxing_envs.perception import (
    camera_rays,
    crop_points,
    depth_to_camera_points,
    transform_points,
)
from liuxing_envs.sim.camera import (
    DEPTH_GEOM_GROUPS,
    REALSENSE_D435_DEPTH,
    CameraIntrinsics,
    DepthCamera,
    DepthNoise,
)
from liuxing_envs.sim.scene import (
    ARM_BASE_BODY,
    HOME_QPOS,
    WRIST_CAMERA,
    WRIST_CAMERA_SITE,
    load_scene_spec,
    reset_to_home,
)
from liuxing_envs.sim.viewpoints import look_at_quat
from tests.forked_child import outcome_in_forked_child

# The test box: 0.10 x 0.06 x 0.08 m, yawed 30 deg, resting on the table in front of the arm.
BOX_HALF = np.array([0.05, 0.03, 0.04])
BOX_POS = np.array([0.45, 0.10, 0.04])
BOX_YAW = math.radians(30.0)
CYLINDER_POS = np.array([0.33, 0.24, 0.03])  # radius 0.03, half-height 0.03
SPHERE_POS = np.array([0.55, 0.27, 0.035])  # radius 0.035

# Extra world-fixed cameras (eye, target) that look at the objects from the side.
EXTRA_VIEWS = {
    "side_view": ((0.80, -0.20, 0.30), (0.45, 0.12, 0.03)),
    "low_view": ((0.15, 0.50, 0.18), (0.45, 0.15, 0.03)),
    "far_view": ((1.20, 0.60, 0.50), (0.45, 0.15, 0.00)),
}
# Arm configurations that turn and tilt the wrist camera away from straight down.
ARM_POSES = {
    "home": HOME_QPOS,
    "tilted": HOME_QPOS + np.array([0.15, 0.10, -0.10, 0.40, 0.10, 0.30]),
    "turned": HOME_QPOS + np.array([-0.10, 0.0, 0.20, -0.45, -0.20, 0.0]),
}

AGREEMENT_TOL = 1e-3  # gl vs raycast, m
SURFACE_TOL = 2e-3  # back-projected points vs the true surfaces, m


def _box_rotation() -> np.ndarray:
    c, s = math.cos(BOX_YAW), math.sin(BOX_YAW)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _build_model(with_round_objects: bool) -> mujoco.MjModel:
    spec = load_scene_spec()
    box = spec.worldbody.add_body(
        name="box", pos=BOX_POS, quat=[math.cos(BOX_YAW / 2), 0.0, 0.0, math.sin(BOX_YAW / 2)]
    )
    box.add_geom(name="box", type=mujoco.mjtGeom.mjGEOM_BOX, size=BOX_HALF)
    if with_round_objects:
        cylinder = spec.worldbody.add_body(name="cylinder", pos=CYLINDER_POS)
        cylinder.add_geom(
            name="cylinder", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.03, 0.03, 0.0]
        )
        sphere = spec.worldbody.add_body(name="sphere", pos=SPHERE_POS)
        sphere.add_geom(name="sphere", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.035, 0, 0])
    for name, (eye, target) in EXTRA_VIEWS.items():
        spec.worldbody.add_camera(name=name, pos=eye, quat=look_at_quat(eye, target))
    return spec.compile()


class _CameraPool:
    """One camera per (model, name, backend), closed at the end of the module."""

    def __init__(self) -> None:
        self.cameras: dict[tuple[int, str, str], DepthCamera] = {}

    def get(self, model: mujoco.MjModel, name: str, backend: str) -> DepthCamera:
        key = (id(model), name, backend)
        if key not in self.cameras:
            self.cameras[key] = DepthCamera(model, name, backend=backend)
        return self.cameras[key]

    def close(self) -> None:
        for camera in self.cameras.values():
            camera.close()


@pytest.fixture(scope="module")
def objects_model() -> mujoco.MjModel:
    return _build_model(with_round_objects=True)


@pytest.fixture(scope="module")
def box_model() -> mujoco.MjModel:
    return _build_model(with_round_objects=False)


@pytest.fixture(scope="module")
def pool():
    cameras = _CameraPool()
    yield cameras
    cameras.close()


def _data_at(model: mujoco.MjModel, qpos: np.ndarray = HOME_QPOS) -> mujoco.MjData:
    data = mujoco.MjData(model)
    reset_to_home(model, data)
    data.qpos[: len(qpos)] = qpos
    mujoco.mj_forward(model, data)
    return data


def _geom_ids(camera: DepthCamera, data: mujoco.MjData) -> np.ndarray:
    """Ground-truth geom hit by each pixel-centre ray (-1: none), from MuJoCo's ray caster."""
    position, rotation = camera.pose(data)
    rays = camera_rays(camera.intrinsics, "unit").reshape(-1, 3) @ rotation.T
    n = rays.shape[0]
    geom_ids = np.empty(n, dtype=np.int32)
    dist = np.empty(n)
    groups = np.zeros(6, dtype=np.uint8)
    groups[list(DEPTH_GEOM_GROUPS)] = 1
    mujoco.mj_multiRay(
        camera.model, data, position, rays.ravel(), groups, 1, -1, geom_ids, dist, None, n, 100.0
    )
    return geom_ids.reshape(camera.intrinsics.height, camera.intrinsics.width)


def _near_boundary(labels: np.ndarray) -> np.ndarray:
    """Pixels within 1 px (8-neighbourhood) of a pixel with a different label."""
    padded = np.pad(labels, 1, mode="edge")
    h, w = labels.shape
    out = np.zeros(labels.shape, dtype=bool)
    for di in (0, 1, 2):
        for dj in (0, 1, 2):
            out |= padded[di : di + h, dj : dj + w] != labels
    return out


def _box_local(points: np.ndarray) -> np.ndarray:
    return (points - BOX_POS) @ _box_rotation()


def _box_surface_distance(points: np.ndarray) -> np.ndarray:
    """Unsigned distance of world points to the surface of the test box."""
    excess = np.abs(_box_local(points)) - BOX_HALF
    outside = np.linalg.norm(np.maximum(excess, 0.0), axis=1)
    inside = np.minimum(excess.max(axis=1), 0.0)
    return np.abs(outside + inside)


# --- gl vs raycast ---------------------------------------------------------------------------

AGREEMENT_CASES = [(WRIST_CAMERA, pose) for pose in ARM_POSES] + [
    (name, "home") for name in EXTRA_VIEWS
]


@pytest.mark.parametrize(("camera_name", "arm_pose"), AGREEMENT_CASES)
def test_gl_and_raycast_agree_away_from_silhouettes(objects_model, pool, camera_name, arm_pose):
    data = _data_at(objects_model, ARM_POSES[arm_pose])
    gl = pool.get(objects_model, camera_name, "gl")
    ray = pool.get(objects_model, camera_name, "raycast")
    depth_gl = gl.render(data)
    depth_ray = ray.render(data)
    assert depth_gl.dtype == np.float32 and depth_gl.shape == (64, 64)
    assert depth_ray.dtype == np.float32 and depth_ray.shape == (64, 64)

    geom_ids = _geom_ids(ray, data)
    box_id = objects_model.geom("box").id
    assert (geom_ids == box_id).sum() > 20, "the view should see the box"
    interior = ~_near_boundary(geom_ids)
    assert interior.sum() > 1500

    valid_gl, valid_ray = depth_gl > 0, depth_ray > 0
    np.testing.assert_array_equal(valid_gl[interior], valid_ray[interior])
    both = interior & valid_gl & valid_ray
    diff = np.abs(depth_gl - depth_ray)[both]
    assert diff.max() < AGREEMENT_TOL, f"max |gl - raycast| = {diff.max() * 1e3:.3f} mm"


# --- back-projection -------------------------------------------------------------------------


@pytest.mark.parametrize("backend", ["gl", "raycast"])
@pytest.mark.parametrize("camera_name", [WRIST_CAMERA, "side_view"])
def test_back_projected_points_lie_on_the_box_and_table(box_model, pool, backend, camera_name):
    data = _data_at(box_model)
    camera = pool.get(box_model, camera_name, backend)
    depth = camera.render(data)
    points = camera.points_world(depth, data)
    valid = depth > 0
    assert points.shape == (valid.sum(), 3) and points.dtype == np.float64

    geom_ids = _geom_ids(pool.get(box_model, camera_name, "raycast"), data)
    labels = geom_ids[valid]
    interior = ~_near_boundary(geom_ids)[valid]
    on_box = interior & (labels == box_model.geom("box").id)
    on_table = interior & (labels == box_model.geom("table_top").id)
    assert on_box.sum() > 50 and on_table.sum() > 500

    box_dist = _box_surface_distance(points[on_box])
    assert box_dist.max() < SURFACE_TOL, f"box points off by {box_dist.max() * 1e3:.2f} mm"
    table_z = np.abs(points[on_table, 2])
    assert table_z.max() < SURFACE_TOL, f"table points off by {table_z.max() * 1e3:.2f} mm"
    # Box points cover the top face, not just its rim.
    top = np.abs(_box_local(points[on_box])[:, 2] - BOX_HALF[2]) < SURFACE_TOL
    assert top.sum() > 10

    # Every point around the box, silhouettes included, is on the box or the table.
    near, _ = crop_points(points, [0.25, -0.10, -0.05], [0.65, 0.30, 0.20], return_mask=True)
    off = np.minimum(_box_surface_distance(near), np.abs(near[:, 2]))
    assert off.max() < SURFACE_TOL


# --- intrinsics ------------------------------------------------------------------------------


def test_intrinsics_defaults_and_matrix():
    intr = CameraIntrinsics()
    assert (intr.width, intr.height, intr.fovy_deg) == (64, 64, 58.0)
    assert (intr.min_depth, intr.max_depth) == (0.105, 3.0)
    fy = 32.0 / math.tan(math.radians(29.0))
    np.testing.assert_allclose(intr.matrix, [[fy, 0, 32.0], [0, fy, 32.0], [0, 0, 1]])
    assert intr.fovx_deg == pytest.approx(58.0)

    d435 = REALSENSE_D435_DEPTH
    assert (d435.width, d435.height) == (848, 480)
    assert d435.fx == d435.fy == pytest.approx(240.0 / math.tan(math.radians(29.0)))
    assert (d435.cx, d435.cy) == (424.0, 240.0)
    assert 88.0 < d435.fovx_deg < 90.0


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("width", 0),
        ("width", 64.0),
        ("height", -3),
        ("fovy_deg", 0.0),
        ("fovy_deg", 180.0),
        ("min_depth", 0.0),
        ("max_depth", 0.1),
        ("max_depth", math.inf),
    ],
)
def test_intrinsics_validation_names_the_field(field, value):
    with pytest.raises(ValueError, match=rf"CameraIntrinsics\.{field} must"):
        CameraIntrinsics(**{field: value})


def _project(intr: CameraIntrinsics, position, rotation, point) -> tuple[np.ndarray, float]:
    """Pixel coordinates (u, v) and z-depth of a world point through K (OpenCV axes)."""
    p = rotation.T @ (np.asarray(point) - position)
    p_cv = np.array([p[0], -p[1], -p[2]])  # MuJoCo camera (y up, -z forward) -> OpenCV
    uvw = intr.matrix @ p_cv
    return uvw[:2] / uvw[2], p_cv[2]


@pytest.mark.parametrize(
    ("camera_name", "arm_pose"),
    [(WRIST_CAMERA, "home"), (WRIST_CAMERA, "tilted"), ("side_view", "home")],
)
def test_matrix_matches_mujoco_projection(objects_model, pool, camera_name, arm_pose):
    data = _data_at(objects_model, ARM_POSES[arm_pose])
    camera = pool.get(objects_model, camera_name, "gl")  # MuJoCo's own projection
    depth = camera.render(data)
    position, rotation = camera.pose(data)
    intr = camera.intrinsics
    rays = camera_rays(intr, "z")
    tops = {"box": (BOX_POS, BOX_HALF[2]), "cylinder": (CYLINDER_POS, 0.03)}
    checked = []
    for name, (centre, half_height) in tops.items():
        top_centre = centre + np.array([0.0, 0.0, half_height])
        (u, v), z = _project(intr, position, rotation, top_centre)
        row, col = math.floor(v), math.floor(u)  # pixel centres at integer + 0.5
        if not (1 <= row < intr.height - 1 and 1 <= col < intr.width - 1):
            continue
        checked.append(name)
        # z-depth where that pixel's centre ray meets the top face's plane.
        ray_world = rotation @ rays[row, col]
        expected = (top_centre[2] - position[2]) / ray_world[2]
        hit = position + expected * ray_world
        assert np.linalg.norm(hit - top_centre) < 0.02, "pixel centre should stay on the face"
        assert abs(expected - z) < 0.02
        assert depth[row, col] == pytest.approx(expected, abs=5e-4), name
    assert checked, "no top face is in view"
    if arm_pose == "home":
        assert checked == ["box", "cylinder"]


def test_pose_follows_the_kinematics_and_matches_the_optical_site(objects_model, pool):
    camera = pool.get(objects_model, WRIST_CAMERA, "raycast")
    data = _data_at(objects_model)
    data.qpos[:6] = ARM_POSES["tilted"]
    mujoco.mj_kinematics(objects_model, data)  # no mj_camlight: pose() must refresh it
    position, rotation = camera.pose(data)
    site = objects_model.site(WRIST_CAMERA_SITE).id
    np.testing.assert_allclose(position, data.site_xpos[site], atol=1e-9)
    np.testing.assert_allclose(rotation, data.site_xmat[site].reshape(3, 3), atol=1e-9)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-9)


# --- range and noise -------------------------------------------------------------------------


def test_noise_is_off_by_default(box_model, pool):
    data = _data_at(box_model)
    camera = pool.get(box_model, WRIST_CAMERA, "gl")
    assert not camera.noise.enabled and not DepthNoise().enabled
    first = camera.render(data)
    np.testing.assert_array_equal(first, camera.render(data, rng=np.random.default_rng(0)))
    with DepthCamera(box_model, backend="gl", noise=DepthNoise()) as explicit_off:
        np.testing.assert_array_equal(first, explicit_off.render(data))
    intr = camera.intrinsics
    np.testing.assert_array_equal(DepthNoise().apply(first, intr, np.random.default_rng(1)), first)


def test_noise_is_seeded(box_model):
    data = _data_at(box_model)
    with DepthCamera(box_model, backend="raycast", noise=DepthNoise.realsense_like()) as camera:
        a = camera.render(data, rng=np.random.default_rng(7))
        b = camera.render(data, rng=np.random.default_rng(7))
        c = camera.render(data, rng=np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c)
    assert a.dtype == np.float32


def test_render_without_rng_raises_when_noise_is_on(box_model):
    data = _data_at(box_model)
    with DepthCamera(box_model, backend="raycast", noise=DepthNoise(dropout_prob=0.1)) as cam:
        with pytest.raises(ValueError, match="rng"):
            cam.render(data)


def test_gaussian_noise_matches_its_sigma_on_a_flat_patch(box_model, pool):
    data = _data_at(box_model)
    clean = pool.get(box_model, WRIST_CAMERA, "raycast").render(data)
    noise = DepthNoise(sigma_base=0.001, sigma_quadratic=0.004)
    rng = np.random.default_rng(3)
    table = clean > 0.45  # the box top is at ~0.41 m, the table at ~0.49 m
    residuals = []
    for _ in range(4):
        noisy = noise.apply(clean, CameraIntrinsics(), rng)
        residuals.append((noisy - clean)[table] / noise.sigma(clean[table]))
    standardized = np.concatenate(residuals)
    assert standardized.std() == pytest.approx(1.0, rel=0.2)
    assert abs(standardized.mean()) < 4.0 / math.sqrt(standardized.size)
    sigma_at_table = noise.sigma(0.4875)
    assert sigma_at_table == pytest.approx(0.001 + 0.004 * 0.4875**2)
    assert DepthNoise.realsense_like().sigma(1.0) == pytest.approx(0.0036, rel=0.05)


def test_quantization_and_random_dropout(box_model, pool):
    data = _data_at(box_model)
    clean = pool.get(box_model, WRIST_CAMERA, "raycast").render(data)
    assert np.all(clean > 0)
    intr = CameraIntrinsics()
    step = 0.005
    quantized = DepthNoise(quantization=step).apply(clean, intr, np.random.default_rng(0))
    np.testing.assert_allclose(quantized / step, np.round(quantized / step), atol=1e-4)
    assert np.abs(quantized - clean).max() <= step / 2 + 1e-6

    dropped = DepthNoise(dropout_prob=0.25).apply(clean, intr, np.random.default_rng(0))
    assert np.mean(dropped == 0) == pytest.approx(0.25, abs=0.03)
    kept = dropped > 0
    np.testing.assert_array_equal(dropped[kept], clean[kept])


@pytest.mark.parametrize("backend", ["gl", "raycast"])
def test_out_of_range_pixels_read_zero(box_model, backend):
    data = _data_at(box_model)  # box top ~0.41 m below the camera, table ~0.49 m
    near_only = CameraIntrinsics(max_depth=0.45)
    far_only = CameraIntrinsics(min_depth=0.45)
    with DepthCamera(box_model, intrinsics=near_only, backend=backend) as camera:
        near = camera.render(data)
    with DepthCamera(box_model, intrinsics=far_only, backend=backend) as camera:
        far = camera.render(data)
    assert np.all((near == 0) | ((near > 0.39) & (near <= 0.45)))
    assert np.all((far == 0) | (far >= 0.45))
    assert 50 < np.count_nonzero(near) < 1000
    np.testing.assert_array_equal(near > 0, far == 0)


def _tabletop_with_a_free_camera(floor_tilt_deg: float = 0.0) -> mujoco.MjModel:
    """The table and floor, a box standing on the table (static), a box and a sphere on a
    mocap body (movable) and a camera on another mocap body."""
    spec = load_scene_spec()
    spec.delete(spec.body(ARM_BASE_BODY))
    for key in list(spec.keys):  # they hold the arm's joints
        spec.delete(key)
    tilt = math.radians(floor_tilt_deg) / 2
    spec.geom("floor").quat = [math.cos(tilt), math.sin(tilt), 0.0, 0.0]
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=BOX_HALF, pos=CYLINDER_POS)
    objects = spec.worldbody.add_body(name="objects", mocap=True, pos=BOX_POS)
    objects.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=BOX_HALF)
    objects.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.035, 0, 0], pos=[0.1, 0.17, 0])
    rig = spec.worldbody.add_body(name="rig", mocap=True)
    rig.add_camera(name="probe")
    return spec.compile()


def _image_casting_every_ray(camera: DepthCamera, data) -> np.ndarray:
    backend = camera.active_backend
    backend.use_table_shortcut = False
    try:
        return camera.render(data)
    finally:
        backend.use_table_shortcut = True


def test_raycast_table_shortcut_gives_the_full_cast_image():
    # The raycast backend answers rays that can only land on the table top in numpy
    # (TableShortcut) and casts the rest; the image must be the one casting every ray gives,
    # bit for bit, from anywhere: looking down, past the table's edge, and from below its top.
    model = _tabletop_with_a_free_camera()
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    rig, objects = model.body("rig").mocapid[0], model.body("objects").mocapid[0]
    rng = np.random.default_rng(0)
    with DepthCamera(model, "probe", backend="raycast") as camera:
        shortcut = camera.active_backend.scene_for(model, data).shortcut
        assert shortcut is not None
        assert shortcut.obstacles.size == 3  # the static box and the two movable geoms
        rays_cam = camera_rays(camera.intrinsics, "unit").reshape(-1, 3)
        answered = 0
        for _ in range(60):
            eye = rng.uniform([-0.4, -0.9, -0.2], [1.3, 0.9, 1.0])
            target = rng.uniform([0.2, -0.4, -0.1], [0.8, 0.5, 0.1])
            data.mocap_pos[rig] = eye
            data.mocap_quat[rig] = look_at_quat(eye, target)
            data.mocap_pos[objects] = BOX_POS + rng.uniform(-0.15, 0.15, 3) * [1, 1, 0]
            mujoco.mj_kinematics(model, data)
            image = camera.render(data)
            position, rotation = camera.pose(data)
            solved = shortcut.solve(data, position, rays_cam @ rotation.T, 10.0)
            answered += solved is not None and solved[1].size < 0.8 * len(rays_cam)
            np.testing.assert_array_equal(image, _image_casting_every_ray(camera, data))
        assert answered >= 20  # the shortcut did the work in many of the views


def test_raycast_table_shortcut_stays_off_where_it_would_not_be_exact():
    # A tilted plane can be met anywhere, also above the table: every ray is cast.
    model = _tabletop_with_a_free_camera(floor_tilt_deg=10.0)
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    with DepthCamera(model, "probe", backend="raycast") as camera:
        assert camera.active_backend.scene_for(model, data).shortcut is None
        np.testing.assert_array_equal(camera.render(data), _image_casting_every_ray(camera, data))


def test_raycast_table_shortcut_with_the_arm_in_the_scene(objects_model):
    # With the arm there are more obstacles than the shortcut tests per ray, and the wrist
    # camera sits inside the bounding spheres of its own housing. Per image it keeps only
    # the obstacles in the field of view (the housing is behind the image plane) and tests
    # the rays near a bounding sphere against the oriented boxes. Images must be bit for
    # bit those of casting every ray, from arm poses that show arm links or not.
    model = objects_model
    data = _data_at(model)
    rng = np.random.default_rng(1)
    with (
        DepthCamera(model, WRIST_CAMERA, backend="raycast") as wrist,
        DepthCamera(model, "side_view", backend="raycast") as side,
    ):
        backend = wrist.active_backend
        shortcut = backend.scene_for(model, data).shortcut
        rays_cam = camera_rays(wrist.intrinsics, "unit").reshape(-1, 3)
        assert shortcut is not None and shortcut.obstacles.size > 10
        housing = model.geom("camera_housing_geom").id
        assert housing in shortcut.obstacles
        movable = model.body_weldid[model.geom_bodyid[shortcut.obstacles]] > 0  # the arm's
        answered = answered_with_arm = 0
        for _ in range(30):
            qpos = HOME_QPOS + rng.uniform(-0.6, 0.6, HOME_QPOS.size)
            data = _data_at(model, qpos)
            for camera in (wrist, side):
                np.testing.assert_array_equal(
                    camera.render(data), _image_casting_every_ray(camera, data)
                )
                position, rotation = camera.pose(data)
                in_view = backend.frustum.may_reach(
                    model, data, shortcut.obstacles, position, rotation
                )
                cutoff = backend.frustum.ray_length
                solved = shortcut.solve(data, position, rays_cam @ rotation.T, cutoff, in_view)
                if solved is not None and solved[1].size < 0.5 * len(rays_cam):
                    answered += 1
                    answered_with_arm += bool(in_view[movable].any())
            position, rotation = wrist.pose(data)
            housing_in_view = backend.frustum.may_reach(model, data, [housing], position, rotation)
            assert not housing_in_view[0]
        assert answered >= 20  # most rays were answered in many views
        assert answered_with_arm >= 10  # also with arm links in view


def _tabletop_with_a_housed_camera(far_obstacles: int) -> mujoco.MjModel:
    """The table and floor, a camera on a mocap rig with a box housing whose front face
    passes through the optical centre, and movable spheres far from the table."""
    spec = load_scene_spec()
    spec.delete(spec.body(ARM_BASE_BODY))
    for key in list(spec.keys):
        spec.delete(key)
    rig = spec.worldbody.add_body(name="rig", mocap=True)
    rig.add_camera(name="probe")
    half = [0.045, 0.0125, 0.0125]
    rig.add_geom(name="housing", type=mujoco.mjtGeom.mjGEOM_BOX, size=half, pos=[0, 0, half[2]])
    for i in range(far_obstacles):
        far = spec.worldbody.add_body(mocap=True, pos=[5.0 + i, 5.0, 0.5])
        far.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.02, 0, 0])
    return spec.compile()


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    quat = rng.normal(size=4)
    rotation = np.empty(9)
    mujoco.mju_quat2Mat(rotation, quat / np.linalg.norm(quat))
    return rotation.reshape(3, 3)


def test_pixel_window_holds_every_ray_that_meets_the_box():
    # The table shortcut tests an obstacle's box only against the rays in the pixel window
    # its corners project to (when all of them are in front of the camera). Every pixel ray
    # that the slab test finds meeting the box must lie in that window, for boxes anywhere
    # in or near the field of view, at any orientation, with square and oblong images.
    from liuxing_envs.sim.depth_backends import BOX_CORNERS, PixelGrid, TableShortcut

    rng = np.random.default_rng(2)
    tested = narrow = 0
    for intrinsics in (CameraIntrinsics(), CameraIntrinsics(width=48, height=30, fovy_deg=70.0)):
        grid = PixelGrid(intrinsics)
        rays_cam = camera_rays(intrinsics, "unit").reshape(-1, 3)
        for _ in range(400):
            rotation, frame = _random_rotation(rng), _random_rotation(rng)
            position = rng.uniform(-0.2, 0.2, 3)
            ahead = [rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), -rng.uniform(-0.05, 0.6)]
            centre = position + rotation @ ahead
            box_centre, half = rng.uniform(-0.02, 0.02, 3), rng.uniform(0.002, 0.1, 3)
            rays = rays_cam @ rotation.T
            meets = TableShortcut.meets_box(frame, centre, box_centre, half, position, rays)
            offsets = (box_centre + BOX_CORNERS * half) @ frame.T + (centre - position)
            corners = offsets @ rotation  # in the camera frame
            window = grid.window(corners)
            if window is None:
                assert corners[:, 2].max() >= -1e-3  # only a box not wholly in front has none
                continue
            inside = np.zeros((grid.height, grid.width), dtype=bool)
            inside[window] = True
            assert not (meets & ~inside.ravel()).any()
            tested += bool(meets.any())
            narrow += bool(meets.any() and inside.sum() < 0.5 * inside.size)
    assert tested >= 300 and narrow >= 200  # boxes in view, most windows a small part


def test_a_geom_touching_the_optical_centre_is_never_culled():
    # Rounding puts a housing face through the optical centre either side of the image
    # plane; mj_multiRay then reports every forward ray hitting it at distance 0. With more
    # obstacles than the shortcut takes, the field-of-view test must keep the housing, or
    # the shortcut answers those rays as table.
    model = _tabletop_with_a_housed_camera(far_obstacles=8)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    housing = [model.geom("housing").id]
    with DepthCamera(model, "probe", backend="raycast") as camera:
        frustum = camera.active_backend.frustum
        for _ in range(100):
            eye = rng.uniform([0.0, -0.5, 0.3], [0.8, 0.5, 1.0])
            target = rng.uniform([0.0, -0.4, 0.0], [0.8, 0.4, 0.05])
            data.mocap_pos[0], data.mocap_quat[0] = eye, look_at_quat(eye, target)
            mujoco.mj_kinematics(model, data)
            position, rotation = camera.pose(data)
            assert frustum.may_reach(model, data, housing, position, rotation)[0]
            np.testing.assert_array_equal(
                camera.render(data), _image_casting_every_ray(camera, data)
            )


def test_field_of_view_test_is_conservative_and_its_kernel_agrees_with_numpy(objects_model):
    # may_reach decides which stand-in a view is cast into and which arm geoms the
    # self-filter tests pixel by pixel, so a geom it rules out must hold no return: with its
    # box grown by a margin, no back-projected point within that margin of the box. The
    # compiled kernel and the numpy code must rule out the same geoms.
    model = objects_model
    rng = np.random.default_rng(4)
    margin = 0.003
    geoms = np.arange(model.ngeom)
    with DepthCamera(model, WRIST_CAMERA, backend="raycast") as camera:
        frustum = camera.active_backend.frustum
        assert frustum.compiled  # numba is a dependency
        ruled_out = kept = 0
        for _ in range(60):
            data = _data_at(model, HOME_QPOS + rng.uniform(-0.9, 0.9, HOME_QPOS.size))
            depth = camera.render(data)
            points = camera.points_world(depth, data)
            position, rotation = camera.pose(data)
            answers = {}
            for compiled in (True, False):
                frustum.compiled = compiled
                for grow in (0.0, margin):
                    answers[compiled, grow] = frustum.may_reach(
                        model, data, geoms, position, rotation, grow
                    )
            frustum.compiled = True
            for grow in (0.0, margin):
                np.testing.assert_array_equal(answers[True, grow], answers[False, grow])
            assert (answers[True, 0.0] <= answers[True, margin]).all()  # growing keeps more
            for geom in np.flatnonzero(~answers[True, margin]):
                box = model.geom_aabb[geom]
                local = (points - data.geom_xpos[geom]) @ data.geom_xmat[geom].reshape(3, 3)
                outside = np.abs(local - box[:3]) > box[3:] + margin
                assert outside.any(axis=1).all(), f"geom {geom} ruled out but holds returns"
                ruled_out += 1
            kept += int(answers[True, margin].sum())
        assert ruled_out >= 200 and kept >= 200  # both answers were given, many times


def test_raycast_shortcut_follows_static_geoms_moved_at_run_time():
    # The shortcut decides once which static geoms rise above the table; a model edited
    # afterwards (here a box raised through the table top) must not keep a stale decision.
    spec = load_scene_spec()
    spec.delete(spec.body(ARM_BASE_BODY))
    for key in list(spec.keys):
        spec.delete(key)
    spec.worldbody.add_geom(name="block", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.04] * 3)
    spec.geom("block").pos = [0.4, 0.0, -0.1]  # inside the table, below its top
    rig = spec.worldbody.add_body(name="rig", mocap=True, pos=[0.4, 0.0, 0.6])
    rig.add_camera(name="probe")
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    with DepthCamera(model, "probe", backend="raycast") as camera:
        flat = camera.render(data)
        model.geom("block").pos[2] = 0.04  # now standing on the table top
        mujoco.mj_kinematics(model, data)
        raised = camera.render(data)
        np.testing.assert_array_equal(raised, _image_casting_every_ray(camera, data))
    assert (raised < flat - 0.05).sum() > 50  # the block shows, 8 cm nearer than the table


def test_raycast_renders_a_model_without_materials():
    spec = mujoco.MjSpec()
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.5, 0.5, 0.02])
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.05, 0, 0], pos=[0, 0, 0.07])
    spec.worldbody.add_camera(name="probe", pos=[0, 0, 0.6])
    model = spec.compile()
    assert model.nmat == 0
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    with DepthCamera(model, "probe", backend="raycast") as camera:
        depth = camera.render(data)
    assert depth[32, 32] == pytest.approx(0.6 - 0.12, abs=1e-3)  # near the sphere's top
    assert depth[0, 0] == pytest.approx(0.6 - 0.02, abs=1e-5)  # the box's top


def _tabletop_with_a_mesh(share_body: bool) -> mujoco.MjModel:
    """The table and floor, an octahedron mesh on a mocap body (with a sphere beside it on
    the same body when ``share_body``), a box on another mocap body, and a free camera."""
    spec = load_scene_spec()
    spec.delete(spec.body(ARM_BASE_BODY))
    for key in list(spec.keys):
        spec.delete(key)
    vertices = 0.06 * np.array(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    )
    faces = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    spec.add_mesh(name="octahedron", uservert=vertices.ravel().tolist(), userface=np.ravel(faces))
    solid = spec.worldbody.add_body(name="solid", mocap=True, pos=BOX_POS + np.array([0, 0, 0.05]))
    solid.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname="octahedron")
    if share_body:
        solid.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.03, 0, 0], pos=[0.1, 0, 0])
    other = spec.worldbody.add_body(name="other", mocap=True, pos=CYLINDER_POS)
    other.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=BOX_HALF)
    rig = spec.worldbody.add_body(name="rig", mocap=True)
    rig.add_camera(name="probe")
    return spec.compile()


@pytest.mark.parametrize("share_body", [False, True])
def test_embree_backend_agrees_with_raycast_and_falls_back_where_it_cannot_split(share_body):
    # Meshes alone on their body go to Embree (float32: micrometres apart, the same pixels);
    # a mesh sharing its body with another geom cannot be left out of mj_multiRay, so the
    # whole image is cast as by the ray-cast backend, bit for bit.
    model = _tabletop_with_a_mesh(share_body)
    data = mujoco.MjData(model)
    rig, solid = model.body("rig").mocapid[0], model.body("solid").mocapid[0]
    rng = np.random.default_rng(1)
    seen = 0
    with (
        DepthCamera(model, "probe", backend="raycast") as cast,
        DepthCamera(model, "probe", backend="embree") as embree,
    ):
        assert embree.backend == "embree"
        for _ in range(30):
            target = BOX_POS + rng.uniform(-0.05, 0.05, 3)
            eye = target + rng.uniform([-0.5, -0.5, 0.1], [0.5, 0.5, 0.6])
            data.mocap_pos[rig] = eye
            data.mocap_quat[rig] = look_at_quat(eye, target)
            yaw = rng.uniform(0, np.pi)
            data.mocap_quat[solid] = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
            mujoco.mj_kinematics(model, data)
            expected, image = cast.render(data), embree.render(data)
            if share_body:
                np.testing.assert_array_equal(image, expected)
            else:
                np.testing.assert_array_equal(image > 0, expected > 0)
                np.testing.assert_allclose(image, expected, rtol=0, atol=2e-5)
            seen += not np.array_equal(image, expected)
        assert embree.active_backend.meshes_in_embree or share_body
    assert (seen == 0) if share_body else (seen >= 10)  # the octahedron was in most views


def test_noise_pushing_depth_out_of_range_reads_zero():
    intr = CameraIntrinsics(min_depth=0.2, max_depth=1.0)
    depth = np.full((intr.height, intr.width), 0.999, dtype=np.float32)
    depth[:, :32] = 0.201
    noisy = DepthNoise(sigma_base=0.05).apply(depth, intr, np.random.default_rng(0))
    assert np.all((noisy == 0) | ((noisy >= intr.min_depth) & (noisy <= intr.max_depth)))
    assert 0.3 < np.mean(noisy == 0) < 0.7  # about half falls outside on both sides
    assert np.all(np.isfinite(noisy))


def _surface_labels_and_normals(points, geom_ids, box_id, table_id):
    """Per point: a label for the flat surface it lies on (-1: neither box nor table; 0: the
    table; 1..6: a box face) and that surface's true normal."""
    labels = np.full(len(points), -1)
    normals = np.zeros_like(points)
    on_table = geom_ids == table_id
    labels[on_table] = 0
    normals[on_table] = (0.0, 0.0, 1.0)
    on_box = geom_ids == box_id
    local = _box_local(points[on_box])
    axis = np.argmax(np.abs(local) / BOX_HALF, axis=1)
    sign = np.sign(local[np.arange(len(local)), axis])
    labels[on_box] = 1 + 2 * axis + (sign > 0)
    local_normals = np.zeros_like(local)
    local_normals[np.arange(len(local)), axis] = sign
    normals[on_box] = local_normals @ _box_rotation().T
    return labels, normals


@pytest.mark.parametrize(("camera_name", "threshold"), [("side_view", 50.0), (WRIST_CAMERA, 45.0)])
def test_grazing_dropout_removes_steep_surfaces_only(box_model, pool, camera_name, threshold):
    data = _data_at(box_model)
    camera = pool.get(box_model, camera_name, "raycast")
    clean = camera.render(data)
    valid = clean > 0
    points = camera.points_world(clean, data)
    eye, _ = camera.pose(data)
    box_id, table_id = box_model.geom("box").id, box_model.geom("table_top").id
    labels, normals = _surface_labels_and_normals(
        points, _geom_ids(camera, data)[valid], box_id, table_id
    )
    view = (points - eye) / np.linalg.norm(points - eye, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.abs(np.sum(normals * view, axis=1)), 0.0, 1.0)))

    # Finite-difference normals mix surfaces within a pixel of a face or object boundary.
    label_image = np.full(clean.shape, -2)
    label_image[valid] = labels
    known = (labels >= 0) & ~_near_boundary(label_image)[valid]

    noise = DepthNoise(grazing_dropout_deg=threshold)
    kept = noise.apply(clean, camera.intrinsics, np.random.default_rng(0))[valid] > 0
    steep = known & (angle > threshold + 5.0)
    gentle = known & (angle < threshold - 5.0)
    assert np.all(~kept[steep]), f"{np.sum(kept[steep])} steep pixels survived"
    assert np.all(kept[gentle]), f"{np.sum(~kept[gentle])} gentle pixels dropped"
    if camera_name == WRIST_CAMERA:
        # Looking straight down, the table is seen head-on everywhere and is all kept.
        assert np.all(kept[known & (labels == 0)])
        assert gentle.sum() > 2500
    else:
        assert steep.sum() > 100 and gentle.sum() > 20


def test_noise_validation_names_the_field():
    for field, value in [
        ("sigma_base", -0.1),
        ("sigma_quadratic", math.nan),
        ("quantization", -1e-3),
        ("grazing_dropout_deg", 90.0),
        ("dropout_prob", 1.5),
    ]:
        with pytest.raises(ValueError, match=rf"DepthNoise\.{field} must"):
            DepthNoise(**{field: value})
    assert DepthNoise.realsense_like().enabled


# --- backends and lifetime -------------------------------------------------------------------


def _make_cameras_in_a_forked_child(model, inherited, data, results) -> None:
    import traceback

    outcome = {}
    try:
        for name, attempt in (
            ("gl", lambda: DepthCamera(model, backend="gl")),
            ("inherited", lambda: inherited.render(data)),
        ):
            try:
                attempt()
            except RuntimeError as error:
                outcome[name] = str(error)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            outcome["auto"] = DepthCamera(model).backend
        outcome["warning"] = " ".join(str(w.message) for w in caught)
    except Exception:  # reported at once, rather than as the parent's timeout
        outcome["error"] = traceback.format_exc()
    results.put(outcome)


def test_a_process_forked_after_an_opengl_context_refuses_gl_instead_of_hanging(box_model):
    """A child forked from a process that had made an OpenGL context waited forever for its
    own (an async vector env made after a render): it now refuses gl, naming spawn, and auto
    falls back to ray casting."""
    data = _data_at(box_model)
    inherited = DepthCamera(box_model, backend="gl")  # made before the fork, used after it
    inherited.render(data)
    outcome = outcome_in_forked_child(_make_cameras_in_a_forked_child, box_model, inherited, data)
    assert "error" not in outcome, outcome["error"]
    for attempt in ("gl", "inherited"):
        assert "forked from one that had made an OpenGL context" in outcome[attempt]
        assert "vector_kwargs={'context': 'spawn'}" in outcome[attempt]
    assert outcome["auto"] == "raycast" and "forked from one" in outcome["warning"]
    # The parent itself still renders with OpenGL.
    assert np.isfinite(inherited.render(data)).any()
    inherited.close()


def _report_of(script: str, **run_kwargs) -> dict:
    """What ``script``, run in a fresh interpreter, prints as JSON on its last line."""
    result = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
        **run_kwargs,
    )
    return json.loads(result.stdout.strip().splitlines()[-1])


_FORK_SCRIPT = """
import json
from liuxing_envs import forking
from tests.forked_child import outcome_in_forked_child

def check_in_child(results):
    try:
        forking.check_opengl_not_forked()
        results.put("allowed")
    except RuntimeError as error:
        results.put(str(error))

before = outcome_in_forked_child(check_in_child)
forking.note_opengl_context()
after = outcome_in_forked_child(check_in_child)
print(json.dumps({"before": before, "after": after}))
"""


def test_only_a_child_forked_after_a_context_is_refused_opengl():
    # The hook runs at every fork since the package was imported: a child forked before
    # this process made any context may still make its own. A fresh interpreter, as this
    # one has made contexts already.
    outcome = _report_of(_FORK_SCRIPT, cwd=os.path.dirname(os.path.dirname(__file__)) or ".")
    assert outcome["before"] == "allowed"
    assert "forked from one that had made an OpenGL context" in outcome["after"]


def test_close_is_idempotent_and_final(box_model):
    data = _data_at(box_model)
    for backend in ("gl", "raycast"):
        camera = DepthCamera(box_model, backend=backend)
        camera.render(data)
        camera.close()
        camera.close()
        assert camera.closed
        with pytest.raises(RuntimeError, match="closed"):
            camera.render(data)
    with DepthCamera(box_model, backend="gl") as camera:
        camera.render(data)
    assert camera.closed


def test_unknown_backend_and_camera_are_clear_errors(box_model):
    with pytest.raises(ValueError, match=r"'vulkan'.*'auto', 'gl', 'raycast'"):
        DepthCamera(box_model, backend="vulkan")
    with pytest.raises(ValueError, match=r"'nope'") as excinfo:
        DepthCamera(box_model, camera_name="nope", backend="raycast")
    assert "'wrist_depth'" in str(excinfo.value) and "'overview'" in str(excinfo.value)


def test_other_intrinsics_agree_and_share_the_camera(box_model, pool):
    data = _data_at(box_model)
    intr = CameraIntrinsics(width=96, height=48, fovy_deg=45.0)
    with DepthCamera(box_model, intrinsics=intr, backend="gl") as gl:
        depth_gl = gl.render(data)
    with DepthCamera(box_model, intrinsics=intr, backend="raycast") as ray:
        depth_ray = ray.render(data)
        interior = ~_near_boundary(_geom_ids(ray, data))
    assert depth_gl.shape == (48, 96)
    assert np.abs(depth_gl - depth_ray)[interior].max() < AGREEMENT_TOL

    # The 45-degree cameras rewrote the MuJoCo camera's fovy; the 58-degree ones still agree.
    assert box_model.cam_fovy[box_model.camera(WRIST_CAMERA).id] == 45.0
    depth_58 = pool.get(box_model, WRIST_CAMERA, "gl").render(data)
    depth_58_ray = pool.get(box_model, WRIST_CAMERA, "raycast").render(data)
    interior = ~_near_boundary(_geom_ids(pool.get(box_model, WRIST_CAMERA, "raycast"), data))
    assert np.abs(depth_58 - depth_58_ray)[interior].max() < AGREEMENT_TOL


def test_gl_enlarges_a_small_offscreen_framebuffer():
    model = _build_model(with_round_objects=False)
    model.vis.global_.offwidth, model.vis.global_.offheight = 32, 32
    offsamples = int(model.vis.quality.offsamples)
    with DepthCamera(model, backend="gl") as camera:
        assert camera.render(_data_at(model)).shape == (64, 64)
    assert (model.vis.global_.offwidth, model.vis.global_.offheight) == (64, 64)
    assert model.vis.quality.offsamples == offsamples  # only borrowed while creating


_FALLBACK_SCRIPT = """
import json, warnings
from liuxing_envs.sim.scene import load_scene_model
from liuxing_envs.sim.camera import DepthCamera
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    camera = DepthCamera(load_scene_model())
ours = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)
        and str(w.message).startswith("DepthCamera")]
print(json.dumps({"backend": camera.backend, "warnings": ours}))
"""


def test_auto_never_picks_an_opengl_that_renders_on_the_cpu(box_model):
    # Mesa's llvmpipe (the tests' EGL here) rendered depth slower than ray casting; on a GPU
    # auto keeps OpenGL.
    with DepthCamera(box_model, backend="gl") as gl:
        name, software = gl.active_backend.renderer_name, gl.active_backend.software
    assert name, "the GL renderer's name could be read"
    assert software == any(word in name.lower() for word in ("llvmpipe", "softpipe", "swrast"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a choice, not a fallback: no warning
        auto = DepthCamera(box_model)
    assert auto.backend == ("raycast" if software else "gl")
    auto.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forces a failing X11 GLFW")
def test_auto_backend_falls_back_to_raycast_without_gl():
    # A fresh interpreter whose GL platform (GLFW on an X display that does not exist) cannot
    # make a context: the backend is picked when mujoco is imported, so it cannot be in-process.
    env = {**os.environ, "MUJOCO_GL": "glfw", "DISPLAY": ":31999"}
    env.pop("WAYLAND_DISPLAY", None)
    report = _report_of(_FALLBACK_SCRIPT, env=env)
    assert report["backend"] == "raycast"
    assert len(report["warnings"]) == 1 and "ray-cast" in report["warnings"][0]


# --- point-cloud helpers ---------------------------------------------------------------------


def test_pointcloud_helpers():
    intr = CameraIntrinsics(width=4, height=3, fovy_deg=60.0)
    unit = camera_rays(intr, "unit")
    assert unit.shape == (3, 4, 3) and not unit.flags.writeable
    np.testing.assert_allclose(np.linalg.norm(unit, axis=-1), 1.0)
    z_rays = camera_rays(intr, "z")
    assert np.all(z_rays[..., 2] == -1.0)
    assert z_rays[0, 0, 0] < 0 < z_rays[0, 0, 1]  # top-left pixel: left and up

    depth = np.full((3, 4), 2.0)
    depth[1, 2] = 0.0
    points, mask = depth_to_camera_points(depth, intr, return_mask=True)
    assert points.shape == (11, 3) and mask.sum() == 11 and not mask[1, 2]
    np.testing.assert_allclose(points[:, 2], -2.0)
    with pytest.raises(ValueError, match="expected"):
        depth_to_camera_points(np.ones((4, 3)), intr)

    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = transform_points(np.array([[1.0, 0.0, 0.0]]), [0.0, 0.0, 1.0], rotation)
    np.testing.assert_allclose(moved, [[0.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        transform_points(np.zeros(3), np.zeros(3), np.eye(3))

    kept = crop_points(np.array([[0.0, 0, 0], [1.0, 1, 1], [2.0, 0, 0]]), [0, 0, 0], [1, 1, 1])
    np.testing.assert_array_equal(kept, [[0.0, 0, 0], [1.0, 1, 1]])
    with pytest.raises(ValueError, match="lower <= upper"):
        crop_points(np.zeros((1, 3)), [1, 0, 0], [0, 1, 1])
    with pytest.raises(ValueError, match="lower <= upper"):  # kept nothing, silently
        crop_points(np.zeros((1, 3)), [np.nan, 0, 0], [1, 1, 1])
