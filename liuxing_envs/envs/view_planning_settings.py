"""ViewPlanning's settings: one frozen part per part of the env, every default in one place.

:data:`V1` (the dataclasses' defaults) is ``ViewPlanning-v1``, the configuration of the
reported results and the shipped policies; :data:`V0` is the deprecated ``ViewPlanning-v0``,
which differs only in its depth backend. The default object set, ``"train"``, holds 13
library objects (box, cylinder, cone, l_bracket, mug, bowl, table, stacked_blocks, bunny,
obelisk, vase, step_pyramid, open_box); results are reported on ``"held_out"`` (torus, chair,
arch, u_bracket, t_pipe), models are chosen on ``"validation"`` (bench, c_channel,
ring_stand, stool); ``"all"`` is the 22 library objects and ``"procedural"`` 64 seeded
composites of the train objects' parts (:mod:`liuxing_envs.sim.objects`).

Kept import-light (no MuJoCo, no open3d): the registry, ``--env-kwargs`` checks and the docs
read it. Checks that need the objects' meshes (an object too flat for the table crop or too
wide for the workspace) are made where the scene is built, in the env.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from liuxing_envs.settings import Part, Settings, knob, part
from liuxing_envs.validation import (
    require_choice,
    require_int,
    require_number,
    require_numbers,
    require_range,
)

ACTION_MODES = ("continuous", "discrete")
#: = liuxing_envs.sim.arm.MOTION_MODES, liuxing_envs.sim.camera.BACKENDS and the keys of
#: liuxing_envs.sim.objects.OBJECT_SETS (a test keeps them equal; those modules import
#: MuJoCo and open3d).
MOTION_MODES = ("kinematic", "dynamic")
DEPTH_BACKENDS = ("auto", "gl", "raycast", "multiray", "embree")
OBJECT_SET_NAMES = ("train", "validation", "held_out", "all", "procedural")
CONTINUOUS = {"action_mode": ("continuous",)}


def _set(part: Part, name: str, value) -> None:
    """Store a checked value in its normal form (tuples of floats) on a frozen part."""
    object.__setattr__(part, name, value)


@dataclasses.dataclass(frozen=True)
class ViewActionSettings(Part):
    """How an action names the next view: a point on a sphere about the estimated centre."""

    action_mode: str = knob(
        "continuous",
        "'continuous': Box(-1, 1, (3,)) mapped onto the ranges below; 'discrete': an index "
        "into the candidate views.",
    )
    azimuth_range_deg: tuple[float, float] = knob(
        (-180.0, 180.0),
        "Azimuths action[0] spans, from +x (away from the arm) towards +y.",
        unit="deg",
        only_with=CONTINUOUS,
    )
    elevation_range_deg: tuple[float, float] = knob(
        (20.0, 90.0), "Elevations action[1] spans.", unit="deg", only_with=CONTINUOUS
    )
    radius_range: tuple[float, float] = knob(
        (0.30, 0.45),
        "Radii action[2] spans; with either mode, the span of the view history's radius.",
        unit="m",
    )
    discrete_azimuths_deg: tuple[float, ...] = knob(
        tuple(range(-180, 180, 45)),
        "Candidate views' azimuths (the discrete actions; the greedy oracle's views).",
        unit="deg",
    )
    discrete_elevations_deg: tuple[float, ...] = knob(
        (25.0, 40.0, 55.0, 70.0),
        "Candidate views' elevations, below 90 (the top view is always a candidate).",
        unit="deg",
    )
    discrete_radius: float = knob(0.38, "Candidate views' radius.", unit="m")

    def check(self) -> None:
        require_choice("action_mode", self.action_mode, ACTION_MODES)
        _set(self, "azimuth_range_deg",
             require_range("azimuth_range_deg", self.azimuth_range_deg, -360, 360))  # fmt: skip
        _set(self, "elevation_range_deg",
             require_range("elevation_range_deg", self.elevation_range_deg, 5.0, 90.0))  # fmt: skip
        _set(self, "radius_range", require_range("radius_range", self.radius_range, 0.15, 0.8))
        require_number("discrete_radius", self.discrete_radius, 0.15, 0.8)
        azimuths = require_numbers(
            "discrete_azimuths_deg", self.discrete_azimuths_deg, -360.0, 360.0
        )
        elevations = require_numbers(
            "discrete_elevations_deg", self.discrete_elevations_deg, 5.0, 90.0
        )
        # A repeated candidate would be two actions for one view; the top view is always one.
        if max(elevations) >= 90.0:
            raise ValueError(
                "discrete_elevations_deg must be below 90 (the top view is always a candidate), "
                f"got {list(elevations)}"
            )
        for name, given, directions in (
            ("discrete_azimuths_deg", azimuths, np.mod(azimuths, 360)),
            ("discrete_elevations_deg", elevations, np.array(elevations)),
        ):
            if np.unique(directions).size < directions.size:
                raise ValueError(
                    f"{name} must name distinct directions (azimuths modulo 360), got {list(given)}"
                )
        _set(self, "discrete_azimuths_deg", azimuths)
        _set(self, "discrete_elevations_deg", elevations)


@dataclasses.dataclass(frozen=True)
class MotionSettings(Part):
    """How the arm goes to a view (IK to the camera pose, collision-checked joint paths)."""

    motion: str = knob(
        "kinematic",
        "'kinematic': the arm is set along the checked path; 'dynamic': its servos follow "
        "it under physics, stopping at a contact or a waypoint not reached in time.",
    )

    def check(self) -> None:
        require_choice("motion", self.motion, MOTION_MODES)


@dataclasses.dataclass(frozen=True)
class SceneSettings(Part):
    """The object on the table: which, how large, where."""

    object_set: str = knob(
        "train",
        "Objects drawn at reset: 'train' (13 library objects), 'validation' (4), "
        "'held_out' (5: the reported results), 'all' (22) or 'procedural' (64).",
    )
    objects: tuple[str, ...] | None = knob(
        None,
        "Library names, procedural_<n> names or mesh files (.obj/.stl/.ply); overrides object_set.",
    )
    scales: tuple[float, ...] = knob(
        (0.8, 0.9, 1.0, 1.1, 1.2), "Uniform scales drawn at reset, one per episode."
    )
    object_region: tuple[tuple[float, float], tuple[float, float]] = knob(
        ((0.45, -0.08), (0.55, 0.08)),
        "((x_min, y_min), (x_max, y_max)) of the object's base centre on the table.",
        unit="m",
    )

    def check(self) -> None:
        require_choice("object_set", self.object_set, OBJECT_SET_NAMES)
        # A str or anything else that is no list is refused where the objects are loaded,
        # with the library's names.
        if isinstance(self.objects, list):
            _set(self, "objects", tuple(self.objects))
        _set(self, "scales", require_numbers("scales", self.scales, 0.05, 5.0))
        try:
            region = np.asarray(self.object_region, dtype=float)
        except (TypeError, ValueError):
            region = np.full(1, np.nan)
        if region.shape != (2, 2) or not (region[0] <= region[1]).all():
            raise ValueError(
                f"object_region must be ((x_min, y_min), (x_max, y_max)) with min <= max, "
                f"got {self.object_region!r}"
            )
        _set(self, "object_region", tuple(tuple(row) for row in region.tolist()))


@dataclasses.dataclass(frozen=True)
class SensorSettings(Part):
    """The wrist depth camera and its image in the observation."""

    resolution: int = knob(64, "Side of the square depth image.", unit="px")
    depth_backend: str = knob(
        "raycast",
        "'raycast' (the same images on every machine; a compiled kernel where numba is "
        "installed), 'multiray' (the same images from MuJoCo's mj_multiRay), 'embree', 'gl' "
        "(OpenGL) or 'auto' (gl where OpenGL works, else raycast).",
    )
    depth_noise: object = knob(
        None,
        "None, 'realsense', a DepthNoise or a mapping of its fields (liuxing_envs.sim.camera).",
    )
    depth_obs_range: float = knob(
        1.0, "Depth mapped to 255 in the uint8 depth observation.", unit="m"
    )
    filter_arm_points: bool = knob(
        True, "Leave the returns on the arm's own links out of the map, coverage and mesh."
    )

    def check(self) -> None:
        require_choice("depth_backend", self.depth_backend, DEPTH_BACKENDS)
        require_int("resolution", self.resolution, 8, 512)
        require_number("depth_obs_range", self.depth_obs_range, 0.2, 3.0)
        require_choice("filter_arm_points", self.filter_arm_points, (False, True))
        if self.depth_noise is not None:
            from liuxing_envs.sim.camera import DepthNoise  # MuJoCo: not at import

            _set(self, "depth_noise", DepthNoise.from_setting(self.depth_noise))


@dataclasses.dataclass(frozen=True)
class FusionSettings(Part):
    """The fused world-frame map, its occupancy summary and how coverage is measured."""

    map_voxel_size: float = knob(0.003, "Voxel size of the fused map.", unit="m")
    map_grid: int = knob(16, "Cells per side of the occupancy observation (map).")
    map_extent: float = knob(
        0.32, "Side of the cube the occupancy observation spans about the centre.", unit="m"
    )
    table_crop_height: float = knob(
        0.0015,
        "Points lower than this above the table are cropped as table before fusion.",
        unit="m",
    )
    observe_free_space: bool = knob(
        False, "Add the cells depth rays crossed (free_space) to the observation."
    )
    coverage_samples: int = knob(8192, "Surface samples of the object that coverage counts.")
    epsilon_fraction: float = knob(
        0.03,
        "A sample is covered by a fused point this close, as a share of the bounding-box "
        "diagonal (above the image's pixel footprint).",
    )

    def check(self) -> None:
        require_number("map_voxel_size", self.map_voxel_size, 5e-4, 0.05)
        require_int("map_grid", self.map_grid, 4, 64)
        require_number("map_extent", self.map_extent, 0.05, 1.0)
        require_number("table_crop_height", self.table_crop_height, 0.0, 0.05)
        require_choice("observe_free_space", self.observe_free_space, (False, True))
        require_int("coverage_samples", self.coverage_samples, 256, 200_000)
        require_number("epsilon_fraction", self.epsilon_fraction, 1e-4, 0.2)


@dataclasses.dataclass(frozen=True)
class TaskSettings(Part):
    """The view budget, the reward terms, success and what the episode ends on."""

    view_budget: int = knob(4, "Views per episode; spending them terminates it.")
    coverage_reward_scale: float = knob(10.0, "Reward per unit of coverage gained.")
    motion_cost: float = knob(
        0.01, "Reward charged per radian of joint-space path travelled.", unit="1/rad"
    )
    refusal_penalty: float = knob(0.1, "Reward charged per refused view.")
    success_coverage: float = knob(0.95, "Coverage at which is_success is true.")
    terminate_on_success: bool = knob(False, "End the episode at success_coverage too.")
    privileged: bool = knob(False, "Add the ground-truth coverage to the observation.")

    def check(self) -> None:
        require_int("view_budget", self.view_budget, 1, 64)
        require_number("coverage_reward_scale", self.coverage_reward_scale, 0.0, 1e4)
        require_number("motion_cost", self.motion_cost, 0.0, 1e3)
        require_number("refusal_penalty", self.refusal_penalty, 0.0, 1e3)
        require_number("success_coverage", self.success_coverage, 0.0, 1.0)
        require_choice("terminate_on_success", self.terminate_on_success, (False, True))
        require_choice("privileged", self.privileged, (False, True))


@dataclasses.dataclass(frozen=True)
class ViewPlanningSettings(Settings):
    """Every setting of :class:`~liuxing_envs.envs.view_planning.ViewPlanningEnv`."""

    extra_keywords = ("render_mode",)

    task: TaskSettings = part(TaskSettings)
    action: ViewActionSettings = part(ViewActionSettings)
    arm: MotionSettings = part(MotionSettings)
    scene: SceneSettings = part(SceneSettings)
    sensor: SensorSettings = part(SensorSettings)
    fusion: FusionSettings = part(FusionSettings)


#: ViewPlanning-v1: the reported results' and the shipped policies' configuration.
V1 = ViewPlanningSettings()
#: ViewPlanning-v0 (deprecated): OpenGL depth where it works, ray casting elsewhere.
V0 = V1.changed(depth_backend="auto")

__all__ = [
    "V0",
    "V1",
    "FusionSettings",
    "MotionSettings",
    "SceneSettings",
    "SensorSettings",
    "TaskSettings",
    "ViewActionSettings",
    "ViewPlanningSettings",
]
