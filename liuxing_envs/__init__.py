"""liuxing_envs: Gymnasium environments for active perception and gentle manipulation on MuJoCo.

Importing the package registers every id in :data:`ENV_IDS` with Gymnasium, so
``gym.make("ViewPlanning-v0")`` works after ``import liuxing_envs`` (or directly as
``gym.make("liuxing_envs:ViewPlanning-v0")``).
"""

import gymnasium as gym

__version__ = "0.1.0"

VIEW_PLANNING_BUDGET = 4  # = envs.view_planning.DEFAULT_VIEW_BUDGET, kept import-free here

ENV_IDS = ("ViewPlanning-v0",)

if "ViewPlanning-v0" not in gym.registry:
    # The env truncates itself after view_budget views; the TimeLimit matches the default
    # budget, so pass max_episode_steps too when you change view_budget.
    gym.register(
        id="ViewPlanning-v0",
        entry_point="liuxing_envs.envs.view_planning:ViewPlanningEnv",
        max_episode_steps=VIEW_PLANNING_BUDGET,
    )
