"""open3d in a forked child, where some of its calls wait forever.

open3d starts OpenMP threads when it is imported. A process forked after that inherits the
thread pool's bookkeeping but not its threads, and open3d calls that use the pool then wait
for them: no error, no timeout. Measured with open3d-cpu 0.19 on Linux: normal estimation,
outlier removal (so every :func:`~liuxing_envs.perception.reconstruction.reconstruct`) and a
ray-casting scene of more than one mesh (the observable-surface precomputation of an object
not yet cached) hang; reading meshes and single-mesh ray casting (the ``"embree"`` depth
backend) do not. With ``OMP_NUM_THREADS=1`` nothing hangs.

It matters because ``gym.make_vec(..., vectorization_mode="async")`` forks its workers by
default on Linux, after making one env in the parent, which imports open3d. The calls that
would hang check :func:`check_open3d_not_forked` first and name the fix instead.
"""

from __future__ import annotations

import os
import sys

_forked_after_open3d = False
#: OpenMP reads the variable once, when open3d loads it: read at this module's import (the
#: package's), not at the fork, so setting it later is not taken for a fix it is not.
_single_openmp_thread = os.environ.get("OMP_NUM_THREADS") == "1"


def _after_fork_in_child() -> None:
    global _forked_after_open3d
    if "open3d" in sys.modules and not _single_openmp_thread:
        _forked_after_open3d = True


# Registered when the package is imported, so that it sees forks made before any module
# here imports open3d (the "embree" camera imports it late, user code on its own).
if hasattr(os, "register_at_fork"):  # not on Windows, which cannot fork
    os.register_at_fork(after_in_child=_after_fork_in_child)


def check_open3d_not_forked(what: str) -> None:
    """RuntimeError naming the fix when this process was forked from one that had imported
    open3d, where ``what`` (the call about to run) would wait forever."""
    if _forked_after_open3d:
        raise RuntimeError(
            f"{what} uses open3d, and this process was forked from one that had already "
            "imported it: open3d's OpenMP threads do not survive a fork, so the call would "
            "wait forever. Start worker processes with spawn (gym.make_vec(..., "
            "vectorization_mode='async', vector_kwargs={'context': 'spawn'}); SB3's "
            "SubprocVecEnv, whose default is forkserver, is safe), or set OMP_NUM_THREADS=1 "
            "before the parent process starts"
        )
