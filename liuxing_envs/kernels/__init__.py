"""Compiled kernels (numba) for the hot paths of a view step and of a grasp step.

Each kernel lives in its own module of this package together with the helpers it calls:
numba invalidates a function's on-disk cache only when the file that defines it changes, and
it freezes module globals into the compiled code, so every tunable is passed as an argument
and a kernel reads nothing another module defines or decides (no other module's kernels, no
constant computed from another module; ``tests/test_kernel_modules.py`` checks this).
Every kernel has a reference in numpy or MuJoCo that it is tested against (equal results, or
a stated bound), and the package works without numba: :func:`available` is then False and
callers use their references.

Importing this package does not import numba (about half a second); callers reach a kernel
module through :func:`module`, which imports it at its first use. A kernel compiles on its
first call (seconds), and the machine code is cached on disk in ``$NUMBA_CACHE_DIR``, next to
the sources or in ``~/.cache/numba`` (numba's own order), so later processes load it in
milliseconds. Where none of those can be written (a read-only install with no writable home)
kernels compile in every process, with one warning.
"""

from __future__ import annotations

import ctypes
import functools
import importlib
import importlib.util
import os
import tempfile
import warnings
from pathlib import Path
from types import ModuleType

import numpy as np

#: Options every kernel compiles with. ``error_model="numpy"``: a division by zero gives
#: inf or nan as in numpy (the references rely on it) instead of raising. No ``fastmath``:
#: results must equal their references bit for bit.
KERNEL_OPTIONS = {"nogil": True, "error_model": "numpy"}


@functools.cache
def module(name: str) -> ModuleType:
    """The kernel module ``name`` of this package (``module("fusion")``), imported at its
    first use. Callers in a step's path look their kernels up here: an import statement in
    a function runs the import machinery every time (a microsecond or two), this a cached
    call."""
    return importlib.import_module(f"{__name__}.{name}")


@functools.cache
def available() -> bool:
    """Whether numba can be imported (then the compiled kernels are used)."""
    return importlib.util.find_spec("numba") is not None


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError:
        return False
    return True


@functools.cache
def disk_cache() -> bool:
    """Whether compiled kernels can be cached on disk (numba raises at the first compile when
    no place it looks in is writable, so this is decided before)."""
    candidates = []
    if os.environ.get("NUMBA_CACHE_DIR"):
        candidates.append(Path(os.environ["NUMBA_CACHE_DIR"]))
    candidates.append(Path(__file__).parent / "__pycache__")
    try:
        candidates.append(Path.home() / ".cache" / "numba")
    except RuntimeError:
        pass
    if any(_writable(folder) for folder in candidates):
        return True
    warnings.warn(
        "liuxing_envs: no folder for numba's cache can be written (set NUMBA_CACHE_DIR to a "
        "writable folder); the kernels compile again in every process",
        RuntimeWarning,
        stacklevel=2,
    )
    return False


def jit_options() -> dict:
    """Keyword arguments for ``numba.njit`` of every kernel and helper in this package."""
    return {"cache": disk_cache(), **KERNEL_OPTIONS}


#: Arguments of CBLAS: row-major storage, matrices not transposed.
_ROW_MAJOR, _NO_TRANS = 101, 111


@functools.cache
def numpy_dgemm() -> int | None:
    """The address of the ``cblas_dgemm`` that numpy's ``matmul`` calls for float64
    matrices (the OpenBLAS numpy's wheels ship, with 64-bit integers), for kernels whose
    matrix products must be numpy's bit for bit; None where it is not found, or where calling
    it does not reproduce ``matmul`` on this machine (callers then keep numpy's products)."""
    try:
        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
    except (KeyError, TypeError, AttributeError):
        return None
    if blas.get("name") != "scipy-openblas" or "USE64BITINT" not in str(
        blas.get("openblas configuration", "")
    ):
        return None
    for path in sorted((Path(np.__file__).parent.parent / "numpy.libs").glob("*openblas64*")):
        try:
            dgemm = ctypes.CDLL(str(path)).scipy_cblas_dgemm64_
        except (OSError, AttributeError):
            continue
        if _reproduces_matmul(dgemm):
            return ctypes.cast(dgemm, ctypes.c_void_p).value
    return None


def _reproduces_matmul(dgemm) -> bool:
    """Whether ``dgemm`` gives ``a @ b``'s bits for seeded 4x4 matrices."""
    size, pointer = ctypes.c_int64, ctypes.c_void_p
    dgemm.argtypes = [ctypes.c_int] * 3 + [size] * 3 + [ctypes.c_double, pointer, size]
    dgemm.argtypes += [pointer, size, ctypes.c_double, pointer, size]
    dgemm.restype = None
    rng = np.random.default_rng(0)
    for _ in range(64):
        a, b, product = rng.normal(size=(4, 4)), rng.normal(size=(4, 4)), np.empty((4, 4))
        dgemm(_ROW_MAJOR, _NO_TRANS, _NO_TRANS, 4, 4, 4, 1.0, a.ctypes.data, 4,
              b.ctypes.data, 4, 0.0, product.ctypes.data, 4)  # fmt: skip
        if product.tobytes() != (a @ b).tobytes():
            return False
    return True
