"""Locate the MJCF assets shipped with the package.

In an installed wheel the top-level ``assets/`` folder of the repository is packaged as
``liuxing_envs/assets`` (see ``pyproject.toml``); in a source checkout or an editable install
it stays at the repository root. :func:`asset_path` hides the difference.
"""

from __future__ import annotations

from pathlib import Path

_PACKAGE_DIR = Path(__file__).resolve().parent
_CANDIDATE_DIRS = (_PACKAGE_DIR / "assets", _PACKAGE_DIR.parent / "assets")


def assets_dir() -> Path:
    """The folder holding the shipped MJCF files (wheel layout first, then the checkout)."""
    for candidate in _CANDIDATE_DIRS:
        if (candidate / "tabletop.xml").is_file():
            return candidate
    searched = ", ".join(str(c) for c in _CANDIDATE_DIRS)
    raise FileNotFoundError(
        f"liuxing_envs assets not found (looked in {searched}); reinstall the package"
    )


def asset_path(name: str) -> Path:
    """Absolute path of a shipped asset file, e.g. ``asset_path("tabletop.xml")``."""
    path = assets_dir() / name
    if not path.is_file():
        available = sorted(p.name for p in assets_dir().iterdir() if p.is_file())
        raise FileNotFoundError(f"no asset named {name!r}; available: {available}")
    return path
