"""InstrumentGrasp's settings: one frozen part per part of the env, every default in its knob.

The dataclass defaults are ``V1``, the benchmark task (``InstrumentGrasp-v1``: the task of the
shipped grasp policy); ``V0`` holds the deprecated ``InstrumentGrasp-v0``'s defaults. Import-light:
no MuJoCo here, so the constants the checks need from the simulation are named below and a test
keeps them equal to the simulation's.
"""

from __future__ import annotations

import dataclasses
import math

from liuxing_envs.settings import Part, Settings, knob, part
from liuxing_envs.validation import require_choice, require_int, require_number, require_range

OBS_MODES = ("state", "depth", "rgbd")
CONTROLLERS = ("ee_delta", "joint_delta")
GRIPPER_CONTROLS = ("opening", "delta", "force")
#: The instrument sets by name (``liuxing_envs.sim.instruments.INSTRUMENT_SETS``).
INSTRUMENT_SETS = {
    "train": ("scalpel", "tissue_forceps", "scissors", "hemostat", "retractor"),
    "held_out": ("needle_holder", "probe"),
    "all": (
        "scalpel", "tissue_forceps", "scissors", "hemostat", "needle_holder", "probe", "retractor",
    ),
}  # fmt: skip
#: ``liuxing_envs.sim.camera.BACKENDS``.
DEPTH_BACKENDS = ("auto", "gl", "raycast", "multiray", "embree")
#: The simulated gripper's (``liuxing_envs.sim.gripper``): both fingers' full opening (m), the
#: finger servos' force range (N) and a force-commanded finger's damping (N s/m).
MAX_OPENING = 0.08
SERVO_FORCE_LIMIT = 40.0
FORCE_COMMAND_DAMPING = 40.0
#: The smallest ``max_gripper_delta`` (m) and ``max_grip_force`` (N) taken.
MIN_GRIPPER_DELTA = 1e-4
MIN_GRIP_FORCE = 0.1
#: At 1 the set-point may reach the instrument's surface: no braking at all.
MAX_APPROACH_LEAD_SLOPE = 1.0
#: The approach guard off: every setting of it, as the messages that need it off name them.
GUARD_OFF = (
    "approach_lead_limit=None, approach_lead_slope=0.0, approach_guard_fingers=False (as "
    "InstrumentGraspUnguarded-v1 does)"
)
#: The end of a message refusing part of the guard without approach_lead_limit, which turns it on.
GUARD_ON_OR_OFF = (
    "(the lead allowed at a touch, m; controller='ee_delta' only), or turn the whole guard off "
    f"with {GUARD_OFF}"
)
#: Allowed factors of mass_range and friction_range.
SCALE_LIMITS = (0.1, 10.0)


@dataclasses.dataclass(frozen=True)
class ArmControl(Part):
    """The arm's controller and its joint servos."""

    controller: str = knob(
        "ee_delta",
        "'ee_delta': the action moves the tool centre (x, y, z) and its yaw; 'joint_delta': "
        "it moves the six arm joints' set-points (with the approach guard off).",
    )
    max_translation: float = knob(
        0.01, "Tool-centre move per step at a full action (+-1), per axis.", unit="m",
        only_with={"controller": ("ee_delta",)},
    )  # fmt: skip
    max_yaw: float = knob(
        0.1, "Tool yaw change per step at a full action (+-1).", unit="rad",
        only_with={"controller": ("ee_delta",)},
    )  # fmt: skip
    max_joint_delta: float = knob(
        0.05, "Joint set-point change per step at a full action (+-1).", unit="rad",
        only_with={"controller": ("joint_delta",)},
    )  # fmt: skip
    arm_stiffness: float = knob(
        0.1,
        "Factor on the joint servos' stiffness (1: a stiff position-controlled arm; 0.1: a "
        "cobot's compliance mode); their damping follows its square root.",
    )
    servo_damping_ratio: float | None = knob(
        0.7,
        "Every arm joint servo's damping ratio at the ready pose (None: the model's, "
        "MuJoCo's dampratio=1 computed with the arm stretched out flat).",
    )

    def check(self) -> None:
        require_choice("controller", self.controller, CONTROLLERS)
        require_number("max_translation", self.max_translation, 1e-4, 0.1)
        require_number("max_yaw", self.max_yaw, 0.0, 1.0)
        require_number("max_joint_delta", self.max_joint_delta, 1e-4, 0.5)
        require_number("arm_stiffness", self.arm_stiffness, 0.01, 1.0)
        if self.servo_damping_ratio is not None:
            require_number("servo_damping_ratio", self.servo_damping_ratio, 0.1, 10.0)


@dataclasses.dataclass(frozen=True)
class ControlTiming(Part):
    """The control rate and the physics step under it."""

    control_hz: float = knob(20.0, "Control steps per second.", unit="Hz")
    timestep: float = knob(0.002, "Physics step; 1 / control_hz must be a whole number of them.",
                           unit="s")  # fmt: skip

    def check(self) -> None:
        require_number("control_hz", self.control_hz, 1.0, 500.0)
        require_number("timestep", self.timestep, 1e-4, 0.01)
        if self.substeps < 1 or not math.isclose(
            self.substeps * self.timestep * self.control_hz, 1.0, rel_tol=1e-6
        ):
            raise ValueError(
                f"1 / control_hz must be a whole number of timesteps; got control_hz="
                f"{self.control_hz}, timestep={self.timestep}"
            )

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return round(1.0 / (self.control_hz * self.timestep))


@dataclasses.dataclass(frozen=True)
class GripperControl(Part):
    """How the action's last entry drives the fingers."""

    gripper_control: str = knob(
        "force",
        "'opening': the pad opening to servo to (0 m at -1 to 0.08 m at +1); 'delta': the "
        "change of the commanded opening; 'force': the grip force, each finger servoing closed "
        "(> 0) or open (< 0) with at most the action's magnitude x max_grip_force.",
    )
    max_gripper_delta: float = knob(
        0.004, "Commanded-opening change per step at a full action (+-1).", unit="m",
        only_with={"gripper_control": ("delta",)},
    )  # fmt: skip
    max_grip_force: float = knob(
        3.0, "Grip force per finger at a full action (+-1).", unit="N",
        only_with={"gripper_control": ("force",)},
    )  # fmt: skip

    def check(self) -> None:
        require_choice("gripper_control", self.gripper_control, GRIPPER_CONTROLS)
        require_number("max_gripper_delta", self.max_gripper_delta, MIN_GRIPPER_DELTA, MAX_OPENING)
        require_number("max_grip_force", self.max_grip_force, MIN_GRIP_FORCE, SERVO_FORCE_LIMIT)

    def closing_per_step(self, control_hz: float) -> tuple[str, float, str, float, float, str]:
        """How far (m) a finger may close in one control step, as (the knob that sets it, its
        value, its unit, its smallest value, metres a step per unit, how the travel follows)."""
        if self.gripper_control == "force":
            return (
                "max_grip_force", self.max_grip_force, "N", MIN_GRIP_FORCE,
                1.0 / (FORCE_COMMAND_DAMPING * control_hz),  # m a step per N
                f"max_grip_force / {FORCE_COMMAND_DAMPING:g} N s/m / control_hz",
            )  # fmt: skip
        return (
            "max_gripper_delta", self.max_gripper_delta, "m", MIN_GRIPPER_DELTA,
            0.5,  # the opening is both fingers' travel
            "max_gripper_delta / 2",
        )  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Safety(Part):
    """The force limits, the protective stop and the guarded approach."""

    force_limit: float = knob(5.0, "Fingertip force a gentle grasp stays under.", unit="N")
    hard_limit_factor: float = knob(
        3.0,
        "A pad force above this times force_limit, or an impact above this times "
        "impact_limit, triggers the protective stop.",
    )
    impact_limit: float = knob(
        10.0, "Contact force on the instrument from anything but the pads.", unit="N"
    )
    approach_distance: float = knob(
        0.015, "Pad-to-instrument gap within which the approach guard and penalty watch a pad.",
        unit="m",
    )  # fmt: skip
    approach_lead_limit: float | None = knob(
        0.00025,
        "With ee_delta: how far the arm's set-point may lead a pad toward the instrument "
        "within approach_distance (None: no guard).",
        unit="m",
    )
    approach_lead_slope: float = knob(
        0.3, "Extra lead allowed per metre of the pad's gap: a braking ramp (0 to 1).", unit="m/m"
    )
    approach_guard_fingers: bool = knob(
        True, "Whether the guard also shortens a closing finger's servo target."
    )

    def check(self) -> None:
        require_number("force_limit", self.force_limit, 0.1, 100.0)
        require_number("hard_limit_factor", self.hard_limit_factor, 1.0, 100.0)
        require_number("impact_limit", self.impact_limit, 0.1, 1000.0)
        require_number("approach_distance", self.approach_distance, 0.0, 0.1)
        require_number(
            "approach_lead_slope", self.approach_lead_slope, 0.0, MAX_APPROACH_LEAD_SLOPE
        )
        if self.approach_lead_limit is not None:
            require_number("approach_lead_limit", self.approach_lead_limit, 0.0, 0.1)
        elif self.approach_lead_slope:
            raise ValueError(
                f"approach_lead_slope={self.approach_lead_slope} raises approach_lead_limit "
                f"with a pad's gap; set approach_lead_limit too {GUARD_ON_OR_OFF}"
            )
        require_choice("approach_guard_fingers", self.approach_guard_fingers, (False, True))
        if self.approach_guard_fingers and self.approach_lead_limit is None:
            raise ValueError(
                "approach_guard_fingers=True widens the approach guard, which "
                f"approach_lead_limit turns on; set approach_lead_limit too {GUARD_ON_OR_OFF}"
            )

    @property
    def hard_limit(self) -> float:
        """The pad force (N) that triggers the protective stop."""
        return self.force_limit * self.hard_limit_factor

    @property
    def hard_impact_limit(self) -> float:
        """The impact (N) that triggers the protective stop."""
        return self.impact_limit * self.hard_limit_factor

    @property
    def lead_allowed_at_entry(self) -> float:
        """The lead (m) the guard allows a pad where it starts watching it."""
        return self.approach_lead_limit + self.approach_lead_slope * self.approach_distance


@dataclasses.dataclass(frozen=True)
class GraspTask(Part):
    """The reward terms, success and the episode's length."""

    target_height: float = knob(0.10, "Lift that counts, above where the grasp point lay.",
                                unit="m")  # fmt: skip
    hold_time: float = knob(1.0, "Time to hold the instrument at target_height.", unit="s")
    reach_sharpness: float = knob(
        3.0, "Steepness of the reach term 1 - tanh(reach_sharpness x distance).", unit="1/m"
    )
    force_penalty: float = knob(2.0, "Reward per newton a pad's peak is over force_limit.")
    impact_penalty: float = knob(0.05, "Reward per newton the impact is over impact_limit.")
    failure_penalty: float = knob(50.0, "Reward of a protective stop.")
    approach_penalty: float = knob(
        0.0, "Reward per metre the set-point moves a near pad beyond approach_allowance (0: off)."
    )
    approach_allowance: float = knob(
        0.003, "Set-point move toward the instrument per step that approach_penalty lets pass.",
        unit="m",
    )  # fmt: skip
    terminate_on_success: bool = knob(
        False, "Whether success ends the episode (paying what holding on would have)."
    )
    episode_steps: int = knob(200, "Control steps in an episode.")

    def check(self) -> None:
        require_number("target_height", self.target_height, 0.01, 0.2)
        require_number("hold_time", self.hold_time, 0.0, 10.0)
        require_number("reach_sharpness", self.reach_sharpness, 0.1, 100.0)
        require_number("force_penalty", self.force_penalty, 0.0, 100.0)
        require_number("impact_penalty", self.impact_penalty, 0.0, 100.0)
        require_number("failure_penalty", self.failure_penalty, 0.0, 1000.0)
        require_number("approach_penalty", self.approach_penalty, 0.0, 1e5)
        require_number("approach_allowance", self.approach_allowance, 0.0, 0.1)
        require_choice("terminate_on_success", self.terminate_on_success, (False, True))
        require_int("episode_steps", self.episode_steps, 1, 100_000)


@dataclasses.dataclass(frozen=True)
class GraspScene(Part):
    """Which instruments, and how their mass and friction vary."""

    instrument_set: str = knob(
        "train",
        "The instruments drawn from: 'train' (scalpel, tissue_forceps, scissors, hemostat, "
        "retractor), 'held_out' (needle_holder, probe) or 'all'.",
    )
    instruments: tuple[str, ...] | None = knob(
        None, "The instruments drawn from, by name, instead of instrument_set."
    )
    mass_range: tuple[float, float] | None = knob(
        None, "Range of the factor on the instrument's mass, drawn each episode (None: 1)."
    )
    friction_range: tuple[float, float] | None = knob(
        None,
        "Range of the factor on the friction of every contact the instrument makes, drawn each "
        "episode (None: 1).",
    )

    def check(self) -> None:
        require_choice("instrument_set", self.instrument_set, tuple(INSTRUMENT_SETS))
        if self.instruments is not None:
            object.__setattr__(self, "instruments", _instrument_names(self.instruments))
        for name in ("mass_range", "friction_range"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, require_range(name, value, *SCALE_LIMITS))

    @property
    def names(self) -> tuple[str, ...]:
        """The instruments an episode draws from."""
        return self.instruments or INSTRUMENT_SETS[self.instrument_set]


def _instrument_names(instruments) -> tuple[str, ...]:
    expected = f"instruments must be a non-empty list of names from {INSTRUMENT_SETS['all']}"
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
    return names


#: The observation modes with wrist images.
IMAGES = {"obs_mode": ("depth", "rgbd")}


@dataclasses.dataclass(frozen=True)
class GraspSensors(Part):
    """What the policy observes."""

    obs_mode: str = knob(
        "state",
        "'state': proprioception, pad forces and the PRIVILEGED instrument pose; 'depth': "
        "the wrist depth image instead of the pose; 'rgbd': depth and colour.",
    )
    resolution: int = knob(64, "Side of the square wrist images.", unit="px", only_with=IMAGES)
    depth_backend: str = knob(
        "raycast",
        "How depth is rendered: 'raycast' (the same image on every machine), 'multiray' "
        "(the same image from MuJoCo's mj_multiRay), 'gl', 'embree' or 'auto'.",
        only_with=IMAGES,
    )

    def check(self) -> None:
        require_choice("obs_mode", self.obs_mode, OBS_MODES)
        require_choice("depth_backend", self.depth_backend, DEPTH_BACKENDS)
        require_int("resolution", self.resolution, 8, 512)


@dataclasses.dataclass(frozen=True)
class InstrumentGraspSettings(Settings):
    """Every setting of InstrumentGrasp, part by part."""

    extra_keywords = ("render_mode",)

    sensors: GraspSensors = part(GraspSensors)
    arm: ArmControl = part(ArmControl)
    gripper: GripperControl = part(GripperControl)
    timing: ControlTiming = part(ControlTiming)
    scene: GraspScene = part(GraspScene)
    safety: Safety = part(Safety)
    task: GraspTask = part(GraspTask)

    def check(self) -> None:
        if self.safety.approach_lead_limit is not None and self.arm.controller != "ee_delta":
            raise ValueError(
                "approach_lead_limit slows ee_delta steps; with controller='joint_delta' it must "
                f"be None, and the rest of the approach guard off with it: {GUARD_OFF}"
            )
        if self.safety.approach_guard_fingers:
            self._require_guardable_fingers()

    def _require_guardable_fingers(self) -> None:
        """Refuse a finger guard that a closing finger can outrun. The guard watches a pad from
        ``approach_distance`` of the instrument in; a finger that closes farther in one control
        step than the ramp allows there enters that band too fast to be braked, or crosses it
        within the step, and lands as hard as unguarded."""
        gripper_control = self.gripper.gripper_control
        if gripper_control == "opening":
            raise ValueError(
                "approach_guard_fingers=True cannot brake gripper_control='opening': its "
                "position servos close the whole stroke within one control step (up to about "
                "2 m/s); use gripper_control='force' or 'delta', or leave the fingers unguarded "
                "with approach_guard_fingers=False (the arm's guard stays on)"
            )
        allowance = self.safety.lead_allowed_at_entry
        name, value, unit, minimum, per_unit, travel_of = self.gripper.closing_per_step(
            self.timing.control_hz
        )
        travel = value * per_unit
        if travel <= allowance:
            return
        fits = allowance / per_unit
        remedies = [f"lower {name} to at most {fits:.3g} {unit}"] if fits >= minimum else []
        remedies.append("raise approach_lead_limit or approach_lead_slope")
        raise ValueError(
            "approach_guard_fingers=True needs fingers that close no farther in one control "
            "step than the guard allows where it starts watching a pad (approach_lead_limit + "
            f"approach_lead_slope x approach_distance = {1e3 * allowance:.2f} mm); "
            f"with gripper_control={gripper_control!r} a finger closes {travel_of} = "
            f"{1e3 * travel:.2f} mm a step: {', or '.join(remedies)}"
        )


#: ``InstrumentGrasp-v1``: the task of the shipped grasp policy
#: (``policies/InstrumentGrasp-v1/sac/config.yml``), depth ray-cast on every machine.
V1 = InstrumentGraspSettings()
#: ``InstrumentGrasp-v0`` (deprecated): a stiff arm with the model's servo damping, the
#: gripper servoing to an opening, gentler penalties, no guard.
V0 = V1.replaced(
    reach_sharpness=10.0,
    gripper_control="opening",
    max_grip_force=20.0,
    arm_stiffness=1.0,
    max_translation=0.02,
    max_yaw=0.2,
    servo_damping_ratio=None,
    force_penalty=0.2,
    failure_penalty=5.0,
    approach_lead_limit=None,
    approach_lead_slope=0.0,
    approach_guard_fingers=False,
    depth_backend="auto",
)
