"""An on-disk cache of precomputed arrays, shared by processes, runs and users.

Making a ``ViewPlanning-v0`` env ray-casts which ground-truth samples of every object variant
some view can see: seconds per process, paid again by every vector-env worker, test process
and training run. Each result is stored once under a key that hashes everything it was
computed from (the inputs, the source of the module that computes it, and the numpy and
open3d versions), so a stored array is what the computation would return, bit for bit, and
a change to any of them misses the old entry instead of reading it.

An entry is a SHA-256 of its content followed by the array in ``.npy`` format. An entry
that does not match its checksum (a damaged disk, a bad copy, a hand edit) is never used: it
is computed again and replaced, with one warning that names the file. So a cache that
cannot be trusted costs time, never a result.

Where: ``$LIUXING_ENVS_CACHE`` if set (``off`` turns the cache off), else
``$XDG_CACHE_HOME/liuxing_envs`` or ``~/.cache/liuxing_envs``. Deleting the folder is always
safe. Files are created with the user's umask, so a folder shared by a group (umask 002)
serves the group. A folder that cannot be written only costs the time (one warning per
process). Entries that a code change made obsolete stay until the folder is deleted (each is
a few kilobytes). One folder shared by machines of different CPUs may hand one the other's
result: equally valid, though a ray grazing an edge may have landed the other way.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import secrets
import warnings
from pathlib import Path

import numpy as np

CACHE_ENV_VAR = "LIUXING_ENVS_CACHE"
#: Values of ``$LIUXING_ENVS_CACHE`` that turn the cache off.
CACHE_OFF_VALUES = ("off", "0", "false", "no", "none")
#: Bump when the file layout changes; the keys already cover the computations themselves.
CACHE_FORMAT = 2
#: What every entry starts with: the format, then the SHA-256 of the ``.npy`` bytes after it.
ENTRY_MAGIC = b"liuxing_envs cache 2\n"
_DIGEST_SIZE = hashlib.sha256().digest_size

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


def entry_path(kind: str, key: str) -> Path | None:
    """Where the entry of ``kind`` under ``key`` lives, or None when the cache is off."""
    folder = cache_dir()
    return None if folder is None else folder / f"{kind}-{key}.entry"


class DamagedEntryError(ValueError):
    """A cache entry whose bytes are not what was stored."""


def decode_entry(data: bytes) -> np.ndarray:
    """The array an entry's bytes hold; DamagedEntryError unless they match their checksum."""
    header = len(ENTRY_MAGIC) + _DIGEST_SIZE
    if len(data) < header or not data.startswith(ENTRY_MAGIC):
        raise DamagedEntryError("it does not start with the cache's header")
    payload = data[header:]
    if hashlib.sha256(payload).digest() != data[len(ENTRY_MAGIC) : header]:
        raise DamagedEntryError("its content does not match its checksum")
    try:
        return np.load(io.BytesIO(payload), allow_pickle=False)
    except Exception as error:  # noqa: BLE001 - checksummed, yet not an array: a foreign file
        raise DamagedEntryError(f"it holds no array ({error})") from error


def encode_entry(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=False)
    payload = buffer.getvalue()
    return ENTRY_MAGIC + hashlib.sha256(payload).digest() + payload


def load_array(kind: str, key: str, shape: tuple[int, ...], dtype) -> np.ndarray | None:
    """The stored array of ``kind`` under ``key``, or None when there is none or the cache is
    off. An entry that fails its checksum, or holds no array of ``shape`` and ``dtype``, is
    damaged: None, with a warning naming the file (the caller computes and stores it again)."""
    path = entry_path(kind, key)
    if path is None:
        return None
    try:
        data = path.read_bytes()
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as error:
        _warn_unusable(path, f"it cannot be read ({error})")
        return None
    try:
        array = decode_entry(data)
        if array.shape != tuple(shape) or array.dtype != np.dtype(dtype):
            raise DamagedEntryError(
                f"it holds a {array.dtype} array of shape {array.shape}, not {np.dtype(dtype)} "
                f"of shape {tuple(shape)}"
            )
    except DamagedEntryError as error:
        _warn_unusable(path, str(error))
        return None
    return array


def _warn_unusable(path: Path, why: str) -> None:
    warnings.warn(
        f"ignoring the damaged cache entry {path}: {why}; computing it again and replacing it",
        RuntimeWarning,
        stacklevel=3,
    )


def store_array(kind: str, key: str, array: np.ndarray) -> None:
    """Store ``array`` of ``kind`` under ``key``. The file appears whole or not at all, so
    processes filling the cache at once never read half an entry."""
    global _warned_unwritable
    target = entry_path(kind, key)
    if target is None:
        return
    temporary = target.with_name(f".{target.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        # os.open with 0o666, not mkstemp (0o600): the umask decides who else may read it.
        descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(descriptor, "wb") as file:
            file.write(encode_entry(array))
        try:
            os.replace(temporary, target)
        except OSError:
            if not target.exists():
                raise
            # Another process stored it first and the file is in use (Windows): theirs holds
            # the same array.
            temporary.unlink(missing_ok=True)
    except OSError as error:
        with contextlib.suppress(OSError):  # the folder itself may be what is wrong
            temporary.unlink(missing_ok=True)
        if not _warned_unwritable:
            _warned_unwritable = True
            warnings.warn(
                f"cannot write the cache folder {target.parent} ({error}); precomputed results "
                f"will be computed again in every process. Set {CACHE_ENV_VAR} to a writable "
                "folder, or to 'off'.",
                RuntimeWarning,
                stacklevel=2,
            )
