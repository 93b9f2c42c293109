"""One trial of a sweep, in its own process: ``python -m agents.sweep_trial RUN_DIR`` with the
trial's resolved run configuration (pickled) on stdin.

It does what ``train.py`` does with that configuration: starts the run in ``RUN_DIR``, or,
where the folder already holds it, resumes it from its newest checkpoint (a retried trial),
or leaves a finished run alone; a run stopped before its first checkpoint starts again.
Ctrl-C and SIGTERM save a checkpoint first, as in ``train.py``.
"""

from __future__ import annotations

import pickle
import shutil
import sys
from pathlib import Path

from liuxing_envs.opengl import use_headless_default

use_headless_default()

from agents import interrupts  # noqa: E402
from agents.run_folder import CONFIG, latest_checkpoint  # noqa: E402


def thread_counts() -> str:
    """The threads torch and numba may use here (the trial's CPU budget caps both)."""
    import torch

    from liuxing_envs import kernels

    numba = "none (not installed)"
    if kernels.available():
        import numba as numba_module

        numba = str(numba_module.config.NUMBA_NUM_THREADS)
    return f"torch {torch.get_num_threads()}, numba {numba}"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m agents.sweep_trial RUN_DIR < pickled-config", file=sys.stderr)
        return 2
    run_dir = Path(argv[0])
    config = pickle.load(sys.stdin.buffer)
    interrupts.install()
    with interrupts.deferred():
        from agents import training
    print(f"threads: {thread_counts()}", flush=True)
    if (run_dir / CONFIG).is_file() and latest_checkpoint(run_dir) is None:
        # Stopped before its first checkpoint (a worker killed outright): nothing to resume.
        print(f"{run_dir} stopped before its first checkpoint: starting it again", flush=True)
        shutil.rmtree(run_dir)
    try:
        if not (run_dir / CONFIG).is_file():
            print(f"run folder: {run_dir}", flush=True)
            training.train(config, run_dir)
            return 0
        left = training.work_left(run_dir)
        if not left:
            print(f"{run_dir} finished before; kept", flush=True)
            return 0
        print(f"{run_dir} resumed ({', '.join(left)} left)", flush=True)
        training.resume(run_dir)
    except KeyboardInterrupt:
        return interrupts.exit_status()
    return 0


if __name__ == "__main__":
    sys.exit(main())
