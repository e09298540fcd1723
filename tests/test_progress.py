"""The run's progress: one line with phase, sensor time, share, agents alive and time left; in
place on a terminal, a line every few seconds elsewhere."""

from __future__ import annotations

import io

from slcp.deploy.progress import FleetProgress, ProgressView


def _p(phase: str, t: float, alive: int = 3, wall: float = 10.0) -> FleetProgress:
    return FleetProgress("paper-1", phase, t, 50.0, alive, 3, 1234, wall, "vehicle t [s]\nV0 20.0", wall - 4.0)


def test_the_line_says_phase_time_share_agents_and_time_left() -> None:
    line = _p("playing", 20.0).line()
    # 20 of 50 s played in the 6 s since the first estimate: 9 s to go
    assert line == "paper-1: playing · t = 20.0 / 50 s (40 %) · 3/3 agents alive · 10 s, about 9 s left · 1234 messages"
    start = _p("starting", 0.0, alive=1, wall=2.0).line()
    assert "starting" in start and "1/3 agents reporting" in start and "%" not in start
    assert "left" not in _p("evaluating", 50.0).line()
    assert _p("playing", 80.0).fraction == 1.0


def test_off_a_terminal_a_line_at_each_phase_and_every_few_seconds() -> None:
    out = io.StringIO()
    clock = iter([0.0, 1.0, 2.0, 12.5, 13.0, 14.0])
    with ProgressView(stream=out, every=10.0, live=False, clock=lambda: next(clock)) as view:
        for p in (_p("starting", 0.0), _p("starting", 0.0), _p("playing", 5.0), _p("playing", 9.0),
                  _p("playing", 9.5), _p("evaluating", 50.0)):
            view(p)
    lines = out.getvalue().splitlines()
    assert [x.split(": ")[1].split(" ")[0] for x in lines] == ["starting", "playing", "playing", "evaluating"]
    assert "vehicle t [s]" not in out.getvalue()  # the table is for the live view


def test_on_a_terminal_the_status_updates_in_place() -> None:
    out = io.StringIO()
    with ProgressView(stream=out, live=True) as view:
        view(_p("playing", 20.0))
        view(_p("playing", 30.0))
    text = out.getvalue()
    assert "t = 30.0 / 50 s (60 %)" in text and "\x1b[" in text  # redrawn in place (cursor controls)
