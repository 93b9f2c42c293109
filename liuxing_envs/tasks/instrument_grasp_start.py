"""Where an InstrumentGrasp episode starts: its reset options, checked before the reset
touches anything, and the instrument's draw and placement on the tray."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from liuxing_envs.sim.grasp_world import TRAY_MARGIN
from liuxing_envs.sim.gripper import MAX_OPENING
from liuxing_envs.validation import (
    checked_reset_options,
    finite_vector,
    option_angle,
    option_in,
    option_xy,
    require_number,
)

if TYPE_CHECKING:
    from liuxing_envs.envs.instrument_grasp_settings import GraspScene
    from liuxing_envs.sim.grasp_world import GraspWorld

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


@dataclass(frozen=True)
class Start:
    """An episode's start: the instrument, its grasp point (x, y) and yaw on the tray, the
    factors on its mass and friction, and the tool's start (None: the ready pose)."""

    instrument: str
    xy: np.ndarray
    yaw: float
    mass_scale: float
    friction_scale: float
    tool_start: np.ndarray | None
    tool_yaw_error: float
    jaw_clearance: float | None


class StartDraw:
    """Draws episode starts for the worlds of an env's instruments."""

    def __init__(self, worlds: dict[str, GraspWorld]) -> None:
        self.worlds = worlds
        self.names = tuple(worlds)

    def checked_options(self, options) -> dict:
        """``reset``'s options, each checked by name; a ``position`` must put its instrument
        (or, without an ``instrument`` option, every instrument) inside the tray at its
        ``yaw`` option or at some yaw. Raises before the reset touches anything."""
        options = checked_reset_options(
            options,
            {
                "instrument": option_in(self.names),
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
            names = [options["instrument"]] if "instrument" in options else self.names
            yaws = [options["yaw"]] if "yaw" in options else CHECKED_YAWS
            xy = np.asarray(options["position"], dtype=float)
            for name in names:
                world = self.worlds[name]
                if not any(world.fits_on_tray(xy, float(yaw)) for yaw in yaws):
                    turned = f"at yaw {yaws[0]:.3f} rad" if "yaw" in options else "at any yaw"
                    raise ValueError(
                        f"reset option position {xy.tolist()} does not put {name} inside the "
                        f"tray {turned} with {TRAY_MARGIN * 1000:.0f} mm to spare"
                        f"{tray_extent(world)}"
                    )
        return options

    def draw(self, options: dict, rng: np.random.Generator, scene: GraspScene) -> Start:
        """A start from checked ``options`` and ``rng``, drawn where the options leave it."""
        name = options.get("instrument", self.names[rng.integers(len(self.names))])
        world = self.worlds[name]
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
                    f"{tray_extent(world)}"
                )
            yaw = float(fitting[rng.integers(len(fitting))])
        mass_scale = rng.uniform(*scene.mass_range) if scene.mass_range else 1.0
        friction_scale = rng.uniform(*scene.friction_range) if scene.friction_range else 1.0
        return Start(
            name,
            xy,
            yaw,
            mass_scale,
            friction_scale,
            options.get("tool_start"),
            options.get("tool_yaw_error", 0.0),
            options.get("jaw_clearance"),
        )


def tray_extent(world: GraspWorld) -> str:
    """The tray's inside, for messages."""
    tray = world.tray
    low = np.asarray(tray.center) - np.asarray(tray.inner_half_size)
    high = np.asarray(tray.center) + np.asarray(tray.inner_half_size)
    return (
        f" (the tray's inside spans x {low[0]:.3f}-{high[0]:.3f} m, y {low[1]:.3f}-{high[1]:.3f} m)"
    )
