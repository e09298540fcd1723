"""A fleet run's progress as the launcher sees it, and its two views: a live status that updates
in place on a terminal (rich), and a plain line every few seconds anywhere else (a pipe, a log)."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class FleetProgress:
    """What the launcher knows of a running fleet."""

    scenario: str
    phase: str  #: "starting", "playing" or "evaluating"
    sensor_t: float  #: the newest sensor time recorded [s]
    end_t: float | None  #: the scenario's end [s]
    alive: int  #: vehicles whose estimates arrived within the last few seconds (wall)
    vehicles: int
    recorded: int  #: messages recorded so far
    wall_s: float  #: since the launcher started the processes [s]
    table: str = ""  #: the per-vehicle status table (supervisor.status_table)
    playing_s: float = 0.0  #: since the first estimate was recorded [s, wall]

    @property
    def fraction(self) -> float | None:
        if not self.end_t or self.phase == "starting":
            return None
        return min(max(self.sensor_t / self.end_t, 0.0), 1.0)

    def line(self) -> str:
        """One line: phase, sensor time and share of the scenario, agents alive, time left."""
        head = f"{self.scenario}: {self.phase}"
        if self.phase == "starting":
            return (f"{head} (agents, emulator, router) · {self.alive}/{self.vehicles} agents reporting · "
                    f"{self.wall_s:.0f} s")
        frac = self.fraction
        parts = [head, f"t = {self.sensor_t:.1f}" + (f" / {self.end_t:.0f} s" if self.end_t else " s")]
        if frac is not None:
            parts[-1] += f" ({100 * frac:.0f} %)"
        parts.append(f"{self.alive}/{self.vehicles} agents alive")
        left = ""
        if frac is not None and 0.05 < frac < 1.0 and self.phase == "playing" and self.playing_s > 0:
            left = f", about {self.playing_s * (1 - frac) / frac:.0f} s left"
        parts.append(f"{self.wall_s:.0f} s{left}")
        parts.append(f"{self.recorded} messages")
        return " · ".join(parts)


class ProgressView:
    """Shows :class:`FleetProgress` updates: in place on a terminal, else a line every ``every``
    seconds and at each change of phase. Use as a context manager; call it with each update."""

    def __init__(self, stream=None, every: float = 10.0, live: bool | None = None, clock=time.monotonic) -> None:
        self.stream = stream or sys.stdout
        self.clock = clock
        self.every = every
        self.live = self.stream.isatty() if live is None else live
        self._live = None
        self._last = -float("inf")
        self._phase = None

    def __enter__(self) -> ProgressView:
        if self.live:
            from rich.console import Console
            from rich.live import Live

            self._live = Live(console=Console(file=self.stream, force_terminal=True), refresh_per_second=4,
                              transient=True)
            self._live.__enter__()
        return self

    def __call__(self, p: FleetProgress) -> None:
        if self._live is not None:
            from rich.console import Group
            from rich.text import Text

            self._live.update(Group(Text(p.line(), style="bold"), Text(p.table)) if p.table else Text(p.line()))
            return
        now = self.clock()
        if p.phase != self._phase or now - self._last >= self.every:
            self._phase, self._last = p.phase, now
            print(p.line(), file=self.stream, flush=True)

    def __exit__(self, *exc) -> None:
        if self._live is not None:
            self._live.__exit__(*exc)
            self._live = None
