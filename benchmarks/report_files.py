"""Where a benchmark writes its report: a Markdown file and its raw figures beside it as
JSON, both checked before measuring, which takes minutes, so that a bad ``--out`` fails at
once instead of after the measurements."""

from __future__ import annotations

import argparse
from pathlib import Path


def report_paths(parser: argparse.ArgumentParser, out: Path) -> Path:
    """The JSON path beside the Markdown report ``out``, once neither is a folder and they
    differ."""
    if out.is_dir():
        parser.error(
            f"--out {out} is a folder; --out names the Markdown report file, "
            f"e.g. {out / Path(parser.get_default('out')).name}"
        )
    if out.suffix.lower() == ".json":
        parser.error(
            f"--out {out} ends in .json: --out names the Markdown report, and the raw figures go "
            f"to the same path with the suffix .json, so one would overwrite the other; "
            f"give e.g. {out.with_suffix('.md')}"
        )
    json_path = out.with_suffix(".json")
    if json_path.is_dir():
        parser.error(f"--out {out}: its raw figures go to {json_path}, which is a folder")
    return json_path


def check_writable(parser: argparse.ArgumentParser, out: Path, json_path: Path) -> None:
    """Both report files can be written: the folder exists or is created, an existing file
    opens for writing (left as it is), and a new one is created and removed again. Checked
    before measuring, which takes minutes."""
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        file = next((p for p in (out.parent, *out.parent.parents) if p.is_file()), None)
        why = f"{file} is a file, not a folder" if file else error.strerror
        parser.error(f"--out {out}: cannot create its folder {out.parent}: {why}")
    for path in (out, json_path):
        try:
            if path.exists():
                with path.open("r+b"):  # not "w": a refused or failed run keeps the old report
                    pass
            else:
                with path.open("xb"):
                    pass
                path.unlink()
        except OSError as error:
            parser.error(f"--out {out}: cannot write {path}: {error.strerror or error}")
