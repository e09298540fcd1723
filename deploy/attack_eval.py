"""``slcp attack-eval``: how well the agents' misbehaviour detection finds the VeReMi attacks, and
how often it flags an honest vehicle.

Each run plays a scenario with the real agents and emulator on the in-memory bus (no Zenoh: the
same code paths, several times faster) with one misbehaving vehicle: attacker, kind and start
time are drawn from the seed; the start is a moment the attacker moves (> 3 m/s), so that every
attack changes what it claims. The run stops ``after`` seconds of sensor time past the start.

Figures:

* **detection** -- per (run, honest receiver that heard the attacker after the start): flagged
  within ``deadline`` (1 s) of the start; the latency of the first flag;
* **false alarms** -- the share of honest vehicles' beacons excluded by honest receivers, in
  attack runs (honest neighbours) and in clean runs of whole scenarios.
"""

from __future__ import annotations

import asyncio
import statistics

import numpy as np

from slcp.hw_emulation.attacks import ATTACKS, Attack


def _truth(scenario: str):
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.truth import build_truth

    return build_truth(load_scenario(scenario))


def _fleet(truth, seed: int, attack: Attack | None, until: float | None):
    from slcp.agent.runtime import Agent
    from slcp.hw_emulation.service import EmulatorService
    from slcp.transport.bus import InMemoryNetwork

    from .agent_configs import agent_config

    scn = truth.scenario

    async def main():
        net = InMemoryNetwork()
        stop, emu_stop = asyncio.Event(), asyncio.Event()
        agents = {v: Agent(agent_config(scn, v), net.bus()) for v in sorted(truth.vehicles)}
        emu = EmulatorService(truth, net.bus(), seed=seed, attacks=[attack] if attack else [])
        tasks = [asyncio.create_task(a.run(stop)) for a in agents.values()]

        async def cut() -> None:
            while until is not None and emu.now < until:
                await asyncio.sleep(0.01)
            emu_stop.set()

        cutter = asyncio.create_task(cut()) if until is not None else None
        await emu.run(emu_stop)
        if cutter:
            cutter.cancel()
        stop.set()
        await asyncio.gather(*tasks)
        return agents

    return asyncio.run(main())


def draw_attack(truth, kind: str, seed: int, rng: np.random.Generator) -> Attack:
    """Attacker and start for a seed: a vehicle and a moment it moves faster than 3 m/s."""
    ids = sorted(truth.vehicles)
    for k in range(len(ids)):
        vid = ids[(seed + k) % len(ids)]
        tr = truth.vehicles[vid].truth
        speed = np.hypot(tr.v_ned[:, 0], tr.v_ned[:, 1])
        ok = np.flatnonzero((speed > 3.0) & (tr.t > 5.0) & (tr.t < tr.t[-1] - 8.0))
        if ok.size:
            return Attack(vid, kind, float(tr.t[ok[int(rng.integers(ok.size))]]))
    raise ValueError("no vehicle moves fast enough for an attack")


def evaluate_attack(scenario: str, kind: str, seed: int, after: float = 4.0, deadline: float = 1.0) -> dict:
    """One attack run; per honest receiver the detection latency (None: not flagged)."""
    truth = _truth(scenario)
    attack = draw_attack(truth, kind, seed, np.random.default_rng(seed))
    agents = _fleet(truth, seed, attack, attack.start + after)
    out = {"attacker": attack.vehicle, "kind": kind, "start_s": attack.start, "receivers": {},
           "honest_beacons": 0, "honest_excluded": 0}
    for v, a in agents.items():
        if v == attack.vehicle:
            continue
        if a.beacons_from.get(attack.vehicle, 0) == 0:
            continue  # never heard the attacker: nothing to detect
        flags = [t for t, who, _ in a.misbehaviour.events if who == attack.vehicle]
        early = [t for t in flags if t < attack.start]
        late = [t for t in flags if t >= attack.start]
        out["receivers"][v] = {
            "latency_s": (late[0] - attack.start) if late else None,
            "flagged_before_start": bool(early),
            "detected": bool(late) and late[0] - attack.start <= deadline and not early,
        }
        for other, n in a.beacons_from.items():
            if other != attack.vehicle:
                out["honest_beacons"] += n
                out["honest_excluded"] += a.excluded_from.get(other, 0)
    return out


def evaluate_clean(scenario: str, seed: int) -> dict:
    """A whole scenario without attackers: the share of beacons excluded (false alarms)."""
    agents = _fleet(_truth(scenario), seed, None, None)
    total = sum(sum(a.beacons_from.values()) for a in agents.values())
    excl = sum(sum(a.excluded_from.values()) for a in agents.values())
    flags = sum(len(a.misbehaviour.events) for a in agents.values())
    return {"scenario": scenario, "seed": seed, "beacons": total, "excluded": excl, "flags": flags,
            "false_alarm_rate": excl / total if total else 0.0}


def attack_study(scenario: str, seeds: list[int], kinds: tuple[str, ...] = ATTACKS, after: float = 4.0,
                 deadline: float = 1.0, progress=None) -> dict:
    """Every kind over the seeds: detection rate within ``deadline``, latencies, false alarms."""
    per_kind = {}
    for kind in kinds:
        runs = []
        for s in seeds:
            runs.append(evaluate_attack(scenario, kind, s, after, deadline))
            if progress:
                progress(kind, s, runs[-1])
        rec = [r for run in runs for r in run["receivers"].values()]
        lat = [r["latency_s"] for r in rec if r["latency_s"] is not None]
        per_kind[kind] = {
            "cases": len(rec),
            "detected": sum(r["detected"] for r in rec),
            "detection_rate": sum(r["detected"] for r in rec) / len(rec) if rec else None,
            "latency_median_s": statistics.median(lat) if lat else None,
            "latency_max_s": max(lat) if lat else None,
            "honest_excluded_share": (
                sum(r["honest_excluded"] for r in runs) / max(1, sum(r["honest_beacons"] for r in runs))
            ),
            "runs": runs,
        }
    return {"scenario": scenario, "seeds": seeds, "deadline_s": deadline, "kinds": per_kind}
