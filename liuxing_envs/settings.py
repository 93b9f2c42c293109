"""Typed env settings: one frozen dataclass per part of an env, behind a flat keyword interface.

An env's settings are a :class:`Settings` dataclass whose fields are its parts' settings
(:class:`Part` dataclasses: the arm controller, the gripper, the safety layer, the reward, the
scene, the sensors), each declared with :func:`part`. Every default lives in one place, the
part's field, declared with :func:`knob` (its meaning, unit and the modes it applies to). The
flat names of the parts' fields, unique across an env, are the public keyword interface:
``gym.make(id, **kwargs)``, ``train.py --env-kwargs``, the YAML files, the docs' argument
tables and sweeps all name them.

    settings = GraspSettings.from_flat({"max_grip_force": 3.0}, defaults=GRASP_V1)
    settings.gripper.max_grip_force  # 3.0
    settings.flat()["max_grip_force"]  # the same, by its public name

:meth:`Settings.from_flat` refuses a misspelt name (with the closest valid one and the list), a
bad value (each part's :meth:`Part.check`, then the env's cross-part :meth:`Settings.check`),
and an explicitly given setting that does not apply to the chosen mode
(``knob(..., only_with={"gripper_control": ("force",)})``), rather than ignoring it.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, ClassVar, Self

from liuxing_envs.validation import closest


def knob(default: Any, doc: str, *, unit: str = "", only_with: Mapping[str, tuple] | None = None):
    """A setting's field: its default, what it means (one sentence, for the docs' argument
    table), its unit, and the modes it applies to, ``{setting: allowed values}``: given
    explicitly under any other mode, it is refused by name. Defaults must be immutable
    (numbers, strings, None, tuples): the settings are shared, frozen values."""
    if isinstance(default, list | dict | set):
        raise TypeError(f"a knob's default must be immutable, got {default!r}")
    metadata = {"doc": doc, "unit": unit, "only_with": dict(only_with or {})}
    return dataclasses.field(default=default, metadata=metadata)


def part(part_type: type[Part]):
    """A :class:`Settings` field holding one part's settings, its defaults by default."""
    return dataclasses.field(default_factory=part_type)


@dataclasses.dataclass(frozen=True)
class Part:
    """The settings of one part of an env. Subclasses declare their fields with :func:`knob`
    and check their own values in :meth:`check`, naming the setting and what is allowed."""

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Raise ``ValueError`` naming a setting whose value this part cannot take."""


@dataclasses.dataclass(frozen=True)
class Settings:
    """An env's settings: each field is one :class:`Part`. Subclasses add the rules between
    parts in :meth:`check`."""

    #: Names of the keywords the env takes besides its settings (``render_mode``).
    extra_keywords: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Raise ``ValueError`` for settings of different parts that do not go together."""

    # ------------------------------------------------------------------ the flat interface
    @classmethod
    def parts(cls) -> dict[str, type[Part]]:
        """The part dataclasses, by field name, in order."""
        return {f.name: _part_type(cls, f) for f in dataclasses.fields(cls)}

    @classmethod
    @functools.cache
    def knobs(cls) -> Mapping[str, tuple[str, dataclasses.Field]]:
        """Every setting's flat name -> (its part's field name, its dataclass field). Found
        once per class: an env reads its settings by flat name every step."""
        found: dict[str, tuple[str, dataclasses.Field]] = {}
        for part_name, part in cls.parts().items():
            for field in dataclasses.fields(part):
                if field.name in found:
                    raise TypeError(
                        f"{cls.__name__}: {field.name!r} is a setting of both "
                        f"{found[field.name][0]!r} and {part_name!r}; flat names must be unique"
                    )
                found[field.name] = (part_name, field)
        return MappingProxyType(found)

    @classmethod
    def flat_names(cls) -> tuple[str, ...]:
        """The public keyword names, part by part, in declaration order."""
        return tuple(cls.knobs())

    @classmethod
    def from_flat(
        cls,
        given: Mapping[str, Any],
        defaults: Self | None = None,
        *,
        refuse_inapplicable: bool = True,
    ) -> Self:
        """Settings from flat keyword values over ``defaults`` (the dataclasses' own defaults
        if None). Unknown names and bad values are refused by name, and so are inapplicable
        settings unless ``refuse_inapplicable`` is False (a deprecated version that always
        took them and left them unused)."""
        knobs = cls.knobs()
        for name in given:
            if name not in knobs:
                allowed = cls.flat_names()
                raise TypeError(
                    f"{cls.__name__} has no setting {name!r}{closest(name, allowed)}; "
                    f"allowed: {', '.join(allowed)}"
                )
        settings = (cls() if defaults is None else defaults).replaced(**given)
        if refuse_inapplicable:
            settings.refuse_inapplicable(given)
        return settings

    def flat(self) -> dict[str, Any]:
        """Every setting by its public name."""
        return {
            name: getattr(getattr(self, part_name), name)
            for name, (part_name, _) in self.knobs().items()
        }

    def applicable(self) -> dict[str, Any]:
        """Every setting that applies to these settings' modes, by its public name: what
        pins an env's task completely (giving one of the others would be refused)."""
        knobs, values = self.knobs(), self.flat()
        return {
            name: value
            for name, value in values.items()
            if all(
                values[mode] in allowed
                for mode, allowed in knobs[name][1].metadata["only_with"].items()
            )
        }

    def replaced(self, **given) -> Self:
        """These settings with some replaced by their flat names, each part's values checked
        but not whether a setting applies to its mode: a version's defaults hold every mode's
        settings. Unknown names are :meth:`from_flat`'s to refuse."""
        knobs = self.knobs()
        changes: dict[str, dict[str, Any]] = {}
        for name, value in given.items():
            changes.setdefault(knobs[name][0], {})[name] = value
        parts = {
            part_name: dataclasses.replace(getattr(self, part_name), **part_changes)
            for part_name, part_changes in changes.items()
        }
        return dataclasses.replace(self, **parts)

    def changed(self, **given) -> Self:
        """These settings with some changed by their flat names (checked as :meth:`from_flat`
        checks them)."""
        return self.from_flat(given, defaults=self)

    def differences(self, other: Settings) -> dict[str, tuple[Any, Any]]:
        """Flat name -> (this value, the other's) where the two differ."""
        mine, theirs = self.flat(), other.flat()
        return {name: (mine[name], theirs[name]) for name in mine if mine[name] != theirs[name]}

    def refuse_inapplicable(self, given: Mapping[str, Any]) -> None:
        """Refuse an explicitly given setting that its mode settings leave unused. None, a
        setting's "off", is taken anywhere."""
        knobs, values = self.knobs(), self.flat()
        for name, value in given.items():
            if value is None:
                continue
            for mode, allowed in knobs[name][1].metadata["only_with"].items():
                if values[mode] not in allowed:
                    modes = " or ".join(f"{mode}={choice!r}" for choice in allowed)
                    raise ValueError(
                        f"{name} applies only with {modes}; with {mode}={values[mode]!r} it "
                        "would be ignored, so leave it out"
                    )

    @classmethod
    def table(cls, defaults: Settings | None = None) -> list[dict[str, Any]]:
        """One row per setting: name, part, default (of ``defaults``), unit, doc, only_with;
        what the docs' argument tables are made of."""
        values = (cls() if defaults is None else defaults).flat()
        return [
            {
                "name": name,
                "part": part_name,
                "default": values[name],
                "unit": field.metadata["unit"],
                "doc": field.metadata["doc"],
                "only_with": field.metadata["only_with"],
            }
            for name, (part_name, field) in cls.knobs().items()
        ]

    @classmethod
    def markdown_table(cls, defaults: Settings | None = None) -> str:
        """:meth:`table` as a Markdown table (name, default, unit, meaning)."""
        lines = ["| argument | default | unit | meaning |", "|---|---|---|---|"]
        for row in cls.table(defaults):
            applies = "".join(
                f" Only with `{mode}` {' or '.join(repr(v) for v in allowed)}."
                for mode, allowed in row["only_with"].items()
            )
            lines.append(
                f"| `{row['name']}` | `{row['default']!r}` | {row['unit']} | "
                f"{row['doc']}{applies} |"
            )
        return "\n".join(lines)


def _part_type(settings: type[Settings], field: dataclasses.Field) -> type[Part]:
    """A Settings field's Part class, from its default (each part field has one)."""
    if field.default is not dataclasses.MISSING:
        part = type(field.default)
    elif field.default_factory is not dataclasses.MISSING:
        part = type(field.default_factory())
    else:
        part = None
    if part is None or not issubclass(part, Part):
        raise TypeError(
            f"{settings.__name__}.{field.name} must default to a Part's settings (part(ThePart))"
        )
    return part
