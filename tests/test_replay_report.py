"""A replay's report (``report.md``), the figures of another filter it compares with, and the
real-drive results page generated from it."""

from __future__ import annotations

import importlib.util
import json
import shlex
from pathlib import Path

import pytest

from slcp.deploy.cli import build_parser, main
from slcp.deploy.replay_report import load_comparison, replay_command, replay_report

REPO = Path(__file__).resolve().parents[1]


def _page_tool():
    spec = importlib.util.spec_from_file_location("real_drive_page", REPO / "tools" / "real_drive_page.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _phase(first: float, rms: float, end: float, mx: float, n: int = 10) -> dict:
    return {"first_outage_s": first, "n_outages": n, "n_withheld_fixes": 60 * n, "outage_h_rms_m": rms,
            "outage_h_end_mean_m": end, "outage_h_end_max_m": mx, "outage_h_max_m": mx}


def _metrics(phases: list[dict] | None = None) -> dict:
    base = {**_phase(40.0, 1.5, 2.5, 8.0), "imu_span_s": 500.0, "gnss_on_h_rms_m": 0.2,
            "imu_time_offset_s": -0.2, "wall_s": 2.0, "realtime_factor": 250.0,
            "config": {"profile": {"name": "test car"}, "outage": {"first": 40.0, "period": 45.0, "length": 15.0}}}
    if phases:
        base["phases_pooled"] = {"n_phases": len(phases), "phases": phases, "n_outages": 20, "n_withheld_fixes": 1200,
                                 "outage_h_rms_m": 2.0, "outage_h_end_mean_m": 3.0, "outage_h_end_max_m": 9.0,
                                 "outage_h_max_m": 9.0}
    return base


COMPARISON = """
name = "filter X"
source = "run by hand"

[[phase]]
first_outage_s = 40.0
outage_h_rms_m = 2.0
outage_h_end_mean_m = 3.0
outage_h_max_m = 11.0

[[phase]]
first_outage_s = 62.5
outage_h_rms_m = 1.0
outage_h_end_mean_m = 4.0
"""


def test_the_report_puts_the_other_filters_figures_beside_ours_phase_by_phase(tmp_path) -> None:
    f = tmp_path / "x.toml"
    f.write_text(COMPARISON)
    other = load_comparison(f)
    assert other.name == "filter X" and other.at(62.5) == {"outage_h_rms_m": 1.0, "outage_h_end_mean_m": 4.0}
    assert other.at(62.5004) == other.at(62.5) and other.at(55.0) == {} and other.at(None) == {}
    # phase 40: ours lower on both; phase 62.5: our RMS lower, our end mean higher (not a win)
    text = replay_report("slcp replay csv rec --out o", _metrics([_phase(40.0, 1.5, 2.5, 8.0),
                                                                  _phase(62.5, 0.9, 4.5, 9.0)]), other)
    lines = text.splitlines()
    assert lines[0] == "# SP replay" and "`slcp replay csv rec --out o`" in lines
    assert "| outage horizontal RMS | 1.50 | 2.00 |" in lines and "| outage maximum | 8.00 | 11.00 |" in lines
    assert "| end-of-outage maximum | 8.00 |  |" in lines  # a metric the comparison does not give: blank
    assert "| 40 | 10 | 1.50 | 2.50 | 8.00 | 8.00 | 2.00 / 3.00 |" in lines
    assert "| 62.5 | 10 | 0.90 | 4.50 | 9.00 | 9.00 | 1.00 / 4.00 |" in lines
    assert "| pooled | 20 | 2.00 | 3.00 | 9.00 | 9.00 | |" in lines
    assert "slcp has the lower RMS and end mean at 1 of the 2 phases the comparison gives." in lines
    assert lines[-1] == "Compared with filter X. run by hand"
    # without a comparison: no such column, no tally; one phase: no phases section
    plain = replay_report("c", _metrics(), title="SP replay of drive")
    assert plain.startswith("# SP replay of drive\n") and "| metric [m] | slcp |\n|---|---|\n" in plain
    assert "phases" not in plain and "Compared" not in plain and "lower RMS" not in plain
    # no outage (--no-outage): the outage rows are not measured and not shown
    nan = float("nan")
    every_fix = {**_metrics(), "n_outages": 0, "n_withheld_fixes": 0, "outage_h_rms_m": nan,
                 "outage_h_end_mean_m": nan, "outage_h_end_max_m": nan, "outage_h_max_m": nan}
    text = replay_report("c", every_fix)
    assert "no GNSS outage: every fix is used" in text and "| RMS with GNSS on | 0.20 |" in text
    assert "outage horizontal RMS" not in text and "nan" not in text


@pytest.mark.parametrize(("text", "match"), [
    ("name = ", "not TOML"),
    ("source = 'x'\n[[phase]]\nfirst_outage_s = 40.0", "needs a name"),
    ("name = 'x'", "at least one"),
    ("name = 'x'\ncolour = 1\n[[phase]]\nfirst_outage_s = 40.0", "unknown keys"),
    ("name = 'x'\n[[phase]]\noutage_h_rms_m = 1.0", "needs first_outage_s"),
    ("name = 'x'\n[[phase]]\nfirst_outage_s = 40.0\nrms = 1.0", "unknown keys"),
    ("name = 'x'\n[[phase]]\nfirst_outage_s = 40.0\noutage_h_rms_m = -1.0", "non-negative number"),
    ("name = 'x'\n[[phase]]\nfirst_outage_s = 40.0\noutage_h_rms_m = nan", "non-negative number"),
    ("name = 'x'\n[[phase]]\nfirst_outage_s = 40.0\noutage_h_rms_m = true", "non-negative number"),
    ("name = 'x'\n[[phase]]\nfirst_outage_s = 40.0\n[[phase]]\nfirst_outage_s = 40.0", "a second phase"),
])
def test_a_comparison_file_that_is_not_one_is_a_clear_error(tmp_path, text, match) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ValueError, match=match):
        load_comparison(f)


def test_a_bad_comparison_stops_the_replay_before_it_reads_the_recording(tmp_path, capsys) -> None:
    f = tmp_path / "bad.toml"
    f.write_text("name = 'x'")
    assert main(["replay", "rtklib", str(tmp_path / "no-such-drive"), "--compare", str(f)]) == 2
    err = capsys.readouterr().err
    assert "at least one [[phase]]" in err and "no-such-drive" not in err
    assert main(["replay", "rtklib", str(tmp_path / "no-such-drive"), "--compare", str(f), "--publish"]) == 2
    assert "--compare reports beside the offline replay's figures" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["replay", "rtklib", "drive dir"],
    ["replay", "csv", "r", "--vehicle", "car.toml", "--outage", "10:35", "--first-outage", "20", "--end-margin", "5",
     "--phases", "3", "--no-nhc", "--no-zupt", "--no-time-offset-estimation", "--imu-time-offset", "-0.3",
     "--compare", "x.toml", "--out", "o"],
    ["replay", "ros2", "bag", "--no-outage"],
])
def test_the_reports_command_line_parses_back_to_the_same_options(argv) -> None:
    args = build_parser().parse_args(argv)
    command = replay_command(args)
    assert command.startswith("slcp replay ")
    again = build_parser().parse_args(shlex.split(command)[1:])
    assert vars(again) == vars(args)


def test_the_real_drive_page_is_the_replays_report_under_its_commands(tmp_path) -> None:
    tool = _page_tool()
    run = tmp_path / "real-drive"
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps(_metrics()))
    (run / "report.md").write_text(replay_report("slcp replay rtklib d --out runs/real-drive", _metrics(),
                                                 title="SP replay of d"))
    page = tool.build_page(run)
    assert page.startswith("# Results on the real drive\n") and '!!! note "Generated"' in page
    assert "    slcp replay rtklib d --out runs/real-drive\n" in page
    assert "    python tools/real_drive_page.py runs/real-drive > docs/results-real-drive.md\n" in page
    assert "\n## SP replay of d\n" in page and "| outage horizontal RMS | 1.50 |" in page
    # not a replay's folder: a clear error, exit 2
    (tmp_path / "empty").mkdir()
    with pytest.raises(tool.PageError, match="not a replay folder"):
        tool.build_page(tmp_path / "empty")
    (run / "metrics.json").write_text("[1]")
    with pytest.raises(tool.PageError, match="not a replay's metrics"):
        tool.build_page(run)
    (run / "metrics.json").write_text(json.dumps(_metrics()))
    (run / "report.md").write_text("# something else\n")
    with pytest.raises(tool.PageError, match="not a replay's report"):
        tool.build_page(run)
    assert tool.main([str(tmp_path / "empty")]) == 2


def test_the_real_drive_page_in_the_docs_is_the_generated_one() -> None:
    text = (REPO / "docs" / "results-real-drive.md").read_text()
    assert '!!! note "Generated"' in text and "python tools/real_drive_page.py runs/real-drive" in text
    assert "--compare docs/data/rtklibexplorer-drive-authors-nhc.toml" in text
    assert "\n### The protocol at 6 phases\n" in text
    load_comparison(REPO / "docs" / "data" / "rtklibexplorer-drive-authors-nhc.toml")  # the file it names reads
