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
#: Fence languages that are shown, never run (output, configuration files).
SHOWN = ("text", "console", "yaml", "json", "toml", "diff")
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
            above = [line.strip() for line in lines[:index] if line.strip()]
            previous = above[-1] if above else ""
            code = "\n".join(line[indent:] for line in lines[index + 1 : end])
            blocks.append(CodeBlock(path, index + 1, language, code, previous == LONG_MARK))
        index = end + 1
    return blocks


def all_code_blocks() -> list[CodeBlock]:
    return [block for path in documentation_files() for block in code_blocks(path)]


def fence_problems(path: Path) -> list[str]:
    """Fences the examples test would get wrong: a language neither run nor in
    :data:`SHOWN`, and a long mark that no runnable fence follows."""
    lines = path.read_text().split("\n")
    problems, inside = [], None
    for number, line in enumerate(lines, start=1):
        opening = _FENCE.match(line)
        if inside:
            if line.strip().startswith(inside):
                inside = None
            continue
        if opening:
            inside = opening["fence"]
            language = opening["info"].lower()
            if language not in RUNNABLE and language not in SHOWN:
                problems.append(
                    f"{path.name}:{number}: fence language {language!r} is neither "
                    f"run ({', '.join(RUNNABLE)}) nor shown ({', '.join(SHOWN)})"
                )
        elif line.strip() == LONG_MARK:
            following = next((text for text in lines[number:] if text.strip()), "")
            fence = _FENCE.match(following)
            if not (fence and fence["info"].lower() in RUNNABLE):
                problems.append(
                    f"{path.name}:{number}: {LONG_MARK} is not followed by a runnable fence"
                )
    return problems
