"""Running the repository's command-line scripts (train.py, evaluate.py) as users do."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
from collections.abc import Callable, Sequence
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


def run_main(
    main: Callable[[list[str]], int], script: str, args: Sequence[str], check: bool = True
) -> subprocess.CompletedProcess:
    """``script``'s ``main(args)`` in this process, as ``python <script> <args>`` runs it:
    ``sys.argv`` set (run folders record the command line), stdout and stderr captured, an
    argparse exit taken as the exit status. The script's imports (torch, SB3) are then paid
    once per test process, not once per run; tests of what only a process shows (signals,
    exit codes of the interpreter, environment variables) use :func:`run_script`."""
    args = [str(arg) for arg in args]
    stdout, stderr = io.StringIO(), io.StringIO()
    saved_argv = sys.argv
    sys.argv = [script, *args]
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            try:
                code = main(args)
            except SystemExit as stop:
                code = stop.code if isinstance(stop.code, int) else int(stop.code is not None)
    finally:
        sys.argv = saved_argv
    if check and code != 0:
        raise AssertionError(f"{script} failed ({code}):\n{stderr.getvalue()[-3000:]}")
    return subprocess.CompletedProcess([script, *args], code, stdout.getvalue(), stderr.getvalue())


def outcomes_without_opengl(code: str):
    """The JSON that ``code`` prints last, run in a fresh interpreter with MuJoCo's OpenGL
    disabled (``MUJOCO_GL`` is read once, when mujoco is imported)."""
    import json

    result = run_script("-c", code, timeout=120, env={"MUJOCO_GL": "disable"})
    return json.loads(result.stdout.splitlines()[-1])
