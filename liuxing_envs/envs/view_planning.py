"""ViewPlanning-v0: next-best-view shape recording ("留形") with a wrist depth camera."""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import mujoco
import numpy as np
from gymnasium import spaces

from liuxing_envs.envs.base import LiuxingEnv
from liuxing_envs.forking import check_opengl_not_forked
from liuxing_envs.opengl import new_renderer, require_opengl
from liuxing_envs.perception.coverage import CoverageTracker
from liuxing_envs.perception.free_space import FreeSpaceGrid
from liuxing_envs.perception.fusion import VoxelMap
from liuxing_envs.perception.pointcloud import crop_points
from liuxing_envs.perception.reconstruction import Reconstruction, reconstruct
from liuxing_envs.sim.arm import MOTION_MODES, Arm
from liuxing_envs.sim.camera import (
    BACKENDS,
    RAY_CAST_BACKENDS,
    CameraIntrinsics,
    DepthCamera,
    DepthNoise,
)
from liuxing_envs.sim.markers import add_frustum, add_points
from liuxing_envs.sim.object_lists import load_objects
from liuxing_envs.sim.object_stage import ObjectStage
from liuxing_envs.sim.objects import (
    OBJECT_SETS,
    OBSERVABLE_CACHE_SIZE,
    observable_samples,
    surface_samples,
)
from liuxing_envs.sim.scene import (
    OVERVIEW_CAMERA,
    WRIST_CAMERA,
    load_scene_spec,
    reset_to_home,
)
from liuxing_envs.sim.stand_ins import VariantScenes
from liuxing_envs.sim.viewpoints import look_at, sphere_point
from liuxing_envs.validation import (
    as_action,
    as_index,
    checked_reset_options,
    is_number,
    option_angle,
    option_in,
    option_xy,
    refuse_if_closed,
    require_choice,
    require_int,
    require_number,
    require_numbers,
    require_range,
    step_context,
)

ACTION_MODES = ("continuous", "discrete")
OBJECT_SET_NAMES = tuple(OBJECT_SETS)

DEFAULT_VIEW_BUDGET = 4
DEFAULT_OBJECT_SET = "train"
DEFAULT_SCALES = (0.8, 0.9, 1.0, 1.1, 1.2)
#: Region of the table (x, y) in which the object's base centre is placed, metres.
DEFAULT_OBJECT_REGION = ((0.45, -0.08), (0.55, 0.08))
DEFAULT_RESOLUTION = 64
DEFAULT_AZIMUTH_RANGE_DEG = (-180.0, 180.0)
DEFAULT_ELEVATION_RANGE_DEG = (20.0, 90.0)
DEFAULT_RADIUS_RANGE = (0.30, 0.45)
#: Coverage counts the samples some view of the env's view space sees: with continuous
#: actions, rings at this many elevations across ``elevation_range_deg``, at both ends of
#: ``radius_range``, around the object's middle (see observable_samples in
#: liuxing_envs.sim.objects); with discrete ones, rings at the candidates' elevations.
OBSERVATION_ELEVATION_RINGS = 5
#: The discrete action set: every azimuth at every elevation, at one radius, plus the top view.
DEFAULT_DISCRETE_AZIMUTHS_DEG = tuple(range(-180, 180, 45))
#: 8 azimuths x 4 elevations + the top view = 33 candidates (the size of RL-NBV's action set);
#: the four-view and uniform baselines' views are among them.
DEFAULT_DISCRETE_ELEVATIONS_DEG = (25.0, 40.0, 55.0, 70.0)
DEFAULT_DISCRETE_RADIUS = 0.38
DEFAULT_COVERAGE_SAMPLES = 8192
#: Coverage tolerance as a share of the bounding-box diagonal (3%: 4.5-7.5 mm at scale 1). It
#: must exceed the depth image's pixel footprint (about 5 mm at 64x64 and the working
#: distance), or coverage measures the sampling density instead of what was seen: at 1% even a
#: greedy oracle stays below 30%. Published dense-cloud set-ups use 0.7-1%; raise the
#: resolution to match them.
DEFAULT_EPSILON_FRACTION = 0.03
#: Returns this close to one of the arm's own geoms are the arm (with ``filter_arm_points``):
#: exact returns lie on its surface, GL's tessellation puts them up to 0.34 mm off it.
ARM_FILTER_MARGIN = 0.003  # m
#: F-score threshold of the reconstruction, as a share of the bounding-box diagonal.
DEFAULT_TAU_FRACTION = 0.01
DEFAULT_SUCCESS_COVERAGE = 0.95
DEFAULT_COVERAGE_REWARD_SCALE = 10.0
DEFAULT_MOTION_COST = 0.01  # reward per radian of joint-space path
DEFAULT_REFUSAL_PENALTY = 0.1
DEFAULT_MAP_VOXEL_SIZE = 0.003  # m
DEFAULT_MAP_GRID = 16  # cells per side of the occupancy summary
DEFAULT_MAP_EXTENT = 0.32  # m, side of the cube summarised around the estimated centre
DEFAULT_DEPTH_OBS_RANGE = 1.0  # m mapped to uint8 255 in the depth observation
DEFAULT_TABLE_CROP_HEIGHT = 0.0015  # m; fused points must be this far above the table top
#: Fused points must lie in this world box (above the table, around the object region).
WORKSPACE_LOWER = (0.15, -0.4, 0.0)
WORKSPACE_UPPER = (0.85, 0.4, 0.5)
#: Random IK restarts per requested view (after the current and home seeds). Unreachable
#: views cost every restart, so fewer than the Arm's default; roll-free IK rarely needs many.
VIEW_IK_RESTARTS = 4
#: Ground-truth surface samples for reconstruction metrics (about 4 * area / τ² are needed).
METRIC_SAMPLES = 100_000
VIEW_HISTORY_FEATURES = 5
RENDER_SIZE = (480, 640)
RENDER_MAX_POINTS = 3000


class ViewPlanningEnv(LiuxingEnv):
    """Next-best-view planning: choose where the wrist depth camera looks next.

    A 6-DoF arm (UR5e kinematics) with a wrist depth camera stands at a table with one object
    on it. Each step the agent picks a viewpoint on a sphere around the object's estimated
    centre; the arm moves there (inverse kinematics, joint limits, collision-checked paths),
    the camera renders depth, the points are fused in the world frame, and the reward is the
    gain in surface coverage of the object. At the end, :meth:`reconstruct` turns the fused
    cloud into a mesh (open3d) scored against the ground truth.

    **Episode.** ``reset`` draws an object (from ``object_set`` or ``objects``), a scale from
    ``scales``, a position in ``object_region`` and a yaw in [0, 2π); the arm starts at home
    and the first depth image is taken from there (the start view looks straight down at the
    object region). The view sphere's centre is estimated from that first cloud (the centre
    of its bounding box at half its height), not from ground truth. Each step uses one view of
    the budget, and the episode terminates when the budget is spent: the remaining budget is
    in the observation, so no value lies beyond the last view and learners must not bootstrap
    from it. Through ``gym.make``, whose registered TimeLimit is the default budget of 4,
    pass ``max_episode_steps`` equal to a larger ``view_budget``: the TimeLimit would
    otherwise truncate the episode at 4, as Gymnasium's time limits are set apart from an
    env's kwargs (at the budget's last step it also reports truncated, beside terminated). It
    terminates early (success) only if ``terminate_on_success`` and coverage reaches
    ``success_coverage``.
    ``reset(options=...)`` may fix any of ``object`` (one of :attr:`object_names`), ``scale``
    (one of ``scales``), ``position`` ((x, y) in m; the whole object must stay inside the
    workspace crop, as ``object_region`` must for every object: without ``object`` and
    ``scale``, every one the reset may draw, so a refusal does not depend on the seed) and
    ``yaw`` (rad). A refused reset changes nothing: the seed and the episode stay as they
    were.

    **Action.** ``action_mode="continuous"``: ``Box(-1, 1, (3,))`` mapped linearly to

    ====  ==========  =========================================  ======
    idx   quantity    range (defaults)                           unit
    ====  ==========  =========================================  ======
    0     azimuth     ``azimuth_range_deg`` (-180, 180)           deg
    1     elevation   ``elevation_range_deg`` (20, 90)            deg
    2     radius      ``radius_range`` (0.30, 0.45)               m
    ====  ==========  =========================================  ======

    Azimuth is measured from +x (away from the arm) towards +y about the estimated centre;
    azimuth 180° is the side facing the arm. Values outside [-1, 1] are clipped; NaN or inf
    raise ``ValueError``. ``action_mode="discrete"``: ``Discrete(K)`` indexes
    :attr:`candidate_views`: every azimuth in ``discrete_azimuths_deg`` at every elevation in
    ``discrete_elevations_deg`` at ``discrete_radius``, then the top view (K = 33 by default).

    **Reaching a view.** The camera must look at the centre from the chosen point (roll is
    free). IK is solved for that pose; the arm takes the straight joint path if it is free,
    else a path through the home pose. A view whose IK fails or whose paths both collide is
    *refused*: the arm stays, no image is taken, the view still uses one step of the budget,
    and ``refusal_penalty`` is charged. With ``motion="dynamic"`` the servos follow the plan
    under physics and stop at the first contact or at a waypoint not reached in time; a
    view stopped short that way is refused too (penalty charged, -1 in the history), but the
    arm stays where it stopped and the image is taken from there.

    **Observation** (``Dict``; usable by SB3's ``MultiInputPolicy`` as is):

    ``depth`` (1, H, W) uint8
        Latest depth image; 255 = ``depth_obs_range`` m (~3.9 mm per unit at 1 m),
        0 = no return. Channel-first, so SB3 treats it as an image (NatureCNN). It shows
        whatever the camera sees, the arm's own links included.
    ``map`` (G³,) float32
        1 where the fused map holds a point, in a cube of ``map_extent`` m around the
        estimated centre; with ``filter_arm_points`` (default) the returns on the arm's own
        links (within ``ARM_FILTER_MARGIN``, 3 mm) are left out of the map, the coverage and
        the reconstruction, as a robot's self-filter does; ``reshape(G, G, G)`` gives it
        indexed [x, y, z] (G = ``map_grid``). Flat, so SB3 does not mistake it for an image.
    ``view_history`` (``view_budget`` * 5,) float32
        Per used view (as requested): cos azimuth, sin azimuth, elevation / 90°, radius
        normalised to [0, 1] over ``radius_range`` (widened to take in ``discrete_radius`` in
        discrete mode; 0 when only one radius is possible), +1 reached / -1 refused; zeros
        for views not yet used.
    ``camera_pose`` (9,) float32
        Camera position relative to the estimated centre (m), then its optical axis and its
        image-up axis (unit vectors, world frame).
    ``budget`` (1,) float32
        Share of the view budget left.
    ``free_space`` (G³,) float32
        Only with ``observe_free_space=True``: 1 where a depth ray has crossed the cell on
        its way to a surface and ``map`` is 0, on ``map``'s cube and indexing. With ``map``
        it tells seen-empty from unseen cells (OctoMap's free / occupied / unknown), which
        ``map`` alone cannot. Every 2nd pixel with a return carves, up to half a cell short
        of its surface; rays to the table carve too, so the cell holding the table top
        (cropped from ``map``) can read free.
    ``coverage`` (1,) float32
        Only with ``privileged=True``: the current coverage (ground truth).

    **Reward.** ``r = coverage_reward_scale * Δcoverage - motion_cost * path_length -
    refusal_penalty * refused`` with Δcoverage the step's coverage gain and path_length the
    joint-space distance travelled (rad). ``info`` holds each term (``reward_coverage``,
    ``reward_motion``, ``reward_refusal``; they sum to the reward) and ``coverage``,
    ``coverage_gain``, ``views_used``, ``reachable`` (IK and a collision-free path were
    found), ``refused`` (the view was not reached; only dynamic motion can be ``reachable``
    and refused), ``path_length``, ``is_success`` (coverage ≥ ``success_coverage``),
    ``viewpoint`` (azimuth, elevation in degrees, radius in m), ``object``, ``scale`` and
    ``sim_unstable``. ``reset()``'s ``info`` has the same keys but the three reward terms and
    ``viewpoint``; its ``coverage`` is the start view's, which no reward pays (an episode's
    coverage rewards sum to ``coverage_reward_scale`` × (final − start coverage)).

    **Simulator faults.** With ``motion="dynamic"``, physics that diverges (NaN, inf or huge
    accelerations, which MuJoCo answers by resetting its data) stops the motion; the episode
    is truncated (terminated instead, when that view spent the budget) with
    ``info["sim_unstable"] = True`` and the next ``reset()`` starts clean.

    **Coverage** (the NBV metric of PC-NBV, SCONE, RL-NBV): ``coverage_samples`` points
    sampled uniformly on the object's surface, restricted to those some view of this env's
    view space can see (nothing resting on the table, nothing occluded from every such
    view): with continuous actions, views around the object's middle at five elevations
    across ``elevation_range_deg`` (24 azimuths each; one view at 90°) and both ends of
    ``radius_range``; with discrete ones, views at ``discrete_radius`` at each of
    ``discrete_elevations_deg`` (24 azimuths, for any yaw of the object) and the top view. A
    sample is covered when a fused point lies within ε = ``epsilon_fraction`` × the object's
    bounding-box diagonal. Which samples some view can see is ray-cast once per object,
    scale and view space when the env is made, and kept on disk for the next process
    (:mod:`liuxing_envs.disk_cache`; ``LIUXING_ENVS_CACHE=off`` turns that off).

    **Arguments** (all keyword): ``view_budget``, ``action_mode``, ``motion``
    ({"kinematic", "dynamic"}), ``object_set`` ({"train", "validation", "held_out", "all",
    "procedural"}; validation families are for choosing a model, held-out ones for reporting
    it; "all" is the library's 22 families; "procedural" is 64 seeded random composites of the
    train families' parts, a larger training set, see ``liuxing_envs.sim.objects``),
    ``objects`` (list of library names, ``procedural_<n>`` shape names (n < 1,000,000) or mesh
    files .obj/.stl/.ply, scaled to ``USER_MESH_SIZE`` and named after the file's stem or,
    where names clash, by as much of the path as tells them apart; each must stand taller
    than ``table_crop_height`` at the smallest scale; overrides ``object_set``), ``scales``,
    ``object_region``, ``resolution`` (square depth image side),
    ``depth_backend`` ({"auto", "gl", "raycast", "embree"}; embree is the fastest, see
    ``liuxing_envs.sim.camera``; in a process forked from one that had made an OpenGL
    context, as async vector envs made after a render are, gl is refused and auto falls back
    to raycast: pass ``vector_kwargs={"context": "spawn"}``), ``depth_noise`` (a
    ``DepthNoise``, None, ``"realsense"`` for ``DepthNoise.realsense_like()``, or a mapping
    of its fields, as YAML gives it),
    the action ranges above, ``coverage_samples``, ``epsilon_fraction``, ``success_coverage``,
    ``terminate_on_success``, ``coverage_reward_scale``, ``motion_cost``, ``refusal_penalty``,
    ``map_voxel_size``, ``map_grid``, ``map_extent``, ``depth_obs_range``,
    ``table_crop_height`` (m above the table below which points are cropped before fusion
    and coverage: the table itself; ground-truth samples more than ε below it do not count,
    as no point could cover them), ``observe_free_space``, ``filter_arm_points``,
    ``privileged``,
    ``render_mode`` ("rgb_array": the scene from the overview camera with the fused points
    and the camera's frustum).

    **Defaults** (the module's ``DEFAULT_*`` constants): ``view_budget=4``,
    ``action_mode='continuous'``, ``motion='kinematic'``, ``object_set='train'``,
    ``objects=None``, ``scales=(0.8, 0.9, 1.0, 1.1, 1.2)``, ``object_region=((0.45, -0.08),
    (0.55, 0.08))``, ``resolution=64``, ``depth_backend='auto'``, ``depth_noise=None``,
    ``azimuth_range_deg=(-180.0, 180.0)``, ``elevation_range_deg=(20.0, 90.0)``,
    ``radius_range=(0.3, 0.45)``, ``discrete_azimuths_deg=(-180, -135, -90, -45, 0, 45, 90,
    135)``, ``discrete_elevations_deg=(25.0, 40.0, 55.0, 70.0)``, ``discrete_radius=0.38``,
    ``coverage_samples=8192``, ``epsilon_fraction=0.03``, ``success_coverage=0.95``,
    ``terminate_on_success=False``, ``coverage_reward_scale=10.0``, ``motion_cost=0.01``,
    ``refusal_penalty=0.1``, ``map_voxel_size=0.003``, ``map_grid=16``, ``map_extent=0.32``,
    ``depth_obs_range=1.0``, ``table_crop_height=0.0015``, ``observe_free_space=False``,
    ``filter_arm_points=True``, ``privileged=False``, ``render_mode=None``.

    **Version history.** v0: initial release. Fixed within v0 (2026-11-21): the placed
    object takes part in the arm's collision checks (before, paths could pass through it;
    only refusals and detours change), and ``info["sim_unstable"]``. Added within v0
    (2026-11-22, off by default, so existing observations are unchanged):
    ``observe_free_space``; ``object_set="validation"`` (four new families: bench, c_channel,
    ring_stand, stool; ``"train"`` and ``"held_out"`` are unchanged, ``"all"`` now has them).
    Fixed within v0 (2026-11-22; default kinematic episodes are unchanged): a dynamic view
    stopped short takes its image where the arm stopped (before, none, so the observed pose
    and depth disagreed) and ``reachable`` means a path was found; ``preview_view`` restores
    the dynamic state exactly; the history's radius feature stays in [0, 1] with a
    ``discrete_radius`` outside ``radius_range``; the env can be reset after ``close()``.
    Added within v0 (2026-11-23): ``depth_backend="embree"``. Added within v0 (2026-11-25):
    ``object_set="procedural"`` and ``procedural_<n>`` object names (the other sets are
    unchanged). Fixed within v0 (2026-11-26; observations and rewards unchanged): spending
    the budget terminates the episode (before, it was truncated, so PPO and SAC added the
    extrapolated value of a state with no views left, about 0.5 on the shipped PPO's critic
    against a mean last-view reward of 0.08, to every episode's last reward; the policies
    measured before are unchanged, their training was not). The fused map, coverage and
    reconstruction leave out the returns on the arm's own links (``filter_arm_points``,
    default on; before, a view showing the upper arm fused it as object: up to half the
    points of a random episode's cloud, its Chamfer distance 34 mm against 3 mm without
    them). Fixed within v0 (2026-11-26; coverage, its reward and ``is_success`` change): the
    observable samples are judged from the env's own view space around the object's middle
    (before, from a 0.4 m hemisphere around its base with a ring at 10° elevation, outside
    the views the env can take: about 10-29% of the samples of a table, stool, chair, bench,
    C-channel or T-pipe, at some or all scales, counted although only such a view saw them,
    which capped their coverage below the success level for every agent, and 4-7% of a
    bowl's, 4% of an arch's; of a vase's, it counted 10-13% that no view of the env sees and
    left out 14-24% that they see). Changed within v0 (2026-11-27; default episodes unchanged):
    ``view_to_action`` refuses a view outside the action's ranges, where it clipped it
    silently (an azimuth beyond a narrowed range went to the range's upper end);
    ``clip=True`` clips, to the angularly nearer end of a narrowed azimuth range (the scripted
    baselines under narrowed ranges may take other views than before; under the default
    ranges they are unchanged). OpenGL is refused in a process forked from one that had made
    a context, where it hung (``"auto"`` falls back to ray casting). A ``reconstruct()``
    record pickles, so a vector env's ``call("reconstruct")`` no longer kills its workers.
    ``copy.deepcopy(env)`` (2026-11-27) shares the per-process caches a second env would share
    (ground truth, stand-in scenes' models, coverage grids): +93 MiB and 0.23 s a copy of an
    env with ray-cast depth after a step, against +306 MiB and 0.55 s before and +74 MiB and
    0.22 s for a new env; with OpenGL depth the copy's first image adds its own context.
    ``reconstruct()`` in a worker forked after open3d was imported (an async vector env's
    default) raises, naming spawn, where it waited forever (2026-11-27,
    :mod:`liuxing_envs.forking`).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        *,
        view_budget: int = DEFAULT_VIEW_BUDGET,
        action_mode: str = "continuous",
        motion: str = "kinematic",
        object_set: str = DEFAULT_OBJECT_SET,
        objects: Sequence[str] | None = None,
        scales: Sequence[float] = DEFAULT_SCALES,
        object_region=DEFAULT_OBJECT_REGION,
        resolution: int = DEFAULT_RESOLUTION,
        depth_backend: str = "auto",
        depth_noise: DepthNoise | None = None,
        azimuth_range_deg: Sequence[float] = DEFAULT_AZIMUTH_RANGE_DEG,
        elevation_range_deg: Sequence[float] = DEFAULT_ELEVATION_RANGE_DEG,
        radius_range: Sequence[float] = DEFAULT_RADIUS_RANGE,
        discrete_azimuths_deg: Sequence[float] = DEFAULT_DISCRETE_AZIMUTHS_DEG,
        discrete_elevations_deg: Sequence[float] = DEFAULT_DISCRETE_ELEVATIONS_DEG,
        discrete_radius: float = DEFAULT_DISCRETE_RADIUS,
        coverage_samples: int = DEFAULT_COVERAGE_SAMPLES,
        epsilon_fraction: float = DEFAULT_EPSILON_FRACTION,
        success_coverage: float = DEFAULT_SUCCESS_COVERAGE,
        terminate_on_success: bool = False,
        coverage_reward_scale: float = DEFAULT_COVERAGE_REWARD_SCALE,
        motion_cost: float = DEFAULT_MOTION_COST,
        refusal_penalty: float = DEFAULT_REFUSAL_PENALTY,
        map_voxel_size: float = DEFAULT_MAP_VOXEL_SIZE,
        map_grid: int = DEFAULT_MAP_GRID,
        map_extent: float = DEFAULT_MAP_EXTENT,
        depth_obs_range: float = DEFAULT_DEPTH_OBS_RANGE,
        table_crop_height: float = DEFAULT_TABLE_CROP_HEIGHT,
        observe_free_space: bool = False,
        filter_arm_points: bool = True,
        privileged: bool = False,
        render_mode: str | None = None,
    ) -> None:
        require_int("view_budget", view_budget, 1, 64)
        require_choice("action_mode", action_mode, ACTION_MODES)
        require_choice("motion", motion, MOTION_MODES)
        require_choice("object_set", object_set, OBJECT_SET_NAMES)
        require_choice("depth_backend", depth_backend, BACKENDS)
        require_choice("render_mode", render_mode, (None, *self.metadata["render_modes"]))
        # Without OpenGL these would fail at the first image with an AttributeError.
        if depth_backend == "gl":
            require_opengl(
                "depth_backend", depth_backend, "'auto' (ray-cast where OpenGL is missing)"
            )
        if render_mode is not None:
            require_opengl("render_mode", render_mode, "None")
        require_int("resolution", resolution, 8, 512)
        require_int("coverage_samples", coverage_samples, 256, 200_000)
        require_int("map_grid", map_grid, 4, 64)
        self.azimuth_range = np.deg2rad(
            require_range("azimuth_range_deg", azimuth_range_deg, -360, 360)
        )
        elevation_range_deg = require_range("elevation_range_deg", elevation_range_deg, 5.0, 90.0)
        self.elevation_range = np.deg2rad(elevation_range_deg)
        self.radius_range = np.asarray(require_range("radius_range", radius_range, 0.15, 0.8))
        for name, value, low, high in (
            ("epsilon_fraction", epsilon_fraction, 1e-4, 0.2),
            ("success_coverage", success_coverage, 0.0, 1.0),
            ("coverage_reward_scale", coverage_reward_scale, 0.0, 1e4),
            ("motion_cost", motion_cost, 0.0, 1e3),
            ("refusal_penalty", refusal_penalty, 0.0, 1e3),
            ("map_voxel_size", map_voxel_size, 5e-4, 0.05),
            ("map_extent", map_extent, 0.05, 1.0),
            ("depth_obs_range", depth_obs_range, 0.2, 3.0),
            ("table_crop_height", table_crop_height, 0.0, 0.05),
            ("discrete_radius", discrete_radius, 0.15, 0.8),
        ):
            require_number(name, value, low, high)
        require_choice("terminate_on_success", terminate_on_success, (False, True))
        require_choice("observe_free_space", observe_free_space, (False, True))
        require_choice("filter_arm_points", filter_arm_points, (False, True))
        require_choice("privileged", privileged, (False, True))
        scales = require_numbers("scales", scales, 0.05, 5.0)
        discrete_azimuths_deg = require_numbers(
            "discrete_azimuths_deg", discrete_azimuths_deg, -360.0, 360.0
        )
        discrete_elevations_deg = require_numbers(
            "discrete_elevations_deg", discrete_elevations_deg, 5.0, 90.0
        )
        # A repeated candidate would be two actions for one view; the top view is always one.
        if max(discrete_elevations_deg) >= 90.0:
            raise ValueError(
                "discrete_elevations_deg must be below 90 (the top view is always a candidate), "
                f"got {list(discrete_elevations_deg)}"
            )
        for name, given, directions in (
            ("discrete_azimuths_deg", discrete_azimuths_deg, np.mod(discrete_azimuths_deg, 360)),
            ("discrete_elevations_deg", discrete_elevations_deg, np.array(discrete_elevations_deg)),
        ):
            if np.unique(directions).size < directions.size:
                raise ValueError(
                    f"{name} must name distinct directions (azimuths modulo 360), got {list(given)}"
                )
        # The views whose sight decides which samples coverage counts: the action's own.
        if action_mode == "continuous":
            self._observation_views = (
                tuple(float(radius) for radius in self.radius_range),
                tuple(
                    float(elevation)
                    for elevation in np.linspace(*elevation_range_deg, OBSERVATION_ELEVATION_RINGS)
                ),
            )
        else:  # the candidates' elevations (and the top view) at every azimuth: any yaw
            elevations = (*(float(elevation) for elevation in discrete_elevations_deg), 90.0)
            self._observation_views = ((float(discrete_radius),), elevations)
        try:
            region = np.asarray(object_region, dtype=float)
        except (TypeError, ValueError):
            region = np.full(1, np.nan)
        if region.shape != (2, 2) or not (region[0] <= region[1]).all():
            raise ValueError(
                f"object_region must be ((x_min, y_min), (x_max, y_max)) with min <= max, "
                f"got {object_region!r}"
            )
        depth_noise = DepthNoise.from_setting(depth_noise)

        self.view_budget = view_budget
        self.action_mode = action_mode
        self.motion = motion
        self.object_region = region
        self.coverage_samples = coverage_samples
        self.epsilon_fraction = float(epsilon_fraction)
        self.table_crop_height = float(table_crop_height)
        self.success_coverage = float(success_coverage)
        self.terminate_on_success = bool(terminate_on_success)
        self.coverage_reward_scale = float(coverage_reward_scale)
        self.motion_cost = float(motion_cost)
        self.refusal_penalty = float(refusal_penalty)
        self.map_grid = map_grid
        self.map_extent = float(map_extent)
        self.depth_obs_range = float(depth_obs_range)
        self.privileged = bool(privileged)
        self.filter_arm_points = bool(filter_arm_points)
        self.render_mode = render_mode

        meshes = load_objects(object_set, objects)
        self.object_names = tuple(mesh.name for mesh in meshes)
        self.scales = tuple(float(s) for s in scales)
        for mesh in meshes:
            height = min(self.scales) * float(mesh.extents[2])
            if height <= table_crop_height:
                raise ValueError(
                    f"objects: {mesh.name!r} stands {height * 1000:.2f} mm tall at scale "
                    f"{min(self.scales)}, no taller than table_crop_height "
                    f"({table_crop_height * 1000:.2f} mm): every point of it would be cropped "
                    "as table, so no view could cover it. Stand it on an edge (turn it in its "
                    "file) or lower table_crop_height."
                )
        self._stage = ObjectStage(meshes, self.scales)
        # Placements keep the whole object inside the workspace crop: points outside it are
        # dropped, which would cap coverage below what the views saw.
        self._footprints = {
            (mesh.name, scale): scale * float(np.hypot(*mesh.vertices[:, :2].T).max())
            for mesh in meshes
            for scale in self.scales
        }
        widest = max(self._footprints, key=self._footprints.get)
        largest = self._footprints[widest]
        low, high = self._placeable(largest)
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
                f"workspace {WORKSPACE_LOWER[:2]}-{WORKSPACE_UPPER[:2]}; got {object_region!r}"
            )
        # Ground truth of every variant up front: resets stay cheap, and worker processes
        # forked from this one never reach the open3d calls that wait forever after a fork
        # (liuxing_envs.forking); reconstruct() does, and is refused there.
        self._ground_truth = {}
        radii, elevations_deg = self._observation_views
        for mesh in meshes:
            for scale in self.scales:
                try:
                    truth = observable_samples(
                        mesh, scale, coverage_samples, radii=radii, elevations_deg=elevations_deg
                    )
                except ValueError as error:  # too large for the views around it
                    raise ValueError(
                        f"objects: {mesh.name!r} at scale {scale}: {error}; lower scales, keep "
                        "the views farther out (radius_range, or discrete_radius with discrete "
                        "actions) or drop the object"
                    ) from None
                self._ground_truth[(mesh.name, scale)] = truth
        # One tracker per variant, in the object's frame, reset per episode: its lookup grid
        # costs milliseconds to build, a reset microseconds. All are made here, next to the
        # ground truth they index (~3 ms each, once per process: envs share the grids), so
        # no reset pays for one.
        self._trackers: dict[tuple[str, float], CoverageTracker] = {}
        for name, scale in self._ground_truth:
            self._tracker(name, scale)
        spec = load_scene_spec()
        self._stage.add_to_spec(spec)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self._stage.bind(self.model, self.data)
        reset_to_home(self.model, self.data)
        self.arm = Arm(self.model, self.data)
        self.intrinsics = CameraIntrinsics(width=resolution, height=resolution)
        self._depth_backend = depth_backend
        self._depth_noise = depth_noise
        self._camera: DepthCamera | None = None
        # Stand-ins of the scene with one variant each (see VariantScenes): ~3 ms apiece.
        self._variant_scenes = {
            key: VariantScenes(self.model, self._stage.meshes[key[0]], key[1])
            for key in self._ground_truth
        }
        self._noise_enabled = depth_noise is not None and depth_noise.enabled
        lower = np.array(WORKSPACE_LOWER, dtype=float)
        lower[2] = self.table_crop_height
        self._crop = (lower, np.array(WORKSPACE_UPPER, dtype=float))
        self.map = VoxelMap(map_voxel_size, *self._crop)
        self.free_space = FreeSpaceGrid(map_grid) if observe_free_space else None
        self._hits = np.zeros((0, 3))  # world points of the latest image, uncropped

        self.candidate_views = _candidate_views(
            discrete_azimuths_deg, discrete_elevations_deg, discrete_radius
        )
        if action_mode == "continuous":
            self.action_space = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)
        else:
            self.action_space = spaces.Discrete(len(self.candidate_views))
        # The history's radius feature spans every radius this env can request, so it stays
        # in [0, 1] when discrete_radius lies outside radius_range (the default is inside).
        radii = [*self.radius_range] + ([discrete_radius] if action_mode == "discrete" else [])
        self._history_radii = (float(min(radii)), float(max(radii)))
        obs_spaces = {
            "depth": spaces.Box(0, 255, (1, resolution, resolution), dtype=np.uint8),
            "map": spaces.Box(0.0, 1.0, (map_grid**3,), dtype=np.float32),
            "view_history": spaces.Box(
                -1.0, 1.0, (view_budget * VIEW_HISTORY_FEATURES,), dtype=np.float32
            ),
            "camera_pose": spaces.Box(-2.0, 2.0, (9,), dtype=np.float32),
            "budget": spaces.Box(0.0, 1.0, (1,), dtype=np.float32),
        }
        if self.free_space is not None:
            obs_spaces["free_space"] = spaces.Box(0.0, 1.0, (map_grid**3,), dtype=np.float32)
        if self.privileged:
            obs_spaces["coverage"] = spaces.Box(0.0, 1.0, (1,), dtype=np.float32)
        self.observation_space = spaces.Dict(obs_spaces)

        self._renderer: mujoco.Renderer | None = None
        self._preview_saved: mujoco.MjData | None = None  # preview_view's copy of the data
        self._reset_seed: int | None = None
        self._episode_ready = False
        self.placed = None
        self.coverage: CoverageTracker | None = None
        self.center = np.zeros(3)
        self.views_used = 0
        self._history = np.zeros((view_budget, VIEW_HISTORY_FEATURES), dtype=np.float32)
        self._depth = np.zeros((resolution, resolution), dtype=np.float32)
        self._camera_locations: list[np.ndarray] = []

    # ------------------------------------------------------------------ Gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.closed = False  # reopened: renderers are made again when needed
        options = checked_reset_options(
            options,
            {
                "object": option_in(self.object_names),
                "scale": option_in(self.scales),
                "position": option_xy,
                "yaw": option_angle,
            },
        )
        if "position" in options:  # refused before the seed and the episode change
            self._check_position(options["position"], options.get("object"), options.get("scale"))
        super().reset(seed=seed)
        self._reset_seed = seed
        rng = self.np_random
        name = options.get("object", self.object_names[rng.integers(len(self.object_names))])
        scale = float(options.get("scale", self.scales[rng.integers(len(self.scales))]))
        position_xy = options.get(
            "position", rng.uniform(self.object_region[0], self.object_region[1])
        )
        yaw = float(options.get("yaw", rng.uniform(0.0, 2 * np.pi)))

        reset_to_home(self.model, self.data)
        self.placed = self._stage.place(
            name, scale, [*np.asarray(position_xy, float)[:2], 0.0], yaw
        )
        mujoco.mj_forward(self.model, self.data)
        scenes = self._variant_scenes[(name, scale)]
        self.arm.use_collision_scene(*scenes.collision_scene(self.placed))

        self.coverage = self._tracker(name, scale)
        self.coverage.reset()
        self.map.reset()
        self.views_used = 0
        self._history[:] = 0.0
        self._camera_locations = []

        points = self._capture()
        self.center = self._estimate_center(points)
        if self.free_space is not None:
            self.free_space.reset(self.center, self.map_extent)
        self._carve_free_space()
        self.coverage.update(self.placed.to_object(points))
        self._episode_ready = True
        info = self._info(0.0, {}, planned=True, refused=False, path=0.0)
        return self._observation(), info

    def step(self, action):
        refuse_if_closed(self)
        with step_context(self, self.views_used + 1, self._reset_seed):
            return self._step(action)

    def _step(self, action):
        if not self._episode_ready:
            raise RuntimeError("call reset() before step(), and again after an episode ends")
        azimuth, elevation, radius = self._view_from_action(action)
        plan = self._plan_view(sphere_point(self.center, azimuth, elevation, radius))
        gain, path_length, reached, unstable = 0.0, 0.0, False, False
        if plan is not None:
            motion = self.arm.follow(plan, self.motion)
            path_length = motion.path_length
            reached = motion.reached
            unstable = motion.unstable
            # A dynamic motion can stop short of the view (see the class docstring); the
            # camera then looks from where the arm stopped, so depth and pose still agree.
            if not unstable:
                gain = self.coverage.update(self.placed.to_object(self._capture()))
                self._carve_free_space()
        refused = not reached
        self._history[self.views_used] = [
            math.cos(azimuth),
            math.sin(azimuth),
            elevation / (np.pi / 2),
            (radius - self._history_radii[0])
            / max(self._history_radii[1] - self._history_radii[0], 1e-9),
            -1.0 if refused else 1.0,
        ]
        self.views_used += 1

        terms = {
            "reward_coverage": self.coverage_reward_scale * gain,
            "reward_motion": -self.motion_cost * path_length,
            "reward_refusal": -self.refusal_penalty * float(refused),
        }
        reward = float(sum(terms.values()))
        info = self._info(
            gain,
            terms,
            planned=plan is not None,
            refused=refused,
            path=path_length,
            unstable=unstable,
        )
        info["viewpoint"] = (math.degrees(azimuth), math.degrees(elevation), radius)
        # The budget is part of the task (the observation counts it down), so spending it
        # ends the episode as a terminal state: truncation would have learners bootstrap
        # from views that can never follow.
        terminated = self.views_used >= self.view_budget or (
            self.terminate_on_success and info["is_success"]
        )
        # A diverged simulation (dynamic motion only) was reset by MuJoCo: the episode's
        # state is gone, so it ends here; reset() starts a clean one.
        truncated = unstable and not terminated
        if terminated or truncated:
            self._episode_ready = False
        return self._observation(), reward, terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        check_opengl_not_forked()  # a renderer made before a fork hangs in the child
        if self._renderer is None:
            self._renderer = new_renderer(self.model, *RENDER_SIZE)
        self._renderer.update_scene(self.data, camera=OVERVIEW_CAMERA)
        scene = self._renderer.scene
        add_points(scene, self.map.points(), RENDER_MAX_POINTS)
        position, rotation = self.camera.pose(self.data)
        add_frustum(scene, position, rotation, self.intrinsics, length=0.25)
        return self._renderer.render().copy()

    def __deepcopy__(self, memo: dict) -> ViewPlanningEnv:
        """A copy sharing what a second env made in this process would share with this one:
        the ground truth and the stand-in scenes' models, cached per process, and the coverage
        trackers' lookup grids. Copying them cost four times a new env's memory (+300 MiB)."""
        for truth in self._ground_truth.values():
            memo.setdefault(id(truth), truth)
        clone = type(self).__new__(type(self))
        memo[id(self)] = clone
        # The stand-ins first, so that the arm's reference to one meets their copies.
        copy.deepcopy(self._variant_scenes, memo)
        clone.__dict__.update(copy.deepcopy(self.__getstate__(), memo))
        return clone

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_renderer"] = None  # a GL context does not pickle; render() makes a new one
        state["_preview_saved"] = None  # scratch, made again on the next preview
        return state

    @property
    def camera(self) -> DepthCamera:
        """The wrist depth camera. Its renderer is made on first use, not in ``__init__``:
        Gymnasium's async vector env builds a throw-away env in the parent and then forks,
        and an OpenGL context made before a fork hangs the forked workers."""
        if self._camera is None:
            self._camera = DepthCamera(
                self.model,
                WRIST_CAMERA,
                self.intrinsics,
                backend=self._depth_backend,
                noise=self._depth_noise,
            )
        return self._camera

    def close(self) -> None:
        super().close()
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._camera is not None:
            self._camera.close()
            self._camera = None  # the camera property makes a new one if the env is reset again

    # ------------------------------------------------------------------ reconstruction
    def reconstruct(
        self,
        save_dir: str | Path | None = None,
        *,
        tau_fraction: float = DEFAULT_TAU_FRACTION,
        **kwargs,
    ) -> tuple[Reconstruction, dict]:
        """The "留形" record of the episode so far: the fused cloud turned into a mesh with
        open3d (see :func:`liuxing_envs.perception.reconstruction.reconstruct`; ``kwargs`` go
        there), and its metrics (Chamfer distance, precision, completeness, F-score) against
        the ground-truth surface samples with τ = ``tau_fraction`` × the object's
        bounding-box diagonal. The samples cover the whole surface, the face resting on the
        table and what no view can see included (as in the reconstruction literature), so
        completeness stays below the observable share of the surface that coverage counts.
        Saves .pcd/.ply files to ``save_dir`` when given. Heavy (Poisson meshing, about a
        second): call it at the end of an episode, not per step."""
        if self.placed is None:
            raise RuntimeError("call reset() first: there is nothing to reconstruct")
        require_number("tau_fraction", tau_fraction, 1e-4, 1.0)
        if "camera_locations" in kwargs:
            raise TypeError(
                "reconstruct() takes the camera locations from the episode's views; call "
                "liuxing_envs.perception.reconstruct(env.unwrapped.map.points(), "
                "camera_locations=...) to give others"
            )
        record = reconstruct(
            self.map.points(), camera_locations=np.array(self._camera_locations), **kwargs
        )
        diagonal = self.placed.scale * self._stage.meshes[self.placed.name].diagonal
        # Dense ground truth: precision is only meaningful with samples much closer than τ.
        surface, _ = surface_samples(self._stage.meshes[self.placed.name], METRIC_SAMPLES, 0)
        gt_world = self.placed.to_world(self.placed.scale * surface)
        metrics = record.metrics(gt_world, tau_fraction * diagonal)
        if save_dir is not None:
            record.save(save_dir)
        return record, metrics

    def preview_view(self, azimuth: float, elevation: float, radius: float) -> dict:
        """PRIVILEGED (uses ground truth): what taking this view (azimuth and elevation in rad,
        radius in m, about the estimated centre) now would earn, without taking it. Any view
        on the sphere is scored, whether or not the continuous action's ranges can request
        it. The arm is put there kinematically, a depth image is rendered (noise from
        a fixed seed) and scored against the ground-truth samples, and the simulation state is
        restored exactly (velocities and servo targets too, so a ``motion="dynamic"`` episode
        goes on as if no preview had happened). ``reward`` charges the plan's joint-space
        length; a dynamic step charges the path it actually travels, so the two can differ
        there. For oracles and analysis, never for a policy's observations."""
        if not self._episode_ready:
            raise RuntimeError("call reset() before preview_view()")
        view = (azimuth, elevation, radius)
        if not all(is_number(value) and math.isfinite(value) for value in view) or radius <= 0:
            raise ValueError(
                "preview_view needs a finite azimuth and elevation (rad) and a radius > 0 (m), "
                f"got {view!r}"
            )
        plan = self._plan_view(sphere_point(self.center, azimuth, elevation, radius))
        if plan is None:
            return {
                "reachable": False,
                "gain": 0.0,
                "path_length": 0.0,
                "reward": -self.refusal_penalty,
            }
        # The whole data, not just the state: in a dynamic episode the poses lag the state by
        # one integration step, which recomputing them (mj_forward) would not give back.
        if self._preview_saved is None:
            self._preview_saved = mujoco.MjData(self.model)
        mujoco.mj_copyData(self._preview_saved, self.model, self.data)
        self.arm.set_qpos(plan.waypoints[-1])
        points = self._preview_points()
        mujoco.mj_copyData(self.data, self.model, self._preview_saved)
        gain = self.coverage.preview(self.placed.to_object(points))
        reward = self.coverage_reward_scale * gain - self.motion_cost * plan.length
        return {"reachable": True, "gain": gain, "path_length": plan.length, "reward": reward}

    # ------------------------------------------------------------------ internals
    def _plan_view(self, eye: np.ndarray):
        """The arm's path to the camera at ``eye`` looking at the centre (any roll), or None
        when no IK solution or no collision-free path reaches it."""
        ik = self.arm.solve_ik(
            eye, look_at(eye, self.center), roll_free=True, restarts=VIEW_IK_RESTARTS
        )
        return self.arm.plan_path(ik.qpos) if ik.success else None

    def _preview_points(self) -> np.ndarray:
        """The cropped world points of a depth image at the live state, not fused; noise, if
        any, from a generator of its own, so the episode's noise stream is left untouched."""
        rng = np.random.default_rng(0) if self._noise_enabled else None
        return crop_points(self._world_points(self._render_depth(rng)), *self._crop)

    def _check_position(self, position_xy: np.ndarray, name: str | None, scale: float | None):
        """Refuses a reset ``position`` that puts an object partly outside the workspace. Every
        object and scale the reset may draw must fit there, so that whether a position is
        refused does not depend on the draw."""
        for drawn_name in self.object_names if name is None else (name,):
            for drawn_scale in self.scales if scale is None else (scale,):
                low, high = self._placeable(self._footprints[(drawn_name, drawn_scale)])
                if not ((position_xy >= low).all() and (position_xy <= high).all()):
                    raise ValueError(
                        f"reset option position {np.round(position_xy, 4).tolist()} puts "
                        f"{drawn_name} at scale {drawn_scale} partly outside the workspace: x "
                        f"must lie in [{low[0]:.3f}, {high[0]:.3f}] and y in "
                        f"[{low[1]:.3f}, {high[1]:.3f}] m (without the object and scale "
                        "options, every object and scale the reset may draw must fit)"
                    )

    @staticmethod
    def _placeable(footprint: float) -> tuple[np.ndarray, np.ndarray]:
        """The (x, y) box where an object of this footprint radius lies inside the crop."""
        return np.array(WORKSPACE_LOWER[:2]) + footprint, np.array(WORKSPACE_UPPER[:2]) - footprint

    def _tracker(self, name: str, scale: float) -> CoverageTracker:
        key = (name, scale)
        if key not in self._trackers:
            shared = _shared_tracker(
                self._stage.meshes[name],
                scale,
                self.coverage_samples,
                self.epsilon_fraction,
                self.table_crop_height,
                self._observation_views,
            )
            self._trackers[key] = shared.fresh()
        return self._trackers[key]

    def view_to_action(
        self, azimuth: float, elevation: float, radius: float, *, clip: bool = False
    ) -> np.ndarray:
        """The continuous action that requests view (azimuth and elevation in rad, radius in
        m; ``info["viewpoint"]`` gives degrees). Azimuths wrap by whole turns. A view outside
        the action's ranges, which no action requests, is refused with a ValueError, or with
        ``clip`` taken at the nearest one that can be requested, the angularly nearer end of
        a narrowed azimuth range (the scripted baselines' views under narrowed ranges)."""
        values = np.array([azimuth, elevation, radius], dtype=float)
        if not np.isfinite(values).all():
            raise ValueError(f"view_to_action needs finite numbers, got {values.tolist()}")
        low, high = self.azimuth_range
        turn, tolerance = 2 * np.pi, 1e-9
        values[0] = (values[0] - low) % turn + low
        if values[0] > high + tolerance and values[0] - turn >= low - tolerance:
            values[0] -= turn  # a rounding below the range's start, not almost a turn above
        if clip and values[0] > high:  # only a narrowed range: the nearer of its ends
            values[0] = high if values[0] - high <= low + turn - values[0] else low
        ranges = np.array([self.azimuth_range, self.elevation_range, self.radius_range])
        outside = (values < ranges[:, 0] - tolerance) | (values > ranges[:, 1] + tolerance)
        if outside.any() and not clip:
            degrees = np.rad2deg(ranges[:2]).round(2).tolist()
            raise ValueError(
                f"view (azimuth {np.rad2deg(azimuth):.4g} deg, elevation "
                f"{np.rad2deg(elevation):.4g} deg, radius {radius:.4g} m) lies outside the "
                f"action's ranges (azimuth {degrees[0]} deg, elevation {degrees[1]} deg, radius "
                f"{self.radius_range.tolist()} m), so no action requests it; view_to_action takes "
                "radians (info['viewpoint'] is in degrees), or pass clip=True for the nearest "
                "view that can be requested"
            )
        scaled = 2 * (values - ranges[:, 0]) / np.maximum(ranges[:, 1] - ranges[:, 0], 1e-9) - 1
        return np.clip(scaled, -1.0, 1.0).astype(np.float32)

    def _view_from_action(self, action) -> tuple[float, float, float]:
        if self.action_mode == "discrete":
            return self.candidate_views[as_index(action, int(self.action_space.n))]
        action = as_action(action, self.action_space.shape)
        unit = (np.clip(action, -1.0, 1.0) + 1.0) / 2.0
        ranges = np.array([self.azimuth_range, self.elevation_range, self.radius_range])
        values = ranges[:, 0] + unit * (ranges[:, 1] - ranges[:, 0])
        return float(values[0]), float(values[1]), float(values[2])

    def _capture(self) -> np.ndarray:
        """Render depth at the current pose, fuse it, and return the new cropped points."""
        rng = self.np_random if self._noise_enabled else None
        self._depth = self._render_depth(rng)
        self._hits = self._world_points(self._depth)
        points = crop_points(self._hits, *self._crop)
        self.map.fuse(points)
        self._camera_locations.append(self.camera.pose(self.data)[0])
        return points

    def _world_points(self, depth: np.ndarray) -> np.ndarray:
        """World points of the image's returns at the live state, less those on the arm's
        own links with ``filter_arm_points`` (the depth observation keeps them: the camera
        does see the arm)."""
        if self.filter_arm_points:
            on_arm = self.camera.pixels_on_geoms(
                depth, self.data, self.arm.geom_ids, ARM_FILTER_MARGIN
            )
            if on_arm.any():
                depth = np.where(on_arm, 0.0, depth).astype(depth.dtype)
        return self.camera.points_world(depth, self.data)

    def _carve_free_space(self) -> None:
        """Mark the cells the latest image's rays crossed (needs the episode's centre)."""
        if self.free_space is not None:
            self.free_space.carve(self._camera_locations[-1], self._hits)

    def _render_depth(self, rng: np.random.Generator | None) -> np.ndarray:
        """Depth at the live state; rays are cast in the placed variant's stand-in scene."""
        camera = self.camera
        if camera.backend not in RAY_CAST_BACKENDS:
            return camera.render(self.data, rng=rng)
        scenes = self._variant_scenes[(self.placed.name, self.placed.scale)]
        scene = scenes.ray_scene(self.data, self.placed, camera)
        return camera.render(self.data, rng=rng, scene=scene)

    def _estimate_center(self, points: np.ndarray) -> np.ndarray:
        if len(points) == 0:  # nothing seen: aim at the middle of the placement region
            return np.array([*self.object_region.mean(axis=0), 0.05])
        low, high = points.min(axis=0), points.max(axis=0)
        return np.array([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, high[2] / 2])

    def _observation(self) -> dict:
        scaled = np.clip(self._depth / self.depth_obs_range, 0.0, 1.0)
        depth = np.round(255 * scaled).astype(np.uint8)
        position, rotation = self.camera.pose(self.data)
        occupied = self.map.occupancy_grid(
            self.center, self.map_extent, self.map_grid, dtype=np.float32
        )
        obs = {
            "depth": depth[None],
            "map": occupied.flatten(),
            "view_history": self._history.flatten(),
            "camera_pose": np.concatenate(
                [position - self.center, -rotation[:, 2], rotation[:, 1]]
            ).astype(np.float32),
            "budget": np.array([1.0 - self.views_used / self.view_budget], dtype=np.float32),
        }
        if self.free_space is not None:
            obs["free_space"] = self.free_space.free(occupied).astype(np.float32).ravel()
        if self.privileged:
            obs["coverage"] = np.array([self.coverage.coverage], dtype=np.float32)
        return obs

    def _info(
        self, gain: float, terms: dict, *, planned: bool, refused: bool, path: float, unstable=False
    ) -> dict:
        coverage = self.coverage.coverage
        return {
            **terms,
            "coverage": coverage,
            "coverage_gain": gain,
            "views_used": self.views_used,
            "reachable": planned,
            "refused": refused,
            "path_length": path,
            "is_success": coverage >= self.success_coverage,
            "object": self.placed.name,
            "scale": self.placed.scale,
            "sim_unstable": unstable,
        }


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


def _candidate_views(
    azimuths_deg, elevations_deg, radius
) -> tuple[tuple[float, float, float], ...]:
    views = [
        (math.radians(az), math.radians(el), float(radius))
        for el in elevations_deg
        for az in azimuths_deg
    ]
    views.append((0.0, math.pi / 2, float(radius)))
    return tuple(views)
