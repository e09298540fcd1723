"""A scenario's ``[trajectories]`` table: where its vehicles' paths come from when they do not
come from the traffic model (:mod:`hw_emulation.trajectory_truth` builds the truth from them)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class TrajectorySource:
    """A scenario's ``[trajectories]`` table: its vehicles drive these recorded or simulated
    paths instead of the scenario's traffic model.

    ``file``: CSV (:func:`~hw_emulation.external.read_csv_tracks`) or SUMO FCD XML (``.xml``,
    :func:`~hw_emulation.external.read_sumo_fcd`, less ``offset``); ``point``: what the
    positions are of, ``"front"`` (the middle of the front bumper, as SUMO reports) or
    ``"reference"`` (the vehicle's reference point, ``l0`` behind the front). A file with
    headings, speeds and lanes (SUMO's, or a CSV with the optional columns) also gives the
    queues at the stop lines.
    """

    file: Path
    point: str = "front"
    offset: tuple[float, float] = (0.0, 0.0)

    POINTS = ("front", "reference")

    def tracks(self) -> dict:
        """The file's tracks (:class:`hw_emulation.external.Track` by vehicle)."""
        from .external import read_csv_tracks, read_sumo_fcd

        if self.file.suffix.lower() == ".xml":
            return read_sumo_fcd(self.file, self.offset)
        return read_csv_tracks(self.file)


def parse_trajectories(ctx, tj: dict) -> TrajectorySource | None:
    """The ``[trajectories]`` table (``ctx``: the scenario parser's context, for its errors)."""
    if not tj:
        return None
    unknown = set(tj) - {"file", "point", "offset"}
    if unknown:
        raise ctx.fail(f"trajectories.{sorted(unknown)[0]}", "unknown field (known: file, offset, point)")
    point = tj.get("point", "front")
    if point not in TrajectorySource.POINTS:
        raise ctx.fail("trajectories.point", f"must be one of {', '.join(TrajectorySource.POINTS)}, got {point!r}")
    off = tj.get("offset", [0.0, 0.0])
    if not (isinstance(off, list) and len(off) == 2 and all(isinstance(x, (int, float)) for x in off)):
        raise ctx.fail("trajectories.offset", "must be [x, y] in metres")
    f = Path(ctx.string(tj, "file", "trajectories"))
    base = Path(ctx.source).parent if Path(ctx.source).is_file() else Path.cwd()
    f = f if f.is_absolute() else base / f
    if not f.is_file():
        raise ctx.fail("trajectories.file", f"no such file: {f}")
    return TrajectorySource(f, point, (float(off[0]), float(off[1])))
