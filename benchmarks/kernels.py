"""The compiled kernels against what they replace, and a view step against MuJoCo's own cost.

Every figure is a ratio measured in one process, alternating the two sides and keeping each
side's fastest of several rounds, so a machine busy with other work slows both alike:

* **reference**: MuJoCo casting one 64x64 depth image of a small scene (a table box and a
  UV-sphere mesh of 960 triangles, 0.13 m across, seen from 0.4 m) with one ``mj_multiRay``
  after one ``mj_kinematics``: the C cost a view step is measured against.
* **view step**: one ``ViewPlanning-v1`` step with its defaults (a view taken: IK, path checks,
  depth, fusion, coverage, observation), the mean over seeded random episodes with their
  resets included (a reset's time is shared among its episode's view steps: the target's
  "episodes with resets"); the median step and the median reset beside it.
* **vector env**: ``gym.make_vec("ViewPlanning-v1", N, workers=K)`` per scene-step, against
  Gymnasium's ``SyncVectorEnv`` of N envs in its same-step autoreset mode (both include the
  resets that their steps make), and its scene-steps/s against the reference's images/s.
* **kernels**: the coverage update, the depth image and the roll-free IK, compiled against
  their numpy or ``mj_multiRay`` references, on inputs recorded from seeded episodes.
* **first make**: seconds from a fresh interpreter to a made ``ViewPlanning-v1`` (warm
  caches), median of three.

Run: ``MUJOCO_GL=egl python -m benchmarks --sections kernels``.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from collections.abc import Callable

import mujoco
import numpy as np

ENV_ID = "ViewPlanning-v1"
RESOLUTION = 64
#: A view step no dearer than casting one image with MuJoCo (the issue's target).
STEP_TO_REFERENCE_TARGET = 1.0
FIRST_MAKE_TARGET_S = 2.0
#: The vector env's runs: (scenes, processes stepping them). 1, 4, 16 and 64 scenes in one
#: process, and 16 on both cores of a 2-core machine, which the batched target is about.
VECTOR_RUNS = ((1, 1), (4, 1), (16, 1), (16, 2), (64, 1))
#: The batched env, 16 scenes on 2 cores: scene-steps/s at least this many times the
#: reference's images/s (the issue's target).
BATCHED_TARGET = 2.5
BATCHED_TARGET_RUN = (16, 2)


def reference_scene_xml(rings: int = 16, segments: int = 32, radius: float = 0.065) -> str:
    """The reference scene: a table top and a UV sphere of ``2 * segments * (rings - 1)``
    triangles on it, and a camera 0.4 m away looking at it."""
    vertices = [(0.0, 0.0, radius)]
    for ring in range(1, rings):
        polar = math.pi * ring / rings
        for segment in range(segments):
            azimuth = 2 * math.pi * segment / segments
            vertices.append(
                (
                    radius * math.sin(polar) * math.cos(azimuth),
                    radius * math.sin(polar) * math.sin(azimuth),
                    radius * math.cos(polar),
                )
            )
    vertices.append((0.0, 0.0, -radius))
    faces = []
    last = len(vertices) - 1
    for segment in range(segments):
        nxt = (segment + 1) % segments
        faces.append((0, 1 + segment, 1 + nxt))
        bottom = 1 + (rings - 2) * segments
        faces.append((last, bottom + nxt, bottom + segment))
    for ring in range(rings - 2):
        for segment in range(segments):
            nxt = (segment + 1) % segments
            a, b = 1 + ring * segments + segment, 1 + ring * segments + nxt
            c, d = a + segments, b + segments
            faces += [(a, c, b), (b, c, d)]
    vertex_text = " ".join(f"{v:.6f}" for vertex in vertices for v in vertex)
    face_text = " ".join(str(i) for face in faces for i in face)
    return f"""<mujoco>
  <asset><mesh name="sphere" vertex="{vertex_text}" face="{face_text}"/></asset>
  <worldbody>
    <geom name="table" type="box" size="1 1 0.02" pos="0.5 0 -0.02"/>
    <body name="object" pos="0.5 0 {radius:.6f}"><geom type="mesh" mesh="sphere"/></body>
    <camera name="view" pos="0.5 -0.283 0.283" xyaxes="1 0 0 0 0.707 0.707" fovy="58"/>
  </worldbody>
</mujoco>"""


def _best(function: Callable[[], object], repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def _alternate(sides: dict[str, Callable[[], object]], rounds: int, repeats: int) -> dict:
    """Each side's fastest call (seconds), the sides alternating round by round."""
    best = {name: math.inf for name in sides}
    for round_ in range(rounds):
        order = list(sides) if round_ % 2 == 0 else list(reversed(sides))
        for name in order:
            best[name] = min(best[name], _best(sides[name], repeats))
    return best


def reference_cast(resolution: int = RESOLUTION):
    """A call that casts one image of the reference scene with MuJoCo (its C cost)."""
    model = mujoco.MjModel.from_xml_string(reference_scene_xml())
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    camera = model.camera("view").id
    fovy = math.radians(float(model.cam_fovy[camera]))
    half = math.tan(fovy / 2)
    pixels = (np.arange(resolution) + 0.5) / resolution * 2 - 1
    u, v = np.meshgrid(pixels * half, -pixels * half)
    directions_camera = np.stack([u, v, -np.ones_like(u)], axis=-1).reshape(-1, 3)
    rotation = data.cam_xmat[camera].reshape(3, 3)
    directions = np.ascontiguousarray(directions_camera @ rotation.T).ravel()
    origin = data.cam_xpos[camera].copy()
    count = resolution * resolution
    geomid = np.zeros(count, dtype=np.int32)
    dist = np.zeros(count)

    def cast() -> np.ndarray:
        mujoco.mj_kinematics(model, data)
        mujoco.mj_multiRay(
            model, data, origin, directions, None, 1, -1, geomid, dist, None, count, 10.0
        )
        return dist

    image = cast()
    assert (image > 0).mean() > 0.9, "the reference camera must see the table and the sphere"
    return cast


def _recorded_steps(env, steps: int, seed: int) -> tuple[list, list]:
    """(step times, reset times) in seconds of seeded random actions."""
    env.action_space.seed(seed)
    env.reset(seed=seed)
    step_times, reset_times = [], []
    for _ in range(steps):
        action = env.action_space.sample()
        start = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(action)
        step_times.append(time.perf_counter() - start)
        if terminated or truncated:
            start = time.perf_counter()
            env.reset()
            reset_times.append(time.perf_counter() - start)
    return step_times, reset_times


def view_step(steps: int, rounds: int) -> dict:
    """A view step's mean time with resets included (and its median, and a reset's),
    against the reference cast, in alternating rounds; each figure the fastest round's."""
    import gymnasium as gym

    import liuxing_envs  # noqa: F401  (registers the ids)

    env = gym.make(ENV_ID)
    cast = reference_cast()
    env.unwrapped.prepare_objects()
    _recorded_steps(env, 40, seed=0)  # the kernels' loading
    with_resets, step_medians, reset_medians, reference = [], [], [], math.inf
    for round_ in range(rounds):
        reference = min(reference, _best(cast, 200))
        times, resets = _recorded_steps(env, steps, seed=round_ + 1)
        with_resets.append((sum(times) + sum(resets)) / len(times))
        step_medians.append(float(np.median(times)))
        reset_medians.append(float(np.median(resets)) if resets else 0.0)
    env.close()
    step = min(with_resets)
    return {
        "reference_ms": reference * 1e3,
        "step_ms": step * 1e3,
        "median_step_ms": min(step_medians) * 1e3,
        "reset_ms": min(reset_medians) * 1e3,
        "step_to_reference": step / reference,
    }


def vector_env(runs: tuple[tuple[int, int], ...], steps: int, rounds: int) -> list[dict]:
    """Per scene-step, the task's own vector env of each (scenes, processes) run against
    SyncVectorEnv (same-step resets), and against the reference cast, in alternating rounds."""
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode

    import liuxing_envs  # noqa: F401  (registers the ids)

    cast = reference_cast()
    casts = max(20, steps)
    rows = []
    for size, workers in runs:
        envs = {
            "batched": gym.make_vec(ENV_ID, size, workers=workers),
            "sync": gym.make_vec(
                ENV_ID,
                size,
                vectorization_mode="sync",
                vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP},
            ),
        }
        rng = np.random.default_rng(0)
        actions = rng.uniform(-1, 1, (steps, size, 3))
        envs["batched"].call("prepare_objects")  # the workers' scenes too
        for env in envs["sync"].envs:
            env.unwrapped.prepare_objects()
        for venv in envs.values():
            venv.reset(seed=0)
            for action in actions[: max(8, steps // 4)]:
                venv.step(action)

        def runner(venv, batches=actions):
            def run():
                for action in batches:
                    venv.step(action)

            return run

        def reference():
            for _ in range(casts):
                cast()

        sides = {name: runner(venv) for name, venv in envs.items()}
        best = _alternate({**sides, "reference": reference}, rounds, 1)
        for venv in envs.values():
            venv.close()
        per_scene = {name: best[name] / (steps * size) * 1e3 for name in envs}
        reference_ms = best["reference"] / casts * 1e3
        rows.append(
            {
                "num_envs": size,
                "workers": workers,
                "batched_ms_per_scene_step": per_scene["batched"],
                "sync_ms_per_scene_step": per_scene["sync"],
                "sync_to_batched": per_scene["sync"] / per_scene["batched"],
                "reference_ms": reference_ms,
                "batched_to_reference": reference_ms / per_scene["batched"],
            }
        )
    return rows


def kernel_ratios(rounds: int) -> list[dict]:
    """Each compiled kernel against its reference on inputs recorded from seeded steps."""
    import gymnasium as gym

    import liuxing_envs  # noqa: F401  (registers the ids)
    from liuxing_envs.perception.coverage import CoverageTracker
    from liuxing_envs.sim.camera import DepthCamera
    from liuxing_envs.sim.scene import WRIST_CAMERA
    from liuxing_envs.sim.viewpoints import look_at

    env = gym.make(ENV_ID).unwrapped
    env.reset(seed=0)
    env.action_space.seed(0)
    clouds, poses, eyes = [], [], []
    for _ in range(24):
        before = env.map.points().shape[0]
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        clouds.append(env.placed.to_object(env.map.points()[before:]))
        poses.append(env.arm.qpos.copy())
        eyes.append(env.camera.pose(env.data)[0])
        if terminated or truncated:
            break
    rows = []

    tracker = env.coverage
    trackers = {
        method: CoverageTracker(tracker.samples, tracker.epsilon, tracker.observable, method=method)
        for method in ("grid", "compiled")
    }

    def scan(coverage):
        def run():
            coverage.reset()
            for points in clouds:
                coverage.update(points)

        return run

    best = _alternate({name: scan(t) for name, t in trackers.items()}, rounds, 3)
    rows.append(_ratio("coverage update", best["grid"], best["compiled"], len(clouds)))

    scene, placed = env.scene, env.placed
    stand_ins = scene.stand_ins(placed.name, placed.scale)
    cameras = {
        name: DepthCamera(scene.model, WRIST_CAMERA, env.intrinsics, backend=name)
        for name in ("multiray", "raycast")
    }

    def render(camera):
        def run():
            for qpos in poses:
                scene.arm.set_qpos(qpos)
                camera.render(scene.data, scene=stand_ins.ray_scene(scene.data, placed, camera))

        return run

    best = _alternate({name: render(c) for name, c in cameras.items()}, rounds, 3)
    rows.append(_ratio("depth image 64x64", best["multiray"], best["raycast"], len(poses)))
    for camera in cameras.values():
        camera.close()

    ik, center = env.arm.ik, env.center

    def solve(compiled: bool):
        def run():
            ik.compiled = compiled
            for eye in eyes:
                env.arm.solve_ik(eye, look_at(eye, center), roll_free=True, check_collisions=False)

        return run

    best = _alternate({"numpy": solve(False), "compiled": solve(True)}, rounds, 3)
    ik.compiled = True
    rows.append(_ratio("roll-free IK (24 rolls)", best["numpy"], best["compiled"], len(eyes)))
    env.close()
    return rows


def _ratio(name: str, reference_s: float, compiled_s: float, calls: int) -> dict:
    return {
        "kernel": name,
        "reference_ms": reference_s / calls * 1e3,
        "compiled_ms": compiled_s / calls * 1e3,
        "speedup": reference_s / compiled_s,
    }


_FIRST_MAKE = (
    "import time; start = time.perf_counter(); import gymnasium as gym, liuxing_envs; "
    f"gym.make({ENV_ID!r}); print(time.perf_counter() - start)"
)


def first_make(repeats: int = 3) -> dict:
    """Seconds from a fresh interpreter to a made env (caches warm: one make first)."""
    subprocess.run([sys.executable, "-c", _FIRST_MAKE], check=True, capture_output=True)
    seconds = []
    for _ in range(repeats):
        done = subprocess.run(
            [sys.executable, "-c", _FIRST_MAKE], check=True, capture_output=True, text=True
        )
        seconds.append(float(done.stdout.split()[-1]))
    return {"median_s": float(np.median(seconds)), "min_s": min(seconds), "max_s": max(seconds)}
