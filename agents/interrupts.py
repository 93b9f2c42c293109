"""Ctrl-C and SIGTERM during training: the run stops at the next env step, not mid-call.

A ``KeyboardInterrupt`` raised from a signal handler lands wherever the main thread happens
to be. Inside the ctypes call that makes the EGL context current for a depth render it
surfaces as ``ctypes.ArgumentError: argument 1: KeyboardInterrupt``, which is no
``KeyboardInterrupt``: the run died with exit 1 and no checkpoint (seen once in the test
suite). Inside SB3's buffer or optimiser code it could leave them half updated.

So while training runs inside :func:`deferred`, the handler only records the request;
a callback (``agents.training.StopWhenRequested``) ends ``learn()`` at the next env step
and the run then saves its checkpoint as before. The block lasts until the trained run is
saved, so a signal between the last step and the final checkpoint waits for it. Outside
it (parsing, set-up, which a stopped start undoes, the final evaluation) and for a second
signal, the handler raises ``KeyboardInterrupt`` at once, so a run that no longer steps
can still be stopped.

While the checkpoint of a stopped run is written (:func:`saving`), a second signal only
says so, and a third abandons the checkpoint: a second Ctrl-C is a common reflex while
"saving" shows, and it used to lose every step since the last periodic checkpoint.

Worker processes of a ``SubprocVecEnv`` ignore both signals (:func:`ignore_in_worker`):
Ctrl-C on a terminal, like a scheduler signalling a job's process group, reaches every
process, and a worker killed by it would turn a clean stop into a "worker died" error. The
parent closes them when it stops; a worker whose parent is gone ends on its closed pipe.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
from collections.abc import Iterator

_state = {"deferring": False, "requested": False, "saving": False, "warned": False, "signal": None}


def _handler(signum, frame) -> None:
    _state["signal"] = signum
    if _state["deferring"] and not _state["requested"]:
        _state["requested"] = True
        return
    if _state["saving"] and not _state["warned"]:
        _state["warned"] = True
        # os.write, not print: a handler that prints while the main thread prints raises
        # "reentrant call" in Python's buffered writer.
        os.write(2, b"\nsaving the checkpoint first; signal again to abandon it\n")
        return
    raise KeyboardInterrupt


def install() -> None:
    """Handle SIGINT and SIGTERM (a scheduler's pre-emption, ``kill``) alike. SIGINT is set
    explicitly: a process started in the background by a non-interactive shell inherits it
    ignored, and Python then leaves it ignored."""
    _state["signal"] = None
    signal.signal(signal.SIGTERM, _handler)
    signal.signal(signal.SIGINT, _handler)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Within this block a first signal only sets :func:`requested`."""
    _state.update(deferring=True, requested=False)
    try:
        yield
    finally:
        _state["deferring"] = False


@contextlib.contextmanager
def saving() -> Iterator[None]:
    """Within this block (writing a stopped run's checkpoint) one more signal is only
    reported; the one after raises KeyboardInterrupt."""
    _state.update(saving=True, warned=False)
    try:
        yield
    finally:
        _state["saving"] = False


def requested() -> bool:
    """Whether a signal asked the current :func:`deferred` block to stop."""
    return _state["requested"]


def exit_status() -> int:
    """The exit status of a process the last signal stopped: 128 + its number, as a shell
    reports a process the signal killed (130 for SIGINT, 143 for SIGTERM), so a scheduler
    tells a pre-emption from a Ctrl-C. A KeyboardInterrupt no handled signal raised counts
    as SIGINT."""
    return 128 + (_state["signal"] or signal.SIGINT)


def ignore_in_worker() -> None:
    """In a child process (a vectorised env's worker), ignore SIGINT and SIGTERM; in the
    main process, do nothing."""
    if multiprocessing.parent_process() is not None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
