"""ViewPlanning: next-best-view shape recording ("留形") with a wrist depth camera.

The env composes its parts: :class:`~liuxing_envs.sim.view_scene.ViewScene` (the simulation),
:class:`~liuxing_envs.control.view_action.ViewActions` (which view an action names),
:class:`~liuxing_envs.control.view_motion.ViewMotion` (the arm to a view),
:class:`~liuxing_envs.sensors.view_sensor.ViewSensor` (depth, fusion, free space) and
:class:`~liuxing_envs.tasks.view_planning_task.ViewPlanningTask` (coverage, reward, budget).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from gymnasium import spaces

from liuxing_envs.control.view_action import ViewActions
from liuxing_envs.control.view_motion import ViewMotion
from liuxing_envs.envs.base import LiuxingEnv, delegate
from liuxing_envs.envs.view_planning_settings import V0, V1, ViewPlanningSettings
from liuxing_envs.opengl import require_opengl
from liuxing_envs.perception.reconstruction import Reconstruction
from liuxing_envs.sensors.view_sensor import ViewSensor, estimate_center
from liuxing_envs.sim.camera import CameraIntrinsics
from liuxing_envs.sim.markers import add_frustum, add_points
from liuxing_envs.sim.object_lists import load_objects
from liuxing_envs.sim.objects import OBJECT_SETS
from liuxing_envs.sim.scene import OVERVIEW_CAMERA
from liuxing_envs.sim.view_scene import CoverageSetUp, Placements, ViewScene, check_observable
from liuxing_envs.sim.viewpoints import sphere_point
from liuxing_envs.tasks.view_planning_task import ViewPlanningTask
from liuxing_envs.validation import is_number, require_choice, require_number

#: = view_planning_settings.OBJECT_SET_NAMES (a test keeps them equal).
OBJECT_SET_NAMES = tuple(OBJECT_SETS)
#: F-score threshold of the reconstruction, as a share of the bounding-box diagonal.
DEFAULT_TAU_FRACTION = 0.01
RENDER_MAX_POINTS = 3000
#: The observation's keys, in their order (the sensor's and the task's, interleaved).
OBSERVATION_KEYS = (
    "depth",
    "map",
    "view_history",
    "camera_pose",
    "budget",
    "free_space",
    "coverage",
)


class ViewPlanningEnv(LiuxingEnv):
    """Next-best-view planning: choose where the wrist depth camera looks next.

    ## Description
    A 6-DoF arm (UR5e kinematics) with a wrist depth camera stands at a table with one object
    on it. Each step the agent picks a viewpoint on a sphere around the object's estimated
    centre; the arm moves there (inverse kinematics, joint limits, collision-checked paths),
    the camera renders depth, the points are fused in the world frame, and the reward is the
    gain in surface coverage of the object (the NBV metric of PC-NBV, SCONE, RL-NBV):
    ``coverage_samples`` points on its surface, of those some view of the env's view space
    can see, each covered when a fused point lies within ``epsilon_fraction`` × the object's
    bounding-box diagonal. :meth:`reconstruct` turns the fused cloud into a mesh (open3d)
    scored against the ground truth. The default objects are the 13 of ``"train"`` (box,
    cylinder, cone, l_bracket, mug, bowl, table, stacked_blocks, bunny, obelisk, vase,
    step_pyramid, open_box); results are reported on ``"held_out"`` (torus, chair, arch,
    u_bracket, t_pipe).

    ## Action space
    ``ViewPlanning-v1``: ``Box(-1, 1, (3,))`` mapped linearly onto azimuth
    (``azimuth_range_deg``, from +x, away from the arm, towards +y), elevation
    (``elevation_range_deg``) and radius (``radius_range``); values outside [-1, 1] are
    clipped, NaN or inf refused. ``ViewPlanningDiscrete-v1`` (``action_mode="discrete"``):
    ``Discrete(33)`` indexing :attr:`candidate_views`, every ``discrete_azimuths_deg`` at
    every ``discrete_elevations_deg`` at ``discrete_radius``, then the top view.
    :meth:`view_to_action` gives the continuous action of a view.

    A view whose IK fails or whose paths (straight, else through home) both collide is
    *refused*: the arm stays, no image is taken, the view uses one step of the budget and
    ``refusal_penalty`` is charged. With ``motion="dynamic"`` a view the servos stop short of
    (a contact, a waypoint not reached in time) is refused too, imaged from where it stopped.

    ## Observation space
    A ``Dict`` (SB3's ``MultiInputPolicy`` takes it as is; G = ``map_grid``):

    ==================  =======================  ============================================
    key                 shape, dtype             meaning
    ==================  =======================  ============================================
    ``depth``           (1, H, W) uint8          latest depth image; 255 = ``depth_obs_range``
                                                 m, 0 = no return (the arm's links included)
    ``map``             (G³,) float32            1 where the fused map holds a point, in a
                                                 cube of ``map_extent`` m about the centre,
                                                 indexed [x, y, z] after ``reshape(G, G, G)``
    ``view_history``    (``view_budget`` × 5,)   per used view: cos, sin azimuth, elevation /
                        float32                  90°, radius in [0, 1], +1 reached / -1
                                                 refused; zeros for views not yet used
    ``camera_pose``     (9,) float32             camera position relative to the centre (m),
                                                 optical axis, image-up axis
    ``budget``          (1,) float32             share of the view budget left
    ``free_space``      (G³,) float32            only with ``observe_free_space``: cells a
                                                 depth ray crossed that ``map`` leaves 0
    ``coverage``        (1,) float32             only with ``privileged``: current coverage
    ==================  =======================  ============================================

    ## Rewards
    ``coverage_reward_scale * Δcoverage - motion_cost * joint path (rad) - refusal_penalty *
    refused``; ``info`` holds each term (``reward_coverage``, ``reward_motion``,
    ``reward_refusal``) and ``coverage``, ``coverage_gain``, ``views_used``, ``reachable``,
    ``refused``, ``path_length``, ``is_success`` (coverage ≥ ``success_coverage``),
    ``viewpoint`` (deg, deg, m), ``object``, ``scale``, ``sim_unstable``.

    ## Starting state
    ``reset`` draws an object, a scale from ``scales``, a position in ``object_region`` and a
    yaw in [0, 2π); the arm starts at home and takes the first image looking down; the view
    sphere's centre is estimated from that cloud (its bounding box's centre at half its
    height). ``reset(options=...)`` may fix ``object``, ``scale``, ``position`` ((x, y), m)
    and ``yaw`` (rad); a refused option changes nothing.

    ## Episode end
    Terminated when ``view_budget`` views are spent (the observation counts them down, so
    learners must not bootstrap past the last), or, with ``terminate_on_success``, at
    ``success_coverage``. Truncated when dynamic motion's physics diverges
    (``info["sim_unstable"]``). No registered time limit.

    ## Arguments
    Keyword arguments (``gym.make("ViewPlanning-v1", **kwargs)``), with v1's defaults;
    ``render_mode="rgb_array"`` renders the overview camera with the fused points and the
    camera's frustum.

    {arguments}

    ## Version history
    * v1: the reported results' configuration; depth is ray-cast (``depth_backend="raycast"``),
      the same images on every machine; the env ends its own episodes at any ``view_budget``.
    * v0 (deprecated, kept one release): depth from OpenGL where it works
      (``depth_backend="auto"``); a registered time limit of 4 steps.
    """

    episode_length_setting = "view_budget"
    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}
    settings_type = ViewPlanningSettings
    #: The settings of the id this class is registered as (``ViewPlanning-v1``).
    default_settings: ViewPlanningSettings = V1
    #: Made again from the settings after a pickle or deep copy (:meth:`rebuild_after_copy`):
    #: the compiled scene, its stand-ins and coverage set-up are most of an env's size.
    rebuilt_on_copy = ("scene",)

    def __init__(self, *, render_mode: str | None = None, **settings) -> None:
        self.settings = self.settings_from(settings)
        task, sensor, scene = self.settings.task, self.settings.sensor, self.settings.scene
        require_choice("render_mode", render_mode, (None, *self.metadata["render_modes"]))
        # Without OpenGL these would fail at the first image with an AttributeError.
        if sensor.depth_backend == "gl":
            require_opengl(
                "depth_backend", sensor.depth_backend, "'auto' (ray-cast where OpenGL is missing)"
            )
        if render_mode is not None:
            require_opengl("render_mode", render_mode, "None")
        self.render_mode = render_mode
        self.actions = ViewActions(self.settings.action)
        self.arm_motion = ViewMotion(self.settings.arm.motion)
        self.task = ViewPlanningTask(task)
        self.sensor = ViewSensor(sensor, self.settings.fusion, sensor.resolution)
        self.intrinsics = CameraIntrinsics(width=sensor.resolution, height=sensor.resolution)
        meshes = load_objects(scene.object_set, scene.objects)
        self.placements = Placements(meshes, scene, self.settings.fusion.table_crop_height)
        self.object_names = self.placements.object_names
        check_observable(meshes, self.scales, self._coverage_set_up())
        self.scene = self._build_scene(meshes)

        self.action_space = self.actions.space
        self.observation_space = spaces.Dict(
            {**self.sensor.observation_spaces(), **self.task.observation_spaces()}
        )
        self.center = np.zeros(3)

    def _coverage_set_up(self) -> CoverageSetUp:
        fusion = self.settings.fusion
        return CoverageSetUp(
            fusion.coverage_samples,
            float(fusion.epsilon_fraction),
            float(fusion.table_crop_height),
            self.actions.observation_views,
        )

    def _build_scene(self, meshes) -> ViewScene:
        sensor = self.settings.sensor
        return ViewScene(
            meshes,
            self.scales,
            self._coverage_set_up(),
            self.intrinsics,
            sensor.depth_backend,
            sensor.depth_noise,
        )

    # ------------------------------------------------------------------ Gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.closed = False  # reopened: renderers are made again when needed
        options = self.placements.checked_options(options)  # before the seed changes
        super().reset(seed=seed)
        self._reset_seed = seed
        placed = self.scene.place(*self.placements.draw(self.np_random, options))
        self.task.reset(self.scene.tracker(placed.name, placed.scale))
        self.sensor.reset()
        points = self.sensor.capture(self.scene, self.np_random)
        self.center = estimate_center(points, self.object_region)
        self.sensor.start_free_space(self.center)
        self.sensor.carve_free_space()
        self.coverage.update(placed.to_object(points))
        self._episode_ready = True
        info = self.task.info(0.0, {}, placed, planned=True, refused=False, path=0.0)
        return self._observation(), info

    def _steps_taken(self) -> int:
        return self.views_used

    def _step(self, action):
        azimuth, elevation, radius = self.actions.view(action)
        plan = self._plan_view(sphere_point(self.center, azimuth, elevation, radius))
        gain, path_length, reached, unstable = 0.0, 0.0, False, False
        if plan is not None:
            motion = self.arm_motion.follow(self.arm, plan)
            path_length, reached, unstable = motion.path_length, motion.reached, motion.unstable
            # A dynamic motion can stop short of the view; the camera then looks from where
            # the arm stopped, so depth and pose still agree.
            if not unstable:
                points = self.sensor.capture(self.scene, self.np_random)
                gain = self.coverage.update(self.placed.to_object(points))
                self.sensor.carve_free_space()
        refused = not reached
        self.task.record_view((azimuth, elevation, radius), refused, self.actions.requestable_radii)
        terms = self.task.reward_terms(gain, path_length, refused)
        reward = float(sum(terms.values()))
        info = self.task.info(
            gain,
            terms,
            self.placed,
            planned=plan is not None,
            refused=refused,
            path=path_length,
            unstable=unstable,
        )
        info["viewpoint"] = (math.degrees(azimuth), math.degrees(elevation), radius)
        terminated, truncated = self.task.episode_end(info, unstable)
        if terminated or truncated:
            self._episode_ready = False
        return self._observation(), reward, terminated, truncated, info

    def prepare_objects(self) -> None:
        """Build every object variant's coverage grid and stand-in scenes now (each is built
        at the variant's first episode otherwise: tens of milliseconds, once per process)."""
        for name in self.object_names:
            for scale in self.scales:
                self.scene.tracker(name, scale)
                self.scene.stand_ins(name, scale)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        renderer = self._overview_renderer(self.model)
        renderer.update_scene(self.data, camera=OVERVIEW_CAMERA)
        add_points(renderer.scene, self.map.points(), RENDER_MAX_POINTS)
        position, rotation = self.camera.pose(self.data)
        add_frustum(renderer.scene, position, rotation, self.intrinsics, length=0.25)
        return renderer.render().copy()

    def close(self) -> None:
        super().close()
        self.scene.close_camera()

    # ------------------------------------------------------------------ copies
    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state["_copied_episode"] = self.scene.episode_state()
        return state

    def rebuild_after_copy(self) -> None:
        """Build the simulation again from the settings and put the episode back (the
        object where it stood, MuJoCo's state); the rest of the episode was copied."""
        episode = self.__dict__.pop("_copied_episode", None)
        scene = self.settings.scene
        self.scene = self._build_scene(load_objects(scene.object_set, scene.objects))
        self.scene.restore_episode(episode)

    # ------------------------------------------------------------------ the parts' names
    # Every setting reads by its flat name (``env.view_budget``, see LiuxingEnv); the parts'
    # state by the names code outside has always read it by.
    model = delegate("scene.model")
    data = delegate("scene.data")
    arm = delegate("scene.arm")
    camera = delegate("scene.camera", "The wrist depth camera (made on first use, see ViewScene).")
    placed = delegate("scene.placed", "The object on the table (None before the first reset).")
    coverage = delegate("task.coverage", "The episode's coverage tracker (ground truth).")
    views_used = delegate("task.views_used", "Views of the budget used this episode.")
    map = delegate("sensor.map", "The fused voxel map of the episode.")
    free_space = delegate("sensor.free_space", "The carved free space (observe_free_space).")
    depth = delegate("sensor.depth", "The latest depth image (m, 0 = no return).")
    object_region = delegate("placements.region", "Where the object's base centre is drawn (m).")
    scales = delegate("placements.scales", "The object scales a reset draws from.")
    candidate_views = delegate("actions.candidate_views", "(azimuth, elevation, radius) each.")
    azimuth_range = delegate("actions.azimuth_range", "The continuous actions' (rad).")
    elevation_range = delegate("actions.elevation_range", "The continuous actions' (rad).")
    radius_range = delegate("actions.radius_range", "The continuous actions' (m).")

    def view_to_action(
        self, azimuth: float, elevation: float, radius: float, *, clip: bool = False
    ) -> np.ndarray:
        """See :meth:`ViewActions.view_to_action`."""
        return self.actions.view_to_action(azimuth, elevation, radius, clip=clip)

    # ------------------------------------------------------------------ reconstruction
    def reconstruct(
        self,
        save_dir: str | Path | None = None,
        *,
        tau_fraction: float = DEFAULT_TAU_FRACTION,
        **kwargs,
    ) -> tuple[Reconstruction, dict]:
        """The "留形" record of the episode so far: the fused cloud meshed with open3d
        (``kwargs`` go to :func:`liuxing_envs.perception.reconstruction.reconstruct`) and its
        Chamfer distance, precision, completeness and F-score against the whole ground-truth
        surface, τ = ``tau_fraction`` × the bounding-box diagonal (so completeness stays
        below the observable share coverage counts); files saved to ``save_dir`` when given.
        Heavy (Poisson meshing, about a second): call it at an episode's end."""
        if self.placed is None:
            raise RuntimeError("call reset() first: there is nothing to reconstruct")
        require_number("tau_fraction", tau_fraction, 1e-4, 1.0)
        return self.sensor.reconstruct(
            self.scene.stage.meshes[self.placed.name], self.placed, tau_fraction, save_dir, **kwargs
        )

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
                "reward": -self.task.refusal_penalty,
            }
        points = self.scene.look_from(plan.waypoints[-1], self._preview_points)
        gain = self.coverage.preview(self.placed.to_object(points))
        reward = self.task.preview_reward(gain, plan.length)
        return {"reachable": True, "gain": gain, "path_length": plan.length, "reward": reward}

    # ------------------------------------------------------------------ internals
    def _plan_view(self, eye: np.ndarray):
        return self.arm_motion.plan(self.arm, eye, self.center)

    def _preview_points(self) -> np.ndarray:
        return self.sensor.preview_points(self.scene)

    def _observation(self) -> dict:
        found = {**self.sensor.observation(self.scene, self.center), **self.task.observation()}
        return {key: found[key] for key in OBSERVATION_KEYS if key in found}


class ViewPlanningV0Env(ViewPlanningEnv):
    """``ViewPlanning-v0``: deprecated, kept for one release so old run folders evaluate.
    Its depth backend is ``"auto"`` (OpenGL where it works); its registered time limit of 4
    steps cuts a larger ``view_budget`` short; a setting its mode leaves unused is taken and
    ignored, as v0 always did."""

    default_settings = V0
    refuses_inapplicable = False  # v0 took another mode's settings and ignored them
    deprecation = (
        "ViewPlanning-v0",
        "ViewPlanning-v1",
        "v1 renders depth by ray casting everywhere and ends its episodes on its own view "
        "budget, with no registered time limit",
    )
