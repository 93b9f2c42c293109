"""The registered ids: each task family's versions and variants, as data.

A family's ``-v1`` id is its benchmark task: the env class's own defaults (its settings'
``V1``), which the published results and shipped policies use. A variant id names a real
choice researchers make (discrete view actions, image observations, the grasp without the
privileged approach guard) as the flat settings it changes; results and policies name ids,
not combinations of flags, so a keyword that changes a variant's own settings is refused
(:class:`VariantMaker`). ``-v0`` ids are deprecated and kept for one release, so that old
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
    #: What ``gym.make_vec`` makes N envs of the id with by default (a vector env of its own).
    vector_entry_point: str | None = None

    @property
    def gym_entry_point(self) -> str:
        """What Gymnasium makes the id with: the env class, or for a variant its
        :class:`VariantMaker` (``liuxing_envs.registration:<id with _ for ->``)."""
        if not self.kwargs:
            return self.entry_point
        return f"{__name__}:{_maker_name(self.env_id)}"


class VariantMaker:
    """A variant id's entry point: makes the env class with the variant's settings, and refuses
    a keyword that changes one of them (``gym.make("ViewPlanningDiscrete-v1",
    action_mode="continuous")`` would be continuous under the discrete id), naming the id to
    make instead. Otherwise it reads as the env class (``keyword_names()``,
    ``episode_length_setting``), which it imports when first used."""

    def __init__(self, registration: Registration) -> None:
        self.registration = registration

    @property
    def env_class(self) -> type:
        from gymnasium.envs.registration import load_env_creator

        return load_env_creator(self.registration.entry_point)

    def __call__(self, **kwargs: Any):
        self.refuse_redefinition(kwargs)
        return self.env_class(**kwargs)

    def refuse_redefinition(self, kwargs: dict[str, Any]) -> None:
        """Refuse a keyword that changes one of the variant's registered settings (Gymnasium
        passes them all, with the caller's over them)."""
        registration = self.registration
        for name, registered in registration.kwargs.items():
            if name in kwargs and not _same(kwargs[name], registered):
                defined_by = ", ".join(f"{n}={v!r}" for n, v in registration.kwargs.items())
                raise ValueError(
                    f"{registration.env_id} is defined by {defined_by}; for "
                    f"{name}={kwargs[name]!r} make {self._instead(name, kwargs[name])}"
                )

    def _instead(self, name: str, value: Any) -> str:
        """The id whose settings have ``name=value``: a sibling variant's, else the family's
        benchmark task (with the keyword, where it is not its default)."""
        registration = self.registration
        for other in REGISTRATIONS:
            if (
                other.family == registration.family
                and not other.deprecated
                and other is not registration
                and name in other.kwargs
                and _same(other.kwargs[name], value)
            ):
                return other.env_id
        task = benchmark_id(registration.family)
        default = self.env_class.default_settings.flat()[name]
        return task if _same(default, value) else f"{task} with {name}={value!r}"

    def __getattr__(self, name: str):
        if name.startswith("__"):  # copy and pickle ask for dunders the class has not
            raise AttributeError(name)
        return getattr(self.env_class, name)

    def __repr__(self) -> str:
        return f"VariantMaker({self.registration.env_id!r})"


def _same(given: Any, registered: Any) -> bool:
    try:
        return bool(given == registered)
    except (TypeError, ValueError):  # an array of several values is no registered setting
        return False


def _maker_name(env_id: str) -> str:
    return env_id.replace("-", "_")


def _view_planning(env_id: str, **kwargs: Any) -> Registration:
    return Registration(env_id, "ViewPlanning", VIEW_PLANNING, MappingProxyType(kwargs))


def _instrument_grasp(env_id: str, **kwargs: Any) -> Registration:
    return Registration(env_id, "InstrumentGrasp", INSTRUMENT_GRASP, MappingProxyType(kwargs))


VIEW_PLANNING = "liuxing_envs.envs.view_planning:ViewPlanningEnv"
INSTRUMENT_GRASP = "liuxing_envs.envs.instrument_grasp:InstrumentGraspEnv"

REGISTRATIONS = (
    Registration(
        "ViewPlanning-v1",
        "ViewPlanning",
        VIEW_PLANNING,
        vector_entry_point="liuxing_envs.envs.view_planning_vector:ViewPlanningVectorEnv",
    ),
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
_VARIANTS = {_maker_name(r.env_id): r for r in REGISTRATIONS if r.kwargs}


def __getattr__(name: str) -> VariantMaker:
    """A variant's entry point by its name in :attr:`Registration.gym_entry_point`."""
    if name not in _VARIANTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return VariantMaker(_VARIANTS[name])


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


def settings_of(env_id: str, **kwargs: Any):
    """The settings ``gym.make(env_id, **kwargs)`` makes its env with, each value checked,
    without making the env (no scene is built, no object set prepared)."""
    from gymnasium.envs.registration import load_env_creator

    family(env_id)  # an unknown id is refused by name
    registration = BY_ID[env_id]
    env_class = load_env_creator(registration.entry_point)
    if kwargs and registration.kwargs:
        VariantMaker(registration).refuse_redefinition(kwargs)
    return env_class.settings_from({**registration.kwargs, **kwargs})


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
                entry_point=registration.gym_entry_point,
                max_episode_steps=registration.max_episode_steps,
                kwargs=dict(registration.kwargs),
                vector_entry_point=registration.vector_entry_point,
            )
