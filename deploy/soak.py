"""The soak: a fleet run for many minutes on an open bus beside a hostile station (``slcp soak``).

A stranger on the host (:class:`hw_emulation.hostile.HostileStation`, its own process) joins the
run's router, churns thousands of liveliness identities, floods the agents with bad beacons
(unknown keys, wrong names, no signature, future and stale times, replays, garbage), sends
10 MB payloads to the agents, the radio and the recorder, and listens to the genuine beacons to
replay them. Meanwhile the resident set of every process is sampled. The verdict
(``soak.json``, and the curve in ``soak-rss.csv``):

* ``memory_bounded``: no process of the fleet grows over the last third of the run beyond its
  peak of the middle third (a tolerance of 5 % or 8 MB, whichever is larger);
* ``diagnostics_decodable``: every recorded line reads back, the recorder refused nothing it
  could decode, and every agent's diagnostics came in once a sensor second;
* ``genuine_beacons_delivered``: on every link, the verified beacons the receiver counted equal
  the beacons the radio delivered less those a late delivery let a newer one overtake (which any
  receiver refuses as old): nothing genuine was lost to the flood;
* ``shed_before_verification``: no beacon of the flood reached a signature verification (no bad
  signature, no verification budget spent) while the cheap checks refused it.

The run is insecure on purpose (``slcp run --insecure``): a locked-down run admits no stranger.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from slcp.hw_emulation.hostile import HostileStation
from slcp.hw_emulation.scenario import load_scenario, scenario_lasting
from slcp.transport import keys
from slcp.transport.codec import CodecError, decode
from slcp.transport.messages import Beacon

from .fleet_bench import _proc_status
from .launcher import run_fleet

log = logging.getLogger(__name__)

#: growth allowed over the last third of a soak, beyond the peak of its middle third
GROWTH_REL, GROWTH_MB = 0.05, 8.0


# ----------------------------------------------------------------- the hostile process
async def _attack(endpoint: str, fleet_dir: Path, vehicles: list[str], rate: float, big_rate: float,
                  identities: int, token_life: float, seed: int, stop: asyncio.Event) -> dict:
    from slcp.transport.security import TrustStore
    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    trust = TrustStore.from_dir(fleet_dir)
    station = HostileStation(vehicles, trust.key_ids(), identities=identities, token_life=token_life, seed=seed)
    bus = ZenohBus(ZenohConfig(mode="client", connect=(endpoint,)))
    heard = bus.subscribe(keys.ROOT + "/radio/rx/*", 4096, wake=False)
    sent = declared = withdrawn = big = 0
    t0 = last = time.monotonic()
    owed = 0.0
    next_big = t0
    try:
        while not stop.is_set():
            await asyncio.sleep(0.01)
            now = time.monotonic()
            dt, last = now - last, now
            for key, payload in heard.drain()[-32:]:  # the newest: the fleet's clock, and replays
                try:
                    b = decode(payload)
                except CodecError:
                    continue
                if isinstance(b, Beacon) and b.vehicle in vehicles and not trust.precheck(b):
                    station.hear(key, payload, b)
            up, down = station.churn(dt)
            for k in down:
                bus.withdraw_alive(k)
            for k in up:
                bus.declare_alive(k)
            declared, withdrawn = declared + len(up), withdrawn + len(down)
            owed += rate * dt
            n = int(owed)
            owed -= n
            for key, payload in station.flood(n):
                await bus.publish(key, payload)
            sent += n
            if big_rate > 0 and now >= next_big:
                next_big = now + 1.0 / big_rate
                for key, payload in station.oversized():
                    await bus.publish(key, payload)
                    big += 1
    finally:
        await bus.close()
    wall = time.monotonic() - t0
    return {"wall_s": wall, "bad_beacons": sent, "bad_per_s": sent / max(wall, 1e-9), "kinds": station.sent,
            "oversized_payloads": big, "oversized_bytes": station.big_size,
            "tokens_declared": declared, "tokens_withdrawn": withdrawn, "identities": identities}


def attacker_main(argv: list[str] | None = None) -> int:
    """``python -m slcp.deploy.soak``: the hostile station, until SIGTERM; its account to ``--report``."""
    from .processes import _install_signals

    ap = argparse.ArgumentParser(prog="python -m slcp.deploy.soak", description="the soak's hostile station")
    ap.add_argument("--connect", required=True)
    ap.add_argument("--fleet", type=Path, required=True)
    ap.add_argument("--vehicles", required=True, help="comma-separated")
    ap.add_argument("--rate", type=float, default=10_000.0)
    ap.add_argument("--big-rate", type=float, default=1.0)
    ap.add_argument("--identities", type=int, default=5000)
    ap.add_argument("--token-life", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--report", type=Path, required=True)
    a = ap.parse_args(argv)

    async def main() -> dict:
        stop = asyncio.Event()
        _install_signals(stop)
        return await _attack(a.connect, a.fleet, a.vehicles.split(","), a.rate, a.big_rate, a.identities,
                             a.token_life, a.seed, stop)

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    a.report.write_text(json.dumps(asyncio.run(main()), indent=2))
    return 0


# ----------------------------------------------------------------- the monitor
@dataclass
class SoakMonitor:
    """Starts the hostile station once the fleet runs and samples every process's resident set
    (see :func:`deploy.launcher.run_fleet`'s ``monitor``)."""

    out: Path
    vehicles: list[str]
    attacker: list[str]  #: the hostile station's arguments, but for --connect, --fleet and --report
    every: float = 5.0
    curve: list[dict] = field(default_factory=list)  #: {"wall_s", "t", name: RSS [MB], ...}

    def __post_init__(self) -> None:
        self.procs: dict = {}
        self.proc: subprocess.Popen | None = None
        self._t0 = time.monotonic()
        self._next = 0.0

    def attach(self, bus, procs: dict, endpoint: str) -> None:  # noqa: ARG002 - the monitor interface
        self.procs = procs
        cmd = [sys.executable, "-m", "slcp.deploy.soak", "--connect", endpoint, "--fleet",
               str(self.out / "keys"), "--vehicles", ",".join(self.vehicles), "--report",
               str(self.out / "attacker.json"), *self.attacker]
        with open(self.out / "logs" / "attacker.log", "ab") as fh:
            self.proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)

    def sample(self, rec) -> None:
        now = time.monotonic()
        if now < self._next:
            return
        self._next = now + self.every
        ts = [rec.latest_t[v] for v in self.vehicles if v in rec.latest_t]
        point: dict = {"wall_s": round(now - self._t0, 2), "t": round(min(ts), 2) if ts else None}
        pids = {n: p.pid for n, p in self.procs.items()}
        pids["launcher"] = os.getpid()
        if self.proc is not None:
            pids["attacker"] = self.proc.pid
        for n, pid in pids.items():
            kb = _proc_status(pid, "VmRSS")
            if kb is not None:
                point[n] = round(kb / 1024.0, 1)
        self.curve.append(point)

    def stop(self) -> dict:
        """Stop the hostile station; its account."""
        if self.proc is None:
            return {}
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        try:
            return json.loads((self.out / "attacker.json").read_text())
        except (OSError, ValueError):
            return {"error": f"the hostile station left no account (exit {self.proc.returncode})"}


# ----------------------------------------------------------------- the verdict
def _read_diagnostics(path: Path) -> tuple[dict[str, dict], dict[str, int], int, int]:
    """Last diagnostics (counters and status) per source, their number per source, the lines
    read and the lines that could not be read."""
    last: dict[str, dict] = {}
    count: dict[str, int] = {}
    lines = bad = 0
    with open(path) as fh:
        for line in fh:
            lines += 1
            try:
                r = json.loads(line)
            except json.JSONDecodeError:
                bad += 1
                continue
            if r.get("type") == "Diagnostics":
                last[r["source"]] = r
                count[r["source"]] = count.get(r["source"], 0) + 1
    return last, count, lines, bad


def memory_growth(curve: list[dict]) -> dict[str, dict]:
    """Per process: peak RSS of the middle and of the last third of the run [MB], and whether the
    last stays within the tolerance (:data:`GROWTH_REL`, :data:`GROWTH_MB`)."""
    out = {}
    names = sorted({k for p in curve for k in p} - {"wall_s", "t"})
    n = len(curve)
    for name in names:
        mid = [p[name] for p in curve[n // 3: 2 * n // 3] if name in p]
        end = [p[name] for p in curve[2 * n // 3:] if name in p]
        if not mid or not end:
            continue
        peak_mid, peak_end = max(mid), max(end)
        out[name] = {"peak_mid_mb": peak_mid, "peak_end_mb": peak_end, "peak_mb": max(p.get(name, 0) for p in curve),
                     "bounded": peak_end <= peak_mid + max(GROWTH_MB, GROWTH_REL * peak_mid)}
    return out


def beacon_account(diags: dict[str, dict], vehicles: list[str]) -> dict[str, dict]:
    """Per link ``tx>rx``: what the radio delivered, what overtook, what the receiver verified."""
    links = diags.get("emulator", {}).get("status", {}).get("links", {})
    out = {}
    for link, (delivered, out_of_order) in sorted(links.items()):
        tx, rx = link.split(">")
        got = diags.get(rx, {}).get("status", {}).get("beacons_from", {}).get(tx, 0)
        # exact: a replay goes to a receiver that has the beacon already, and a genuine beacon
        # reaches a receiver by no other path than its link
        out[link] = {"delivered": delivered, "out_of_order": out_of_order, "verified": got,
                     "lost": delivered - out_of_order - got}
    for rx in vehicles:
        if rx not in diags:
            out[f"?>{rx}"] = {"error": f"no diagnostics of {rx}"}
    return out


FLOOD_COUNTERS = ("beacon_unknown_key", "beacon_wrong_vehicle", "beacon_unsigned", "beacon_future", "beacon_stale",
                  "codec_errors", "oversized_beacon")


def evaluate_soak(out: Path, vehicles: list[str], duration: float, curve: list[dict], attacker: dict,
                  stats: dict) -> dict:
    """The soak's verdict (see the module's docstring)."""
    diags, count, lines, bad = _read_diagnostics(out / "recorded" / "messages.jsonl")
    memory = memory_growth(curve)
    account = beacon_account(diags, vehicles)
    # the recorder's refusals but the oversized payloads (the flood's, counted and never copied)
    rejected = {k: v for k, v in (stats.get("rejected") or {}).items() if k != "oversized"}
    agents = {v: diags.get(v, {}).get("counters", {}) for v in vehicles}
    shed = {v: {k: n for k, n in c.items() if k in FLOOD_COUNTERS or k.startswith("prefilter_")}
            for v, c in agents.items()}
    verified_bad = {v: c.get("beacon_bad_signature", 0) + c.get("beacon_verify_budget", 0) for v, c in agents.items()}
    checks = {
        # the fleet's processes: the hostile station's own memory is its business (reported)
        "memory_bounded": bool(memory) and all(m["bounded"] for n, m in memory.items() if n != "attacker"),
        "diagnostics_decodable": bad == 0 and not rejected and stats.get("codec_errors", 0) == 0
        and all(count.get(v, 0) >= 0.9 * duration for v in vehicles),
        "genuine_beacons_delivered": bool(account) and all(a.get("lost") == 0 for a in account.values()),
        "shed_before_verification": all(n == 0 for n in verified_bad.values())
        and all(sum(s.values()) > 0 for s in shed.values()),
    }
    return {"checks": checks, "passed": all(checks.values()), "duration_s": duration, "attacker": attacker,
            "memory": memory, "beacons": account, "flood_shed": shed, "verified_bad": verified_bad,
            "diagnostics": {"lines": lines, "unreadable": bad, "per_source": count, "recorder_rejected": rejected},
            "emulator": diags.get("emulator", {}).get("counters", {}), "processes": stats}


def run_soak(scenario: str = "paper-1", duration: float = 600.0, seed: int = 0, out: Path = Path("runs/soak"),
             rate: float = 10_000.0, big_rate: float = 1.0, identities: int = 5000, token_life: float = 5.0,
             speed: float | None = 1.0, progress=None, sample_every: float = 5.0) -> dict:
    """Run the soak; the verdict is returned and written to ``out/soak.json`` (the RSS curve,
    sampled every ``sample_every`` seconds of wall time, to ``out/soak-rss.csv``)."""
    out = Path(out)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    path = scenario_lasting(scenario, duration, out)
    vehicles = [v.id for v in load_scenario(str(path)).vehicles]
    mon = SoakMonitor(out, vehicles, ["--rate", f"{rate:g}", "--big-rate", f"{big_rate:g}", "--identities",
                                      str(identities), "--token-life", f"{token_life:g}", "--seed", str(seed)],
                      every=sample_every)
    try:
        res = run_fleet(str(path), speed=speed, seed=seed, out=out, secure=False, evaluate=False, monitor=mon,
                        progress=progress)
    finally:
        attacker = mon.stop()
    verdict = evaluate_soak(out, vehicles, duration, mon.curve, attacker, res["processes"])
    (out / "soak.json").write_text(json.dumps(verdict, indent=2, default=str))
    names = sorted({k for p in mon.curve for k in p} - {"wall_s", "t"})
    rows = ["wall_s,t," + ",".join(f"{n}_rss_mb" for n in names)]
    rows += [",".join(str(p.get(k, "")) for k in ("wall_s", "t", *names)) for p in mon.curve]
    (out / "soak-rss.csv").write_text("\n".join(rows) + "\n")
    return verdict


if __name__ == "__main__":
    sys.exit(attacker_main())
