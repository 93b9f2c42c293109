"""Run one benchmark configuration in a fresh Python process, so each reports its own peak
resident memory and no configuration warms caches for the next."""

from __future__ import annotations

import json
import resource
import subprocess
import sys


def run_in_fresh_process(module: str, *args: str) -> dict:
    """``python -m module *args`` must print its result as a JSON object on its last line."""
    out = subprocess.run(
        [sys.executable, "-m", module, *args], capture_output=True, text=True, check=True
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def peak_rss_mib() -> float:
    """This process's peak resident memory so far (MiB; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
