"""ViewPlanning's typed settings: one source of the defaults, the spec's argument table made
from them, v0 and v1 told apart by value, and the rules refused by name."""

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import yaml

import liuxing_envs  # noqa: F401  (registers the ids)
from liuxing_envs.envs.view_planning import ViewPlanningEnv, ViewPlanningV0Env
from liuxing_envs.envs.view_planning_settings import (
    DEPTH_BACKENDS,
    MOTION_MODES,
    OBJECT_SET_NAMES,
    V0,
    V1,
    ViewPlanningSettings,
)
from liuxing_envs.sim import arm, camera, objects
from tests.behaviour_digests import REPO


def test_the_spec_argument_table_is_the_settings_table():
    doc_lines = {line.strip() for line in ViewPlanningEnv.__doc__.splitlines()}
    rows = ViewPlanningSettings.markdown_table(V1).splitlines()
    assert len(rows) == 2 + len(ViewPlanningSettings.flat_names())
    assert all(row in doc_lines for row in rows)
    assert ViewPlanningEnv.keyword_names() == (*ViewPlanningSettings.flat_names(), "render_mode")


def test_v1_is_the_shipped_policies_configuration_and_v0_differs_in_its_depth_backend():
    assert ViewPlanningEnv.default_settings is V1 == ViewPlanningSettings()
    assert ViewPlanningV0Env.default_settings is V0
    assert V1.differences(V0) == {"depth_backend": ("raycast", "auto")}
    # The shipped policies trained with v0's defaults but for the object set (a training
    # choice): nothing else of theirs differs from v1 but the backend the changelog names.
    for config in sorted((REPO / "policies" / "ViewPlanning-v1").glob("*/config.yml")):
        kwargs = yaml.safe_load(config.read_text())["env_kwargs"]
        kwargs.pop("object_set", None)
        assert V1.changed(**kwargs) == V1, config


def test_the_import_light_names_match_the_simulation_modules():
    assert MOTION_MODES == arm.MOTION_MODES
    assert DEPTH_BACKENDS == camera.BACKENDS
    assert OBJECT_SET_NAMES == tuple(objects.OBJECT_SETS)
    assert V1.scene.object_set == "train"
    assert len(objects.OBJECT_SETS["train"]) == 13 and len(objects.OBJECT_SETS["held_out"]) == 5


def test_the_settings_module_imports_neither_mujoco_nor_open3d():
    code = (
        "import sys, liuxing_envs.envs.view_planning_settings as s; s.V1.changed(scales=[1.0]); "
        "print(sorted(m for m in ('mujoco', 'open3d') if m in sys.modules))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert result.stdout.strip() == "[]", result.stderr


def test_continuous_only_ranges_are_refused_with_discrete_actions():
    message = "azimuth_range_deg applies only with action_mode='continuous'; with action_mode="
    with pytest.raises(ValueError, match=message + "'discrete' it would be ignored"):
        ViewPlanningSettings.from_flat({"action_mode": "discrete", "azimuth_range_deg": (0, 90)})
    # radius_range spans the history's radius in either mode; the candidates serve the oracle.
    settings = V1.changed(action_mode="discrete", radius_range=(0.3, 0.4), discrete_radius=0.35)
    assert settings.action.radius_range == (0.3, 0.4)


def test_values_given_as_yaml_gives_them_are_kept_in_normal_form():
    settings = V1.changed(scales=[1, 1.2], object_region=[[0.45, -0.05], [0.5, 0.05]],
                          depth_noise={"sigma_base": 0.002}, objects=["box"])  # fmt: skip
    assert settings.scene.scales == (1.0, 1.2) and settings.scene.objects == ("box",)
    assert settings.scene.object_region == ((0.45, -0.05), (0.5, 0.05))
    assert settings.sensor.depth_noise == camera.DepthNoise(sigma_base=0.002)
    with pytest.raises(ValueError, match="depth_noise has no setting 'sigma'"):
        V1.changed(depth_noise={"sigma": 0.1})


SMALL = {"objects": ["box"], "scales": [1.0], "coverage_samples": 512}


def test_v0_takes_continuous_ranges_with_discrete_actions_and_ignores_them_as_before():
    def rollout(**kwargs):
        with pytest.warns(DeprecationWarning):
            env = gym.make("ViewPlanning-v0", **SMALL, action_mode="discrete", **kwargs)
        trace = [env.reset(seed=1)[0]] + [env.step(action)[:4] for action in (5, 32)]
        env.close()
        return trace

    ignored = rollout(azimuth_range_deg=(0.0, 90.0), elevation_range_deg=(30.0, 60.0))
    for mine, theirs in zip(ignored, rollout(), strict=True):
        np.testing.assert_equal(mine, theirs)


def test_a_setting_assigned_on_the_env_is_refused_and_the_budget_kept():
    env = ViewPlanningEnv(**SMALL)
    message = r"view_budget is a setting of ViewPlanningEnv, fixed when the env is made "
    with pytest.raises(AttributeError, match=message + r".*ViewPlanningEnv\(view_budget=8, "):
        env.view_budget = 8
    assert env.view_budget == env.settings.task.view_budget == 4
    env.reset(seed=0)
    ends = [env.step(np.zeros(3, np.float32))[2] for _ in range(4)]
    assert ends == [False, False, False, True]
    env.close()
