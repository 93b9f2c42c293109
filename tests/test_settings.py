"""The typed-settings machinery every env's keyword interface goes through."""

import dataclasses

import pytest

from liuxing_envs.envs.instrument_grasp_settings import V0 as GRASP_V0
from liuxing_envs.envs.instrument_grasp_settings import V1 as GRASP_V1
from liuxing_envs.envs.view_planning_settings import V0 as VIEW_V0
from liuxing_envs.envs.view_planning_settings import V1 as VIEW_V1
from liuxing_envs.settings import Part, Settings, knob
from liuxing_envs.validation import require_choice, require_number


@dataclasses.dataclass(frozen=True)
class Gripper(Part):
    gripper_control: str = knob("force", "How the action drives the fingers.")
    max_grip_force: float = knob(3.0, "Grip force at |action| = 1.", unit="N",
                                 only_with={"gripper_control": ("force",)})  # fmt: skip
    max_gripper_delta: float | None = knob(None, "Opening change per step.", unit="m",
                                           only_with={"gripper_control": ("delta",)})  # fmt: skip

    def check(self):
        require_choice("gripper_control", self.gripper_control, ("opening", "delta", "force"))
        require_number("max_grip_force", self.max_grip_force, 0.1, 40.0)


@dataclasses.dataclass(frozen=True)
class Reward(Part):
    force_penalty: float = knob(2.0, "Reward per newton over the limit.")


@dataclasses.dataclass(frozen=True)
class Toy(Settings):
    gripper: Gripper = dataclasses.field(default_factory=Gripper)
    reward: Reward = dataclasses.field(default_factory=Reward)

    def check(self):
        if self.gripper.gripper_control == "opening" and self.reward.force_penalty > 10:
            raise ValueError("force_penalty above 10 needs a force-limited gripper")


def test_flat_names_map_to_the_parts_and_back():
    settings = Toy.from_flat({"max_grip_force": 5.0, "force_penalty": 1.0})
    assert settings.gripper.max_grip_force == 5.0 and settings.reward.force_penalty == 1.0
    assert settings.flat() == {
        "gripper_control": "force", "max_grip_force": 5.0, "max_gripper_delta": None,
        "force_penalty": 1.0,
    }  # fmt: skip
    assert Toy.flat_names() == ("gripper_control", "max_grip_force", "max_gripper_delta",
                                "force_penalty")  # fmt: skip
    assert settings.differences(Toy()) == {
        "max_grip_force": (5.0, 3.0),
        "force_penalty": (1.0, 2.0),
    }


def test_a_misspelt_name_is_refused_with_the_closest_one():
    with pytest.raises(TypeError, match=r"'max_grip_forse'.*max_grip_force.*allowed: gripper_c"):
        Toy.from_flat({"max_grip_forse": 1.0})


def test_bad_values_are_refused_by_the_part_and_by_the_rules_between_parts():
    with pytest.raises(ValueError, match=r"max_grip_force must be a number in \[0.1, 40.0\]"):
        Toy.from_flat({"max_grip_force": 400.0})
    with pytest.raises(ValueError, match="force_penalty above 10"):
        Toy.from_flat({"gripper_control": "opening", "force_penalty": 20.0})


def test_an_inapplicable_setting_is_refused_by_name_and_its_default_is_not():
    with pytest.raises(ValueError, match=r"max_grip_force applies only with gripper_control="
                       r"'force'; with gripper_control='delta' it would be ignored"):  # fmt: skip
        Toy.from_flat({"gripper_control": "delta", "max_grip_force": 3.0})
    # The default grip force, not given, does not stand in the way of another mode.
    assert Toy.from_flat({"gripper_control": "opening"}).gripper.gripper_control == "opening"
    # None is "off" anywhere.
    Toy.from_flat({"gripper_control": "force", "max_gripper_delta": None})


def test_defaults_come_from_one_place_and_a_version_changes_them_as_a_value():
    older = Toy().changed(gripper_control="opening")
    assert Toy.from_flat({}, defaults=older).gripper.gripper_control == "opening"
    rows = {row["name"]: row for row in Toy.table(defaults=older)}
    assert rows["gripper_control"]["default"] == "opening"
    assert rows["max_grip_force"]["unit"] == "N" and rows["max_grip_force"]["part"] == "gripper"
    assert "Only with `gripper_control` 'force'" in Toy.markdown_table()
    with pytest.raises(dataclasses.FrozenInstanceError):
        older.gripper.gripper_control = "force"


def test_a_mutable_default_is_refused_when_declared():
    with pytest.raises(TypeError, match="immutable"):
        knob([1, 2], "a list")


def test_a_deprecated_version_may_take_an_inapplicable_setting_and_leave_it_unused():
    # v0 ids always took another mode's settings and ignored them; their values are checked.
    kept = Toy.from_flat(
        {"gripper_control": "delta", "max_grip_force": 3.5}, refuse_inapplicable=False
    )
    assert kept.gripper.gripper_control == "delta" and kept.gripper.max_grip_force == 3.5
    with pytest.raises(ValueError, match=r"max_grip_force must be a number in \[0.1, 40.0\]"):
        Toy.from_flat({"gripper_control": "delta", "max_grip_force": 400.0},
                      refuse_inapplicable=False)  # fmt: skip


@pytest.mark.parametrize(
    "defaults",
    [GRASP_V0, GRASP_V1, VIEW_V0, VIEW_V1],
    ids=["grasp-v0", "grasp-v1", "view-v0", "view-v1"],
)
def test_every_float_setting_defaults_to_a_float(defaults):
    """A float knob with an int default puts ints into info (``reward_failure`` was -50)."""
    values = defaults.flat()
    for name, (_, field) in type(defaults).knobs().items():
        if str(field.type).startswith("float"):
            assert values[name] is None or type(values[name]) is float, (name, values[name])
