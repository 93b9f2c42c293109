"""MuJoCo's OpenGL platform, the ``MUJOCO_GL`` variable, settled before mujoco is imported.

The envs fall back to the ray-cast depth backend when no OpenGL context can be made, but a
``MUJOCO_GL`` value MuJoCo does not know makes ``import mujoco`` itself raise, before any of
that code runs. The command-line tools check for it first and name the allowed values instead
of printing the traceback.
"""

from __future__ import annotations

import os

from liuxing_envs.forking import check_opengl_not_forked, note_opengl_context

#: The command-line tools' platform when MUJOCO_GL is unset: headless, as on a server or CI.
DEFAULT_MUJOCO_GL = "egl"
#: What each Linux value of MUJOCO_GL needs, for the error message.
LINUX_PLATFORMS = (
    ("egl", "headless; libEGL, GPU or Mesa"),
    ("osmesa", "headless, software; libOSMesa"),
    ("glx", "an X display"),
    ("glfw", "an X display"),
    ("disable", "no OpenGL: depth images are ray-cast"),
)


def use_headless_default() -> None:
    """Make headless EGL the platform unless MUJOCO_GL (and PyOpenGL's) already say one."""
    os.environ.setdefault("MUJOCO_GL", DEFAULT_MUJOCO_GL)
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])


def mujoco_import_problem() -> str | None:
    """None when mujoco imports; else a message naming the MUJOCO_GL value that stops it and
    the allowed ones. Other import errors (mujoco missing) are raised as they are."""
    try:
        import mujoco  # noqa: F401
    except RuntimeError as error:
        if "MUJOCO_GL" not in str(error):
            raise
        allowed = "; ".join(f"{name} ({needs})" for name, needs in LINUX_PLATFORMS)
        return (
            f"MuJoCo cannot start with MUJOCO_GL={os.environ.get('MUJOCO_GL', '')!r} ({error}). "
            f"Set MUJOCO_GL to one of: {allowed}."
        )
    return None


def opengl_disabled() -> bool:
    """Whether MuJoCo runs without OpenGL (``MUJOCO_GL=disable``, read once, when mujoco is
    imported). Its renderers are then made without complaint and fail on first use with an
    AttributeError that names no setting, so the envs check this when they are made."""
    try:
        from mujoco.rendering.classic import gl_context
    except ImportError:  # mujoco before 3.4 kept it at the top level
        from mujoco import gl_context
    return not hasattr(gl_context, "GLContext")


def require_opengl(name: str, value, instead: str) -> None:
    """ValueError naming the keyword ``name=value``, which renders with OpenGL, when MuJoCo
    runs without it, and what works instead."""
    if opengl_disabled():
        raise ValueError(
            f"{name}={value!r} needs OpenGL, but MuJoCo was imported with it disabled "
            f"(MUJOCO_GL={os.environ.get('MUJOCO_GL', '')!r}): set MUJOCO_GL to egl, osmesa or "
            f"glfw before mujoco is imported, or use {name}={instead}"
        )


def new_renderer(model, height: int, width: int):
    """A :class:`mujoco.Renderer` of ``model``, refused where it would hang (see
    :mod:`liuxing_envs.forking`)."""
    check_opengl_not_forked()
    import mujoco

    note_opengl_context()
    return mujoco.Renderer(model, height=height, width=width)
