"""Noticing a simulation that diverged.

MuJoCo answers NaN, inf or huge values in ``qpos``, ``qvel`` or ``qacc`` (its checks in
``mj_step``) by resetting ``mjData`` to the model's defaults and counting a warning; the
simulation then carries on from a state that has nothing to do with the episode. The
environments read the warning counters around each control step and end the episode
(``truncated``, ``info["sim_unstable"] = True``) instead of training on that state; the next
``reset()`` starts clean.
"""

from __future__ import annotations

import math

import mujoco

DIVERGENCE_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADQACC,
)


_DIVERGENCE_INDICES = [int(warning) for warning in DIVERGENCE_WARNINGS]


def divergence_count(data: mujoco.MjData) -> int:
    """How many times MuJoCo has found ``data`` diverged (and reset it) so far."""
    counts = data.warning.number.tolist()  # a third of the cost of indexing the array
    return sum([counts[index] for index in _DIVERGENCE_INDICES])


def diverged_since(data: mujoco.MjData, count_before: int) -> bool:
    """True when MuJoCo reset ``data`` after ``count_before`` was read, or its state is not
    finite now (a sum is finite only if every term is; it costs a microsecond a call)."""
    if divergence_count(data) > count_before:
        return True
    return not math.isfinite(data.qpos.sum() + data.qvel.sum())
