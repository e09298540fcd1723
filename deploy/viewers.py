"""The live viewers a recorder can feed: the map in the browser (:mod:`deploy.live_map`) and
Foxglove (:mod:`deploy.foxglove_view`)."""

from __future__ import annotations


def viewer_sinks(view_port: int | None, foxglove_port: int | None, scenario=None, truth=None) -> list:
    """The servers asked for (a port None: not that one), started: the map with ``scenario``'s
    site and, given, its ``truth`` (a :class:`hw_emulation.truth.ScenarioTruth`). A port that is
    taken raises :class:`OSError` with nothing left listening."""
    sinks: list = []
    try:
        if view_port is not None:
            from .live_map import LiveMapSink, LiveMapState

            state = LiveMapState(scenario.lanes.values() if scenario is not None else (),
                                 scenario.origin_llh if scenario is not None else None, truth)
            sinks.append(LiveMapSink(state, port=view_port))
        if foxglove_port is not None:
            from .foxglove_view import FoxgloveSink

            sinks.append(FoxgloveSink(port=foxglove_port,
                                      name=f"slcp {scenario.name}" if scenario is not None else "slcp",
                                      lanes=scenario.lanes.values() if scenario is not None else (),
                                      origin_llh=scenario.origin_llh if scenario is not None else None))
    except BaseException:
        for s in sinks:
            s.close()
        raise
    return sinks
