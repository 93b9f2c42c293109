"""The registered ids: each task family's versions and variants, as data.

A family's ``-v1`` id is its benchmark task: the env class's own defaults (its settings'
``V1``), which the published results and shipped policies use. A variant id names a real
choice researchers make (discrete view actions, image observations, the grasp without the
privileged approach guard) as the flat settings it changes; results and policies name ids,
not combinations of flags. ``-v0`` ids are deprecated and kept for one release, so that old
run folders still evaluate.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any


@dataclass(frozen=True)
class Registration:
    """One registered id: its task family, env class, the settings it changes from the
    class's defaults, and a registered time limit (None: the env ends its own episodes)."""

    env_id: str
    family: str
    entry_point: str
    kwargs: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    max_episode_steps: int | None = None
    deprecated: bool = False


def _view_planning(env_id: str, **kwargs: Any) -> Registration:
    return Registration(env_id, "ViewPlanning", VIEW_PLANNING, MappingProxyType(kwargs))


def _instrument_grasp(env_id: str, **kwargs: Any) -> Registration:
    return Registration(env_id, "InstrumentGrasp", INSTRUMENT_GRASP, MappingProxyType(kwargs))


VIEW_PLANNING = "liuxing_envs.envs.view_planning:ViewPlanningEnv"
INSTRUMENT_GRASP = "liuxing_envs.envs.instrument_grasp:InstrumentGraspEnv"

REGISTRATIONS = (
    _view_planning("ViewPlanning-v1"),
    _view_planning("ViewPlanningDiscrete-v1", action_mode="discrete"),
    _instrument_grasp("InstrumentGrasp-v1"),
    _instrument_grasp("InstrumentGraspDepth-v1", obs_mode="depth"),
    _instrument_grasp("InstrumentGraspRGBD-v1", obs_mode="rgbd"),
    _instrument_grasp(
        "InstrumentGraspUnguarded-v1",
        approach_lead_limit=None,
        approach_lead_slope=0.0,
        approach_guard_fingers=False,
    ),
    # v0: the registered time limits were its episode ends (a view budget of 4, 200 steps).
    Registration(
        "ViewPlanning-v0",
        "ViewPlanning",
        "liuxing_envs.envs.view_planning:ViewPlanningV0Env",
        max_episode_steps=4,
        deprecated=True,
    ),
    Registration(
        "InstrumentGrasp-v0",
        "InstrumentGrasp",
        "liuxing_envs.envs.instrument_grasp:InstrumentGraspV0Env",
        max_episode_steps=200,
        deprecated=True,
    ),
)
BY_ID = {registration.env_id: registration for registration in REGISTRATIONS}


def family(env_id: str) -> str:
    """The task family of a registered id (``"InstrumentGraspRGBD-v1"`` ->
    ``"InstrumentGrasp"``): what the tools that serve every version and variant of a task key
    their per-task parts by."""
    if env_id not in BY_ID:
        from liuxing_envs.validation import closest

        raise ValueError(
            f"unknown environment id {env_id!r}{closest(env_id, BY_ID)}; "
            f"registered: {', '.join(BY_ID)}"
        )
    return BY_ID[env_id].family


def benchmark_id(family_name: str) -> str:
    """The family's current benchmark task (``"ViewPlanning"`` -> ``"ViewPlanning-v1"``)."""
    return f"{family_name}-v1"


def register_all() -> None:
    """Register every id with Gymnasium (ids already there are left alone)."""
    import gymnasium as gym

    for registration in REGISTRATIONS:
        if registration.env_id not in gym.registry:
            gym.register(
                id=registration.env_id,
                entry_point=registration.entry_point,
                max_episode_steps=registration.max_episode_steps,
                kwargs=dict(registration.kwargs),
            )
