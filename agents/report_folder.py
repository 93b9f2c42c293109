"""The files of a report folder beyond its numbers: reconstructions, videos and figures.

A report written into the folder of an earlier one replaces that report's files, never
anyone else's, and never before its own numbers are ready:

- what is removed is what the earlier ``report.json`` (one evaluate.py wrote: it has
  ``environments``, ``seeds`` and ``settings``) says its report wrote: its figures, and per
  contestant ``reconstructions/<label>/`` and ``videos/<label>.mp4``;
- reconstructions are written during the episodes into a staging folder, and the earlier
  files are removed and the staged ones moved into place only when the episodes are done,
  so a run stopped before then leaves the earlier report whole (a stale mesh beside the new
  numbers, or the new meshes beside the old ones, was the bug this prevents).
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterable
from pathlib import Path

from agents.config import NamesSettings
from agents.contestants import slug
from agents.video import VIDEOS_FOLDER

REPORT_JSON = "report.json"
RECONSTRUCTIONS_FOLDER = "reconstructions"
#: Where the reconstructions of a report in progress go; evaluate.py's own, cleared at start.
STAGING_FOLDER = ".reconstructions.partial"
#: The keys that make a report.json evaluate.py's: another tool's is not ours to act on.
_REPORT_KEYS = ("environments", "seeds", "settings")


class ReportFolderError(NamesSettings, ValueError):
    """The folder cannot take a report's files; the message names the path."""


def check_subfolders(out: Path) -> None:
    """Refuse, before any episode, names the report's files go under that are links or files:
    an earlier report's files behind a link would mix with the new ones (a link is not ours
    to follow), and a file there would stop the report after its episodes."""
    for name in (RECONSTRUCTIONS_FOLDER, VIDEOS_FOLDER, STAGING_FOLDER):
        path = out / name
        if path.is_symlink():
            raise ReportFolderError(
                f"{path} is a link: the report writes its {name} there; remove the link or "
                "choose another «out»"
            )
        if path.exists() and not path.is_dir():
            raise ReportFolderError(f"{path} is not a folder, and the report writes one there")


def earlier_report_files(out: Path, figure_files: Iterable[str] = ()) -> list[Path]:
    """The files and folders the report in ``out`` wrote besides its numbers (none when
    there is no report.json of evaluate.py's there): ``figure_files``, the figures it names
    and each contestant's folder and video."""
    try:
        earlier = json.loads((out / REPORT_JSON).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    if not isinstance(earlier, dict) or not all(key in earlier for key in _REPORT_KEYS):
        return []
    # Only the shapes a report writes: its pictures and videos, and per contestant a folder.
    names = [*figure_files]
    names += [n for n in _strings(earlier.get("figures")) if n.endswith((".png", ".mp4"))]
    try:
        for section in earlier["environments"].values():
            for contestant in section["contestants"]:
                name = slug(str(contestant["label"]))
                names += [f"{RECONSTRUCTIONS_FOLDER}/{name}", f"{VIDEOS_FOLDER}/{name}.mp4"]
    except (AttributeError, KeyError, TypeError):
        return []  # not a report this code wrote, whatever its keys
    return [out / name for name in dict.fromkeys(names) if name and _is_inside(out, name)]


def check_reconstruction_folders(out: Path, labels: Iterable[str], earlier: list[Path]) -> None:
    """Refuse, before any episode, a contestant's reconstructions folder that exists but is
    not the earlier report's: moving this report's into place would replace someone's."""
    for label in labels:
        folder = out / RECONSTRUCTIONS_FOLDER / slug(label)
        if folder.exists() and folder not in earlier:
            raise ReportFolderError(
                f"{folder} exists and no earlier report in the folder wrote it: the report "
                "writes its reconstructions of that contestant there; move it or choose "
                "another «out»"
            )


def fresh_staging_folder(out: Path) -> Path:
    """The empty folder the reconstructions of this report are written into."""
    staging = out / STAGING_FOLDER
    shutil.rmtree(staging, ignore_errors=True)  # a stopped report's, never a user's
    return staging


def replace_earlier_files(out: Path, earlier: Iterable[Path]) -> list[str]:
    """Remove the ``earlier`` report's files and move the staged reconstructions into place.
    Returns what could not be done, one message each: the report's numbers are written
    whatever happens here."""
    problems = []
    for path in earlier:
        try:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink(missing_ok=True)
        except OSError as error:
            problems.append(f"could not remove the earlier report's {path}: {error.strerror}")
    staging, final = out / STAGING_FOLDER, out / RECONSTRUCTIONS_FOLDER
    for staged in sorted(staging.iterdir()) if staging.is_dir() else []:
        target = final / staged.name  # checked free or the earlier report's, before it ran
        try:
            final.mkdir(exist_ok=True)
            os.replace(staged, target)
        except OSError as error:
            problems.append(f"could not move {staged} to {target}: {error.strerror}")
    for folder in (staging, final, out / VIDEOS_FOLDER):
        try:
            folder.rmdir()  # only when empty
        except OSError:
            pass
    return problems


def _strings(value) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, dict):
        value = list(value.values())
    if isinstance(value, list):
        return [s for item in value for s in _strings(item)]
    return []


def _is_inside(out: Path, name: str) -> bool:
    """Whether the relative ``name`` stays in ``out`` without passing through a link."""
    relative = Path(name)
    if relative.is_absolute() or ".." in relative.parts or not relative.parts:
        return False
    folder = out
    for part in relative.parts[:-1]:
        folder = folder / part
        if folder.is_symlink():
            return False
    return True
