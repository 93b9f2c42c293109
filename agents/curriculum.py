"""Start-state curriculum for InstrumentGrasp: some training episodes begin near the handle.

Every episode of InstrumentGrasp begins with the tool 30 cm above the tray. A learner
finds the handle from there (the reach term leads it), but the grasp itself is millimetre
work: lower the open jaws across a 10 mm handle to within millimetres of the tray without
striking the instrument, close, lift. Without help PPO and SAC learned to hover 25-34 mm above
the handle and never grasped (docs/design/training.md): the rewards of a grasp lie beyond a
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

The curriculum can also move its starts away from the handle as the learner masters them
(``advance_at``): :class:`AdvanceStartLevel`, a training callback, keeps the success of the
last ``window`` curriculum episodes and, each time their success rate reaches ``advance_at``,
raises the start *level* by ``level_step`` (at most 1) and starts a new window. At level l the
height's upper end, the jitter and the yaw jitter move the fraction l of the way from their
configured values to the env's limits (30 cm above the grasp point, 5 cm, a quarter turn), so
level 1 starts anywhere from the handle to the height of the ready pose. The level is one for
all training envs, saved with every checkpoint and restored by ``--resume``.

Configured by the ``start_curriculum`` harness key of a hyper-parameter entry::

    start_curriculum:
      probability: 0.5        # share of training episodes that start near the handle
      height: [0.0, 0.06]     # m of the tool centre above the grasp point
      jitter: 0.005           # m, largest x and y offset
      yaw_jitter: 0.5         # rad, largest turn from across the handle
      clearance: [0.02, 0.05] # m of opening beyond the handle's width
      advance_at: null        # success rate that raises the level (null: the starts stay)
      window: 50              # curriculum episodes per success rate
      level_step: 0.1         # level added at each advance
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from agents.config import ConfigError, number_in, require_known
from liuxing_envs.envs.instrument_grasp import (
    TOOL_START_HIGH,
    TOOL_START_LOW,
    TOOL_START_MAX_YAW_ERROR,
)
from liuxing_envs.registration import family
from liuxing_envs.sim.gripper import MAX_OPENING

#: The task families whose episodes can start near the grasp.
FAMILIES = ("InstrumentGrasp",)
#: Settings of the starts (:class:`StartNearGrasp`).
START_DEFAULTS = {
    "probability": 0.5,
    "height": [0.0, 0.06],
    "jitter": 0.005,
    "yaw_jitter": 0.5,
    "clearance": [0.02, 0.05],
}
#: Settings of the level's advance (:class:`AdvanceStartLevel`).
ADVANCE_DEFAULTS = {"advance_at": None, "window": 50, "level_step": 0.1}
DEFAULTS = {**START_DEFAULTS, **ADVANCE_DEFAULTS}
#: The env's bounds of its reset options (see InstrumentGraspEnv.reset).
HEIGHT_LIMITS = (float(TOOL_START_LOW[2]), float(TOOL_START_HIGH[2]))
MAX_JITTER = float(TOOL_START_HIGH[0])
MAX_YAW_JITTER = TOOL_START_MAX_YAW_ERROR
MAX_WINDOW = 10_000
#: ``info`` key, set at the end of every episode: whether it started near the handle.
STARTED_NEAR = "curriculum_start"


class StartNearGrasp(gym.Wrapper):
    """Start an episode, with probability ``probability``, with the tool near the handle.

    ``level`` (0 to 1; :meth:`set_level`) widens the starts towards the env's limits. The last
    step of every episode carries ``info["curriculum_start"]``: whether it started near the
    handle."""

    def __init__(
        self,
        env: gym.Env,
        *,
        probability: float = START_DEFAULTS["probability"],
        height=tuple(START_DEFAULTS["height"]),
        jitter: float = START_DEFAULTS["jitter"],
        yaw_jitter: float = START_DEFAULTS["yaw_jitter"],
        clearance=tuple(START_DEFAULTS["clearance"]),
        level: float = 0.0,
    ) -> None:
        super().__init__(env)
        self.probability = probability
        self.height = tuple(height)
        self.jitter, self.yaw_jitter = jitter, yaw_jitter
        self.clearance = tuple(clearance)
        self.set_level(level)
        self._rng = np.random.default_rng()
        self._started_near = False

    def set_level(self, level: float) -> None:
        self.level = number_in("start level", level, 0.0, 1.0)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            # Its own stream, seeded with the env's: the same seeds give the same starts (an
            # unseeded first reset draws from OS entropy, as the env itself then does).
            self._rng = np.random.default_rng([seed, 1])
        options = dict(options or {})
        # A caller's own start (any of its options) is left alone.
        chosen = options.keys() & {"tool_start", "tool_yaw_error", "jaw_clearance"}
        self._started_near = not chosen and self._rng.random() < self.probability
        if self._started_near:
            options.update(self._draw_start())
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        observation, reward, terminated, truncated, info = self.env.step(action)
        if terminated or truncated:
            info = {**info, STARTED_NEAR: self._started_near}
        return observation, reward, terminated, truncated, info

    def _draw_start(self) -> dict:
        rng, level = self._rng, self.level
        height = (self.height[0], _towards(self.height[1], HEIGHT_LIMITS[1], level))
        jitter = _towards(self.jitter, MAX_JITTER, level)
        yaw_jitter = _towards(self.yaw_jitter, MAX_YAW_JITTER, level)
        return {
            "tool_start": [
                rng.uniform(-jitter, jitter),
                rng.uniform(-jitter, jitter),
                rng.uniform(*height),
            ],
            "tool_yaw_error": rng.uniform(-yaw_jitter, yaw_jitter),
            "jaw_clearance": rng.uniform(*self.clearance),
        }


def _towards(value: float, limit: float, level: float) -> float:
    return value + level * (limit - value)


class AdvanceStartLevel(BaseCallback):
    """Raises the training envs' start level by ``level_step`` each time the success rate of
    the last ``window`` episodes that started near the handle reaches ``advance_at``.

    :meth:`state` / ``state=`` carry the level, the current window and the history of
    advances (steps, level) across checkpoints (``state`` as :meth:`state` gave it, or as
    ``run_folder.read_curriculum_state`` checked it)."""

    def __init__(
        self, advance_at: float, window: int, level_step: float, state: Mapping | None = None
    ) -> None:
        super().__init__()
        self.advance_at, self.level_step = advance_at, level_step
        state = state or {"level": 0.0, "recent": [], "history": []}
        self.level = state["level"]
        self.recent = deque(state["recent"], maxlen=window)
        self.history = [list(entry) for entry in state["history"]]

    def state(self) -> dict:
        return {"level": self.level, "recent": list(self.recent), "history": self.history}

    def _on_training_start(self) -> None:
        self.training_env.env_method("set_level", self.level)

    def _on_step(self) -> bool:
        for done, info in zip(self.locals["dones"], self.locals["infos"], strict=True):
            if done and info.get(STARTED_NEAR):
                self.recent.append(bool(info.get("is_success")))
                self._advance_if_mastered()
        return True

    def _advance_if_mastered(self) -> None:
        full = len(self.recent) == self.recent.maxlen
        if self.level >= 1.0 or not full or np.mean(self.recent) < self.advance_at:
            return
        self.level = min(1.0, round(self.level + self.level_step, 6))
        self.recent.clear()
        self.history.append([int(self.num_timesteps), self.level])
        self.training_env.env_method("set_level", self.level)
        self.logger.record("curriculum/level", self.level)
        print(f"start curriculum: level {self.level:g} at {self.num_timesteps} steps")


def start_settings(settings: Mapping) -> dict:
    """The :class:`StartNearGrasp` arguments of a checked ``start_curriculum`` entry."""
    return {key: settings[key] for key in START_DEFAULTS}


def level_callback(settings: Mapping | None, state: Mapping | None) -> AdvanceStartLevel | None:
    """The callback that advances the start level of a checked ``start_curriculum`` entry,
    or None where the starts stay put."""
    if not settings or settings["advance_at"] is None:
        return None
    return AdvanceStartLevel(
        settings["advance_at"], settings["window"], settings["level_step"], state
    )


def check_start_curriculum(env_id: str, settings) -> dict | None:
    """The ``start_curriculum`` harness entry with defaults filled in, or ConfigError."""
    if settings is None:
        return None
    if family(env_id) not in FAMILIES:
        raise ConfigError(f"start_curriculum is for {', '.join(FAMILIES)} tasks only, not {env_id}")
    if not isinstance(settings, Mapping):
        raise ConfigError(f"start_curriculum must be a mapping of {', '.join(DEFAULTS)}")
    for key in settings:
        require_known("start_curriculum key", key, tuple(DEFAULTS))
    merged = {**DEFAULTS, **settings}
    window = merged["window"]
    if isinstance(window, bool) or not isinstance(window, int) or not 1 <= window <= MAX_WINDOW:
        raise ConfigError(
            f"start_curriculum.window must be a whole number of episodes in [1, {MAX_WINDOW}], "
            f"got {window!r}"
        )
    advance_at = merged["advance_at"]
    return {
        "probability": number_in("start_curriculum.probability", merged["probability"], 0, 1),
        "height": _range("height", merged["height"], *HEIGHT_LIMITS),
        "jitter": number_in("start_curriculum.jitter", merged["jitter"], 0, MAX_JITTER),
        "yaw_jitter": number_in(
            "start_curriculum.yaw_jitter", merged["yaw_jitter"], 0, MAX_YAW_JITTER
        ),
        "clearance": _range("clearance", merged["clearance"], 0.0, MAX_OPENING),
        "advance_at": None
        if advance_at is None
        else number_in("start_curriculum.advance_at", advance_at, 0, 1),
        "window": window,
        "level_step": number_in("start_curriculum.level_step", merged["level_step"], 0.001, 1),
    }


def _range(name: str, value, low: float, high: float) -> list[float]:
    if not (isinstance(value, list | tuple) and len(value) == 2):
        raise ConfigError(f"start_curriculum.{name} must be a pair [low, high] in m, got {value!r}")
    bounds = [number_in(f"start_curriculum.{name}", bound, low, high) for bound in value]
    if bounds[0] > bounds[1]:
        raise ConfigError(f"start_curriculum.{name} must be [low, high], low <= high, got {value}")
    return bounds
