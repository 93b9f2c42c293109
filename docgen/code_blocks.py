"""The runnable examples of the README and the docs pages: fenced ``python`` and ``bash``
blocks. A block right after the line ``<!-- long -->`` is long: the test suite skips it and
``make docs-long`` runs it."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from docgen.results import ROOT

LONG_MARK = "<!-- long -->"
RUNNABLE = {"python": "python", "bash": "bash", "sh": "bash", "shell": "bash"}
_FENCE = re.compile(r"^(?P<indent> *)(?P<fence>```+|~~~+)\s*(?P<info>[\w-]*)")


@dataclasses.dataclass(frozen=True)
class CodeBlock:
    path: Path
    line: int  # of the opening fence, from 1
    language: str  # "python" or "bash"
    code: str
    long: bool

    @property
    def name(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def documentation_files() -> list[Path]:
    """README.md and every page of the docs site."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def code_blocks(path: Path) -> list[CodeBlock]:
    """The runnable fenced blocks of one Markdown file, in order."""
    lines = path.read_text().split("\n")
    blocks, index = [], 0
    while index < len(lines):
        opening = _FENCE.match(lines[index])
        if not opening:
            index += 1
            continue
        fence, indent = opening["fence"], len(opening["indent"])
        end = index + 1
        while end < len(lines) and not lines[end].strip().startswith(fence):
            end += 1
        language = RUNNABLE.get(opening["info"].lower())
        if language:
            previous = lines[index - 1].strip() if index else ""
            code = "\n".join(line[indent:] for line in lines[index + 1 : end])
            blocks.append(CodeBlock(path, index + 1, language, code, previous == LONG_MARK))
        index = end + 1
    return blocks


def all_code_blocks() -> list[CodeBlock]:
    return [block for path in documentation_files() for block in code_blocks(path)]
