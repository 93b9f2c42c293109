"""InstrumentGrasp-v1: the registered task is the shipped policy's, the env ends its own
episodes, settings of another mode are refused by name, the spec's argument table is the
settings', and the deprecated v0 id keeps v0."""

import dataclasses
import inspect
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest

import liuxing_envs  # noqa: F401  (registers the ids)
from liuxing_envs.envs import instrument_grasp_settings as grasp_settings
from liuxing_envs.envs.instrument_grasp import InstrumentGraspEnv, InstrumentGraspV0Env
from liuxing_envs.envs.instrument_grasp_settings import V0, V1, InstrumentGraspSettings
from liuxing_envs.sim import camera, gripper, instruments
from tests.behaviour_digests import SHIPPED_GRASP_TASK as SHIPPED_TASK

FAST = {"instruments": ["scalpel"]}


def test_the_registered_v1_is_the_shipped_policys_task():
    env = gym.make("InstrumentGrasp-v1")
    settings = env.unwrapped.settings.flat()
    assert {name: settings[name] for name in SHIPPED_TASK} == SHIPPED_TASK
    assert settings["depth_backend"] == "raycast"  # the same images on every machine
    assert env.spec.max_episode_steps is None  # the env ends its own episodes
    env.close()
    # v1 changes v0's defaults where the shipped task did, and the depth backend.
    assert set(V0.differences(V1)) == {*SHIPPED_TASK, "depth_backend"} - {"obs_mode"}


def test_v1_plays_as_v0_given_the_shipped_task():
    """v1 changed defaults, not dynamics: v0 given the shipped kwargs steps identically."""

    def rollout(env):
        env.action_space.seed(0)
        trace = [env.reset(seed=4)[0]]
        for _ in range(40):
            trace.append(env.step(env.action_space.sample())[:4])
        env.close()
        return trace

    with pytest.warns(DeprecationWarning):
        v0 = InstrumentGraspV0Env(**FAST, **SHIPPED_TASK)
    v1_trace, v0_trace = rollout(InstrumentGraspEnv(**FAST)), rollout(v0)
    for mine, theirs in zip(v1_trace, v0_trace, strict=True):
        np.testing.assert_equal(mine, theirs)


def test_v1_truncates_itself_at_episode_steps():
    env = InstrumentGraspEnv(**FAST, episode_steps=5)
    env.reset(seed=0)
    hold = np.zeros(env.action_space.shape, np.float32)
    flags = [env.step(hold)[2:4] for _ in range(5)]
    assert flags == [(False, False)] * 4 + [(False, True)]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(hold)
    env.reset(seed=1)  # and a new episode starts
    env.step(hold)
    env.close()


def test_v0_ends_only_at_its_registered_time_limit():
    with pytest.warns(DeprecationWarning):
        env = InstrumentGraspV0Env(**FAST, episode_steps=5)
    env.reset(seed=0)
    hold = np.zeros(env.action_space.shape, np.float32)
    assert not any(env.step(hold)[3] for _ in range(8))
    env.close()


def test_v0_warns_naming_v1_and_keeps_v0s_defaults():
    with pytest.warns(
        DeprecationWarning, match=r"InstrumentGrasp-v0 is deprecated.*InstrumentGrasp-v1"
    ):
        env = gym.make("InstrumentGrasp-v0", **FAST)
    assert env.unwrapped.settings == V0.changed(instruments=("scalpel",))
    assert env.spec.max_episode_steps == 200
    assert env.unwrapped.gripper_control == "opening" and env.unwrapped.max_grip_force == 20.0
    env.close()


@pytest.mark.parametrize(
    ("env_id", "kwargs", "message"),
    [
        ("InstrumentGrasp-v1", {"max_joint_delta": 0.05},
         r"max_joint_delta applies only with controller='joint_delta'; with "
         r"controller='ee_delta' it would be ignored"),
        ("InstrumentGraspUnguarded-v1", {"gripper_control": "opening", "max_grip_force": 3.0},
         r"max_grip_force applies only with gripper_control='force'; with "
         r"gripper_control='opening' it would be ignored"),
        ("InstrumentGraspUnguarded-v1", {"controller": "joint_delta", "max_translation": 0.01},
         r"max_translation applies only with controller='ee_delta'"),
        ("InstrumentGrasp-v1", {"max_gripper_delta": 0.002},
         r"max_gripper_delta applies only with gripper_control='delta'"),
        # The guard's own rule comes first: an opening gripper outruns the finger guard.
        ("InstrumentGrasp-v1", {"gripper_control": "opening", "max_grip_force": 3.0},
         r"approach_guard_fingers=True cannot brake gripper_control='opening'"),
        # The wrist images' settings with state observations.
        ("InstrumentGrasp-v1", {"depth_backend": "gl"},
         r"depth_backend applies only with obs_mode='depth' or obs_mode='rgbd'; with "
         r"obs_mode='state' it would be ignored"),
        ("InstrumentGrasp-v1", {"resolution": 32},
         r"resolution applies only with obs_mode='depth' or obs_mode='rgbd'"),
    ],
)  # fmt: skip
def test_a_setting_of_another_mode_is_refused_by_name(env_id, kwargs, message):
    with pytest.raises(ValueError, match=message):
        gym.make(env_id, **FAST, **kwargs)


def test_a_mode_switch_alone_leaves_the_other_modes_defaults_alone():
    env = gym.make("InstrumentGraspUnguarded-v1", **FAST, controller="joint_delta")
    assert env.action_space.shape == (7,) and env.unwrapped.controller == "joint_delta"
    env.close()


def test_the_spec_argument_table_is_the_settings():
    doc = InstrumentGraspEnv.__doc__
    for row in InstrumentGraspSettings.table(V1):
        assert f"| `{row['name']}` | `{row['default']!r}` |" in doc, row["name"]
        assert row["doc"] and "|" not in row["doc"], f"{row['name']}: no meaning, or a stray |"
    for section in ("Description", "Action space", "Observation space", "Rewards",
                    "Starting state", "Episode end", "Arguments", "Version history"):  # fmt: skip
        assert f"## {section}\n" in doc
    for name in instruments.INSTRUMENT_SETS["all"]:  # the instrument sets are named
        assert name in doc


def test_the_settings_constants_are_the_simulations():
    assert grasp_settings.INSTRUMENT_SETS == instruments.INSTRUMENT_SETS
    assert grasp_settings.DEPTH_BACKENDS == camera.BACKENDS
    assert grasp_settings.MAX_OPENING == gripper.MAX_OPENING
    assert grasp_settings.SERVO_FORCE_LIMIT == gripper.SERVO_FORCE_LIMIT
    assert grasp_settings.FORCE_COMMAND_DAMPING == gripper.FORCE_COMMAND_DAMPING


def test_the_settings_module_does_not_import_the_simulator():
    code = "import sys, liuxing_envs.envs.instrument_grasp_settings; print('mujoco' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_settings_are_frozen_values():
    with pytest.raises(dataclasses.FrozenInstanceError):
        V1.gripper.max_grip_force = 10.0
    assert V1.scene.names == instruments.INSTRUMENT_SETS["train"]
    assert InstrumentGraspSettings.from_flat({"instruments": ["probe"]}).scene.names == ("probe",)


def test_the_signature_spells_out_the_settings_with_each_versions_defaults():
    """help(), IDEs and inspect see every setting as a keyword with its default."""
    for env_class, defaults in ((InstrumentGraspEnv, V1), (InstrumentGraspV0Env, V0)):
        parameters = inspect.signature(env_class.__init__).parameters
        keywords = {n: p.default for n, p in parameters.items() if p.kind is p.KEYWORD_ONLY}
        assert tuple(keywords) == env_class.keyword_names()
        assert keywords == {**defaults.flat(), "render_mode": None}


def test_v0_takes_another_modes_settings_and_ignores_them_as_before():
    """v0 ids behave as before v1: a setting its mode leaves unused is taken, not refused."""

    def rollout(**kwargs):
        with pytest.warns(DeprecationWarning):
            env = gym.make("InstrumentGrasp-v0", **FAST, **kwargs)
        env.action_space.seed(1)
        trace = [env.reset(seed=2)[0]]
        trace += [env.step(env.action_space.sample())[:4] for _ in range(15)]
        env.close()
        return trace

    ignored = {"max_grip_force": 3.0, "max_gripper_delta": 0.002, "max_joint_delta": 0.1,
               "depth_backend": "embree", "resolution": 32}  # fmt: skip
    for mine, theirs in zip(rollout(**ignored), rollout(), strict=True):
        np.testing.assert_equal(mine, theirs)


GUARD_OFF = "approach_lead_limit=None, approach_lead_slope=0.0, approach_guard_fingers=False"


@pytest.mark.parametrize(
    "kwargs",
    [{}, {"approach_lead_limit": None},
     {"approach_lead_limit": None, "approach_lead_slope": 0.0}],
    ids=["guard-on", "limit-off", "limit-and-slope-off"],
)  # fmt: skip
def test_turning_the_guard_off_for_joint_delta_names_every_setting_of_it(kwargs):
    """Each message on the way names all that turns the guard off: none contradicts another."""
    with pytest.raises(ValueError) as refused:
        gym.make("InstrumentGrasp-v1", **FAST, controller="joint_delta", **kwargs)
    assert GUARD_OFF in str(refused.value) and "InstrumentGraspUnguarded-v1" in str(refused.value)
    # As the messages say: the whole guard off.
    env = gym.make("InstrumentGrasp-v1", **FAST, controller="joint_delta",
                   approach_lead_limit=None, approach_lead_slope=0.0,
                   approach_guard_fingers=False)  # fmt: skip
    assert env.action_space.shape == (7,)
    env.close()


def test_an_opening_gripper_is_told_it_may_leave_the_fingers_unguarded():
    with pytest.raises(ValueError, match=r"cannot brake gripper_control='opening'.*or leave the "
                       r"fingers unguarded with approach_guard_fingers=False"):  # fmt: skip
        gym.make("InstrumentGrasp-v1", **FAST, gripper_control="opening")
    env = gym.make("InstrumentGrasp-v1", **FAST, gripper_control="opening",
                   approach_guard_fingers=False)  # fmt: skip
    assert env.unwrapped.approach_lead_limit == V1.safety.approach_lead_limit  # the arm's guard
    env.close()


@pytest.mark.parametrize("name", ["hold_time", "max_grip_force", "obs_mode"])
def test_a_setting_assigned_on_the_env_is_refused(name):
    """Its parts were built from the settings: an assigned value would read back and do nothing."""
    env = gym.make("InstrumentGrasp-v1", **FAST)
    before = getattr(env.unwrapped, name)
    message = rf"{name} is a setting of InstrumentGraspEnv, fixed when the env is made "
    with pytest.raises(
        AttributeError, match=message + rf".*gym.make\('InstrumentGrasp-v1', {name}="
    ):
        setattr(env.unwrapped, name, 2.0)
    assert getattr(env.unwrapped, name) == before == env.unwrapped.settings.flat()[name]
    env.unwrapped.render_mode = None  # what is no setting is assigned as before
    env.close()
