"""Library state a forked process inherits half-copied, and the checks that name the fix.

A child forked from a process that had started either of these waits forever (no error, no
timeout) in some calls, measured on Linux:

* **An OpenGL context** (MuJoCo's EGL, OSMesa or GLX renderers): the child inherits the
  driver's threads and locks half-copied, and its first context or render hangs.
* **open3d** (open3d-cpu 0.19): importing it starts OpenMP threads, which the child
  inherits the bookkeeping of but not the threads. Normal estimation, outlier removal (so
  every :func:`~liuxing_envs.perception.reconstruction.reconstruct`) and a ray-casting scene
  of more than one mesh (the observable-surface precomputation of an object not yet cached)
  then wait for them; reading meshes and single-mesh ray casting (the ``"embree"`` depth
  backend) do not. With ``OMP_NUM_THREADS=1`` nothing hangs.

It matters because ``gym.make_vec(..., vectorization_mode="async")`` forks its workers by
default on Linux (Python before 3.14), after making one env in the parent, which imports
open3d; a parent that has rendered also holds an OpenGL context. The calls that would hang
check first and raise instead.
"""

from __future__ import annotations

import os
import sys

#: What every message offers: worker processes that start clean.
_START_CLEAN = (
    "start worker processes with spawn (gym.make_vec(..., vectorization_mode='async', "
    "vector_kwargs={'context': 'spawn'}); SB3's SubprocVecEnv, whose default is forkserver, "
    "is safe)"
)

_made_opengl_context = False
#: OpenMP reads the variable once, when open3d loads it: read at this module's import (the
#: package's), not at the fork, so setting it later is not taken for a fix it is not.
_single_openmp_thread = os.environ.get("OMP_NUM_THREADS") == "1"
_forked_after_opengl = False
_forked_after_open3d = False


def _after_fork_in_child() -> None:
    global _forked_after_opengl, _forked_after_open3d
    if _made_opengl_context:  # inherited, so a grandchild is refused too
        _forked_after_opengl = True
    if "open3d" in sys.modules and not _single_openmp_thread:
        _forked_after_open3d = True


# Registered when the package is imported, so that it sees forks made before any module
# here imports open3d (the "embree" camera imports it late, user code on its own).
if hasattr(os, "register_at_fork"):  # not on Windows, which cannot fork
    os.register_at_fork(after_in_child=_after_fork_in_child)


def note_opengl_context() -> None:
    """Record that this process makes an OpenGL context (called before the attempt: one
    that fails part-way has already set up the driver)."""
    global _made_opengl_context
    _made_opengl_context = True


def check_opengl_not_forked() -> None:
    """RuntimeError naming the fix in a process forked from one that had made an OpenGL
    context, where making a context or rendering with an inherited one would hang."""
    if _forked_after_opengl:
        raise RuntimeError(
            "this process was forked from one that had made an OpenGL context, and OpenGL "
            f"hangs in such a child: {_START_CLEAN}, or make the envs before anything "
            "renders (depth_backend='raycast' needs no OpenGL)"
        )


def check_open3d_not_forked(what: str) -> None:
    """RuntimeError naming the fix when this process was forked from one that had imported
    open3d, where ``what`` (the call about to run) would wait forever."""
    if _forked_after_open3d:
        raise RuntimeError(
            f"{what} uses open3d, and this process was forked from one that had already "
            "imported it: open3d's OpenMP threads do not survive a fork, so the call would "
            f"wait forever: {_START_CLEAN}, or set OMP_NUM_THREADS=1 before the parent "
            "process starts"
        )
