"""Helpers of the generated documentation pages (``tools/*_page.py``)."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any


def demote(markdown: str) -> str:
    """Every heading one level down (a report's title becomes a section of the page); fenced
    code is left alone."""
    out, fenced = [], False
    for line in markdown.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        out.append("#" + line if line.startswith("#") and not fenced else line)
    return "\n".join(out).rstrip() + "\n"


class PageError(ValueError):
    """A folder that is not the output a page is made of (the message says which and why)."""


def report_and_json(folder: Path, json_name: str, what: str, kind: str) -> tuple[str, Any]:
    """``folder``'s ``report.md`` and its JSON file ``json_name`` (parsed): the output of a ``what``
    (a study, a replay); a :class:`PageError` naming the folder when either is missing, and the
    file when it is not JSON (``kind`` says what it should be: a summary, metrics)."""
    report, meta = folder / "report.md", folder / json_name
    if not (report.is_file() and meta.is_file()):
        raise PageError(f"{folder}: not a {what} folder (no report.md and {json_name})")
    try:
        data = json.loads(meta.read_text())
    except ValueError as exc:
        raise PageError(f"{meta}: not a {what}'s {kind} ({exc!r})") from exc
    return report.read_text(), data


def write_page(build: Callable[[], str], tool: str) -> int:
    """A page tool's main: the page ``build`` makes on standard output (exit status 0), or
    ``tool``'s one-line error on standard error for a folder it cannot use (status 2)."""
    try:
        sys.stdout.write(build())
    except (PageError, OSError) as exc:
        print(f"{tool}: {exc}", file=sys.stderr)
        return 2
    return 0
