"""liuxing_envs: Gymnasium environments for active perception and gentle manipulation on MuJoCo.

Importing the package registers every id in :data:`ENV_IDS` with Gymnasium, so
``gym.make("ViewPlanning-v1")`` works after ``import liuxing_envs`` (or directly as
``gym.make("liuxing_envs:ViewPlanning-v1")``). The ids, their variants and versions are listed
in :mod:`liuxing_envs.registration`.
"""

import liuxing_envs.forking  # noqa: F401 (tracks forks for the calls that would hang)
from liuxing_envs.registration import BY_ID, register_all

__version__ = "0.1.0"

#: Every registered id: the v1 tasks and their variants, then the deprecated v0 ids.
ENV_IDS = tuple(BY_ID)

register_all()
