"""Shared machinery of the benchmarks: one measurement per fresh Python process (so each
reports its own peak resident memory and none warms caches for the next), random-action
timing, and a description of the machine and library versions."""

from __future__ import annotations

import importlib.metadata
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

from agents.run_folder import git_commit

REPO = Path(__file__).resolve().parents[1]


def run_in_fresh_process(module: str, *args: str, optimize: bool = False) -> dict:
    """``python -m module *args`` must print its result as a JSON object on its last line.
    ``optimize`` runs it as ``python -O`` (asserts stripped)."""
    command = [sys.executable, *(["-O"] if optimize else []), "-m", module, *args]
    done = subprocess.run(command, capture_output=True, text=True, cwd=REPO)
    if done.returncode != 0:
        raise RuntimeError(
            f"{' '.join(command)} failed with exit status {done.returncode}:\n{done.stderr[-3000:]}"
        )
    return json.loads(done.stdout.strip().splitlines()[-1])


def peak_rss_mib() -> float:
    """This process's peak resident memory so far (MiB). Linux's ``VmHWM``: ``ru_maxrss``
    would start a child at its parent's peak, as a forked process inherits it."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def random_action_throughput(env, steps: int, repeats: int, warmup: int) -> dict:
    """Env steps/s under seeded uniform random actions, resets included: ``warmup`` steps
    untimed, then ``repeats`` runs of ``steps``, each from a fresh episode. Closes ``env``.
    Returns the median, min and max rate and the process's peak resident memory (MiB)."""
    env.action_space.seed(0)
    env.reset(seed=0)  # seeds the episode stream

    def run(count: int) -> float:
        return count / random_steps(env, count)

    run(warmup)
    rates = sorted(run(steps) for _ in range(repeats))
    env.close()
    return {**spread(rates), "mib": peak_rss_mib()}


def random_steps(env, count: int) -> float:
    """Seconds taken by ``count`` steps of the env's seeded random actions, each run starting
    a fresh episode (the env must have been reset with a seed once). The actions are drawn
    before the clock starts: Gymnasium's ``Box.sample`` costs about 70 µs, a tenth of a grasp
    step, and it is the agent's cost, not the env's (the physics limit leaves it out too)."""
    actions = random_actions(env.action_space, count)
    done, start = True, time.perf_counter()
    for action in actions:
        if done:
            env.reset()
        _, _, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
    return time.perf_counter() - start


def random_actions(action_space, count: int) -> list:
    """The next ``count`` seeded random actions of ``action_space``, drawn in order."""
    return [action_space.sample() for _ in range(count)]


def spread(values) -> dict:
    """Median, min and max of a few repeated measurements."""
    values = sorted(values)
    return {"median": values[len(values) // 2], "min": values[0], "max": values[-1]}


def gl_renderer() -> str:
    """The OpenGL renderer that MUJOCO_GL gives (``llvmpipe ...`` is Mesa's software one, on
    the CPU; a GPU's name means the gl rows rendered there), or why there is none."""
    if not os.environ.get("MUJOCO_GL"):
        return "none (MUJOCO_GL unset)"
    probe = (
        "import mujoco\n"
        "context = mujoco.GLContext(1, 1)\n"
        "context.make_current()\n"
        "from OpenGL import GL\n"
        "print(GL.glGetString(GL.GL_RENDERER).decode())\n"
        "context.free()\n"
    )
    # In a child process, so no GL context outlives the probe in the benchmark's own.
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    if done.returncode != 0 or not done.stdout.strip():
        return "none (no GL context)"
    return done.stdout.strip().splitlines()[-1]


def describe_cores(machine: dict) -> str:
    """``"2 cores"``, or ``"2 of its 16 cores usable by this run"`` under ``taskset``."""
    usable = machine.get("usable_cores", machine["cores"])
    if usable == machine["cores"]:
        return f"{usable} cores"
    return f"{usable} of its {machine['cores']} cores usable by this run"


def machine() -> dict:
    """What the figures were measured on: CPU, cores, memory, OS, Python, library versions,
    the rendering back end and the git commit."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        pages = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        memory = f"{pages / 2**30:.0f} GiB"
    except (ValueError, OSError):
        memory = "unknown"
    versions = {}
    for package in (
        "mujoco",
        "gymnasium",
        "numpy",
        "stable_baselines3",
        "torch",
        "open3d-cpu",
        "gymnasium-robotics",
    ):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            continue
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        # A run under `taskset` sees fewer cores than the machine has; its figures are for those.
        "usable_cores": len(os.sched_getaffinity(0)),
        "gl_renderer": gl_renderer(),
        "memory": memory,
        "os": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "versions": versions,
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", ""),
        "commit": git_commit(REPO) or "unknown",
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }
