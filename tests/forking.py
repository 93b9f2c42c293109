"""Running a test's code in a child forked from the test process, as a vector env's worker."""

from __future__ import annotations

import multiprocessing


def outcome_in_forked_child(target, *args, timeout: float = 120):
    """Fork a child running ``target(*args, results)``, which puts one outcome on the
    ``results`` queue, and return that outcome; a child that hangs fails the test after
    ``timeout`` seconds (``queue.Empty``) and is killed."""
    fork = multiprocessing.get_context("fork")
    results = fork.Queue()
    child = fork.Process(target=target, args=(*args, results))
    child.start()
    try:
        return results.get(timeout=timeout)
    finally:
        child.join(timeout=10)
        if child.is_alive():
            child.kill()
