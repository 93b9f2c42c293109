"""Running the repository's command-line scripts (train.py, evaluate.py) as users do."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run_script(
    script: str, *args: str, check: bool = True, timeout: float = 900, env: dict | None = None
):
    """``python <script> <args>`` in the repository root, with ``env`` added to the
    environment variables; with ``check``, a non-zero exit fails the test with the script's
    stderr."""
    result = subprocess.run(
        [sys.executable, script, *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), **(env or {})},
    )
    if check and result.returncode != 0:
        raise AssertionError(f"{script} failed ({result.returncode}):\n{result.stderr[-3000:]}")
    return result


def outcomes_without_opengl(code: str):
    """The JSON that ``code`` prints last, run in a fresh interpreter with MuJoCo's OpenGL
    disabled (``MUJOCO_GL`` is read once, when mujoco is imported)."""
    import json

    result = run_script("-c", code, timeout=120, env={"MUJOCO_GL": "disable"})
    return json.loads(result.stdout.splitlines()[-1])
