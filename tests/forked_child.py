"""Running a test's code in a child forked from the test process, as a vector env's worker."""

from __future__ import annotations

import multiprocessing
import queue
import time


def outcome_in_forked_child(target, *args, timeout: float = 120):
    """Fork a child running ``target(*args, results)``, which puts one outcome on the
    ``results`` queue, and return that outcome. A child that dies without one fails the
    test at once, naming its exit code; one that hangs fails it after ``timeout`` seconds
    and is killed."""
    fork = multiprocessing.get_context("fork")
    results = fork.Queue()
    child = fork.Process(target=target, args=(*args, results))
    child.start()
    deadline = time.monotonic() + timeout
    try:
        while True:
            try:
                return results.get(timeout=1.0)
            except queue.Empty:
                pass
            if not child.is_alive():
                try:  # it may have put its outcome just before exiting
                    return results.get(timeout=1.0)
                except queue.Empty:
                    raise AssertionError(
                        f"the forked child exited with code {child.exitcode} and no outcome"
                    ) from None
            if time.monotonic() > deadline:
                raise AssertionError(f"the forked child gave no outcome in {timeout} s: it hangs")
    finally:
        child.join(timeout=10)
        if child.is_alive():
            child.kill()
