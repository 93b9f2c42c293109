"""Where models saved before the policy parts moved into the package find them.

A saved model names its features extractor by import path; models trained in a checkout before
the move name ``agents.policies.PerceptionExtractor``. New models name
:mod:`liuxing_envs.policy_parts`, which a ``pip install`` of the package ships.
"""

from liuxing_envs.policy_parts import ImageEncoder, OccupancyEncoder, PerceptionExtractor

__all__ = ["ImageEncoder", "OccupancyEncoder", "PerceptionExtractor"]
