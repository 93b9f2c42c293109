"""An on-disk cache of precomputed arrays, shared by processes and runs.

Making a ``ViewPlanning-v0`` env ray-casts which ground-truth samples of every object variant
some view can see: seconds per process, paid again by every vector-env worker, test process
and training run. Each result is stored once under a key that hashes everything it was
computed from (the inputs, the source of the module that computes it, and the numpy and
open3d versions), so a stored array is what the computation would return, bit for bit, and
a change to any of them misses the old entry instead of reading it.

Where: ``$LIUXING_ENVS_CACHE`` if set (``off`` turns the cache off), else
``$XDG_CACHE_HOME/liuxing_envs`` or ``~/.cache/liuxing_envs``. Deleting the folder is always
safe. A damaged entry is computed again and replaced; a folder that cannot be written only
costs the time (one warning per process). Entries that a code change made obsolete stay
until the folder is deleted (each is a few kilobytes). One folder shared by machines of
different CPUs may hand one the other's result: equally valid, though a ray grazing an edge
may have landed the other way.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np

CACHE_ENV_VAR = "LIUXING_ENVS_CACHE"
#: Values of ``$LIUXING_ENVS_CACHE`` that turn the cache off.
CACHE_OFF_VALUES = ("off", "0", "false", "no", "none")
#: Bump when the file layout changes; the keys already cover the computations themselves.
CACHE_FORMAT = 1

_warned_unwritable = False


def cache_dir() -> Path | None:
    """The cache folder now, or None when ``$LIUXING_ENVS_CACHE`` turns it off."""
    value = os.environ.get(CACHE_ENV_VAR)
    if value is not None:
        if value.strip().lower() in CACHE_OFF_VALUES or not value.strip():
            return None
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME")
    if not base:
        try:
            base = Path.home() / ".cache"
        except RuntimeError:  # no home folder to be found: nowhere to keep it
            return None
    return Path(base) / "liuxing_envs"


def cache_key(*parts) -> str:
    """A hex digest of ``parts``: arrays by dtype, shape and bytes; anything else by repr."""
    sha = hashlib.sha256(f"format {CACHE_FORMAT}".encode())
    for part in parts:
        if isinstance(part, np.ndarray):
            sha.update(f"array {part.dtype.str} {part.shape}".encode())
            sha.update(np.ascontiguousarray(part).tobytes())
        else:
            sha.update(f"{type(part).__name__} {part!r}".encode())
        sha.update(b"\x00")
    return sha.hexdigest()


def load_array(kind: str, key: str, shape: tuple[int, ...], dtype) -> np.ndarray | None:
    """The stored array of ``kind`` under ``key``, or None when there is none, the cache is
    off, or the file does not hold an array of ``shape`` and ``dtype`` (a damaged entry)."""
    folder = cache_dir()
    if folder is None:
        return None
    path = folder / f"{kind}-{key}.npy"
    try:
        array = np.load(path, allow_pickle=False)
    except Exception:  # noqa: BLE001 - a damaged header raises tokenize's errors, among others
        return None
    if array.shape != tuple(shape) or array.dtype != np.dtype(dtype):
        return None
    return array


def store_array(kind: str, key: str, array: np.ndarray) -> None:
    """Store ``array`` of ``kind`` under ``key``. The file appears whole or not at all, so
    processes filling the cache at once never read half an entry."""
    global _warned_unwritable
    folder = cache_dir()
    if folder is None:
        return
    temporary = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        descriptor, temporary = tempfile.mkstemp(dir=folder, prefix=f".{kind}-", suffix=".tmp")
        with os.fdopen(descriptor, "wb") as file:
            np.save(file, array, allow_pickle=False)
        target = folder / f"{kind}-{key}.npy"
        try:
            os.replace(temporary, target)
        except OSError:
            if not target.exists():
                raise
            # Another process stored it first and the file is in use (Windows): theirs holds
            # the same array.
            Path(temporary).unlink(missing_ok=True)
    except OSError as error:
        if temporary is not None:
            Path(temporary).unlink(missing_ok=True)
        if not _warned_unwritable:
            _warned_unwritable = True
            warnings.warn(
                f"cannot write the cache folder {folder} ({error}); precomputed results will "
                f"be computed again in every process. Set {CACHE_ENV_VAR} to a writable "
                "folder, or to 'off'.",
                RuntimeWarning,
                stacklevel=2,
            )
