"""The compiled depth kernel (``depth_backend="raycast"`` with numba) against casting every ray with
``mj_multiRay``: identical images, bit for bit, on seeded views of ViewPlanning's scenes and
of a scene of every primitive geom type, and identical episodes in the env.

Real MuJoCo scenes, no mocks (``MUJOCO_GL=egl`` from conftest.py).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

pytest.importorskip("numba")

from liuxing_envs.envs.view_planning import ViewPlanningEnv  # noqa: E402
from liuxing_envs.sim.camera import CameraIntrinsics, DepthCamera  # noqa: E402
from liuxing_envs.sim.objects import OBJECT_SETS  # noqa: E402
from liuxing_envs.sim.scene import ARM_BASE_BODY, HOME_QPOS, WRIST_CAMERA, load_scene_spec  # noqa: E402
from liuxing_envs.sim.viewpoints import look_at_quat  # noqa: E402

#: Small and fast env settings (one scale, few coverage samples).
FAST = {"scales": (1.0,), "coverage_samples": 1024}
#: Objects of each set the views are taken of.
OBJECTS = {
    "train": list(OBJECT_SETS["train"])[::3],
    "held_out": list(OBJECT_SETS["held_out"]),
    "procedural": list(OBJECT_SETS["procedural"])[::13],
}


def _cameras(model: mujoco.MjModel, name: str, intrinsics: CameraIntrinsics):
    """The reference (every ray cast by mj_multiRay) and the compiled camera."""
    reference = DepthCamera(model, name, intrinsics, backend="multiray")
    reference.active_backend.use_table_shortcut = False
    return reference, DepthCamera(model, name, intrinsics, backend="raycast")


def _env_views(env: ViewPlanningEnv, rng: np.random.Generator, count: int):
    """Seeded views of the env's scene, alternately at random joint angles around home (many
    show arm links; yields them) and at the views random actions reach (yields None)."""
    env.reset(seed=int(rng.integers(1 << 30)))
    for i in range(count):
        if i % 2 == 0:
            yield HOME_QPOS + rng.uniform(-0.7, 0.7, HOME_QPOS.size)
            continue
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        yield None
        if terminated or truncated:
            env.reset(seed=int(rng.integers(1 << 30)))


def _compare_in_env(set_name: str, size: int, count: int, seed: int) -> tuple[int, int]:
    """(views, views with the arm in the stand-in): every one bit for bit the reference."""
    env = ViewPlanningEnv(depth_backend="multiray", objects=OBJECTS[set_name], **FAST)
    env.action_space.seed(seed)
    intrinsics = CameraIntrinsics(width=size, height=size)
    scene = env.scene
    reference, compiled = _cameras(scene.model, WRIST_CAMERA, intrinsics)
    rng = np.random.default_rng(seed)
    views = with_arm = 0

    def look():
        placed = scene.placed
        stand_ins = scene.stand_ins(placed.name, placed.scale)
        ray_scene = stand_ins.ray_scene(scene.data, placed, reference)
        expected = reference.render(scene.data, scene=ray_scene)
        image = compiled.render(scene.data, scene=ray_scene)
        np.testing.assert_array_equal(image, expected, err_msg=f"{placed.name}, view {views}")
        return ray_scene[0] is stand_ins.model, bool((expected > 0).any())

    try:
        for qpos in _env_views(env, rng, count):
            arm, _ = look() if qpos is None else scene.look_from(qpos, look)
            views += 1
            with_arm += arm
    finally:
        reference.close()
        compiled.close()
        env.close()
    return views, with_arm


@pytest.mark.parametrize("set_name", ["train", "held_out", "procedural"])
def test_compiled_images_equal_casting_every_ray_in_view_planning(set_name):
    # Train, held-out and procedural objects, 64x64 and 8x8 images, views the env's actions
    # reach and random arm poses that show arm links: ~270 views in all.
    seed = {"train": 0, "held_out": 1, "procedural": 2}[set_name]
    views, with_arm = _compare_in_env(set_name, 64, 60, seed)
    small, small_with_arm = _compare_in_env(set_name, 8, 30, seed + 10)
    assert views + small == 90
    assert with_arm + small_with_arm >= 10  # the arm's links were cast too


def _every_primitive_scene() -> mujoco.MjModel:
    """The table and floor, a camera on a mocap rig, and on a mocap body one geom of each
    primitive type, turned, next to a mesh-free box standing on the table."""
    spec = load_scene_spec()
    spec.delete(spec.body(ARM_BASE_BODY))
    for key in list(spec.keys):
        spec.delete(key)
    shapes = spec.worldbody.add_body(name="shapes", mocap=True, pos=[0.45, 0.0, 0.06])
    turn = [math.cos(0.4), math.sin(0.4) * 0.6, math.sin(0.4) * 0.8, 0.0]
    geoms = (
        (mujoco.mjtGeom.mjGEOM_SPHERE, [0.04, 0, 0], [0.0, 0.0, 0.0]),
        (mujoco.mjtGeom.mjGEOM_CAPSULE, [0.02, 0.05, 0], [0.12, 0.0, 0.02]),
        (mujoco.mjtGeom.mjGEOM_CYLINDER, [0.03, 0.04, 0], [-0.12, 0.05, 0.0]),
        (mujoco.mjtGeom.mjGEOM_ELLIPSOID, [0.05, 0.02, 0.03], [0.0, 0.14, 0.0]),
        (mujoco.mjtGeom.mjGEOM_BOX, [0.03, 0.05, 0.02], [0.0, -0.14, 0.01]),
    )
    for gtype, size, pos in geoms:
        shapes.add_geom(type=gtype, size=size, pos=pos, quat=turn)
    spec.worldbody.add_geom(
        type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.02, 0.08], pos=[0.3, -0.25, 0.05]
    )
    rig = spec.worldbody.add_body(name="rig", mocap=True)
    rig.add_camera(name="probe")
    return spec.compile()


def test_compiled_images_equal_casting_every_ray_for_every_primitive_type():
    # Spheres, capsules, cylinders, ellipsoids and boxes turned every way, the table and the
    # floor, from anywhere around them (below the table top too): ~60 views.
    model = _every_primitive_scene()
    data = mujoco.MjData(model)
    shapes, rig = model.body("shapes").mocapid[0], model.body("rig").mocapid[0]
    rng = np.random.default_rng(3)
    shown = 0
    for size in (64, 8):
        reference, compiled = _cameras(model, "probe", CameraIntrinsics(width=size, height=size))
        for _ in range(30 if size == 64 else 10):
            eye = rng.uniform([-0.3, -0.9, -0.3], [1.3, 0.9, 1.0])
            target = rng.uniform([0.3, -0.2, 0.0], [0.6, 0.2, 0.1])
            data.mocap_pos[rig] = eye
            data.mocap_quat[rig] = look_at_quat(eye, target)
            quat = rng.normal(size=4)
            data.mocap_quat[shapes] = quat / np.linalg.norm(quat)
            data.mocap_pos[shapes] = [0.45, 0.0, 0.06] + rng.uniform(-0.1, 0.1, 3)
            mujoco.mj_kinematics(model, data)
            expected = reference.render(data)
            np.testing.assert_array_equal(compiled.render(data), expected)
            shown += bool((expected > 0).any())
        reference.close()
        compiled.close()
    assert shown >= 30


def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of a unit icosphere, flattened a little so that it has flat sides."""
    t = (1 + 5**0.5) / 2
    vertices = [
        [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
        [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1],
    ]  # fmt: skip
    faces = [
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
        [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
        [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ]  # fmt: skip
    vertices = [np.array(v, float) / np.linalg.norm(v) for v in vertices]
    middle: dict[tuple[int, int], int] = {}  # an edge split once is never an edge again

    def mid(a, b):
        key = (min(a, b), max(a, b))
        if key not in middle:
            point = vertices[a] + vertices[b]
            vertices.append(point / np.linalg.norm(point))
            middle[key] = len(vertices) - 1
        return middle[key]

    for _ in range(subdivisions):
        faces = [
            face
            for a, b, c in faces
            for face in ([a, mid(a, b), mid(a, c)], [b, mid(b, c), mid(a, b)],
                         [c, mid(a, c), mid(b, c)], [mid(a, b), mid(b, c), mid(a, c)])
        ]  # fmt: skip
    return np.clip(np.array(vertices), -0.8, 0.8), np.array(faces)


def test_compiled_images_equal_casting_every_ray_from_on_in_and_beside_boxes_and_meshes():
    # Cameras flush against a box or a mesh's bounding box, a little inside or outside it,
    # behind it, and looking along its faces and edges: the views where the kernel's culls
    # (the box cut at the image plane, boxes behind the camera, rays entering a face, a
    # camera inside a bounding sphere) decide most, each image bit for bit mj_multiRay's.
    spec = load_scene_spec()
    spec.delete(spec.body(ARM_BASE_BODY))
    for key in list(spec.keys):
        spec.delete(key)
    vertices, faces = _icosphere(2)
    spec.add_mesh(name="ball", uservert=(vertices * 0.05).ravel(), userface=faces.ravel())
    things = spec.worldbody.add_body(name="things", mocap=True, pos=[0.45, 0.0, 0.1])
    things.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.04, 0.03, 0.02], pos=[0, -0.1, 0])
    things.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname="ball", pos=[0, 0.1, 0])
    rig = spec.worldbody.add_body(name="rig", mocap=True)
    rig.add_camera(name="probe")
    model = spec.compile()
    data = mujoco.MjData(model)
    mocap_things, mocap_rig = model.body("things").mocapid[0], model.body("rig").mocapid[0]
    boxes = [model.geom("table_top").id, model.geom("table_leg_1").id] + [
        g for g in range(model.ngeom) if model.geom_bodyid[g] == model.body("things").id
    ]
    rng = np.random.default_rng(7)
    reference, compiled = _cameras(model, "probe", CameraIntrinsics(width=32, height=32))
    shown = 0
    for view in range(120):
        quat = rng.normal(size=4)
        data.mocap_quat[mocap_things] = quat / np.linalg.norm(quat)
        mujoco.mj_kinematics(model, data)
        geom = boxes[view % len(boxes)]
        centre, half = model.geom_aabb[geom, :3], model.geom_aabb[geom, 3:]
        rotation = data.geom_xmat[geom].reshape(3, 3)
        # A point on a face of the geom's bounding box, moved along the face's normal by up to
        # 2 mm either way, and a direction along that face (tilted a little) or anywhere.
        axis, side = rng.integers(3), rng.choice([-1.0, 1.0])
        local = rng.uniform(-1.0, 1.0, 3) * half
        local[axis] = side * (half[axis] + rng.choice([0.0, 1e-4, -1e-4, 2e-3, -2e-3]))
        normal = np.zeros(3)
        normal[axis] = side
        direction = rng.normal(size=3)
        if view % 3:
            direction -= normal * (direction @ normal)  # along the face
            direction += normal * rng.choice([0.0, 0.02, -0.02, 0.5, -0.5])
        eye = data.geom_xpos[geom] + rotation @ (centre + local)
        direction = rotation @ direction
        data.mocap_pos[mocap_rig] = eye
        data.mocap_quat[mocap_rig] = look_at_quat(eye, eye + direction / np.linalg.norm(direction))
        mujoco.mj_kinematics(model, data)
        expected = reference.render(data)
        np.testing.assert_array_equal(compiled.render(data), expected, err_msg=f"view {view}")
        shown += bool((expected > 0).any())
    reference.close()
    compiled.close()
    assert shown >= 50


def test_an_env_with_the_compiled_backend_runs_the_raycast_episodes():
    # The same seeded episodes give the same observations, rewards and coverage.
    episodes = {}
    for backend in ("multiray", "raycast"):
        env = ViewPlanningEnv(depth_backend=backend, objects=["mug", "l_bracket"], **FAST)
        env.action_space.seed(0)
        record = []
        for seed in range(3):
            obs, info = env.reset(seed=seed)
            record.append((obs, None, info["coverage"]))
            done = False
            while not done:
                obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
                record.append((obs, reward, info["coverage"]))
                done = terminated or truncated
        assert env.camera.backend == backend
        episodes[backend] = record
        env.close()
    assert len(episodes["multiray"]) == len(episodes["raycast"])
    for (obs, reward, coverage), (obs2, reward2, coverage2) in zip(
        episodes["multiray"], episodes["raycast"], strict=True
    ):
        assert obs.keys() == obs2.keys()
        for key in obs:
            np.testing.assert_array_equal(obs2[key], obs[key], err_msg=key)
        assert reward2 == reward and coverage2 == coverage


def test_without_numba_raycast_is_cast_by_mj_multiray_and_the_kernel_names_it(monkeypatch):
    from liuxing_envs import kernels
    from liuxing_envs.sim.depth_backends import CompiledBackend

    monkeypatch.setattr(kernels, "available", lambda: False)
    model = _every_primitive_scene()
    camera = DepthCamera(model, "probe", backend="raycast")
    assert camera.backend == "multiray"
    camera.close()
    camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "probe")
    with pytest.raises(ImportError, match=r"numba.*depth_backend='multiray'"):
        CompiledBackend(model, camera_id, CameraIntrinsics(), (0, 1, 2))


@pytest.mark.parametrize("obs_mode", ["depth", "rgbd"])
def test_instrument_grasp_images_are_the_same_from_the_kernel_and_mj_multiray(obs_mode):
    # The gripper's boxes and the instruments' meshes, seen from the wrist while it moves.
    import gymnasium as gym

    frames, used = {}, {}
    for backend in ("multiray", "raycast"):
        env = gym.make("InstrumentGrasp-v1", obs_mode=obs_mode, depth_backend=backend)
        env.action_space.seed(0)
        images = []
        for episode in range(2):
            observation, _ = env.reset(seed=episode)
            images.append(observation["depth"])
            for _ in range(40):
                observation, _, terminated, truncated, _ = env.step(env.action_space.sample())
                images.append(observation["depth"])
                if terminated or truncated:
                    break
        grasp = env.unwrapped
        used[backend] = grasp.world.camera(grasp.intrinsics, backend).backend
        frames[backend] = np.stack(images)
        env.close()
    assert used == {"multiray": "multiray", "raycast": "raycast"}
    assert frames["raycast"].any()
    np.testing.assert_array_equal(frames["raycast"], frames["multiray"])
