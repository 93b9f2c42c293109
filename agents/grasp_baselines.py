"""Scripted grasping baselines for InstrumentGrasp-v0.

All expose SB3's ``predict(observation, state=None, episode_start=None, deterministic=True)
-> (action, state)`` for one env's observation, bare or as a batch of one (SB3's
``evaluate_policy`` works on them; :mod:`agents.scripted_policy`), so evaluation code treats
them like trained policies. They are built on the environment they act in (for its action scales,
camera intrinsics and the arm's kinematic model: what a real robot knows from calibration).

- :class:`ScriptedGrasp`: the seed pipeline. Needs ``obs_mode="rgbd"`` and the ``ee_delta``
  controller. It finds the red handle in the wrist RGB image (HSV threshold, morphology,
  largest contour, principal axis), lifts it to 3-D with the depth image, the intrinsics and
  the camera pose from forward kinematics, looks again from closer, turns the jaws across the
  handle, descends (stopping early if a pad touches anything), closes in small steps until
  both pads press with ``grip_force``, lifts and holds. It reads no privileged state.
- :class:`Squeeze`: the same, but it closes the gripper fully: the force term must bite.
- :class:`PrivilegedGrasp`: the same state machine reading the handle from the simulator
  instead of the images (the values of the privileged ``instrument`` observation), so it runs
  in every ``obs_mode``: the expert whose episodes seed SAC's replay buffer (see
  ``agents/demonstrations.py``).
- :class:`RandomGrasp`: uniform samples of the action space (seeded).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import cv2
import numpy as np

from agents.scripted_policy import RandomActions, ScriptedPolicy
from liuxing_envs.perception.pointcloud import camera_rays
from liuxing_envs.sim.gripper import MAX_OPENING

#: HSV band of the handles' red (OpenCV hue is 0-179 and red wraps round 0).
RED_HUE_BANDS = ((0, 10), (170, 179))
MIN_SATURATION, MIN_VALUE = 120, 70
#: Smallest handle blob (pixels) taken as a detection.
MIN_BLOB_PIXELS = 4
#: Slices of the blob along its axis (m) and the widest slice that is still handle (m):
#: handles are 10-15 mm across, finger rings about 45 mm.
SLICE_LENGTH = 0.005
MAX_HANDLE_WIDTH = 0.022
DEFAULT_GRIP_FORCE = 2.5  # N per pad: half the default force limit
#: Height of the wrist camera above the handle for the second, closer look (m).
CLOSE_LOOK_HEIGHT = 0.22
#: Height of the tool centre above the handle before the final descent (m).
PRE_GRASP_HEIGHT = 0.06
#: The fingertips are 4 mm below the tool centre; they grasp this far above the surface the
#: handle lies on (m), so the 16 mm pads straddle even a 4 mm thick handle.
FINGERTIP_BELOW_TCP = 0.004
FINGERTIP_CLEARANCE = 0.002
LIFT_HEIGHT = 0.13  # m above the grasp height: past the 0.10 m target with margin
#: A pad touching anything with this force (N) ends the descent.
TOUCH_FORCE = 0.3
#: Closing speed (m of opening per step): fast while the jaws are wider than CLOSE_SLOW_BELOW
#: (handles are at most 25 mm across), slower below, slowest once a pad touches. A pad servo pushes
#: about 2.5 N per mm the command runs ahead of it, so the slow step bounds the first squeeze
#: to about 4 N and the contact step adds about 1 N a step.
CLOSE_STEP_FREE = 0.004
CLOSE_STEP_NEAR = 0.0015
CLOSE_STEP_CONTACT = 0.0004
CLOSE_SLOW_BELOW = 0.032
#: The grip is loosened when a pad presses harder than grip_force by this much (N), and
#: tightened while either presses less than grip_force (closing) or 70% of it (holding).
GRIP_FORCE_BAND = 1.5
HOLD_FORCE_FRACTION = 0.7
SETTLE_STEPS = 2
FORCE_COMMAND_FIRM = 0.9
POSITION_TOLERANCE = 0.004  # m
YAW_TOLERANCE = 0.03  # rad
DESCENT_SPEED = 0.5  # fraction of the env's max translation per step
LOOK_TIMEOUT_STEPS = 15
#: Where the wrist camera goes to look again when the first image shows no handle (m): 30 cm
#: above the tray's two halves (the workcell's layout, which a deployed robot knows).
SEARCH_CAMERA_POSITIONS = np.array([[0.5, -0.06, 0.31], [0.5, 0.08, 0.31]])


@dataclass(frozen=True)
class HandleDetection:
    """A handle seen in one image, in the world frame (m): where to grasp it (the middle of
    the longest stretch of the blob no wider than MAX_HANDLE_WIDTH, so finger rings are
    skipped), its axis (unit, horizontal), the height of the surface it lies on, and the
    blob's size in pixels."""

    point: np.ndarray
    axis: np.ndarray
    floor_z: float
    pixels: int


def red_mask(rgb: np.ndarray) -> np.ndarray:
    """Binary mask (uint8 0/255) of red pixels of an (H, W, 3) RGB image, with gaps from
    highlights filled by a morphological close. (No opening: at 64 x 64 a handle can be a
    single pixel wide; stray pixels are left to the largest-contour step.)"""
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2HSV)
    mask = np.zeros(hsv.shape[:2], dtype=np.uint8)
    for low, high in RED_HUE_BANDS:
        mask |= cv2.inRange(hsv, (low, MIN_SATURATION, MIN_VALUE), (high, 255, 255))
    # A symmetric (odd) kernel: even ones shift the mask by a pixel.
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))


def detect_handle(
    rgb: np.ndarray,
    depth_m: np.ndarray,
    intrinsics,
    camera_position: np.ndarray,
    camera_rotation: np.ndarray,
) -> HandleDetection | None:
    """The largest red blob of ``rgb`` as a 3-D handle, or None if there is none.

    ``depth_m`` is the z-depth image in metres (0 = no return); the blob's pixels are
    back-projected with it and the camera pose, and the axis is the principal direction of
    the resulting points in the horizontal plane.
    """
    mask = red_mask(rgb)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    largest = max(contours, key=cv2.contourArea)
    blob = np.zeros_like(mask)
    cv2.drawContours(blob, [largest], -1, 255, thickness=cv2.FILLED)
    pixels = (blob > 0) & (mask > 0) & (depth_m > 0)
    if pixels.sum() < MIN_BLOB_PIXELS:
        return None
    rays = camera_rays(intrinsics, "z")

    def to_world(selected: np.ndarray) -> np.ndarray:
        return (rays[selected] * depth_m[selected][:, None]) @ camera_rotation.T + camera_position

    points = to_world(pixels)
    centre = points[:, :2].mean(axis=0)
    _, _, axes = np.linalg.svd(points[:, :2] - centre, full_matrices=False)
    axis, across = axes[0], np.array([-axes[0, 1], axes[0, 0]])
    along = (points[:, :2] - centre) @ axis
    side = (points[:, :2] - centre) @ across
    # Width of the blob in slices across its axis; grasp in the longest narrow run.
    slices = np.floor((along - along.min()) / SLICE_LENGTH).astype(int)
    count = slices.max() + 1
    widest = np.full(count, -np.inf)
    narrowest = np.full(count, np.inf)
    np.maximum.at(widest, slices, side)
    np.minimum.at(narrowest, slices, side)
    narrow = (widest - narrowest) <= MAX_HANDLE_WIDTH
    run_start, best = 0, (0, 0)
    for index in range(count + 1):
        if index == count or not narrow[index]:
            if index - run_start > best[1] - best[0]:
                best = (run_start, index)
            run_start = index + 1
    if best[1] == best[0]:
        return None
    in_run = (slices >= best[0]) & (slices < best[1])
    grasp_xy = centre + axis * along[in_run].mean() + across * side[in_run].mean()
    # The surface round the blob (not red, a few pixels out) gives the height it lies on.
    ring = cv2.dilate(blob, np.ones((3, 3), np.uint8), iterations=2)
    surround = (ring > 0) & (mask == 0) & (depth_m > 0)
    floor_z = float(np.median(to_world(surround)[:, 2])) if surround.any() else points[:, 2].min()
    top_z = float(np.percentile(points[:, 2], 75))
    return HandleDetection(
        point=np.array([*grasp_xy, top_z]),
        axis=np.array([axis[0], axis[1], 0.0]),
        floor_z=floor_z,
        pixels=int(pixels.sum()),
    )


class Phase(enum.IntEnum):
    LOOK = 0
    CLOSE_LOOK = 1
    PRE_GRASP = 2
    DESCEND = 3
    CLOSE = 4
    LIFT = 5


class ScriptedGrasp(ScriptedPolicy):
    """Detect the red handle, approach aligned with it, close to a gentle force, lift, hold."""

    squeeze = False
    #: The env kwargs it needs: it reads the colour image and moves the tool centre.
    ENV_KWARGS = {"obs_mode": "rgbd", "controller": "ee_delta"}

    def __init__(self, env, grip_force: float = DEFAULT_GRIP_FORCE) -> None:
        env = env.unwrapped
        if any(getattr(env, key) != value for key, value in self.ENV_KWARGS.items()):
            raise ValueError(
                f"{type(self).__name__} needs {self.ENV_KWARGS}, got "
                f"obs_mode={env.obs_mode!r}, controller={env.controller!r}"
            )
        if not 0.0 < grip_force:
            raise ValueError(f"grip_force must be > 0 N, got {grip_force}")
        super().__init__(env)
        self.grip_force = float(grip_force)
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        self._episode_seen: int | None = None
        self.phase = Phase.LOOK
        self.detection: HandleDetection | None = None
        self.target_yaw = 0.0
        self.grasp_z = 0.0
        self.lift_target = np.zeros(3)
        self.opening_command = MAX_OPENING
        self._steps_in_phase = 0
        self._settled = 0
        self._search_index = 0

    # -------------------------------------------------------------------------------------
    def act(self, observation):
        # A plain Gymnasium loop calls no reset() between episodes: the env counts them. (A
        # policy acting in another env than its own sees no count change: reset() it.)
        started = self.env.episodes_started
        if self._episode_seen is not None and started != self._episode_seen:
            self.reset()
        self._episode_seen = started
        proprio = np.asarray(observation["proprio"], dtype=np.float64)
        forces = np.asarray(observation["forces"], dtype=np.float64)
        tcp, yaw = proprio[12:15], math.atan2(proprio[16], proprio[15])
        opening = proprio[17]
        if self.phase == Phase.LOOK and self._steps_in_phase == 0:
            self.opening_command = opening
        self._steps_in_phase += 1
        target, target_yaw = tcp.copy(), yaw
        speed = 1.0

        if self.phase == Phase.LOOK:
            # Look from where the arm is; if nothing is seen, from each search pose in turn.
            search = self._search_index
            camera = self.env.wrist_camera_pose(proprio[:6])[0]
            if search > 0:
                target = tcp + (SEARCH_CAMERA_POSITIONS[search - 1] - camera)
            if search == 0 or np.linalg.norm(target - tcp) < POSITION_TOLERANCE:
                self.detection = self._detect(observation)
                if self.detection is not None:
                    self._enter(Phase.CLOSE_LOOK)
                else:
                    self._search_index = (search + 1) % (len(SEARCH_CAMERA_POSITIONS) + 1)
        if self.phase == Phase.CLOSE_LOOK:
            # Hover with the camera straight above the far detection, then look again.
            camera_offset = self.env.wrist_camera_pose(proprio[:6])[0] - tcp
            target = self.detection.point.copy()
            target[:2] -= camera_offset[:2]
            target[2] += CLOSE_LOOK_HEIGHT - camera_offset[2]
            arrived = np.linalg.norm(target - tcp) < POSITION_TOLERANCE
            if arrived or self._steps_in_phase > LOOK_TIMEOUT_STEPS:
                closer = self._detect(observation) if arrived else None
                if closer is not None:
                    self.detection = closer
                self.target_yaw = _nearest_equivalent_yaw(
                    math.atan2(self.detection.axis[1], self.detection.axis[0]), yaw
                )
                self._enter(Phase.PRE_GRASP)
        if self.phase == Phase.PRE_GRASP:
            target = self.detection.point + [0.0, 0.0, PRE_GRASP_HEIGHT]
            target_yaw = self.target_yaw
            self.grasp_z = self.detection.floor_z + FINGERTIP_BELOW_TCP + FINGERTIP_CLEARANCE
            aligned = abs(_wrap(target_yaw - yaw)) < YAW_TOLERANCE
            if np.linalg.norm(target - tcp) < POSITION_TOLERANCE and aligned:
                self._enter(Phase.DESCEND)
        if self.phase == Phase.DESCEND:
            target = np.array([*self.detection.point[:2], self.grasp_z])
            target_yaw, speed = self.target_yaw, DESCENT_SPEED
            touched = forces.max() >= TOUCH_FORCE
            if touched or tcp[2] - self.grasp_z < POSITION_TOLERANCE / 2:
                target = tcp if touched else target
                self._enter(Phase.CLOSE)
        if self.phase == Phase.CLOSE:
            target, target_yaw = tcp, yaw
            if self.squeeze:
                self.opening_command = 0.0
            else:
                self._regulate_grip(forces, opening, self.grip_force)
            firm = forces.min() > 0 if self.squeeze else forces.min() >= self._firm_force()
            self._settled = self._settled + 1 if firm else 0
            if self._settled >= SETTLE_STEPS:
                self.lift_target = tcp + [0.0, 0.0, LIFT_HEIGHT]
                self._enter(Phase.LIFT)
        if self.phase == Phase.LIFT:
            target, target_yaw = self.lift_target, yaw
            if not self.squeeze:
                self._regulate_grip(forces, opening, HOLD_FORCE_FRACTION * self.grip_force)

        commanded_opening = proprio[18]
        return self._action(tcp, yaw, target, target_yaw, speed, commanded_opening)

    # -------------------------------------------------------------------------------------
    def _regulate_grip(self, forces: np.ndarray, opening: float, least_force: float) -> None:
        """Step the opening command to keep both pad forces in [least_force, grip_force +
        GRIP_FORCE_BAND]."""
        if forces.max() > self.grip_force + GRIP_FORCE_BAND:
            self.opening_command = min(MAX_OPENING, self.opening_command + CLOSE_STEP_CONTACT)
        elif forces.min() < least_force:
            if forces.max() >= TOUCH_FORCE:
                step = CLOSE_STEP_CONTACT
            elif opening > CLOSE_SLOW_BELOW:
                step = CLOSE_STEP_FREE
            else:
                step = CLOSE_STEP_NEAR
            self.opening_command = max(0.0, min(self.opening_command, opening) - step)

    def _enter(self, phase: Phase) -> None:
        self.phase = phase
        self._steps_in_phase = 0

    def _detect(self, observation) -> HandleDetection | None:
        env = self.env
        rgb = np.asarray(observation["rgb"]).transpose(1, 2, 0)
        depth = env.decode_depth(observation["depth"][0])
        position, rotation = env.wrist_camera_pose(np.asarray(observation["proprio"][:6]))
        return detect_handle(rgb, depth, env.intrinsics, position, rotation)

    def _action(self, tcp, yaw, target, target_yaw, speed, commanded_opening) -> np.ndarray:
        env = self.env
        move = np.clip((target - tcp) / env.max_translation, -speed, speed)
        turn = np.clip(_wrap(target_yaw - yaw) / env.max_yaw, -1.0, 1.0) if env.max_yaw else 0.0
        if env.gripper_control == "delta":
            change = (self.opening_command - commanded_opening) / env.max_gripper_delta
            grip = np.clip(change, -1.0, 1.0)
        elif env.gripper_control == "force":
            grip = self._grip_force_action()
        else:
            grip = 2.0 * self.opening_command / MAX_OPENING - 1.0
        return np.array([*move, turn, grip], dtype=np.float32)

    def _firm_force(self) -> float:
        """The pad force at which the close is done; a force command is met exactly, give
        or take the solver's last digits, so under force commands a little less."""
        force_commands = self.env.gripper_control == "force"
        return self.grip_force * (FORCE_COMMAND_FIRM if force_commands else 1.0)

    def _grip_force_action(self) -> float:
        """The gripper action under force commands: open with the most force until the
        close, then grip with grip_force (HOLD_FORCE_FRACTION of it while lifting); the
        squeeze closes with the most force."""
        if self.phase not in (Phase.CLOSE, Phase.LIFT):
            return -1.0
        if self.squeeze:
            return 1.0
        force = self.grip_force * (HOLD_FORCE_FRACTION if self.phase == Phase.LIFT else 1.0)
        return min(1.0, force / self.env.max_grip_force)


class Squeeze(ScriptedGrasp):
    """ScriptedGrasp that closes the gripper all the way: it lifts, but crushes the handle."""

    squeeze = True


class PrivilegedGrasp(ScriptedGrasp):
    """ScriptedGrasp that knows where the handle is: the grasp point and axis read from the
    simulator, the surface under it from the workcell's tray. It reads them as float32, the
    values of the ``state`` observation's ``instrument`` entry, so it acts the same in every
    ``obs_mode`` (a privileged teacher for a depth-only student)."""

    ENV_KWARGS = {"controller": "ee_delta"}

    def _detect(self, observation) -> HandleDetection:
        world = self.env.world
        point = world.grasp_point().astype(np.float32).astype(np.float64)
        axis = world.grasp_axis().astype(np.float32).astype(np.float64)
        axis[2] = 0.0
        return HandleDetection(
            point=point,
            axis=axis / max(np.linalg.norm(axis), 1e-9),
            floor_z=world.tray.floor_z,
            pixels=0,
        )


class RandomGrasp(RandomActions):
    """Uniform random actions, seeded."""


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def _nearest_equivalent_yaw(handle_yaw: float, yaw: float) -> float:
    """The jaws close along the tool's y axis, which is across the handle when the tool yaw
    equals the handle's angle; the gripper is symmetric, so any half turn of it will do."""
    return yaw + _wrap(2 * (handle_yaw - yaw)) / 2


GRASP_BASELINES = {
    "scripted-grasp": ScriptedGrasp,
    "squeeze": Squeeze,
    "privileged-grasp": PrivilegedGrasp,
    "random": RandomGrasp,
}
