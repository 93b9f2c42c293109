"""open3d, imported when first used.

Importing open3d takes about 2.5 s (it imports scikit-learn for its ML datasets), and an env
step never needs it: only the ground-truth precomputation (cached on disk), reconstruction and
file export do. Modules write ``from liuxing_envs.open3d_import import o3d`` and use ``o3d`` as
the module itself; the import happens at the first attribute read. Until then open3d is not in
``sys.modules``, so :mod:`liuxing_envs.forking` does not count a fork as one after open3d.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from types import ModuleType


class _Open3D:
    """Stands for the ``open3d`` module; reading an attribute imports it."""

    def __getattr__(self, name: str):
        return getattr(_module(), name)

    def __repr__(self) -> str:
        return "<open3d, imported on first use>"


def _module() -> ModuleType:
    return importlib.import_module("open3d")


o3d = _Open3D()


def open3d_version() -> str:
    """open3d's version, read without importing it (disk-cache keys include it). The CPU
    build installs as ``open3d-cpu``, the other as ``open3d``."""
    for distribution in ("open3d-cpu", "open3d"):
        try:
            return importlib.metadata.version(distribution)
        except importlib.metadata.PackageNotFoundError:
            continue
    return o3d.__version__
