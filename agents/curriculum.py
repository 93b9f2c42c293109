"""Start-state curriculum for InstrumentGrasp-v0: some training episodes begin near the handle.

Every episode of InstrumentGrasp-v0 begins with the tool 30 cm above the tray. A learner
finds the handle from there (the reach term leads it), but the grasp itself is millimetre
work: lower the open jaws across a 10 mm handle to within millimetres of the tray without
striking the instrument, close, lift. Without help PPO and SAC learned to hover 25-34 mm above
the handle and never grasped (README, "Training"): the rewards of a grasp lie beyond a
descent that they had no reason to try.

This wrapper starts a fraction of the *training* episodes with the tool at the handle
instead, using the env's ``tool_start`` and ``tool_yaw_error`` reset options: the tool centre
``height`` above the grasp point (uniform in a range; at 0 the open jaws are around the
handle, the fingertips just above the tray), shifted by up to ``jitter`` in x and y, turned
by up to ``yaw_jitter`` from across the handle, and the jaws open to the handle's width plus
``clearance`` (uniform in a range). The force-commanded gripper closes at a speed set by the
grip force, so from the ready opening (6 cm) a gentle close takes ~10 steps of consistently
positive actions, which exploration rarely strings together; from a few centimetres of
clearance it takes two or three. The learner meets the grasp and the
lift there early, and its value estimates carry them back to where it arrives from the ready
pose (a reverse curriculum, as in starting from demonstration states: Salimans and Chen, 2018;
Florensa et al., 2017). Nothing else changes: the reward, the physics and the episode length
are the env's own, and the periodic and final evaluations never use the wrapper, so every
success figure is from the ready pose.

Configured by the ``start_curriculum`` harness key of a hyper-parameter entry::

    start_curriculum:
      probability: 0.5        # share of training episodes that start near the handle
      height: [0.0, 0.06]     # m of the tool centre above the grasp point
      jitter: 0.005           # m, largest x and y offset
      yaw_jitter: 0.5         # rad, largest turn from across the handle
      clearance: [0.02, 0.05] # m of opening beyond the handle's width
"""

from __future__ import annotations

from collections.abc import Mapping

import gymnasium as gym
import numpy as np

from agents.config import ConfigError, number_in, require_known
from liuxing_envs.envs.instrument_grasp import (
    TOOL_START_HIGH,
    TOOL_START_LOW,
    TOOL_START_MAX_YAW_ERROR,
)
from liuxing_envs.sim.gripper import MAX_OPENING

ENV_IDS = ("InstrumentGrasp-v0",)
DEFAULTS = {
    "probability": 0.5,
    "height": [0.0, 0.06],
    "jitter": 0.005,
    "yaw_jitter": 0.5,
    "clearance": [0.02, 0.05],
}
#: The env's bounds of its reset options (see InstrumentGraspEnv.reset).
HEIGHT_LIMITS = (float(TOOL_START_LOW[2]), float(TOOL_START_HIGH[2]))
MAX_JITTER = float(TOOL_START_HIGH[0])
MAX_YAW_JITTER = TOOL_START_MAX_YAW_ERROR


class StartNearGrasp(gym.Wrapper):
    """Start an episode, with probability ``probability``, with the tool near the handle."""

    def __init__(
        self,
        env: gym.Env,
        *,
        probability: float = DEFAULTS["probability"],
        height=tuple(DEFAULTS["height"]),
        jitter: float = DEFAULTS["jitter"],
        yaw_jitter: float = DEFAULTS["yaw_jitter"],
        clearance=tuple(DEFAULTS["clearance"]),
    ) -> None:
        super().__init__(env)
        self.probability = probability
        self.height = tuple(height)
        self.jitter, self.yaw_jitter = jitter, yaw_jitter
        self.clearance = tuple(clearance)
        self._rng = np.random.default_rng()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            # Its own stream, seeded with the env's: the same seeds give the same starts (an
            # unseeded first reset draws from OS entropy, as the env itself then does).
            self._rng = np.random.default_rng([seed, 1])
        options = dict(options or {})
        # A caller's own start (any of its options) is left alone.
        chosen = options.keys() & {"tool_start", "tool_yaw_error", "jaw_clearance"}
        if not chosen and self._rng.random() < self.probability:
            rng = self._rng
            options["tool_start"] = [
                rng.uniform(-self.jitter, self.jitter),
                rng.uniform(-self.jitter, self.jitter),
                rng.uniform(*self.height),
            ]
            options["tool_yaw_error"] = rng.uniform(-self.yaw_jitter, self.yaw_jitter)
            options["jaw_clearance"] = rng.uniform(*self.clearance)
        return self.env.reset(seed=seed, options=options)


def check_start_curriculum(env_id: str, settings) -> dict | None:
    """The ``start_curriculum`` harness entry with defaults filled in, or ConfigError."""
    if settings is None:
        return None
    if env_id not in ENV_IDS:
        raise ConfigError(f"start_curriculum is for {', '.join(ENV_IDS)} only, not {env_id}")
    if not isinstance(settings, Mapping):
        raise ConfigError(f"start_curriculum must be a mapping of {', '.join(DEFAULTS)}")
    for key in settings:
        require_known("start_curriculum key", key, tuple(DEFAULTS))
    merged = {**DEFAULTS, **settings}
    return {
        "probability": number_in("start_curriculum.probability", merged["probability"], 0, 1),
        "height": _range("height", merged["height"], *HEIGHT_LIMITS),
        "jitter": number_in("start_curriculum.jitter", merged["jitter"], 0, MAX_JITTER),
        "yaw_jitter": number_in(
            "start_curriculum.yaw_jitter", merged["yaw_jitter"], 0, MAX_YAW_JITTER
        ),
        "clearance": _range("clearance", merged["clearance"], 0.0, MAX_OPENING),
    }


def _range(name: str, value, low: float, high: float) -> list[float]:
    if not (isinstance(value, list | tuple) and len(value) == 2):
        raise ConfigError(f"start_curriculum.{name} must be a pair [low, high] in m, got {value!r}")
    bounds = [number_in(f"start_curriculum.{name}", bound, low, high) for bound in value]
    if bounds[0] > bounds[1]:
        raise ConfigError(f"start_curriculum.{name} must be [low, high], low <= high, got {value}")
    return bounds
