"""The results pages: generated from the studies' own reports, and free of the session's traces."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
#: a commit hash: 7-40 hex digits with at least one letter and one digit (not a plain number)
HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")


def _page_tool():
    spec = importlib.util.spec_from_file_location("fleet_results_page", REPO / "tools" / "fleet_results_page.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_no_user_page_carries_a_date_or_a_commit_hash() -> None:
    """The README and every docs page: what the code does, not when or at which commit (those
    belong in the CHANGELOG and the closing notes)."""
    pages = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    assert len(pages) > 20
    for page in pages:
        text = page.read_text()
        assert not DATE.search(text), f"{page.relative_to(REPO)}: a date ({DATE.search(text).group()})"
        assert not HASH.search(text), f"{page.relative_to(REPO)}: a commit hash? ({HASH.search(text).group()})"


def test_the_patterns_catch_what_they_are_for() -> None:
    assert DATE.search("at 2026-11-25") and HASH.search("at c9d8d45,") and HASH.search("5898270abc")
    assert not HASH.search("1234567 samples") and not HASH.search("deadbeef") and not DATE.search("20-11-2026")


def _study(d: Path, study: dict, report: str) -> Path:
    d.mkdir()
    (d / "study.json").write_text(json.dumps(study))
    (d / "report.md").write_text(report)
    return d


def test_the_fleet_page_is_the_studies_reports_under_the_commands_that_made_them(tmp_path) -> None:
    tool = _page_tool()
    fleet = _study(tmp_path / "paper-2-25", {"scenario": "paper-2", "seeds": list(range(25)), "fusion": "split-ci",
                                            "lane_constraint": False},
                   "# slcp study: paper-2\n\ntext\n\n## t_s1-t_e\n\n```\n# not a heading\n```\n")
    inproc = _study(tmp_path / "rush", {"scenario": "rush-hour", "seeds": [0, 1, 2], "summary": {}},
                    "# rush-hour study\n\n### deep\n")
    page = tool.build_page([fleet, inproc])
    assert page.startswith("# Fleet results\n") and '!!! note "Generated"' in page
    assert "slcp run paper-2 --seeds 25 --fusion split-ci --no-lane-constraint --out runs/paper-2-25" in page
    assert "slcp scenario study rush-hour --seeds 3 --out runs/rush" in page
    assert "python tools/fleet_results_page.py runs/paper-2-25 runs/rush > docs/results-fleet.md" in page
    assert "\n## slcp study: paper-2\n" in page and "\n### t_s1-t_e\n" in page and "\n# not a heading\n" in page
    assert "\n## rush-hour study\n" in page and "\n#### deep\n" in page
    assert page.index("paper-2\n") < page.index("rush-hour study")
    # an in-process study with the bound (its seeds carry it) names --bound
    bound = _study(tmp_path / "rush-b", {"scenario": "rush-hour", "seeds": [0], "summary": {},
                                         "per_seed": [{"seed": 0, "bound": {}}]}, "# rush-hour study\n")
    assert "slcp scenario study rush-hour --seeds 1 --bound --out runs/rush-b" in tool.build_page([bound])
    # a folder that is not a study, or a damaged summary: a clear error, exit 2
    (tmp_path / "empty").mkdir()
    with pytest.raises(tool.PageError, match="not a study folder"):
        tool.build_page([tmp_path / "empty"])
    for i, summary in enumerate(({"scenario": "x"}, {"seeds": [0]}, ["not", "a", "map"])):
        bad = _study(tmp_path / f"bad{i}", summary, "# x\n")
        with pytest.raises(tool.PageError, match="not a study's summary"):
            tool.build_page([bad])
    assert tool.main([str(tmp_path / "empty")]) == 2


def test_the_fleet_results_page_in_the_docs_is_the_generated_one() -> None:
    text = (REPO / "docs" / "results-fleet.md").read_text()
    assert '!!! note "Generated"' in text and "python tools/fleet_results_page.py" in text
    assert text.count("\n## ") >= 3  # a section per study


_ITEM = re.compile(r"^(\s*)(?:[-*]|\d+\.) ")


def lists_read_as_paragraphs(text: str) -> list[int]:
    """Line numbers of list items that Python-Markdown (mkdocs) takes for paragraph text: a new
    list, or a nested one, right under a paragraph line without a blank line between (GitHub
    shows them as lists all the same), and nested items indented by 2 instead of 4 (shown as
    their parent's siblings). Within a list, a paragraph after a blank line belongs to the item
    only if indented by 4; a fence closed at less ends the list too."""
    bad, fence, in_list, last_ind, after_blank = [], False, False, -1, True
    for no, line in enumerate(text.split("\n"), 1):
        ind = len(line) - len(line.lstrip(" "))
        if line.lstrip().startswith("```"):
            fence = not fence
            if not fence and ind < 4:
                in_list, last_ind = False, -1
            after_blank = False
            continue
        if fence:
            continue
        if not line.strip():
            after_blank = True
            continue
        if _ITEM.match(line):
            if not after_blank and (not in_list or ind > last_ind) or ind % 4:  # nested by 4, not 2
                bad.append(no)
            in_list, last_ind = True, ind
        elif after_blank and ind < 4:
            in_list, last_ind = False, -1
        after_blank = False
    return bad


def test_every_list_in_the_docs_renders_as_a_list() -> None:
    assert lists_read_as_paragraphs("Leads:\n- one\n- two\n") == [2]  # the rule catches what it is for
    assert lists_read_as_paragraphs("Leads:\n\n- one\n  more\n- two\n  - nested under its item\n") == [6]
    assert lists_read_as_paragraphs("Leads:\n\n- one\n\n    - nested after a blank line\n- two\n") == []
    assert lists_read_as_paragraphs("Leads:\n\n- one\n\n  - nested by 2\n") == [5]
    bad = {str(p.relative_to(REPO)): lines for p in sorted((REPO / "docs").rglob("*.md"))
           if (lines := lists_read_as_paragraphs(p.read_text()))}
    assert bad == {}, f"add a blank line before these list items: {bad}"
