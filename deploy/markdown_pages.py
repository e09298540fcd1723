"""Helpers of the generated documentation pages (``tools/*_page.py``)."""

from __future__ import annotations


def demote(markdown: str) -> str:
    """Every heading one level down (a report's title becomes a section of the page); fenced
    code is left alone."""
    out, fenced = [], False
    for line in markdown.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        out.append("#" + line if line.startswith("#") and not fenced else line)
    return "\n".join(out).rstrip() + "\n"
