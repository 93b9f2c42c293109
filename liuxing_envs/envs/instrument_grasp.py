"""InstrumentGrasp-v0: gentle, force-limited grasp and lift of a surgical instrument."""

from __future__ import annotations

import math
from collections.abc import Sequence

import mujoco
import numpy as np
from gymnasium import spaces

from liuxing_envs.envs.base import LiuxingEnv
from liuxing_envs.forking import check_opengl_not_forked
from liuxing_envs.opengl import new_renderer, require_opengl
from liuxing_envs.sim.camera import BACKENDS, CameraIntrinsics
from liuxing_envs.sim.grasp_world import (
    TRAY_MARGIN,
    GraspWorld,
    jaws_across,
    tool_down,
)
from liuxing_envs.sim.gripper import (
    FORCE_COMMAND_DAMPING,
    GRASP_NOSLIP_ITERATIONS,
    MAX_OPENING,
    SERVO_FORCE_LIMIT,
    TCP_SITE,
)
from liuxing_envs.sim.instruments import (
    INSTRUMENT_SETS,
)
from liuxing_envs.sim.scene import (
    OVERVIEW_CAMERA,
)
from liuxing_envs.sim.stability import diverged_since, divergence_count
from liuxing_envs.validation import (
    as_action,
    checked_reset_options,
    finite_vector,
    option_angle,
    option_in,
    option_xy,
    refuse_if_closed,
    require_choice,
    require_int,
    require_number,
    require_range,
    step_context,
)

OBS_MODES = ("state", "depth", "rgbd")
CONTROLLERS = ("ee_delta", "joint_delta")
GRIPPER_CONTROLS = ("opening", "delta", "force")
INSTRUMENT_SET_NAMES = ("train", "held_out", "all")

DEFAULT_CONTROL_HZ = 20.0
DEFAULT_TIMESTEP = 0.002  # s
DEFAULT_MAX_EPISODE_STEPS = 200  # 10 s at 20 Hz
DEFAULT_FORCE_LIMIT = 5.0  # N per fingertip
DEFAULT_HARD_LIMIT_FACTOR = 3.0
DEFAULT_IMPACT_LIMIT = 10.0  # N, contact force on the instrument from anything but the pads
DEFAULT_TARGET_HEIGHT = 0.10  # m of lift
DEFAULT_HOLD_TIME = 1.0  # s
#: Steepness of the reach term (1/m): 10 pays 0.24 at 10 cm and almost nothing beyond 30 cm
#: (the ready pose is ~32 cm from the grasp point); 3 still pays 0.26 there.
DEFAULT_REACH_SHARPNESS = 10.0
DEFAULT_FORCE_PENALTY = 0.2  # reward per newton above the limit, per pad
DEFAULT_IMPACT_PENALTY = 0.05  # reward per newton above the impact limit
DEFAULT_FAILURE_PENALTY = 5.0
#: Reward per metre the arm's set-point moves a pad toward the instrument, beyond
#: ``approach_allowance``, when the pad is within ``approach_distance`` of it (0: off). The
#: hard-limit stops of trained policies come from a pad landing on the instrument while the
#: set-point runs a full ``max_translation`` ahead (a compliant servo presses with about its
#: stiffness times that lead): the force passes the hard limit within 2 ms of the first
#: touch, too fast for the force terms to warn the policy. This term charges the command
#: before the contact.
DEFAULT_APPROACH_PENALTY = 0.0
DEFAULT_APPROACH_DISTANCE = 0.015  # m, pad to instrument
DEFAULT_APPROACH_ALLOWANCE = 0.003  # m of set-point move per control step
#: With ``controller="ee_delta"``: how far (m) the arm's set-point may run ahead of a pad toward
#: the instrument while the pad is between GUARD_MIN_GAP and ``approach_distance`` of it (None:
#: no limit). A step asking for more is slowed as a whole, translation and yaw by one factor,
#: as a cobot's speed and separation monitoring slows it near an obstacle: a guarded approach.
#: A servo presses with about its stiffness times its lead when the pad lands, so this bounds
#: that push (not the arm's momentum), which the force terms cannot see coming.
DEFAULT_APPROACH_LEAD_LIMIT = None
#: How much further (m per metre of the pad's gap) the set-point may lead a pad that is still
#: away from the instrument: the lead allowed is ``approach_lead_limit`` plus this times the
#: gap, so a pad slows as it nears the instrument and lands at the speed that
#: ``approach_lead_limit`` alone sets. A compliant arm moves at a rate proportional to its
#: lead, and a pad landing at 5-10 cm/s passes the hard limit within one 10 ms force sample,
#: often within one 2 ms physics step (``docs/training_notes.md``): a constant limit lets the
#: arm arrive that fast, and a small constant one stalls it. At 1 the set-point may reach the
#: instrument's surface, no braking at all, hence the bound.
DEFAULT_APPROACH_LEAD_SLOPE = 0.0
MAX_APPROACH_LEAD_SLOPE = 1.0
#: Whether the approach guard also shortens a closing finger's servo target, so that a pad's
#: lead counts the finger's closing as well as the arm's move. Force-commanded fingers close at
#: 7.5 cm/s at 3 N (``max_grip_force`` over their damping), as fast as the arm landings that pass
#: the hard limit.
DEFAULT_APPROACH_GUARD_FINGERS = False
#: The approach lead limit guards pads down to this gap (m); a pad touching the instrument is
#: left to the grip (its lead across the handle is what squeezes it).
GUARD_MIN_GAP = 1e-5
#: The guard's scale is refined at most this many times, until no lead is over the limit by
#: more than GUARD_TOLERANCE (m).
GUARD_TRIES = 4
GUARD_TOLERANCE = 1e-6
#: The most the reach, grasp, lift and hold terms pay in one step.
MAX_STEP_REWARD = 5.0
#: Largest joint set-point change (rad) an ee_delta step may ask for. A step's own moves need
#: a few tenths at most; switching to another IK configuration needs about pi.
MAX_SETPOINT_JUMP = 1.0
REWARD_TERMS = (
    "reward_reach", "reward_grasp", "reward_lift", "reward_hold",
    "reward_force", "reward_impact", "reward_approach", "reward_failure", "reward_success",
)  # fmt: skip
DEFAULT_MAX_TRANSLATION = 0.02  # m per control step at |action| = 1
DEFAULT_MAX_YAW = 0.2  # rad per control step
DEFAULT_MAX_JOINT_DELTA = 0.05  # rad per control step
#: The smallest ``max_gripper_delta`` (m) and ``max_grip_force`` (N) taken.
MIN_GRIPPER_DELTA = 1e-4
MIN_GRIP_FORCE = 0.1
#: With gripper_control="delta": the most the commanded opening moves per control step (m).
#: A pad servo pushes about 2.5 N per mm its command runs ahead of the pad, so a gentle
#: grasp needs command steps of a fraction of a millimetre: 0.1 of this one.
DEFAULT_MAX_GRIPPER_DELTA = 0.004
#: With gripper_control="force": the grip force (N per finger) at |action| = 1. Above the
#: default hard limit (15 N), so a force-commanded policy can still squeeze too hard.
DEFAULT_MAX_GRIP_FORCE = 20.0
#: Factor on the arm's joint servo stiffness (kp; kv follows its square root, so each servo
#: keeps its damping ratio). 1 is the stiff position-controlled arm: a fingertip driven into the
#: instrument at 1 cm/step presses it with ~36 N. A cobot's compliance mode is softer: at 0.1
#: the same push peaks at ~13 N. The arm is gravity compensated, so soft servos do not sag.
DEFAULT_ARM_STIFFNESS = 1.0
#: The arm's joint servos' damping ratio at the ready pose, the same for every joint: kv = 2
#: ratio sqrt(kp m), m the joint's entry on the mass matrix's diagonal there (the joint moved
#: alone, the others held; the gripper's inertia and ``arm_stiffness`` included). None keeps
#: the model's: its MJCF asks for ``dampratio="1"``, which MuJoCo turns into each kv from the
#: joint's effective inertia at qpos0, the arm stretched out flat. Over the tray that leaves
#: shoulder pan overdamped (1.91 there, by the measure above) and shoulder lift and elbow
#: underdamped (0.69, 0.48), so the tool wanders off the axis an ``ee_delta`` action asks
#: for (see the class doc).
DEFAULT_SERVO_DAMPING_RATIO = None
DEFAULT_RESOLUTION = 64
#: Allowed factors of mass_range and friction_range.
SCALE_LIMITS = (0.1, 10.0)
#: Depth observations are uint8 (what SB3's CNNs take): level 0 = no return, levels 1-255
#: span this z-depth range linearly (about 2 mm per level); farther saturates at 255.
DEPTH_RANGE = (0.1, 0.6)  # m
#: Forces are sampled every this many physics steps (10 ms at the default timestep).
FORCE_SAMPLE_SUBSTEPS = 5
#: Region (x, y) of the instrument's grasp point on the tray at reset, metres.
PLACEMENT_REGION = ((0.44, -0.08), (0.56, 0.08))
PLACEMENT_TRIES = 100
#: The yaws a ``position`` reset option is checked at (and drawn from, where random draws
#: miss the few at which it fits).
CHECKED_YAWS = np.linspace(0, 2 * np.pi, 24, endpoint=False)
#: Bounds of the ``tool_start`` reset option: the tool centre's offset from the grasp point (m).
TOOL_START_LOW = np.array([-0.05, -0.05, 0.0])
TOOL_START_HIGH = np.array([0.05, 0.05, 0.30])
TOOL_START_MAX_YAW_ERROR = math.pi / 2
FORCE_COLOUR_RANGE = 15.0  # N shown as full red on the pads in render()


def option_tool_start(key, value) -> np.ndarray:
    """The ``tool_start`` reset option: three finite numbers within TOOL_START_LOW/HIGH."""
    offset = finite_vector(value, 3)
    if offset is None or np.any(offset < TOOL_START_LOW) or np.any(offset > TOOL_START_HIGH):
        raise ValueError(
            f"reset option {key} must be the tool centre's offset (x, y, z) in m from the grasp "
            f"point, within {TOOL_START_LOW.tolist()} to {TOOL_START_HIGH.tolist()}, got {value!r}"
        )
    return offset


def option_yaw_error(key, value) -> float:
    """The ``tool_yaw_error`` reset option: an angle within +-TOOL_START_MAX_YAW_ERROR."""
    angle = option_angle(key, value)
    if abs(angle) > TOOL_START_MAX_YAW_ERROR:
        raise ValueError(
            f"reset option {key} must be within +-{TOOL_START_MAX_YAW_ERROR:.4f} rad (a quarter "
            f"turn: the jaws are symmetric), got {value!r}"
        )
    return angle


def option_jaw_clearance(key, value) -> float:
    """The ``jaw_clearance`` reset option: metres of opening beyond the handle's width."""
    require_number(f"reset option {key}", value, 0.0, MAX_OPENING)
    return float(value)


def _require_guardable_fingers(
    gripper_control: str,
    max_grip_force: float,
    max_gripper_delta: float,
    control_hz: float,
    allowance_at_entry: float,
) -> None:
    """Refuse a finger guard that a closing finger can outrun. The guard watches a pad from
    ``approach_distance`` of the instrument in; a finger that closes farther in one control
    step than the ramp allows there (``allowance_at_entry``, m) enters that band too fast to
    be braked, or crosses it within the step, and lands as hard as unguarded."""
    if gripper_control == "opening":
        raise ValueError(
            "approach_guard_fingers=True cannot brake gripper_control='opening': its position "
            "servos close the whole stroke within one control step (up to about 2 m/s); use "
            "gripper_control='force' or 'delta'"
        )
    if gripper_control == "force":
        knob, value, unit, minimum = "max_grip_force", max_grip_force, "N", MIN_GRIP_FORCE
        per_unit = 1.0 / (FORCE_COMMAND_DAMPING * control_hz)  # m a step per N
        travel_of = f"max_grip_force / {FORCE_COMMAND_DAMPING:g} N s/m / control_hz"
    else:
        knob, value, unit, minimum = "max_gripper_delta", max_gripper_delta, "m", MIN_GRIPPER_DELTA
        per_unit = 0.5  # the opening is both fingers' travel
        travel_of = "max_gripper_delta / 2"
    travel = value * per_unit
    if travel <= allowance_at_entry:
        return
    fits = allowance_at_entry / per_unit
    remedies = [f"lower {knob} to at most {fits:.3g} {unit}"] if fits >= minimum else []
    remedies.append("raise approach_lead_limit or approach_lead_slope")
    raise ValueError(
        "approach_guard_fingers=True needs fingers that close no farther in one control "
        "step than the guard allows where it starts watching a pad (approach_lead_limit + "
        f"approach_lead_slope x approach_distance = {1e3 * allowance_at_entry:.2f} mm); "
        f"with gripper_control={gripper_control!r} a finger closes {travel_of} = "
        f"{1e3 * travel:.2f} mm a step: {', or '.join(remedies)}"
    )


class InstrumentGraspEnv(LiuxingEnv):
    """Pick a surgical instrument off a tray without squeezing or striking it too hard.

    The arm (UR5e kinematics) carries a parallel-jaw gripper with touch-sensing pads and the
    wrist depth/RGB camera. One instrument lies on a tray in front of it. The grasp is by
    friction only (elliptic cones, noslip iterations); nothing welds the instrument. An
    instrument at rest sleeps (MuJoCo's island sleeping: frozen, its velocity exactly 0) until
    the arm or gripper touches it, which wakes it within the same physics step.

    **Action** ``Box(-1, 1)``, float32; out-of-range values are clipped, NaN/inf raise
    ``ValueError``.

    ===  =====================  ===============================================================
    idx  ``controller``         meaning
    ===  =====================  ===============================================================
    0-2  ``"ee_delta"``         tool-centre displacement x, y, z from where it is now (up to
                                ``max_translation`` m per step each, world frame)
    3    ``"ee_delta"``         yaw change about world z (up to ``max_yaw`` rad per step)
    0-5  ``"joint_delta"``      arm joint set-point changes (up to ``max_joint_delta`` rad)
    -1   both                   gripper, ``gripper_control="opening"`` (default): the pad
                                opening to servo to, 0 m at -1 (closed) to 0.08 m at +1 (each
                                finger servo is limited to 40 N); ``"delta"``: the change of
                                the commanded opening (up to ``max_gripper_delta`` m per step);
                                ``"force"``: the grip force, as an industrial gripper's force
                                setting: each finger servos closed (action > 0) or open
                                (< 0) with at most |action| x ``max_grip_force`` N, its
                                speed capped by damping (6 cm/s at 2.5 N)
    ===  =====================  ===============================================================

    With ``ee_delta`` (default) the tool stays pointing down; the target is clipped to the
    workspace above the tray (the fingertips stop 1 mm above its floor; the tool centre stays
    within the tray's inner walls, which the pads and open fingers can still touch) and solved
    with the arm's closed-form IK; a target it cannot reach, or reaches only by switching to
    another arm configuration (a joint set-point jumping by more than 1 rad, as turning one
    way until wrist 3 meets its limit would), leaves the arm's set-point unchanged.
    Control runs at ``control_hz`` over physics steps of ``timestep`` seconds. The arm's joint
    servos track their set-points with ``arm_stiffness`` times their full stiffness (1: a stiff
    position-controlled arm; 0.1: a cobot's compliance mode, which bumps the instrument with
    about a third of the force, 36 -> 13 N in a 1 cm-per-step push onto the retractor, and
    settles on it gently; on the scissors, 82 -> 18 N still trips the protective stop).

    With ``approach_lead_limit`` (m; None, off, by default) an ``ee_delta`` step becomes a
    guarded approach near the instrument. For each pad between 10 um and
    ``approach_distance`` of it, the set-point's lead over the pad toward the instrument's
    nearest point (the set-point's forward kinematics, fingers as open as now) may not exceed
    the limit. A step asking for more is shortened, translation and yaw by one factor (to
    holding the pose where even that leads too far), as a cobot's speed and separation
    monitoring slows it near an obstacle; a step that leads less than holding would is let
    through, and where IK refuses the held pose the set-point stays where it was. That bounds
    the servo's push when the pad lands (about its stiffness times the lead), not the arm's
    momentum, and a pad already touching is not guarded (its lead across the handle is what
    grips). Closed jaws lowered 1 cm a step onto a handle (``arm_stiffness=0.1``) land with
    7.2 N at a limit of 3 mm against 12.9 N unguarded, the tool descending the last 1.5 cm
    at about 1 mm a step instead of 2.9 mm. With ``approach_lead_slope`` (0 by default) the
    limit grows with the pad's gap, ``approach_lead_limit`` + ``approach_lead_slope`` x gap,
    a braking ramp: a compliant arm moves at a rate proportional to its lead, so a pad slows
    as it nears the instrument and lands at the speed the limit at a touch allows, where a
    constant limit lets the arm arrive fast (a pad landing at 5-10 cm/s passes the hard limit
    within one 10 ms force sample) or, if small, stalls it. The same descent at 0.25 mm + 0.3
    x gap lands with 2.1 N; at a constant 0.25 mm the arm crawls and never reaches the handle
    in 60 steps. The slope may be 0 to 1 (at 1 the set-point may reach the instrument).
    With ``approach_guard_fingers`` (False by default) the guard counts the fingers too: where
    a finger closes toward the instrument, its servo target is shortened so that its pad,
    carried by the arm's set-point and by its finger together, leads no more than the same
    allowance: the arm's move has it first, the finger what the arm leaves (a pad already
    touching is left to grip). Force-commanded fingers close at
    ``max_grip_force`` over their damping, 7.5 cm/s at 3 N, as fast as the arm landings that
    pass the hard limit. Jaws open 6 cm across a handle and closed with the arm held
    (``max_grip_force=3``, ``arm_stiffness=0.1``, 0.25 mm + 0.3 x gap) land with 1.2 N
    instead of 3.9 N, five steps later, and grip. The observation's commanded opening stays
    the action's. Fingers must close no farther in a control step than the ramp allows where
    the guard starts watching a pad (``approach_lead_limit`` + ``approach_lead_slope`` x
    ``approach_distance``), or they would enter that band too fast to brake, or cross it
    within the step: ``gripper_control="opening"`` is refused (its servos close the whole
    stroke within a step), and so are force commands above that speed (3 N at 20 Hz closes
    3.75 mm a step; the default 20 N, 25 mm) and delta steps above twice it. With ``"delta"``
    the command goes on adding up while a finger is held back, and once its pad touches, that
    finger's target is the whole command: the guard softens the landing, not the squeeze
    after it. Fingers, like the arm, are judged by each pad's direction to the instrument's
    nearest point, and a pad nearer than 10 µm counts as touching: jaws reset low over the
    instrument (``tool_start``) can leave a pad a hair above one part, with no contact, while
    its finger closes sideways into another part beside it, unbraked (closed at 3 N with the
    arm held, a hemostat and scissors struck 16-17 N, a protective stop). Braking toward
    every part near a pad instead ended those, but the shipped policy, trained under this
    rule, then lifted in 62% and 74% of 600 episodes, with 3 and 2 stops (not adopted;
    ``docs/training_notes.md``). The guard, on the arm or the fingers, reads the
    instrument's geometry from the simulator: privileged, as the ``instrument`` observation
    is (a real cell would measure those gaps itself).

    An ``ee_delta`` action moves the set-point, from where the tool is: the tool follows
    within the step only as far as the servos take it, and not exactly along the action's
    axis. With the model's servo damping (``servo_damping_ratio=None``: MuJoCo's
    ``dampratio="1"`` of the MJCF, computed at qpos0, the arm stretched out flat) the joints
    over the tray are damped unevenly, shoulder pan at 1.91 times critical, shoulder lift and
    elbow at 0.69 and 0.48, the wrists at 0.93-1.00 (by ``servo_damping_ratio``'s measure;
    by MuJoCo's, the other joints free, 2.02, 0.84, 0.59 and 0.97-1.01). Measured from the
    ready pose, six steps of full action along one
    axis, then four of none (tool-centre moves in mm, x y z; ``arm_stiffness=0.1``,
    ``max_translation=0.01``): +x moves (4.5, 0, 4.1) in the sixth step, climbing at 42
    degrees, and coasts (4.5, -0.6, 7.7) after it; +y moves 1.5 mm a step; -z moves 4.9 mm a
    step and coasts 9.0 mm further down. With ``servo_damping_ratio=0.7`` (each arm joint at
    0.7 of critical at the ready pose): +x (3.2, 0, 1.7), coasting (1.7, -1.0, 0.3); +y 3.6
    mm a step; -z 3.2 mm a step, coasting 4.5 mm (``docs/training_notes.md``).

    **Observation** ``Dict`` (float32 unless noted), for SB3's ``MultiInputPolicy``:

    ==============  ==========  =============================================================
    key             shape       content
    ==============  ==========  =============================================================
    ``proprio``     (19,)       arm joint angles (6, rad), joint velocities (6, rad/s),
                                tool-centre position (3, m), cos and sin of the tool yaw (2),
                                pad opening and commanded opening (2, m; the action's,
                                before ``approach_guard_fingers`` shortens it; with
                                ``gripper_control="force"`` the command is the servos'
                                end of travel: 0 while closing, 0.08 while opening; after
                                a reset or a protective stop, the opening it left)
    ``forces``      (2,)        left and right fingertip normal force (N): the pads' touch
                                sensors, i.e. every contact on a pad (instrument, tray, ...)
    ``instrument``  (14,)       ``obs_mode="state"`` only, PRIVILEGED: grasp-point position
                                (3, m), handle axis (3), instrument linear velocity (3, m/s),
                                grasp point relative to the tool centre in the tool's yaw
                                frame (3, m: x along the tool's x axis, the jaws closing
                                along y, z up; the tool frame's own y and z point the other
                                way, as the tool points down), cos and sin of
                                twice the tool's yaw from across the handle (2; 1 and 0 when
                                the jaws are across it, either way round)
    ``depth``       (1, H, W)   ``"depth"`` and ``"rgbd"``: wrist z-depth, uint8 levels (see
                                :meth:`decode_depth`: 0 = no return, 1-255 span 0.1-0.6 m)
    ``rgb``         (3, H, W)   ``"rgbd"`` only: wrist colour image, uint8, channel-first
    ==============  ==========  =============================================================

    **Reward**: the sum of these terms, each in ``info``:

    - ``reward_reach`` = 1 - tanh(``reach_sharpness`` d), d = distance tool centre to grasp
      point (m), ``reach_sharpness`` 10/m by default;
    - ``reward_grasp`` = 1 while both pads press on the instrument with >= 0.5 N each
      (contact normal forces with the instrument alone, not what the touch sensors add up);
    - ``reward_lift`` = 2 min(1, max(0, lift) / ``target_height``) while grasped (lift: the
      grasp point's height above where it lay at reset, m; pressed down, it pays 0);
    - ``reward_hold`` = 1 while grasped at the target height;
    - ``reward_force`` = -``force_penalty`` sum_pads max(0, peak pad force - ``force_limit``);
    - ``reward_impact`` = -``impact_penalty`` max(0, peak impact - ``impact_limit``), the
      impact being the net contact force on the instrument from anything but the pads, less
      its weight;
    - ``reward_approach`` = -``approach_penalty`` sum_pads max(0, m - ``approach_allowance``)
      for each pad between 0.5 mm and ``approach_distance`` of the instrument, m being how far
      the arm's new set-point would carry the pad toward the instrument's nearest point (m;
      the set-point's forward kinematics with the fingers as open as now, so the jaws' own
      closing does not count). Off by default (0); it warns a policy before a strike, which
      the force terms cannot: a compliant arm whose set-point runs a centimetre ahead passes
      the hard limit within 2 ms of the first touch (``docs/training_notes.md``);
    - ``reward_failure`` = -``failure_penalty`` when a pad force exceeds
      ``hard_limit_factor`` x ``force_limit``, or the impact exceeds ``hard_limit_factor`` x
      ``impact_limit``: a protective stop holds the arm and fingers, and the episode ends
      (terminated; ``info["hard_limit_exceeded"]``);
    - ``reward_success`` = 5 per step left of ``episode_steps`` when the episode ends in
      success (only with ``terminate_on_success``), what holding on until the time limit
      would have paid. The env cannot see its TimeLimit wrapper: when you change
      ``max_episode_steps``, pass the same number as ``episode_steps`` (default 200).

    Peaks are over the control step, sampled every 5 physics steps (10 ms at the default
    ``timestep``).

    **Success** (``info["is_success"]``): the instrument has been lifted by ``target_height``
    and held there, grasped, for ``hold_time`` s, and the episode's peak fingertip force has
    never been above ``force_limit``. It ends the episode only with ``terminate_on_success``.
    ``info`` also carries ``peak_force`` (episode, N), ``step_peak_force``, ``grip_force``
    (now), ``lift_height`` (m), ``force_violations`` (control steps above the limit),
    ``impact_violations``, ``guarded_steps`` (control steps whose move the approach guard
    shortened; 0 without ``approach_lead_limit``), ``guarded_finger_steps`` (control steps in
    which it shortened a finger's target; 0 without ``approach_guard_fingers``),
    ``hard_limit_exceeded``, ``grasped``,
    ``instrument`` and ``sim_unstable``.

    **Simulator faults**: physics that diverges (NaN, inf or huge accelerations, which MuJoCo
    answers by resetting its data) ends the step at once: reward 0 (every term 0), truncated,
    ``info["sim_unstable"] = True``, a finite observation; the next ``reset()`` starts clean.

    **Episode**: a random instrument of ``instrument_set`` (or of ``instruments``; one
    compiled model each), level on the tray at a random position and yaw (redrawn until it
    lies 1 cm inside the rim), optionally with its mass and friction scaled by factors drawn
    from ``mass_range`` / ``friction_range``. The friction factor multiplies the coefficients
    (sliding, torsional, rolling) of every contact the instrument makes, with the pads, the
    tray, the fingers or the arm: MuJoCo takes a contact's friction from the geom of higher
    contact priority (the pads and the tray outrank the instrument), so the factor scales the
    instrument's geoms and every geom that can touch it, and with them the contacts among
    those (a fingertip on the tray). The arm starts in a ready pose with the wrist
    camera 0.45 m above the tray and the gripper open 6 cm. ``reset(options=...)`` may fix
    ``instrument``, ``position`` (grasp point x, y; without ``yaw``, at a random yaw at which
    the instrument fits the tray) and ``yaw``, and may start the arm
    elsewhere: ``tool_start`` = (x, y, z), the tool centre's offset from the grasp point (m;
    z 0-0.3; clipped to the workspace, so offsets below 1.5-3.5 mm, by instrument, all start
    at its floor), with
    the jaws open 6 cm across the handle, turned by ``tool_yaw_error`` (rad) and opened to
    the handle's width plus ``jaw_clearance`` (m) if given (a training curriculum's starts;
    see ``agents/curriculum.py``). Where the gripper would then overlap the instrument or the
    tray (an offset off the handle can put a finger into a ring, a blade or a shaft), the tool
    is raised in 1 mm steps until it touches nothing, x, y and yaw kept: every episode starts
    with nothing touched, some such starts higher than asked. Registered with a
    TimeLimit of 200 steps (10 s; ``gym.make(..., max_episode_steps=N)`` changes it); the
    environment itself truncates only on a simulator fault (above).

    **Arguments**: every keyword above, ``resolution`` (square image side, pixels),
    ``depth_backend`` (``"gl"``, ``"raycast"``, ``"embree"`` or ``"auto"``; the
    instruments are primitives, so embree casts as raycast does) and ``render_mode``
    (``"rgb_array"``: the overview camera, pads shaded white to red with their force; a
    frame a control step, so ``metadata["render_fps"]`` is ``control_hz``). The colour image,
    ``depth_backend="gl"`` and ``render_mode`` need OpenGL: with ``MUJOCO_GL=disable`` they
    are refused when the env is made (``obs_mode="depth"`` is then ray-cast).

    **Defaults** (the module's ``DEFAULT_*`` constants): ``obs_mode='state'``,
    ``controller='ee_delta'``, ``gripper_control='opening'``, ``instrument_set='train'``,
    ``instruments=None``, ``control_hz=20.0``, ``timestep=0.002``, ``force_limit=5.0``,
    ``hard_limit_factor=3.0``, ``impact_limit=10.0``, ``target_height=0.1``,
    ``hold_time=1.0``, ``reach_sharpness=10.0``, ``force_penalty=0.2``,
    ``impact_penalty=0.05``, ``failure_penalty=5.0``, ``approach_penalty=0.0``,
    ``approach_distance=0.015``, ``approach_allowance=0.003``, ``approach_lead_limit=None``,
    ``approach_lead_slope=0.0``, ``approach_guard_fingers=False``,
    ``terminate_on_success=False``,
    ``max_translation=0.02``, ``max_yaw=0.2``, ``max_joint_delta=0.05``,
    ``max_gripper_delta=0.004``, ``max_grip_force=20.0``, ``arm_stiffness=1.0``,
    ``servo_damping_ratio=None``, ``mass_range=None``, ``friction_range=None``, ``resolution=64``,
    ``depth_backend='auto'``, ``episode_steps=200``, ``render_mode=None``.

    **Version history.** v0: initial release; ``gripper_control="delta"`` and
    ``max_gripper_delta``, then ``gripper_control="force"`` and ``max_grip_force``, then
    ``arm_stiffness`` and the ``tool_start``, ``tool_yaw_error`` and ``jaw_clearance`` reset
    options, added later (the defaults are unchanged); the ``instrument`` observation grew from
    9 to 14 entries (the grasp point and the handle's yaw relative to the tool) before any
    grasp policy was published. Fixed within v0 (2026-11-22): an ``ee_delta`` step that IK
    could only reach in another arm configuration swung the arm across the workspace (now
    refused); ``hold_time=0`` counted as success without a grasp; a protective stop's last
    physics steps were left out of the force peaks; the success bonus counts to the new
    ``episode_steps`` (it always counted to 200); ``close()`` then ``reset()`` failed with
    image observations; a ``position`` reset option outside the tray is refused before the
    reset changes anything. Fixed within v0 (2026-11-26): ``friction_range`` scaled only the
    instrument's own geoms, whose friction the higher-priority pads and tray override, so it
    changed no contact (the default, no factor, is unchanged); ``metadata["render_fps"]``
    was 20 at every ``control_hz`` (now the control rate); without OpenGL, ``obs_mode="rgbd"``,
    ``depth_backend="gl"`` and ``render_mode`` failed in ``reset()`` or ``render()`` with an
    AttributeError (now refused by name when the env is made); a ``tool_start`` could put a
    finger into the instrument, which the settling steps shoved, or which started the episode
    at up to 208 N on a pad (now raised clear); numpy arrays as choices, complex numbers,
    dicts and sets as ranges, and actions of strings or complex numbers were taken (now
    refused by name). Fixed within v0 (2026-11-27): in a process forked from one that had
    made an OpenGL context (an async vector env made after a render), OpenGL hung; it is now
    refused by name (``obs_mode="rgbd"``, ``render_mode``, ``depth_backend="gl"``) and
    ``"auto"`` falls back to ray casting. Added within v0 (2026-11-27; the default keeps the
    model's damping, so default episodes are unchanged): ``servo_damping_ratio``. Added
    within v0 (2026-11-28; off by default, so default rewards are unchanged):
    ``approach_penalty``, ``approach_distance``, ``approach_allowance`` and the
    ``reward_approach`` term (0 unless the penalty is set); then ``approach_lead_limit``
    (None, off, so default episodes are unchanged), then ``approach_lead_slope`` (0, so
    episodes with a constant limit are unchanged too) and ``info["guarded_steps"]``; then
    ``approach_guard_fingers`` (False, so episodes without it are unchanged) and
    ``info["guarded_finger_steps"]``. Fixed within v0 (2026-11-28): ``approach_guard_fingers``
    took gripper settings whose fingers outrun it (``"opening"``, the default 20 N force
    commands), where a pad crossed the guarded band within one step; they are now refused by
    name (the shipped policy's 3 N force commands pass).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        *,
        obs_mode: str = "state",
        controller: str = "ee_delta",
        gripper_control: str = "opening",
        instrument_set: str = "train",
        instruments: Sequence[str] | None = None,
        control_hz: float = DEFAULT_CONTROL_HZ,
        timestep: float = DEFAULT_TIMESTEP,
        force_limit: float = DEFAULT_FORCE_LIMIT,
        hard_limit_factor: float = DEFAULT_HARD_LIMIT_FACTOR,
        impact_limit: float = DEFAULT_IMPACT_LIMIT,
        target_height: float = DEFAULT_TARGET_HEIGHT,
        hold_time: float = DEFAULT_HOLD_TIME,
        reach_sharpness: float = DEFAULT_REACH_SHARPNESS,
        force_penalty: float = DEFAULT_FORCE_PENALTY,
        impact_penalty: float = DEFAULT_IMPACT_PENALTY,
        failure_penalty: float = DEFAULT_FAILURE_PENALTY,
        approach_penalty: float = DEFAULT_APPROACH_PENALTY,
        approach_distance: float = DEFAULT_APPROACH_DISTANCE,
        approach_allowance: float = DEFAULT_APPROACH_ALLOWANCE,
        approach_lead_limit: float | None = DEFAULT_APPROACH_LEAD_LIMIT,
        approach_lead_slope: float = DEFAULT_APPROACH_LEAD_SLOPE,
        approach_guard_fingers: bool = DEFAULT_APPROACH_GUARD_FINGERS,
        terminate_on_success: bool = False,
        max_translation: float = DEFAULT_MAX_TRANSLATION,
        max_yaw: float = DEFAULT_MAX_YAW,
        max_joint_delta: float = DEFAULT_MAX_JOINT_DELTA,
        max_gripper_delta: float = DEFAULT_MAX_GRIPPER_DELTA,
        max_grip_force: float = DEFAULT_MAX_GRIP_FORCE,
        arm_stiffness: float = DEFAULT_ARM_STIFFNESS,
        servo_damping_ratio: float | None = DEFAULT_SERVO_DAMPING_RATIO,
        mass_range: Sequence[float] | None = None,
        friction_range: Sequence[float] | None = None,
        resolution: int = DEFAULT_RESOLUTION,
        depth_backend: str = "auto",
        episode_steps: int = DEFAULT_MAX_EPISODE_STEPS,
        render_mode: str | None = None,
    ) -> None:
        require_choice("obs_mode", obs_mode, OBS_MODES)
        require_choice("controller", controller, CONTROLLERS)
        require_choice("gripper_control", gripper_control, GRIPPER_CONTROLS)
        require_choice("instrument_set", instrument_set, INSTRUMENT_SET_NAMES)
        require_choice("render_mode", render_mode, (None, "rgb_array"))
        require_choice("terminate_on_success", terminate_on_success, (False, True))
        require_choice("depth_backend", depth_backend, BACKENDS)
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
        for name, value, low, high in (
            ("control_hz", control_hz, 1.0, 500.0),
            ("timestep", timestep, 1e-4, 0.01),
            ("force_limit", force_limit, 0.1, 100.0),
            ("hard_limit_factor", hard_limit_factor, 1.0, 100.0),
            ("impact_limit", impact_limit, 0.1, 1000.0),
            ("target_height", target_height, 0.01, 0.2),
            ("hold_time", hold_time, 0.0, 10.0),
            ("reach_sharpness", reach_sharpness, 0.1, 100.0),
            ("force_penalty", force_penalty, 0.0, 100.0),
            ("impact_penalty", impact_penalty, 0.0, 100.0),
            ("failure_penalty", failure_penalty, 0.0, 1000.0),
            ("approach_penalty", approach_penalty, 0.0, 1e5),
            ("approach_distance", approach_distance, 0.0, 0.1),
            ("approach_allowance", approach_allowance, 0.0, 0.1),
            ("max_translation", max_translation, 1e-4, 0.1),
            ("max_yaw", max_yaw, 0.0, 1.0),
            ("max_joint_delta", max_joint_delta, 1e-4, 0.5),
            ("max_gripper_delta", max_gripper_delta, MIN_GRIPPER_DELTA, MAX_OPENING),
            ("max_grip_force", max_grip_force, MIN_GRIP_FORCE, SERVO_FORCE_LIMIT),
            ("arm_stiffness", arm_stiffness, 0.01, 1.0),
        ):
            require_number(name, value, low, high)
        if servo_damping_ratio is not None:
            require_number("servo_damping_ratio", servo_damping_ratio, 0.1, 10.0)
        require_number("approach_lead_slope", approach_lead_slope, 0.0, MAX_APPROACH_LEAD_SLOPE)
        if approach_lead_limit is not None:
            require_number("approach_lead_limit", approach_lead_limit, 0.0, 0.1)
            if controller != "ee_delta":
                raise ValueError(
                    "approach_lead_limit slows ee_delta steps; with controller='joint_delta' "
                    "it must be None"
                )
        elif approach_lead_slope:
            raise ValueError(
                f"approach_lead_slope={approach_lead_slope} raises approach_lead_limit with a "
                "pad's gap; set approach_lead_limit too (the lead allowed at a touch, m; "
                "controller='ee_delta' only)"
            )
        require_choice("approach_guard_fingers", approach_guard_fingers, (False, True))
        if approach_guard_fingers and approach_lead_limit is None:
            raise ValueError(
                "approach_guard_fingers=True widens the approach guard, which "
                "approach_lead_limit turns on; set approach_lead_limit too (the lead allowed at "
                "a touch, m; controller='ee_delta' only)"
            )
        if approach_guard_fingers:
            _require_guardable_fingers(
                gripper_control,
                max_grip_force,
                max_gripper_delta,
                control_hz,
                approach_lead_limit + approach_lead_slope * approach_distance,
            )
        require_int("resolution", resolution, 8, 512)
        require_int("episode_steps", episode_steps, 1, 100_000)
        self.episode_steps = episode_steps
        substeps = round(1.0 / (control_hz * timestep))
        if substeps < 1 or not math.isclose(substeps * timestep * control_hz, 1.0, rel_tol=1e-6):
            raise ValueError(
                f"1 / control_hz must be a whole number of timesteps; got control_hz="
                f"{control_hz}, timestep={timestep}"
            )
        names = INSTRUMENT_SETS[instrument_set]
        if instruments is not None:
            expected = (
                f"instruments must be a non-empty list of names from {INSTRUMENT_SETS['all']}"
            )
            if isinstance(instruments, str | bytes):
                raise ValueError(f"{expected}, got the single {instruments!r} (wrap it in a list)")
            try:
                names = tuple(instruments)
            except TypeError:
                raise ValueError(f"{expected}, got {instruments!r}") from None
            if not names or any(name not in INSTRUMENT_SETS["all"] for name in names):
                raise ValueError(f"{expected}, got {instruments!r}")
            if len(set(names)) < len(names):  # a repeat would silently weight the sampling
                raise ValueError(f"instruments must be unique, got {instruments!r}")
        self.mass_range = (
            None if mass_range is None else require_range("mass_range", mass_range, *SCALE_LIMITS)
        )
        self.friction_range = (
            None
            if friction_range is None
            else require_range("friction_range", friction_range, *SCALE_LIMITS)
        )

        self.obs_mode, self.controller, self.render_mode = obs_mode, controller, render_mode
        # A frame a control step: video writers (agents/video.py, Gymnasium's RecordVideo)
        # play the frames at this rate, in real time only if it is the control rate. Per
        # instance: the class's dict is shared by every env.
        fps = float(control_hz)
        self.metadata = {**self.metadata, "render_fps": int(fps) if fps.is_integer() else fps}
        self.instrument_names = names
        self.substeps = substeps
        self.force_limit, self.hard_limit = force_limit, force_limit * hard_limit_factor
        self.impact_limit, self.target_height = impact_limit, target_height
        self.hard_impact_limit = impact_limit * hard_limit_factor
        self.hold_steps = max(1, round(hold_time * control_hz))  # at height for a step at least
        self.reach_sharpness = float(reach_sharpness)
        self.force_penalty, self.impact_penalty = force_penalty, impact_penalty
        self.failure_penalty = failure_penalty
        self.approach_penalty, self.approach_allowance = approach_penalty, approach_allowance
        self.approach_distance = approach_distance
        self.approach_lead_limit = (
            None if approach_lead_limit is None else float(approach_lead_limit)
        )
        self.approach_lead_slope = float(approach_lead_slope)
        self.approach_guard_fingers = bool(approach_guard_fingers)
        self.terminate_on_success = bool(terminate_on_success)
        self.max_translation, self.max_yaw = max_translation, max_yaw
        self.max_joint_delta = max_joint_delta
        self.gripper_control, self.max_gripper_delta = gripper_control, max_gripper_delta
        self.max_grip_force = max_grip_force
        self.intrinsics = CameraIntrinsics(width=resolution, height=resolution)
        self._depth_backend = depth_backend
        self.arm_stiffness = float(arm_stiffness)
        self.servo_damping_ratio = (
            None if servo_damping_ratio is None else float(servo_damping_ratio)
        )
        self._worlds = {
            name: GraspWorld(name, timestep, self.arm_stiffness, self.servo_damping_ratio)
            for name in names
        }
        if gripper_control == "force":
            for world in self._worlds.values():
                world.gripper.use_force_commands()
        self.world: GraspWorld = self._worlds[names[0]]

        action_dim = 5 if controller == "ee_delta" else 7
        self.action_space = spaces.Box(-1.0, 1.0, shape=(action_dim,), dtype=np.float32)
        obs = {
            "proprio": spaces.Box(-np.inf, np.inf, (19,), dtype=np.float32),
            "forces": spaces.Box(0.0, np.inf, (2,), dtype=np.float32),
        }
        if obs_mode == "state":
            obs["instrument"] = spaces.Box(-np.inf, np.inf, (14,), dtype=np.float32)
        else:
            obs["depth"] = spaces.Box(0, 255, (1, resolution, resolution), dtype=np.uint8)
        if obs_mode == "rgbd":
            obs["rgb"] = spaces.Box(0, 255, (3, resolution, resolution), dtype=np.uint8)
        self.observation_space = spaces.Dict(obs)
        self._reset_seed: int | None = None
        self._episodes_started = 0
        self._steps = 0
        self._episode_ready = False
        self._renderer: mujoco.Renderer | None = None

    # ------------------------------------------------------------------ Gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        self.closed = False  # reopened: renderers are made again when needed
        options = checked_reset_options(
            options,
            {
                "instrument": option_in(self.instrument_names),
                "position": option_xy,
                "yaw": option_angle,
                "tool_start": option_tool_start,
                "tool_yaw_error": option_yaw_error,
                "jaw_clearance": option_jaw_clearance,
            },
        )
        for key in ("tool_yaw_error", "jaw_clearance"):
            if key in options and "tool_start" not in options:
                raise ValueError(f"reset option {key} needs tool_start as well")
        if "position" in options:
            self._check_position(options)
        super().reset(seed=seed)
        self._reset_seed = seed
        rng = self.np_random
        name = options.get(
            "instrument", self.instrument_names[rng.integers(len(self.instrument_names))]
        )
        world = self._worlds[name]
        for _ in range(PLACEMENT_TRIES):
            xy = np.asarray(options.get("position", rng.uniform(*PLACEMENT_REGION)), dtype=float)
            yaw = float(options.get("yaw", rng.uniform(0.0, 2 * np.pi)))
            if world.fits_on_tray(xy, yaw):
                break
        else:
            # A position that fits at few yaws (checked above) may be missed by every draw.
            free_yaw = "position" in options and "yaw" not in options
            fitting = [y for y in CHECKED_YAWS if world.fits_on_tray(xy, y)] if free_yaw else []
            if not fitting:
                raise ValueError(
                    f"{name} with its grasp point at {xy.tolist()} and yaw {yaw:.3f} rad does "
                    f"not lie inside the tray with {TRAY_MARGIN * 1000:.0f} mm to spare"
                    f"{self._tray_extent()}"
                )
            yaw = float(fitting[rng.integers(len(fitting))])
        mass_scale = rng.uniform(*self.mass_range) if self.mass_range else 1.0
        friction_scale = rng.uniform(*self.friction_range) if self.friction_range else 1.0
        if self._renderer is not None and self.world.name != name:
            self._renderer.close()
            self._renderer = None
        self.world = world
        self._episode_ready = False  # until the reset below has succeeded
        self.world.reset(
            xy,
            yaw,
            mass_scale,
            friction_scale,
            tool_start=options.get("tool_start"),
            tool_yaw_error=options.get("tool_yaw_error", 0.0),
            jaw_clearance=options.get("jaw_clearance"),
        )

        self._steps = 0
        self._episodes_started += 1
        self._hold_count = 0
        self._held = False
        self._peak_force = 0.0
        self._force_violations = 0
        self._impact_violations = 0
        self._guarded_steps = 0
        self._guarded_finger_steps = 0
        self._gripper_command = self.world.gripper.commanded_opening()
        self._start_height = self.world.grasp_point()[2]
        self._episode_ready = True
        info = self._info(terms={}, grasped=False, step_peak=0.0, success=False, lift=0.0)
        return self._observation(), info

    def step(self, action):
        refuse_if_closed(self)
        with step_context(self, self._steps + 1, self._reset_seed):
            return self._step(action)

    def _step(self, action):
        if not self._episode_ready:
            raise RuntimeError("call reset() before step(), and again after an episode ends")
        action = np.clip(as_action(action, self.action_space.shape), -1.0, 1.0)
        world = self.world
        near, arm_leads = self._apply_arm_action(action[:-1])
        approach = (
            sum(
                max(0.0, move - self.approach_allowance)
                for move in world.pad_approaches(self.approach_distance)
            )
            if self.approach_penalty
            else 0.0
        )
        if self.gripper_control == "delta":
            world.gripper.command(self._gripper_command + self.max_gripper_delta * action[-1])
        elif self.gripper_control == "force":
            world.gripper.grip(self.max_grip_force * float(action[-1]))
        else:
            world.gripper.command((action[-1] + 1.0) / 2.0 * MAX_OPENING)
        self._gripper_command = world.gripper.commanded_opening()
        if near and self.approach_guard_fingers:
            self._guard_fingers(near, arm_leads)

        model, data, gripper = world.model, world.data, world.gripper
        # The pads' peaks as Python floats: this loop runs once per force sample (five times a
        # step by default), and numpy's per-call overhead on 2-vectors cost more than the
        # bookkeeping's arithmetic.
        peak_left = peak_right = impact_peak = 0.0
        left, right = gripper.fingertip_forces().tolist()
        divergences = divergence_count(data)
        for start in range(0, self.substeps, FORCE_SAMPLE_SUBSTEPS):
            # Noslip iterations stop a held instrument creeping in the pads; they cost a third
            # of a physics step, so they run only while a pad touches something.
            model.opt.noslip_iterations = GRASP_NOSLIP_ITERATIONS if max(left, right) > 0.0 else 0
            mujoco.mj_step(model, data, nstep=min(FORCE_SAMPLE_SUBSTEPS, self.substeps - start))
            left, right = gripper.fingertip_forces().tolist()
            peak_left, peak_right = max(peak_left, left), max(peak_right, right)
            impact_peak = max(impact_peak, world.impact_force())
            if max(peak_left, peak_right) > self.hard_limit or impact_peak > self.hard_impact_limit:
                # Protective stop, as a real arm's force monitor does: hold the arm and the
                # fingers where they are and end the step (and the episode) here.
                world.set_arm_ctrl(world.arm.qpos)
                gripper.command(gripper.opening())
                self._gripper_command = gripper.commanded_opening()
                mujoco.mj_step(model, data, nstep=FORCE_SAMPLE_SUBSTEPS)
                left, right = gripper.fingertip_forces().tolist()
                peak_left, peak_right = max(peak_left, left), max(peak_right, right)
                impact_peak = max(impact_peak, world.impact_force())
                break
        # Checked once per control step: after a divergence MuJoCo's reset state is finite,
        # so the loop above runs on harmlessly, and its figures are discarded here.
        if diverged_since(data, divergences):
            return self._end_unstable()
        self._steps += 1

        grasped = world.grasped()
        grasp_point = world.grasp_point()
        lift = grasp_point[2] - self._start_height
        at_height = grasped and lift >= self.target_height
        self._hold_count = self._hold_count + 1 if at_height else 0
        step_peak = max(peak_left, peak_right)
        self._peak_force = max(self._peak_force, step_peak)
        self._force_violations += step_peak > self.force_limit
        self._impact_violations += impact_peak > self.impact_limit
        broke_limit = step_peak > self.hard_limit or impact_peak > self.hard_impact_limit
        self._held = self._held or self._hold_count >= self.hold_steps
        success = self._held and self._peak_force <= self.force_limit
        ends_in_success = success and self.terminate_on_success

        offset = world.tcp_position() - grasp_point
        distance = math.sqrt(offset.dot(offset))  # np.linalg.norm's own sum, without its checks
        terms = {
            "reward_reach": 1.0 - math.tanh(self.reach_sharpness * distance),
            "reward_grasp": float(grasped),
            "reward_lift": 2.0 * min(1.0, max(lift, 0.0) / self.target_height) if grasped else 0.0,
            "reward_hold": float(at_height),
            "reward_force": -self.force_penalty
            * (max(peak_left - self.force_limit, 0.0) + max(peak_right - self.force_limit, 0.0)),
            "reward_impact": -self.impact_penalty * max(0.0, impact_peak - self.impact_limit),
            "reward_approach": -self.approach_penalty * approach,
            "reward_failure": -self.failure_penalty if broke_limit else 0.0,
            # Ending early must not pay less than holding on until the time limit would.
            "reward_success": MAX_STEP_REWARD * max(0, self.episode_steps - self._steps)
            if ends_in_success and not broke_limit
            else 0.0,
        }
        reward = float(sum(terms.values()))
        terminated = bool(broke_limit or ends_in_success)
        truncated = False  # the TimeLimit wrapper's job, as in Gymnasium's MuJoCo envs
        if terminated:
            self._episode_ready = False
        info = self._info(
            terms,
            grasped=grasped,
            step_peak=step_peak,
            success=success,
            lift=lift,
            broke_limit=broke_limit,
        )
        return self._observation(), reward, terminated, truncated, info

    def _end_unstable(self):
        """The step's return when the physics diverged: MuJoCo has reset the data, so the
        episode's state is gone. No reward; truncated; the next reset() starts clean."""
        self._steps += 1
        self._episode_ready = False
        self._gripper_command = self.world.gripper.commanded_opening()  # reset with the data
        terms = dict.fromkeys(REWARD_TERMS, 0.0)
        info = self._info(
            terms, grasped=False, step_peak=0.0, success=False, lift=0.0, unstable=True
        )
        observation = {key: np.nan_to_num(value) for key, value in self._observation().items()}
        return observation, 0.0, False, True, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        world = self.world
        check_opengl_not_forked()  # a renderer made before a fork hangs in the child
        if self._renderer is None:
            self._renderer = new_renderer(world.model, 480, 640)
        # Pads shade from white to red with their force: the force read-out.
        forces = world.gripper.fingertip_forces()
        saved = world.model.geom_rgba[world.gripper.pad_geoms].copy()
        level = np.clip(forces / FORCE_COLOUR_RANGE, 0.0, 1.0)[:, None]
        world.model.geom_rgba[world.gripper.pad_geoms, :3] = (1 - level) * 0.92 + level * np.array(
            [0.95, 0.05, 0.05]
        )
        self._renderer.update_scene(world.data, camera=OVERVIEW_CAMERA)
        frame = self._renderer.render().copy()
        world.model.geom_rgba[world.gripper.pad_geoms] = saved
        return frame

    def close(self) -> None:
        super().close()
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        for world in self._worlds.values():
            world.close()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_renderer"] = None
        return state

    @staticmethod
    def encode_depth(depth_m: np.ndarray) -> np.ndarray:
        """uint8 levels of a z-depth image in metres (see DEPTH_RANGE; 0 = no return)."""
        near, far = DEPTH_RANGE
        levels = 1.0 + np.round((np.clip(depth_m, near, far) - near) / (far - near) * 254.0)
        return np.where(depth_m > 0, levels, 0.0).astype(np.uint8)

    @staticmethod
    def decode_depth(levels: np.ndarray) -> np.ndarray:
        """z-depth in metres of the ``depth`` observation's levels (0 where no return)."""
        near, far = DEPTH_RANGE
        levels = np.asarray(levels, dtype=np.float64)
        return np.where(levels > 0, near + (levels - 1.0) / 254.0 * (far - near), 0.0)

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

    def _check_position(self, options: dict) -> None:
        """A ``position`` reset option must place its instrument (or, without an
        ``instrument`` option, every instrument) inside the tray at its ``yaw`` option or at
        some yaw; checked before the reset touches the env's state or generator."""
        names = [options["instrument"]] if "instrument" in options else self.instrument_names
        yaws = [options["yaw"]] if "yaw" in options else CHECKED_YAWS
        xy = np.asarray(options["position"], dtype=float)
        for name in names:
            if not any(self._worlds[name].fits_on_tray(xy, float(yaw)) for yaw in yaws):
                turned = f"at yaw {yaws[0]:.3f} rad" if "yaw" in options else "at any yaw"
                raise ValueError(
                    f"reset option position {xy.tolist()} does not put {name} inside the tray "
                    f"{turned} with {TRAY_MARGIN * 1000:.0f} mm to spare{self._tray_extent()}"
                )

    def _tray_extent(self) -> str:
        tray = self.world.tray
        low = np.asarray(tray.center) - np.asarray(tray.inner_half_size)
        high = np.asarray(tray.center) + np.asarray(tray.inner_half_size)
        return (
            f" (the tray's inside spans x {low[0]:.3f}-{high[0]:.3f} m, "
            f"y {low[1]:.3f}-{high[1]:.3f} m)"
        )

    def _apply_arm_action(self, arm_action: np.ndarray) -> tuple[list, list | None]:
        """Set the arm's servos for ``arm_action``: the pads the approach guard watches this
        step (see :meth:`GraspWorld.approach_directions`; none when it is off) and their leads at
        the set-point left (None where the set-point did not change)."""
        world = self.world
        if self.controller == "joint_delta":
            ctrl = world.arm_ctrl() + self.max_joint_delta * arm_action
            world.set_arm_ctrl(np.clip(ctrl, world.arm.lower, world.arm.upper))
            return [], None
        qpos = self._ee_set_point(arm_action)
        near, leads = [], None
        if self.approach_lead_limit is not None:
            near = world.approach_directions(self.approach_distance, min_gap=GUARD_MIN_GAP)
            if qpos is not None:
                qpos, leads = self._guard_approach(arm_action, qpos, near)
        if qpos is not None:
            world.set_arm_ctrl(qpos)
        return near, leads

    def _lead_limits(self, near) -> list[float]:
        """The lead (m) the approach guard allows each of the ``near`` pads."""
        return [self.approach_lead_limit + self.approach_lead_slope * gap for _, _, gap in near]

    def _guard_approach(
        self, arm_action: np.ndarray, qpos: np.ndarray, near
    ) -> tuple[np.ndarray | None, list | None]:
        """``qpos``, the set-point of ``arm_action``, or where it runs more than
        ``approach_lead_limit`` (plus ``approach_lead_slope`` times its gap) ahead of one of the
        ``near`` pads, the set-point of the same move shortened until it does not (to nothing:
        hold the pose); with the ``near`` pads' leads at it (None with the set-point)."""
        world = self.world
        limits = self._lead_limits(near)
        leads = world.pad_leads(near, qpos)
        if all(lead <= limit for lead, limit in zip(leads, limits, strict=True)):
            return qpos, leads
        self._guarded_steps += 1  # from here on the step is shortened or held
        held = self._ee_set_point(arm_action, scale=0.0)
        if held is None:
            return None, None
        held_leads = world.pad_leads(near, held)
        # Holding still leads a little (the set-point points the tool straight down, the
        # compliant arm tilts). A translation moves the pads rigidly, so each lead is linear in
        # the move's scale between holding and the step; a yaw bends that, so the scale is
        # refined from where each try lands. A move that leads less than holding is not cut.
        scale = 1.0
        for _ in range(GUARD_TRIES):
            shorter = scale
            for lead, held_lead, limit in zip(leads, held_leads, limits, strict=True):
                gain = lead - held_lead
                if lead > limit and gain > 0.0:
                    shorter = min(shorter, scale * max(0.0, limit - held_lead) / gain)
            if shorter == scale:
                break
            scale = shorter
            qpos = self._ee_set_point(arm_action, scale) if scale > 0.0 else held
            if qpos is None:
                return held, held_leads
            leads = world.pad_leads(near, qpos) if scale > 0.0 else held_leads
            if all(
                lead <= limit + GUARD_TOLERANCE for lead, limit in zip(leads, limits, strict=True)
            ):
                break
        return qpos, leads

    def _guard_fingers(self, near, arm_leads: list | None) -> None:
        """Shorten the servo target of each finger closing toward the instrument so that its
        pad, carried also by the arm's set-point (``arm_leads``, or None to measure them),
        leads no more than the approach guard allows."""
        world, gripper = self.world, self.world.gripper
        if arm_leads is None:
            arm_leads = world.pad_leads(near, world.arm_ctrl())
        closing = gripper.closing_directions()
        shortened = False
        for (pad, toward, _), arm_lead, limit in zip(
            near, arm_leads, self._lead_limits(near), strict=True
        ):
            finger = gripper.finger_of(pad)
            rate = float(closing[finger] @ toward)  # pad travel toward it per m of closing
            if rate > 0.0:
                spare = max(0.0, limit - arm_lead)
                shortened |= gripper.limit_closing(finger, spare / rate)
        self._guarded_finger_steps += shortened

    def _ee_set_point(self, arm_action: np.ndarray, scale: float = 1.0) -> np.ndarray | None:
        """The arm joint set-point an ``ee_delta`` action asks for, its move (after the
        workspace clip) times ``scale``, or None where it is refused."""
        world = self.world
        # Displacements are from the actual pose (not the last target), so a zero action holds
        # the arm where it is and pushing against the tray cannot wind its servos up.
        tcp = world.tcp_position()
        target = np.clip(
            tcp + self.max_translation * arm_action[:3],
            world.workspace_lower,
            world.workspace_upper,
        )
        yaw_change = self.max_yaw * arm_action[3]
        if scale != 1.0:
            start = np.clip(tcp, world.workspace_lower, world.workspace_upper)  # a zero action's
            target = start + scale * (target - start)
            yaw_change *= scale
        yaw = world.tcp_yaw() + yaw_change
        yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
        reference = world.arm_ctrl()
        qpos = world.arm.closed_form_nearest(target, tool_down(yaw), reference, site=TCP_SITE)
        # Near a joint limit the nearest solution can be another arm configuration (elbow or
        # wrist flipped), which a servo would swing to across the workspace: refused, as an
        # unreachable target is.
        if qpos is not None and np.abs(qpos - reference).max() <= MAX_SETPOINT_JUMP:
            return qpos
        return None

    def _observation(self) -> dict:
        world, gripper = self.world, self.world.gripper
        tcp = world.tcp_position()
        yaw = world.tcp_yaw()
        cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)
        # Lists of Python floats made into one float32 array each: concatenating 2- and
        # 3-vectors in numpy cost twice as much, every step.
        proprio = [
            *world.arm.qpos.tolist(),
            *world.arm.qvel.tolist(),
            *tcp.tolist(),
            cos_yaw,
            sin_yaw,
            gripper.opening(),
            self._gripper_command,  # the action's, which the approach guard may shorten
        ]
        obs = {
            "proprio": np.array(proprio, dtype=np.float32),
            "forces": gripper.fingertip_forces().astype(np.float32),
        }
        if self.obs_mode == "state":
            grasp_point, axis = world.grasp_point(), world.grasp_axis()
            # The same geometry relative to the tool, as a controller needs it: millimetre
            # offsets are small differences of the absolute positions, which a network
            # fed normalised absolute inputs resolves poorly.
            dx, dy, dz = (grasp_point - tcp).tolist()
            misalignment = 2.0 * (yaw - jaws_across(axis))  # the jaws: half-turn symmetric
            instrument = [
                *grasp_point.tolist(),
                *axis.tolist(),
                *world.instrument_velocity().tolist(),
                cos_yaw * dx + sin_yaw * dy,
                -sin_yaw * dx + cos_yaw * dy,
                dz,
                math.cos(misalignment),
                math.sin(misalignment),
            ]
            obs["instrument"] = np.array(instrument, dtype=np.float32)
        else:
            depth = world.camera(self.intrinsics, self._depth_backend).render(world.data)
            obs["depth"] = self.encode_depth(depth)[None]
        if self.obs_mode == "rgbd":
            obs["rgb"] = world.rgb(self.intrinsics).transpose(2, 0, 1).copy()
        return obs

    def _info(
        self,
        terms: dict,
        *,
        grasped: bool,
        step_peak: float,
        success: bool,
        lift: float,
        unstable: bool = False,
        broke_limit: bool = False,
    ) -> dict:
        world = self.world
        return {
            **terms,
            "is_success": bool(success),
            "grasped": bool(grasped),
            "peak_force": self._peak_force,
            "step_peak_force": step_peak,
            "grip_force": max(world.gripper.fingertip_forces().tolist()),
            "lift_height": float(lift),
            "force_violations": self._force_violations,
            "impact_violations": self._impact_violations,
            "guarded_steps": self._guarded_steps,
            "guarded_finger_steps": self._guarded_finger_steps,
            "instrument": world.name,
            "sim_unstable": unstable,
            "hard_limit_exceeded": bool(broke_limit),
        }


#: Counters of MjData's sleep state that its pickle (mujoco 4.0) does not restore, while it
#: does restore the per-tree arrays they summarise: a clone with a sleeping instrument would
#: stop with "mj_sleep: found sleeping tree 1 in island 0".
