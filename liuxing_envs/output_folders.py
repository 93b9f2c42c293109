"""Output folders, made and checked writable before any work whose results they will hold.

The demo, ``train.py`` and ``evaluate.py`` call this first: a folder that cannot take a file
must be refused at once, not after minutes of episodes whose results are then lost.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterable
from pathlib import Path


class OutputFolderError(ValueError):
    """A folder that cannot be made or written into; the message says why."""


def prepare_output_folder(folder: str | Path, files: Iterable[str] = ()) -> Path:
    """Make ``folder`` (with its parents) and check that a file can be written into it, and
    that none of the ``files`` the work will write there is taken by a folder or the like."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputFolderError(f"{folder} is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        file = next((p for p in folder.parents if p.is_file()), None)
        why = f"{file} is a file, not a folder" if file else error.strerror or str(error)
        raise OutputFolderError(f"cannot create the folder: {why}") from error
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        raise OutputFolderError(
            f"cannot write into the folder: {error.strerror or error}"
        ) from error
    for name in files:
        path = folder / name
        if path.exists() and not path.is_file():
            raise OutputFolderError(
                f"{path} is not a file, and a file of that name is written there"
            )
    return folder
