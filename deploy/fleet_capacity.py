"""The fleet's performance targets, and the largest fleet this machine holds within them.

A fleet point (:func:`deploy.fleet_bench.run_fleet_point`) meets the targets when the agents keep
real time (the median agent's real-time factor at least :data:`REALTIME_MIN`), the radio's
beacons arrive within :data:`BEACON_P99_MAX_MS` at the 99th percentile, no sensor sample is
dropped, and no agent's peak resident set exceeds :data:`RSS_MAX_MB`.

:func:`capacity_search` finds the largest agent count that meets them: it doubles the count from
a start while the points meet the targets, then bisects between the last that met them and the
first that did not, down to a resolution. One run per count: on a machine whose speed drifts,
a count near the boundary may meet the targets in one run and miss them in the next, so the
search reports every point it ran, with the step costs measured beside it.
"""

from __future__ import annotations

from collections.abc import Callable

#: the median agent's sensor time advanced per second of wall time, at least
REALTIME_MIN = 0.97
#: the 99th percentile of the beacons' latency through the emulated radio [ms], below
BEACON_P99_MAX_MS = 20.0
#: every agent's peak resident set [MB], at most
RSS_MAX_MB = 80.0

#: the agents' engines a fleet point can run: the real one, or the stand-in that stops
#: estimating once started (:mod:`agent.stand_in`), whose points say what the rest costs
FLEET_ENGINES = ("full", "stand-in")


def missed_targets(point: dict) -> list[str]:
    """What a fleet point misses of the targets, in words (empty: it meets them all)."""
    if "error" in point:
        return [str(point["error"])]
    missed = []
    rtf = point.get("realtime_factor")
    if rtf is None or not rtf >= REALTIME_MIN:
        missed.append(f"real-time factor {rtf if rtf is None else format(rtf, '.2f')} below {REALTIME_MIN:g}")
    lat = point.get("beacon_latency_ms")
    if not lat:
        missed.append("no beacon delivered")
    elif not lat["p99"] < BEACON_P99_MAX_MS:
        missed.append(f"beacon p99 {lat['p99']:.0f} ms, not below {BEACON_P99_MAX_MS:g}")
    if point.get("sensor_dropped", 1):
        missed.append(f"{point.get('sensor_dropped', '?')} sensor samples dropped")
    rss = point.get("rss_mb_per_agent")
    if not rss or not rss["max"] <= RSS_MAX_MB:
        missed.append(f"peak RSS {rss['max']:.0f} MB above {RSS_MAX_MB:g}" if rss else "no agent's RSS measured")
    return missed


def capacity_search(run_point: Callable[[int], dict], start: int = 10, most: int = 100,
                    resolution: int = 5) -> dict:
    """The largest agent count in [1, ``most``] whose fleet point meets the targets.

    ``run_point(n)`` runs one point (the result of :func:`deploy.fleet_bench.run_fleet_point`).
    Counts are tried from ``start``, doubled while they meet the targets (capped at ``most``),
    then bisected until the counts that met and missed them are ``resolution`` apart or less.
    Returns ``capacity`` (the largest count that met them; 0 if none did), ``first_missed``
    (the smallest that missed them, None if ``most`` met them) and ``points``, every point run,
    in order, each with its ``missed`` list."""
    if not 1 <= start <= most or resolution < 1:
        raise ValueError(f"capacity search: need 1 <= start ({start}) <= most ({most}) and resolution >= 1")
    points: list[dict] = []

    def meets(n: int) -> bool:
        point = run_point(n)
        if "missed" not in point:  # a host may have judged it already
            point["missed"] = missed_targets(point)
        points.append(point)
        return not point["missed"]

    good: int = 0
    bad: int | None = None
    n = start
    while True:
        if meets(n):
            good = n
            if n == most:
                break
            n = min(2 * n, most)
        else:
            bad = n
            break
    if bad is not None and good == 0:  # the start missed them: halve until a count meets them
        n = bad // 2
        while n >= 1:
            if meets(n):
                good = n
                break
            bad, n = n, n // 2
    while bad is not None and good and bad - good > resolution:
        mid = (good + bad) // 2
        if meets(mid):
            good = mid
        else:
            bad = mid
    return {"capacity": good, "first_missed": bad, "points": points}
