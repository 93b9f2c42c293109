"""InstrumentGrasp: gentle, force-limited grasp and lift of a surgical instrument."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from gymnasium import spaces

from liuxing_envs.control.arm_control import arm_controller
from liuxing_envs.control.gripper_control import gripper_controller
from liuxing_envs.envs.base import LiuxingEnv, delegate
from liuxing_envs.envs.instrument_grasp_settings import V0, V1, InstrumentGraspSettings
from liuxing_envs.opengl import require_opengl
from liuxing_envs.safety.approach_guard import ApproachGuard
from liuxing_envs.safety.force_monitor import ForceMonitor
from liuxing_envs.sensors.grasp_sensor import GraspSensor, decode_depth, encode_depth
from liuxing_envs.sim.grasp_world import GraspWorld
from liuxing_envs.sim.scene import OVERVIEW_CAMERA
from liuxing_envs.tasks.instrument_grasp_start import (
    TOOL_START_HIGH,
    TOOL_START_LOW,
    TOOL_START_MAX_YAW_ERROR,
    StartDraw,
)
from liuxing_envs.tasks.instrument_grasp_task import REWARD_TERMS, InstrumentGraspTask
from liuxing_envs.validation import as_action, finite_vector, require_choice

__all__ = [
    "DEFAULT_CONTROL_HZ",
    "DEFAULT_TIMESTEP",
    "REWARD_TERMS",
    "TOOL_START_HIGH",
    "TOOL_START_LOW",
    "TOOL_START_MAX_YAW_ERROR",
    "InstrumentGraspEnv",
    "InstrumentGraspV0Env",
]

#: The default control timing (v0 and v1 alike), for code that sizes runs by it.
DEFAULT_CONTROL_HZ = V1.timing.control_hz
DEFAULT_TIMESTEP = V1.timing.timestep
FORCE_COLOUR_RANGE = 15.0  # N shown as full red on the pads in render()


class InstrumentGraspEnv(LiuxingEnv):
    """Pick a surgical instrument off a tray without squeezing or striking it too hard.

    ## Description
    A 6-DoF arm (UR5e kinematics) carries a parallel-jaw gripper with
    touch-sensing pads and a wrist depth/RGB camera. One instrument lies on a tray in front of
    it; the policy grasps it by friction alone (nothing welds it), lifts it by
    ``target_height`` and holds it for ``hold_time``, keeping each pad's force under
    ``force_limit``. A force monitor makes a protective stop when a pad force or an impact on
    the instrument passes ``hard_limit_factor`` times its limit. The instrument set is named:
    ``"train"`` (scalpel, tissue_forceps, scissors, hemostat, retractor), ``"held_out"``
    (needle_holder, probe) or ``"all"``. The parts: the arm and gripper controllers
    (``liuxing_envs.control``), the approach guard and force monitor (``liuxing_envs.safety``),
    the observation (``liuxing_envs.sensors.grasp_sensor``), the task
    (``liuxing_envs.tasks.instrument_grasp_task``), the world (``sim/grasp_world.py``).

    ## Action space
    ``Box(-1, 1, (5,))`` with ``controller="ee_delta"``, ``(7,)`` with ``"joint_delta"``
    (which needs the approach guard off, as ``InstrumentGraspUnguarded-v1`` has it); float32.
    Out-of-range values are clipped, NaN/inf raise ``ValueError``.

    ===  =================  ===================================================================
    idx  ``controller``     meaning
    ===  =================  ===================================================================
    0-2  ``"ee_delta"``     tool-centre move x, y, z from where it is (``max_translation`` m)
    3    ``"ee_delta"``     yaw change about world z (``max_yaw`` rad)
    0-5  ``"joint_delta"``  arm joint set-point changes (``max_joint_delta`` rad)
    -1   both               gripper: ``gripper_control="force"``, the grip force, each finger
                            servoing closed (> 0) or open (< 0) with at most |action| x
                            ``max_grip_force`` N; ``"opening"``, the pad opening to servo to,
                            0 m at -1 to 0.08 m at +1; ``"delta"``, the change of the
                            commanded opening (``max_gripper_delta`` m)
    ===  =================  ===================================================================

    With ``ee_delta`` the tool points down; the target is clipped to the workspace above the
    tray and solved with closed-form IK; a target out of reach, or reached only by switching
    arm configuration (a joint jumping more than 1 rad), leaves the set-point unchanged. The
    joint servos track their set-points with ``arm_stiffness`` times their full stiffness.
    With ``approach_lead_limit`` (``ee_delta`` only) the move is guarded near the instrument:
    for each pad between 10 µm and ``approach_distance`` of it, the set-point may lead the pad
    toward the instrument's nearest point by at most ``approach_lead_limit`` +
    ``approach_lead_slope`` x the pad's gap; a step asking more is shortened, translation and
    yaw by one factor (to holding the pose). With ``approach_guard_fingers`` a closing
    finger's servo target is shortened too, so that its pad keeps the same allowance; fingers
    that close farther in one step than the allowance at ``approach_distance`` are refused
    when the env is made. The guard reads the instrument's geometry from the simulator
    (privileged, as the ``instrument`` observation is).

    ## Observation space
    ``Dict`` (float32 unless noted), for SB3's ``MultiInputPolicy``:

    ==============  ==========  ===============================================================
    key             shape       content
    ==============  ==========  ===============================================================
    ``proprio``     (19,)       arm joint angles (6, rad) and velocities (6, rad/s), tool-centre
                                position (3, m), cos and sin of the tool yaw (2), pad opening
                                and commanded opening (2, m; the action's, before the finger
                                guard; with ``"force"`` the servos' end of travel)
    ``forces``      (2,)        left and right fingertip normal force (N): every contact on a pad
    ``instrument``  (14,)       ``obs_mode="state"`` only, PRIVILEGED: grasp point (3, m), handle
                                axis (3), instrument velocity (3, m/s), the grasp point in the
                                tool's yaw frame (3, m), cos and sin of twice the tool's yaw from
                                across the handle (2)
    ``depth``       (1, H, W)   ``"depth"`` and ``"rgbd"``: wrist z-depth, uint8 levels (0 = no
                                return, 1-255 span 0.1-0.6 m; :meth:`decode_depth`)
    ``rgb``         (3, H, W)   ``"rgbd"`` only: wrist colour image, uint8, channel-first
    ==============  ==========  ===============================================================

    ## Rewards
    The sum of these terms, each in ``info``; peaks are over the control step,
    sampled every 5 physics steps:

    - ``reward_reach`` = 1 - tanh(``reach_sharpness`` d), d the tool centre's distance to the
      grasp point (m);
    - ``reward_grasp`` = 1 while both pads press on the instrument with >= 0.5 N each;
    - ``reward_lift`` = 2 min(1, max(0, lift) / ``target_height``) while grasped (lift: the
      grasp point's height above where it lay at reset);
    - ``reward_hold`` = 1 while grasped at the target height;
    - ``reward_force`` = -``force_penalty`` sum_pads max(0, peak pad force - ``force_limit``);
    - ``reward_impact`` = -``impact_penalty`` max(0, peak impact - ``impact_limit``), the net
      contact force on the instrument from anything but the pads, less its weight;
    - ``reward_approach`` = -``approach_penalty`` sum_pads max(0, m - ``approach_allowance``)
      for each pad between 0.5 mm and ``approach_distance`` of the instrument, m how far the
      new set-point carries it toward the instrument (0 unless the penalty is set);
    - ``reward_failure`` = -``failure_penalty`` at a protective stop;
    - ``reward_success`` = 5 per step left of ``episode_steps`` when the episode ends in
      success (only with ``terminate_on_success``).

    Success (``info["is_success"]``): lifted by ``target_height`` and held there, grasped,
    for ``hold_time`` s, the episode's peak pad force never above ``force_limit``. ``info``
    also carries ``peak_force`` (episode, N), ``step_peak_force``, ``grip_force``,
    ``lift_height`` (m), ``force_violations``, ``impact_violations`` (control steps over the
    limits), ``guarded_steps``, ``guarded_finger_steps`` (steps in which the approach guard
    shortened the arm's move or a finger's target), ``hard_limit_exceeded``, ``grasped``,
    ``instrument`` and ``sim_unstable``.

    ## Starting state
    A random instrument of ``instrument_set`` (or ``instruments``), level
    on the tray at a random position and yaw (redrawn until it lies 1 cm inside the rim), its
    mass and contact friction optionally scaled by factors drawn from ``mass_range`` and
    ``friction_range``. The arm starts in a ready pose, the wrist camera 0.45 m above the tray
    and the gripper open 6 cm. ``reset(options=...)`` may fix ``instrument``, ``position``
    (grasp point x, y) and ``yaw``, and start the tool at ``tool_start`` = (x, y, z) from the
    grasp point (m; z 0-0.3), the jaws across the handle turned by ``tool_yaw_error`` (rad)
    and opened to the handle's width plus ``jaw_clearance`` (m); a start that would overlap
    the instrument or the tray is raised in 1 mm steps until it touches nothing.

    ## Episode end
    Terminated at a protective stop (``info["hard_limit_exceeded"]``) and,
    with ``terminate_on_success``, at success. Truncated after ``episode_steps`` control steps
    (no registered time limit), and at once when the physics diverges (reward 0,
    ``info["sim_unstable"]``, a finite observation; the next ``reset()`` starts clean).

    ## Arguments
    ``render_mode`` (``"rgb_array"``: the overview camera, pads shaded white to
    red with their force, ``metadata["render_fps"]`` the control rate) and these settings,
    with v1's defaults (from :class:`InstrumentGraspSettings`; the colour image,
    ``depth_backend="gl"`` and ``render_mode`` need OpenGL). A setting of one mode given with
    another is refused by name.

    {arguments}

    ## Version history

    - v1: the shipped grasp policy's task as the defaults (force-commanded gripper at 3 N,
      compliant arm with even servo damping, finer steps, the guarded approach, stiffer force
      and failure penalties, a gentler reach term), ray-cast depth on every machine, and the
      episode truncated at ``episode_steps`` by the env itself.
    - v0 (deprecated, ``InstrumentGraspV0Env``): the stiff position-controlled arm with the
      opening-commanded gripper and no guard; its registered time limit (200) ends episodes.
    """

    episode_length_setting = "episode_steps"
    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}
    settings_type = InstrumentGraspSettings
    #: The settings an argument left out takes.
    default_settings: ClassVar[InstrumentGraspSettings] = V1
    #: Whether the env ends its own episodes at ``episode_steps`` (truncated).
    truncates_at_episode_steps: ClassVar[bool] = True

    def __init__(self, *, render_mode: str | None = None, **settings) -> None:
        require_choice("render_mode", render_mode, (None, "rgb_array"))
        self.settings = self.settings_from(settings)
        sensors, arm, timing = self.settings.sensors, self.settings.arm, self.settings.timing
        obs_mode, depth_backend = sensors.obs_mode, sensors.depth_backend
        # Without OpenGL MuJoCo's renderers are made without complaint and fail when first
        # used, in reset() or render(), with an AttributeError that names no setting.
        for name, value, renders, instead in (
            ("obs_mode", obs_mode, obs_mode == "rgbd", "'depth' (ray-cast) or 'state'"),
            (
                "depth_backend",
                depth_backend,
                depth_backend == "gl" and obs_mode != "state",
                "'auto' (ray-cast where OpenGL is missing), 'raycast' or 'embree'",
            ),
            ("render_mode", render_mode, render_mode is not None, "None"),
        ):
            if renders:
                require_opengl(name, value, instead)
        self.render_mode = render_mode
        # A frame a control step: video writers (agents/video.py, Gymnasium's RecordVideo)
        # play the frames at this rate, in real time only if it is the control rate. Per
        # instance: the class's dict is shared by every env.
        fps = float(timing.control_hz)
        self.metadata = {**self.metadata, "render_fps": int(fps) if fps.is_integer() else fps}
        self.instrument_names = self.settings.scene.names
        self.substeps = timing.substeps
        # The parts: arm and gripper controllers, the safety layer, the sensors, the task.
        self.arm_controller = arm_controller(arm)
        self.gripper_controller = gripper_controller(self.settings.gripper)
        self.approach_guard = ApproachGuard(self.settings.safety)
        self.force_monitor = ForceMonitor(self.settings.safety, self.substeps)
        self.sensor = GraspSensor(sensors)
        self.task = InstrumentGraspTask(self.settings)
        self._worlds = {
            name: GraspWorld(
                name,
                timing.timestep,
                float(arm.arm_stiffness),
                None if arm.servo_damping_ratio is None else float(arm.servo_damping_ratio),
            )
            for name in self.instrument_names
        }
        for world in self._worlds.values():
            self.gripper_controller.prepare(world.gripper)
        self.world: GraspWorld = self._worlds[self.instrument_names[0]]
        self.start_draw = StartDraw(self._worlds)
        self.action_space = spaces.Box(
            -1.0, 1.0, shape=(self.arm_controller.action_size + 1,), dtype=np.float32
        )
        self.observation_space = self.sensor.space
        self._episodes_started = 0

    # Every setting reads by its flat name (``env.max_grip_force``, see LiuxingEnv); these
    # derived ones and the parts' too, as code outside has always read them.
    hard_limit = delegate("settings.safety.hard_limit", "Pad force of a protective stop (N).")
    intrinsics = delegate("sensor.intrinsics", "The wrist camera's intrinsics.")
    encode_depth = staticmethod(encode_depth)
    decode_depth = staticmethod(decode_depth)

    @property
    def worlds(self) -> tuple[GraspWorld, ...]:
        """Every instrument's world (one MuJoCo model each), in ``instrument_names``' order;
        :attr:`world` is the episode's."""
        return tuple(self._worlds.values())

    # ------------------------------------------------------------------ Gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.closed = False  # reopened: renderers are made again when needed
        options = self.start_draw.checked_options(options)
        super().reset(seed=seed)
        self._reset_seed = seed
        start = self.start_draw.draw(options, self.np_random, self.settings.scene)
        if self.world.name != start.instrument:
            self._close_renderer()  # made for the other instrument's model
        self.world = self._worlds[start.instrument]
        self._episode_ready = False  # until the reset below has succeeded
        self.world.reset(
            start.xy,
            start.yaw,
            start.mass_scale,
            start.friction_scale,
            tool_start=start.tool_start,
            tool_yaw_error=start.tool_yaw_error,
            jaw_clearance=start.jaw_clearance,
        )
        self._episodes_started += 1
        self.task.reset(self.world)
        self.gripper_controller.sync(self.world.gripper)
        self._episode_ready = True
        info = self.task.info(self.world, {}, grasped=False, step_peak=0.0, success=False, lift=0.0)
        return self._observation(), info

    def _steps_taken(self) -> int:
        return self.task.stats.steps

    def _step(self, action):
        # np.minimum and np.maximum clip as np.clip does (the action is finite), at half its cost.
        action = np.minimum(np.maximum(as_action(action, self.action_space.shape), -1.0), 1.0)
        world, task = self.world, self.task
        move = self.arm_controller.apply(world, action[:-1], self.approach_guard)
        approach = task.approach(world)
        self.gripper_controller.apply(world.gripper, action[-1])
        braked = False
        if move.near and self.approach_guard.guards_fingers:
            braked = self.approach_guard.brake_fingers(world, move.near, move.leads)
        task.count_guard(move.slowed, braked)
        peaks = self.force_monitor.run(world)
        if peaks.stopped:
            self.gripper_controller.sync(world.gripper)
        if peaks.diverged:
            return self._end_unstable()
        broke_limit = self.force_monitor.broke_limit(peaks)
        result = task.step(world, peaks, broke_limit, approach)
        truncated = (
            self.truncates_at_episode_steps and task.stats.steps >= self.settings.task.episode_steps
        )
        if result.terminated or truncated:
            self._episode_ready = False
        info = task.info(
            world,
            result.terms,
            grasped=result.grasped,
            step_peak=peaks.pad,
            success=result.success,
            lift=result.lift,
            broke_limit=broke_limit,
        )
        return self._observation(), result.reward, result.terminated, truncated, info

    def _end_unstable(self):
        """The step's return when the physics diverged: MuJoCo has reset the data, so the
        episode's state is gone. No reward; truncated; the next reset() starts clean."""
        terms = self.task.unstable_step()
        self._episode_ready = False
        self.gripper_controller.sync(self.world.gripper)  # reset with the data
        info = self.task.info(
            self.world, terms, grasped=False, step_peak=0.0, success=False, lift=0.0, unstable=True
        )
        observation = {key: np.nan_to_num(value) for key, value in self._observation().items()}
        return observation, 0.0, False, True, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        world = self.world
        renderer = self._overview_renderer(world.model)
        # Pads shade from white to red with their force: the force read-out.
        forces = world.gripper.fingertip_forces()
        saved = world.model.geom_rgba[world.gripper.pad_geoms].copy()
        level = np.clip(forces / FORCE_COLOUR_RANGE, 0.0, 1.0)[:, None]
        world.model.geom_rgba[world.gripper.pad_geoms, :3] = (1 - level) * 0.92 + level * np.array(
            [0.95, 0.05, 0.05]
        )
        renderer.update_scene(world.data, camera=OVERVIEW_CAMERA)
        frame = renderer.render().copy()
        world.model.geom_rgba[world.gripper.pad_geoms] = saved
        return frame

    def close(self) -> None:
        super().close()
        for world in self._worlds.values():
            world.close()

    def wrist_camera_pose(self, arm_qpos=None) -> tuple[np.ndarray, np.ndarray]:
        """Wrist camera position (m) and rotation (columns = camera x, y, z; it looks along
        -z) in the world for the given arm joint angles (default: the current ones), from
        the arm's kinematics: the calibration a real robot has, not privileged state."""
        world = self.world
        if arm_qpos is None:
            return world.wrist_camera_pose(world.arm.qpos)
        qpos = finite_vector(arm_qpos, world.arm.qpos.size)
        if qpos is None:
            raise ValueError(
                f"wrist_camera_pose needs {world.arm.qpos.size} finite joint angles (rad), "
                f"got {arm_qpos!r}"
            )
        return world.wrist_camera_pose(qpos)

    @property
    def episodes_started(self) -> int:
        """How many episodes ``reset()`` has begun."""
        return self._episodes_started

    # ------------------------------------------------------------------ internals
    @property
    def dt(self) -> float:
        """Seconds of simulated time per control step (as Gymnasium's MuJoCo envs)."""
        return self.substeps * self.world.model.opt.timestep

    def _observation(self) -> dict:
        return self.sensor.observe(self.world, self.gripper_controller.commanded_opening)


class InstrumentGraspV0Env(InstrumentGraspEnv):
    """``InstrumentGrasp-v0``: deprecated, kept for one release so old run folders evaluate.
    v0's defaults (:data:`~liuxing_envs.envs.instrument_grasp_settings.V0`); its episodes end
    only at the registered time limit (200 steps), never at ``episode_steps``; a setting its
    mode leaves unused is taken and ignored, as v0 always did."""

    default_settings = V0
    truncates_at_episode_steps = False
    refuses_inapplicable = False  # v0 took another mode's settings and ignored them
    deprecation = (
        "InstrumentGrasp-v0",
        "InstrumentGrasp-v1",
        "v1's defaults are the shipped policy's task: force-commanded gripper, compliant arm, "
        "guarded approach, stiffer penalties, ray-cast depth; it truncates itself at "
        "episode_steps",
    )
