"""MkDocs hooks: render the docstrings' reST cross-reference roles as plain code."""

from __future__ import annotations

import re

# ":meth:`~a.b.name`" reaches the page as ":meth:<code>~a.b.name</code>".
_ROLE = re.compile(r":(?:meth|class|attr|data|func|mod|obj):<code>(~?)([\w.]+)</code>")


def _code(match: re.Match) -> str:
    shortened, target = match.groups()
    return f"<code>{target.rsplit('.', 1)[-1] if shortened else target}</code>"


def on_page_content(html: str, **_) -> str:
    return _ROLE.sub(_code, html)
