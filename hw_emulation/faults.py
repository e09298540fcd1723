"""Fault schedules: what goes wrong, when and to whom (pure; SI units, sensor time in seconds).

A schedule is a TOML file (``slcp run --faults FILE``, ``slcp emulate --faults FILE``) of
``[[fault]]`` tables::

    [[fault]]
    kind = "v2v_blackout"      # see below
    start = 20.0               # sensor time [s]
    end = 25.0                 # sensor time [s]; process faults: see below
    vehicles = ["V1"]          # one vehicle: all its links / its sensors; two: the link between
                               # them; empty or absent: every vehicle
    loss = 0.6                 # burst_loss only: loss probability (default 0.5)
    latency = 0.25             # latency_spike only: added latency [s] (default 0.25)

Kinds played by the emulator (links and sensors):

==================  ======================================================================
``v2v_blackout``    no beacon is delivered on the affected links
``burst_loss``      each beacon on the affected links is lost with probability ``loss``
``latency_spike``   ``latency`` seconds are added to each beacon on the affected links
``uwb_outage``      no UWB range of the affected vehicles (or pair)
``gnss_outage``     no GNSS fix of the affected vehicles
==================  ======================================================================

Kinds played by the launcher (processes; one vehicle each):

==================  ======================================================================
``agent_kill``      SIGKILL to the vehicle's agent at ``start`` (the launcher restarts it)
``agent_freeze``    SIGSTOP at ``start``, SIGCONT ``end - start`` seconds of *wall* time later
                    (the clock of the fleet does not wait for a frozen agent)
``emulator_kill``   SIGKILL to the emulator at ``start`` (no vehicles); the launcher restarts
                    it at the fleet's newest sensor time (``slcp emulate --start-at``)
``router_restart``  the launcher's Zenoh router closes at ``start`` and opens again on the
                    same endpoint ``end - start`` seconds of *wall* time later (no vehicles);
                    the clients reconnect, and what was sent meanwhile is lost
==================  ======================================================================
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

LINK_FAULTS = ("v2v_blackout", "burst_loss", "latency_spike")
SENSOR_FAULTS = ("uwb_outage", "gnss_outage")
PROCESS_FAULTS = ("agent_kill", "agent_freeze", "emulator_kill", "router_restart")
KINDS = LINK_FAULTS + SENSOR_FAULTS + PROCESS_FAULTS


class FaultError(ValueError):
    """An invalid fault schedule (the message names the file and fault)."""


@dataclass(frozen=True)
class Fault:
    """One fault of a schedule (the module's docstring lists the kinds).

    Attributes
    ----------
    kind : str
        One of the link, sensor and process kinds (``v2v_blackout``, ..., ``router_restart``).
    start : float
        Sensor time at which it begins [s].
    end : float
        Sensor time at which it ends [s] (``agent_freeze``: the freeze lasts ``end - start`` s of
        wall time; kills: equal to ``start``).
    vehicles : tuple of str
        One vehicle: all its links or its sensors; two: the link or pair between them; none:
        every vehicle.
    loss : float
        ``burst_loss``: the probability that a beacon on an affected link is lost.
    latency : float
        ``latency_spike``: the latency added to each beacon on an affected link [s].
    """

    kind: str
    start: float
    end: float
    vehicles: tuple[str, ...] = ()
    loss: float = 0.5
    latency: float = 0.25

    def active(self, t: float) -> bool:
        return self.start <= t < self.end

    def hits_vehicle(self, vehicle: str) -> bool:
        """Sensor faults: whether ``vehicle``'s sensors are affected."""
        return not self.vehicles or vehicle in self.vehicles

    def hits_link(self, tx: str, rx: str) -> bool:
        """Link faults: whether the link ``tx`` → ``rx`` is affected."""
        if not self.vehicles:
            return True
        if len(self.vehicles) == 2:
            return {tx, rx} == set(self.vehicles)
        return tx in self.vehicles or rx in self.vehicles

    def hits_pair(self, a: str, b: str) -> bool:
        """UWB outages: whether the range between ``a`` and ``b`` is affected."""
        if len(self.vehicles) == 2:
            return {a, b} == set(self.vehicles)
        return not self.vehicles or a in self.vehicles or b in self.vehicles


def parse_faults(data: dict, source: str, known_vehicles: set[str] | None = None) -> list[Fault]:
    """Faults from a parsed TOML document (``[[fault]]`` tables)."""
    unknown = set(data) - {"fault"}
    if unknown:
        raise FaultError(f"{source}: unknown section {sorted(unknown)[0]!r} (expected [[fault]] tables)")
    items = data.get("fault", [])
    if not isinstance(items, list):
        raise FaultError(f"{source}: 'fault' must be an array of tables ([[fault]])")
    return [_parse_fault(d, f"{source}: fault {i + 1}", known_vehicles) for i, d in enumerate(items)]


def _parse_fault(d: dict, where: str, known_vehicles: set[str] | None) -> Fault:
    """One ``[[fault]]`` table; ``where`` names it in errors."""
    if not isinstance(d, dict):
        raise FaultError(f"{where}: must be a table")
    extra = set(d) - {"kind", "start", "end", "vehicles", "loss", "latency"}
    if extra:
        raise FaultError(f"{where}: unknown field {sorted(extra)[0]!r}")
    kind = d.get("kind")
    if kind not in KINDS:
        raise FaultError(f"{where}: kind must be one of {', '.join(KINDS)}, got {kind!r}")
    try:
        start, end = float(d["start"]), float(d.get("end", d["start"]))
    except KeyError:
        raise FaultError(f"{where}: start is missing") from None
    except (TypeError, ValueError):
        raise FaultError(f"{where}: start and end must be numbers [s]") from None
    if not (math.isfinite(start) and math.isfinite(end)) or start < 0 or end < start:
        raise FaultError(f"{where}: need 0 <= start <= end, got {start}, {end}")
    if kind not in ("agent_kill", "emulator_kill") and end == start:
        raise FaultError(f"{where}: {kind} needs an end after its start")
    vehicles = d.get("vehicles", [])
    if not isinstance(vehicles, list) or not all(isinstance(v, str) for v in vehicles) or len(vehicles) > 2:
        raise FaultError(f"{where}: vehicles must be a list of at most two vehicle ids")
    if known_vehicles is not None and set(vehicles) - known_vehicles:
        raise FaultError(f"{where}: unknown vehicle {sorted(set(vehicles) - known_vehicles)[0]!r}")
    if kind in ("agent_kill", "agent_freeze") and len(vehicles) != 1:
        raise FaultError(f"{where}: {kind} needs exactly one vehicle")
    if kind in ("emulator_kill", "router_restart") and vehicles:
        raise FaultError(f"{where}: {kind} takes no vehicles")
    loss, latency = d.get("loss", 0.5), d.get("latency", 0.25)
    if isinstance(loss, bool) or not isinstance(loss, (int, float)) or not 0.0 <= loss <= 1.0:
        raise FaultError(f"{where}: loss must be a probability in [0, 1]")
    if isinstance(latency, bool) or not isinstance(latency, (int, float)) or not 0.0 <= latency <= 10.0:
        raise FaultError(f"{where}: latency must be in [0, 10] s")
    return Fault(kind, start, end, tuple(vehicles), float(loss), float(latency))


def load_faults(path: Path | str, known_vehicles: set[str] | None = None) -> list[Fault]:
    """Read a fault schedule file; :class:`FaultError` names what is wrong."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except OSError as exc:
        raise FaultError(f"{p}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise FaultError(f"{p}: not a fault schedule (not UTF-8 text)") from None
    except tomllib.TOMLDecodeError as exc:
        raise FaultError(f"{p}: not valid TOML ({exc})") from None
    return parse_faults(data, str(p), known_vehicles)


def random_schedule(vehicles: list[str], duration: float, rng: np.random.Generator, per_minute: float = 4.0,
                    max_freeze: float = 30.0, margin: float = 10.0) -> list[Fault]:
    """A chaos schedule: about ``per_minute`` faults a minute of sensor time, drawn from agent
    kills, agent freezes (up to ``max_freeze`` s of wall time), V2V blackouts, GNSS outages,
    emulator kills and router restarts (``rng``: a numpy Generator). Process faults are at least
    ``margin`` s of sensor time apart, none comes within ``margin`` of the start or the end, and
    no process is killed more often than the launcher restarts one (3 times)."""
    if not vehicles or duration <= 3 * margin:
        raise FaultError(f"a chaos schedule needs vehicles and more than {3 * margin:g} s, got {duration:g} s")
    n = max(1, int(round(per_minute * duration / 60.0)))
    kinds = ("agent_kill", "agent_freeze", "v2v_blackout", "gnss_outage", "emulator_kill", "router_restart")
    weights = np.array([3.0, 3.0, 2.0, 1.0, 1.0, 1.0])
    out: list[Fault] = []
    kills: dict[str, int] = {}
    last_process = -math.inf
    for start in np.sort(rng.uniform(margin, duration - margin, n)):
        kind = str(rng.choice(kinds, p=weights / weights.sum()))
        start = round(float(start), 1)
        if kind in PROCESS_FAULTS:
            if start - last_process < margin:
                kind = "v2v_blackout"  # too close to the last process fault: a link fault instead
            else:
                last_process = start
        v = str(rng.choice(vehicles))
        who = "emulator" if kind == "emulator_kill" else v
        if kind in ("agent_kill", "emulator_kill"):
            if kills.get(who, 0) >= 2:
                kind = "agent_freeze"
            else:
                kills[who] = kills.get(who, 0) + 1
        if kind == "agent_kill":
            out.append(Fault(kind, start, start, (v,)))
        elif kind == "emulator_kill":
            out.append(Fault(kind, start, start))
        elif kind == "agent_freeze":
            out.append(Fault(kind, start, round(start + float(rng.uniform(1.0, max_freeze)), 1), (v,)))
        elif kind == "router_restart":
            out.append(Fault(kind, start, round(start + float(rng.uniform(0.5, 5.0)), 1)))
        else:  # a link or sensor fault of one vehicle, a few seconds
            out.append(Fault(kind, start, round(start + float(rng.uniform(2.0, 10.0)), 1), (v,)))
    return out


def schedule_toml(faults: list[Fault], comment: str = "") -> str:
    """A schedule as the TOML that :func:`load_faults` reads."""
    lines = [f"# {comment}"] if comment else []
    for f in faults:
        lines += ["", "[[fault]]", f'kind = "{f.kind}"', f"start = {f.start!r}"]
        if f.end != f.start or f.kind not in ("agent_kill", "emulator_kill"):
            lines.append(f"end = {f.end!r}")
        if f.vehicles:
            lines.append("vehicles = [" + ", ".join(f'"{v}"' for v in f.vehicles) + "]")
    return "\n".join(lines) + "\n"
