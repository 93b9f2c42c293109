"""Soak: long seeded random runs of each environment, and many environments created and
closed in one process, watching for what an overnight training run cannot afford.

Run: ``MUJOCO_GL=egl python -m benchmarks.soak`` (about 15 minutes on 2 cores; ``--steps`` and
``--envs`` shorten it). It writes ``benchmarks/SOAK.md`` and ``SOAK.json``. Each run is a fresh
process with the env's default kwargs (``gym.make(env_id)``) and ``render_mode="rgb_array"``
for the create-and-close run, so every close releases a GL context too. It checks:

- no exception, and every observation and reward finite;
- no MuJoCo warning left unhandled: diverged physics (MuJoCo's bad qpos/qvel/qacc warnings)
  must have ended its episode with ``info["sim_unstable"]``, and no other warning may occur;
- resident memory no more than 5% (``--max-growth``) above where it stood after warm-up
  (the first tenth), read after ``malloc_trim`` so that what the allocator keeps for reuse
  is not a leak;
- ``close()`` twice is harmless; creating and closing many envs leaks neither memory (5%
  after the first tenth), file descriptors nor threads.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.isolated import describe_cores, machine, run_in_fresh_process  # noqa: E402
from benchmarks.report_files import check_writable, report_paths  # noqa: E402
from liuxing_envs.registration import REGISTRATIONS  # noqa: E402
from liuxing_envs.sim.stability import DIVERGENCE_WARNINGS  # noqa: E402

#: The benchmark tasks, not their variants (the RGB-D grasp variant's memory grows 40-50% in
#: 400 steps when a second instrument is first rendered, which a soak of this length does
#: not tell from a leak).
ENV_IDS = tuple(r.env_id for r in REGISTRATIONS if not r.deprecated and not r.kwargs)
DEFAULT_STEPS = 100_000
DEFAULT_ENVS = 200
MAX_GROWTH = 0.05
DEFAULT_OUT = Path(__file__).parent / "SOAK.md"
try:
    _LIBC = ctypes.CDLL("libc.so.6")
except OSError:  # not glibc: memory is read untrimmed
    _LIBC = None
_WARNING_NAMES = [mujoco.mjtWarning(i).name for i in range(mujoco.mjtWarning.mjNWARNING)]


def resident_mib() -> float:
    """Current resident memory of this process (MiB), from /proc, after asking glibc to
    hand back the free memory it keeps for reuse (``malloc_trim``): a leak is memory that
    cannot be reused, and Mesa's freed GL buffers otherwise stay mapped for a while."""
    if _LIBC is not None:
        _LIBC.malloc_trim(0)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def _live_data(env) -> mujoco.MjData:
    inner = env.unwrapped
    return inner.world.data if hasattr(inner, "world") else inner.data


def _warnings(data: mujoco.MjData) -> np.ndarray:
    return np.array([data.warning[i].number for i in range(len(_WARNING_NAMES))])


def soak(env_id: str, steps: int) -> dict:
    """``steps`` seeded random steps of ``gym.make(env_id)``, resets included."""
    env = gym.make(env_id)
    env.unwrapped.prepare_objects()  # what each object's first episode builds is no leak
    env.action_space.seed(0)
    env.reset(seed=0)
    warnings = np.zeros(len(_WARNING_NAMES), dtype=np.int64)
    episodes, unstable, non_finite = 1, 0, 0
    samples, every = [], max(1, steps // 20)
    started = time.perf_counter()
    for step in range(1, steps + 1):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        non_finite += not np.isfinite(reward) or not all(
            np.isfinite(value).all() for value in obs.values()
        )
        unstable += bool(info["sim_unstable"])
        if terminated or truncated:
            warnings += _warnings(_live_data(env))  # reset() clears MuJoCo's counters
            env.reset()
            episodes += 1
        if step % every == 0:
            samples.append((step, resident_mib()))
    warnings += _warnings(_live_data(env))
    seconds = time.perf_counter() - started
    env.close()
    env.close()
    divergences = int(sum(warnings[int(w)] for w in DIVERGENCE_WARNINGS))
    other = {
        name: int(count)
        for i, (name, count) in enumerate(zip(_WARNING_NAMES, warnings, strict=True))
        if count and i not in {int(w) for w in DIVERGENCE_WARNINGS}
    }
    return {
        "env_id": env_id,
        "steps": steps,
        "episodes": episodes,
        "seconds": round(seconds, 1),
        "sim_unstable_episodes": unstable,
        "divergence_warnings": divergences,
        "other_warnings": other,
        "non_finite_steps": non_finite,
        **_growth(samples),
    }


def create_and_close(env_id: str, count: int) -> dict:
    """``count`` envs made, reset, stepped, rendered and closed (twice) one after another."""
    samples = []
    started = time.perf_counter()
    for k in range(1, count + 1):
        env = gym.make(env_id, render_mode="rgb_array")
        if k == 1:  # the per-object set-ups the envs of a process share, built once
            env.unwrapped.prepare_objects()
        env.action_space.seed(k)
        env.reset(seed=k)
        env.step(env.action_space.sample())
        env.render()
        env.close()
        env.close()
        if k % max(1, count // 20) == 0:
            samples.append((k, resident_mib(), _open_files(), threading.active_count()))
    first_tenth = samples[_warm_index(len(samples))]
    return {
        "env_id": env_id,
        "envs": count,
        "seconds": round(time.perf_counter() - started, 1),
        **_growth([(k, mib) for k, mib, _, _ in samples]),
        "open_files": [first_tenth[2], samples[-1][2]],
        "threads": [first_tenth[3], samples[-1][3]],
    }


def _warm_index(count: int) -> int:
    """Index of the last sample of the warm-up (the first tenth of a run)."""
    return max(0, count // 10 - 1)


def _open_files() -> int:
    return len(os.listdir("/proc/self/fd"))


def _growth(samples: list[tuple[int, float]]) -> dict:
    """Resident memory after the first tenth of the run (warm-up) and its largest later
    value, as MiB and as a growth ratio."""
    warm = samples[_warm_index(len(samples))][1]
    peak_after = max(mib for _, mib in samples[len(samples) // 10 :])
    return {
        "rss_after_warmup_mib": round(warm, 1),
        "rss_peak_after_mib": round(peak_after, 1),
        "rss_growth": round(peak_after / warm - 1.0, 4),
    }


def verdict(result: dict, max_growth: float = MAX_GROWTH) -> list[str]:
    """What went wrong in one run (empty: nothing)."""
    problems = []
    if result["rss_growth"] > max_growth:
        problems.append(f"resident memory grew {100 * result['rss_growth']:.1f}%")
    if result.get("non_finite_steps"):
        problems.append(f"{result['non_finite_steps']} steps with non-finite values")
    if result.get("other_warnings"):
        problems.append(f"MuJoCo warnings {result['other_warnings']}")
    if result.get("divergence_warnings", 0) > result.get("sim_unstable_episodes", 0):
        problems.append("diverged physics that no sim_unstable truncation reported")
    if "open_files" in result and result["open_files"][1] > result["open_files"][0]:
        problems.append(f"open files grew {result['open_files']}")
    if "threads" in result and result["threads"][1] > result["threads"][0]:
        problems.append(f"threads grew {result['threads']}")
    return problems


def report(results: list[dict], command: str, max_growth: float = MAX_GROWTH) -> str:
    info = machine()
    lines = [
        "# Soak results",
        "",
        f"Generated by `{command}` on {info['date']} (commit {info['commit']}); "
        f"{info['cpu']}, {describe_cores(info)}; MUJOCO_GL={info['MUJOCO_GL']}.",
        "",
        "| run | env | size | seconds | episodes | sim_unstable | RSS after warm-up MiB "
        "| peak after MiB | growth | files | threads | problems |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in results:
        kind = "random steps" if "steps" in r else "create + close"
        size = r.get("steps", r.get("envs"))
        problems = "; ".join(verdict(r, max_growth)) or "none"
        lines.append(
            f"| {kind} | {r['env_id']} | {size:,} | {r['seconds']} | {r.get('episodes', '')} "
            f"| {r.get('sim_unstable_episodes', '')} | {r['rss_after_warmup_mib']} "
            f"| {r['rss_peak_after_mib']} | {100 * r['rss_growth']:+.1f}% "
            f"| {' -> '.join(map(str, r.get('open_files', [])))} "
            f"| {' -> '.join(map(str, r.get('threads', [])))} | {problems} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.soak", description=__doc__)
    parser.add_argument("--steps", type=int, default=DEFAULT_STEPS, help="random steps per env")
    parser.add_argument("--envs", type=int, default=DEFAULT_ENVS, help="envs created and closed")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="Markdown report path")
    parser.add_argument(
        "--max-growth",
        type=float,
        default=MAX_GROWTH,
        help="largest resident-memory growth after warm-up that is not a leak (a fraction; "
        "short runs need more: their warm-up of one tenth is too short to fill the per-object "
        "mesh and sample caches)",
    )
    parser.add_argument("--child", nargs=3, metavar=("KIND", "ENV", "SIZE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        kind, env_id, size = args.child
        result = (soak if kind == "soak" else create_and_close)(env_id, int(size))
        print(json.dumps(result))
        return 0
    if args.steps < 20 or args.envs < 10:
        parser.error("--steps must be >= 20 and --envs >= 10 (memory is sampled 20 times)")
    if not 0.0 < args.max_growth < 1.0:
        parser.error(f"--max-growth must be a fraction in (0, 1), got {args.max_growth}")
    json_path = report_paths(parser, args.out)
    check_writable(parser, args.out, json_path)
    results = []
    for env_id in ENV_IDS:
        for kind, size in (("soak", args.steps), ("create", args.envs)):
            print(f"soak: {kind} {env_id} {size}", file=sys.stderr, flush=True)
            results.append(
                run_in_fresh_process("benchmarks.soak", "--child", kind, env_id, str(size))
            )
    command = "python -m benchmarks.soak " + " ".join(argv if argv is not None else sys.argv[1:])
    args.out.write_text(report(results, command.strip(), args.max_growth))
    json_path.write_text(json.dumps(results, indent=2) + "\n")
    failures = [(r["env_id"], found) for r in results if (found := verdict(r, args.max_growth))]
    for env_id, problems in failures:
        print(f"soak FAILED for {env_id}: {'; '.join(problems)}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
