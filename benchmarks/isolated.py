"""Throughput benchmarks: one configuration per fresh Python process (so each reports its own
peak resident memory and none warms caches for the next), timed under random actions."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time


def run_in_fresh_process(module: str, *args: str) -> dict:
    """``python -m module *args`` must print its result as a JSON object on its last line."""
    out = subprocess.run(
        [sys.executable, "-m", module, *args], capture_output=True, text=True, check=True
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def peak_rss_mib() -> float:
    """This process's peak resident memory so far (MiB; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def random_action_throughput(env, steps: int, repeats: int, warmup: int) -> dict:
    """Env steps/s under seeded uniform random actions, resets included: ``warmup`` steps
    untimed, then ``repeats`` runs of ``steps``, each from a fresh episode. Closes ``env``.
    Returns the median, min and max rate and the process's peak resident memory (MiB)."""
    env.action_space.seed(0)
    env.reset(seed=0)  # seeds the episode stream

    def run(count: int) -> float:
        done, start = True, time.perf_counter()
        for _ in range(count):
            if done:
                env.reset()
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            done = terminated or truncated
        return count / (time.perf_counter() - start)

    run(warmup)
    rates = sorted(run(steps) for _ in range(repeats))
    env.close()
    return {
        "median": rates[len(rates) // 2],
        "min": rates[0],
        "max": rates[-1],
        "mib": peak_rss_mib(),
    }
