"""ViewPlanning's simulation: the tabletop with every object variant, the camera arm, the
stand-in scenes its hot loops run in, the wrist camera and the coverage set-up per variant.

Everything here follows from the settings, so an env's copies leave it out and build it
again (:meth:`ViewScene.episode_state` / :meth:`ViewScene.restore_episode` carry the little
that belongs to the episode: where the object stands and MuJoCo's state).
"""

from __future__ import annotations

import copy
import itertools
import logging
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import TypeVar

import mujoco
import numpy as np

from liuxing_envs.perception.coverage import CoverageTracker
from liuxing_envs.sim.arm import Arm
from liuxing_envs.sim.camera import RAY_CAST_BACKENDS, CameraIntrinsics, DepthCamera, DepthNoise
from liuxing_envs.sim.object_stage import ObjectStage, PlacedObject
from liuxing_envs.sim.objects import OBSERVABLE_CACHE_SIZE, observable_samples
from liuxing_envs.sim.scene import WRIST_CAMERA, load_scene_spec, reset_to_home
from liuxing_envs.sim.stand_ins import VariantScenes
from liuxing_envs.validation import checked_reset_options, option_angle, option_in, option_xy

logger = logging.getLogger(__name__)
#: A variant whose observable samples took longer than this to prepare is reported (INFO on
#: ``liuxing_envs``): a cold disk cache makes the first env of a process take minutes.
SLOW_PREPARATION_SECONDS = 1.0

T = TypeVar("T")
#: Fused points must lie in this world box (above the table, around the object region).
WORKSPACE_LOWER = (0.15, -0.4, 0.0)
WORKSPACE_UPPER = (0.85, 0.4, 0.5)


@dataclass(frozen=True)
class CoverageSetUp:
    """How coverage is measured for every variant: sample count, tolerance (share of the
    bounding-box diagonal), the table crop height and the view space (radii, elevations in
    degrees) whose sight decides which samples count."""

    samples: int
    epsilon_fraction: float
    crop_height: float
    views: tuple[tuple[float, ...], tuple[float, ...]]


class ViewScene:
    """The compiled scene, its arm, the variants' stand-ins and coverage trackers, and the
    wrist camera (made on first use: an OpenGL context made before a fork hangs the forked
    workers of an async vector env, which builds a throw-away env in the parent first)."""

    def __init__(
        self,
        meshes,
        scales: tuple[float, ...],
        coverage: CoverageSetUp,
        intrinsics: CameraIntrinsics,
        depth_backend: str,
        depth_noise: DepthNoise | None,
    ) -> None:
        self.stage = ObjectStage(meshes, scales)
        self.coverage_set_up = coverage
        # One tracker and one pair of stand-ins per variant, made at the variant's first
        # episode (tens of ms, once per process: envs share the grids and models), not here:
        # making them all up front took most of a first gym.make, and object sets grow.
        self._trackers: dict[tuple[str, float], CoverageTracker] = {}
        self._variant_scenes: dict[tuple[str, float], VariantScenes] = {}
        self._compiled = compiled_scene(self.stage)  # keeps the shared original alive
        self.model = copy.copy(self._compiled)  # this scene's own: placing edits its arrays
        self.data = mujoco.MjData(self.model)
        self.stage.bind(self.model, self.data)
        reset_to_home(self.model, self.data)
        self.arm = Arm(self.model, self.data)
        self._camera: DepthCamera | None = None
        self._camera_settings = (intrinsics, depth_backend, depth_noise)
        self.placed: PlacedObject | None = None
        self._saved: mujoco.MjData | None = None  # look_from's copy of the data

    def tracker(self, name: str, scale: float) -> CoverageTracker:
        """The coverage tracker of one variant (its scan is the episode's)."""
        key = (name, scale)
        if key not in self._trackers:
            set_up = self.coverage_set_up
            shared = _shared_tracker(
                self.stage.meshes[name],
                scale,
                set_up.samples,
                set_up.epsilon_fraction,
                set_up.crop_height,
                set_up.views,
            )
            self._trackers[key] = shared.fresh()
        return self._trackers[key]

    def place(self, name: str, scale: float, position_xy, yaw: float) -> PlacedObject:
        """The arm at home and the variant on the table; the arm's collision checks then run
        in its stand-in."""
        reset_to_home(self.model, self.data)
        self.placed = self.stage.place(name, scale, [*np.asarray(position_xy, float)[:2], 0.0], yaw)
        mujoco.mj_forward(self.model, self.data)
        self.arm.use_collision_scene(*self.stand_ins(name, scale).collision_scene(self.placed))
        return self.placed

    def stand_ins(self, name: str, scale: float) -> VariantScenes:
        """The stand-in scenes of one variant (shared models, this scene's data)."""
        key = (name, scale)
        if key not in self._variant_scenes:
            self._variant_scenes[key] = VariantScenes(self.model, self.stage.meshes[name], scale)
        return self._variant_scenes[key]

    @property
    def camera(self) -> DepthCamera:
        """The wrist depth camera, made on first use (see the class docstring)."""
        if self._camera is None:
            intrinsics, backend, noise = self._camera_settings
            self._camera = DepthCamera(
                self.model, WRIST_CAMERA, intrinsics, backend=backend, noise=noise
            )
        return self._camera

    def render_depth(self, rng: np.random.Generator | None) -> np.ndarray:
        """Depth at the live state; rays are cast in the placed variant's stand-in scene."""
        camera = self.camera
        if camera.backend not in RAY_CAST_BACKENDS:
            return camera.render(self.data, rng=rng)
        scenes = self.stand_ins(self.placed.name, self.placed.scale)
        scene = scenes.ray_scene(self.data, self.placed, camera)
        return camera.render(self.data, rng=rng, scene=scene)

    def look_from(self, qpos: np.ndarray, look: Callable[[], T]) -> T:
        """``look()`` with the arm set at ``qpos``, then the simulation put back exactly:
        the whole data, not just the state, since in a dynamic episode the poses lag the
        state by one integration step, which recomputing them would not give back."""
        if self._saved is None:
            self._saved = mujoco.MjData(self.model)
        mujoco.mj_copyData(self._saved, self.model, self.data)
        self.arm.set_qpos(qpos)
        seen = look()
        mujoco.mj_copyData(self.data, self.model, self._saved)
        return seen

    def close_camera(self) -> None:
        if self._camera is not None:
            self._camera.close()
            self._camera = None  # made again if the env is reset again

    # ------------------------------------------------------------------ copies
    def episode_state(self) -> EpisodeState | None:
        """What a copy of the env needs to put this scene's episode back (a few kB)."""
        if self.placed is None:
            return None
        return EpisodeState.take(self.placed, self.data)

    def restore_episode(self, episode: EpisodeState | None) -> None:
        """Put back an episode taken by :meth:`episode_state` (of a scene of the same
        settings): the object where it stood, the arm's collision scene, MuJoCo's state."""
        if episode is None:
            return
        placed = episode.placed
        self.placed = self.stage.place(placed.name, placed.scale, placed.position, placed.yaw)
        scenes = self.stand_ins(placed.name, placed.scale)
        self.arm.use_collision_scene(*scenes.collision_scene(self.placed))
        episode.restore(self.model, self.data)


#: Derived poses a copy takes over rather than recomputes: after ``mj_step`` (dynamic
#: motion) they lag the state by one integration step, and what the env reads from them
#: (the camera's pose, the stand-ins' sync) must be what the original would read.
_POSE_FIELDS = (
    "xpos", "xquat", "xmat", "xipos", "ximat", "xanchor", "xaxis", "geom_xpos", "geom_xmat",
    "site_xpos", "site_xmat", "cam_xpos", "cam_xmat", "light_xpos", "light_xdir",
)  # fmt: skip
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


@dataclass(frozen=True)
class EpisodeState:
    """The placed object, MuJoCo's integration state, its derived poses and its warning
    counters (which tell a diverged simulation)."""

    placed: PlacedObject
    state: np.ndarray
    poses: dict
    warnings: np.ndarray

    @classmethod
    def take(cls, placed: PlacedObject, data: mujoco.MjData) -> EpisodeState:
        model = data.model
        state = np.empty(mujoco.mj_stateSize(model, _STATE))
        mujoco.mj_getState(model, data, state, _STATE)
        poses = {name: getattr(data, name).copy() for name in _POSE_FIELDS}
        return cls(placed, state, poses, data.warning.number.copy())

    def restore(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        mujoco.mj_setState(model, data, self.state, _STATE)
        mujoco.mj_forward(model, data)
        for name, value in self.poses.items():
            getattr(data, name)[:] = value
        data.warning.number[:] = self.warnings


#: The compiled tabletop of each object set alive in this process, by its variants: an
#: entry goes with the last scene made from it.
COMPILED_SCENES: weakref.WeakValueDictionary = weakref.WeakValueDictionary()


def compiled_scene(stage: ObjectStage) -> mujoco.MjModel:
    """The tabletop with ``stage``'s every variant compiled in, shared by the scenes of a
    process, which each place objects in a copy: copying takes milliseconds where compiling
    builds every mesh's convex hull again (seconds for a large object set)."""
    key = (tuple(stage.meshes.values()), stage.scales)
    model = COMPILED_SCENES.get(key)
    if model is None:
        spec = load_scene_spec()
        stage.add_to_spec(spec)
        model = COMPILED_SCENES[key] = spec.compile()
    return model


@lru_cache(maxsize=OBSERVABLE_CACHE_SIZE)
def _shared_tracker(
    mesh,
    scale: float,
    count: int,
    epsilon_fraction: float,
    crop_height: float,
    observation_views: tuple[tuple[float, ...], tuple[float, ...]],
) -> CoverageTracker:
    """The coverage set-up of one variant, shared by every env of a process (each scans with
    its own :meth:`CoverageTracker.fresh` copy): its lookup grid costs milliseconds and
    about a megabyte, which a vectorised env would otherwise pay per env and variant.

    Samples more than epsilon below ``crop_height`` (above the table) do not count: no
    fused point can come within epsilon of them, so they would cap coverage below 1.
    ``observation_views`` are the radii and elevations (deg) of the env's view space."""
    radii, elevations_deg = observation_views
    truth = observable_samples(mesh, scale, count, radii=radii, elevations_deg=elevations_deg)
    epsilon = epsilon_fraction * scale * mesh.diagonal
    above_crop = truth.points[:, 2] >= crop_height - epsilon
    return CoverageTracker(truth.points, epsilon, observable=truth.observable & above_crop)


class Placements:
    """Where the objects may stand: every variant's footprint radius, and the checks that
    keep each whole object inside the workspace crop (points outside it are dropped, which
    would cap coverage below what the views saw)."""

    def __init__(self, meshes, scene, table_crop_height: float) -> None:
        self.object_names = tuple(mesh.name for mesh in meshes)
        self.scales = scales = tuple(float(s) for s in scene.scales)
        self.region = region = np.asarray(scene.object_region, dtype=float)
        for mesh in meshes:
            height = min(scales) * float(mesh.extents[2])
            if height <= table_crop_height:
                raise ValueError(
                    f"objects: {mesh.name!r} stands {height * 1000:.2f} mm tall at scale "
                    f"{min(scales)}, no taller than table_crop_height "
                    f"({table_crop_height * 1000:.2f} mm): every point of it would be cropped "
                    "as table, so no view could cover it. Stand it on an edge (turn it in its "
                    "file) or lower table_crop_height."
                )
        self.footprints = {
            (mesh.name, scale): scale * float(np.hypot(*mesh.vertices[:, :2].T).max())
            for mesh in meshes
            for scale in scales
        }
        widest = max(self.footprints, key=self.footprints.get)
        largest = self.footprints[widest]
        low, high = self.placeable(largest)
        if (low > high).any():
            raise ValueError(
                f"{widest[0]!r} at scale {widest[1]} reaches {largest:.3f} m from its centre, "
                f"too wide to stand anywhere inside the workspace "
                f"{WORKSPACE_LOWER[:2]}-{WORKSPACE_UPPER[:2]}: lower scales or drop the object"
            )
        if not ((region[0] >= low).all() and (region[1] <= high).all()):
            raise ValueError(
                f"object_region must lie within x in [{low[0]:.3f}, {high[0]:.3f}] and y in "
                f"[{low[1]:.3f}, {high[1]:.3f}] m, so that every object and scale (footprint "
                f"radius up to {largest:.3f} m) stays inside the "
                f"workspace {WORKSPACE_LOWER[:2]}-{WORKSPACE_UPPER[:2]}; got "
                f"{tuple(map(tuple, region.tolist()))!r}"
            )

    def checked_options(self, options) -> dict:
        """``reset()``'s options, refused by name when malformed or, for ``position``, when
        an object the reset may draw would not fit there."""
        options = checked_reset_options(
            options,
            {
                "object": option_in(self.object_names),
                "scale": option_in(self.scales),
                "position": option_xy,
                "yaw": option_angle,
            },
        )
        if "position" in options:
            self.check_position(
                options["position"],
                self.object_names if "object" not in options else (options["object"],),
                self.scales if "scale" not in options else (options["scale"],),
            )
        return options

    def draw(self, rng: np.random.Generator, options: dict) -> tuple[str, float, object, float]:
        """An episode's object, scale, position (x, y) and yaw: drawn, or fixed by options.
        Each draw is made whether or not an option fixes it, so an option leaves the other
        draws as they were."""
        name = options.get("object", self.object_names[rng.integers(len(self.object_names))])
        scale = float(options.get("scale", self.scales[rng.integers(len(self.scales))]))
        position_xy = options.get("position", rng.uniform(self.region[0], self.region[1]))
        yaw = float(options.get("yaw", rng.uniform(0.0, 2 * np.pi)))
        return name, scale, position_xy, yaw

    @staticmethod
    def placeable(footprint: float) -> tuple[np.ndarray, np.ndarray]:
        """The (x, y) box where an object of this footprint radius lies inside the crop."""
        return np.array(WORKSPACE_LOWER[:2]) + footprint, np.array(WORKSPACE_UPPER[:2]) - footprint

    def check_position(self, position_xy: np.ndarray, names, scales) -> None:
        """Refuses a reset ``position`` that puts any of these variants partly outside the
        workspace: every one the reset may draw must fit, so that whether a position is
        refused does not depend on the draw."""
        for drawn_name in names:
            for drawn_scale in scales:
                low, high = self.placeable(self.footprints[(drawn_name, drawn_scale)])
                if not ((position_xy >= low).all() and (position_xy <= high).all()):
                    raise ValueError(
                        f"reset option position {np.round(position_xy, 4).tolist()} puts "
                        f"{drawn_name} at scale {drawn_scale} partly outside the workspace: x "
                        f"must lie in [{low[0]:.3f}, {high[0]:.3f}] and y in "
                        f"[{low[1]:.3f}, {high[1]:.3f}] m (without the object and scale "
                        "options, every object and scale the reset may draw must fit)"
                    )


def check_observable(meshes, scales: tuple[float, ...], coverage: CoverageSetUp) -> None:
    """Refuses a variant too large for the view space around it. Its observable samples are
    ray-cast here, up front (and cached): resets stay cheap, and worker processes forked
    from this one never reach the open3d calls that wait forever after a fork
    (liuxing_envs.forking). Each variant that took a while (not yet in the disk cache) is
    logged with how many are done."""
    radii, elevations_deg = coverage.views
    variants = list(itertools.product(meshes, scales))
    for done, (mesh, scale) in enumerate(variants, 1):
        started = time.perf_counter()
        try:
            observable_samples(
                mesh, scale, coverage.samples, radii=radii, elevations_deg=elevations_deg
            )
        except ValueError as error:
            raise ValueError(
                f"objects: {mesh.name!r} at scale {scale}: {error}; lower scales, keep "
                "the views farther out (radius_range, or discrete_radius with discrete "
                "actions) or drop the object"
            ) from None
        seconds = time.perf_counter() - started
        if seconds > SLOW_PREPARATION_SECONDS:
            logger.info(
                "ray-cast what the views can see of %r at scale %g in %.1f s (%d of %d object "
                "variants; kept in the disk cache, so once per machine)",
                mesh.name,
                scale,
                seconds,
                done,
                len(variants),
            )
