"""liuxing_envs: Gymnasium environments for active perception and gentle manipulation on MuJoCo.

Importing the package registers every id in :data:`ENV_IDS` with Gymnasium, so
``gym.make("ViewPlanning-v0")`` works after ``import liuxing_envs`` (or directly as
``gym.make("liuxing_envs:ViewPlanning-v0")``).
"""

import gymnasium as gym

import liuxing_envs.forking  # noqa: F401 (tracks forks for the calls that would hang)

__version__ = "0.1.0"

# Kept import-free here: = envs.view_planning.DEFAULT_VIEW_BUDGET and
# envs.instrument_grasp.DEFAULT_MAX_EPISODE_STEPS.
VIEW_PLANNING_BUDGET = 4
INSTRUMENT_GRASP_STEPS = 200

ENV_IDS = ("ViewPlanning-v0", "InstrumentGrasp-v0")

if "ViewPlanning-v0" not in gym.registry:
    # The env terminates its episode after view_budget views; the TimeLimit matches the
    # default budget, so pass max_episode_steps too when you change view_budget.
    gym.register(
        id="ViewPlanning-v0",
        entry_point="liuxing_envs.envs.view_planning:ViewPlanningEnv",
        max_episode_steps=VIEW_PLANNING_BUDGET,
    )

if "InstrumentGrasp-v0" not in gym.registry:
    gym.register(
        id="InstrumentGrasp-v0",
        entry_point="liuxing_envs.envs.instrument_grasp:InstrumentGraspEnv",
        max_episode_steps=INSTRUMENT_GRASP_STEPS,
    )
