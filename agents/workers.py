"""The worker processes of a ``SubprocVecEnv``: what became of a dead one, and stopping the rest.

Workers ignore SIGINT and SIGTERM (see :mod:`agents.interrupts`), so that a signal to the
whole process group leaves the parent to stop them in order. The other side of that: when a
worker dies (killed by hand, by the kernel's out-of-memory killer, or on an exception), SB3's
``close()`` stops at the dead worker's pipe, and at exit Python's ``multiprocessing`` sends
SIGTERM to the survivors and waits for them for ever. :func:`stop` ends every worker in a
bounded time instead, killing what does not close by itself.
"""

from __future__ import annotations

import contextlib
import signal
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # SB3 (torch) is imported by the callers; train.py imports this before it
    from stable_baselines3.common.vec_env import SubprocVecEnv, VecEnv

#: What the parent of a SubprocVecEnv sees when a worker process has died.
WORKER_GONE = (EOFError, BrokenPipeError, ConnectionResetError)
#: How long a worker gets to close its env before it is killed.
CLOSE_GRACE_SECONDS = 5.0
#: How long a worker's death may take to be reported after its pipe closed.
REAP_SECONDS = 2.0


class WorkerDied(RuntimeError):
    """Training ended because a worker process of its vectorised env died."""


def subprocess_vec_env(venv: VecEnv | None) -> SubprocVecEnv | None:
    """The SubprocVecEnv under ``venv``'s wrappers (VecNormalize, ...), or None."""
    from stable_baselines3.common.vec_env import SubprocVecEnv

    while venv is not None and not isinstance(venv, SubprocVecEnv):
        venv = getattr(venv, "venv", None)
    return venv


def describe_dead(venv: VecEnv) -> str | None:
    """What is known of ``venv``'s dead workers, after one's pipe closed: which worker, its
    pid, and the signal that killed it or the status it exited with. None when ``venv`` has
    no worker processes."""
    workers = subprocess_vec_env(venv)
    if workers is None:
        return None
    processes = workers.processes
    deadline = time.monotonic() + REAP_SECONDS
    while not any(p.exitcode is not None for p in processes) and time.monotonic() < deadline:
        time.sleep(0.02)
    dead = [(rank, p) for rank, p in enumerate(processes) if p.exitcode is not None]
    if not dead:
        return "a worker process died (its exit status is not known)"
    return "; ".join(
        f"worker {rank} of {len(processes)} (pid {p.pid}) {_death(p.exitcode)}" for rank, p in dead
    )


def _death(exitcode: int) -> str:
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        cause = " (by hand, or by the kernel's out-of-memory killer)" if exitcode == -9 else ""
        return f"was killed by {name}{cause} and printed no traceback"
    if exitcode == 0:
        return "exited early with status 0"
    return (
        f"exited with status {exitcode}; its traceback is printed above and ends with the "
        "env and the step that failed"
    )


def stop(venv: VecEnv | None, grace: float = CLOSE_GRACE_SECONDS) -> None:
    """Close ``venv``; its workers, if any, are asked to close their envs and killed if they
    have not ended after ``grace`` seconds. Safe with dead workers, and when already closed."""
    workers = subprocess_vec_env(venv)
    if workers is None:
        if venv is not None:
            venv.close()
        return
    if workers.closed:
        return
    deadline = time.monotonic() + grace
    for remote in workers.remotes:
        # A worker still stepping answers first; a dead one's pipe is at its end.
        with contextlib.suppress(*WORKER_GONE, OSError):
            if workers.waiting and remote.poll(max(0.0, deadline - time.monotonic())):
                remote.recv()
        with contextlib.suppress(*WORKER_GONE, OSError):
            remote.send(("close", None))
    for process in workers.processes:
        process.join(max(0.0, deadline - time.monotonic()))
    for process in workers.processes:
        if process.is_alive():
            process.kill()  # SIGKILL: the workers ignore SIGTERM
            process.join(REAP_SECONDS)
    for remote in workers.remotes:
        remote.close()
    workers.waiting = False
    workers.closed = True
