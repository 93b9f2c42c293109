"""Shared pytest setup."""

import atexit
import os
import shutil
import tempfile

# Must happen before anything imports mujoco: the GL backend is chosen at import time. EGL
# works headless (Mesa software rendering when there is no GPU).
os.environ.setdefault("MUJOCO_GL", "egl")

# The tests compute the ground truth they check rather than read it from a disk cache
# filled elsewhere (the user's, or the one $LIUXING_ENVS_CACHE names). The CLIs they start in
# subprocesses, and pytest-xdist's workers (which inherit the environment of the process that
# starts them), share this session's folder.
_SESSION_CACHE_VARIABLE = "LIUXING_ENVS_TEST_SESSION_CACHE"
if _SESSION_CACHE_VARIABLE not in os.environ:
    os.environ[_SESSION_CACHE_VARIABLE] = tempfile.mkdtemp(prefix="liuxing_envs_test_cache_")
    atexit.register(shutil.rmtree, os.environ[_SESSION_CACHE_VARIABLE], ignore_errors=True)
os.environ["LIUXING_ENVS_CACHE"] = os.environ[_SESSION_CACHE_VARIABLE]
