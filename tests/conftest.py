"""Shared pytest setup."""

import atexit
import os
import shutil
import tempfile

# Must happen before anything imports mujoco: the GL backend is chosen at import time. EGL
# works headless (Mesa software rendering when there is no GPU).
os.environ.setdefault("MUJOCO_GL", "egl")

# The tests compute the ground truth they check rather than read it from a disk cache
# filled elsewhere (the user's, or the one $LIUXING_ENVS_CACHE names); the CLIs they start
# in subprocesses share this session's folder.
_session_cache = tempfile.mkdtemp(prefix="liuxing_envs_test_cache_")
os.environ["LIUXING_ENVS_CACHE"] = _session_cache
atexit.register(shutil.rmtree, _session_cache, ignore_errors=True)
