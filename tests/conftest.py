"""Shared pytest setup."""

import os

# Must happen before anything imports mujoco: the GL backend is chosen at import time. EGL
# works headless (Mesa software rendering when there is no GPU).
os.environ.setdefault("MUJOCO_GL", "egl")
